"""Two images in, matches and a geometric model out: the Python twin of ``paraformer match``."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from . import geometry as _geo
from ._paraformer import BASELINE_NAMES

#: The baselines' method names, as the core parses them (``ratio`` also as ``ratio:R``).
BASELINES = tuple(BASELINE_NAMES)


class Baseline:
    """Descriptor matching without a network (``mnn``, ``nn``, ``ratio[:R]``), with the
    ``match_dicts`` / ``match_many`` interface; scores are cosine similarities mapped to [0, 1]."""

    def __init__(self, spec: str):
        from ._paraformer import parse_baseline

        parsed = parse_baseline(spec)  # checked in the core: a ratio in (0, 1]
        if parsed is None:
            raise ValueError(f"matcher: unknown baseline {spec!r}")
        self.method, self.ratio = parsed

    def match_dicts(self, f0: dict, f1: dict) -> dict:
        d0, d1 = np.asarray(f0["descriptors"], np.float32), np.asarray(f1["descriptors"], np.float32)
        m0 = np.asarray(_geo.match_baseline(d0, d1, self.method, self.ratio), np.int64)
        s0 = np.zeros(len(m0), np.float32)
        ok = m0 >= 0
        s0[ok] = (np.einsum("ij,ij->i", d0[ok], d1[m0[ok]]) + 1) / 2
        return {"matches0": m0, "matching_scores0": s0}

    def match_many(self, pairs, num_threads: Optional[int] = None) -> list[dict]:
        return [self.match_dicts(f0, f1) for f0, f1 in pairs]


def load_matcher(matcher: Any, precision: str = "fp32") -> Any:
    """A matcher from a shipped name, a baseline (``mnn``, ``nn``, ``ratio[:R]``), a weights
    file (loaded in ``precision``) or a ``paraformer.Matcher`` (returned as is)."""
    from . import Matcher, pretrained_names

    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision: expected \"fp32\" or \"bf16\", got {precision!r}")
    if isinstance(matcher, (Matcher, Baseline)):
        return matcher
    if not isinstance(matcher, (str, os.PathLike)):
        raise ValueError(f"matcher: expected a name, a weights file or a Matcher, got {type(matcher).__name__}")
    spec = os.fspath(matcher)
    if spec in pretrained_names():
        return Matcher.pretrained(spec, precision=precision)
    if spec.partition(":")[0] in BASELINES:
        return Baseline(spec)
    if Path(spec).is_file():
        return Matcher.from_file(spec, precision=precision)
    raise ValueError(f"matcher: {spec!r} is not a pretrained name ({', '.join(pretrained_names())}), "
                     f"a baseline ({', '.join(BASELINES)}) or a weights file")


def load_image(image: Union[str, os.PathLike, np.ndarray], name: str) -> np.ndarray:
    """A path or an array as the grey ``[H, W]`` float32 image XFeat sees."""
    from ._paraformer import load_image as _load

    if isinstance(image, (str, os.PathLike)):
        data, w, h = _load(os.fspath(image))
        return np.frombuffer(data, "<f4").reshape(h, w).astype(np.float32)
    arr = np.asarray(image)
    if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{name}: expected a path or an integer or float array [H, W] or [H, W, C], got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] in (1, 2, 3, 4):
        c = arr.shape[2]
        arr = arr[:, :, :1] if c <= 2 else arr[:, :, :3]
        arr = arr.astype(np.float32).mean(axis=2)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected shape [H, W] or [H, W, C] with C in 1..4, got {list(np.shape(image))}")
    return arr.astype(np.float32, copy=False)


def unrotate(points: np.ndarray, k: int, width: int, height: int) -> np.ndarray:
    """Points of ``np.rot90(img, k)`` (``img`` of ``width × height``) back in ``img``'s
    frame; pixel centres at integer coordinates."""
    p = np.asarray(points, np.float64).reshape(-1, 2).copy()
    for j in range(k % 4, 0, -1):
        # np.rot90 turns an image of width w counter-clockwise: its pixel (x, y) is pixel
        # (w − 1 − y, x) of the image before the turn; undo the turns last one first.
        w = width if (j - 1) % 2 == 0 else height
        p = np.stack([w - 1 - p[:, 1], p[:, 0]], axis=1)
    return p


def match_images(image0: Any, image1: Any, *, matcher: Any = "paraformer-xfeat", max_keypoints: int = 2048,
                 geometry: Optional[str] = "homography", threshold: float = 3.0, rotations: int = 1,
                 precision: str = "fp32") -> dict:
    """Matches two images end to end: XFeat, a matcher, RANSAC (``paraformer match``).

    With ``rotations=4``, image1 is also matched turned by 90, 180 and 270° (XFeat's
    descriptors are upright) and the turn with the most inliers (most matches without a
    geometry) is kept; everything is returned in image1's original frame.

    Args:
        image0, image1: paths or arrays (``[H, W]`` or ``[H, W, C]``, uint8, another
            integer type, or float 0–255).
        matcher: a shipped name, ``mnn``/``nn``/``ratio[:R]``, a weights file or a ``Matcher``.
        max_keypoints: XFeat keypoints per image.
        geometry: ``"homography"``, ``"fundamental"`` or None (no RANSAC).
        threshold: RANSAC inlier threshold in pixels.
        rotations: 1 (as given) or 4 (also 90, 180, 270°).
        precision: ``"fp32"`` or ``"bf16"`` for a learned matcher given by name or file
            (see ``paraformer.Matcher``).
    Returns:
        ``keypoints0`` ``[M, 2]``, ``keypoints1`` ``[N, 2]``, ``matches`` int64 ``[K, 2]``
        (index pairs), ``scores`` ``[K]``, ``model`` (3×3 or None), ``inliers`` bool ``[K]``
        (None without a geometry) and ``rotation`` (degrees image1 was turned
        counter-clockwise for the kept result: 0, 90, 180 or 270).
    """
    from . import extract

    if rotations not in (1, 4) or isinstance(rotations, bool):
        raise ValueError(f"rotations: expected 1 or 4, got {rotations!r}")
    if geometry not in ("homography", "fundamental", None):
        raise ValueError(f"geometry: expected 'homography', 'fundamental' or None, got {geometry!r}")
    if not isinstance(threshold, (int, float)) or isinstance(threshold, bool) or not np.isfinite(threshold) or threshold <= 0:
        raise ValueError(f"threshold: expected a positive number of pixels, got {threshold!r}")
    model_fn = load_matcher(matcher, precision)
    img0, img1 = load_image(image0, "image0"), load_image(image1, "image1")
    h1, w1 = img1.shape
    f0 = extract(img0, max_keypoints=max_keypoints)
    best: dict = {}
    for k in range(rotations):
        f1 = extract(np.ascontiguousarray(np.rot90(img1, k)), max_keypoints=max_keypoints)
        out = model_fn.match_dicts(f0, f1)
        m0 = np.asarray(out["matches0"])
        idx = np.nonzero(m0 >= 0)[0]
        matches = np.stack([idx, m0[idx]], axis=1).astype(np.int64)
        kp1 = unrotate(f1["keypoints"], k, w1, h1).astype(np.float32)
        res: dict[str, Any] = {"keypoints0": f0["keypoints"], "keypoints1": kp1, "matches": matches,
               "scores": np.asarray(out["matching_scores0"], np.float32)[idx], "model": None,
               "inliers": None, "rotation": 90 * k}
        if geometry is not None:
            p0, p1 = f0["keypoints"][matches[:, 0]], kp1[matches[:, 1]]
            if len(matches) >= (4 if geometry == "homography" else 8):
                fit = (_geo.find_homography if geometry == "homography" else _geo.find_fundamental)(
                    p0, p1, threshold=threshold)
                res["model"], res["inliers"] = fit["model"], fit["inliers"]
            else:
                res["inliers"] = np.zeros(len(matches), bool)
        score = len(matches) if geometry is None else int(np.sum(res["inliers"]))
        if not best or score > best["_score"]:
            best = res | {"_score": score}
    best.pop("_score")
    return best
