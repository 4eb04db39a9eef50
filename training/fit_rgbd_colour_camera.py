"""Fits the colour camera of an RGB-D sequence whose colour frames are not the depth camera
that its K.txt and poses describe (7-Scenes: a Kinect's colour camera, focal ≈ 525, a few cm
beside the depth camera, K = 585), so that its pairs can be training data.

Unknowns: the colour intrinsics (one focal, principal point) and the rigid transform from
the depth camera to the colour camera (rotation vector, translation across the optical
axis; along it the offset trades against the focal and drifted without lowering the
residual): 8 parameters shared by every frame. Observations: XFeat matches between colour frames of the training part (mutual
nearest neighbours, kept by a fundamental-matrix RANSAC at 1 px), never the held-out tail.
The residual of a match is where the depth of its first keypoint, carried through the
poses, lands in the second frame, against where the second keypoint is (both directions).
Depth is re-rendered into the colour camera under the current estimate, the parameters are
fitted with that depth held fixed (robust least squares), and the two alternate; the round
with the lowest median residual is kept.

    python training/fit_rgbd_colour_camera.py ../shared/data/rgbd/7scenes_sample

It writes the fit into ``paraformer_train/rgbd_colour_cameras.json`` (read by
``rgbd.Sequence``) with the residuals before and after on training and held-out pairs, and
prints the same for every other sequence (with its shipped calibration) for comparison.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import cv2
import numpy as np
from paraformer.geometry import match_baseline
from scipy.optimize import least_squares

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train import rgbd  # noqa: E402


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]


def camera(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K_colour, T_colour_from_depth) of the parameter vector [f, cx, cy, rvec(3), tx, ty]."""
    f, cx, cy = theta[:3]
    k = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    t = np.eye(4)
    t[:3, :3] = rodrigues(theta[3:6])
    t[:2, 3] = theta[6:8]
    return k, t


def matches(seq: rgbd.Sequence, a: int, b: int, feats: dict, extract) -> tuple[np.ndarray, np.ndarray]:
    """Mutual-nearest XFeat matches of colour frames a and b that a 1 px RANSAC keeps."""
    for i in (a, b):
        if i not in feats:
            feats[i] = extract(seq.gray(i), 2048)
    fa, fb = feats[a], feats[b]
    m0 = match_baseline(fa["descriptors"], fb["descriptors"], "mnn")
    pa, pb = fa["keypoints"][m0 >= 0], fb["keypoints"][m0[m0 >= 0]]
    if len(pa) < 16:
        return pa[:0], pb[:0]
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
    if mask is None:
        return pa[:0], pb[:0]
    keep = mask.ravel().astype(bool)
    return pa[keep].astype(np.float64), pb[keep].astype(np.float64)


