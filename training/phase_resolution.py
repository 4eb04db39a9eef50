"""How finely a trained model's Wave-PE phases resolve keypoint positions: the phase MLP
θ(p) of a checkpoint's EMA weights on a grid of a 640 × 480 image (score 0.5), the change
per 100 px (the larger of a 5 px step in x and in y), median over the grid per channel,
then the median and 90th percentile over channels. PyTorch's initialisation gives about
1.1 rad per 100 px; the trained lines flatten it to about 0.17 (training/README, "High-
frequency positions with unshared projections").

    python training/phase_resolution.py training/checkpoints/paraformer-xfeat-w96-alpha025/last.pt
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def phase_change_per_100px(phase, size=(640, 480), step: float = 5.0) -> np.ndarray:
    """Per channel: the median over a grid of |θ(p + step) − θ(p)| / step · 100, the larger
    of the x and y steps. ``phase`` maps normalised ``[1, K, 3]`` keypoints to ``[1, K, C]``."""
    import torch

    w, h = size
    scale = 0.7 * max(w, h)  # SPEC §1's normalisation
    xs, ys = np.meshgrid(np.linspace(20, w - 20, 31), np.linspace(20, h - 20, 23))
    grid = np.stack([xs.ravel(), ys.ravel()], 1)

    def theta(q: np.ndarray) -> np.ndarray:
        p = np.concatenate([(q - [w / 2, h / 2]) / scale, np.full((len(q), 1), 0.5)], 1)
        with torch.no_grad():
            return phase(torch.tensor(p[None], dtype=torch.float32))[0].numpy()

    base = theta(grid)
    dx = np.abs(theta(grid + [step, 0]) - base)
    dy = np.abs(theta(grid + [0, step]) - base)
    return np.median(np.maximum(dx, dy) / step * 100, axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+", help="train.py checkpoints (last.pt); their EMA weights are read")
    args = ap.parse_args()
    for path in args.checkpoints:
        if not os.path.isfile(path):
            sys.exit(f"error: {path}: no such checkpoint file")
    import torch

    from validate_snapshots import Matcher_from_args

    for path in args.checkpoints:
        state = torch.load(path, weights_only=False)
        model = Matcher_from_args(state["args"])
        model.load_state_dict(state["ema"])
        if not hasattr(model, "wave_pe"):
            sys.exit(f"error: {path}: the model has no Wave-PE (preset {state['args'].get('preset')})")
        per_channel = phase_change_per_100px(model.eval().wave_pe.phase)
        print(f"{path} ({state.get('pairs')} pairs): rad per 100 px, median channel {np.median(per_channel):.3f}, "
              f"90th percentile {np.percentile(per_channel, 90):.3f}, max {per_channel.max():.3f}")


if __name__ == "__main__":
    main()
