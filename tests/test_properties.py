"""Property tests: whatever array a caller passes (shapes, dtypes, strides, read-only,
zero-stride, extreme values), the Python API either returns a valid output or raises a
ValueError / TypeError naming the argument; never a crash. Needs hypothesis (test extra)."""
from __future__ import annotations

import numpy as np
import pytest

import paraformer

hyp = pytest.importorskip("hypothesis", reason="property tests need hypothesis (pip install '.[test]')")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SETTINGS = settings(max_examples=int(__import__("os").environ.get("PARAFORMER_HYPOTHESIS_EXAMPLES", "60")), deadline=None, suppress_health_check=[HealthCheck.too_slow])
DTYPES = [np.float32, np.float64, np.float16, np.int8, np.int32, np.int64, np.uint8, np.bool_,
          np.complex64, object]
VALUES = st.sampled_from([0.0, 1.0, -1.0, 0.5, 1e30, -1e30, np.nan, np.inf, 1e-30, 300.0])
MATCHER = paraformer.Matcher.pretrained("paraformer-xfeat")


@st.composite
def arrays(draw, good_shape=None):
    """A valid-looking array of ``good_shape`` most of the time, otherwise anything."""
    kind = draw(st.sampled_from(["good", "good", "good", "dtype", "shape", "values", "strided", "zero_stride",
                                 "readonly", "list", "scalar", "none"]))
    shape = good_shape if good_shape is not None else (draw(st.integers(0, 6)), 2)
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    base = rng.uniform(0, 100, shape).astype(np.float32)
    if kind == "dtype":
        dt = draw(st.sampled_from(DTYPES))
        return base.astype(dt) if dt is not object else base.astype(object)
    if kind == "shape":
        nd = draw(st.integers(0, 3))
        return rng.uniform(0, 100, tuple(draw(st.integers(0, 5)) for _ in range(nd))).astype(np.float32)
    if kind == "values":
        out = base.copy()
        if out.size:
            out.flat[draw(st.integers(0, out.size - 1))] = draw(VALUES)
        return out
    if kind == "strided":
        big = np.repeat(base, 2, axis=0) if base.ndim else base
        return big[::2]
    if kind == "zero_stride":
        return np.broadcast_to(base[:1] if len(base) else base, base.shape)
    if kind == "readonly":
        base.setflags(write=False)
        return base
    if kind == "list":
        return base.tolist()
    if kind == "scalar":
        return draw(VALUES)
    if kind == "none":
        return None
    return base


def names_argument(e: Exception, names: tuple[str, ...]) -> bool:
    return any(n in str(e) for n in names)


def check_match_output(out: dict, m: int, n: int) -> None:
    m0, m1 = out["matches0"], out["matches1"]
    assert m0.shape == (m,) and m1.shape == (n,)
    assert ((m0 >= -1) & (m0 < max(n, 1))).all() and ((m1 >= -1) & (m1 < max(m, 1))).all()
    for i, j in enumerate(m0):
        if j >= 0:
            assert m1[j] == i
    assert np.isfinite(out["matching_scores0"]).all() and np.isfinite(out["matching_scores1"]).all()


@SETTINGS
@given(st.integers(0, 6), st.integers(0, 6), st.data())
def test_match_never_crashes(m, n, data):
    args = {"kpts0": data.draw(arrays((m, 2))), "desc0": data.draw(arrays((m, 64))),
            "kpts1": data.draw(arrays((n, 2))), "desc1": data.draw(arrays((n, 64)))}
    size0 = data.draw(st.sampled_from([(640, 480), (0, 480), (np.nan, 1), "640x480", (640,), (1e30, 1e30)]))
    try:
        out = MATCHER.match(args["kpts0"], args["desc0"], args["kpts1"], args["desc1"], size0=size0, size1=(640, 480))
    except (ValueError, TypeError) as e:
        assert names_argument(e, ("kpts0", "desc0", "kpts1", "desc1", "size0", "scores")), repr(e)
        return
    check_match_output(out, len(np.asarray(args["kpts0"])), len(np.asarray(args["kpts1"])))


@SETTINGS
@given(st.data())
def test_match_dicts_and_match_many_never_crash(data):
    def feats(k):
        d = {"keypoints": data.draw(arrays((k, 2))), "descriptors": data.draw(arrays((k, 64))),
             "image_size": data.draw(st.sampled_from([(640, 480), [[640, 480]], (-1, 2), None]))}
        if data.draw(st.booleans()):
            d["scores"] = data.draw(arrays((k,)))
        drop = data.draw(st.sampled_from([None, None, "keypoints", "descriptors", "image_size"]))
        if drop:
            d.pop(drop)
        return d if data.draw(st.integers(0, 9)) else data.draw(st.sampled_from([None, 3, "feats", [1, 2]]))

    f0, f1 = feats(data.draw(st.integers(0, 5))), feats(data.draw(st.integers(0, 5)))
    try:
        out = MATCHER.match_dicts(f0, f1)
        check_match_output(out, len(out["matches0"]), len(out["matches1"]))
    except (ValueError, TypeError) as e:
        assert names_argument(e, ("feats0", "feats1", "kpts", "desc", "size", "scores")), repr(e)
    pairs = data.draw(st.sampled_from([[(f0, f1)], [(f0, f1), (f1, f0)], [], [f0], "pairs", [(f0, f1, f0)]]))
    try:
        outs = MATCHER.match_many(pairs, num_threads=data.draw(st.sampled_from([None, 1, 2])))
        assert len(outs) == len(pairs)
    except (ValueError, TypeError) as e:
        assert names_argument(e, ("pairs", "feats", "kpts", "desc", "size", "scores")), repr(e)


@SETTINGS
@given(st.data())
def test_extract_never_crashes(data):
    h, w = data.draw(st.integers(0, 70)), data.draw(st.integers(0, 70))
    img = data.draw(arrays((h, w) if data.draw(st.booleans()) else (h, w, data.draw(st.integers(1, 5)))))
    try:
        out = paraformer.extract(img, max_keypoints=data.draw(st.sampled_from([1, 64, 2048])))
    except (ValueError, TypeError) as e:
        assert names_argument(e, ("image", "max_keypoints")), repr(e)
        return
    k = len(out["keypoints"])
    assert out["descriptors"].shape == (k, 64) and out["scores"].shape == (k,)
    assert np.isfinite(out["keypoints"]).all() and np.isfinite(out["descriptors"]).all()


@SETTINGS
@given(st.data())
def test_geometry_never_crashes(data):
    k = data.draw(st.integers(0, 12))
    p0, p1 = data.draw(arrays((k, 2))), data.draw(arrays((k, 2)))
    g = paraformer.geometry
    for fn in (g.find_homography, g.find_fundamental):
        try:
            fit = fn(p0, p1)
        except (ValueError, TypeError) as e:
            assert names_argument(e, ("points0", "points1")), repr(e)
            continue
        assert fit["inliers"].shape == (len(np.asarray(p0)),)
        assert fit["model"] is None or np.isfinite(fit["model"]).all()
    try:
        g.homography_corner_error(data.draw(arrays((3, 3))), np.eye(3), 640, 480)
    except (ValueError, TypeError) as e:
        assert names_argument(e, ("H_est", "H_gt")), repr(e)
