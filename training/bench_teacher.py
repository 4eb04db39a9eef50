"""The distillation teacher's cost and precision, side by side in one process (calls alternated):
LighterGlue (``paraformer_train/teacher.py``) on the XFeat features of the sample pair at the
trainer's batch shapes (512 x 8, 1024 x 4, 2048 x 2 keypoints x pairs), in float32 and bfloat16,
each with its cross-attention as the teacher runs it (two fused SDPA calls) and as kornia runs
it on CPU (``-kornia``: explicit similarity matrix and two softmaxes). Prints per shape each
variant's median forward time, its speed against the first variant, the mean total variation
between its rows and the first variant's, and how many confident entries (> 0.2) it gives.

    python training/bench_teacher.py --threads 2 --rounds 3
    python training/bench_teacher.py --variants bf16,bf16-kornia
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
    ap.add_argument("--variants", default="fp32,bf16,fp32-kornia,bf16-kornia",
                    help="comma-separated, of fp32, bf16, fp32-kornia, bf16-kornia; the first is the reference")
    args = ap.parse_args()
    if args.rounds < 1 or args.threads < 1:
        sys.exit("error: --rounds and --threads must be at least 1")
    names = args.variants.split(",")
    known = {"fp32", "bf16", "fp32-kornia", "bf16-kornia"}
    if not names or any(n not in known for n in names) or len(set(names)) != len(names):
        sys.exit(f"error: --variants {args.variants!r}: expected distinct names of {sorted(known)}")
    torch.set_num_threads(args.threads)
    teachers = {n: LighterGlueTeacher(bf16=n.startswith("bf16"), sdpa_cross=not n.endswith("-kornia")) for n in names}
    ref = names[0]
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
        print(f"{n} keypoints x {b}:", flush=True)
        for k in names:
            tv = 0.5 * (out[ref] - out[k]).abs().sum(2).mean().item()
            print(f"  {k:12s} {1000 * med[k]:7.0f} ms  {med[ref] / med[k]:5.2f}x {ref}  row TV to {ref} {tv:.4f}  "
                  f"entries > 0.2: {int((out[k] > 0.2).sum())}", flush=True)


if __name__ == "__main__":
    main()
