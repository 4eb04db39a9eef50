"""Trains one matcher on the endless pair stream, resumably, for as many pairs as asked.

    python training/train.py --run training/checkpoints/paraformer-xfeat --preset paraformer \
        --dim 64 --heads 1 --depth 4 --pairs 600000

``--run`` (committed): ``config.json``, ``last.pt`` (weights, optimiser, counters, stream
cursor; rewritten at least every ``--ckpt-minutes``) and ``log.jsonl`` (the learning
curve). ``--work`` (not committed, default ``training/runs/<name>``): the pair pool, the
generator's log and ``best.safetensors``; the holdout pairs live in ``training/cache/holdout``. Rerunning the same command,
on this machine or a fresh clone, resumes from ``last.pt``: the generator restarts at the
stream cursor and regenerates any shard that was not finished (pairs are seeded).

Speed (see ``bench_step.py``): fused SDPA attention and gradients through the last
Sinkhorn iteration only (the earlier ones in the scaling domain without autograd);
``--bf16`` runs the network's forward under bfloat16 autocast.
Keypoint counts vary per step (``--keypoints``), with the batch shrunk so that each step
costs about the same.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import torch
from torch import nn

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train import data, model as model_mod, stream  # noqa: E402
from paraformer_train.io import save_safetensors  # noqa: E402
from paraformer_train.teacher import LighterGlueTeacher, distillation_loss, hint_loss, ridge_map, standardize  # noqa: E402
from paraformer_train.model import (Matcher, extract_matches, log_optimal_transport,  # noqa: E402
                                    log_optimal_transport_last_grad, pair_scores)
from paraformer_train.lightglue_arm import LightGlueArm, is_arm  # noqa: E402
from paraformer_train.lighterglue_transplant import self_closed  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
MODEL_ARGS = ("preset", "dim", "heads", "depth", "sinkhorn", "seed", "unshare", "stage_dims", "stage_depths",
              "pooling", "self_rotary")
# A resume refuses a change of these (the model's, and --layer-loss, whose heads are in the
# optimiser's state); runs saved before an argument existed trained with its default here.
RESUME_ARGS = MODEL_ARGS + ("layer_loss", "lr_scale_from", "serial")
RESUME_DEFAULTS = {"unshare": [], "layer_loss": False, "stage_dims": None, "stage_depths": None, "pooling": None,
                   "lr_scale_from": None,
                   "self_rotary": None, "serial": False}
SHARING = ("qkv", "merge", "attention_weights")


def cpu_flags(cpuinfo: str | None = None) -> set[str] | None:
    """The CPU's feature flags from ``/proc/cpuinfo`` (x86 ``flags``, Arm ``Features``); None
    where that cannot be read or names none."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            return None
    flags = set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() in ("flags", "features"):
            flags.update(value.split())
    return flags or None


def cpu_has_bf16(cpuinfo: str | None = None) -> bool | None:
    """Whether the CPU computes bf16 natively (x86 AVX512-BF16 or AMX-BF16, Arm BF16), from
    ``/proc/cpuinfo``; None where that cannot be read. Without it PyTorch emulates bf16 and
    ``--bf16`` costs instead of paying: 10.8 s against 2.2 s per w96 step at 2048 x 2 on an
    AVX2-only Zen 3 (bench_step.py, one run)."""
    flags = cpu_flags(cpuinfo)
    return None if flags is None else bool(flags & {"avx512_bf16", "amx_bf16", "bf16"})


def native_attention_pays(cpuinfo: str | None = None) -> bool:
    """Whether ``--native-attention`` (the engine's AVX-512 BF16 kernels) beats PyTorch's bf16
    SDPA here: not on CPUs with AMX-BF16, where PyTorch's bf16 products run on AMX tiles (w96
    step on a Xeon Sapphire Rapids, bench_step.py: native 0.996 s and bf16 SDPA 1.000 s at
    512 x 8, 2.24 and 1.84 s at 2048 x 2; on a Zen 5 without AMX the native step was 1.4x
    faster)."""
    flags = cpu_flags(cpuinfo)
    return flags is None or "amx_bf16" not in flags


