"""How fast this CPU multiplies bf16 matrices where a library can (PyTorch/oneDNN: AMX tiles on
Sapphire Rapids and later, AVX-512 BF16 elsewhere) against fp32, at the shapes of the w96
matcher at 2048 keypoints: the attention's score and value products (3 heads of width 32) and
the Linear layers (4096 keypoints of both images, 96 → 288 and 192 → 192), plus PyTorch's fused
attention. It bounds what a bf16 path in the engine could gain on such a CPU; the engine's own
bf16 kernels use `vdpbf16ps` (see training/README, "The trainer on Sapphire Rapids").

    pip install torch
    python benches/bf16_products.py --threads 2
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "training"))


def median_time(f, reps: int) -> float:
    """Median seconds of ``reps`` calls of ``f`` after one warm-up call."""
    f()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=20)
    args = ap.parse_args()
    if args.threads < 1 or args.reps < 1:
        raise SystemExit("error: --threads and --reps must be at least 1")
    import torch
    from train import cpu_flags  # training/train.py: the flags its bf16 choices read (imports torch)

    torch.set_num_threads(args.threads)
    flags = cpu_flags() or set()
    print(f"threads {args.threads}; AMX-BF16 {'amx_bf16' in flags}, AVX512-BF16 {'avx512_bf16' in flags}")
    g = torch.Generator().manual_seed(0)
    # (batch, m, k, n): scores Q·Kᵀ, values P·V, the fused q/k/v projection, the MLP's square layer.
    shapes = {"scores 3 x 2048x32 @ 32x2048": (3, 2048, 32, 2048),
              "values 3 x 2048x2048 @ 2048x32": (3, 2048, 2048, 32),
              "linear 4096x96 @ 96x288": (1, 4096, 96, 288),
              "linear 4096x192 @ 192x192": (1, 4096, 192, 192)}
    for name, (b, m, k, n) in shapes.items():
        a, w = torch.randn(b, m, k, generator=g), torch.randn(b, k, n, generator=g)
        t32 = median_time(lambda: torch.bmm(a, w), args.reps)
        a16, w16 = a.bfloat16(), w.bfloat16()
        t16 = median_time(lambda: torch.bmm(a16, w16), args.reps)
        flop = 2 * b * m * k * n
        print(f"{name:32s} fp32 {1e3 * t32:7.2f} ms ({flop / t32 / 1e9:5.0f} GFLOP/s)  "
              f"bf16 {1e3 * t16:7.2f} ms ({flop / t16 / 1e9:5.0f} GFLOP/s)  {t32 / t16:4.1f}x")
    q = torch.randn(4, 3, 2048, 32, generator=g)
    sdpa = torch.nn.functional.scaled_dot_product_attention
    t32 = median_time(lambda: sdpa(q, q, q), max(1, args.reps // 2))
    qb = q.bfloat16()
    t16 = median_time(lambda: sdpa(qb, qb, qb), max(1, args.reps // 2))
    print(f"{'fused attention 4x3 heads 2048x32':32s} fp32 {1e3 * t32:7.2f} ms  bf16 {1e3 * t16:7.2f} ms  {t32 / t16:4.1f}x")


if __name__ == "__main__":
    main()
