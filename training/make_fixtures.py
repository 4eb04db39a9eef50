"""Regenerates the golden fixtures in ``tests/data/golden`` from the PyTorch reference.

    python training/make_fixtures.py            # from the repository root; needs torch

Random weights at small widths for every model and switch, with inputs covering
M ≠ N, M = 1, N = 1, odd K through the U-Net and keypoints outside the image. Each
configuration gets ``NAME.weights.safetensors`` and ``NAME.caseK.safetensors`` (inputs
and expected outputs, the layout of ``tests/data/spec_vectors``) plus ``index.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from safetensors.torch import save_file

from paraformer_train import Matcher, save_safetensors

U_DIMS = [16, 24, 8, 24, 16]
CONFIGS = {
    "superglue": {"model": "superglue", "descriptor_dim": 16, "dim": 16, "layer_names": ["self", "cross"] * 2},
    "superglue_input_proj": {"model": "superglue", "descriptor_dim": 12, "dim": 16,
                             "layer_names": ["cross", "self", "cross"]},
    "paraformer": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 3},
    "paraformer_input_proj": {"model": "paraformer", "descriptor_dim": 20, "dim": 16, "num_layers": 2},
    "paraformer_mlp_pe": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 2,
                          "positional_encoding": "mlp"},
    "paraformer_no_share_qkv": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 2,
                                "parallel": {"share_qkv": False}},
    "paraformer_no_share_merge": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 2,
                                  "parallel": {"share_merge": False}},
    "paraformer_no_attn_weight_sharing": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 2,
                                          "parallel": {"share_attention_weights": False}},
    "paraformer_all_switches_off": {"model": "paraformer", "descriptor_dim": 16, "dim": 16, "num_layers": 2,
                                    "parallel": {"share_qkv": False, "share_merge": False,
                                                 "share_attention_weights": False}},
    "paraformer_u": {"model": "paraformer_u", "descriptor_dim": 16, "stage_dims": U_DIMS},
    "paraformer_u_input_proj": {"model": "paraformer_u", "descriptor_dim": 10, "stage_dims": U_DIMS,
                                "stage_depths": [1, 2, 1, 1, 1]},
    "paraformer_u_gpool": {"model": "paraformer_u", "descriptor_dim": 16, "stage_dims": U_DIMS, "pooling": "gpool"},
    "paraformer_u_random": {"model": "paraformer_u", "descriptor_dim": 16, "stage_dims": U_DIMS,
                            "pooling": "random", "pooling_seed": 3},
    "paraformer_u_mlp_pe": {"model": "paraformer_u", "descriptor_dim": 16, "stage_dims": U_DIMS,
                            "positional_encoding": "mlp", "stage_depths": [1, 1, 0, 1, 1]},
}
# (M, N) per case: odd K through the U-Net, M = 1, N = 1.
SIZES = [(37, 26), (1, 7), (5, 1)]


def randomize(model: Matcher, gen: torch.Generator) -> None:
    """Random weights, non-trivial norm statistics, and a final projection scaled up
    so that the default threshold keeps a good share of the matches."""
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * (0.5 if p.dim() > 1 else 0.2)
                    / (p.shape[-1] ** 0.5 if p.dim() > 1 else 1.0))
        for name, b in model.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(torch.randn(b.shape, generator=gen) * 0.1)
            elif name.endswith("running_var"):
                b.copy_(torch.rand(b.shape, generator=gen) + 0.5)
        model.final_proj.weight.mul_(2.5)
        if hasattr(model, "input_proj"):
            model.input_proj.weight.mul_(4.0)


def make_pair(m: int, n: int, d: int, gen: torch.Generator) -> dict:
    """Two images whose descriptors overlap (a permuted, noisy copy), some keypoints
    lying outside the image."""
    size0, size1 = torch.tensor([640.0, 480.0]), torch.tensor([512.0, 384.0])
    k0 = torch.rand(m, 2, generator=gen) * (size0 * 1.1) - size0 * 0.05
    k1 = torch.rand(n, 2, generator=gen) * (size1 * 1.1) - size1 * 0.05
    d0 = torch.randn(m, d, generator=gen)
    d1 = torch.randn(n, d, generator=gen)
    shared = min(m, n) * 2 // 3
    perm = torch.randperm(n, generator=gen)[:shared]
    d1[perm] = d0[:shared] + 0.1 * torch.randn(shared, d, generator=gen)
    return {
        "keypoints0": k0, "keypoints1": k1,
        "scores0": torch.rand(m, generator=gen), "scores1": torch.rand(n, generator=gen),
        "descriptors0": d0, "descriptors1": d1,
        "image_size0": size0, "image_size1": size1,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "tests" / "data" / "golden"))
    ap.add_argument("--seed", type=int, default=20261123)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(args.seed)
    index = []
    for name, cfg in CONFIGS.items():
        model = Matcher(cfg)
        randomize(model, gen)
        model.eval()
        weights = f"{name}.weights.safetensors"
        save_safetensors(model, str(out / weights))
        for k, (m, n) in enumerate(SIZES):
            pair = make_pair(m, n, model.config["descriptor_dim"], gen)
            with torch.no_grad():
                res = model({key: v[None] for key, v in pair.items()})
            case = {**pair, **{key: v[0].contiguous() for key, v in res.items()}}
            case_name = f"{name}.case{k}.safetensors"
            save_file(case, str(out / case_name), metadata={"weights": weights})
            valid = int((res["matches0"][0] >= 0).sum())
            index.append({"case": case_name, "weights": weights, "M": m, "N": n, "valid_matches": valid})
            print(f"{case_name:<50} M={m:<3} N={n:<3} valid matches {valid}")
    # Same weights stored as f16 (the reader upcasts); expected outputs are the f32 ones
    # of the f16-rounded weights, so parity must still hold.
    model = Matcher(CONFIGS["paraformer"])
    randomize(model, gen)
    model.eval()
    save_safetensors(model, str(out / "paraformer_f16.weights.safetensors"), dtype=torch.float16)
    with torch.no_grad():
        for p in list(model.parameters()) + list(model.buffers()):
            if p.dtype.is_floating_point:
                p.copy_(p.half().float())
    pair = make_pair(*SIZES[0], 16, gen)
    with torch.no_grad():
        res = model({key: v[None] for key, v in pair.items()})
    save_file({**pair, **{key: v[0].contiguous() for key, v in res.items()}},
              str(out / "paraformer_f16.case0.safetensors"), metadata={"weights": "paraformer_f16.weights.safetensors"})
    index.append({"case": "paraformer_f16.case0.safetensors", "weights": "paraformer_f16.weights.safetensors",
                  "M": SIZES[0][0], "N": SIZES[0][1], "valid_matches": int((res["matches0"][0] >= 0).sum())})
    (out / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    print(f"wrote {len(index)} cases to {out}")


if __name__ == "__main__":
    main()
