"""Weights files: safetensors with SPEC tensor names and the config under ``paraformer.config``."""
from __future__ import annotations

import json

import torch
from safetensors.torch import load_file, safe_open, save_file

from .model import Matcher, resolve_config

CONFIG_KEY = "paraformer.config"


def save_safetensors(model: Matcher, path: str, dtype: torch.dtype = torch.float32) -> None:
    """Writes exactly the SPEC tensors (no ``num_batches_tracked``) and the config."""
    if hasattr(model, "self_rotary"):
        raise ValueError("a model with self rotary (outside the SPEC) has no weights file format")
    tensors = {k: v.detach().to(dtype).contiguous() for k, v in model.state_dict().items()
               if not k.endswith("num_batches_tracked")}
    save_file(tensors, path, metadata={CONFIG_KEY: json.dumps(model.config)})


def load_safetensors(path: str) -> Matcher:
    """Builds a ``Matcher`` in eval mode from a weights file (strict names and shapes)."""
    with safe_open(path, "pt") as f:
        meta = f.metadata() or {}
    if CONFIG_KEY not in meta:
        raise ValueError(f"{path}: no {CONFIG_KEY} metadata")
    model = Matcher(resolve_config(json.loads(meta[CONFIG_KEY])))
    state = {k: v.float() for k, v in load_file(path).items()}
    if "bin_score" in state:
        state["bin_score"] = state["bin_score"].reshape(())
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"{path}: missing {missing}, unexpected {unexpected}")
    return model.eval()
