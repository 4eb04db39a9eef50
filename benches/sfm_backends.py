"""Throughput of paraformer.sfm's backends side by side in one run: extraction (images/s)
and pair matching (pairs/s) with the local backend and with Ray at 1 and 2 workers, plus
the Ray overheads (start-up, feature shipping, the single h5 writer). Outputs are checked
identical to the local backend's.

    python benches/sfm_backends.py --images ../shared/data/pose/scannet_sample/images \\
        --pairs 120 --out benches/results/sfm_backends.json
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np


def same(a: Path, b: Path) -> bool:
    def items(p):
        out = {}
        with h5py.File(p, "r") as f:
            f.visititems(lambda n, o: out.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) else None)
        return out
    x, y = items(a), items(b)
    return sorted(x) == sorted(y) and all(np.array_equal(x[k], y[k]) for k in x)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--pairs", type=int, default=120, help="sequential pairs to match (first N)")
    ap.add_argument("--max-keypoints", type=int, default=2048)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()

    import ray

    from paraformer import sfm
    from paraformer.sfm import ray_backend

    names = sfm.list_images(a.images)
    pairs = sfm.pairs_sequential(names, 10)[: a.pairs]
    res: dict = {"images": len(names), "pairs": len(pairs), "max_keypoints": a.max_keypoints,
                 "cpus": os.cpu_count(), "rows": {}}
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        t0 = time.time()
        sfm.extract(a.images, t / "f_local.h5", max_keypoints=a.max_keypoints, progress=False)
        ext = time.time() - t0
        t0 = time.time()
        sfm.match_pairs(t / "f_local.h5", pairs, t / "m_local.h5", batch=a.batch, progress=False)
        mat = time.time() - t0
        res["rows"]["local (2 threads)"] = {"extract_img_per_s": len(names) / ext, "match_pairs_per_s": len(pairs) / mat}
        print(res["rows"]["local (2 threads)"], flush=True)

        t0 = time.time()
        ray_backend.init(None)
        res["ray_start_s"] = time.time() - t0
        for workers, threads in ((1, 2), (2, 1)):
            key = f"ray {workers} worker(s) × {threads} thread(s)"
            t0 = time.time()
            sfm.extract(a.images, t / f"f_{workers}.h5", max_keypoints=a.max_keypoints, progress=False,
                        backend="ray", num_workers=workers, threads_per_worker=threads)
            ext = time.time() - t0
            t0 = time.time()
            sfm.match_pairs(t / "f_local.h5", pairs, t / f"m_{workers}.h5", batch=a.batch, progress=False,
                            backend="ray", num_workers=workers, threads_per_worker=threads)
            mat = time.time() - t0
            res["rows"][key] = {"extract_img_per_s": len(names) / ext, "match_pairs_per_s": len(pairs) / mat,
                                "features_identical": same(t / "f_local.h5", t / f"f_{workers}.h5"),
                                "matches_identical": same(t / "m_local.h5", t / f"m_{workers}.h5")}
            print(key, res["rows"][key], flush=True)
        # Overheads: putting the features in the object store, and writing results alone.
        from paraformer.sfm.io import read_features, write_matches

        with h5py.File(t / "f_local.h5", "r") as fd:
            feats = {n: read_features(fd, n) for n in names}
        t0 = time.time()
        ref = ray.put(feats)
        res["features_put_s"] = time.time() - t0
        res["features_mb"] = sum(sum(v.nbytes for v in f.values()) for f in feats.values()) / 2**20
        del ref
        # Result serialisation: one batch of match results as the workers return it
        # (int64 matches + float32 scores as bytes), through the object store and back.
        batch = {"index": np.arange(len(pairs)),
                 "matches0": np.array([np.zeros(a.max_keypoints, "<i8").tobytes()] * len(pairs), dtype=object),
                 "matching_scores0": np.array([np.zeros(a.max_keypoints, "<f4").tobytes()] * len(pairs), dtype=object)}
        t0 = time.time()
        ray.get(ray.put(batch))
        res["results_roundtrip_pairs_per_s"] = len(pairs) / (time.time() - t0)
        res["result_kb_per_pair"] = a.max_keypoints * 12 / 1024
        m0 = np.zeros(a.max_keypoints, np.int64)
        s0 = np.zeros(a.max_keypoints, np.float32)
        t0 = time.time()
        with h5py.File(t / "w.h5", "w") as fd:
            for x, y in pairs:
                write_matches(fd, x, y, m0, s0)
        res["h5_writer_pairs_per_s"] = len(pairs) / (time.time() - t0)
    print(json.dumps(res, indent=1))
    if a.out:
        a.out.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
