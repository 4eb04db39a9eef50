"""Validates weight snapshots (``train_gpu.py``'s ``<name>_snapshots.pt``, or ``train.py`` /
``train_gpu.py`` checkpoints) on the holdout that ``train.py`` validates on, so that runs
on other machines join the same learning curve.

    python training/validate_snapshots.py SNAPSHOTS_OR_CKPT... --log training/checkpoints/NAME/log.jsonl \\
        [--offset 70006] [--tag gpu]

Each snapshot becomes one ``log.jsonl`` record (``pairs`` = pairs seen, plus ``--offset``
for a run that started from another one's weights), read by ``plot_curves.py``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Iterator

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from paraformer_train.model import Matcher  # noqa: E402
from train import build_model, ensure_holdout, model_config, validate  # noqa: E402


def snapshots(path: str) -> Iterator[tuple[int, Matcher, dict, dict]]:
    """(pairs, an untrained model of the snapshot's kind, EMA state, extra fields) of every
    snapshot in a file, one model built at a time. A checkpoint's model carries its run's
    ``--self-rotary``."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    if "ema" in blob and "pairs" in blob:  # a checkpoint: its EMA weights
        yield blob["pairs"], Matcher_from_args(blob["args"]), blob["ema"], {"steps": blob.get("steps")}
        return
    for p, s in sorted(blob.items()):
        yield p, Matcher(s["config"], s.get("self_rotary")), s["ema"], {"steps": s.get("steps"), "train_s": s.get("train_s")}


def Matcher_from_args(args: dict) -> Matcher:  # noqa: N802 (a constructor in all but name)
    """The untrained network of a run's saved arguments (also the lightglue_arm diagnostic)."""
    return build_model(model_config(args), args.get("self_rotary"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="+")
    ap.add_argument("--log", required=True, help="log.jsonl to append the records to")
    ap.add_argument("--offset", type=int, default=0, help="pairs the run had seen before (its initial weights)")
    ap.add_argument("--tag", default=None, help="a field 'run' in each record")
    ap.add_argument("--threshold", type=float, default=0.2)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    holdout = ensure_holdout(256)
    os.makedirs(os.path.dirname(os.path.abspath(args.log)), exist_ok=True)
    for path in args.files:
        for pairs, model, state, extra in snapshots(path):
            model.load_state_dict({k: v.float() for k, v in state.items()})
            model.eval()
            v = validate(model, holdout, 512, args.threshold, auc=False)
            v |= validate(model, holdout, 2048, args.threshold, auc=True)
            rec = {"pairs": pairs + args.offset, "weights": "ema"} | {k: x for k, x in extra.items() if x is not None} | v
            if args.tag:
                rec["run"] = args.tag
            with open(args.log, "a") as f:
                f.write(json.dumps(rec) + "\n")
            print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
