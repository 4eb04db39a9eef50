"""Learning curves from ``log.jsonl`` files (validation loss, F1 and homography AUC@5px at
512 and 2048 keypoints against pairs seen) into one PNG, and a JSON/markdown summary of
the last validation of each run.

    python training/plot_curves.py training/checkpoints/paraformer-xfeat --out training/curves.png
    python training/plot_curves.py training/runs/compare/* --out training/results/config_comparison.png \
        --summary training/results/config_comparison.json

A run given as ``RUN=PAIRS`` is drawn shifted by PAIRS: a run started with ``train.py
--init`` from a checkpoint at PAIRS pairs counts its own pairs from 0. ``--from-pairs N``
draws only the validations at N pairs or later, to zoom on branches of a long line (a
branch's log starts with a copy of its line's history).
"""
from __future__ import annotations

import argparse
import json
import os
import sys


def read_log(run: str) -> list[dict]:
    """The rows of RUN/log.jsonl, or of RUN itself when it is a .jsonl file (a run whose
    folder was not kept, only its validation rows)."""
    path = run if run.endswith(".jsonl") and os.path.isfile(run) else os.path.join(run, "log.jsonl")
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


def visible(log: list[dict], offset: int, from_pairs: int) -> list[dict]:
    """The validation rows of a run drawn at ``offset``, from ``from_pairs`` pairs on."""
    return [r for r in log if r["pairs"] + offset >= from_pairs]


def row_key(r: dict) -> tuple:
    """What identifies a validation row across runs: a branch's log repeats its line's rows."""
    return r["pairs"], r.get("val_loss@512"), r.get("val_loss@2048")


def own_rows(log: list[dict], drawn: set) -> list[dict]:
    """A branch's rows without the history it shares with a run drawn before it (its log
    starts with a copy of that run's), keeping the branch point so the curve joins it."""
    first = next((i for i, r in enumerate(log) if row_key(r) not in drawn), len(log))
    return log[max(first - 1, 0):] if first < len(log) else []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders (log.jsonl) or .jsonl files, each RUN or RUN=PAIRS (drawn from PAIRS on)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--summary", default=None)
    ap.add_argument("--from-pairs", type=int, default=0, help="draw validations at this many pairs or later")
    args = ap.parse_args()
    if args.from_pairs < 0:
        ap.error(f"--from-pairs {args.from_pairs}: expected a number of pairs >= 0")
    # which rows each run draws: read first, so bad runs are named before matplotlib loads
    curves, drawn = [], set()
    for index, (run, offset) in enumerate(parse_run(r) for r in args.runs):
        full = read_log(run)
        if not full:
            print(f"{run}: no log.jsonl with validation rows, skipped", file=sys.stderr)
        log = visible(own_rows(full, drawn), offset, args.from_pairs)
        drawn |= {row_key(r) for r in full}
        if log:
            curves.append((index, run, offset, log))
    if not curves:
        print("error: none of the runs has validation rows to draw", file=sys.stderr)
        raise SystemExit(2)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("val_loss@512", "val loss @512"), ("val_loss@2048", "val loss @2048"), ("f1@512", "F1 @512"),
              ("f1@2048", "F1 @2048"), ("auc5px@2048", "H AUC@5px @2048"), ("precision@2048", "precision @2048"),
              ("val_loss_real@2048", "real val loss @2048"), ("f1_real@2048", "real F1 @2048")]
    fig, axes = plt.subplots(2, 4, figsize=(21, 7))
    summary = {}
    # tab20 rather than the default 10-colour cycle, so that up to 20 runs keep distinct colours
    colours = plt.get_cmap("tab20").colors
    for index, run, offset, log in curves:
        name = os.path.basename(os.path.normpath(run)).removesuffix(".jsonl")
        cfg = json.load(open(os.path.join(run, "config.json"))) if os.path.exists(os.path.join(run, "config.json")) else {}
        summary[name] = {"last": log[-1], "args": cfg.get("args", {})}
        x = [r["pairs"] + offset for r in log]
        for ax, (key, _) in zip(axes.ravel(), panels):
            ys = [r.get(key) for r in log]
            if all(y is None for y in ys):  # older runs have no real-pair validation
                continue
            ax.plot(x, ys, marker="o", ms=3, label=name, color=colours[index % len(colours)])
    for ax, (_, title) in zip(axes.ravel(), panels):
        ax.set_title(title)
        ax.set_xlabel("training pairs seen")
        ax.grid(alpha=0.3)
    # one legend beside the panels, so that it hides no curve
    handles = {label: h for ax in axes.ravel() for h, label in zip(*ax.get_legend_handles_labels())}
    fig.legend(list(handles.values()), list(handles), loc="center right", fontsize=8)
    fig.tight_layout(rect=(0, 0, 0.8, 1))
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
