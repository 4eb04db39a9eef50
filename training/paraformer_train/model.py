"""ParaFormer, ParaFormer-U and SuperGlue in PyTorch, written from SPEC.md.

Module and parameter names equal the SPEC tensor names, so ``state_dict()`` (less
BatchNorm's ``num_batches_tracked``) is a valid weights file. Tensors are batched
``[B, K, C]``; every image of a batch has the same K.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

DEFAULTS = {
    "model": "paraformer",
    "descriptor_dim": 256,
    "dim": 256,
    "num_heads": 4,
    "num_layers": 9,
    "layer_names": ["self", "cross"] * 9,
    "positional_encoding": None,  # "mlp" for superglue, "wave" otherwise
    "stage_depths": [2, 1, 2, 1, 2],
    "stage_dims": [256, 384, 128, 384, 256],
    "pooling": "attentional",
    "parallel": {"share_qkv": True, "share_merge": True, "share_attention_weights": True},
    "pooling_seed": 0,
    "sinkhorn_iterations": 100,
    "match_threshold": 0.2,
}


def resolve_config(config: dict) -> dict:
    """Fills SPEC §9 defaults; unknown fields are an error."""
    unknown = set(config) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"unknown config fields: {sorted(unknown)}")
    cfg = copy.deepcopy(DEFAULTS)
    for key, value in config.items():
        if key == "parallel":
            bad = set(value) - set(DEFAULTS["parallel"])
            if bad:
                raise ValueError(f"unknown parallel switches: {sorted(bad)}")
            cfg["parallel"].update(value)
        else:
            cfg[key] = copy.deepcopy(value)
    if cfg["model"] not in ("paraformer", "paraformer_u", "superglue"):
        raise ValueError(f"unknown model {cfg['model']!r}")
    if cfg["positional_encoding"] is None:
        cfg["positional_encoding"] = "mlp" if cfg["model"] == "superglue" else "wave"
    return cfg


def model_dim(cfg: dict) -> int:
    return cfg["stage_dims"][0] if cfg["model"] == "paraformer_u" else cfg["dim"]


class BatchNorm(nn.BatchNorm1d):
    """BatchNorm1d over the channel axis of ``[B, K, C]`` features."""

    def forward(self, x):
        return super().forward(x.transpose(1, 2)).transpose(1, 2)


def mlp(channels: list[int]) -> nn.Sequential:
    """SPEC §2: Linear, then BatchNorm + ReLU between consecutive Linear layers."""
    layers: list[nn.Module] = []
    for i in range(len(channels) - 1):
        layers.append(nn.Linear(channels[i], channels[i + 1]))
        if i < len(channels) - 2:
            layers += [BatchNorm(channels[i + 1]), nn.ReLU()]
    return nn.Sequential(*layers)


def normalize_keypoints(kpts, scores, size):
    """``[(x−cx)/s, (y−cy)/s, score]`` with ``c = size/2``, ``s = 0.7·max(size)``."""
    size = size.to(kpts)
    center = size[:, None, :] / 2
    scale = 0.7 * size.max(-1).values[:, None, None]
    return torch.cat([(kpts - center) / scale, scores[..., None]], -1)


class KeypointEncoder(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.encoder = mlp([3, 32, 64, 128, 256, c])

    def forward(self, desc, pos):
        with torch.autocast(pos.device.type, enabled=False):  # positions stay fp32 (see WavePE)
            enc = self.encoder(pos.to(self.encoder[0].weight.dtype))
        return desc + enc


class WavePE(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.amplitude = mlp([c, 4 * c, c])
        self.phase = mlp([3, c // 2, c])
        self.fuse = mlp([2 * c, 4 * c, c])

    def forward(self, desc, pos):
        a = self.amplitude(desc)
        # Under bf16 autocast (train.py --bf16) the phase stays fp32, as in the engine's bf16
        # path: it reads keypoint positions, and a bf16 phase would blur them.
        with torch.autocast(pos.device.type, enabled=False):
            theta = self.phase(pos.to(self.phase[0].weight.dtype))
        return desc + self.fuse(torch.cat([a * torch.cos(theta), a * torch.sin(theta)], -1))


class SelfRotary(nn.Module):
    """Not in the SPEC (training experiments only; ``save_safetensors`` refuses it): rotary
    encoding of self-attention's queries and keys from learnable 2-D frequencies, as LightGlue
    does. It gives each layer's self-attention the relative positions of keypoints within one
    image, which the SPEC's absolute Wave-PE, added once at the input, does not."""

    def __init__(self, head_dim: int, lo: float, hi: float, gain: float = 0.0):
        """``gain`` > 0: every angle is scaled by ``gain`` x a learnable per-pair factor that
        starts at zero, so the encoding starts as the identity (a trained model fine-tuned
        with it computes what it did) and grows at Adam's step size times ``gain``."""
        super().__init__()
        if head_dim % 2:
            raise ValueError(f"self rotary: head width {head_dim} must be even")
        if not 0 < lo <= hi:
            raise ValueError(f"self rotary: frequencies {lo} {hi}: expected 0 < LO <= HI")
        if gain < 0:
            raise ValueError(f"self rotary: gain {gain}: expected 0 (none) or more")
        self.freq = nn.Linear(2, head_dim // 2, bias=False)
        # One frequency per channel pair, geometrically spaced from lo to hi (radians per unit of
        # normalized position, 0.7 x the image's longer side), in a random direction.
        # A generator of its own: the other weights and the batches stay those of the run without it.
        n = head_dim // 2
        angle = torch.rand(n, generator=torch.Generator().manual_seed(0)) * 2 * math.pi
        mag = torch.logspace(math.log10(lo), math.log10(hi), n)
        with torch.no_grad():
            self.freq.weight.copy_(torch.stack([mag * torch.cos(angle), mag * torch.sin(angle)], -1))
        self.gain = gain
        if gain > 0:
            self.scale = nn.Parameter(torch.zeros(n))

    def forward(self, pos):
        """``pos`` [B,K,≥2] normalized positions → (cos, sin), each [B,1,K,head_dim/2]."""
        with torch.autocast(pos.device.type, enabled=False):
            ang = self.freq(pos[..., :2].to(self.freq.weight.dtype))
            if self.gain > 0:
                ang = ang * (self.gain * self.scale)
        return torch.cos(ang)[:, None], torch.sin(ang)[:, None]


def rotate_pairs(t, rot):
    """Rotates channel pairs (2i, 2i+1) of ``t`` [B,H,K,D] by the angles of ``rot``, so that
    ⟨rotate(q, p_i), rotate(k, p_j)⟩ depends on positions only through p_i − p_j."""
    cos, sin = rot
    a, b = t[..., 0::2].float(), t[..., 1::2].float()
    return torch.stack([a * cos - b * sin, a * sin + b * cos], -1).flatten(-2).to(t.dtype)


def split_heads(x, h):
    b, k, c = x.shape
    return x.view(b, k, h, c // h).transpose(1, 2)


def merge_heads(x):
    b, h, k, d = x.shape
    return x.transpose(1, 2).reshape(b, k, h * d)


def scaled_scores(q, k):
    return q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])


