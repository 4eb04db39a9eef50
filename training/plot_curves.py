"""Learning curves from ``log.jsonl`` files (validation loss, F1 and homography AUC@5px at
512 and 2048 keypoints against pairs seen) into one PNG, and a JSON/markdown summary of
the last validation of each run.

    python training/plot_curves.py training/checkpoints/paraformer-xfeat --out training/curves.png
    python training/plot_curves.py training/runs/compare/* --out training/results/config_comparison.png \
        --summary training/results/config_comparison.json

A run given as ``RUN=PAIRS`` is drawn shifted by PAIRS: a run started with ``train.py
--init`` from a checkpoint at PAIRS pairs counts its own pairs from 0.
"""
from __future__ import annotations

import argparse
import json
import os


def read_log(run: str) -> list[dict]:
    path = os.path.join(run, "log.jsonl")
    if not os.path.exists(path):
        return []
    return [json.loads(line) for line in open(path) if line.strip()]


def parse_run(text: str) -> tuple[str, int]:
    """``RUN`` or ``RUN=PAIRS`` → (folder, pairs offset)."""
    run, sep, offset = text.rpartition("=")
    if not sep:
        return text, 0
    try:
        pairs = int(offset)
    except ValueError:
        raise SystemExit(f"error: {text!r}: expected RUN or RUN=PAIRS, PAIRS a whole number of pairs") from None
    if pairs < 0 or not run:
        raise SystemExit(f"error: {text!r}: expected RUN or RUN=PAIRS, PAIRS a whole number of pairs")
    return run, pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders (log.jsonl), each RUN or RUN=PAIRS (drawn from PAIRS on)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--summary", default=None)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("val_loss@512", "val loss @512"), ("val_loss@2048", "val loss @2048"), ("f1@512", "F1 @512"),
              ("f1@2048", "F1 @2048"), ("auc5px@2048", "H AUC@5px @2048"), ("precision@2048", "precision @2048")]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    summary = {}
    # tab20 rather than the default 10-colour cycle, so that up to 20 runs keep distinct colours
    colours = plt.get_cmap("tab20").colors
    for index, (run, offset) in enumerate(parse_run(r) for r in args.runs):
        log = read_log(run)
        if not log:
            continue
        name = os.path.basename(os.path.normpath(run))
        cfg = json.load(open(os.path.join(run, "config.json"))) if os.path.exists(os.path.join(run, "config.json")) else {}
        summary[name] = {"last": log[-1], "args": cfg.get("args", {})}
        x = [r["pairs"] + offset for r in log]
        for ax, (key, title) in zip(axes.ravel(), panels):
            ys = [r.get(key) for r in log]
            ax.plot(x, ys, marker="o", ms=3, label=name, color=colours[index % len(colours)])
            ax.set_title(title)
            ax.set_xlabel("training pairs seen")
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out, dpi=90)
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=1)
    for name, s in summary.items():
        last = s["last"]
        print(f"{name:20s} pairs {last['pairs']:7d}  " + "  ".join(
            f"{k} {last[k]:.3f}" for k, _ in panels if last.get(k) is not None))


if __name__ == "__main__":
    main()