def preset(name: str, dim: int, depth: int, heads: int) -> dict:
    """The models at one width and depth (paper Table 3 + the U variant)."""
    common = {"descriptor_dim": 64, "num_heads": heads}
    if name == "superglue":
        return common | {"model": "superglue", "dim": dim, "layer_names": ["self", "cross"] * depth}
    if name == "parallel_mlp":
        return common | {"model": "paraformer", "dim": dim, "num_layers": depth, "positional_encoding": "mlp"}
    if name == "paraformer":
        return common | {"model": "paraformer", "dim": dim, "num_layers": depth}
    if name == "lightglue_arm":  # a diagnostic outside the SPEC (paraformer_train/lightglue_arm.py)
        return common | {"model": "lightglue_arm", "dim": dim, "num_layers": depth}
    if name == "paraformer_u":
        # SPEC default widths (256, 384, 128, 384, 256) scaled by dim / 256.
        dims = [dim * w // 256 for w in (256, 384, 128, 384, 256)]
        return common | {"model": "paraformer_u", "stage_dims": dims, "stage_depths": [1, 1, 2, 1, 1]}
    raise ValueError(f"unknown preset {name!r}")


def model_config(args: dict) -> dict:
    """The model config of a run from its arguments (``MODEL_ARGS``; as saved in checkpoints).
    ``unshare`` lists the parallel layers' sharing switches turned off (SPEC §5)."""
    cfg = preset(args["preset"], args["dim"], args["depth"], args["heads"]) | {"sinkhorn_iterations": args["sinkhorn"]}
    dims, depths, pooling = args.get("stage_dims"), args.get("stage_depths"), args.get("pooling")
    if (dims or depths or pooling) and cfg["model"] != "paraformer_u":
        raise ValueError(f"stage_dims, stage_depths and pooling are ParaFormer-U's; the {args['preset']!r} preset has none")
    if depths:
        if len(depths) != 5 or any(not isinstance(d, int) or d < 1 for d in depths):
            raise ValueError(f"stage_depths {depths}: expected five layer counts >= 1")
        cfg["stage_depths"] = list(depths)
    if dims:
        if len(dims) != 5 or dims[0] != args["dim"] or dims[4] != args["dim"]:
            raise ValueError(f"stage_dims {dims}: expected five widths that begin and end with dim {args['dim']}")
        cfg["stage_dims"] = list(dims)
    # The preset's scaled widths as well as given ones: each stage splits into the heads.
    if any(d % args["heads"] for d in cfg.get("stage_dims", [])):
        raise ValueError(f"stage widths {cfg['stage_dims']}: every width must be a multiple of heads {args['heads']}")
    if pooling:
        cfg["pooling"] = pooling
    unshare = args.get("unshare") or []
    if unshare:
        bad = sorted(set(unshare) - set(SHARING))
        if bad:
            raise ValueError(f"unshare: unknown sharing switches {bad}; expected some of {list(SHARING)}")
        if cfg["model"] == "superglue":
            raise ValueError(f"unshare: the {args['preset']!r} preset has no parallel layers")
        cfg["parallel"] = {f"share_{k}": k not in unshare for k in SHARING}
    return cfg


def phase_gain_init(model: Matcher, lo: float, hi: float) -> None:
    """Multiplies row j of the Wave-PE phase MLP's last Linear (weight and bias) by gains
    spaced geometrically from ``lo`` to ``hi``: each channel starts at its own spatial
    frequency (Fourier-feature style) instead of PyTorch's ~1 rad per 100 px, which
    training flattens to ~0.1. Only the initial weights change: the architecture and the
    SPEC are the same. (Tried at 2..100: it trained worse; training/README "Geometry".)"""
    if not hasattr(model, "wave_pe"):
        raise ValueError("--phase-gain needs a Wave-PE model (preset paraformer or paraformer_u)")
    last = model.wave_pe.phase[-1]
    gain = torch.logspace(math.log10(lo), math.log10(hi), last.out_features)
    with torch.no_grad():
        last.weight.mul_(gain[:, None])
        last.bias.mul_(gain)


def build_model(cfg: dict, self_rotary) -> Matcher | LightGlueArm:
    """The run's network: a SPEC ``Matcher`` or the ``lightglue_arm`` diagnostic."""
    if cfg["model"] == "lightglue_arm":
        if self_rotary is not None:
            raise ValueError("--self-rotary is ParaFormer's; the lightglue_arm preset has its own rotary encoding")
        return LightGlueArm(cfg)
    return Matcher(cfg, self_rotary)


def export(model: Matcher | LightGlueArm, path: str) -> None:
    """The EMA weights as a weights file; a model outside the SPEC (``--self-rotary``, the
    ``lightglue_arm`` preset) has none, and its checkpoint's ``ema`` holds them instead."""
    if hasattr(model, "self_rotary") or is_arm(model):
        print(f"not written: {path} (the model is outside the SPEC; the checkpoint holds the weights)", flush=True)
        return
    save_safetensors(model, path)


def init_weights(path: str, config: dict) -> dict:
    """The state dict a run starts from: a checkpoint's EMA weights, or a weights file's
    (e.g. the shipped ``paraformer-xfeat.safetensors``), whose architecture must be the run's."""
    if path.endswith(".safetensors"):
        from paraformer_train.io import load_safetensors

        other = load_safetensors(path)
        # Sharing switches may differ: load_init copies shared tensors into unshared ones.
        keys = [k for k in config if k not in ("match_threshold", "sinkhorn_iterations", "parallel")]
        diff = {k: (other.config.get(k), config[k]) for k in keys if other.config.get(k) != config[k]}
        if diff:
            raise SystemExit(f"error: --init {path} has another architecture (file, run): {diff}")
        return other.state_dict()
    init = torch.load(path, map_location="cpu", weights_only=False)
    return init.get("ema", init["model"])


def unshare_state(state: dict, own: dict) -> dict:
    """``state`` with shared q/k/v projections or merges (``attn.proj.*``, ``attn.merge.*``)
    copied into both the self and the cross tensors where the model has them separate (SPEC
    §5 switches off): the unshared model starts as the shared one and computes the same."""
    out = {}
    for key, value in state.items():
        split = [key.replace(".attn.", f".attn.{side}_") for side in ("self", "cross")]
        if (".attn.proj." in key or ".attn.merge." in key) and key not in own and all(k in own for k in split):
            out.update({k: value.clone() for k in split})
        else:
            out[key] = value
    return out


def load_init(model: Matcher, state: dict, copy_scale: float | None = None) -> list[int]:
    """Loads ``state`` into ``model``. A ParaFormer with more layers than ``state`` is grown:
    the init's layers come first and each new layer's last fuse Linear is zero, so that its
    residual passes the features through and the grown model computes what the init did.
    With ``copy_scale`` the new layers instead start as copies of the init's last layers (in
    order) with that last Linear scaled by ``copy_scale``: trained features from the first
    step, so that every weight of the new layer gets a gradient (a zero Linear passes none to
    the weights before it), at a small change of the init's output.
    Shared q/k/v or merges of the init become equal self and cross copies where the model
    has them separate (``unshare_state``). Returns the indices of the new layers."""
    own = model.state_dict()
    state = unshare_state(state, own)
    # A --self-rotary run from SPEC weights: the encoding keeps its own start (identity with a gain).
    state = {k: v for k, v in own.items() if k.startswith("self_rotary.") and k not in state} | state
    new = sorted({int(k.split(".")[1]) for k in own if k.startswith("layers.")}
                 - {int(k.split(".")[1]) for k in state if k.startswith("layers.")})
    if copy_scale is not None and (model.config["model"] != "paraformer" or not new):
        raise SystemExit("error: --grow-copy needs a ParaFormer --init with fewer layers than --depth")
    if model.config["model"] == "paraformer_u" and any(k.startswith("layers.") for k in state):
        return u_from_paraformer(model, state)
    if model.config["model"] != "paraformer" or not new:
        model.load_state_dict(state)
        return []
    if new != list(range(new[0], len(model.layers))):
        raise SystemExit(f"error: --init has layers the run lacks or a gap before {new[0]}")
    missing, unexpected = model.load_state_dict(state, strict=False)
    stray = [k for k in missing if not any(k.startswith(f"layers.{i}.") for i in new)]
    if stray or unexpected:
        raise SystemExit(f"error: --init does not match the run beyond its depth: missing {stray}, unexpected {unexpected}")
    if copy_scale is not None and len(new) > new[0]:
        raise SystemExit(f"error: --grow-copy needs at least as many init layers ({new[0]}) as new ones ({len(new)})")
    with torch.no_grad():
        for j, i in enumerate(new):
            if copy_scale is not None:
                source = new[0] - len(new) + j
                model.layers[i].load_state_dict(model.layers[source].state_dict())
            last = model.layers[i].fuse[-1]
            for t in (last.weight, last.bias):
                t.mul_(copy_scale) if copy_scale is not None else t.zero_()
    return new


def u_from_paraformer(model: Matcher, state: dict, outer: tuple[int, int] = (0, 2)) -> list[str]:
    """Warm-starts a ParaFormer-U from a ParaFormer of its outer width: the encoder, head and
    dustbin are copied, its first and last stage (one layer each) take the ParaFormer's
    layers ``outer``, and the unpooling back to the outer width starts at zero, so that the
    inner stages are silent and the U computes those two layers of the ParaFormer. The inner
    stages and poolings start fresh and learn from there. Returns the fresh modules.
    The default pair had the lowest validation loss @512 of the six from the 4-layer w96 line
    at 290k pairs (64 holdout pairs): (0, 2) 1.90, (1, 3) 2.07, (1, 2) 2.99, (2, 3) 3.31,
    (0, 3) 3.57, (0, 1) 13.2; the line itself 0.91."""
    depths = model.config["stage_depths"]
    if depths[0] != 1 or depths[4] != 1:
        raise SystemExit(f"error: --init ParaFormer into a U needs outer stages of one layer, not {depths}")
    n = 1 + max(int(k.split(".")[1]) for k in state if k.startswith("layers."))
    outer = tuple(i % n for i in outer)
    mapped = {}
    for key, value in state.items():
        if not key.startswith("layers."):
            mapped[key] = value
            continue
        layer, rest = key.split(".", 2)[1:]
        for stage, src in ((0, outer[0]), (4, outer[1])):
            if int(layer) == src:
                mapped[f"stages.{stage}.layers.0.{rest}"] = value
    missing, unexpected = model.load_state_dict(mapped, strict=False)
    fresh = sorted({".".join(k.split(".")[:2]) for k in missing})
    stray = [k for k in missing if not k.startswith(("stages.1.", "stages.2.", "stages.3.", "pools.", "unpools."))]
    if stray or unexpected:
        raise SystemExit(f"error: --init does not fit the U's outer stages: missing {stray}, unexpected {unexpected}")
    with torch.no_grad():
        model.unpools[-1].proj.weight.zero_()
        model.unpools[-1].proj.bias.zero_()
    return fresh


def lr_scale_unpool_groups(model: Matcher, groups: list[dict], scale: float) -> list[dict]:
    """``groups`` with a ParaFormer-U's unpooling projections moved to a group of their own at
    ``scale`` × the rate: started at zero by a transplant, under Adam's steps of about the rate
    they open far slower than the inner stages, whose work they carry, could use."""
    if not hasattr(model, "unpools"):
        raise ValueError("needs a ParaFormer-U (preset paraformer_u)")
    if not scale > 0:
        raise ValueError(f"expected SCALE > 0, got {scale:g}")
    fast = {id(p) for p in model.unpools.parameters()}
    kept = [g | {"params": [p for p in g["params"] if id(p) not in fast]} for g in groups]
    return kept + [{"params": list(model.unpools.parameters()), "lr_scale": float(scale)}]


def lr_scale_groups(model: Matcher, params: list, first: float, scale: float) -> list[dict]:
    """Optimiser groups in which ParaFormer layers ``first`` onwards learn at ``scale`` × the
    rate: layers grown as identity by ``--init`` start at zero and, under Adam's steps of about
    the rate, would take far longer than the trained layers around them to matter."""
    if not hasattr(model, "layers"):
        raise ValueError("needs a ParaFormer (preset paraformer)")
    if not float(first).is_integer() or not 0 < first < len(model.layers) or not scale > 0:
        raise ValueError(f"expected LAYER a whole number in 1..{len(model.layers) - 1} and SCALE > 0, got {first:g} {scale:g}")
    fast = {id(p) for layer in model.layers[int(first):] for p in layer.parameters()}
    return [{"params": [p for p in params if id(p) not in fast], "lr_scale": 1.0},
            {"params": [p for p in params if id(p) in fast], "lr_scale": float(scale)}]


class LayerHeads(nn.Module):
    """Training-only assignment heads (projection + dustbin score) for every layer but the
    last, which has the model's own: a loss on every layer, as LightGlue trains. They start
    as copies of the model's head and are never exported."""

    def __init__(self, model: Matcher):
        super().__init__()
        n = len(model.layers) - 1
        self.proj = nn.ModuleList([nn.Linear(model.final_proj.in_features, model.final_proj.out_features)
                                   for _ in range(n)])
        self.bin_score = nn.Parameter(torch.ones(n))
        self.copy_from(model)

    @torch.no_grad()
    def copy_from(self, model: Matcher) -> None:
        for p in self.proj:
            p.load_state_dict(model.final_proj.state_dict())
        self.bin_score.fill_(model.bin_score.item())

    def heads(self, model: Matcher) -> list:
        return [(p, self.bin_score[i]) for i, p in enumerate(self.proj)] + [(model.final_proj, model.bin_score)]


class HintAdapters(nn.Module):
    """Training-only maps from student layers' features to the teacher layer each is asked to
    resemble (``--hint``): student layer k of L takes LighterGlue's layer ceil((k+1)·6/L)
    (4 layers: 2, 3, 5, 6), so that both nets' depths line up. ``serial``: the LighterGlue
    transplant's layout (``--serial``), where layer 2i+1 ends LighterGlue's layer i (its self
    block is layer 2i): only the odd layers get hints, each from its own teacher layer. Never
    exported."""

    TEACHER_LAYERS, TEACHER_DIM = 6, 96

    def __init__(self, model: Matcher, serial: bool = False):
        super().__init__()
        n, c = len(model.layers), model.final_proj.in_features
        if serial and n % 2:
            raise ValueError(f"--serial hints pair layers 2i+1 with the teacher's layer i: {n} layers is odd")
        self.layers = [k for k in range(n) if self_closed(k)] if serial else list(range(n))
        m = len(self.layers)
        self.pick = [math.ceil((k + 1) * self.TEACHER_LAYERS / m) - 1 for k in range(m)]
        self.maps = nn.ModuleList([nn.Linear(c, self.TEACHER_DIM) for _ in range(m)])

    def hinted(self, states: list[tuple[torch.Tensor, torch.Tensor]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The features of the hinted layers, out of every layer's (``log_assignments`` states)."""
        return [states[k] for k in self.layers]

    @torch.no_grad()
    def fit(self, student: list[tuple[torch.Tensor, torch.Tensor]], teacher: list[tuple[torch.Tensor, torch.Tensor]],
            ridge: float = 1e-3) -> None:
        """Least-squares maps from one batch's hinted student features to the teacher's picked
        layers: a start for --init runs (and hints added at a resume), whose trained features
        random maps would first pull about."""
        for (x, y), m, t in zip(student, self.maps, self.pick):
            a = torch.cat([x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1])]).float()
            b = torch.cat([u.reshape(-1, self.TEACHER_DIM) for u in standardize(*teacher[t])])
            w = ridge_map(a, b, ridge)  # [C + 1, 96]
            m.weight.copy_(w[:-1].T)
            m.bias.copy_(w[-1])


def group_names(groups: list[dict], names: dict[int, str]) -> list[list[str]]:
    """The parameters' names (``names``, by id) of each optimiser group, as checkpoints keep them."""
    return [[names[id(p)] for p in g["params"]] for g in groups]


def regrouped_state(opt: torch.optim.Optimizer, saved: dict, saved_names: list[list[str]],
                    names: dict[int, str]) -> dict:
    """``saved`` (an optimiser state whose groups held the parameters named ``saved_names``)
    rearranged for ``opt``'s groups: each parameter keeps its Adam moments, found by name, and
    each group this run's hyper-parameters (its ``lr_scale``). Unchanged where the groups are
    the same. ValueError when the two hold different parameters."""
    now = group_names(opt.param_groups, names)
    if now == saved_names:
        return saved
    flat_saved, flat_now = [n for g in saved_names for n in g], [n for g in now for n in g]
    if sorted(flat_saved) != sorted(flat_now):
        extra, missing = set(flat_saved) - set(flat_now), set(flat_now) - set(flat_saved)
        raise ValueError(f"saved parameters not in this run: {sorted(extra)[:3]}, "
                         f"this run's not saved: {sorted(missing)[:3]}")
    at = {n: i for i, n in enumerate(flat_saved)}
    mine = opt.state_dict()  # this run's groups; parameters numbered in group order
    mine["state"] = {j: saved["state"][at[n]] for j, n in enumerate(flat_now) if at[n] in saved["state"]}
    return mine


def resume_optimizer(opt: torch.optim.Optimizer, saved: dict | None, hint_group: dict | None,
                     had_hints: bool, names: dict[int, str] | None = None,
                     saved_names: list[list[str]] | None = None) -> bool:
    """Loads a checkpoint's optimiser state (``saved``; None on a fresh start) into ``opt`` (the
    model's groups). The hint maps' group (``hint_group``, None without --hint) keeps its state
    where the checkpoint trained them (``had_hints``) and otherwise joins after the load, fresh:
    hints added at a resume, or at the start. Given the parameters' ``names`` (by id) and the
    checkpoint's groups by name (``saved_names``), a run resumed with other learning-rate groups
    (--lr-scale-unpool) keeps each parameter's state. True when the maps are new. ValueError
    when the state does not fit the groups (a hinted run resumed without --hint)."""
    if hint_group is not None and had_hints:
        opt.add_param_group(hint_group)
    if saved is not None:
        if names is not None and saved_names is not None:
            saved = regrouped_state(opt, saved, saved_names, names)
        opt.load_state_dict(saved)
    if hint_group is not None and not had_hints:
        opt.add_param_group(hint_group)
        return True
    return False


def log_assignments(model: Matcher | LightGlueArm, heads: LayerHeads | None, bt: dict, sinkhorn, iters: int,
                    bf16: bool = False, states: list | None = None, every_layer: bool = False) -> list[torch.Tensor]:
    """The log-assignment of the last layer, or with ``heads`` of every layer (last one last).
    ``bf16``: the network's forward (not Sinkhorn) under CPU bfloat16 autocast. ``states``: a
    list that receives every layer's ``(x, y)`` features (ParaFormer only; for ``--hint``).
    The ``lightglue_arm`` has its own heads and no Sinkhorn: ``every_layer`` asks for all of them."""
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        if is_arm(model):
            return model.assignments(bt, every_layer)
        if heads is None and states is None:
            scores = [(model.scores(bt), model.bin_score)]
        else:
            layers = model.layer_states(*model.encode_pair(bt), model.rotations(bt))
            if states is not None:
                states.extend(layers)
            if heads is None:
                scores = [(pair_scores(model.final_proj, *layers[-1]), model.bin_score)]
            else:
                scores = [(pair_scores(proj, x, y), b) for (x, y), (proj, b) in zip(layers, heads.heads(model))]
    return [sinkhorn(s.float(), b, iters) for s, b in scores]


def final_log_assignment(model: Matcher | LightGlueArm, bt: dict) -> torch.Tensor:
    """The model's own log assignment, as its users get it: the arm's last head, or SPEC §8
    Sinkhorn at the config's iterations (the value of ``log_optimal_transport``, far faster at
    2048 keypoints in the scaling domain)."""
    if is_arm(model):
        return model.assignments(bt)[-1]
    return log_optimal_transport_last_grad(model.scores(bt), model.bin_score, model.config["sinkhorn_iterations"])


def matching_losses(model: Matcher, heads: LayerHeads | None, bt: dict, sinkhorn, iters: int,
                    bf16: bool = False, counts: tuple[int, int] | None = None) -> list[torch.Tensor]:
    """The assignment NLL of ``log_assignments``' layers. ``counts``: see ``nll_loss`` (a
    data-parallel share of a batch)."""
    return [nll_loss(logp, bt["gt0"], bt["gt1"], counts) for logp in log_assignments(model, heads, bt, sinkhorn, iters, bf16)]


def label_counts(bt: dict) -> tuple[int, int]:
    """(positives, unmatched keypoints of both images) of a batch: ``nll_loss``'s denominators."""
    return int((bt["gt0"] >= 0).sum()), int((bt["gt0"] == -1).sum() + (bt["gt1"] == -1).sum())


def nll_loss(logp: torch.Tensor, gt0: torch.Tensor, gt1: torch.Tensor,
             counts: tuple[int, int] | None = None) -> torch.Tensor:
    """Assignment NLL with dustbins: 0.5 · mean over positives + 0.5 · mean over unmatched
    keypoints of both images; ignored keypoints (−2) are left out. Masked sums, no
    boolean indexing: no host synchronisation on a GPU. ``counts`` (``label_counts`` of the
    whole batch) divides by those instead of this part's own, so that the losses of the parts
    of a split batch sum to the whole batch's loss."""
    pos, un0, un1 = gt0 >= 0, gt0 == -1, gt1 == -1
    pos_ll = logp[:, :-1, :].gather(2, gt0.clamp(min=0)[..., None])[..., 0]
    neg_sum = torch.where(un0, logp[:, :-1, -1], 0.0).sum() + torch.where(un1, logp[:, -1, :-1], 0.0).sum()
    if counts is None:
        n_pos, n_un = pos.sum().clamp(min=1), (un0.sum() + un1.sum()).clamp(min=1)
    else:
        n_pos, n_un = max(counts[0], 1), max(counts[1], 1)
    return 0.5 * -torch.where(pos, pos_ll, 0.0).sum() / n_pos + 0.5 * -neg_sum / n_un


def precision_recall(pred0: torch.Tensor, gt0: torch.Tensor) -> tuple[int, int, int]:
    """(true positives, predicted matches, ground-truth matches) over non-ignored keypoints."""
    keep = gt0 != -2
    predicted = (pred0 >= 0) & keep
    tp = (predicted & (pred0 == gt0)).sum().item()
    return tp, predicted.sum().item(), (gt0 >= 0).sum().item()


def prf(tp: int, npred: int, ngt: int) -> tuple[float, float, float]:
    """Precision, recall and F1 (fractions) of ``precision_recall``'s counts."""
    p, r = tp / max(npred, 1), tp / max(ngt, 1)
    return p, r, 2 * p * r / max(p + r, 1e-12)


def ema_decay(decay: float, step: int, warmup: bool) -> float:
    """The EMA's per-step decay; with ``warmup`` at most (1 + step) / (10 + step), so that a run
    from scratch does not keep decay^step of its random init (0.999: 19% after 1,672 steps)."""
    return min(decay, (1 + step) / (10 + step)) if warmup else decay


DECAY_FROM = 0.6  # the cosine's default start, as a fraction of --pairs


def lr_at(pairs: int, total: int, warmup: int, peak: float, decay_from: float = DECAY_FROM) -> float:
    """Linear warm-up over ``warmup`` pairs, constant, then cosine to 10% over the last
    ``1 − decay_from`` of ``total`` pairs."""
    if pairs < warmup:
        return peak * (pairs + 1) / warmup
    start = decay_from * total
    if pairs < start:
        return peak
    t = min(1.0, (pairs - start) / max(total - start, 1))
    return peak * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * t)))