FUSED_ATTENTION = True  # False: explicit softmax everywhere (the slower pre-SDPA path)
# True (train.py --native-attention): bf16 fused attention in training runs in the project's
# engine (NativeAttention) instead of PyTorch's CPU flash kernels.
NATIVE_ATTENTION = False
NATIVE_HEAD_WIDTHS = (16, 32, 64)  # the engine's kernels; other widths take PyTorch's SDPA


def _bf16_bytes(t: torch.Tensor) -> bytes:
    return t.to(torch.bfloat16).contiguous().view(torch.int16).numpy().tobytes()


def _bf16_tensor(b: bytes, shape) -> torch.Tensor:
    return torch.frombuffer(bytearray(b), dtype=torch.bfloat16).view(shape)


class NativeAttention(torch.autograd.Function):
    """``softmax(q·kᵀ/√d)·v`` of bf16 ``[B, H, N, d]`` tensors in ``paraformer``'s engine:
    ``attention_forward_bf16`` (output and the rows' log-sum-exp) and
    ``attention_backward_bf16`` (blocked recomputation, flash-attention style), both with
    bf16 products and fp32 sums, at the machine's bf16 rate where PyTorch's CPU flash
    kernels run at a third to a half of it for head width 32 (``bench_attention.py``)."""

    @staticmethod
    def forward(ctx, q, k, v):
        from paraformer import _paraformer  # the engine; only needed with the flag on

        b, h, n, d = q.shape
        m = k.shape[2]
        operands = tuple(_bf16_bytes(t) for t in (q, k, v))
        o, lse = _paraformer.attention_forward_bf16(*operands, b * h, n, m, d, 1.0 / math.sqrt(d))
        # The backward takes the same bytes: kept here, not serialised again from tensors.
        ctx.operands, ctx.o, ctx.lse = operands, o, lse
        ctx.dims, ctx.dtypes = (b, h, n, m, d), (q.dtype, k.dtype, v.dtype)
        return _bf16_tensor(o, (b, h, n, d))

    @staticmethod
    def backward(ctx, grad):
        from paraformer import _paraformer

        b, h, n, m, d = ctx.dims
        grads = _paraformer.attention_backward_bf16(*ctx.operands, ctx.o, _bf16_bytes(grad), ctx.lse,
                                                    b * h, n, m, d, 1.0 / math.sqrt(d))
        shapes = ((b, h, n, d), (b, h, m, d), (b, h, m, d))
        return tuple(_bf16_tensor(g, s).to(t) for g, s, t in zip(grads, shapes, ctx.dtypes))


