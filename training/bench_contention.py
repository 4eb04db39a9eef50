"""The training step beside the pair generator: which OpenMP wait policy and thread count
make the most of two cores shared with it.

The long runs train with 2 PyTorch threads while ``generate_pairs.py`` takes about a third
of a core beside them. A thread that waits at an OpenMP barrier spins by default; when the
generator has taken the other core, the spinning thread burns the time that the thread it
waits for needs. This times ``train.py``'s step (bf16 forward, SDPA, last-iteration
Sinkhorn gradient, AdamW) for each setting in its own process (libgomp reads its
environment once), alternating the settings round by round, with and without a background
load that mimics the generator: one process busy for ``--load-busy-ms`` of every
``--load-period-ms``.

    python training/bench_contention.py --weights training/checkpoints/paraformer-xfeat-w96-lowlr/last.pt \\
        --json training/results/step_contention_w96.json

Pause any training first (``kill -STOP``): the load is the only other work this assumes.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SETTINGS = {  # name: (environment, torch threads)
    "2 threads, spin (default)": ({}, 2),
    "2 threads, OMP_WAIT_POLICY=PASSIVE": ({"OMP_WAIT_POLICY": "PASSIVE"}, 2),
    "1 thread": ({}, 1),
}


def child(args: argparse.Namespace) -> None:
    """One setting: time ``--steps`` steps at each keypoint count; print JSON."""
    import torch

    sys.path.insert(0, HERE)
    from paraformer_train import model as model_mod, stream
    from paraformer_train.model import Matcher, log_optimal_transport_last_grad
    from train import nll_loss, preset

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = preset("paraformer", args.dim, args.depth, args.heads) | {"sinkhorn_iterations": 50}
    m = Matcher(cfg).train()
    if args.weights:
        m.load_state_dict(torch.load(args.weights, weights_only=False)["model"])
    opt = torch.optim.AdamW(m.parameters(), lr=1e-4)
    model_mod.FUSED_ATTENTION = True
    shard = stream.Shard(args.shard)
    out = {}
    for kp, batch in ((512, 8), (2048, 2)):
        bt = stream.collate([(shard, i) for i in range(batch)], kp, [False] * batch)

        def step() -> float:
            t = time.perf_counter()
            with torch.autocast("cpu", dtype=torch.bfloat16):
                scores = m.scores(bt)
            loss = nll_loss(log_optimal_transport_last_grad(scores.float(), m.bin_score, 50), bt["gt0"], bt["gt1"])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(m.parameters(), 1.0)
            opt.step()
            return time.perf_counter() - t

        step()  # warm-up
        out[f"{kp}x{batch}"] = [step() for _ in range(args.steps)]
    print("RESULT " + json.dumps(out), flush=True)


def load(busy_ms: float, period_ms: float) -> None:
    """Busy for ``busy_ms`` of every ``period_ms``, like the generator's share of a core."""
    while True:
        t = time.perf_counter()
        x = 0.0
        while (time.perf_counter() - t) * 1000 < busy_ms:
            x += 1.0
        time.sleep(max(0.0, period_ms - (time.perf_counter() - t) * 1000) / 1000)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None, help="train.py checkpoint (last.pt) to start from")
    ap.add_argument("--dim", type=int, default=96)
    ap.add_argument("--heads", type=int, default=3)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--steps", type=int, default=5, help="timed steps per keypoint count and round")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--load-busy-ms", type=float, default=35.0)
    ap.add_argument("--load-period-ms", type=float, default=100.0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--shard", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--load", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.load:
        load(args.load_busy_ms, args.load_period_ms)
        return
    if args.child:
        child(args)
        return
    if args.load_busy_ms < 0 or args.load_period_ms <= args.load_busy_ms:
        sys.exit("error: --load-busy-ms must be in [0, --load-period-ms)")

    sys.path.insert(0, HERE)
    from paraformer_train import data, stream

    # One shard of 8 synthetic pairs, shared by every child.
    photos = data.list_photos([os.path.join(HERE, "..", "..", "shared", "data", "train", "bsds500_train")])[:20]
    if not photos:
        sys.exit("error: no photos in ../shared/data/train/bsds500_train")
    src = stream.PairSource(photos, [], seed=123, real_fraction=0.0)
    os.makedirs("/tmp/bench_contention", exist_ok=True)
    shard = stream.shard_path("/tmp/bench_contention", 0)
    stream.write_shard(shard, [src.pair(i) for i in range(8)])

    times: dict[str, dict[str, list[float]]] = {}
    for loaded in (False, True):
        bg = None
        if loaded:
            bg = subprocess.Popen([sys.executable, __file__, "--load", "--load-busy-ms", str(args.load_busy_ms),
                                   "--load-period-ms", str(args.load_period_ms)])
        try:
            for r in range(args.rounds):
                names = list(SETTINGS) if r % 2 == 0 else list(SETTINGS)[::-1]
                for name in names:
                    env_extra, threads = SETTINGS[name]
                    cmd = [sys.executable, __file__, "--child", "--threads", str(threads), "--shard", shard,
                           "--dim", str(args.dim), "--heads", str(args.heads), "--depth", str(args.depth),
                           "--steps", str(args.steps)] + (["--weights", args.weights] if args.weights else [])
                    res = subprocess.run(cmd, env=dict(os.environ, **env_extra), capture_output=True, text=True)
                    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
                    if res.returncode != 0 or not line:
                        sys.exit(f"error: setting '{name}' failed:\n{res.stderr[-2000:]}")
                    key = f"{name}{' + load' if loaded else ''}"
                    for shape, ts in json.loads(line[0][7:]).items():
                        times.setdefault(key, {}).setdefault(shape, []).extend(ts)
                    print(f"round {r} {key}: " + ", ".join(f"{s} {np.median(t):.3f} s" for s, t in times[key].items()),
                          flush=True)
        finally:
            if bg is not None:
                bg.kill()
    res = {k: {s: {"s_per_step": float(np.median(t)), "steps": len(t)} for s, t in v.items()} for k, v in times.items()}
    print(f"\n{'setting':50s} {'512x8 s/step':>13s} {'2048x2 s/step':>14s}")
    for k, v in res.items():
        print(f"{k:50s} {v['512x8']['s_per_step']:13.3f} {v['2048x2']['s_per_step']:14.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": {k: v for k, v in vars(args).items() if k not in ("child", "shard", "load", "threads")},
                       "results": res}, f, indent=1)


if __name__ == "__main__":
    main()
