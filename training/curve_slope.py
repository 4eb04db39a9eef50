"""How fast a run's validation improves with the pairs it has seen: the least-squares slope
of each metric against log2(pairs), i.e. the change per doubling of the pairs, and how many
doublings that slope would need to reach a target (e.g. LighterGlue's F1 on the holdout).

    python training/curve_slope.py training/checkpoints/paraformer-xfeat-w96-alpha025 \
        --from-pairs 90000 --target f1@2048=0.803

Reads the run's ``log.jsonl`` (the validations ``train.py`` appends); prints one line per metric.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

METRICS = ("val_loss@2048", "f1@2048", "f1_synthetic@2048", "f1_real@2048", "val_loss@512")


def slope(records: list[dict], key: str) -> tuple[float, float, int] | None:
    """(change per doubling, fitted value at the last record's pairs, points) or None when
    fewer than three validations carry ``key``."""
    pts = [(math.log2(r["pairs"]), r[key]) for r in records if r.get(key) is not None and r["pairs"] > 0]
    if len(pts) < 3:
        return None
    x, y = np.array(pts).T
    b, a = np.polyfit(x, y, 1)
    return float(b), float(a + b * x.max()), len(pts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a run folder holding log.jsonl (or the log itself)")
    ap.add_argument("--from-pairs", type=int, default=0, help="fit only validations at or after this many pairs")
    ap.add_argument("--metric", action="append", help=f"metrics to fit (default: {', '.join(METRICS)})")
    ap.add_argument("--target", action="append", default=[], metavar="METRIC=VALUE",
                    help="also print the doublings of pairs the slope needs to reach VALUE")
    args = ap.parse_args()
    path = os.path.join(args.run, "log.jsonl") if os.path.isdir(args.run) else args.run
    try:
        with open(path) as f:
            records = [json.loads(line) for line in f if line.strip()]
    except (OSError, json.JSONDecodeError) as e:
        sys.exit(f"error: {path}: {e}")
    records = [r for r in records if r.get("pairs", 0) >= args.from_pairs and "val_loss@512" in r]
    if not records:
        sys.exit(f"error: {path}: no validations at or after {args.from_pairs} pairs")
    targets = {}
    for t in args.target:
        key, _, value = t.partition("=")
        try:
            targets[key] = float(value)
        except ValueError:
            sys.exit(f"error: --target {t!r}: expected METRIC=VALUE, e.g. f1@2048=0.803")
    print(f"{path}: {len(records)} validations, {records[0]['pairs']:,}..{records[-1]['pairs']:,} pairs")
    for key in args.metric or list(METRICS) + [k for k in targets if k not in METRICS]:
        fit = slope(records, key)
        if fit is None:
            print(f"  {key}: fewer than 3 validations carry it")
            continue
        b, now, n = fit
        line = f"  {key}: {b:+.4f} per doubling of pairs (n={n}; fitted {now:.3f} at {records[-1]['pairs']:,})"
        if key in targets:
            gap = targets[key] - now
            if b != 0 and gap / b > 0:
                need = gap / b
                line += f"; {targets[key]:g} needs {need:.1f} more doublings ({2 ** need:,.0f}x the pairs)"
            else:
                line += f"; {targets[key]:g} is not approached at this slope"
        print(line)


if __name__ == "__main__":
    main()