def parse_schedule(text: str) -> list[tuple[int, int, float]]:
    """``"512x8:0.5,1024x4:0.3,2048x2:0.2"`` → [(keypoints, batch, probability)]."""
    out = []
    for part in text.split(","):
        kb, p = part.split(":")
        k, b = kb.split("x")
        out.append((int(k), int(b), float(p)))
    total = sum(p for _, _, p in out)
    return [(k, b, p / total) for k, b, p in out]


@torch.no_grad()
def validate(model: Matcher, shards: list[stream.Shard], keypoints: int, threshold: float, auc: bool) -> dict:
    """Loss, P/R/F1 at ``threshold`` over the holdout pairs cut to ``keypoints``, in all and per
    kind (``_synthetic``, ``_real``: the real part is where repeated RGB-D pairs could be
    memorised); with ``auc``, homography AUC@5px (corner error, RANSAC 3 px) over the synthetic ones."""
    from paraformer import geometry as g
    from paraformer_train.evalsets import corner_error

    model.eval()
    # Per kind (0 synthetic, 1 real): summed loss, pairs, true positives, predictions, ground truth.
    sums = {k: [0.0, 0, 0, 0, 0] for k in (0, 1)}
    errors = []
    for shard in shards:
        for i in range(len(shard)):
            bt = stream.collate([(shard, i)], keypoints, [False])
            logp = final_log_assignment(model, bt)
            pred = extract_matches(logp, threshold)["matches0"]
            s = sums[int(shard.kind[i])]
            s[0] += nll_loss(logp, bt["gt0"], bt["gt1"]).item()
            s[1] += 1
            for j, v in enumerate(precision_recall(pred, bt["gt0"])):
                s[2 + j] += v
            if auc and shard.kind[i] == 0:
                m0 = pred[0].numpy()
                ok = m0 >= 0
                w, h = shard.image_size[i][0]
                errors.append(corner_error(bt["keypoints0"][0].numpy()[ok], bt["keypoints1"][0].numpy()[m0[ok]],
                                           shard.H[i], w, h))
    model.train()
    out = {}
    for suffix, kinds in (("", (0, 1)), ("_synthetic", (0,)), ("_real", (1,))):
        loss, n, tp, npred, ngt = (sum(sums[k][j] for k in kinds) for j in range(5))
        if n == 0:
            continue
        p, r, f1 = prf(tp, npred, ngt)
        out |= {f"val_loss{suffix}@{keypoints}": loss / n, f"precision{suffix}@{keypoints}": p,
                f"recall{suffix}@{keypoints}": r, f"f1{suffix}@{keypoints}": f1}
    if auc:
        # Exact AUC of the corner-error CDF up to t px (the evaluation harness's rule).
        for t, a in zip((1, 3, 5), g.pose_auc(errors, (1, 3, 5))):
            out[f"auc{t}px@{keypoints}"] = float(a)
    return out


