"""The Python module: parity on every fixture, every bad-input class, thread safety,
memory, match_many, flops, the exception hierarchy and the type stubs.

Parity tolerance: identical matches; log_assignment and matching scores within 1e-4 absolute.
"""
import gc
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import paraformer
from conftest import DATA, index, load_case

TOL = 1e-4


def args(c):
    return (c["keypoints0"], c["descriptors0"], c["keypoints1"], c["descriptors1"])


def kw(c, **extra):
    return dict(size0=c["image_size0"], size1=c["image_size1"], scores0=c["scores0"], scores1=c["scores1"], **extra)


def feats(c, i):
    return {"keypoints": c[f"keypoints{i}"], "descriptors": c[f"descriptors{i}"],
            "image_size": c[f"image_size{i}"], "scores": c[f"scores{i}"]}


_matchers = {}


def matcher_for(path: Path) -> paraformer.Matcher:
    if path not in _matchers:
        _matchers[path] = paraformer.Matcher.from_file(path)
    return _matchers[path]


@pytest.mark.parametrize("folder,entry", index("spec_vectors") + index("golden"),
                         ids=lambda v: v["case"] if isinstance(v, dict) else None)
def test_fixture_parity(folder, entry):
    m = matcher_for(folder / entry["weights"])
    c = load_case(folder / entry["case"])
    out = m.match(*args(c), **kw(c, return_log_assignment=True))
    assert out["matches0"].dtype == np.int64 and out["matches0"].shape == (entry["M"],)
    assert out["matches1"].dtype == np.int64 and out["matches1"].shape == (entry["N"],)
    assert out["matching_scores0"].dtype == np.float32
    assert out["log_assignment"].shape == (entry["M"] + 1, entry["N"] + 1)
    np.testing.assert_array_equal(out["matches0"], c["matches0"])
    np.testing.assert_array_equal(out["matches1"], c["matches1"])
    assert np.abs(out["log_assignment"] - c["log_assignment"]).max() <= TOL
    assert np.abs(out["matching_scores0"] - c["matching_scores0"]).max() <= TOL
    assert np.abs(out["matching_scores1"] - c["matching_scores1"]).max() <= TOL


def test_config_and_constructors(golden_weights):
    m = paraformer.Matcher.from_file(golden_weights)
    cfg = m.config
    assert cfg["model"] == "paraformer" and cfg["descriptor_dim"] == 16 and cfg["num_layers"] == 3
    assert set(cfg) >= {"dim", "num_heads", "positional_encoding", "parallel", "sinkhorn_iterations", "match_threshold"}
    cfg["dim"] = 999  # a copy: the matcher is unchanged
    assert m.config["dim"] == 16
    data = golden_weights.read_bytes()
    explicit = dict(m.config, match_threshold=0.9)
    for w in (str(golden_weights), golden_weights, data):
        assert paraformer.Matcher(explicit, w).config["match_threshold"] == pytest.approx(0.9)
    assert paraformer.Matcher.from_bytes(data).config == m.config


def test_float64_and_fortran_order_give_the_same_result(golden_weights, golden_case):
    m = paraformer.Matcher.from_file(golden_weights)
    c = golden_case
    ref = m.match(*args(c), **kw(c))
    f64 = [np.asfortranarray(a.astype(np.float64)) for a in args(c)]
    out = m.match(*f64, size0=(640, 480), size1=[512.0, 384.0],
                  scores0=c["scores0"].astype(np.float64), scores1=list(c["scores1"]))
    for k in ref:
        np.testing.assert_allclose(out[k], ref[k], atol=1e-6)


def test_match_dicts_accepts_lightglue_style_batched_dicts(golden_weights, golden_case):
    m = paraformer.Matcher.from_file(golden_weights)
    c = golden_case
    ref = m.match(*args(c), **kw(c))
    f0 = {k: np.asarray(v)[None] for k, v in feats(c, 0).items()}
    f1 = dict(feats(c, 1))
    f1["keypoint_scores"] = f1.pop("scores")
    out = m.match_dicts(f0, f1)
    for k in ref:
        np.testing.assert_array_equal(out[k], ref[k])


