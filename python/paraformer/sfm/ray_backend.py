"""Extraction and pair matching fanned out on Ray Data (``backend="ray"``).

Each Ray actor holds one XFeat or one ``Matcher`` and runs batches with its Rust thread pool
sized to the CPUs Ray gives it (``threads_per_worker``). Matching ships the features once:
the driver puts every needed image's features into Ray's object store, and each actor
fetches that one object when it starts (zero-copy for the arrays on its node); the rows
that flow through Ray Data are only pair indices. The driver alone writes the h5 file, in
the same layout and through the same writer as the local backend, as results stream back;
what is already in the file is skipped before anything is dispatched, so an interrupted
run resumes. Ray Data restarts a killed actor and retries its batch.

Images are read by the actors: on a cluster, ``image_dir`` must be visible to every node
(a shared file system). Needs ``pip install 'paraformer[ray]'``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .io import open_h5, read_features, write_features, write_matches
from .progress import bar


def _ray():
    try:
        import ray
    except ImportError:
        raise ImportError("backend='ray' needs Ray: pip install 'paraformer[ray]'") from None
    return ray


def init(address: Optional[str] = None) -> Any:
    """Connects to Ray once per process: ``None`` starts a local Ray on this machine,
    ``"auto"`` or ``"host:port"`` joins a running cluster. Returns the ``ray`` module."""
    ray = _ray()
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False, ignore_reinit_error=True)
    return ray


def _pool_options(ray, num_workers: Optional[int], threads_per_worker: Optional[int]) -> tuple[int, int]:
    threads = 2 if threads_per_worker is None else threads_per_worker
    if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
        raise ValueError(f"threads_per_worker: expected a positive int, got {threads_per_worker!r}")
    if num_workers is None:
        num_workers = max(1, int(ray.cluster_resources().get("CPU", 1)) // threads)
    if not isinstance(num_workers, int) or isinstance(num_workers, bool) or num_workers < 1:
        raise ValueError(f"num_workers: expected a positive int, got {num_workers!r}")
    return num_workers, threads


def _remote_args(threads: int) -> dict:
    # The Rust core sizes its global pool from RAYON_NUM_THREADS when it first runs.
    return {"num_cpus": threads, "runtime_env": {"env_vars": {"RAYON_NUM_THREADS": str(threads)}}}


class XFeatWorker:
    """A Ray Data actor: image names → XFeat features (flat little-endian buffers)."""

    def __init__(self, image_dir: str, max_keypoints: int, subpixel: bool = True):
        self.image_dir, self.max_keypoints, self.subpixel = Path(image_dir), max_keypoints, subpixel

    def __call__(self, batch: dict) -> dict:
        import paraformer

        out: dict[str, list] = {"name": [], "keypoints": [], "descriptors": [], "scores": [], "image_size": []}
        for name in batch["name"]:
            f = paraformer.extract(os.fspath(self.image_dir / str(name)), max_keypoints=self.max_keypoints,
                                   subpixel=self.subpixel)
            out["name"].append(str(name))
            for key in ("keypoints", "descriptors", "scores", "image_size"):
                out[key].append(np.ascontiguousarray(f[key], "<f4").tobytes())
        return {k: np.array(v, dtype=object) for k, v in out.items()}


class MatchWorker:
    """A Ray Data actor: pair indices → matches of one ``Matcher`` (flat buffers)."""

    def __init__(self, matcher: Any, features_ref: list, pairs: Sequence[tuple[str, str]], threads: int):
        import ray

        from ..pipeline import load_matcher

        self.model = load_matcher(matcher)
        self.features = ray.get(features_ref[0])  # once per actor
        self.pairs, self.threads = pairs, threads

    def __call__(self, batch: dict) -> dict:
        idx = [int(i) for i in batch["index"]]
        chunk = [(self.features[self.pairs[i][0]], self.features[self.pairs[i][1]]) for i in idx]
        outs = self.model.match_many(chunk, num_threads=self.threads)
        return {"index": np.array(idx, np.int64),
                "matches0": np.array([np.asarray(o["matches0"], "<i8").tobytes() for o in outs], dtype=object),
                "matching_scores0": np.array([np.asarray(o["matching_scores0"], "<f4").tobytes() for o in outs],
                                             dtype=object)}


def _stream(ds, batch: int, handle: Callable[[dict], int], total: int, desc: str, unit: str, progress: bool) -> None:
    import time

    t0, done = time.time(), 0
    with bar(total, desc, unit, progress) as pb:
        for b in ds.iter_batches(batch_size=batch, batch_format="numpy", prefetch_batches=2):
            n = handle(b)
            done += n
            pb.update(n)
            pb.set_postfix_str(f"{done / max(time.time() - t0, 1e-9):.1f} {unit}/s")


def _quiet_data(ray) -> None:
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False  # ours shows the same count, from the single writer
    ctx.verbose_stats_logs = False
    if hasattr(ctx, "print_on_execution_start"):
        ctx.print_on_execution_start = False


def extract_ray(image_dir: Path, features_path: Path, names: Sequence[str], *, max_keypoints: int,
                subpixel: bool = True, as_half: bool = False, progress: bool = True, address: Optional[str] = None,
                num_workers: Optional[int] = None, threads_per_worker: Optional[int] = None,
                batch: int = 4) -> Path:
    """``extract`` on Ray: one XFeat per actor; the driver writes ``features_path``."""
    ray = init(address)
    _quiet_data(ray)
    workers, threads = _pool_options(ray, num_workers, threads_per_worker)
    ds = ray.data.from_items([{"name": n} for n in names], override_num_blocks=max(1, min(len(names), 4 * workers)))
    ds = ds.map_batches(XFeatWorker, fn_constructor_kwargs={"image_dir": os.fspath(image_dir),
                                                            "max_keypoints": max_keypoints,
                                                            "subpixel": subpixel},
                        batch_size=batch, batch_format="numpy", compute=ray.data.ActorPoolStrategy(size=workers),
                        **_remote_args(threads))
    with open_h5(features_path, "a") as fd:
        def handle(b: dict) -> int:
            for i, name in enumerate(b["name"]):
                feats = {"keypoints": np.frombuffer(b["keypoints"][i], "<f4").reshape(-1, 2),
                         "descriptors": np.frombuffer(b["descriptors"][i], "<f4").reshape(-1, 64),
                         "scores": np.frombuffer(b["scores"][i], "<f4"),
                         "image_size": np.frombuffer(b["image_size"][i], "<f4")}
                write_features(fd, str(name), feats, as_half)
            fd.flush()
            return len(b["name"])

        _stream(ds, batch, handle, len(names), "extract (ray)", "img", progress)
    return features_path


def match_pairs_ray(features_path: Path, pairs: Sequence[tuple[str, str]], matches_path: Path, *, matcher: Any,
                    tag: str, batch: int = 32, progress: bool = True, address: Optional[str] = None,
                    num_workers: Optional[int] = None, threads_per_worker: Optional[int] = None,
                    on_batch: Optional[Callable[[int], None]] = None) -> Path:
    """``match_pairs`` on Ray: features shipped once per actor, the driver writes ``matches_path``.

    ``on_batch(pairs_done)`` is called after each written batch (progress hooks, tests).
    """
    import paraformer

    if isinstance(matcher, paraformer.Matcher):
        raise ValueError("matcher: backend='ray' takes a pretrained name, a baseline or a weights file "
                         "(each worker loads its own), not a Matcher object")
    ray = init(address)
    _quiet_data(ray)
    workers, threads = _pool_options(ray, num_workers, threads_per_worker)
    names = sorted({n for p in pairs for n in p})
    with open_h5(features_path, "r") as ffd:
        features = {n: read_features(ffd, n) for n in names}
    ref = ray.put(features)
    del features
    pairs = [(a, b) for a, b in pairs]
    # In-memory items: a read task would need a CPU that the actors may all hold.
    ds = ray.data.from_items([{"index": i} for i in range(len(pairs))],
                             override_num_blocks=max(1, min(len(pairs) // batch + 1, 8 * workers)))
    ds = ds.map_batches(MatchWorker, fn_constructor_kwargs={"matcher": os.fspath(matcher) if isinstance(matcher, os.PathLike) else matcher,
                                                          "features_ref": [ref], "pairs": pairs, "threads": threads},
                        batch_size=batch, batch_format="numpy", compute=ray.data.ActorPoolStrategy(size=workers),
                        **_remote_args(threads))
    done = 0
    with open_h5(matches_path, "a") as mfd:
        mfd.attrs["paraformer_matcher"] = tag

        def handle(b: dict) -> int:
            nonlocal done
            for i, k in enumerate(b["index"]):
                a, c = pairs[int(k)]
                write_matches(mfd, a, c, np.frombuffer(b["matches0"][i], "<i8"),
                              np.frombuffer(b["matching_scores0"][i], "<f4"))
            mfd.flush()
            done += len(b["index"])
            if on_batch is not None:
                on_batch(done)
            return len(b["index"])

        _stream(ds, batch, handle, len(pairs), "match (ray)", "pair", progress)
    del ref
    return matches_path
