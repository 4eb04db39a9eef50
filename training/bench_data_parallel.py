"""Training-step throughput of one process on two threads against two processes of one
thread each (``paraformer_train/data_parallel.py``), side by side in one run: the same start
weights, the same batches, blocks of steps alternated, at each keypoint count of the
training schedule (512 × 8, 1024 × 4, 2048 × 2) and for the schedule's mix of them.

Before the timed steps it prints, on the same weights and batch, the cosine between the
one-process gradient and the data-parallel one (they differ only by the order of sums), beside the cosine between the gradients of
two different batches (the noise an approximation has to stay well inside), and both losses.

    python training/bench_data_parallel.py --weights training/checkpoints/paraformer-xfeat-w96-lowlr/last.pt \\
        --json training/results/bench_data_parallel_w96.json

Pause other jobs first (kill -STOP): the machine is shared.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from paraformer_train import data, stream  # noqa: E402
from paraformer_train.data_parallel import DataParallel  # noqa: E402
from paraformer_train.model import Matcher, log_optimal_transport_last_grad  # noqa: E402
from train import matching_losses, parse_schedule, preset  # noqa: E402

SHARED = os.path.join(HERE, "..", "..", "shared", "data")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paraformer")
    ap.add_argument("--dim", type=int, default=96)
    ap.add_argument("--heads", type=int, default=3)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--sinkhorn", type=int, default=50)
    ap.add_argument("--keypoints", default="512x8:0.55,1024x4:0.3,2048x2:0.15",
                    help="train.py's schedule: KEYPOINTSxBATCH:FRACTION_OF_STEPS,...")
    ap.add_argument("--steps", type=int, default=4, help="steps per block")
    ap.add_argument("--rounds", type=int, default=3, help="blocks per variant and keypoint count, alternated")
    ap.add_argument("--no-bf16", action="store_true", help="fp32 forward (train.py without --bf16)")
    ap.add_argument("--weights", default=None, help="train.py checkpoint (last.pt) to start from")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    bf16 = not args.no_bf16
    schedule = parse_schedule(args.keypoints)
    photos = data.list_photos([os.path.join(SHARED, "train", "bsds500_train")])[:40]
    src = stream.PairSource(photos, [], seed=321, real_fraction=0.0)
    biggest = max(b for _, b, _ in schedule)
    os.makedirs("/tmp/bench_data_parallel", exist_ok=True)
    path = stream.shard_path("/tmp/bench_data_parallel", 0)
    stream.write_shard(path, [src.pair(i) for i in range(2 * biggest)])
    shard = stream.Shard(path)
    batches = {k: [stream.collate([(shard, j * b + i) for i in range(b)], k, [False] * b) for j in range(2)]
               for k, b, _ in schedule}

    cfg = preset(args.preset, args.dim, args.depth, args.heads) | {"sinkhorn_iterations": args.sinkhorn}
    torch.manual_seed(0)
    start = torch.load(args.weights, weights_only=False)["model"] if args.weights else Matcher(cfg).state_dict()
    models = {}
    for name in ("one process, 2 threads", "two processes, 1 thread each"):
        m = Matcher(cfg).train()
        m.load_state_dict(start)
        models[name] = (m, torch.optim.AdamW(m.parameters(), lr=1e-4))
    single, dual = models
    dp = DataParallel(models[dual][0], cfg, "last", args.sinkhorn, bf16, threads=1)

    def gradient_single(bt: dict) -> tuple[torch.Tensor, float]:
        m = models[single][0]
        m.zero_grad(set_to_none=True)
        loss = matching_losses(m, None, bt, log_optimal_transport_last_grad, args.sinkhorn, bf16)[-1]
        loss.backward()
        return torch.cat([p.grad.flatten() for p in m.parameters()]), loss.item()

    def gradient_dual(bt: dict) -> tuple[torch.Tensor, float]:
        loss = dp.step(bt)
        return torch.cat([p.grad.flatten() for p in models[dual][0].parameters()]), loss

    def cosine(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(a @ b / (a.norm() * b.norm()))

    torch.set_num_threads(2)
    k0 = schedule[0][0]
    g1, l1 = gradient_single(batches[k0][0])
    g1b, _ = gradient_single(batches[k0][1])
    torch.set_num_threads(1)
    g2, l2 = gradient_dual(batches[k0][0])
    agreement = {"one process vs two, same batch": cosine(g1, g2), "two batches, one process": cosine(g1, g1b),
                 "loss one process": l1, "loss two processes": l2}
    for name, v in agreement.items():
        print(f"{name}: {v:.6f}")

    def step(name: str, bt: dict) -> float:
        m, opt = models[name]
        t = time.perf_counter()
        if name == single:
            torch.set_num_threads(2)
            m.zero_grad(set_to_none=True)
            matching_losses(m, None, bt, log_optimal_transport_last_grad, args.sinkhorn, bf16)[-1].backward()
        else:
            torch.set_num_threads(1)
            dp.step(bt)
        torch.nn.utils.clip_grad_norm_(m.parameters(), 1.0)
        opt.step()
        return time.perf_counter() - t

    results: dict = {}
    try:
        for k, b, _ in schedule:
            times = {single: [], dual: []}
            for name in times:  # warm-up
                step(name, batches[k][0])
            for r in range(args.rounds):
                for name in (times if r % 2 == 0 else list(times)[::-1]):
                    times[name] += [step(name, batches[k][s % 2]) for s in range(args.steps)]
            results[f"{k}x{b}"] = {name: {"s_per_step": float(np.median(ts)), "pairs_per_s": b / float(np.median(ts))}
                                   for name, ts in times.items()}
            for name, r in results[f"{k}x{b}"].items():
                print(f"{k:5d} keypoints x {b}: {name:30s} {r['s_per_step']:.3f} s/step  {r['pairs_per_s']:.2f} pairs/s")
    finally:
        dp.close()
    mix = {}
    for name in (single, dual):  # the schedule's mix: pairs over time, steps weighted by their fraction
        pairs = sum(f * b for _, b, f in schedule)
        secs = sum(f * results[f"{k}x{b}"][name]["s_per_step"] for k, b, f in schedule)
        mix[name] = pairs / secs
    ratio = mix[dual] / mix[single]
    print(f"schedule mix: one process {mix[single]:.2f} pairs/s, two processes {mix[dual]:.2f} pairs/s, {ratio:.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "config": cfg, "gradient_agreement": agreement, "results": results,
                       "schedule_mix_pairs_per_s": mix, "ratio": ratio}, f, indent=1)


if __name__ == "__main__":
    main()