def start_generator(args, work: str, cursor: int) -> subprocess.Popen:
    log = open(os.path.join(work, "generator.log"), "a")
    cmd = [sys.executable, os.path.join(HERE, "generate_pairs.py"), "--pool", os.path.join(work, "pool"),
           "--seed", str(args.seed), "--start", str(cursor), "--shard-size", str(args.shard_size),
           "--max-pending", str(args.max_pending), "--real-fraction", str(args.real_fraction),
           "--heavy-noise", str(args.heavy_noise), "--real-warp", str(args.real_warp),
           "--parent", str(os.getpid())]
    env = dict(os.environ, RAYON_NUM_THREADS=str(args.gen_threads), OMP_NUM_THREADS="1")
    return subprocess.Popen(["nice", "-n", str(args.gen_nice)] + cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


def ensure_holdout(pairs: int = 256) -> list[stream.Shard]:
    """Up to 256 fixed validation pairs: synthetic from train/bsds500_val (never trained on)
    and real pairs from the held-out tail of each RGB-D sequence."""
    folder = os.path.join(HERE, "cache", "holdout")
    shared = os.path.join(HERE, "..", "..", "shared", "data")
    if len([f for f in os.listdir(folder) if f.endswith(".npz")] if os.path.isdir(folder) else []) < 2:
        subprocess.run([sys.executable, os.path.join(HERE, "generate_pairs.py"), "--pool", folder, "--seed", "1",
                        "--shards", "2", "--shard-size", "128", "--max-pending", "1000",
                        "--photos", os.path.join(shared, "train", "bsds500_val"), "--rgbd-split", "holdout",
                        "--real-fraction", "0.25"], check=True)
    shards = [stream.Shard(stream.shard_path(folder, i)) for i in range(2)]
    return shards[: max(1, -(-pairs // 128))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="committed folder: config, last.pt, log.jsonl")
    ap.add_argument("--work", default=None, help="scratch folder (default training/runs/<run name>)")
    ap.add_argument("--preset", default="paraformer", choices=["superglue", "parallel_mlp", "paraformer", "paraformer_u", "lightglue_arm"],
                    help="lightglue_arm: a LightGlue-style diagnostic outside the SPEC (no weights file; "
                         "--layer-loss puts its loss on every layer, as LightGlue trains)")
    ap.add_argument("--dim", type=int, default=64)
    ap.add_argument("--heads", type=int, default=1)
    ap.add_argument("--depth", type=int, default=4, help="layers (SuperGlue: self+cross pairs)")
    ap.add_argument("--sinkhorn", type=int, default=50, help="Sinkhorn iterations (training and shipped config)")
    ap.add_argument("--sinkhorn-grad", choices=["last", "full"], default="last")
    ap.add_argument("--bf16", action="store_true",
                    help="the network's forward under bfloat16 autocast: ~1.2x pairs/s on CPUs with "
                         "AVX512-BF16, gradients within 0.999 cosine of fp32 (bench_step.py); "
                         "validation and export stay fp32, and a run may switch it on or off at a resume")
    ap.add_argument("--native-attention", action="store_true",
                    help="with --bf16: the fused attention's forward and backward in the project's engine "
                         "(paraformer attention_forward/backward_bf16, AVX-512 BF16 CPUs): 1.35-1.4x the "
                         "step of --bf16 alone at the same gradient accuracy (bench_step.py, "
                         "bench_attention.py); a run may switch it on or off at a resume")
    ap.add_argument("--stage-dims", type=int, nargs=5, default=None, metavar="C",
                    help="ParaFormer-U: the five stage widths (default dim x 256,384,128,384,256 / 256); "
                         "the first and last must equal --dim")
    ap.add_argument("--stage-depths", type=int, nargs=5, default=None, metavar="L",
                    help="ParaFormer-U: the five stages' layer counts (default 1 1 2 1 1; the SPEC's 2 1 2 1 2)")
    ap.add_argument("--pooling", choices=["attentional", "gpool", "random"], default=None,
                    help="ParaFormer-U: the pooling (SPEC §7; default attentional)")
    ap.add_argument("--unshare", nargs="*", choices=SHARING, default=[],
                    help="ParaFormer(-U): sharing switches to turn off (separate self/cross q/k/v, merges, "
                         "or cross-attention weights); more parameters at little CPU cost")
    ap.add_argument("--serial", action="store_true",
                    help="the LighterGlue transplant's layout (--init lighterglue, or a checkpoint of one) stays "
                         "serial: layer 2i's cross-branch and layer 2i+1's self-branch fuse columns (counted in "
                         "each stage of a ParaFormer-U) are zeroed and kept at zero, so each layer computes one "
                         "attention and the engine skips the other")
    ap.add_argument("--layer-loss", action="store_true",
                    help="ParaFormer: average the loss over every layer's assignment (training-only heads)")
    ap.add_argument("--phase-gain", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="a fresh start's Wave-PE phase: per-channel gains from LO to HI on its last "
                         "Linear (spatial frequencies per channel; e.g. 2 100); ignored by a resume")
    ap.add_argument("--self-rotary", type=float, nargs="+", default=None, metavar="LO HI [GAIN]",
                    help="an experiment outside the SPEC (no weights file; compare_capacity.sh arm "
                         "wide_rotary): rotary encoding of self-attention's queries and keys, learnable "
                         "frequencies from LO to HI rad per normalized unit (0.7 x the longer side); with "
                         "GAIN the angles start at zero (an --init model keeps its function) and grow")
    ap.add_argument("--pairs", type=int, default=600_000, help="training pairs in all (lr schedule length)")
    ap.add_argument("--decay-start", type=int, default=None,
                    help="pairs at which the cosine decay begins (default 60%% of --pairs); a branch off a "
                         "constant-rate run anneals from where it is, e.g. --decay-start 54000 --pairs 74000")
    ap.add_argument("--stop-after", type=int, default=None, help="stop this invocation after this many pairs in all")
    ap.add_argument("--keypoints", default="512x8:0.55,1024x4:0.3,2048x2:0.15",
                    help="per-step keypoints x batch : probability")
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--lr-scale-from", type=float, nargs=2, default=None, metavar=("LAYER", "SCALE"),
                    help="ParaFormer layers LAYER onwards learn at SCALE x --lr (e.g. layers grown by --init)")
    ap.add_argument("--lr-scale-unpool", type=float, default=None, metavar="SCALE",
                    help="a ParaFormer-U's unpooling projections learn at SCALE x --lr (may change at a resume)")
    ap.add_argument("--warmup", type=int, default=4000, help="warm-up pairs")
    ap.add_argument("--weight-decay", type=float, default=0.01)
    ap.add_argument("--ema", type=float, default=0.999,
                    help="per-step decay of the weights' moving average that is validated and exported (0: off)")
    ap.add_argument("--ema-warmup", action="store_true",
                    help="the EMA's decay starts low and rises to --ema ((1 + step) / (10 + step)): "
                         "needed from scratch, where a fixed 0.999 validates mostly the random init for "
                         "thousands of steps")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--shard-size", type=int, default=128)
    ap.add_argument("--max-pending", type=int, default=24)
    ap.add_argument("--reuse", type=float, default=1.0, help="draws per pair before its shard is retired")
    ap.add_argument("--real-fraction", type=float, default=0.2)
    ap.add_argument("--heavy-noise", type=data.probability, default=0.0,
                    help="probability per view of Gaussian noise of sigma 15-80 grey levels instead of the "
                         "recipe's 2-12 (homography/iguazu_noise reaches 78); 0 leaves the stream unchanged")
    ap.add_argument("--real-warp", type=data.probability, default=0.0,
                    help="probability per view of a real (RGB-D) pair that the view is a rotated (up to 39 deg), "
                         "scaled, perspective patch of its frame, so that the ~1,500 real frame pairs recur in "
                         "new geometry; 0 leaves the stream unchanged")
    ap.add_argument("--distill", type=data.probability, default=0.0, metavar="ALPHA",
                    help="weight of a distillation term: loss = (1 - ALPHA) x NLL of the labels + ALPHA x KL from "
                         "LighterGlue's soft assignment on the same features (paraformer_train/teacher.py; ~0.1 s "
                         "per pair on 2 cores); 0 trains on the labels alone; a run may switch it at a resume")
    ap.add_argument("--hint", type=float, default=0.0, metavar="BETA",
                    help="weight of a feature-hint term added to the loss: BETA x the squared error between each "
                         "student layer's features (through a training-only linear map) and LighterGlue's at the same "
                         "relative depth on the same features, standardized per channel (1 - R^2; train.py "
                         "HintAdapters, paraformer_train/teacher.py hint_loss); needs --preset paraformer; 0: off")
    ap.add_argument("--teacher-bf16", action="store_true",
                    help="run the --distill teacher under bfloat16 autocast: 1.6-2x faster alone (bench_teacher.py), "
                         "less inside the trainer; rows within 0.02-0.05 total variation of the float32 "
                         "teacher's (paraformer_train/teacher.py)")
    ap.add_argument("--blind-descriptors", type=data.probability, default=0.0, metavar="P",
                    help="probability per keypoint and view that the student sees a random descriptor of the same "
                         "norm in its place (the teacher and the labels see the true one), so that it must match "
                         "that keypoint by its place among the others; 0 leaves the batches unchanged")
    ap.add_argument("--synthetic-positive-px", type=float, default=None,
                    help="positive radius for synthetic pairs (default: 3 px like the evaluation; "
                         "keypoints between it and 3 px are ignored)")
    ap.add_argument("--real-unmatched-from", type=float, default=8.0,
                    help="training labels of real pairs: unmatched only from this distance (px), ignored "
                         "between it and 3 px (pose/depth noise); validation keeps the evaluation rule")
    ap.add_argument("--generate-inline", action="store_true",
                    help="generate the stream's shards inside the trainer between steps, on both cores, instead of "
                         "in a process beside it (the same pairs; the generator beside it costs the step its "
                         "OpenMP barriers)")
    ap.add_argument("--gen-threads", type=int, default=1)
    ap.add_argument("--gen-nice", type=int, default=0,
                    help="generator niceness over the trainer's: equal by default, since a starved generator means pairs drawn twice")
    ap.add_argument("--ckpt-minutes", type=float, default=10.0)
    ap.add_argument("--val-every", type=int, default=20_000, help="validate every this many pairs")
    ap.add_argument("--val-threshold", type=float, default=0.2)
    ap.add_argument("--val-pairs", type=int, default=256, help="holdout pairs per validation")
    ap.add_argument("--validate-only", action="store_true",
                    help="validate the run's checkpoint once, append it to log.jsonl and exit")
    ap.add_argument("--init", default=None,
                    help="a run that has no checkpoint yet starts from these weights (a train.py or train_gpu.py "
                         "checkpoint: its EMA weights), e.g. to fine-tune the GPU run on real pairs; a "
                         "ParaFormer init with fewer layers than --depth is grown by identity layers; 'lighterglue': LighterGlue's "
                         "trained weights, for the lightglue_arm diagnostic or a SPEC ParaFormer --dim 96 --heads 1 "
                         "--depth 2k --unshare qkv merge (k <= 6: LighterGlue's first k layers), or a ParaFormer-U --dim 96 --heads 1 "
                         "--stage-dims 96 96 96 96 96 --stage-depths (even) --pooling gpool --unshare qkv merge "
                         "(paraformer_train/lighterglue_transplant.py)")
    ap.add_argument("--grow-copy", type=float, default=None, metavar="SCALE",
                    help="with a grown --init: the new layers start as copies of the init's last layers, "
                         "their last fuse Linear scaled by SCALE (e.g. 0.1), instead of as identity layers")
    ap.add_argument("--fixed-pool", default=None,
                    help="read this pre-generated pool (kept, no generator): short comparison runs")
    args = ap.parse_args()
    args.unshare = [k for k in SHARING if k in args.unshare]  # one spelling per set, for the resume check
    if args.decay_start is not None and not 0 <= args.decay_start < args.pairs:
        sys.exit(f"error: --decay-start {args.decay_start}: expected 0 <= it < --pairs ({args.pairs})")
    decay_from = DECAY_FROM if args.decay_start is None else args.decay_start / args.pairs
    if args.native_attention and not args.bf16:
        sys.exit("error: --native-attention runs the bf16 attention; add --bf16")
    if cpu_has_bf16() is False:
        # bf16 is a speed option only (validation and export stay fp32): dropped, not refused,
        # so one resume command serves every machine.
        for flag in ("bf16", "teacher_bf16", "native_attention"):
            if getattr(args, flag):
                print(f"note: --{flag.replace('_', '-')} dropped: this CPU has no native bf16 "
                      "(emulated bf16 is several times slower than fp32)", flush=True)
                setattr(args, flag, False)
    if args.native_attention and not native_attention_pays():
        # A speed option only (validation and export stay fp32 SDPA): dropped, not refused.
        print("note: --native-attention dropped: this CPU has AMX-BF16, where PyTorch's bf16 attention "
              "is as fast or faster (train.py native_attention_pays)", flush=True)
        args.native_attention = False
    if args.native_attention:
        try:
            from paraformer import _paraformer
        except ImportError as e:
            sys.exit(f"error: --native-attention needs the paraformer package (pip install .): {e}")
        if not _paraformer.attention_bf16_available():
            sys.exit("error: --native-attention needs a CPU with AVX-512 BF16; drop the flag")
        model_mod.NATIVE_ATTENTION = True

    torch.set_num_threads(args.threads)
    name = os.path.basename(os.path.normpath(args.run))
    work = args.work or os.path.join(HERE, "runs", name)
    os.makedirs(args.run, exist_ok=True)
    os.makedirs(work, exist_ok=True)
    ckpt = os.path.join(args.run, "last.pt")
    state = torch.load(ckpt, weights_only=False) if os.path.exists(ckpt) else None
    if state is not None:
        saved = state["args"]
        was = {k: saved.get(k, RESUME_DEFAULTS.get(k)) for k in RESUME_ARGS}
        changed = {k: (was[k], getattr(args, k)) for k in RESUME_ARGS if was[k] != getattr(args, k)}
        if changed:
            sys.exit(f"error: {ckpt} was trained with other model arguments: {changed}")
    torch.manual_seed(args.seed)
    try:
        cfg = model_config(vars(args))
    except ValueError as e:
        sys.exit(f"error: {e}")
    if args.self_rotary is not None and len(args.self_rotary) not in (2, 3):
        sys.exit(f"error: --self-rotary {args.self_rotary}: expected LO HI or LO HI GAIN")
    try:
        model = build_model(cfg, args.self_rotary).train()
    except ValueError as e:
        sys.exit(f"error: {e}")
    if args.phase_gain and state is None:
        lo, hi = args.phase_gain
        if args.init:
            sys.exit("error: --phase-gain applies to a fresh start, not to --init weights")
        if not 0 < lo <= hi:
            sys.exit(f"error: --phase-gain {lo} {hi}: expected 0 < LO <= HI")
        try:
            phase_gain_init(model, lo, hi)
        except ValueError as e:
            sys.exit(f"error: {e}")
    # The exported weights: an exponential moving average of the trained ones, which smooths
    # the noise of small batches (batch 2-8) at a constant learning rate.
    # With --ema 0 it is the trained model itself.
    ema = build_model(cfg, args.self_rotary).eval() if args.ema > 0 else model
    ema.load_state_dict(model.state_dict())
    if args.layer_loss and args.preset not in ("paraformer", "lightglue_arm"):
        sys.exit("error: --layer-loss needs --preset paraformer or lightglue_arm")
    if args.preset == "lightglue_arm" and args.init not in (None, "lighterglue"):
        sys.exit(f"error: --init {args.init}: the lightglue_arm preset starts from scratch or from LighterGlue's "
                 "weights (--init lighterglue)")
    if args.init == "lighterglue" and not is_arm(model):
        from paraformer_train.lighterglue_transplant import check_transplant_config

        try:
            check_transplant_config(model.config)
        except ValueError as e:
            sys.exit(f"error: --init lighterglue: {e}; or the diagnostic --preset lightglue_arm --dim 96 --heads 1 --depth 6")
        if args.self_rotary is not None:
            sys.exit("error: --init lighterglue starts a SPEC model; --self-rotary is outside the SPEC")
    heads = LayerHeads(model) if args.layer_loss and not is_arm(model) else None
    if args.hint < 0:
        sys.exit(f"error: --hint {args.hint:g}: expected a weight >= 0")
    if args.hint > 0 and args.preset != "paraformer":
        sys.exit("error: --hint needs --preset paraformer (per-layer features)")
    try:
        adapters = HintAdapters(model, serial=args.serial) if args.hint > 0 else None
    except ValueError as e:
        sys.exit(f"error: --hint: {e}")
    params = list(model.parameters()) + (list(heads.parameters()) if heads is not None else [])
    groups = [{"params": params, "lr_scale": 1.0}]
    if args.lr_scale_from is not None:
        try:
            groups = lr_scale_groups(model, params, *args.lr_scale_from)
        except ValueError as e:
            sys.exit(f"error: --lr-scale-from: {e}")
    base_groups = groups  # as runs saved before checkpoints named their groups had them
    if args.lr_scale_unpool is not None:
        try:
            groups = lr_scale_unpool_groups(model, groups, args.lr_scale_unpool)
        except ValueError as e:
            sys.exit(f"error: --lr-scale-unpool: {e}")
    opt = torch.optim.AdamW(groups, lr=args.lr, weight_decay=args.weight_decay)
    names = {id(p): n for n, p in model.named_parameters()}
    names |= {id(p): "heads." + n for n, p in heads.named_parameters()} if heads is not None else {}
    names |= {id(p): "hint." + n for n, p in adapters.named_parameters()} if adapters is not None else {}
    # The hint maps are a param group of their own, so that hints can join a run at a resume.
    hint_group = {"params": list(adapters.parameters()), "lr_scale": 1.0} if adapters is not None else None
    if adapters is not None:
        params = params + hint_group["params"]
    try:  # new maps are fitted on the first batch where they meet trained features (--init, a resume)
        had_hints = state is not None and "hint" in state
        saved_names = None
        if state is not None:
            saved_names = state.get("opt_names") or group_names(
                base_groups + ([hint_group] if had_hints and hint_group else []), names)
        fit_adapters = resume_optimizer(opt, state["opt"] if state is not None else None, hint_group,
                                        had_hints, names, saved_names)
    except ValueError as e:
        sys.exit(f"error: {ckpt}: its optimiser state does not fit this run's parameters ({e}); "
                 "a run that had --hint keeps it, or restarts with --init")
    fit_adapters = fit_adapters and (state is not None or bool(args.init))
    pairs_seen, steps, cursor, spent, best = 0, 0, 0, 0.0, -1.0
    rng = np.random.default_rng([args.seed, 7])
    if state is not None:
        model.load_state_dict(state["model"])
        if ema is not model:
            ema.load_state_dict(state.get("ema", state["model"]))
        if heads is not None:
            heads.load_state_dict(state["heads"])
        if adapters is not None and "hint" in state:
            adapters.load_state_dict(state["hint"])
        pairs_seen, steps, cursor = state["pairs"], state["steps"], state["cursor"]
        spent, best = state["train_s"], state["best"]
        rng.bit_generator.state = state["rng"]
        print(f"resumed at {pairs_seen} pairs, step {steps}, stream shard {cursor}", flush=True)
    elif args.init:
        if args.grow_copy is not None and not 0 <= args.grow_copy <= 1:
            sys.exit(f"error: --grow-copy {args.grow_copy:g}: expected a scale in [0, 1]")
        if args.init == "lighterglue":
            from paraformer_train.lightglue_arm import lighterglue_state
            from paraformer_train.lighterglue_transplant import transplant_state

            try:
                model.load_state_dict(lighterglue_state() if is_arm(model) else transplant_state(model))
            except (RuntimeError, KeyError) as e:
                sys.exit(f"error: --init lighterglue: {e}")
            grown = []
        else:
            grown = load_init(model, init_weights(args.init, model.config), args.grow_copy)
        ema.load_state_dict(model.state_dict())
        if heads is not None:
            heads.copy_from(model)
        how = f"copies of the init's last layers, last Linear x{args.grow_copy:g}" if args.grow_copy is not None else "identity or silent"
        print(f"initialised from {args.init}" + (f", new ({how}) parts {grown}" if grown else ""), flush=True)
    elif args.grow_copy is not None:
        sys.exit("error: --grow-copy needs --init (weights with fewer layers than --depth)")
    closed = None
    if args.serial:
        from paraformer_train.lighterglue_transplant import close_branches, zero_closed

        try:
            closed = close_branches(model)
        except (ValueError, AttributeError) as e:
            sys.exit(f"error: --serial: {e}")
        removed = zero_closed(closed)
        if ema is not model:
            zero_closed(close_branches(ema))
        if removed:
            print(f"--serial: closed branches zeroed (their fuse columns had norm {removed:.3f})", flush=True)
    holdout = ensure_holdout(args.val_pairs)
    if args.validate_only:
        v = validate(ema, holdout, 512, args.val_threshold, auc=False)
        v |= validate(ema, holdout, 2048, args.val_threshold, auc=True)
        rec = {"pairs": pairs_seen, "steps": steps, "validate_only": True} | v
        with open(os.path.join(args.run, "log.jsonl"), "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(json.dumps(rec), flush=True)
        return
    with open(os.path.join(args.run, "config.json"), "w") as f:
        json.dump({"args": vars(args), "config": model.config}, f, indent=1)
    inline = None
    if args.fixed_pool:
        gen = None
        reader = stream.PoolReader(args.fixed_pool, cursor, reuse=args.reuse, rng=rng, delete=False)
    else:
        gen = None
        if args.generate_inline:
            import generate_pairs

            src = generate_pairs.pair_source(args.seed, args.real_fraction, args.heavy_noise, real_warp=args.real_warp)
            inline = generate_pairs.InlineGenerator(src, os.path.join(work, "pool"), cursor, args.shard_size)
        else:
            gen = start_generator(args, work, cursor)
        reader = stream.PoolReader(os.path.join(work, "pool"), cursor, reuse=args.reuse, rng=rng)
    schedule = parse_schedule(args.keypoints)
    teacher = None
    if args.distill > 0 or args.hint > 0:
        try:
            teacher = LighterGlueTeacher(bf16=args.teacher_bf16, hidden=args.hint > 0)
        except RuntimeError as e:
            sys.exit(f"error: {'--distill' if args.distill > 0 else '--hint'}: {e}")
    sinkhorn = log_optimal_transport_last_grad if args.sinkhorn_grad == "last" else log_optimal_transport
    log = open(os.path.join(args.run, "log.jsonl"), "a")
    stop = {"now": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    signal.signal(signal.SIGINT, lambda *_: stop.update(now=True))
    limit = min(args.pairs, args.stop_after or args.pairs)
    next_val = (pairs_seen // args.val_every + 1) * args.val_every
    t_ckpt = t_mark = time.time()
    running: list[float] = []
    running_kl: list[float] = []
    running_hint: list[float] = []
    teacher_s = 0.0
    kinds = {k: 0 for k, _, _ in schedule}

    def save() -> None:
        blob = {"model": model.state_dict(), "ema": ema.state_dict(), "opt": opt.state_dict(), "pairs": pairs_seen, "steps": steps,
                "cursor": reader.low_water(), "train_s": spent + time.time() - t_mark, "best": best,
                "rng": rng.bit_generator.state, "args": vars(args),
                "opt_names": group_names(opt.param_groups, names)}
        if heads is not None:
            blob["heads"] = heads.state_dict()
        if adapters is not None:
            blob["hint"] = adapters.state_dict()
        torch.save(blob, ckpt + ".tmp")
        os.replace(ckpt + ".tmp", ckpt)

    try:
        while pairs_seen < limit and not stop["now"]:
            if gen is not None and gen.poll() is not None:
                gen = start_generator(args, work, reader.low_water())
            k, bsz, _ = schedule[int(rng.choice(len(schedule), p=[p for _, _, p in schedule]))]
            if inline is not None:
                inline.top_up(reader.waiting(), reader.high_water())
            items = reader.draw(bsz)
            bt = stream.collate(items, k, list(rng.random(bsz) < 0.5), real_unmatched_from=args.real_unmatched_from,
                                    synthetic_positive_px=args.synthetic_positive_px)
            for g_ in opt.param_groups:
                g_["lr"] = g_.get("lr_scale", 1.0) * lr_at(pairs_seen, args.pairs, args.warmup, args.lr, decay_from)
            seen = stream.blind_descriptors(bt, args.blind_descriptors, rng) if args.blind_descriptors > 0 else bt
            states: list | None = [] if adapters is not None else None
            logps = log_assignments(model, heads, seen, sinkhorn, args.sinkhorn, args.bf16, states,
                                    every_layer=args.layer_loss)
            losses = [nll_loss(logp, bt["gt0"], bt["gt1"]) for logp in logps]
            if teacher is not None:
                t0 = time.time()
                target = teacher(bt)
                teacher_s += time.time() - t0
            if args.distill > 0:
                kls = [distillation_loss(logp, target) for logp in logps]
                running_kl.append(kls[-1].item())
                loss = sum((1 - args.distill) * n + args.distill * k for n, k in zip(losses, kls)) / len(losses)
            else:
                loss = sum(losses) / len(losses)
            if adapters is not None:
                features = teacher.hidden()
                hinted = adapters.hinted(states)
                if fit_adapters:
                    adapters.fit(hinted, features)
                    fit_adapters = False
                hint = hint_loss(hinted, adapters.maps, features, adapters.pick)
                running_hint.append(hint.item())
                loss = loss + args.hint * hint
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if closed is not None:  # Adam's moments of the closed weights stay zero, so do they
                zero_closed(closed, grads=True)
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            opt.step()
            if ema is not model:
                decay = ema_decay(args.ema, steps, args.ema_warmup)
                with torch.no_grad():
                    for e, p in zip(ema.parameters(), model.parameters()):
                        e.lerp_(p, 1.0 - decay)
                    for e, b in zip(ema.buffers(), model.buffers()):  # BatchNorm statistics: as trained
                        e.copy_(b)
            steps += 1
            pairs_seen += bsz
            kinds[k] += bsz
            running.append(losses[-1].item())  # the last layer's loss: comparable with or without --layer-loss
            if steps % 50 == 0:
                rate = sum(kinds.values()) / max(time.time() - t_mark, 1e-9)
                print(f"step {steps} pairs {pairs_seen} loss {np.mean(running[-50:]):.4f} "
                      f"lr {opt.param_groups[0]['lr']:.2e} {rate:.1f} pairs/s shard {reader.low_water()}"
                      + (f" inline generation {100 * inline.seconds / max(time.time() - t_mark, 1e-9):.0f}%"
                         if inline is not None else "")
                      + (f" kl {np.mean(running_kl[-50:]):.4f}" if running_kl else "")
                      + (f" hint {np.mean(running_hint[-50:]):.4f}" if running_hint else "")
                      + (f" teacher {100 * teacher_s / max(time.time() - t_mark, 1e-9):.0f}%"
                         if teacher is not None else ""), flush=True)
            if pairs_seen >= next_val or pairs_seen >= limit:
                next_val += args.val_every
                v = validate(ema, holdout, 512, args.val_threshold, auc=False)
                v |= validate(ema, holdout, 2048, args.val_threshold, auc=True)
                rec = {"pairs": pairs_seen, "steps": steps, "weights": "ema" if args.ema > 0 else "trained",
                       "loss": float(np.mean(running)) if running else None,
                       "lr": opt.param_groups[0]["lr"], "train_s": round(spent + time.time() - t_mark, 1),
                       "distinct_pairs": reader.low_water() * args.shard_size, "by_keypoints": dict(kinds)} | v
                if args.blind_descriptors > 0:
                    rec["blind_descriptors"] = args.blind_descriptors
                if teacher is not None:
                    rec["distill"] = args.distill
                    rec["teacher_bf16"] = args.teacher_bf16
                    rec["distill_kl"] = float(np.mean(running_kl)) if running_kl else None
                if adapters is not None:
                    rec["hint"] = args.hint
                    rec["hint_loss"] = float(np.mean(running_hint)) if running_hint else None
                running, running_kl, running_hint = [], [], []
                log.write(json.dumps(rec) + "\n")
                log.flush()
                print(json.dumps(rec), flush=True)
                score = v["auc5px@2048"] + v["f1@2048"]
                if score > best:
                    best = score
                    export(ema, os.path.join(work, "best.safetensors"))
                save()
                t_ckpt = time.time()
            if time.time() - t_ckpt > args.ckpt_minutes * 60:
                save()
                t_ckpt = time.time()
    finally:
        save()
        export(ema, os.path.join(work, "last.safetensors"))
        if gen is not None:
            gen.terminate()
        print(f"stopped at {pairs_seen} pairs, step {steps}", flush=True)


if __name__ == "__main__":
    main()
