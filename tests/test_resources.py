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
    return {"keypoints": rng.uniform(0, 600, (n, 2)).astype(np.float32), "descriptors": desc,
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