def attention(q, k, v, need_prob: bool = True):
    """Softmax attention; without ``need_prob`` it runs as one fused
    ``scaled_dot_product_attention`` (same value, far less memory traffic in training)."""
    if not need_prob and FUSED_ATTENTION:
        if (NATIVE_ATTENTION and q.dtype == torch.bfloat16 and torch.is_grad_enabled()
                and q.shape[-1] in NATIVE_HEAD_WIDTHS):
            return merge_heads(NativeAttention.apply(q, k, v)), None
        return merge_heads(F.scaled_dot_product_attention(q, k, v)), None
    prob = scaled_scores(q, k).softmax(-1)
    return merge_heads(prob @ v), prob


class Attention(nn.Module):
    """SuperGlue's multi-headed attention: ``proj.{0,1,2}`` and ``merge``."""

    def __init__(self, c: int, heads: int):
        super().__init__()
        self.heads = heads
        self.proj = nn.ModuleList([nn.Linear(c, c) for _ in range(3)])
        self.merge = nn.Linear(c, c)

    def forward(self, x, src):
        q, k, v = (split_heads(p(t), self.heads) for p, t in zip(self.proj, (x, src, src)))
        return self.merge(attention(q, k, v, need_prob=False)[0])


class SerialLayer(nn.Module):
    def __init__(self, c: int, heads: int, kind: str):
        super().__init__()
        self.kind = kind
        self.attn = Attention(c, heads)
        self.mlp = mlp([2 * c, 2 * c, c])

    def forward(self, x, y):
        sx, sy = (x, y) if self.kind == "self" else (y, x)
        dx = self.mlp(torch.cat([x, self.attn(x, sx)], -1))
        dy = self.mlp(torch.cat([y, self.attn(y, sy)], -1))
        return x + dx, y + dy


