"""The PyTorch reference (training/paraformer_train) reproduces the SPEC test vectors.

Needs torch; skipped (with the reason printed) where it is not installed, as in CI.
Pass: identical matches; log_assignment and matching scores within 1e-4 absolute.
"""
import json
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch", reason="torch not installed: the reference model is checked only where it is")
safetensors_torch = pytest.importorskip("safetensors.torch")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "training"))
from paraformer_train import load_safetensors  # noqa: E402

TOL = 1e-4
INPUTS = ["keypoints0", "keypoints1", "scores0", "scores1", "descriptors0", "descriptors1", "image_size0", "image_size1"]


def cases(folder):
    d = ROOT / "tests" / "data" / folder
    return [(d, e) for e in json.loads((d / "index.json").read_text())]


@pytest.mark.parametrize("folder,entry", cases("spec_vectors") + cases("golden"),
                         ids=lambda v: v["case"] if isinstance(v, dict) else None)
def test_reference_reproduces_fixture(folder, entry):
    model = load_safetensors(str(folder / entry["weights"]))
    case = safetensors_torch.load_file(str(folder / entry["case"]))
    with torch.no_grad():
        out = model({k: case[k][None] for k in INPUTS})
    assert (out["log_assignment"][0] - case["log_assignment"]).abs().max().item() <= TOL
    assert torch.equal(out["matches0"][0], case["matches0"])
    assert torch.equal(out["matches1"][0], case["matches1"])
    for k in ("matching_scores0", "matching_scores1"):
        assert (out[k][0] - case[k]).abs().max().item() <= TOL
