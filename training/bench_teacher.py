"""The distillation teacher's cost and precision, float32 against bfloat16, side by side in one
process (calls alternated): LighterGlue (``paraformer_train/teacher.py``) on the XFeat features
of the sample pair at the trainer's batch shapes (512 x 8, 1024 x 4, 2048 x 2 keypoints x pairs).
Prints per shape the median forward time of each, their ratio, the mean total variation
between their rows, and how many confident entries (> 0.2) each gives.

    python training/bench_teacher.py --threads 2 --rounds 3
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train.teacher import LighterGlueTeacher, features_batch  # noqa: E402

SAMPLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "assets", "sample")


def sample_batch(keypoints: int, batch: int) -> dict:
    """The sample pair's XFeat features at ``keypoints`` per image, repeated ``batch`` times."""
    import paraformer

    feats = [paraformer.extract(os.path.join(SAMPLE, f"coffee_{i}.jpg"), max_keypoints=keypoints) for i in (0, 1)]
    return features_batch(*feats, batch=batch)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3, help="alternated timed calls of each teacher per shape")
    ap.add_argument("--shapes", default="512x8,1024x4,2048x2", help="KEYPOINTSxBATCH,...")
    args = ap.parse_args()
    if args.rounds < 1 or args.threads < 1:
        sys.exit("error: --rounds and --threads must be at least 1")
    torch.set_num_threads(args.threads)
    teachers = {"fp32": LighterGlueTeacher(), "bf16": LighterGlueTeacher(bf16=True)}
    for shape in args.shapes.split(","):
        try:
            n, b = (int(v) for v in shape.split("x"))
        except ValueError:
            sys.exit(f"error: --shapes: {shape!r} is not KEYPOINTSxBATCH")
        bt = sample_batch(n, b)
        out = {k: t(bt) for k, t in teachers.items()}  # warm-up, and the outputs compared
        times = {k: [] for k in teachers}
        for _ in range(args.rounds):
            for k, t in teachers.items():
                t0 = time.perf_counter()
                t(bt)
                times[k].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) for k, v in times.items()}
        tv = 0.5 * (out["fp32"] - out["bf16"]).abs().sum(2).mean().item()
        conf = {k: int((v > 0.2).sum()) for k, v in out.items()}
        print(f"{n} keypoints x {b}: fp32 {1000 * med['fp32']:.0f} ms, bf16 {1000 * med['bf16']:.0f} ms, "
              f"ratio {med['fp32'] / med['bf16']:.2f}; row TV {tv:.4f}; entries > 0.2: fp32 {conf['fp32']}, "
              f"bf16 {conf['bf16']}", flush=True)


if __name__ == "__main__":
    main()
