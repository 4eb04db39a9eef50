"""Generates training pairs into numbered shards of a pool folder (see
``paraformer_train/stream.py``). The trainer starts it itself (``train.py``), from the
shard its checkpoint reached; it can also run alone, e.g. for a fixed validation set:

    python training/generate_pairs.py --pool training/cache/holdout --seed 1 --shards 2 \
        --photos ../shared/data/train/bsds500_val --rgbd-split holdout

Features are the project's XFeat (``paraformer.extract``, top-2048); ground truth is not
stored but rebuilt by the trainer from each keypoint's projection, for whatever top-k it cuts.
Only ``../shared/data/train`` and ``../shared/data/rgbd`` are read, never ``val/``,
``pose/`` or ``homography/``.
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paraformer_train import data, rgbd, stream  # noqa: E402

SHARED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "..", "shared", "data")
TRAIN_PHOTOS = [os.path.join(SHARED, "train", d) for d in ("bsds500_train", "urban100", "sun80")]
RGBD_CACHE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cache", "rgbd_pairs")


def train_rgbd() -> list[str]:
    """The RGB-D sequence folders that ``rgbd.usable`` accepts."""
    return [p for p in sorted(glob.glob(os.path.join(SHARED, "rgbd", "*"))) if rgbd.usable(p)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pool", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0, help="first shard index")
    ap.add_argument("--shards", type=int, default=None, help="stop after this many shard indices (default: endless)")
    ap.add_argument("--shard-size", type=int, default=128)
    ap.add_argument("--max-pending", type=int, default=24, help="wait while this many shards are on disk")
    ap.add_argument("--photos", nargs="+", default=TRAIN_PHOTOS)
    ap.add_argument("--rgbd", nargs="*", default=train_rgbd(),
                    help="RGB-D sequence folders (default: all that rgbd.usable accepts)")
    ap.add_argument("--rgbd-split", choices=["train", "holdout"], default="train")
    ap.add_argument("--real-fraction", type=float, default=0.2)
    ap.add_argument("--heavy-noise", type=data.probability, default=0.0,
                    help="probability per view of Gaussian noise of sigma 15-80 instead of 2-12 (default 0: the stream unchanged)")
    ap.add_argument("--real-warp", type=data.probability, default=0.0,
                    help="probability per view of a real pair that the view is a rotated, scaled, perspective patch "
                         "of its frame (default 0: the stream unchanged)")
    ap.add_argument("--cache", default=RGBD_CACHE)
    ap.add_argument("--parent", type=int, default=None, help="exit when this process is gone")
    args = ap.parse_args()
    for p in args.photos:
        if os.sep + "val" + os.sep in os.path.abspath(p) + os.sep:
            sys.exit("error: training photos must not come from val/")
    os.makedirs(args.pool, exist_ok=True)
    src = pair_source(args.seed, args.real_fraction, args.heavy_noise, args.photos, args.rgbd, args.rgbd_split, args.cache,
                      args.real_warp)
    print(f"generator: {len(src.photos)} photos, RGB-D pairs {[len(p) for _, p in src.sequences]}, "
          f"real fraction {src.real_fraction}, heavy noise {src.heavy_noise}, real warp {src.real_warp}, from shard {args.start}", flush=True)
    index = args.start
    t0, made = time.time(), 0
    while args.shards is None or index < args.start + args.shards:
        path = stream.shard_path(args.pool, index)
        if os.path.exists(path):
            index += 1
            continue
        while len(stream.shard_files(args.pool)) >= args.max_pending:
            if args.parent is not None and not _alive(args.parent):
                return
            time.sleep(3)
        if args.parent is not None and not _alive(args.parent):
            return
        pairs = write_shard(src, args.pool, index, args.shard_size)
        made += len(pairs)
        kp = np.mean([min(len(p["f"][0]["keypoints"]), len(p["f"][1]["keypoints"])) for p in pairs])
        print(f"{os.path.basename(path)}: {made / (time.time() - t0):.1f} pairs/s, mean keypoints {kp:.0f}, "
              f"real {sum(p['kind'] for p in pairs)}", flush=True)
        index += 1


def pair_source(seed: int, real_fraction: float, heavy_noise: float = 0.0, photos: list[str] | None = None,
                rgbd_dirs: list[str] | None = None, split: str = "train", cache: str | None = None,
                real_warp: float = 0.0) -> stream.PairSource:
    """The stream's pair maker (defaults: the training photos and RGB-D sequences)."""
    import cv2

    cv2.setNumThreads(1)
    photos = TRAIN_PHOTOS if photos is None else photos
    rgbd_dirs = train_rgbd() if rgbd_dirs is None else rgbd_dirs
    seqs = rgbd.split_pairs([r for r in rgbd_dirs if os.path.isdir(r)], split, cache or RGBD_CACHE)
    return stream.PairSource(data.list_photos(photos), seqs, seed, real_fraction, heavy_noise=heavy_noise,
                             real_warp=real_warp)


def write_shard(src: stream.PairSource, pool: str, index: int, shard_size: int) -> list[dict]:
    """Shard ``index`` of ``src``'s stream into ``pool`` (pairs ``index·size …``); returns its pairs."""
    pairs = [src.pair(index * shard_size + i) for i in range(shard_size)]
    stream.write_shard(stream.shard_path(pool, index), pairs)
    return pairs


class InlineGenerator:
    """The generator inside the trainer (``train.py --generate-inline``): between steps, on
    the trainer's cores, it writes the next shards of the same stream while fewer than
    ``ahead`` wait on disk, instead of a process competing with every step."""

    def __init__(self, src: stream.PairSource, pool: str, start: int, shard_size: int, ahead: int = 2):
        os.makedirs(pool, exist_ok=True)
        self.src, self.pool, self.next, self.shard_size, self.ahead = src, pool, start, shard_size, ahead
        self.seconds, self.made = 0.0, 0

    def top_up(self, waiting: int, seen: int) -> None:
        """``waiting``: shards on disk that the reader has not loaded yet; ``seen``: the highest
        shard index it has loaded or retired (a retired shard is gone from disk, not to be
        made again)."""
        t = time.time()
        self.next = max(self.next, seen + 1)
        while waiting < self.ahead:
            if not os.path.exists(stream.shard_path(self.pool, self.next)):
                self.made += len(write_shard(self.src, self.pool, self.next, self.shard_size))
                waiting += 1
            self.next += 1
        self.seconds += time.time() - t


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except OSError:
        return False


if __name__ == "__main__":
    main()
