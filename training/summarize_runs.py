"""A markdown table of short runs' validations (their ``log.jsonl``), one row per run and
validation, for comparisons at equal pairs (``compare_configs.sh``, ``compare_finetunes.sh``):

    python training/summarize_runs.py training/runs/compare_finetunes/* [--last] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import sys

COLUMNS = [("pairs", "pairs", "{:.0f}"), ("loss", "train loss", "{:.3f}"), ("val_loss@512", "val loss @512", "{:.3f}"),
           ("val_loss@2048", "val loss @2048", "{:.3f}"), ("precision@2048", "P@2048", "{:.3f}"),
           ("recall@2048", "R@2048", "{:.3f}"), ("f1@2048", "F1@2048", "{:.3f}"), ("auc1px@2048", "AUC@1px", "{:.3f}"),
           ("auc3px@2048", "AUC@3px", "{:.3f}"), ("auc5px@2048", "AUC@5px", "{:.3f}"), ("train_s", "train s", "{:.0f}")]


def read_log(run: str) -> list[dict]:
    path = os.path.join(run, "log.jsonl")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{run}: no log.jsonl (not a train.py run folder, or it has not validated yet)")
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def table(rows: list[tuple[str, dict]]) -> str:
    out = ["| run | " + " | ".join(h for _, h, _ in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for name, rec in rows:
        cells = [fmt.format(rec[k]) if isinstance(rec.get(k), (int, float)) else "–" for k, _, fmt in COLUMNS]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="train.py --run folders (non-folders are skipped)")
    ap.add_argument("--last", action="store_true", help="only each run's last validation")
    ap.add_argument("--json", default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    rows = []
    for run in args.runs:
        if not os.path.isdir(run):
            continue
        try:
            recs = read_log(run)
        except FileNotFoundError as e:
            print(f"skipped {e}", file=sys.stderr)
            continue
        recs = recs[-1:] if args.last else recs
        rows += [(os.path.basename(os.path.normpath(run)), r) for r in recs]
    if not rows:
        print("error: none of the folders has a log.jsonl", file=sys.stderr)
        return 2
    print(table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump([{"run": n} | r for n, r in rows], f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
