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


def test_self_rotary_sees_only_relative_positions():
    """The training-only rotary encoding (outside the SPEC): query·key products are unchanged
    when both images' keypoints shift together, and change when distances change."""
    from paraformer_train.model import SelfRotary, rotate_pairs

    rot = SelfRotary(16, 1.0, 100.0)
    g = torch.Generator().manual_seed(3)
    pos = torch.rand(1, 20, 3, generator=g) - 0.5
    q, k = torch.randn(2, 1, 2, 20, 16, generator=g)

    def products(p):
        r = rot(p)
        return rotate_pairs(q, r) @ rotate_pairs(k, r).transpose(-1, -2)

    shifted = pos + torch.tensor([0.3, -0.2, 0.0])
    assert torch.allclose(products(pos), products(shifted), atol=1e-4)
    assert not torch.allclose(products(pos), products(pos * 1.5), atol=1e-2)


def test_self_rotary_leaves_the_spec_model_and_has_no_weights_file(tmp_path):
    from paraformer_train.io import save_safetensors
    from paraformer_train.model import Matcher

    cfg = {"descriptor_dim": 64, "dim": 48, "num_heads": 3, "num_layers": 2}
    torch.manual_seed(5)
    plain = Matcher(cfg).state_dict()
    torch.manual_seed(5)
    rotary = Matcher(cfg, (1.0, 100.0))
    # Its own generator: every SPEC weight starts as in the run without it.
    spec = {k: v for k, v in rotary.state_dict().items() if not k.startswith("self_rotary.")}
    assert spec.keys() == plain.keys()
    assert all(torch.equal(spec[k], plain[k]) for k in plain)
    with pytest.raises(ValueError, match="outside the SPEC"):
        save_safetensors(rotary, str(tmp_path / "w.safetensors"))
    with pytest.raises(ValueError, match="needs a paraformer model"):
        Matcher({"model": "superglue", "descriptor_dim": 64, "dim": 48, "num_heads": 3}, (1.0, 100.0))
    with pytest.raises(ValueError, match="expected 0 < LO <= HI"):
        Matcher(cfg, (5.0, 1.0))


def test_validate_snapshots_rebuilds_rotary_checkpoints(tmp_path):
    """``validate_snapshots.py`` builds each snapshot's model with its run's ``--self-rotary``
    (it built every checkpoint without, so a rotary one failed to load)."""
    import validate_snapshots
    from paraformer_train.model import Matcher

    args = {"preset": "paraformer", "dim": 48, "heads": 3, "depth": 2, "sinkhorn": 5, "seed": 0,
            "self_rotary": [1.0, 100.0]}
    model = Matcher(validate_snapshots.model_config(args), tuple(args["self_rotary"]))
    path = tmp_path / "last.pt"
    torch.save({"ema": model.state_dict(), "pairs": 1234, "steps": 7, "args": args}, path)
    ((pairs, rebuilt, state, extra),) = validate_snapshots.snapshots(str(path))
    assert (pairs, extra) == (1234, {"steps": 7})
    rebuilt.load_state_dict(state)  # strict: every rotary weight has its place
    assert any(k.startswith("self_rotary.") for k in rebuilt.state_dict())
    # A snapshots file (train_gpu.py's) without the field builds the SPEC model.
    torch.save({500: {"config": model.config, "ema": Matcher(model.config).state_dict()}}, tmp_path / "snap.pt")
    ((pairs, plain, state, _),) = validate_snapshots.snapshots(str(tmp_path / "snap.pt"))
    plain.load_state_dict(state)
    assert pairs == 500 and not any(k.startswith("self_rotary.") for k in plain.state_dict())


def test_self_rotary_with_a_gain_starts_as_the_identity():
    """``--self-rotary LO HI GAIN`` fine-tunes a trained model: at the start it computes what
    the model without the encoding does."""
    from paraformer_train.model import Matcher

    cfg = {"descriptor_dim": 8, "dim": 16, "num_heads": 2, "num_layers": 2, "sinkhorn_iterations": 5}
    torch.manual_seed(2)
    plain = Matcher(cfg).eval()
    grown = Matcher(cfg, (1.0, 100.0, 10.0)).eval()
    grown.load_state_dict(plain.state_dict() | {"self_rotary.freq.weight": grown.self_rotary.freq.weight,
                                                 "self_rotary.scale": grown.self_rotary.scale})
    g = torch.Generator().manual_seed(4)
    data = {f"keypoints{i}": torch.rand(1, 12, 2, generator=g) * 300 for i in (0, 1)}
    data |= {f"scores{i}": torch.rand(1, 12, generator=g) for i in (0, 1)}
    data |= {f"descriptors{i}": torch.randn(1, 12, 8, generator=g) for i in (0, 1)}
    data |= {f"image_size{i}": torch.tensor([[320.0, 240.0]]) for i in (0, 1)}
    with torch.no_grad():
        assert torch.allclose(plain.scores(data), grown.scores(data), atol=1e-5)
        grown.self_rotary.scale.fill_(0.1)
        assert not torch.allclose(plain.scores(data), grown.scores(data), atol=1e-3)
