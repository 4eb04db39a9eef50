"""Two-view geometry and evaluation metrics, computed by the Rust core.

Estimators return ``None`` for the model (with ``reason``) on degenerate input
instead of raising.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from . import _paraformer as _core

__all__ = ["find_homography", "find_fundamental", "find_relative_pose", "pose_auc", "pose_auc_approx",
           "homography_corner_error", "gt_matches_from_homography", "match_baseline",
           "precision_recall", "mma"]


def _real(value: Any, dtype: Any, name: str, expected: str) -> np.ndarray:
    """``value`` as a real ``dtype`` array; complex input is an error, not a silently dropped imaginary part."""
    try:
        raw = np.asarray(value)
        arr = None if np.iscomplexobj(raw) else raw.astype(dtype, copy=False)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric {expected}") from None
    if arr is None:
        raise ValueError(f"{name}: expected a real {expected}, got complex dtype {raw.dtype}")
    return arr


def _points(value: Any, name: str) -> np.ndarray:
    arr = _real(value, np.float64, name, "array of shape [N, 2]")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected shape [N, 2], got {list(arr.shape)}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    return arr


def _pair(points0: Any, points1: Any) -> tuple[bytes, bytes]:
    p0, p1 = _points(points0, "points0"), _points(points1, "points1")
    if len(p0) != len(p1):
        raise ValueError(f"points1: expected shape [{len(p0)}, 2] (as many as points0), got {list(p1.shape)}")
    return np.ascontiguousarray(p0, "<f8").tobytes(), np.ascontiguousarray(p1, "<f8").tobytes()


def _mat3(value: Any, name: str) -> list[float]:
    m = _real(value, np.float64, name, "3×3 matrix")
    if m.shape != (3, 3) or not np.isfinite(m).all():
        raise ValueError(f"{name}: expected a finite 3×3 matrix, got shape {list(m.shape)}")
    return [float(v) for v in m.reshape(-1)]


def _fit(raw: tuple) -> dict:
    model, inliers, reason = raw
    return {"model": None if model is None else np.array(model).reshape(3, 3),
            "inliers": np.array(inliers, dtype=bool), "reason": reason}


def find_homography(points0: Any, points1: Any, *, threshold: float = 3.0, confidence: float = 0.999,
                    max_iterations: int = 10000, seed: int = 0) -> dict:
    """Homography by normalised DLT in RANSAC (adaptive iterations, local optimisation).

    Args:
        points0, points1: ``[N, 2]`` corresponding pixel coordinates.
        threshold: inlier transfer error ``‖H·p0 − p1‖`` in pixels.
        confidence, max_iterations, seed: RANSAC parameters.
    Returns:
        ``{"model": H [3, 3] or None, "inliers": bool [N], "reason": None or str}``.
    """
    return _fit(_core.find_homography(*_pair(points0, points1), threshold, confidence, max_iterations, seed))


def find_fundamental(points0: Any, points1: Any, *, threshold: float = 1.0, confidence: float = 0.999,
                     max_iterations: int = 10000, seed: int = 0) -> dict:
    """Fundamental matrix (``x1ᵀ F x0 = 0``) by the normalised 8-point algorithm in RANSAC.

    Args:
        points0, points1: ``[N, 2]`` pixel coordinates.
        threshold: inlier Sampson distance in pixels.
        confidence, max_iterations, seed: RANSAC parameters.
    Returns:
        ``{"model": F [3, 3] or None, "inliers": bool [N], "reason": None or str}``.
    """
    return _fit(_core.find_fundamental(*_pair(points0, points1), threshold, confidence, max_iterations, seed))


def find_relative_pose(points0: Any, points1: Any, K0: Any, K1: Any, *, threshold: float = 1.0,
                       confidence: float = 0.999, max_iterations: int = 10000, seed: int = 0) -> dict:
    """Relative pose ``x1 = R·x0 + t`` from an essential matrix in RANSAC and cheirality.

    Args:
        points0, points1: ``[N, 2]`` pixel coordinates.
        K0, K1: ``[3, 3]`` intrinsics.
        threshold: inlier Sampson distance in pixels.
        confidence, max_iterations, seed: RANSAC parameters.
    Returns:
        ``{"R": [3, 3], "t": [3] (unit), "E": [3, 3], "inliers": bool [N], "reason": None}``,
        or ``R``/``t``/``E`` None with ``reason`` when no model exists.
    """
    model, inliers, reason = _core.find_relative_pose(*_pair(points0, points1), _mat3(K0, "K0"), _mat3(K1, "K1"),
                                                      threshold, confidence, max_iterations, seed)
    out: dict = {"R": None, "t": None, "E": None, "inliers": np.array(inliers, dtype=bool), "reason": reason}
    if model is not None:
        r, t, e = model
        out.update(R=np.array(r).reshape(3, 3), t=np.array(t), E=np.array(e).reshape(3, 3))
    return out


def pose_auc(errors: Sequence[float], thresholds: Sequence[float] = (5, 10, 20)) -> list[float]:
    """Exact AUC of the recall-vs-error curve up to each threshold (SuperGlue's ``pose_auc``)."""
    return _core.pose_auc([float(e) for e in errors], [float(t) for t in thresholds])


def pose_auc_approx(errors: Sequence[float], thresholds: Sequence[int] = (5, 10, 20)) -> list[float]:
    """Approximate AUC: the mean accuracy at integer thresholds ``1..t``."""
    return _core.pose_auc_approx([float(e) for e in errors], [int(t) for t in thresholds])


def homography_corner_error(H_est: Any, H_gt: Any, width: float, height: float) -> float:
    """Mean distance of the four corners of image 0 mapped by ``H_est`` and ``H_gt`` (pixels)."""
    return _core.homography_corner_error(_mat3(H_est, "H_est"), _mat3(H_gt, "H_gt"), float(width), float(height))


def gt_matches_from_homography(H: Any, kpts0: Any, kpts1: Any, threshold: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth matches: mutual nearest neighbours under
    ``d = max(‖H·p0 − p1‖, ‖p0 − H⁻¹·p1‖)`` with ``d < threshold``; −1 unmatched, −2 ignored.

    Returns:
        ``(matches0 int64 [M], matches1 int64 [N])``.
    """
    k0 = np.ascontiguousarray(_points(kpts0, "kpts0"), "<f8").tobytes()
    k1 = np.ascontiguousarray(_points(kpts1, "kpts1"), "<f8").tobytes()
    m0, m1 = _core.gt_matches_from_homography(_mat3(H, "H"), k0, k1, float(threshold))
    return np.array(m0, dtype=np.int64), np.array(m1, dtype=np.int64)


def match_baseline(desc0: Any, desc1: Any, method: str = "mnn", ratio: float = 0.8) -> np.ndarray:
    """Nearest neighbour (``"nn"``), mutual nearest neighbour (``"mnn"``) or Lowe's ratio
    test (``"ratio"``, ``ratio`` in (0, 1]) on Euclidean descriptor distances.

    Returns:
        ``matches0`` int64 ``[M]`` (−1 = unmatched).
    """
    d0, d1 = _real(desc0, np.float32, "desc0", "[M, D] array"), _real(desc1, np.float32, "desc1", "[N, D] array")
    if d0.ndim != 2 or d1.ndim != 2 or d0.shape[1] != d1.shape[1]:
        raise ValueError(f"desc0, desc1: expected [M, D] and [N, D], got {list(d0.shape)} and {list(d1.shape)}")
    out = _core.match_baseline(np.ascontiguousarray(d0, "<f4").tobytes(), np.ascontiguousarray(d1, "<f4").tobytes(),
                               int(d0.shape[1]), method, float(ratio))
    return np.array(out, dtype=np.int64)


def precision_recall(matches0: Any, gt_matches0: Any) -> dict:
    """Precision, recall and F1 of predicted ``matches0`` against ground truth (−2 = ignored)."""
    pred, gt = _real(matches0, np.int64, "matches0", "[M] array"), _real(gt_matches0, np.int64, "gt_matches0", "[M] array")
    keep = (pred >= 0) & (gt != -2)
    tp = int(((pred == gt) & keep).sum())
    predicted, positives = int(keep.sum()), int((gt >= 0).sum())
    p = tp / predicted if predicted else 0.0
    r = tp / positives if positives else 0.0
    return {"precision": p, "recall": r, "f1": 2 * p * r / (p + r) if p + r else 0.0,
            "true_positives": tp, "predicted": predicted, "positives": positives}


def mma(H: Any, kpts0: Any, kpts1: Any, matches0: Any, max_px: int = 10) -> np.ndarray:
    """Mean matching accuracy at ``1..max_px`` pixels under the true homography ``H``."""
    k0, k1 = _points(kpts0, "kpts0"), _points(kpts1, "kpts1")
    m = _real(matches0, np.int64, "matches0", "[M] array")
    i = np.flatnonzero(m >= 0)
    if len(i) == 0:
        return np.zeros(max_px)
    p = np.c_[k0[i], np.ones(len(i))] @ _real(H, np.float64, "H", "3×3 matrix").T
    err = np.linalg.norm(p[:, :2] / p[:, 2:] - k1[m[i]], axis=1)
    return np.array([(err <= t).mean() for t in range(1, max_px + 1)])
