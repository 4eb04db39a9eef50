"""Inputs that used to kill the interpreter or slip through: a match beyond the memory
limit, images beyond it, hostile weights (NaN/Inf) and absurd configs."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import paraformer
from conftest import DATA


@pytest.fixture
def limit_restored():
    yield
    paraformer.set_memory_limit(None)


def _feats(n: int, d: int = 64, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(n, d)).astype(np.float32)
    return {"keypoints": rng.uniform(0, 480, (n, 2)).astype(np.float32), "descriptors": desc,
            "image_size": (640, 480)}


def test_60000_keypoints_raise_resource_error_not_abort():
    m = paraformer.Matcher.pretrained("paraformer-xfeat")
    f = _feats(60_000)
    paraformer.set_memory_limit(8 * 10**9)
    try:
        with pytest.raises(paraformer.ResourceError, match=r"60000 × 60000 keypoints needs .* GB"):
            m.match_dicts(f, f)
        with pytest.raises(MemoryError):  # a ResourceError is a MemoryError too
            m.match_many([(f, f)])
    finally:
        paraformer.set_memory_limit(None)
    assert issubclass(paraformer.ResourceError, paraformer.ParaformerError)
    # The default limit comes from the memory available: the same call is refused there too
    # on any machine with less than ~33 GB free.
    if paraformer.memory_limit() < 30 * 10**9:
        with pytest.raises(paraformer.ResourceError):
            m.match_dicts(f, f)


def test_memory_limit_must_be_a_positive_int(limit_restored):
    """0 would refuse every call; negatives, floats and bools are not sizes: each is named."""
    for bad in (0, -1, 1.5, True, "8G", 2**64):
        with pytest.raises(ValueError, match=r"^bytes: expected a positive int or None"):
            paraformer.set_memory_limit(bad)
    paraformer.set_memory_limit(np.int64(10**9))
    assert paraformer.memory_limit() == 10**9


def test_huge_array_image_is_refused_before_it_is_copied():
    """A 10-gigapixel array was copied to bytes and to float32 before XFeat's memory check,
    and the process was killed for memory: now the check comes first. (Broadcast views: the
    test arrays hold no memory.)"""
    for dtype in (np.uint8, np.float32):
        huge = np.broadcast_to(np.zeros(1, dtype), (100_000, 100_000))
        with pytest.raises(paraformer.ResourceError, match=r"XFeat on a 100000×100000 image needs .* GB"):
            paraformer.extract(huge)
    # Sizes whose byte counts overflow 64 bits (a broadcast view holds no memory) saturate.
    with pytest.raises(paraformer.ResourceError):
        paraformer.extract(np.broadcast_to(np.zeros(1, np.uint8), (2**31, 2**30, 3)))


def test_limit_is_settable_and_applies_to_match_many_and_extract(limit_restored):
    m = paraformer.Matcher.pretrained("paraformer-xfeat")
    f0, f1 = _feats(512, seed=1), _feats(512, seed=2)
    assert len(m.match_dicts(f0, f1)["matches0"]) == 512
    paraformer.set_memory_limit(1_000_000)
    assert paraformer.memory_limit() == 1_000_000
    with pytest.raises(paraformer.ResourceError, match="limit of 1.0 MB"):
        m.match_dicts(f0, f1)
    with pytest.raises(paraformer.ResourceError):
        m.match_many([(f0, f1)] * 3, num_threads=2)
    with pytest.raises(paraformer.ResourceError, match="XFeat on a 600×400 image"):
        paraformer.extract(DATA.parent.parent / "assets" / "sample" / "coffee_0.jpg")
    paraformer.set_memory_limit(None)
    assert paraformer.memory_limit() > 1_000_000
    # a limit that fits one pair at a time: match_many still finishes, pairs run one by one
    need_one = m.memory_needed(512, 512)
    # Counts too large to hold: named, and the estimate saturates rather than wraps.
    with pytest.raises(ValueError, match=r"^m: "):
        m.memory_needed(10**30, 5)
    assert m.memory_needed(2**63, 2**63) == 2**64 - 1
    assert 2 * 513 * 513 * 4 < need_one < 40 * 10**6
    paraformer.set_memory_limit(int(need_one * 1.5))
    outs = m.match_many([(f0, f1)] * 3, num_threads=2)
    paraformer.set_memory_limit(None)
    ref = m.match_dicts(f0, f1)
    for o in outs:
        np.testing.assert_array_equal(o["matches0"], ref["matches0"])


def _golden_with(edit) -> bytes:
    raw = (DATA / "golden" / "paraformer.weights.safetensors").read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    body = bytearray(raw[8 + n:])
    edit(header, body)
    head = json.dumps(header).encode()
    head += b" " * (-len(head) % 8)
    return struct.pack("<Q", len(head)) + head + bytes(body)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_weights_raise_weights_error_naming_the_tensor(value):
    def edit(header, body):
        start = header["final_proj.weight"]["data_offsets"][0]
        body[start + 8:start + 12] = struct.pack("<f", value)

    with pytest.raises(paraformer.WeightsError, match=r"final_proj.weight.*flat index 2"):
        paraformer.Matcher.from_bytes(_golden_with(edit))


@pytest.mark.parametrize("field,value", [("dim", 10**9), ("num_layers", 10**6), ("sinkhorn_iterations", 10**9),
                                         ("descriptor_dim", 10**9), ("num_heads", 10**9)])
def test_absurd_configs_are_refused_before_allocating(field, value):
    weights = (DATA / "golden" / "paraformer.weights.safetensors").read_bytes()
    with pytest.raises((paraformer.WeightsError, ValueError), match=field):
        paraformer.Matcher({"model": "paraformer", field: value}, weights)


def test_ctrl_c_interrupts_a_long_match_many():
    import signal
    import subprocess
    import sys
    import time

    # The child installs Python's own SIGINT handler: a parent that ignores SIGINT (any
    # `cmd &` of a non-interactive shell, as CI runners start jobs) hands the ignore down,
    # and Python then keeps it, so Ctrl-C would never reach the call under test.
    code = """
