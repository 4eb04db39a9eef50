"""``paraformer-sfm`` / ``python -m paraformer.sfm``: photos → features, matches, COLMAP model."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from .. import ParaformerError


def _ray_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=["local", "ray"], default="local",
                   help="where extraction and matching run (default: local threads)")
    p.add_argument("--address", default=None,
                   help="Ray cluster address for --backend ray ('auto' or host:port; default: a local Ray)")
    p.add_argument("--workers", type=int, default=None, help="Ray workers (default: 1 per 2 CPUs)")
    p.add_argument("--threads-per-worker", type=int, default=None, help="Rust threads per Ray worker (default 2)")


def _ray_options(a: argparse.Namespace) -> dict:
    if a.backend != "ray":
        for flag, v in (("--address", a.address), ("--workers", a.workers), ("--threads-per-worker", a.threads_per_worker)):
            if v is not None:
                raise ValueError(f"{flag} needs --backend ray")
        return {}
    opts = {"address": a.address}
    if a.workers is not None:
        opts["num_workers"] = a.workers
    if a.threads_per_worker is not None:
        opts["threads_per_worker"] = a.threads_per_worker
    return opts


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="paraformer-sfm", description=__doc__)
    sub = ap.add_subparsers(dest="command", required=True)

    r = sub.add_parser("reconstruct", help="photos → features.h5, pairs.txt, matches.h5, database.db, sparse/0")
    r.add_argument("images", type=Path, help="folder of photos (searched recursively)")
    r.add_argument("out", type=Path, help="output folder")
    r.add_argument("--matcher", default="paraformer-xfeat",
                   help="pretrained name, mnn, nn, ratio[:R] or a weights file (default paraformer-xfeat)")
    r.add_argument("--pairs", default="exhaustive", help="exhaustive, sequential:N or a pairs file (default exhaustive)")
    r.add_argument("--max-keypoints", type=int, default=4096, help="XFeat keypoints per image (default 4096)")
    r.add_argument("--no-subpixel", dest="subpixel", action="store_false",
                   help="whole-pixel keypoints, as the original XFeat (default: sub-pixel)")
    r.add_argument("--seed", type=int, default=0, help="random seed of COLMAP's verification and mapping (default 0)")
    r.add_argument("--camera-mode", default="auto", choices=["auto", "single", "per_folder", "per_image"],
                   help="COLMAP camera sharing (default auto)")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--verbose", action="store_true", help="show COLMAP's log (always written to OUT/colmap.LOG.*)")
    _ray_args(r)

    e = sub.add_parser("extract", help="XFeat on every photo → hloc features.h5")
    e.add_argument("images", type=Path, help="folder of photos")
    e.add_argument("features", type=Path, help="features.h5 to create or extend")
    e.add_argument("--max-keypoints", type=int, default=2048, help="keypoints per image (default 2048)")
    e.add_argument("--no-subpixel", dest="subpixel", action="store_false",
                   help="whole-pixel keypoints, as the original XFeat (default: sub-pixel)")
    e.add_argument("--overwrite", action="store_true", help="recompute images already in the file")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    _ray_args(e)

    p = sub.add_parser("pairs", help="write a pairs file for a folder of photos")
    p.add_argument("images", type=Path, help="folder of photos")
    p.add_argument("out", type=Path, help="pairs file to write")
    p.add_argument("--pairs", default="exhaustive", help="exhaustive or sequential:N (default exhaustive)")

    m = sub.add_parser("match", help="match the pairs of a pairs file → hloc matches.h5")
    m.add_argument("features", type=Path, help="hloc features.h5")
    m.add_argument("pairs", type=Path, help="pairs file")
    m.add_argument("matches", type=Path, help="matches.h5 to create or extend")
    m.add_argument("--matcher", default="paraformer-xfeat", help="as for reconstruct")
    m.add_argument("--batch", type=int, default=32, help="pairs per match_many call (default 32)")
    m.add_argument("--overwrite", action="store_true", help="recompute pairs already in the file")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    _ray_args(m)
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Console entry point; returns the exit code (1 with a one-line error on bad input)."""
    a = _parser().parse_args(argv)
    try:
        from . import extract, match_pairs, reconstruct, write_pairs
        from .extract_features import list_images
        from .pairs import pairs_from_spec

        if a.command == "reconstruct":
            rec = reconstruct(a.images, a.out, matcher=a.matcher, pairs=a.pairs, max_keypoints=a.max_keypoints,
                              subpixel=a.subpixel, seed=a.seed, camera_mode=a.camera_mode, progress=not a.quiet, verbose=a.verbose, backend=a.backend, **_ray_options(a))
            summary = json.loads((a.out / "summary.json").read_text())
            print(json.dumps(summary, indent=1))
            if rec is None:
                print("no model: COLMAP registered no image pair", file=sys.stderr)
                return 2
        elif a.command == "extract":
            extract(a.images, a.features, max_keypoints=a.max_keypoints, subpixel=a.subpixel, overwrite=a.overwrite,
                    progress=not a.quiet, backend=a.backend, **_ray_options(a))
        elif a.command == "pairs":
            pairs = pairs_from_spec(a.pairs, list_images(a.images))
            write_pairs(pairs, a.out)
            print(f"wrote {len(pairs)} pairs to {a.out}")
        elif a.command == "match":
            match_pairs(a.features, a.pairs, a.matches, matcher=a.matcher, batch=a.batch, overwrite=a.overwrite,
                        progress=not a.quiet, backend=a.backend, **_ray_options(a))
    except (ValueError, TypeError, KeyError, OSError, ImportError, RuntimeError, ParaformerError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"paraformer-sfm: error: {msg}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