class ParallelAttention(nn.Module):
    def __init__(self, c: int, heads: int, switches: dict):
        super().__init__()
        self.heads = heads
        self.share_qkv = switches["share_qkv"]
        self.share_merge = switches["share_merge"]
        self.share_weights = switches["share_attention_weights"]
        lin3 = lambda: nn.ModuleList([nn.Linear(c, c) for _ in range(3)])  # noqa: E731
        if self.share_qkv:
            self.proj = lin3()
        else:
            self.self_proj, self.cross_proj = lin3(), lin3()
        if self.share_merge:
            self.merge = nn.Linear(c, c)
        else:
            self.self_merge, self.cross_merge = nn.Linear(c, c), nn.Linear(c, c)

    def projections(self):
        if self.share_qkv:
            return self.proj, self.proj
        return self.self_proj, self.cross_proj

    def merges(self):
        if self.share_merge:
            return self.merge, self.merge
        return self.self_merge, self.cross_merge

    def forward(self, x, y, need_probs: bool = True, rot=None, branches=(True, True)):
        """``need_probs``: also return the self-attention probabilities (attentional pooling
        reads them); without, every attention is fused SDPA. ``branches``: (self, cross) to
        compute; a skipped one's messages are None. The shared cross-attention of
        image 1 is SDPA with query K_y and key Q_x: exactly the column softmax of Q_x·K_yᵀ.
        ``rot``: (image 0's, image 1's) ``SelfRotary`` output, applied to self-attention's
        queries and keys only (not in the SPEC; None there)."""
        sp, cp = self.projections()
        h = self.heads
        sh = lambda p, t: split_heads(p(t), h)  # noqa: E731
        rx, ry = rot if rot is not None else (None, None)

        def self_qk(t, r):
            q, k = sh(sp[0], t), sh(sp[1], t)
            return (q, k) if r is None else (rotate_pairs(q, r), rotate_pairs(k, r))

        if branches[0] or need_probs:
            self_x, prob_x = attention(*self_qk(x, rx), sh(sp[2], x), need_probs)
            self_y, prob_y = attention(*self_qk(y, ry), sh(sp[2], y), need_probs)
        else:
            self_x = prob_x = self_y = prob_y = None
        if not branches[1]:
            return (self_x, None), (self_y, None), (prob_x, prob_y)
        vx, vy = sh(cp[2], x), sh(cp[2], y)
        qx, ky = sh(cp[0], x), sh(cp[1], y)
        cross_x = attention(qx, ky, vy, need_prob=False)[0]
        if self.share_weights:
            cross_y = attention(ky, qx, vx, need_prob=False)[0]
        else:
            cross_y = attention(sh(cp[0], y), sh(cp[1], x), vx, need_prob=False)[0]
        return (self_x, cross_x), (self_y, cross_y), (prob_x, prob_y)


class ParallelLayer(nn.Module):
    def __init__(self, c: int, heads: int, switches: dict):
        super().__init__()
        self.attn = ParallelAttention(c, heads, switches)
        self.fuse = nn.Sequential(nn.Linear(3 * c, 2 * c), nn.LayerNorm(2 * c), nn.GELU(), nn.Linear(2 * c, c))
        # (self, cross) messages computed; a closed one (its fuse columns held at zero, as
        # train.py --serial does) is a zero message, which is what it contributes anyway.
        self.branches = (True, True)

    def forward(self, x, y, need_probs: bool = True, rot=None):
        (sx, cx), (sy, cy), probs = self.attn(x, y, need_probs, rot, self.branches)
        m_self, m_cross = self.attn.merges()

        def update(f, s, c):
            ms = m_self(s) if self.branches[0] else torch.zeros_like(f)
            mc = m_cross(c) if self.branches[1] else torch.zeros_like(f)
            return f + self.fuse(torch.cat([f, ms, mc], -1))

        return update(x, sx, cx), update(y, sy, cy), probs


def splitmix64_indices(n: int, k: int, seed: int) -> list[int]:
    """Partial Fisher–Yates shuffle of ``0..n`` driven by SplitMix64 (SPEC §7)."""
    mask = (1 << 64) - 1
    state = seed & mask
    a = list(range(n))
    for t in range(k):
        state = (state + 0x9E3779B97F4A7C15) & mask
        z = state
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        z ^= z >> 31
        j = t + z % (n - t)
        a[t], a[j] = a[j], a[t]
    return a[:k]


class Pool(nn.Module):
    def __init__(self, c_in: int, c_out: int, kind: str, seed: int, index: int):
        super().__init__()
        self.kind, self.seed, self.index = kind, seed, index
        self.proj = nn.Linear(c_in, c_out)
        if kind == "gpool":
            self.score = nn.Parameter(torch.randn(c_in) / math.sqrt(c_in))

    def forward(self, x, prob, image: int):
        b, n, _ = x.shape
        k = (n + 1) // 2
        if self.kind == "random":
            seed = 4 * self.seed + 2 * self.index + image
            idx = torch.tensor(splitmix64_indices(n, k, seed), device=x.device).expand(b, k)
            gate = None
        else:
            if self.kind == "attentional":
                s = prob.sum(-2).mean(1)  # column sums, mean over heads: [B, K]
            else:
                s = x @ self.score / self.score.norm()
            # Descending, ties by lower index: a stable sort of −s.
            idx = torch.sort(-s, dim=-1, stable=True).indices[:, :k]
            gate = torch.sigmoid(s.gather(1, idx))[..., None]
        rows = x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))
        out = self.proj(rows)
        return (out if gate is None else out * gate), idx


