"""Synthetic homography pairs on the glue-factory-like recipe: each of the two views is a
perspective patch of one photo (no black borders), both views warped, rotation up to ±45°
per view, difficulty up to 0.8, then photometric changes.

Everything is seeded by the caller's ``np.random.Generator``, so a pair regenerates
bit-for-bit from ``(seed, index)``.
"""
from __future__ import annotations

import glob
import math
import os

import cv2
import numpy as np

PHOTO_EXTS = (".jpg", ".jpeg", ".png", ".pgm", ".ppm")


def probability(text: str) -> float:
    """An argparse type for the stream's per-view probabilities (--heavy-noise, --real-warp)."""
    import argparse

    p = float(text)
    if not 0.0 <= p <= 1.0:
        raise argparse.ArgumentTypeError(f"is a probability in [0, 1], got {text}")
    return p


def list_photos(roots: list[str]) -> list[str]:
    files = []
    for root in roots:
        files += [p for p in glob.glob(os.path.join(root, "**", "*"), recursive=True) if p.lower().endswith(PHOTO_EXTS)]
    if not files:
        raise FileNotFoundError(f"no photos under {roots}")
    return sorted(files)


def load_photo(path: str, max_side: int = 1024) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"{path}: unreadable image")
    s = max_side / max(img.shape)
    if s < 1:
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    return img


def output_size(photo: np.ndarray) -> tuple[int, int]:
    """640×480 for photos that hold it, 480×320 for small ones (BSDS), in the photo's orientation."""
    h, w = photo.shape
    big = min(h, w) >= 560
    long_, short = (640, 480) if big else (480, 320)
    return (long_, short) if w >= h else (short, long_)


def sample_patch(photo_wh: tuple[int, int], out_wh: tuple[int, int], difficulty: float,
                 rng: np.random.Generator, tries: int = 50) -> np.ndarray:
    """A homography mapping photo pixels to a ``out_wh`` view: a patch of the photo, scaled,
    rotated up to ±45°, with its corners displaced by up to ``0.25·difficulty`` of its size
    (perspective), kept inside the photo (resampled, then less difficult, if it leaves)."""
    pw, ph = photo_wh
    ow, oh = out_wh
    rect = np.array([[0, 0], [ow, 0], [ow, oh], [0, oh]], np.float64)
    d = float(np.clip(difficulty, 0.0, 1.0))
    for t in range(tries):
        dd = d * (1.0 - t / tries)
        # Patch size as a fraction of the largest patch of the view's aspect that fits.
        fit = min(pw / ow, ph / oh)
        size = fit * rng.uniform(0.55, 0.95) * math.exp(rng.uniform(-0.3, 0.1) * dd)
        angle = math.radians(rng.uniform(-45.0, 45.0) * min(1.0, dd / 0.7))
        half = np.array([ow, oh]) * size / 2
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64) * half
        corners += rng.uniform(-0.25 * dd, 0.25 * dd, size=(4, 2)) * half * 2
        rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        corners = corners @ rot.T
        lo, hi = -corners.min(0), np.array([pw, ph]) - corners.max(0)
        if np.any(hi <= lo):
            continue
        quad = corners + rng.uniform(lo, hi)
        return cv2.getPerspectiveTransform(quad.astype(np.float32), rect.astype(np.float32)).astype(np.float64)
    # Fallback: the centred, upright patch that fits.
    size = min(pw / ow, ph / oh)
    quad = (rect - [ow / 2, oh / 2]) * size + [pw / 2, ph / 2]
    return cv2.getPerspectiveTransform(quad.astype(np.float32), rect.astype(np.float32)).astype(np.float64)


def motion_kernel(k: int, angle: float) -> np.ndarray:
    """A ``k × k`` motion-blur kernel: a line through the centre at ``angle`` degrees, summing to 1."""
    kernel = np.zeros((k, k), np.float32)
    kernel[k // 2] = 1.0 / k
    m = cv2.getRotationMatrix2D((k / 2 - 0.5, k / 2 - 0.5), angle, 1.0)
    kernel = cv2.warpAffine(kernel, m, (k, k))
    return kernel / max(kernel.sum(), 1e-6)


def photometric(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0,
                heavy_noise: float = 0.0) -> np.ndarray:
    """Brightness/contrast, gamma, blur, Gaussian noise, JPEG, each applied with probability.

    ``heavy_noise``: the probability of Gaussian noise of σ 15-80 grey levels instead of the
    mild σ 2-12 (homography/iguazu_noise reaches σ 78). At 0 no random number is drawn for it,
    so the default stream stays bit-identical."""
    x = img.astype(np.float32)
    if rng.random() < 0.8:
        x = (x - 127.5) * rng.uniform(1 - 0.35 * strength, 1 + 0.35 * strength) + 127.5 + rng.uniform(-35, 35) * strength
    x = np.clip(x, 0, 255)
    if rng.random() < 0.5:
        x = 255.0 * (x / 255.0) ** rng.uniform(1 - 0.4 * strength, 1 + 0.5 * strength)
    if rng.random() < 0.3:
        k = int(rng.choice([3, 5, 7]))
        x = cv2.GaussianBlur(x, (k, k), rng.uniform(0.3, 1.8))
    elif rng.random() < 0.1:
        k = int(rng.choice([5, 7, 9]))
        x = cv2.filter2D(x, -1, motion_kernel(k, rng.uniform(0, 180)))
    if heavy_noise > 0 and rng.random() < heavy_noise:
        x = x + rng.normal(0, rng.uniform(15, 80), x.shape)
    elif rng.random() < 0.4:
        x = x + rng.normal(0, rng.uniform(2, 12) * strength, x.shape)
    x = np.clip(x, 0, 255).astype(np.uint8)
    if rng.random() < 0.4:
        ok, buf = cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(25, 90))])
        if ok:
            x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return x


def make_pair(photo: np.ndarray, rng: np.random.Generator, difficulty=(0.3, 0.85), heavy_noise: float = 0.0):
    """Two independently warped, photometrically changed views of ``photo`` and the
    homography mapping view-0 pixels to view-1 pixels."""
    ph, pw = photo.shape
    ow, oh = output_size(photo)
    hs = [sample_patch((pw, ph), (ow, oh), rng.uniform(*difficulty), rng) for _ in range(2)]
    views = [photometric(cv2.warpPerspective(photo, hm, (ow, oh), flags=cv2.INTER_LINEAR,
                                             borderMode=cv2.BORDER_REFLECT), rng, heavy_noise=heavy_noise) for hm in hs]
    return views, hs[1] @ np.linalg.inv(hs[0])


def apply_h(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Pixels ``[K, 2]`` mapped by a homography (float32; points at infinity become NaN)."""
    p = np.concatenate([pts.astype(np.float64), np.ones((len(pts), 1))], 1) @ h.T
    with np.errstate(divide="ignore", invalid="ignore"):
        out = p[:, :2] / p[:, 2:3]
    out[~np.isfinite(out).all(1)] = np.nan
    return out.astype(np.float32)
