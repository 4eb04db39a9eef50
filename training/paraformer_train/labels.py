"""Ground-truth matches from per-keypoint projections, for any subset of keypoints.

The evaluation rule (``paraformer.geometry.gt_matches_from_homography``) generalised to
projections that may be unknown: ``d(i, j) = max(‖P0_i − p1_j‖, ‖p0_i − P1_j‖)`` over the
terms that are known (P = the keypoint projected into the other image, NaN = unknown);
a pair is positive when mutual nearest under d with d < threshold; a keypoint is unmatched
when its nearest d is at least the threshold and its own projection is known; otherwise it
is ignored. With every projection known (homographies) this is exactly the evaluation rule.

``unmatched_from`` (per pair) widens the gap between the two: a keypoint is unmatched only
when its nearest d reaches it, and ignored in between. Real pairs use it, because their
projections carry pose and depth noise of a few pixels: without the band, true
correspondences that land 3-5 px off would be taught as unmatched.
"""
from __future__ import annotations

import torch

UNMATCHED, IGNORED = -1, -2


def ground_truth(kpts0, kpts1, proj0, proj1, threshold: float = 3.0, unmatched_from=None):
    """``kpts0`` ``[B, M, 2]``, ``kpts1`` ``[B, N, 2]``, ``proj0`` (keypoints 0 in image 1)
    ``[B, M, 2]``, ``proj1`` ``[B, N, 2]``, ``threshold`` a float or ``[B]`` (per pair),
    ``unmatched_from`` ``None`` (= threshold), a float or ``[B]`` → ``(matches0 [B, M],
    matches1 [B, N])`` int64."""
    b, m, _ = kpts0.shape
    far = torch.as_tensor(threshold if unmatched_from is None else unmatched_from, dtype=kpts0.dtype)
    far = torch.maximum(far, torch.as_tensor(threshold, dtype=kpts0.dtype)).reshape(-1, 1)
    threshold = torch.as_tensor(threshold, dtype=kpts0.dtype).reshape(-1, 1).to(kpts0.device)
    n = kpts1.shape[1]
    known0 = torch.isfinite(proj0).all(-1)
    known1 = torch.isfinite(proj1).all(-1)
    dev = kpts0.device
    far = far.to(dev)
    inf = torch.tensor(float("inf"), dtype=kpts0.dtype, device=dev)
    fwd = torch.cdist(torch.nan_to_num(proj0, nan=0.0), kpts1)
    bwd = torch.cdist(kpts0, torch.nan_to_num(proj1, nan=0.0))
    fwd = torch.where(known0[:, :, None], fwd, inf)
    bwd = torch.where(known1[:, None, :], bwd, inf)
    both = known0[:, :, None] & known1[:, None, :]
    d = torch.where(both, torch.maximum(fwd, bwd), torch.minimum(fwd, bwd))
    if m == 0 or n == 0:
        return (torch.full((b, m), UNMATCHED, dtype=torch.long, device=dev),
                torch.full((b, n), UNMATCHED, dtype=torch.long, device=dev))
    d0, j0 = d.min(2)
    d1, i1 = d.min(1)
    ar0 = torch.arange(m, device=dev)[None].expand(b, m)
    mutual0 = i1.gather(1, j0) == ar0
    pos0 = mutual0 & (d0 < threshold)
    m0 = torch.full((b, m), IGNORED, dtype=torch.long, device=dev)
    m0 = torch.where(pos0, j0, m0)
    m0 = torch.where((d0 >= far) & known0, torch.full_like(m0, UNMATCHED), m0)
    m1 = torch.full((b, n), IGNORED, dtype=torch.long, device=dev)
    ar1 = torch.arange(n, device=dev)[None].expand(b, n)
    pos1 = (j0.gather(1, i1) == ar1) & (d1 < threshold)
    m1 = torch.where(pos1, i1, m1)
    m1 = torch.where((d1 >= far) & known1, torch.full_like(m1, UNMATCHED), m1)
    return m0, m1