class Unpool(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.proj = nn.Linear(c_in, c_out)

    def forward(self, x, idx, skip):
        u = self.proj(x)
        return torch.zeros_like(skip).scatter(1, idx[..., None].expand(-1, -1, u.shape[-1]), u) + skip


class Stage(nn.Module):
    def __init__(self, c: int, depth: int, heads: int, switches: dict):
        super().__init__()
        self.layers = nn.ModuleList([ParallelLayer(c, heads, switches) for _ in range(depth)])

    def forward(self, x, y, need_probs: bool = False):
        """``need_probs``: the last layer's self-attention probabilities are returned."""
        probs = None
        for i, layer in enumerate(self.layers):
            x, y, probs = layer(x, y, need_probs and i == len(self.layers) - 1)
        return x, y, probs


def log_optimal_transport(scores, bin_score, iters: int):
    """SPEC §8 log-domain Sinkhorn with dustbins; ``scores`` ``[B, M, N]``."""
    b, m, n = scores.shape
    one = scores.new_tensor(1)
    ms, ns = m * one, n * one
    bins0 = bin_score.expand(b, m, 1)
    bins1 = bin_score.expand(b, 1, n)
    alpha = bin_score.expand(b, 1, 1)
    z = torch.cat([torch.cat([scores, bins0], -1), torch.cat([bins1, alpha], -1)], 1)
    norm = -(ms + ns).log()
    log_mu = torch.cat([norm.expand(m), ns.log()[None] + norm]).expand(b, -1)
    log_nu = torch.cat([norm.expand(n), ms.log()[None] + norm]).expand(b, -1)
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(z + u[:, :, None], dim=1)
    return z + u[:, :, None] + v[:, None, :] - norm


def _couplings(scores, bin_score):
    b, m, n = scores.shape
    one = scores.new_tensor(1)
    ms, ns = m * one, n * one
    z = torch.cat([torch.cat([scores, bin_score.expand(b, m, 1)], -1),
                   torch.cat([bin_score.expand(b, 1, n), bin_score.expand(b, 1, 1)], -1)], 1)
    norm = -(ms + ns).log()
    log_mu = torch.cat([norm.expand(m), ns.log()[None] + norm]).expand(b, -1)
    log_nu = torch.cat([norm.expand(n), ms.log()[None] + norm]).expand(b, -1)
    return z, log_mu, log_nu, norm


def _log_domain_potentials(z, log_mu, log_nu, iters: int):
    """SPEC §8 iterations in the log domain from u = v = 0: the fallback of the scaling domain."""
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(z + u[:, :, None], dim=1)
    return u, v


@torch.no_grad()
def _sinkhorn_potentials(z, log_mu, log_nu, iters: int):
    """``iters`` SPEC §8 iterations from u = v = 0 without autograd, in the scaling domain
    (one exp, then matrix–vector products; rows and columns stabilised by their maxima, so
    every row and column of the kernel holds a 1); falls back to the log domain if a
    scaling leaves float32's range."""
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    if iters <= 0:
        return u, v
    if z.is_cuda:
        return _sinkhorn_potentials_torch(z, log_mu, log_nu, iters)
    r = z.amax(2, keepdim=True)
    c = (z - r).amax(1, keepdim=True)
    # numpy's batched matrix–vector product is ~8x faster than torch.bmm's on CPU here.
    k = (z - r - c).exp().cpu().numpy()
    kt = np.ascontiguousarray(k.transpose(0, 2, 1))
    mu, nu = log_mu.exp().cpu().numpy(), log_nu.exp().cpu().numpy()
    bvec = c[:, 0, :].exp().cpu().numpy()
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        for _ in range(iters):
            a = mu / np.matmul(k, bvec[..., None])[..., 0]
            bvec = nu / np.matmul(kt, a[..., None])[..., 0]
        us = torch.from_numpy(np.log(a)).to(z) - r[..., 0]
        vs = torch.from_numpy(np.log(bvec)).to(z) - c[:, 0, :]
    if torch.isfinite(us).all() and torch.isfinite(vs).all():
        return us, vs
    return _log_domain_potentials(z, log_mu, log_nu, iters)


@torch.no_grad()
def _sinkhorn_potentials_torch(z, log_mu, log_nu, iters: int):
    """``_sinkhorn_potentials`` in torch on any device (a GPU: the kernel is read twice per
    iteration instead of the log domain's many passes)."""
    u = torch.zeros_like(log_mu)
    v = torch.zeros_like(log_nu)
    if iters <= 0:
        return u, v
    r = z.amax(2, keepdim=True)
    c = (z - r).amax(1, keepdim=True)
    k = (z - r - c).exp()
    mu, nu = log_mu.exp(), log_nu.exp()
    b = c[:, 0, :].exp()
    for _ in range(iters):
        a = mu / torch.bmm(k, b[..., None])[..., 0]
        b = nu / torch.bmm(k.transpose(1, 2), a[..., None])[..., 0]
    us, vs = a.log() - r[..., 0], b.log() - c[:, 0, :]
    if bool(torch.isfinite(us).all() & torch.isfinite(vs).all()):
        return us, vs
    return _log_domain_potentials(z, log_mu, log_nu, iters)


def log_optimal_transport_last_grad(scores, bin_score, iters: int, grad_iters: int = 1):
    """SPEC §8 Sinkhorn whose value equals ``log_optimal_transport`` (up to rounding) but
    whose gradient flows through the last ``grad_iters`` iterations only: the earlier ones
    run without autograd from the same start (a training approximation, A/B-tested in
    ``training/ab_sinkhorn_grad.py``)."""
    z, log_mu, log_nu, norm = _couplings(scores, bin_score)
    grad_iters = max(1, min(grad_iters, iters))
    u, v = _sinkhorn_potentials(z.detach(), log_mu, log_nu, iters - grad_iters)
    for _ in range(grad_iters):
        u = log_mu - torch.logsumexp(z + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(z + u[:, :, None], dim=1)
    return z + u[:, :, None] + v[:, None, :] - norm


def extract_matches(p, threshold: float):
    """SPEC §8 mutual-best matches from a log assignment ``[B, M+1, N+1]``."""
    inner = p[:, :-1, :-1]
    max0, max1 = inner.max(2), inner.max(1)
    idx0, idx1 = max0.indices, max1.indices
    ar0 = torch.arange(idx0.shape[1], device=p.device)[None]
    ar1 = torch.arange(idx1.shape[1], device=p.device)[None]
    mutual0 = ar0 == idx1.gather(1, idx0)
    mutual1 = ar1 == idx0.gather(1, idx1)
    zero = inner.new_tensor(0)
    score0 = torch.where(mutual0, max0.values.exp(), zero)
    score1 = torch.where(mutual1, score0.gather(1, idx1), zero)
    valid0 = mutual0 & (score0 > threshold)
    valid1 = mutual1 & valid0.gather(1, idx1)
    return {
        "matches0": torch.where(valid0, idx0, idx0.new_tensor(-1)),
        "matches1": torch.where(valid1, idx1, idx1.new_tensor(-1)),
        "matching_scores0": score0,
        "matching_scores1": score1,
    }


def pair_scores(proj: nn.Linear, x, y):
    """SPEC §8 score matrix ⟨proj(x_i), proj(y_j)⟩ / √C (fp32 even under bf16 autocast)."""
    with torch.autocast(x.device.type, enabled=False):
        mx, my = proj(x.to(proj.weight.dtype)), proj(y.to(proj.weight.dtype))
        return mx @ my.transpose(1, 2) / math.sqrt(mx.shape[-1])


class Matcher(nn.Module):
    """The whole network; ``config`` is a SPEC §9 dict (missing fields take defaults).
    ``self_rotary`` (LO, HI[, GAIN]): an experiment outside the SPEC, ParaFormer only (``SelfRotary``)."""

    def __init__(self, config: dict | None = None, self_rotary: tuple[float, ...] | None = None):
        super().__init__()
        cfg = self.config = resolve_config(config or {})
        c, heads = model_dim(cfg), cfg["num_heads"]
        if self_rotary is not None and cfg["model"] != "paraformer":
            raise ValueError(f"self rotary needs a paraformer model, not {cfg['model']!r}")
        if cfg["descriptor_dim"] != c:
            self.input_proj = nn.Linear(cfg["descriptor_dim"], c)
        if cfg["positional_encoding"] == "mlp":
            self.kenc = KeypointEncoder(c)
        else:
            self.wave_pe = WavePE(c)
        if cfg["model"] == "superglue":
            self.gnn = nn.Module()
            self.gnn.layers = nn.ModuleList([SerialLayer(c, heads, k) for k in cfg["layer_names"]])
        elif cfg["model"] == "paraformer":
            self.layers = nn.ModuleList([ParallelLayer(c, heads, cfg["parallel"]) for _ in range(cfg["num_layers"])])
        else:
            dims, depths = cfg["stage_dims"], cfg["stage_depths"]
            self.stages = nn.ModuleList([Stage(dims[s], depths[s], heads, cfg["parallel"]) for s in range(5)])
            self.pools = nn.ModuleList(
                [Pool(dims[p], dims[p + 1], cfg["pooling"], cfg["pooling_seed"], p) for p in range(2)])
            self.unpools = nn.ModuleList([Unpool(dims[q + 2], dims[q + 3]) for q in range(2)])
        self.final_proj = nn.Linear(c, c)
        self.bin_score = nn.Parameter(torch.tensor(1.0))
        if self_rotary is not None:
            self.self_rotary = SelfRotary(c // heads, *self_rotary)

    def encode(self, kpts, scores, desc, size):
        if hasattr(self, "input_proj"):
            desc = self.input_proj(desc)
        pos = normalize_keypoints(kpts, scores, size)
        enc = self.kenc if hasattr(self, "kenc") else self.wave_pe
        return enc(desc, pos)

    def body(self, x, y, rot=None):
        model = self.config["model"]
        if model == "superglue":
            for layer in self.gnn.layers:
                x, y = layer(x, y)
        elif model == "paraformer":
            x, y = self.layer_states(x, y, rot)[-1]
        else:
            skips, indices = [], []
            for p in range(2):
                x, y, probs = self.stages[p](x, y, need_probs=self.config["pooling"] == "attentional")
                px, py = probs if probs is not None else (None, None)
                skips.append((x, y))
                (x, ix), (y, iy) = self.pools[p](x, px, 0), self.pools[p](y, py, 1)
                indices.append((ix, iy))
            for q in range(2):
                x, y, _ = self.stages[2 + q](x, y)
                (sx, sy), (ix, iy) = skips[1 - q], indices[1 - q]
                x, y = self.unpools[q](x, ix, sx), self.unpools[q](y, iy, sy)
            x, y, _ = self.stages[4](x, y)
        return x, y

    def encode_pair(self, data: dict):
        x = self.encode(data["keypoints0"], data["scores0"], data["descriptors0"], data["image_size0"])
        y = self.encode(data["keypoints1"], data["scores1"], data["descriptors1"], data["image_size1"])
        return x, y

    def rotations(self, data: dict):
        """The ``SelfRotary`` encodings of both images, or None (every SPEC model)."""
        if not hasattr(self, "self_rotary"):
            return None
        return tuple(self.self_rotary(normalize_keypoints(data[f"keypoints{i}"], data[f"scores{i}"],
                                                          data[f"image_size{i}"])) for i in (0, 1))

    def scores(self, data: dict):
        return pair_scores(self.final_proj, *self.body(*self.encode_pair(data), self.rotations(data)))

    def layer_states(self, x, y, rot=None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """ParaFormer only: the features of both images after every layer, from the encoded
        ``x, y`` (the last entry is what ``body`` returns); training puts a loss on each."""
        if self.config["model"] != "paraformer":
            raise ValueError(f"layer_states needs a paraformer model, not {self.config['model']!r}")
        states = []
        for layer in self.layers:
            x, y, _ = layer(x, y, need_probs=False, rot=rot)
            states.append((x, y))
        return states

    def forward(self, data: dict, sinkhorn_iterations: int | None = None) -> dict:
        """``data``: batched ``keypoints0/1`` [B,K,2], ``scores0/1`` [B,K], ``descriptors0/1``
        [B,K,D], ``image_size0/1`` [B,2]. Returns ``log_assignment`` and the matches."""
        iters = self.config["sinkhorn_iterations"] if sinkhorn_iterations is None else sinkhorn_iterations
        p = log_optimal_transport(self.scores(data), self.bin_score, iters)
        return {"log_assignment": p, **extract_matches(p, self.config["match_threshold"])}
