"""Trains one matcher (SuperGlue, parallel + MLP-PE, ParaFormer, ParaFormer-U) on cached
XFeat pairs from `make_dataset.py`. Resumable: rerunning the same command continues from
`<out>/last.pt`. Writes `<out>/log.jsonl` (loss, lr, validation precision/recall/F1) and
`<out>/best.safetensors` (SPEC weights file of the best validation F1).

    python training/train.py --preset paraformer --out training/runs/paraformer \
        --data training/cache/train --val training/cache/holdout --steps 3000
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train.io import save_safetensors  # noqa: E402
from paraformer_train.model import Matcher  # noqa: E402


def preset(name: str, dim: int, depth: int) -> dict:
    """The four models of the comparison at one width and depth (Table 3 + the U variant)."""
    common = {"descriptor_dim": 64, "num_heads": 4}
    if name == "superglue":
        return common | {"model": "superglue", "dim": dim, "layer_names": ["self", "cross"] * depth}
    if name == "parallel_mlp":
        return common | {"model": "paraformer", "dim": dim, "num_layers": depth, "positional_encoding": "mlp"}
    if name == "paraformer":
        return common | {"model": "paraformer", "dim": dim, "num_layers": depth}
    if name == "paraformer_u":
        # SPEC default widths (256, 384, 128, 384, 256) scaled by dim / 256.
        dims = [dim * w // 256 for w in (256, 384, 128, 384, 256)]
        return common | {"model": "paraformer_u", "stage_dims": dims, "stage_depths": [1, 1, 2, 1, 1]}
    raise ValueError(f"unknown preset {name!r}")


def load_shards(folder: str) -> dict[str, torch.Tensor]:
    paths = sorted(glob.glob(os.path.join(folder, "shard_*.npz")))
    if not paths:
        raise FileNotFoundError(f"no shard_*.npz in {folder} (run training/make_dataset.py)")
    parts = [dict(np.load(p)) for p in paths]
    out = {k: torch.from_numpy(np.concatenate([p[k] for p in parts])) for k in parts[0]}
    out["scores"] = out["scores"].float()
    out["descriptors"] = out["descriptors"].float()
    out["matches0"] = out["matches0"].long()
    out["matches1"] = out["matches1"].long()
    return out


def batch(data: dict, idx: torch.Tensor, swap: torch.Tensor | None = None) -> dict:
    """A model input dict for pairs `idx`; `swap[b]` exchanges the two views of pair b."""
    k, s, d, sz = (data[n][idx] for n in ("keypoints", "scores", "descriptors", "image_size"))
    m0, m1 = data["matches0"][idx], data["matches1"][idx]
    if swap is not None:
        flip = swap.view(-1, 1, 1, 1)
        k = torch.where(flip, k.flip(1), k)
        d = torch.where(flip, d.flip(1), d)
        s = torch.where(swap.view(-1, 1, 1), s.flip(1), s)
        sz = torch.where(swap.view(-1, 1, 1), sz.flip(1), sz)
        m0, m1 = torch.where(swap.view(-1, 1), m1, m0), torch.where(swap.view(-1, 1), m0, m1)
    return {
        "keypoints0": k[:, 0], "keypoints1": k[:, 1], "scores0": s[:, 0], "scores1": s[:, 1],
        "descriptors0": d[:, 0], "descriptors1": d[:, 1], "image_size0": sz[:, 0], "image_size1": sz[:, 1],
        "gt0": m0, "gt1": m1,
    }


def nll_loss(logp: torch.Tensor, gt0: torch.Tensor, gt1: torch.Tensor) -> torch.Tensor:
    """Assignment NLL with dustbins: 0.5 · mean over positives + 0.5 · mean over unmatched
    keypoints of both images; ignored keypoints (−2) are left out."""
    b, m1, n1 = logp.shape
    pos = gt0 >= 0
    pos_ll = logp[:, :-1, :][torch.arange(b)[:, None].expand_as(gt0)[pos], torch.nonzero(pos)[:, 1], gt0[pos]]
    un0 = logp[:, :-1, -1][gt0 == -1]
    un1 = logp[:, -1, :-1][gt1 == -1]
    neg_ll = torch.cat([un0, un1])
    pos_term = -pos_ll.mean() if pos_ll.numel() else logp.new_zeros(())
    neg_term = -neg_ll.mean() if neg_ll.numel() else logp.new_zeros(())
    return 0.5 * pos_term + 0.5 * neg_term


def precision_recall(pred0: torch.Tensor, gt0: torch.Tensor) -> tuple[int, int, int]:
    """(true positives, predicted matches, ground-truth matches) over non-ignored keypoints."""
    keep = gt0 != -2
    predicted = (pred0 >= 0) & keep
    tp = (predicted & (pred0 == gt0)).sum().item()
    return tp, predicted.sum().item(), (gt0 >= 0).sum().item()


@torch.no_grad()
def validate(model: Matcher, data: dict, bs: int) -> dict:
    model.eval()
    tp = npred = ngt = 0
    loss = 0.0
    n = data["keypoints"].shape[0]
    for s in range(0, n, bs):
        bt = batch(data, torch.arange(s, min(s + bs, n)))
        out = model(bt)
        loss += nll_loss(out["log_assignment"], bt["gt0"], bt["gt1"]).item() * bt["gt0"].shape[0]
        a, b_, c = precision_recall(out["matches0"], bt["gt0"])
        tp, npred, ngt = tp + a, npred + b_, ngt + c
    model.train()
    p, r = tp / max(npred, 1), tp / max(ngt, 1)
    return {"val_loss": loss / n, "precision": p, "recall": r, "f1": 2 * p * r / max(p + r, 1e-12)}


def lr_at(step: int, total: int, warmup: int, peak: float) -> float:
    """Linear warm-up, then cosine decay to 1% of the peak (paper §Implementation: AdamW)."""
    if step < warmup:
        return peak * (step + 1) / warmup
    t = (step - warmup) / max(total - warmup, 1)
    return peak * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", required=True, choices=["superglue", "parallel_mlp", "paraformer", "paraformer_u"])
    ap.add_argument("--dim", type=int, default=128)
    ap.add_argument("--depth", type=int, default=4, help="layers (SuperGlue: self+cross pairs)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--weight-decay", type=float, default=0.01)
    ap.add_argument("--sinkhorn", type=int, default=50, help="Sinkhorn iterations (training and shipped config)")
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    cfg = preset(args.preset, args.dim, args.depth) | {"sinkhorn_iterations": args.sinkhorn}
    model = Matcher(cfg).train()
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    data, val = load_shards(args.data), load_shards(args.val)
    n = data["keypoints"].shape[0]
    gen = torch.Generator().manual_seed(args.seed)
    step, best, spent = 0, -1.0, 0.0
    ckpt = os.path.join(args.out, "last.pt")
    if os.path.exists(ckpt):
        state = torch.load(ckpt, weights_only=False)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        gen.set_state(state["gen"])
        step, best, spent = state["step"], state["best"], state.get("spent", 0.0)
        print(f"resumed at step {step} (best F1 {best:.4f})", flush=True)
    with open(os.path.join(args.out, "config.json"), "w") as f:
        json.dump({"args": vars(args), "config": model.config, "train_pairs": n}, f, indent=1)
    log = open(os.path.join(args.out, "log.jsonl"), "a")
    try:
        from tqdm import tqdm

        bar = tqdm(total=args.steps, initial=step, dynamic_ncols=True, mininterval=5)
    except ImportError:
        bar = None
    running, t_last = [], time.time()
    while step < args.steps:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, args.steps, args.warmup, args.lr)
        idx = torch.randint(0, n, (args.batch,), generator=gen)
        swap = torch.rand(args.batch, generator=gen) < 0.5
        bt = batch(data, idx, swap)
        out = model.scores(bt)
        from paraformer_train.model import log_optimal_transport

        logp = log_optimal_transport(out, model.bin_score, args.sinkhorn)
        loss = nll_loss(logp, bt["gt0"], bt["gt1"])
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        step += 1
        running.append(loss.item())
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(running[-50:]):.3f}")
        if step % args.val_every == 0 or step == args.steps:
            now = time.time()
            spent += now - t_last
            v = validate(model, val, 16)
            rec = {"step": step, "loss": float(np.mean(running)), "lr": opt.param_groups[0]["lr"], "train_s": round(spent, 1)} | v
            running = []
            log.write(json.dumps(rec) + "\n")
            log.flush()
            print(json.dumps(rec), flush=True)
            if v["f1"] > best:
                best = v["f1"]
                save_safetensors(model, os.path.join(args.out, "best.safetensors"))
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "gen": gen.get_state(),
                        "step": step, "best": best, "spent": spent}, ckpt + ".tmp")
            os.replace(ckpt + ".tmp", ckpt)
            t_last = time.time()
    save_safetensors(model, os.path.join(args.out, "last.safetensors"))
    print(f"done: {step} steps, best validation F1 {best:.4f}", flush=True)


if __name__ == "__main__":
    main()
