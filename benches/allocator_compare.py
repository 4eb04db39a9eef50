"""The process allocator, mimalloc (the default) against the system's (glibc), in one script:
the same work in alternated child processes that differ only in ``PARAFORMER_ALLOCATOR``.

  * ``pipeline``: a Python loop as a pipeline runs it, XFeat on both images of the sample pair
    (2048 keypoints) and then ``paraformer-xfeat`` on the pair; the medians of both parts;
  * ``bench``: ``paraformer bench --model paraformer-xfeat --keypoints 2048`` (random weights,
    the best of its repeats; needs ``cargo build --release -p paraformer-cli``).

Ratios are mimalloc / system (below 1: mimalloc faster).

    python benches/allocator_compare.py --rounds 3
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ALLOCATORS = ("system", "mimalloc")

PIPELINE = r"""
import json, sys, time
import paraformer
m = paraformer.Matcher.pretrained("paraformer-xfeat")
imgs = sys.argv[1:3]
ex, mt = [], []
for i in range(int(sys.argv[3]) + 1):
    t0 = time.perf_counter()
    f0, f1 = (paraformer.extract(p, 2048) for p in imgs)
    t1 = time.perf_counter()
    m.match_dicts(f0, f1)
    t2 = time.perf_counter()
    if i:  # the first call warms up
        ex.append(t1 - t0); mt.append(t2 - t1)
print(json.dumps({"allocator": paraformer._paraformer.allocator(), "extract": ex, "match": mt}))
"""


def child_env(allocator: str, threads: int) -> dict:
    return dict(os.environ, PARAFORMER_ALLOCATOR=allocator, RAYON_NUM_THREADS=str(threads))


def pipeline(allocator: str, calls: int, threads: int) -> dict:
    sample = ROOT / "assets" / "sample"
    out = subprocess.run([sys.executable, "-c", PIPELINE, str(sample / "coffee_0.jpg"), str(sample / "coffee_1.jpg"),
                          str(calls)], env=child_env(allocator, threads), capture_output=True, text=True, check=True)
    res = json.loads(out.stdout)
    if res["allocator"] != allocator:
        sys.exit(f"error: asked for {allocator}, the module runs {res['allocator']}")
    return res


def bench(cli: str, allocator: str, threads: int) -> dict:
    out = subprocess.run([cli, "bench", "--model", "paraformer-xfeat", "--keypoints", "2048", "--repeat", "5"],
                         env=child_env(allocator, threads), capture_output=True, text=True, check=True)
    if f"allocator: {allocator}" not in out.stdout:
        sys.exit(f"error: asked for {allocator}, the command reports:\n{out.stdout}")
    row = out.stdout.strip().splitlines()[-1].split()
    return {"total": float(row[2]) / 1e3, "layers": float(row[4]) / 1e3, "sinkhorn": float(row[6]) / 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3, help="alternated rounds (each runs every allocator once)")
    ap.add_argument("--calls", type=int, default=8, help="timed pipeline iterations per child")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cli", default=str(ROOT / "target" / "release" / "paraformer"))
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    times: dict = {a: {"extract": [], "match": [], "bench_total": [], "bench_layers": [], "bench_sinkhorn": []} for a in ALLOCATORS}
    have_cli = os.path.exists(args.cli)
    if not have_cli:
        print(f"skipped the bench rows: no {args.cli} (cargo build --release -p paraformer-cli)")
    for r in range(args.rounds):
        for a in ALLOCATORS if r % 2 == 0 else ALLOCATORS[::-1]:
            res = pipeline(a, args.calls, args.threads)
            times[a]["extract"].append(statistics.median(res["extract"]))
            times[a]["match"].append(statistics.median(res["match"]))
            if have_cli:
                b = bench(args.cli, a, args.threads)
                for k in ("total", "layers", "sinkhorn"):
                    times[a][f"bench_{k}"].append(b[k])
    report = {"threads": args.threads, "rounds": args.rounds, "calls": args.calls, "rows": {}}
    print(f"{'row':<16} {'system ms':>10} {'mimalloc ms':>12} {'ratio':>7}")
    for row in times["system"]:
        if not times["system"][row]:
            continue
        s, m = (statistics.median(times[a][row]) for a in ALLOCATORS)
        report["rows"][row] = {"system_s": s, "mimalloc_s": m, "ratio": m / s}
        print(f"{row:<16} {1e3 * s:>10.1f} {1e3 * m:>12.1f} {m / s:>7.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
