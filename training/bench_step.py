"""Training-step throughput, old against new, side by side in one process (calls alternated):

  * before: explicit softmax attention, autograd through all Sinkhorn iterations
    (the step of the first shipped weights);
  * after: fused ``scaled_dot_product_attention`` and gradients through the last Sinkhorn
    iteration only, the earlier ones in the scaling domain without autograd (``train.py``);
  * after + bf16: the same with the network's forward under bfloat16 autocast
    (``train.py --bf16``);
  * after + bf16 + native attention: the same with the fused attention's forward and
    backward in the project's engine (``train.py --bf16 --native-attention``; AVX-512 BF16
    CPUs).

Same model config, same batches (XFeat pairs from the stream), forward + backward + AdamW.
``--weights`` starts every variant from a ``train.py`` checkpoint instead of random
weights; before the timed steps, the cosine between each variant's gradient and that of
``train.py``'s default step ("after") on the same batch is printed, beside the cosine between two batches' gradients
(the size of the noise that an approximation has to stay well inside).

    python training/bench_step.py --dim 64 --heads 4 --depth 4 --batch 8 --keypoints 512
    python training/bench_step.py --dim 96 --heads 3 --depth 4 --batch 4 --keypoints 1024 \
        --weights training/checkpoints/paraformer-xfeat-w96/last.pt
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train import data, model as model_mod, stream  # noqa: E402
from paraformer_train.model import Matcher, log_optimal_transport, log_optimal_transport_last_grad  # noqa: E402
from train import nll_loss, preset  # noqa: E402

SHARED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paraformer")
    ap.add_argument("--dim", type=int, default=64)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--keypoints", type=int, default=512)
    ap.add_argument("--sinkhorn", type=int, default=50)
    ap.add_argument("--steps", type=int, default=10, help="timed steps per variant")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--weights", default=None, help="train.py checkpoint (last.pt) to start from")
    ap.add_argument("--variants", default="before,after,bf16,native",
                    help="comma-separated subset of before, after, bf16, native (ratios are to the first)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    photos = data.list_photos([os.path.join(SHARED, "train", "bsds500_train")])[:40]
    src = stream.PairSource(photos, [], seed=123, real_fraction=0.0)
    os.makedirs("/tmp/bench_step", exist_ok=True)
    path = stream.shard_path("/tmp/bench_step", 0)
    stream.write_shard(path, [src.pair(i) for i in range(args.batch * 2)])
    shard = stream.Shard(path)
    batches = [stream.collate([(shard, b * args.batch + i) for i in range(args.batch)], args.keypoints,
                              [False] * args.batch) for b in range(2)]
    cfg = preset(args.preset, args.dim, args.depth, args.heads) | {"sinkhorn_iterations": args.sinkhorn}
    known = {  # key: (name, (fused attention, Sinkhorn, bf16 autocast, native attention))
        "before": ("before (explicit attention, full Sinkhorn autograd)", (False, log_optimal_transport, False, False)),
        "after": ("after (SDPA, last-iteration Sinkhorn gradient)", (True, log_optimal_transport_last_grad, False, False)),
        "bf16": ("after + bf16 autocast (train.py --bf16)", (True, log_optimal_transport_last_grad, True, False)),
        "native": ("after + bf16 + native attention (--bf16 --native-attention)",
                   (True, log_optimal_transport_last_grad, True, True)),
    }
    keys = [k.strip() for k in args.variants.split(",") if k.strip()]
    if not keys or any(k not in known for k in keys):
        raise SystemExit(f"error: --variants {args.variants!r}: expected a comma-separated subset of {', '.join(known)}")
    if "native" in keys:
        from paraformer import _paraformer
        if not _paraformer.attention_bf16_available():
            raise SystemExit("error: --variants native needs a CPU with AVX-512 BF16")
    if "after" not in keys:
        keys.insert(0, "after")  # the gradient reference
    variants = dict(known[k] for k in keys)
    start = torch.load(args.weights, weights_only=False)["model"] if args.weights else None
    models = {}
    for name in variants:
        torch.manual_seed(0)
        m = Matcher(cfg).train()
        if start is not None:
            m.load_state_dict(start)
        models[name] = (m, torch.optim.AdamW(m.parameters(), lr=1e-4))
    times = {name: [] for name in variants}

    def loss_of(name: str, bt: dict) -> torch.Tensor:
        fused, sinkhorn, bf16, native = variants[name]
        model_mod.FUSED_ATTENTION = fused
        model_mod.NATIVE_ATTENTION = native
        m = models[name][0]
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            scores = m.scores(bt)
        return nll_loss(sinkhorn(scores.float(), m.bin_score, args.sinkhorn), bt["gt0"], bt["gt1"])

    def gradient(name: str, bt: dict) -> torch.Tensor:
        m = models[name][0]
        m.zero_grad(set_to_none=True)
        loss_of(name, bt).backward()
        return torch.cat([p.grad.flatten() for p in m.parameters() if p.grad is not None])

    def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(a @ b / (a.norm() * b.norm()))

    # Gradient agreement before any step (all variants hold the same weights), against the
    # step train.py takes by default; the lower of the two batches.
    base = known["after"][0]
    ref = [gradient(base, bt) for bt in batches]
    agreement = {"two batches, one variant": cosine(ref[0], ref[1])}
    for name in variants:
        if name != base:
            agreement[name] = min(cosine(gradient(name, bt), r) for bt, r in zip(batches, ref))
    for name, c in agreement.items():
        print(f"gradient cosine to '{base}', {name}: {c:.5f}")

    def step(name: str, bt: dict) -> float:
        m, opt = models[name]
        t = time.perf_counter()
        loss = loss_of(name, bt)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(m.parameters(), 1.0)
        opt.step()
        return time.perf_counter() - t

    for name in variants:  # warm-up
        step(name, batches[0])
    for s in range(args.steps):
        for name in (variants if s % 2 == 0 else list(variants)[::-1]):
            times[name].append(step(name, batches[s % 2]))
    res = {}
    for name, ts in times.items():
        med = float(np.median(ts))
        res[name] = {"s_per_step": med, "pairs_per_s": args.batch / med}
    base = list(res.values())[0]["pairs_per_s"]
    for name, r in res.items():
        r["speedup"] = r["pairs_per_s"] / base
        print(f"{name:55s} {r['s_per_step']:.3f} s/step  {r['pairs_per_s']:.1f} pairs/s  {r['speedup']:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            # The thread pools' spin settings and glibc's heap settings change the native row
            # (train_shipped.sh sets GOMP_SPINCOUNT and the MALLOC_* variables).
            env = {k: os.environ.get(k) for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "RAYON_NUM_THREADS",
                                                  "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")}
            json.dump({"args": vars(args), "env": env, "config": cfg, "results": res, "gradient_cosine": agreement}, f, indent=1)


if __name__ == "__main__":
    main()
