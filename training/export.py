"""Exports a trained run as a shipped weights file: picks `match_threshold` by F1 on the
held-out training pairs (train/bsds500_val, never val/), writes the SPEC safetensors file
with the full config in its metadata.

    python training/export.py --run training/runs/paraformer --holdout training/cache/holdout \
        --out crates/paraformer/weights/paraformer-xfeat.safetensors
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train.io import load_safetensors, save_safetensors  # noqa: E402
from paraformer_train.model import extract_matches  # noqa: E402
from train import batch, load_shards, precision_recall  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--weights", nargs="+", default=["best.safetensors", "last.safetensors"],
                    help="candidate files in the run folder; the best calibrated hold-out F1 wins")
    ap.add_argument("--holdout", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    data = load_shards(args.holdout)
    n = data["keypoints"].shape[0]
    choice = None
    for name in args.weights:
        path = os.path.join(args.run, name)
        if not os.path.exists(path):
            continue
        model = load_safetensors(path)
        logps, gts = [], []
        with torch.no_grad():
            for s in range(0, n, 16):
                bt = batch(data, torch.arange(s, min(s + 16, n)))
                logps.append(model(bt)["log_assignment"])
                gts.append(bt["gt0"])
        for t in [0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]:
            tp = npred = npos = 0
            for logp, gt in zip(logps, gts):
                a, b, c = precision_recall(extract_matches(logp, t)["matches0"], gt)
                tp, npred, npos = tp + a, npred + b, npos + c
            p, r = tp / max(npred, 1), tp / max(npos, 1)
            f1 = 2 * p * r / max(p + r, 1e-12)
            print(f"{name} match_threshold {t:.2f}: P {p:.3f} R {r:.3f} F1 {f1:.3f}")
            if choice is None or f1 > choice[0]:
                choice = (f1, t, name, model)
    if choice is None:
        sys.exit(f"error: none of {args.weights} in {args.run}")
    f1, best, name, model = choice
    model.config["match_threshold"] = best
    save_safetensors(model, args.out)
    print(json.dumps({"out": args.out, "from": name, "match_threshold": best, "holdout_f1": f1,
                      "bytes": os.path.getsize(args.out), "config": model.config}))


if __name__ == "__main__":
    main()