import signal, sys, numpy as np, paraformer
signal.signal(signal.SIGINT, signal.default_int_handler)
m = paraformer.Matcher.pretrained("paraformer-xfeat")
rng = np.random.default_rng(0)
f = {"keypoints": rng.uniform(0, 480, (2048, 2)).astype(np.float32),
     "descriptors": rng.normal(size=(2048, 64)).astype(np.float32), "image_size": (640, 480)}
print("ready", flush=True)
try:
    m.match_many([(f, f)] * 400, num_threads=2)
    print("finished")
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(3)
"""
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    time.sleep(1.5)
    t0 = time.time()
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=30)
    waited = time.time() - t0
    assert p.returncode == 3 and "interrupted" in out, (p.returncode, out, waited)
    # About one pair per worker (~0.3 s) on an idle machine; all 400 pairs would take > 80 s.
    assert waited < 20, f"took {waited:.1f} s to stop"
    print(f"stopped {waited:.2f} s after SIGINT")


@pytest.mark.parametrize("name", paraformer.pretrained_names())
def test_extreme_but_valid_inputs_give_finite_outputs(name):
    m = paraformer.Matcher.pretrained(name)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 64)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = rng.uniform(0, 480, (300, 2)).astype(np.float32)
    k8 = rng.uniform(0, 480, (8192, 2)).astype(np.float32)
    d8 = rng.normal(size=(8192, 64)).astype(np.float32)
    same = np.full((300, 2), 100, np.float32)
    cases = {
        "all keypoints identical": (same, d, same, d, (640, 480), (640, 480)),
        "keypoints on opposite borders": (np.zeros((300, 2), np.float32), d, np.full((300, 2), [640, 480], np.float32), d,
                                          (640, 480), (640, 480)),
        "image size 1 × 1e6": (k, d, k, d, (1, 1e6), (1e6, 1)),
        "all-zero descriptors": (k, np.zeros_like(d), k, np.zeros_like(d), (640, 480), (640, 480)),
        "1 keypoint against 8192": (k[:1], d[:1], k8, d8, (640, 480), (640, 480)),
    }
    for label, (k0, d0, k1, d1, s0, s1) in cases.items():
        out = m.match(k0, d0, k1, d1, size0=s0, size1=s1, return_log_assignment=True)
        for key in ("matching_scores0", "matching_scores1", "log_assignment"):
            assert not np.isnan(out[key]).any(), (label, key)
        assert out["matches0"].shape == (len(k0),) and out["matches1"].shape == (len(k1),), label
