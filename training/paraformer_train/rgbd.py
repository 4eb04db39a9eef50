"""Real pairs from the RGB-D sequences in ``../shared/data/rgbd``: frame pairs chosen by
depth covisibility, and per-keypoint reprojections into the other frame with an
occlusion check, from which ``labels.ground_truth`` builds the 3 px ground truth.

Projection codes per keypoint (``[K, 2]`` float32):
  * the pixel in the other frame where its 3D point lands (visible, or outside the frame);
  * ``OCCLUDED`` (far away: it becomes unmatched) when the other frame's depth shows a
    surface in front of it;
  * NaN (unknown: ignored unless the other direction decides) when either depth is missing
    or the two depths disagree the other way (sensor or pose error).
"""
from __future__ import annotations

import glob
import hashlib
import json
import os

import cv2
import numpy as np

OCCLUDED = 1.0e6
DEPTH_TOLERANCE = 0.05  # relative depth agreement for "the same surface"
# Sequences whose colour frames do not fit the intrinsics and poses they ship with: 7-Scenes'
# colour camera (focal ≈ 525, a few cm beside the depth camera) is not the depth camera
# (K = 585) that K.txt and the poses describe, so reprojected keypoints miss by 10-50 px
# (median distance of LighterGlue's matches to their reprojections; HoloLens: 2-6 px).
# Such a sequence is used only with a fitted colour camera (COLOUR_CAMERAS, written by
# ``training/fit_rgbd_colour_camera.py``): its depth is then re-rendered into the colour frame.
MISREGISTERED = ("7scenes_sample",)
FRAME_CACHE = 2048  # decoded frames a Sequence keeps (grey 0.3 MB, depth 1.2 MB at 640×480)
COLOUR_CAMERAS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "rgbd_colour_cameras.json")


def colour_cameras(path: str | None = None) -> dict:
    """Fitted colour cameras by sequence name: ``K`` (3×3) and ``T_colour_from_depth`` (4×4)."""
    path = path or COLOUR_CAMERAS
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        return json.load(f)


def usable(root: str) -> bool:
    """Whether a sequence's colour frames fit its depth and poses (as shipped, or fitted)."""
    name = os.path.basename(os.path.normpath(root))
    return name not in MISREGISTERED or name in colour_cameras()


