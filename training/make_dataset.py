"""Generates self-supervised training pairs with XFeat features into npz shards.

    python training/make_dataset.py --out training/cache/train --count 6000 --keypoints 512

Shards already written are skipped, so an interrupted run resumes where it stopped.
Only ../shared/data/train/* is read (never val/).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train.data import XFeatExtractor, gt_matches, list_photos, load_photo, make_pair  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", nargs="+", default=["../shared/data/train"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--count", type=int, default=6000)
    ap.add_argument("--shard", type=int, default=250)
    ap.add_argument("--keypoints", type=int, default=512)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--size", type=int, nargs=2, default=[480, 320], metavar=("W", "H"))
    args = ap.parse_args()
    if any(os.sep + "val" in os.path.abspath(p) for p in args.photos):
        sys.exit("error: training photos must not come from val/")
    torch.set_num_threads(args.threads)
    files = list_photos(args.photos)
    photos = [load_photo(p) for p in files]
    ext = XFeatExtractor(args.keypoints)
    os.makedirs(args.out, exist_ok=True)
    t0, done = time.time(), 0
    for s0 in range(0, args.count, args.shard):
        path = os.path.join(args.out, f"shard_{s0 // args.shard:04d}.npz")
        if os.path.exists(path):
            continue
        rec = {k: [] for k in ("keypoints", "scores", "descriptors", "image_size", "matches0", "matches1", "H", "photo")}
        for i in range(s0, min(s0 + args.shard, args.count)):
            rng = np.random.default_rng([args.seed, i])
            pid = int(rng.integers(len(photos)))
            views, h = make_pair(photos[pid], rng, size=tuple(args.size))
            f0, f1 = ext(views[0], rng), ext(views[1], rng)
            m0, m1 = gt_matches(h, f0["keypoints"], f1["keypoints"], 3.0)
            rec["keypoints"].append(np.stack([f0["keypoints"], f1["keypoints"]]))
            rec["scores"].append(np.stack([f0["scores"], f1["scores"]]).astype(np.float16))
            rec["descriptors"].append(np.stack([f0["descriptors"], f1["descriptors"]]).astype(np.float16))
            rec["image_size"].append(np.stack([f0["image_size"], f1["image_size"]]))
            rec["matches0"].append(np.asarray(m0, np.int16))
            rec["matches1"].append(np.asarray(m1, np.int16))
            rec["H"].append(h)
            rec["photo"].append(pid)
            done += 1
        np.savez(path + ".tmp.npz", **{k: np.stack(v) for k, v in rec.items()})
        os.replace(path + ".tmp.npz", path)
        pos = np.mean([(np.stack(rec["matches0"]) >= 0).sum(1)])
        rate = done / (time.time() - t0)
        print(f"{path}: {done} new pairs, {rate:.1f} pairs/s, mean positives {pos:.0f}", flush=True)


if __name__ == "__main__":
    main()