def transfer(theta: np.ndarray, pts: np.ndarray, z: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Colour keypoints of frame a with colour depth z, in the colour frame b (depth-camera poses)."""
    k, t_cd = camera(theta)
    x_ca = np.linalg.solve(k, np.stack([pts[:, 0], pts[:, 1], np.ones(len(pts))])) * z
    rel = t_cd @ np.linalg.solve(pose_b, pose_a) @ np.linalg.inv(t_cd)  # colour a → colour b
    x_cb = rel[:3, :3] @ x_ca + rel[:3, 3:4]
    uv = (k @ x_cb)[:2] / np.maximum(x_cb[2], 1e-6)
    return uv.T


def residual_distances(seq: rgbd.Sequence, pairs: list, obs: dict) -> np.ndarray:
    """Distance of each match (both directions) to the reprojection of ``rgbd.project`` with
    the sequence's own K, poses and depth, over the keypoints that it calls visible."""
    out = []
    for a, b in pairs:
        pa, pb = obs[(a, b)]
        if len(pa) == 0:
            continue
        da, db = seq.depth(a), seq.depth(b)
        for p, q, d0, d1, i, j in ((pa, pb, da, db, a, b), (pb, pa, db, da, b, a)):
            proj = rgbd.project(p.astype(np.float32), d0, d1, seq.K, seq.poses[i], seq.poses[j])
            ok = np.isfinite(proj[:, 0]) & (proj[:, 0] < rgbd.OCCLUDED)
            out.append(np.linalg.norm(proj[ok] - q[ok], axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def summary(d: np.ndarray) -> dict:
    if len(d) == 0:
        return {"matches": 0}
    return {"matches": int(len(d)), "median_px": round(float(np.median(d)), 2),
            "p75_px": round(float(np.percentile(d, 75)), 2),
            "within_3px": round(float((d < 3).mean()), 3), "within_8px": round(float((d < 8).mean()), 3)}


def frame_pairs(frames: range, gaps: tuple[int, ...], stride: int) -> list[tuple[int, int]]:
    return [(a, a + g) for a in frames[::stride] for g in gaps if a + g in frames]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", help="RGB-D sequence folder")
    ap.add_argument("--focal", type=float, default=525.0, help="initial colour focal (px)")
    ap.add_argument("--gaps", default="2,4,6", help="frame gaps of the fitting pairs")
    ap.add_argument("--stride", type=int, default=3, help="every this many frames starts pairs")
    ap.add_argument("--rounds", type=int, default=6, help="depth re-rendering / fitting rounds")
    ap.add_argument("--out", default=rgbd.COLOUR_CAMERAS)
    ap.add_argument("--dry-run", action="store_true", help="print, write nothing")
    args = ap.parse_args()
    import paraformer

    gaps = tuple(int(g) for g in args.gaps.split(","))
    raw = rgbd.Sequence(args.sequence, colour_camera=False)
    cut = int(len(raw) * (1 - rgbd.HOLDOUT_FRACTION))
    train = frame_pairs(range(0, cut - 10), gaps, args.stride)
    held = frame_pairs(range(cut, len(raw)), gaps, 1)
    feats: dict = {}
    obs = {p: matches(raw, *p, feats, paraformer.extract) for p in train + held}
    print(f"{raw.name}: {len(train)} training pairs ({sum(len(obs[p][0]) for p in train)} matches), "
          f"{len(held)} held-out pairs ({sum(len(obs[p][0]) for p in held)} matches)", flush=True)
    before = {"train": summary(residual_distances(raw, train, obs)),
              "holdout": summary(residual_distances(raw, held, obs))}
    print("as shipped:", before, flush=True)

    k_d = raw.K
    theta = np.array([args.focal, k_d[0, 2], k_d[1, 2], 0, 0, 0, 0, 0], np.float64)
    best = (np.inf, theta)
    depths = {i: raw.depth(i) for p in train for i in p}
    rays = {s: rgbd.pixel_rays(k_d, s) for s in {d.shape for d in depths.values()}}  # K_d is fixed
    for r in range(args.rounds):
        k_c, t_cd = camera(theta)
        reg = {i: rgbd.register_depth(d, k_d, k_c, t_cd, d.shape, rays[d.shape]) for i, d in depths.items()}
        terms = []  # (points of a, their colour depth, matched points of b, pose a, pose b)
        for a, b in train:
            pa, pb = obs[(a, b)]
            for p, q, i, j in ((pa, pb, a, b), (pb, pa, b, a)):
                z = rgbd.depth_at(reg[i], p)
                ok = z > 0
                if ok.sum() >= 8:
                    terms.append((p[ok], z[ok], q[ok], raw.poses[i], raw.poses[j]))

        def residuals(th: np.ndarray) -> np.ndarray:
            return np.concatenate([(transfer(th, p, z, pa, pb) - q).ravel() for p, z, q, pa, pb in terms])

        fit = least_squares(residuals, theta, loss="soft_l1", f_scale=2.0, x_scale=[10, 10, 10, .01, .01, .01, .01, .01])
        theta = fit.x
        med = float(np.median(np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)))
        best = min(best, (med, theta), key=lambda b: b[0])
        print(f"round {r}: f {theta[0]:.1f} c ({theta[1]:.1f}, {theta[2]:.1f}) rotation {np.degrees(np.linalg.norm(theta[3:6])):.2f}° "
              f"t {np.round(theta[6:8] * 100, 2)} cm, median residual {med:.2f} px over {len(fit.fun) // 2}", flush=True)

    k_c, t_cd = camera(best[1])
    entry = {"K": k_c.tolist(), "T_colour_from_depth": t_cd.tolist(),
             "fit": {"command": " ".join(sys.argv), "training_pairs": len(train), "holdout_pairs": len(held),
                     "as_shipped": before}}
    fitted = rgbd.Sequence(args.sequence, colour_camera=False)  # the path training takes, with the fit
    fitted.use_colour_camera(k_c, t_cd)
    after = {"train": summary(residual_distances(fitted, train, obs)),
             "holdout": summary(residual_distances(fitted, held, obs))}
    entry["fit"]["fitted"] = after
    print("fitted:", after, flush=True)
    for other in sorted(os.listdir(os.path.dirname(os.path.abspath(args.sequence)))):
        root = os.path.join(os.path.dirname(os.path.abspath(args.sequence)), other)
        if other == raw.name or not os.path.isdir(root) or other in rgbd.MISREGISTERED:
            continue
        seq = rgbd.Sequence(root)
        c = int(len(seq) * (1 - rgbd.HOLDOUT_FRACTION))
        ref = frame_pairs(range(c, len(seq)), gaps, 1)
        ref_feats: dict = {}
        o = {p: matches(seq, *p, ref_feats, paraformer.extract) for p in ref}
        entry["fit"][f"reference_{other}_holdout"] = summary(residual_distances(seq, ref, o))
        print(f"reference {other} (held-out tail, shipped calibration):", entry["fit"][f"reference_{other}_holdout"])
    if args.dry_run:
        return
    cams = rgbd.colour_cameras(args.out)
    cams[raw.name] = entry
    with open(args.out + ".tmp", "w") as f:
        json.dump(cams, f, indent=1)
    os.replace(args.out + ".tmp", args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
