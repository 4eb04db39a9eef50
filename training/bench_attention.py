"""Where the training step's time goes: the fused attention's forward against its backward,
at the shapes of the wide model's steps (3 heads of width 32; 512 x 8, 1024 x 4 and
2048 x 2 keypoints x batch), in one process, calls alternated.

A ParaFormer step makes 16 such calls at depth 4 (self-attention of each image and the two
directions of the shared cross-attention, per layer). Rows:

  * ``sdpa``: ``F.scaled_dot_product_attention``, what ``train.py`` runs (PyTorch's CPU
    flash kernel, forward and backward);
  * ``explicit``: softmax(QKᵀ/√d)·V with autograd (the probabilities are stored);
  * ``flash_fwd_recompute_bwd``: the flash forward, and a backward that recomputes the
    probabilities from its log-sum-exp with whole-matrix matmuls (no blocking);
  * ``native`` (bf16 only, on AVX-512 BF16 CPUs): the engine's forward and blocked backward
    (``paraformer``'s ``attention_forward_bf16`` / ``attention_backward_bf16``; ``train.py
    --native-attention``).

Each row's gradient is compared with a float64 reference on the same inputs (cosine and
relative error), so a faster row can be judged on its accuracy too.

    python training/bench_attention.py --json training/results/attention_fwd_bwd_2threads.json
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import os
import sys

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train.model import NativeAttention  # noqa: E402

SHAPES = ((8, 512), (4, 1024), (2, 2048))  # (batch, keypoints) of the stream's step kinds
HEADS, HEAD_DIM = 3, 32


class FlashRecompute(torch.autograd.Function):
    """Flash forward (keeps the log-sum-exp); the backward rebuilds P = exp(QKᵀ·s − lse)
    in the inputs' dtype and applies the softmax gradient with plain matmuls."""

    @staticmethod
    def forward(ctx, q, k, v):
        out, lse = torch.ops.aten._scaled_dot_product_flash_attention_for_cpu(q, k, v)
        ctx.save_for_backward(q, k, v, out, lse)
        return out

    @staticmethod
    def backward(ctx, grad):
        q, k, v, out, lse = ctx.saved_tensors
        scale = 1.0 / math.sqrt(q.shape[-1])
        grad = grad.contiguous()
        row = (grad.float() * out.float()).sum(-1, keepdim=True).to(q.dtype)
        p = torch.matmul(q * scale, k.transpose(-1, -2))
        p.sub_(lse.unsqueeze(-1).to(q.dtype)).exp_()
        dv = torch.matmul(p.transpose(-1, -2), grad)
        ds = torch.matmul(grad, v.transpose(-1, -2)).sub_(row).mul_(p)
        dq = torch.matmul(ds, k).mul_(scale)
        dk = torch.matmul(ds.transpose(-1, -2), q).mul_(scale)
        return dq, dk, dv


def explicit(q, k, v):
    return (q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])).softmax(-1) @ v


ROWS = {"sdpa": F.scaled_dot_product_attention, "explicit": explicit,
        "flash_fwd_recompute_bwd": FlashRecompute.apply}


def native_rows(dtype: torch.dtype) -> dict:
    """The rows this run can time: ``native`` needs bf16 and the engine's kernels."""
    try:
        from paraformer import _paraformer
        native = dtype == torch.bfloat16 and _paraformer.attention_bf16_available()
    except ImportError:
        native = False
    return {**ROWS, "native": NativeAttention.apply} if native else dict(ROWS)


def gradients(fn, q, k, v, grad) -> torch.Tensor:
    q, k, v = (t.detach().clone().requires_grad_() for t in (q, k, v))
    fn(q, k, v).backward(grad.to(q.dtype))
    return torch.cat([t.grad.double().flatten() for t in (q, k, v)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=8, help="timed calls per row and shape")
    ap.add_argument("--dtype", choices=["bf16", "fp32"], default="bf16")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.reps < 1:
        raise SystemExit(f"error: --reps {args.reps}: expected at least 1")
    torch.set_num_threads(args.threads)
    dtype = torch.bfloat16 if args.dtype == "bf16" else torch.float32
    torch.manual_seed(0)
    rows = native_rows(dtype)
    results = []
    for batch, n in SHAPES:
        shape = (batch, HEADS, n, HEAD_DIM)
        # Scores of a trained model's spread (|QKᵀ/√d| up to ~10), not unit-variance noise.
        q, k = torch.randn(shape) * 1.5, torch.randn(shape) * 1.5
        v, grad = torch.randn(shape), torch.randn(shape)
        reference = gradients(explicit, q.double(), k.double(), v.double(), grad.double())
        inputs = {name: tuple(t.to(dtype).requires_grad_() for t in (q, k, v)) for name in rows}
        grad_in = grad.to(dtype)  # cast once, outside the timed backward
        times = {name: {"forward": [], "backward": []} for name in rows}
        for rep in range(args.reps + 2):  # two warm-up calls per row
            order = list(rows) if rep % 2 == 0 else list(rows)[::-1]
            for name in order:
                qq, kk, vv = inputs[name]
                t0 = time.perf_counter()
                out = rows[name](qq, kk, vv)
                t1 = time.perf_counter()
                out.backward(grad_in)
                t2 = time.perf_counter()
                if rep >= 2:
                    times[name]["forward"].append(t1 - t0)
                    times[name]["backward"].append(t2 - t1)
        for name, fn in rows.items():
            g = gradients(fn, *(t.to(dtype) for t in (q, k, v)), grad)
            fwd, bwd = (statistics.median_high(times[name][part]) * 1e3 for part in ("forward", "backward"))
            row = {"batch": batch, "keypoints": n, "row": name, "forward_ms": fwd, "backward_ms": bwd,
                   "backward_over_forward": bwd / fwd,
                   "grad_cosine": float(g @ reference / (g.norm() * reference.norm())),
                   "grad_rel_error": float((g - reference).norm() / reference.norm())}
            results.append(row)
            print(f"{batch} x {n:4d} {name:24s} forward {fwd:6.1f} ms  backward {bwd:6.1f} ms "
                  f"({bwd / fwd:4.1f}x)  gradient cosine {row['grad_cosine']:.6f}  rel. error {row['grad_rel_error']:.4f}",
                  flush=True)
    if args.json:
        meta = {"threads": args.threads, "dtype": args.dtype, "heads": HEADS, "head_dim": HEAD_DIM,
                "torch": torch.__version__, "reps": args.reps, "statistic": "median per call",
                "env": {k: os.environ.get(k) for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "RAYON_NUM_THREADS")}}
        with open(args.json, "w") as f:
            json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
