"""Geometry and metrics from Python, cross-checked against OpenCV (estimators) and
independent numpy implementations (metrics, ground truth, baselines).

Accuracy criterion against OpenCV on the same clean-with-outliers correspondences:
our error ≤ max(1.5 × OpenCV's, OpenCV's + 0.5) (pixels of corner error for
homographies, degrees of pose error for relative pose), averaged over several seeds.
"""
import numpy as np
import pytest

from paraformer import geometry as g


def homography_scene(seed, n=300, outlier_ratio=0.4, noise=1.0):
    rng = np.random.default_rng(seed)
    H = np.array([[0.9, 0.12, 25.0], [-0.06, 1.05, -15.0], [2e-4, -1.5e-4, 1.0]])
    x0 = rng.uniform([0, 0], [640, 480], (n, 2))
    p = np.c_[x0, np.ones(n)] @ H.T
    x1 = p[:, :2] / p[:, 2:] + rng.normal(0, noise / 2, (n, 2))
    out = rng.random(n) < outlier_ratio
    x1[out] = rng.uniform([0, 0], [640, 480], (out.sum(), 2))
    return x0, x1, H


def pose_scene(seed, n=300, outlier_ratio=0.3, noise=0.5):
    rng = np.random.default_rng(seed)
    K = np.array([[520.0, 0, 320], [0, 520.0, 240], [0, 0, 1]])
    a = rng.normal(0, 0.15, 3)
    theta = np.linalg.norm(a)
    k = a / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx  # Rodrigues
    t = rng.normal(0, 1, 3)
    t /= np.linalg.norm(t)
    X = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(5, 12, n)]
    Xc = X @ R.T + t
    keep = Xc[:, 2] > 0.5
    X, Xc = X[keep], Xc[keep]
    x0 = (X / X[:, 2:]) @ K.T
    x1 = (Xc / Xc[:, 2:]) @ K.T
    x0, x1 = x0[:, :2], x1[:, :2] + rng.normal(0, noise, (len(X), 2))
    out = rng.random(len(x1)) < outlier_ratio
    x1[out] = rng.uniform([0, 0], [640, 480], (out.sum(), 2))
    return x0, x1, K, R, t