def test_match_many_equals_a_loop(golden_weights):
    m = paraformer.Matcher.from_file(golden_weights)
    cases = [load_case(DATA / "golden" / f"paraformer.case{k}.safetensors") for k in range(3)] * 3
    pairs = [(feats(c, 0), feats(c, 1)) for c in cases]
    many = m.match_many(pairs, return_log_assignment=True)
    assert len(many) == len(pairs)
    for (f0, f1), got in zip(pairs, many):
        want = m.match_dicts(f0, f1, return_log_assignment=True)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])
    assert m.match_many([]) == []
    one_thread = m.match_many(pairs, num_threads=1)
    for a, b in zip(one_thread, many):
        np.testing.assert_array_equal(a["matches0"], b["matches0"])


# ---- bad inputs: ValueError naming the argument and the expected shape -----------

def bad(m, c, expect, **changes):
    a = dict(zip(("kpts0", "desc0", "kpts1", "desc1"), args(c)))
    k = kw(c)
    for key, v in changes.items():
        (a if key in a else k)[key] = v
    with pytest.raises(ValueError) as e:
        m.match(a["kpts0"], a["desc0"], a["kpts1"], a["desc1"], **k)
    for needle in expect:
        assert needle in str(e.value), str(e.value)


def test_wrong_shapes(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    M = len(c["keypoints0"])
    bad(m, c, ["kpts0", "[K, 2]"], kpts0=c["keypoints0"][:, :1])
    bad(m, c, ["kpts1", "[K, 2]"], kpts1=c["keypoints1"].reshape(-1))
    bad(m, c, ["desc0", f"[{M}, 16]"], desc0=c["descriptors0"][:, :8])  # descriptor width
    bad(m, c, ["desc0", f"[{M}, 16]"], desc0=c["descriptors0"][:-1])    # rows
    bad(m, c, ["scores0", f"[{M}]"], scores0=c["scores0"][:-2])
    bad(m, c, ["size1", "(width, height)"], size1=(640,))
    bad(m, c, ["size0", "positive"], size0=(0, 480))


def test_nan_and_inf(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    k = c["keypoints0"].copy(); k[4, 0] = np.nan
    bad(m, c, ["kpts0", "NaN or Inf", "(4, 0)"], kpts0=k)
    d = c["descriptors1"].copy(); d[2, 3] = np.inf
    bad(m, c, ["desc1", "NaN or Inf"], desc1=d)
    s = c["scores1"].copy(); s[0] = -np.inf
    bad(m, c, ["scores1", "NaN or Inf"], scores1=s)
    bad(m, c, ["size0"], size0=(np.nan, 480))


def test_keypoints_far_outside_the_image(golden_weights, golden_case):
    """A swapped (height, width), another image's size or normalised keypoints used to give
    matches silently: keypoints beyond the margin are named with their row."""
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    k = np.clip(c["keypoints0"], 0, 470); k[1] = [630.0, 20.0]
    bad(m, c, ["kpts0", "row 1", "lies outside the", "(width, height)"], kpts0=k, size0=(480, 640))
    k = c["keypoints1"].copy(); k[0] = [-1e30, 5.0]
    bad(m, c, ["kpts1", "row 0", "lies outside the"], kpts1=k)
    f0 = {"keypoints": c["keypoints0"], "descriptors": c["descriptors0"], "image_size": (64, 48)}
    f1 = {"keypoints": c["keypoints1"], "descriptors": c["descriptors1"], "image_size": c["image_size1"]}
    with pytest.raises(ValueError, match="kpts0: row .* lies outside the"):
        m.match_dicts(f0, f1)


def test_wrong_dtype_and_non_numeric(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    bad(m, c, ["kpts0", "float16, float32 or float64 (or integer)", "bool"], kpts0=c["keypoints0"] > 0)
    bad(m, c, ["kpts0", "complex64"], kpts0=c["keypoints0"].astype(np.complex64))
    # Integer descriptors are binary ones (ORB, BRIEF): named, not widened.
    bad(m, c, ["desc1", "float16, float32 or float64 array", "uint8"], desc1=c["descriptors1"].astype(np.uint8))
    bad(m, c, ["kpts1", "float16, float32 or float64"], kpts1=[["a", "b"]])
    bad(m, c, ["scores0", "object"], scores0=np.array([None] * len(c["scores0"])))
    bad(m, c, ["desc0"], desc0=None)
    bad(m, c, ["kpts0"], kpts0=[[1.0, 2.0], [3.0]])  # ragged
    bad(m, c, ["scores0"], scores0="high")
    bad(m, c, ["size1"], size1="640x480")
    with pytest.raises(ValueError, match="feats1: missing descriptors"):
        m.match_dicts(feats(c, 0), {"keypoints": c["keypoints1"], "image_size": (1, 1)})
    with pytest.raises(ValueError, match=r"pairs\[1\]"):
        m.match_many([(feats(c, 0), feats(c, 1)), (feats(c, 0), {"keypoints": 1})])


def test_half_precision_and_integer_inputs_widen(golden_weights, golden_case):
    """float16 arrays (from a GPU extractor) and integer pixel coordinates or scores match as
    their exact float32 values do; the results are the same arrays."""
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    k0, d0, k1, d1 = (c["keypoints0"].round(), c["descriptors0"].astype(np.float16),
                      c["keypoints1"].astype(np.float16), c["descriptors1"].astype(np.float16))
    s0 = (c["scores0"] > np.median(c["scores0"])).astype(np.int32)
    kw = dict(size0=c["image_size0"], size1=c["image_size1"])
    want = m.match(k0.astype(np.float32), d0.astype(np.float32), k1.astype(np.float32), d1.astype(np.float32),
                   scores0=s0.astype(np.float32), scores1=c["scores1"].astype(np.float16).astype(np.float32), **kw)
    got = m.match(k0.astype(np.int64), d0, k1, d1, scores0=s0, scores1=c["scores1"].astype(np.float16), **kw)
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    f0 = {"keypoints": k0.astype(np.int16), "descriptors": d0, "image_size": c["image_size0"], "scores": s0}
    f1 = {"keypoints": k1, "descriptors": d1, "image_size": c["image_size1"], "scores": c["scores1"].astype(np.float16)}
    np.testing.assert_array_equal(m.match_dicts(f0, f1)["matches0"], want["matches0"])
    # A tensor that cannot become an array (torch's that require grad raise RuntimeError) is named.
    class Unconvertible:
        def __array__(self, *args, **kwargs):
            raise RuntimeError("Can't call numpy() on Tensor that requires grad")
    bad(m, c, ["desc1", "requires grad"], desc1=Unconvertible())
    # float64 beyond float32's range is named by row, without a numpy warning ahead of it.
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bad(m, c, ["desc0", "row 0 is not finite"], desc0=np.where(np.arange(len(d0))[:, None] == 0, 1e300, d0.astype(np.float64)))
    # float16 overflow is an error, as any Inf is.
    bad(m, c, ["desc0", "NaN or Inf"], desc0=np.full_like(d0, np.inf))


def test_zero_and_one_keypoint(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    e2, ed = np.zeros((0, 2), np.float32), np.zeros((0, 16), np.float32)
    out = m.match(e2, ed, c["keypoints1"], c["descriptors1"], size0=(640, 480), size1=(512, 384),
                  return_log_assignment=True)
    assert out["matches0"].shape == (0,)
    assert (out["matches1"] == -1).all() and (out["matching_scores1"] == 0).all()
    assert out["log_assignment"].shape == (1, len(c["keypoints1"]) + 1)
    out = m.match(c["keypoints0"], c["descriptors0"], e2, ed, size0=(640, 480), size1=(512, 384))
    assert (out["matches0"] == -1).all() and out["matches1"].shape == (0,)
    out = m.match(c["keypoints0"][:1], c["descriptors0"][:1], c["keypoints1"][:1], c["descriptors1"][:1],
                  size0=(640, 480), size1=(512, 384))
    assert out["matches0"].shape == (1,) and out["matches1"].shape == (1,)
    assert 0.0 <= float(out["matching_scores0"][0]) <= 1.0


# ---- weights files and configs ---------------------------------------------------

def test_exception_hierarchy():
    assert issubclass(paraformer.WeightsError, paraformer.ParaformerError)
    assert issubclass(paraformer.ParaformerError, Exception)
    assert paraformer.WeightsError.__module__ == "paraformer"
    assert {"Matcher", "ParaformerError", "WeightsError", "flops", "__version__"} <= set(paraformer.__all__)


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.safetensors"):
        paraformer.Matcher.from_file(tmp_path / "nope.safetensors")
    with pytest.raises(FileNotFoundError):
        paraformer.Matcher({"model": "paraformer"}, str(tmp_path / "nope.safetensors"))


def test_truncated_corrupted_and_foreign_files(golden_weights, tmp_path):
    data = golden_weights.read_bytes()
    for blob in (data[: len(data) // 2], data[:7], b"", b"\x89PNG\r\n\x1a\n" + bytes(100), b"{}" * 50):
        p = tmp_path / "w.safetensors"
        p.write_bytes(blob)
        with pytest.raises(paraformer.WeightsError):
            paraformer.Matcher.from_file(p)
        with pytest.raises(paraformer.ParaformerError):
            paraformer.Matcher.from_bytes(blob)


def test_mismatched_weights_list_every_tensor(golden_weights):
    sg = (DATA / "golden" / "superglue.weights.safetensors").read_bytes()
    cfg = dict(paraformer.Matcher.from_file(golden_weights).config)
    with pytest.raises(paraformer.WeightsError) as e:
        paraformer.Matcher(cfg, sg)
    msg = str(e.value)
    assert "missing tensor `wave_pe.amplitude.0.weight`" in msg
    assert "unexpected tensor `gnn.layers.0.attn.merge.weight`" in msg
    cfg["dim"] = 32  # right names, wrong shapes
    with pytest.raises(paraformer.WeightsError, match=r"`final_proj.weight` has shape \[16, 16\], expected \[32, 32\]"):
        paraformer.Matcher(cfg, golden_weights.read_bytes())


def test_bad_config_dicts_are_value_errors(golden_weights):
    w = golden_weights.read_bytes()
    for cfg, needle in (({"model": "paraformer", "colour": 1}, "colour"),
                        ({"model": "lightglue"}, "lightglue"),
                        ({"dim": 30}, "num_heads"),
                        ([1, 2], "config")):
        with pytest.raises(ValueError, match=needle):
            paraformer.Matcher(cfg, w)


def test_flops():
    assert paraformer.flops({"model": "paraformer"}, 2048, 2048) / 1e9 == pytest.approx(105.9, abs=0.05)
    assert paraformer.flops({"model": "superglue"}, 2048, 2048) / 1e9 == pytest.approx(127.4, abs=0.05)
    assert paraformer.flops({"model": "paraformer_u"}, 2048, 2048) / 1e9 == pytest.approx(65.8, abs=0.05)
    m = paraformer.Matcher.from_file(DATA / "golden" / "paraformer.weights.safetensors")
    assert paraformer.flops(m, 10, 12) == paraformer.flops(m.config, 10, 12) > 0
    assert paraformer.flops(m, 0, 12) == 0
    with pytest.raises(ValueError, match="m"):
        paraformer.flops(m, -1, 3)
    with pytest.raises(ValueError, match="unknown"):
        paraformer.flops({"model": "paraformer", "depth": 3}, 1, 1)


# ---- threads and memory ------------------------------------------------------------

def test_threads_give_identical_results(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    ref = m.match(*args(c), **kw(c, return_log_assignment=True))
    errors, results = [], []

    def work():
        try:
            for _ in range(40):
                results.append(m.match(*args(c), **kw(c, return_log_assignment=True)))
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(results) == 160
    for r in results:
        for k in ref:
            np.testing.assert_array_equal(r[k], ref[k])


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs /proc to read the resident set size")
def test_no_memory_growth_over_2000_calls(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    for _ in range(200):  # warm up allocator pools
        m.match(*args(c), **kw(c, return_log_assignment=True))
    gc.collect()
    before = rss_bytes()
    for _ in range(2000):
        m.match(*args(c), **kw(c, return_log_assignment=True))
    gc.collect()
    growth = rss_bytes() - before
    # One call allocates ~20 KB of outputs; a leak of one output per call would be ~40 MB.
    assert growth < 8 * 2**20, f"resident memory grew by {growth / 2**20:.1f} MiB over 2000 calls"


# ---- stubs --------------------------------------------------------------------------

def test_type_stubs_match_the_module():
    pytest.importorskip("mypy", reason="mypy not installed: stubtest skipped")
    r = subprocess.run([sys.executable, "-m", "mypy.stubtest", "paraformer._paraformer"],
                       capture_output=True, text=True, cwd=Path(__file__).parent)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (Path(paraformer.__file__).parent / "py.typed").exists()


def test_the_typed_package_type_checks():
    """The package says it is typed (py.typed): its own annotations must hold, or users'
    mypy runs inherit the errors. Optional extras (h5py, pycolmap, ray) may be absent."""
    pytest.importorskip("mypy", reason="mypy not installed: the package's type check skipped")
    r = subprocess.run([sys.executable, "-m", "mypy", "-p", "paraformer", "--ignore-missing-imports",
                        "--no-incremental"], capture_output=True, text=True, cwd=Path(__file__).parent)
    assert r.returncode == 0, r.stdout + r.stderr


def test_profile_reports_parts_and_the_counted_macs(golden_weights, golden_case):
    m, c = paraformer.Matcher.from_file(golden_weights), golden_case
    p = m.profile(*args(c), **kw(c))
    assert set(p) == {"encoder", "layers", "final_projection", "sinkhorn", "extraction", "total", "macs"}
    assert all(p[k] >= 0 for k in p)
    assert p["total"] == pytest.approx(sum(p[k] for k in ("encoder", "layers", "final_projection", "sinkhorn", "extraction")))
    assert p["macs"] == paraformer.flops(m, len(c["keypoints0"]), len(c["keypoints1"]))


def test_gil_is_released_while_matching(golden_weights):
    # While a thread matches, the main thread keeps running Python code; with the GIL
    # held for the whole computation it could not count at all until the thread ended.
    m = paraformer.Matcher.from_file(golden_weights)
    rng = np.random.default_rng(0)
    big = {"keypoints": rng.uniform(0, 480, (1500, 2)), "descriptors": rng.standard_normal((1500, 16)),
           "image_size": (640, 480)}
    done = threading.Event()
    worker = threading.Thread(target=lambda: (m.match_many([(big, big)] * 4, num_threads=1), done.set()))
    counter = 0
    worker.start()
    while not done.is_set():
        counter += 1
    worker.join()
    assert counter > 1000, f"the main thread ran only {counter} loop iterations while matching"


def test_config_shows_only_the_fields_the_model_uses():
    c = paraformer.Matcher.pretrained("paraformer-xfeat").config
    assert c["model"] == "paraformer" and "layer_names" not in c and "stage_dims" not in c
    u = paraformer.Matcher.pretrained("paraformer-u-xfeat").config
    assert "stage_dims" in u and "dim" not in u and "num_layers" not in u
    assert paraformer.flops(u, 512, 512) > 0  # the trimmed config reads back as the same model


def test_too_small_image_file_is_named(tmp_path):
    import struct
    import zlib

    def png(w, h):
        raw = b"".join(b"\x00" + b"\x80" * w for _ in range(h))
        def chunk(t, d):
            return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
        return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))

    p = tmp_path / "tiny.png"
    p.write_bytes(png(16, 16))
    with pytest.raises(ValueError, match=r"tiny\.png.*32×32"):
        paraformer.extract(p)


def test_precision_keyword(golden_weights, golden_case):
    data = golden_weights.read_bytes()
    fp32 = paraformer.Matcher.from_file(golden_weights)
    assert fp32.precision == "fp32" and "precision='fp32'" in repr(fp32)
    made = [paraformer.Matcher.from_file(golden_weights, precision="bf16"),
            paraformer.Matcher.from_bytes(data, precision="bf16"),
            paraformer.Matcher(fp32.config, data, precision="bf16"),
            paraformer.Matcher.pretrained("paraformer-xfeat", precision="bf16")]
    for m in made:
        assert m._inner.precision[0] == "bf16"
        assert m.precision in ("bf16", "fp32")  # fp32 where the CPU has no AVX-512 BF16
    c = golden_case
    ref, out = fp32.match(*args(c), **kw(c)), made[0].match(*args(c), **kw(c))
    assert out["matches0"].shape == ref["matches0"].shape
    if made[0].precision == "fp32":
        np.testing.assert_array_equal(out["matches0"], ref["matches0"])
    for bad in ("fp16", "FP32", 32, None):
        with pytest.raises(ValueError, match="precision"):
            paraformer.Matcher.from_file(golden_weights, precision=bad)
        with pytest.raises(ValueError, match="precision"):
            paraformer.Matcher.pretrained(precision=bad)


def test_training_attention_kernels_name_bad_arguments():
    """The bf16 attention kernels that training calls (`train.py --native-attention`)
    refuse wrong byte counts, widths and a non-finite scale or lse by name, on any CPU."""
    from paraformer import _paraformer

    bh, n, m, d = 2, 4, 3, 16
    q, kv, lse = bytes(2 * bh * n * d), bytes(2 * bh * m * d), np.zeros(bh * n, np.float32).tobytes()
    cases = [
        (lambda: _paraformer.attention_forward_bf16(q[:-2], kv, kv, bh, n, m, d, 0.25), "q"),
        (lambda: _paraformer.attention_forward_bf16(q, kv, kv[:-1], bh, n, m, d, 0.25), "v"),
        (lambda: _paraformer.attention_forward_bf16(q, kv, kv, bh, n, m, 12, 0.25), "d"),
        (lambda: _paraformer.attention_forward_bf16(q, b"", b"", bh, n, 0, d, 0.25), "k"),
        (lambda: _paraformer.attention_backward_bf16(q, kv, kv, q, q, lse[:-4], bh, n, m, d, 0.25), "lse"),
        (lambda: _paraformer.attention_backward_bf16(q, kv, kv, q, q, lse, bh, n, m, d, float("nan")), "scale"),
        (lambda: _paraformer.attention_backward_bf16(
            q, kv, kv, q, q, np.full(bh * n, np.inf, np.float32).tobytes(), bh, n, m, d, 0.25), "lse"),
        (lambda: _paraformer.attention_backward_bf16(q, kv, kv, q, q[:-2], lse, bh, n, m, d, 0.25), "d_o"),
    ]
    for call, name in cases:
        with pytest.raises(ValueError) as e:
            call()
        assert str(e.value).startswith(f"{name}:"), (name, str(e.value))


def test_amx_switch_keeps_the_matches_and_a_bad_environment_value_is_named():
    """bf16 matchers run on AMX tiles where the CPU has them: switching them off (set_amx or
    PARAFORMER_AMX=0) changes the kernels, not the matches beyond bf16 rounding; a bad
    PARAFORMER_AMX makes the import fail with its name."""
    n = paraformer._paraformer
    supported = n.amx()
    m = paraformer.Matcher.pretrained("paraformer-xfeat", precision="bf16")
    sample = Path(__file__).resolve().parent.parent / "assets" / "sample"
    f0, f1 = (paraformer.extract(sample / f"coffee_{i}.jpg", 1024) for i in (0, 1))
    try:
        n.set_amx(False)
        assert n.amx() is False
        off = m.match_dicts(f0, f1)["matches0"]
        n.set_amx(True)
        assert n.amx() is supported
        on = m.match_dicts(f0, f1)["matches0"]
    finally:
        n.set_amx(True)
    assert (off == on).mean() >= 0.99, (off != on).sum()
    code = "import paraformer._paraformer as n; print(n.amx())"
    env = {k: v for k, v in os.environ.items() if k != "PARAFORMER_AMX"}
    out = subprocess.run([sys.executable, "-c", code], env=dict(env, PARAFORMER_AMX="0"), capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr
    out = subprocess.run([sys.executable, "-c", code], env=dict(env, PARAFORMER_AMX="maybe"), capture_output=True, text=True)
    assert out.returncode != 0
    assert "PARAFORMER_AMX" in out.stderr and "maybe" in out.stderr and "expected" in out.stderr, out.stderr


def test_simd_cap_keeps_the_matches_and_a_bad_environment_value_is_named(tmp_path):
    """PARAFORMER_SIMD=avx2 or baseline runs the narrower kernels (the AVX2 fused attention,
    the scalar general path) on a wider CPU: the same matches beyond float rounding; a bad
    value makes the import fail with its name."""
    sample = Path(__file__).resolve().parent.parent / "assets" / "sample"
    f0, f1 = (paraformer.extract(sample / f"coffee_{i}.jpg", 1024) for i in (0, 1))
    feats = tmp_path / "feats.npz"
    np.savez(feats, **{f"{k}{i}": v for i, f in enumerate((f0, f1)) for k, v in f.items()})
    want = paraformer.Matcher.pretrained("paraformer-xfeat").match_dicts(f0, f1)["matches0"]
    code = (
        "import sys, numpy as np, paraformer, paraformer._paraformer as n\n"
        "z = np.load(sys.argv[1]); f = [{k[:-1]: z[k] for k in z.files if k.endswith(str(i))} for i in (0, 1)]\n"
        "np.save(sys.argv[2], paraformer.Matcher.pretrained('paraformer-xfeat').match_dicts(*f)['matches0'])\n"
        "print(n.simd())"
    )
    env = {k: v for k, v in os.environ.items() if k != "PARAFORMER_SIMD"}
    widest = paraformer._paraformer.simd()
    for level in ("avx2", "baseline"):
        got_path = tmp_path / f"{level}.npy"
        out = subprocess.run([sys.executable, "-c", code, str(feats), str(got_path)], env=dict(env, PARAFORMER_SIMD=level),
                             capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == (level if widest != "baseline" else "baseline"), out.stdout
        got = np.load(got_path)
        assert (got == want).mean() >= 0.99, (level, (got != want).sum())
    out = subprocess.run([sys.executable, "-c", "import paraformer"], env=dict(env, PARAFORMER_SIMD="sse9"), capture_output=True, text=True)
    assert out.returncode != 0
    assert "PARAFORMER_SIMD" in out.stderr and "sse9" in out.stderr and "expected" in out.stderr, out.stderr


def test_allocator_is_chosen_by_the_environment_and_a_bad_value_is_named():
    """The native code's allocator: mimalloc by default, the system's with
    PARAFORMER_ALLOCATOR=system; another value makes the import fail with its name."""
    code = "import paraformer, paraformer._paraformer as n; print(n.allocator())"
    env = {k: v for k, v in os.environ.items() if k != "PARAFORMER_ALLOCATOR"}
    assert paraformer._paraformer.allocator() in ("mimalloc", "system")
    for value, name in ((None, "mimalloc"), ("system", "system"), ("mimalloc", "mimalloc")):
        e = dict(env, **({} if value is None else {"PARAFORMER_ALLOCATOR": value}))
        out = subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True)
        assert out.returncode == 0 and out.stdout.strip() == name, (value, out.stdout, out.stderr)
    out = subprocess.run([sys.executable, "-c", code], env=dict(env, PARAFORMER_ALLOCATOR="tcmalloc"),
                         capture_output=True, text=True)
    assert out.returncode != 0
    assert "PARAFORMER_ALLOCATOR" in out.stderr and "tcmalloc" in out.stderr and "expected" in out.stderr, out.stderr