def pixel_rays(k: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``K⁻¹ (x, y, 1)`` of every pixel, ``[3, H, W]`` float64."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    return np.linalg.solve(k, np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)]).astype(np.float64)).reshape(3, h, w)


def register_depth(depth: np.ndarray, k_depth: np.ndarray, k_colour: np.ndarray,
                   t_colour_from_depth: np.ndarray, shape: tuple[int, int],
                   rays: np.ndarray | None = None) -> np.ndarray:
    """A depth camera's map re-rendered in the colour camera: each valid depth pixel lands on
    its nearest colour pixel, the nearest surface wins; metres along the colour camera's
    axis, 0 where nothing lands (missing: its keypoints are ignored, not unmatched).
    ``rays``: ``pixel_rays(k_depth, depth.shape)``, when the caller keeps it."""
    ys, xs = np.nonzero(depth > 0)
    z = depth[ys, xs].astype(np.float64)
    if rays is None:
        rays = pixel_rays(k_depth, depth.shape)
    rays = rays[:, ys, xs]
    x_c = t_colour_from_depth[:3, :3] @ (rays * z) + t_colour_from_depth[:3, 3:4]
    front = x_c[2] > 1e-3
    x_c = x_c[:, front]
    uv = (k_colour @ x_c)[:2] / x_c[2]
    u, v = np.round(uv[0]).astype(np.int64), np.round(uv[1]).astype(np.int64)
    h, w = shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.full(h * w, np.inf)
    np.minimum.at(out, v[inside] * w + u[inside], x_c[2, inside])
    out[np.isinf(out)] = 0.0
    return out.reshape(h, w).astype(np.float32)


class Sequence:
    """Frames of one RGB-D sequence: colour paths, depth paths, K, camera-to-world poses."""

    def __init__(self, root: str, colour_camera: bool = True):
        """``colour_camera``: use the fitted colour camera of ``COLOUR_CAMERAS`` when the
        sequence has one (K, poses and depth then describe the colour frames)."""
        self.root = root
        self.name = os.path.basename(os.path.normpath(root))
        self.K = np.loadtxt(os.path.join(root, "K.txt")).reshape(3, 3)
        if os.path.isdir(os.path.join(root, "images")):  # hololens layout
            self.images = sorted(glob.glob(os.path.join(root, "images", "*.jpg")))
            self.depths = [os.path.join(root, "depth", os.path.basename(p)[:-4] + ".png") for p in self.images]
            poses = np.loadtxt(os.path.join(root, "poses.txt")).reshape(-1, 4, 4)
            self.invalid_depth = None
        else:  # 7-Scenes layout
            self.images = sorted(glob.glob(os.path.join(root, "frame-*.color.jpg")))
            self.depths = [p.replace(".color.jpg", ".depth.png") for p in self.images]
            poses = np.stack([np.loadtxt(p.replace(".color.jpg", ".pose.txt")) for p in self.images])
            self.invalid_depth = 65535
        if len(poses) != len(self.images) or not self.images:
            raise ValueError(f"{root}: {len(self.images)} images but {len(poses)} poses")
        self.poses = poses.astype(np.float64)
        self.k_depth, self.t_colour_from_depth = self.K, None
        # Decoded frames, kept because the generator revisits the same few hundred frames:
        # re-reading and re-registering a depth map cost ~40 ms, a grey frame ~9 ms.
        self._frames: dict[tuple[str, int], np.ndarray] = {}
        self._rays: np.ndarray | None = None
        cal = colour_cameras().get(self.name) if colour_camera else None
        if cal is not None:
            self.use_colour_camera(np.asarray(cal["K"], np.float64).reshape(3, 3),
                                   np.asarray(cal["T_colour_from_depth"], np.float64).reshape(4, 4))

    def use_colour_camera(self, k_colour: np.ndarray, t_colour_from_depth: np.ndarray) -> None:
        """Describe the colour frames from now on: their K, the colour camera's poses and the
        depth re-rendered into it (the shipped K and poses are the depth camera's)."""
        self.K, self.t_colour_from_depth = k_colour, t_colour_from_depth
        self._frames.clear()
        # camera-to-world of the colour camera: T_w_depth · T_depth_colour
        self.poses = self.poses @ np.linalg.inv(t_colour_from_depth)

    @property
    def key(self) -> str:
        """Name for caches: the fitted colour camera's values change it."""
        if self.t_colour_from_depth is None:
            return self.name
        vals = np.concatenate([self.K.ravel(), self.t_colour_from_depth.ravel()])
        return f"{self.name}_colour{hashlib.sha1(np.round(vals, 6).tobytes()).hexdigest()[:8]}"

    def __len__(self) -> int:
        return len(self.images)

    def gray(self, i: int) -> np.ndarray:
        """Frame i as XFeat sees a colour image: the mean of R, G and B, uint8 (read-only)."""
        return self._cached("gray", i, self._read_gray)

    def depth(self, i: int) -> np.ndarray:
        """Depth in metres, float32, 0 where missing (read-only)."""
        return self._cached("depth", i, self._read_depth)

    def _cached(self, kind: str, i: int, read) -> np.ndarray:
        key = (kind, i)
        out = self._frames.get(key)
        if out is None:
            out = read(i)
            out.setflags(write=False)
            if len(self._frames) < FRAME_CACHE:
                self._frames[key] = out
        return out

    def _read_gray(self, i: int) -> np.ndarray:
        img = cv2.imread(self.images[i], cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{self.images[i]}: unreadable image")
        # round((b + g + r) / 3) in integers: a third is never a tie, so this equals the
        # rounded float mean exactly.
        return ((img.astype(np.uint16).sum(2) + 1) // 3).astype(np.uint8)

    def _read_depth(self, i: int) -> np.ndarray:
        d = cv2.imread(self.depths[i], cv2.IMREAD_UNCHANGED)
        if d is None:
            raise ValueError(f"{self.depths[i]}: unreadable depth")
        d = d.astype(np.float32)
        if self.invalid_depth is not None:
            d[d == self.invalid_depth] = 0
        d = d / 1000.0
        if self.t_colour_from_depth is not None:
            if self._rays is None or self._rays.shape[1:] != d.shape:
                self._rays = pixel_rays(self.k_depth, d.shape)
            d = register_depth(d, self.k_depth, self.K, self.t_colour_from_depth, d.shape, self._rays)
        return d


def depth_at(depth: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Depth (float64) at the nearest pixel of each point, clamped into the frame."""
    h, w = depth.shape
    xi = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    return depth[yi, xi].astype(np.float64)


def project(pts: np.ndarray, depth_a: np.ndarray, depth_b: np.ndarray, K: np.ndarray,
            pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Keypoints ``pts`` of frame a mapped into frame b (codes in the module doc)."""
    h, w = depth_a.shape
    out = np.full((len(pts), 2), np.nan, np.float32)
    if len(pts) == 0:
        return out
    z = depth_at(depth_a, pts)
    ok = z > 0
    rays = np.linalg.solve(K, np.stack([pts[:, 0], pts[:, 1], np.ones(len(pts))]).astype(np.float64))
    x_a = rays * z
    rel = np.linalg.solve(pose_b, pose_a)  # camera a → camera b
    x_b = rel[:3, :3] @ x_a + rel[:3, 3:4]
    zb = x_b[2]
    front = zb > 1e-3
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (K @ x_b)[:2] / x_b[2]
    inside = (uv[0] >= -0.5) & (uv[0] <= w - 0.5) & (uv[1] >= -0.5) & (uv[1] <= h - 0.5)
    safe = np.nan_to_num(np.round(uv), nan=0.0, posinf=0.0, neginf=0.0)
    ub = np.clip(safe[0], 0, w - 1).astype(int)
    vb = np.clip(safe[1], 0, h - 1).astype(int)
    seen = depth_b[vb, ub].astype(np.float64)
    vis = ok & front & inside & (seen > 0) & (np.abs(zb - seen) <= DEPTH_TOLERANCE * seen)
    occl = ok & front & inside & (seen > 0) & (zb > seen * (1 + DEPTH_TOLERANCE))
    outside = ok & front & ~inside
    out[vis | outside] = uv.T[vis | outside]
    out[occl] = OCCLUDED
    return out


def covisibility(K: np.ndarray, poses: np.ndarray, depths: dict, a: int, b: int, step: int = 16) -> float:
    """Fraction of frame a's grid pixels with depth that are visible in frame b."""
    da = depths[a]
    ys, xs = np.mgrid[step // 2 : da.shape[0] : step, step // 2 : da.shape[1] : step]
    pts = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    pts = pts[da[ys.ravel(), xs.ravel()] > 0]
    if len(pts) == 0:
        return 0.0
    proj = project(pts, da, depths[b], K, poses[a], poses[b])
    ok = np.isfinite(proj[:, 0]) & (proj[:, 0] < OCCLUDED)
    h, w = da.shape
    vis = ok & (proj[:, 0] >= 0) & (proj[:, 0] < w) & (proj[:, 1] >= 0) & (proj[:, 1] < h)
    return float(vis.mean())


def pair_list(seq: Sequence, frames: range, cache: str, max_gap: int = 40,
              overlap: tuple[float, float] = (0.2, 0.85)) -> list[tuple[int, int, float]]:
    """Frame pairs ``(a, b, covisibility)`` within ``frames`` whose mutual covisibility lies in
    ``overlap`` (cached as JSON: covisibility needs every depth map once)."""
    key = f"{seq.key}_{frames.start}_{frames.stop}_{max_gap}_{overlap[0]}_{overlap[1]}.json"
    path = os.path.join(cache, key)
    if os.path.exists(path):
        return [tuple(p) for p in json.load(open(path))]
    depths = {i: seq.depth(i)[::2, ::2] for i in frames}
    half = seq.K.copy()  # intrinsics of the depth maps at half resolution
    half[:2] /= 2
    pairs = []
    idx = list(frames)
    for ia, a in enumerate(idx):
        for b in idx[ia + 1 : ia + 1 + max_gap]:
            c = min(covisibility(half, seq.poses, depths, a, b, 8), covisibility(half, seq.poses, depths, b, a, 8))
            if overlap[0] <= c <= overlap[1]:
                pairs.append((a, b, round(c, 3)))
    os.makedirs(cache, exist_ok=True)
    json.dump(pairs, open(path + ".tmp", "w"))
    os.replace(path + ".tmp", path)
    return pairs


HOLDOUT_FRACTION = 0.15  # the last 15% of each RGB-D sequence is held out for validation


def split_pairs(roots: list[str], split: str, cache: str) -> list[tuple[Sequence, list]]:
    """Each sequence with its covisible pairs in ``split``: "train" (frames before the
    held-out tail, less a 10-frame gap) or "holdout" (the last ``HOLDOUT_FRACTION``)."""
    if split not in ("train", "holdout"):
        raise ValueError(f"split: expected 'train' or 'holdout', got {split!r}")
    out = []
    for root in roots:
        seq = Sequence(root)
        cut = int(len(seq) * (1 - HOLDOUT_FRACTION))
        frames = range(0, cut - 10) if split == "train" else range(cut, len(seq))
        out.append((seq, pair_list(seq, frames, cache)))
    return out