def rotation_error(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def translation_error(ta, tb):
    a = np.degrees(np.arccos(np.clip(ta @ tb / np.linalg.norm(ta) / np.linalg.norm(tb), -1, 1)))
    return min(a, 180 - a)


def test_homography_as_accurate_as_opencv():
    cv2 = pytest.importorskip("cv2", reason="opencv-python-headless not installed")
    ours, theirs = [], []
    for seed in range(8):
        x0, x1, H = homography_scene(seed)
        r = g.find_homography(x0, x1, threshold=3.0, seed=seed)
        assert r["model"] is not None and r["reason"] is None
        Hc, _ = cv2.findHomography(x0, x1, cv2.RANSAC, 3.0, maxIters=10000, confidence=0.999)
        ours.append(g.homography_corner_error(r["model"], H, 640, 480))
        theirs.append(g.homography_corner_error(Hc, H, 640, 480))
    o, t = np.mean(ours), np.mean(theirs)
    print(f"mean corner error: ours {o:.3f} px, OpenCV {t:.3f} px")
    assert o <= max(1.5 * t, t + 0.5), (ours, theirs)


def test_relative_pose_as_accurate_as_opencv():
    cv2 = pytest.importorskip("cv2", reason="opencv-python-headless not installed")
    ours, theirs = [], []
    for seed in range(8):
        x0, x1, K, R, t = pose_scene(seed)
        r = g.find_relative_pose(x0, x1, K, K, threshold=1.0, seed=seed)
        assert r["R"] is not None
        ours.append(max(rotation_error(r["R"], R), translation_error(r["t"], t)))
        E, mask = cv2.findEssentialMat(x0, x1, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
        _, Rc, tc, _ = cv2.recoverPose(E[:3], x0, x1, K, mask=mask)
        theirs.append(max(rotation_error(Rc, R), translation_error(tc.ravel(), t)))
    o, t_ = np.mean(ours), np.mean(theirs)
    print(f"mean pose error: ours {o:.3f}°, OpenCV {t_:.3f}°")
    assert o <= max(1.5 * t_, t_ + 0.5), (ours, theirs)


def test_fundamental_inliers():
    x0, x1, K, R, t = pose_scene(3, outlier_ratio=0.3)
    r = g.find_fundamental(x0, x1, threshold=1.0)
    F = r["model"]
    inl = r["inliers"]
    h0, h1 = np.c_[x0, np.ones(len(x0))], np.c_[x1, np.ones(len(x1))]
    algebraic = np.abs(np.einsum("ij,jk,ik->i", h1[inl], F, h0[inl]))
    assert inl.mean() > 0.6 and np.median(algebraic) < 1e-2


def test_degenerate_input_gives_no_model():
    r = g.find_homography(np.zeros((3, 2)), np.zeros((3, 2)))
    assert r["model"] is None and "at least 4" in r["reason"] and not r["inliers"].any()
    line = np.c_[np.arange(20.0), 2 * np.arange(20.0)]
    assert g.find_homography(line, line)["model"] is None
    K = np.eye(3)
    assert g.find_relative_pose(line[:7], line[:7], K, K)["reason"].startswith("need at least 8")
    with pytest.raises(ValueError, match="points1"):
        g.find_homography(np.zeros((5, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        g.find_homography(np.full((5, 2), np.nan), np.zeros((5, 2)))


def superglue_pose_auc(errors, thresholds):
    # Independent numpy version of SuperGlue's pose_auc.
    idx = np.argsort(errors)
    errors = np.r_[0.0, np.array(errors)[idx]]
    recall = np.r_[0.0, (np.arange(len(idx)) + 1) / len(idx)]
    aucs = []
    for t in thresholds:
        last = np.searchsorted(errors, t)
        r = np.r_[recall[:last], recall[last - 1]]
        e = np.r_[errors[:last], t]
        aucs.append(np.trapezoid(r, x=e) / t)
    return aucs


def test_pose_auc_matches_superglue_formula():
    rng = np.random.default_rng(0)
    errors = np.r_[rng.exponential(8, 50), [np.inf] * 5]
    np.testing.assert_allclose(g.pose_auc(errors, [5, 10, 20]), superglue_pose_auc(errors, [5, 10, 20]), atol=1e-12)
    approx = g.pose_auc_approx(errors, [5, 10, 20])
    want = [np.mean([np.mean(errors < k) for k in range(1, t + 1)]) for t in (5, 10, 20)]
    np.testing.assert_allclose(approx, want, atol=1e-12)


def test_ground_truth_and_baselines_match_brute_force():
    rng = np.random.default_rng(1)
    x0, _, H = homography_scene(1, n=120, outlier_ratio=0.0, noise=0.0)
    p = np.c_[x0, np.ones(len(x0))] @ H.T
    x1 = np.r_[p[:80, :2] / p[:80, 2:] + rng.normal(0, 1.2, (80, 2)), rng.uniform([0, 0], [640, 480], (50, 2))]
    m0, m1 = g.gt_matches_from_homography(H, x0, x1, 3.0)
    fw = np.c_[x0, np.ones(len(x0))] @ H.T
    fw = fw[:, :2] / fw[:, 2:]
    bw = np.c_[x1, np.ones(len(x1))] @ np.linalg.inv(H).T
    bw = bw[:, :2] / bw[:, 2:]
    d = np.maximum(np.linalg.norm(fw[:, None] - x1[None], axis=2), np.linalg.norm(x0[:, None] - bw[None], axis=2))
    nn0, nn1 = d.argmin(1), d.argmin(0)
    want0 = np.where((nn1[nn0] == np.arange(len(x0))) & (d.min(1) < 3), nn0, -2)
    want0[d.min(1) >= 3] = -1
    np.testing.assert_array_equal(m0, want0)
    assert (m0 >= 0).sum() > 50 and ((m1 >= 0).sum() == (m0 >= 0).sum())

    d0, d1 = rng.normal(size=(60, 8)).astype(np.float32), rng.normal(size=(70, 8)).astype(np.float32)
    d1[:40] = d0[:40] + 0.05 * rng.normal(size=(40, 8))
    dist = np.linalg.norm(d0[:, None] - d1[None], axis=2)
    nn = dist.argmin(1)
    np.testing.assert_array_equal(g.match_baseline(d0, d1, "nn"), nn)
    mutual = dist.argmin(0)[nn] == np.arange(60)
    np.testing.assert_array_equal(g.match_baseline(d0, d1, "mnn"), np.where(mutual, nn, -1))
    s = np.sort(dist, 1)
    np.testing.assert_array_equal(g.match_baseline(d0, d1, "ratio", 0.8), np.where(s[:, 0] < 0.8 * s[:, 1], nn, -1))
    # A ratio outside (0, 1] (negative, NaN, above 1) would keep nothing or everything: refused by name.
    from paraformer.pipeline import Baseline
    for bad in (-1.0, 0.0, float("nan"), 1.5):
        with pytest.raises(ValueError, match=r"^ratio: .*\(0, 1\]"):
            g.match_baseline(d0, d1, "ratio", bad)
        with pytest.raises(ValueError, match=r"ratio.*\(0, 1\]"):
            Baseline(f"ratio:{bad}")
    # An unknown method is named, with the core's list of names.
    from paraformer.pipeline import BASELINES
    assert BASELINES == ("mnn", "nn", "ratio")
    with pytest.raises(ValueError, match=r"^method: \"lowe\": expected one of mnn, nn, ratio"):
        g.match_baseline(d0, d1, "lowe")
    pr = g.precision_recall(g.match_baseline(d0, d1, "mnn"), np.r_[np.arange(40), [-1] * 20])
    assert pr["recall"] == 1.0 and 0 < pr["precision"] <= 1.0
    acc = g.mma(np.eye(3), x0[:5], x0[:5] + [0.0, 2.5], np.arange(5), 3)
    np.testing.assert_array_equal(acc, [0.0, 0.0, 1.0])


def test_features_file_round_trip(tmp_path):
    import paraformer
    rng = np.random.default_rng(0)
    feats = {"a.png": {"keypoints": rng.uniform(0, 100, (7, 2)), "descriptors": rng.normal(size=(7, 4)),
                       "image_size": (100, 80)},
             "dir/b.jpg": {"keypoints": np.zeros((0, 2)), "descriptors": np.zeros((0, 4)), "image_size": (5, 5),
                           "scores": np.zeros(0)}}
    p = tmp_path / "f.safetensors"
    paraformer.features.write(str(p), feats)
    back = paraformer.features.read(str(p))
    assert set(back) == {"a.png", "dir/b.jpg"}
    np.testing.assert_allclose(back["a.png"]["keypoints"], feats["a.png"]["keypoints"], rtol=1e-6)
    np.testing.assert_array_equal(back["a.png"]["scores"], np.ones(7, np.float32))
    assert back["dir/b.jpg"]["descriptors"].shape == (0, 4)
    with pytest.raises(ValueError, match="descriptors"):
        paraformer.features.write(str(p), {"x": {"keypoints": np.zeros((3, 2)), "descriptors": np.zeros((2, 4)),
                                                "image_size": (1, 1)}})
    # A [K, 3] array was reshaped into 3K/2 points, a missing field was a bare KeyError, NaN was
    # written, and a file of another format failed with a struct error: each is named now.
    good = {"keypoints": np.zeros((4, 2)), "descriptors": np.zeros((4, 4)), "image_size": (1, 1)}
    for bad, pattern in (({**good, "keypoints": np.zeros((4, 3))}, r"^x: keypoints must be \[K, 2\], got \[4, 3\]"),
                         ({k: v for k, v in good.items() if k != "image_size"}, r"^x: missing image_size"),
                         ({**good, "descriptors": np.full((4, 4), np.nan)}, r"^x: descriptors contains NaN")):
        with pytest.raises(ValueError, match=pattern):
            paraformer.features.write(str(tmp_path / "bad.safetensors"), {"x": bad})
    (tmp_path / "junk.safetensors").write_bytes(b"junk")
    (tmp_path / "short.safetensors").write_bytes(p.read_bytes()[:-10])
    for junk in ("junk.safetensors", "short.safetensors"):
        with pytest.raises(ValueError, match=rf"{junk}: not a features file"):
            paraformer.features.read(str(tmp_path / junk))
    h5py = pytest.importorskip("h5py", reason="h5py not installed: hloc .h5 round trip skipped")
    paraformer.features.write_h5(str(tmp_path / "f.h5"), feats)
    h5 = paraformer.features.read_h5(str(tmp_path / "f.h5"))
    np.testing.assert_allclose(h5["a.png"]["descriptors"], feats["a.png"]["descriptors"], rtol=1e-6)


def test_parameters_that_cannot_work_are_named():
    """A threshold of 0 used to read as "no hypothesis reached 4 inliers", max_iterations=0 as
    "degenerate", a confidence of 1.5 or NaN was used as given, a negative int was an unnamed
    OverflowError; AUC thresholds ≤ 0 and a corner error of a 0×0 image gave numbers."""
    from paraformer import geometry as g

    rng = np.random.default_rng(1)
    p = rng.uniform(0, 500, (40, 2))
    q = p + [5.0, -3.0]
    K = np.array([[500.0, 0, 250], [0, 500, 250], [0, 0, 1]])
    fits = [lambda **kw: g.find_homography(p, q, **kw), lambda **kw: g.find_fundamental(p, q, **kw),
            lambda **kw: g.find_relative_pose(p, q, K, K, **kw)]
    bad = [("threshold", 0.0), ("threshold", -1.0), ("threshold", float("nan")), ("confidence", 0.0),
           ("confidence", 1.5), ("confidence", float("nan")), ("max_iterations", 0), ("max_iterations", -5),
           ("seed", -1)]
    for fit in fits:
        for name, value in bad:
            with pytest.raises(ValueError, match=rf"^{name}: "):
                fit(**{name: value})
    assert g.find_homography(p, q)["model"] is not None
    for thresholds in ([5, 0], [-5, 10], [float("nan")]):
        with pytest.raises(ValueError, match=r"^thresholds: "):
            g.pose_auc([1.0, 2.0], thresholds)
    with pytest.raises(ValueError, match=r"^thresholds: "):
        g.pose_auc_approx([1.0, 2.0], [0, 5])
    for w, h, name in ((0, 480, "width"), (640, -1, "height"), (640, float("inf"), "height")):
        with pytest.raises(ValueError, match=rf"^{name}: "):
            g.homography_corner_error(np.eye(3), np.eye(3), w, h)


def test_complex_input_is_named_not_truncated():
    """A complex array would lose its imaginary part in a float cast: each entry point names it instead."""
    import paraformer
    from paraformer import geometry as g

    pts = np.random.default_rng(0).uniform(0, 100, (8, 2))
    cases = [(lambda: g.find_homography(pts.astype(np.complex128), pts), "points0"),
             (lambda: g.find_relative_pose(pts, pts, np.eye(3) * (1 + 1j), np.eye(3)), "K0"),
             (lambda: g.homography_corner_error(np.eye(3), np.eye(3, dtype=np.complex64), 640, 480), "H_gt"),
             (lambda: g.match_baseline(np.ones((4, 8), np.complex64), np.ones((4, 8), np.float32)), "desc0"),
             (lambda: g.mma(np.eye(3) + 0j, pts, pts, np.arange(8)), "H"),
             (lambda: g.mma(np.eye(3), pts, pts, np.arange(8) + 0j), "matches0"),
             (lambda: g.precision_recall(np.arange(8), np.arange(8) * (1 + 0j)), "gt_matches0")]
    for call, name in cases:
        with pytest.raises(ValueError, match=rf"^{name}: expected a real .*complex"):
            call()
    k = np.zeros((2, 2), np.float32)
    d = np.zeros((2, 64), np.float32)
    with pytest.raises(ValueError, match=r"^size0: "):
        paraformer.Matcher.pretrained("paraformer-xfeat").match(k, d, k, d, size0=(640 + 1j, 480), size1=(640, 480))
