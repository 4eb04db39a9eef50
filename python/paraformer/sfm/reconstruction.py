"""From hloc-format features and matches to a COLMAP model through pycolmap: database import,
geometric verification, incremental mapping (the stages of hloc's ``reconstruction``)."""
from __future__ import annotations

import json
import multiprocessing
import shutil
import time
import warnings
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .extract_features import extract, list_images
from .io import PathLike, list_names, open_h5, read_matches, write_pairs
from .match_features import match_pairs, resolve_pairs
from .pairs import pairs_from_spec

#: pycolmap releases whose API this module was written and tested against.
PYCOLMAP_SUPPORTED = ">=3.12,<5"


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise ImportError("paraformer.sfm.reconstruct needs pycolmap: pip install 'paraformer[sfm]'") from None
    return pycolmap


def _camera_mode(pycolmap, camera_mode: str):
    modes = {"auto": "AUTO", "single": "SINGLE", "per_folder": "PER_FOLDER", "per_image": "PER_IMAGE"}
    if camera_mode not in modes:
        raise ValueError(f"camera_mode: expected one of {', '.join(modes)}, got {camera_mode!r}")
    return getattr(pycolmap.CameraMode, modes[camera_mode])


def import_into_database(image_dir: Path, database: Path, names: list[str], features_path: Path,
                         pairs: list[tuple[str, str]], matches_path: Path, camera_mode: str = "auto",
                         min_match_score: Optional[float] = None) -> dict[str, int]:
    """A fresh COLMAP database with the images, their keypoints (COLMAP's convention: origin
    at the top-left corner, so hloc's +0.5) and the raw matches of ``pairs``.

    Returns:
        COLMAP image id per name.
    """
    pycolmap = _pycolmap()
    if database.exists():
        database.unlink()
    with pycolmap.Database.open(database):
        pass  # creates the empty schema that import_images expects
    pycolmap.import_images(database, image_dir, _camera_mode(pycolmap, camera_mode), image_names=names)
    with pycolmap.Database.open(database) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        missing = [n for n in names if n not in ids]
        if missing:
            raise RuntimeError(f"COLMAP could not import {len(missing)} image(s): {missing[:5]}")
        with open_h5(features_path, "r") as fd:
            for name in names:
                if name not in fd:
                    raise KeyError(f"image {name!r} is not in the features file {features_path}")
                kpts = np.asarray(fd[name]["keypoints"][()], np.float64) + 0.5
                db.write_keypoints(ids[name], kpts.astype(np.float32))
        with open_h5(matches_path, "r") as fd:
            for a, b in pairs:
                m, s = read_matches(fd, a, b)
                if min_match_score is not None:
                    m = m[s > min_match_score]
                db.write_matches(ids[a], ids[b], m.astype(np.uint32))
    return ids


def verify(pycolmap, database: Path, pairs_path: Path, seed: Optional[int] = None) -> None:
    """pycolmap's geometric verification (two-view geometries) of the imported matches."""
    ransac = dict(max_num_trials=20000, min_inlier_ratio=0.1)
    if seed is not None:
        ransac["random_seed"] = seed
    opts = pycolmap.TwoViewGeometryOptions(ransac=ransac)
    pycolmap.verify_matches(database, pairs_path, options=opts)


def map_incremental(pycolmap, database: Path, image_dir: Path, out_dir: Path,
                    mapper_options: Optional[dict] = None, seed: Optional[int] = None):
    """Incremental mapping; the largest model goes to ``out_dir/sparse/0`` (COLMAP binary)."""
    models = out_dir / "models"
    if models.exists():
        shutil.rmtree(models)
    models.mkdir(parents=True)
    seeded = {} if seed is None else {"random_seed": seed}
    opts = pycolmap.IncrementalPipelineOptions({"num_threads": min(multiprocessing.cpu_count(), 16), **seeded,
                                                **(mapper_options or {})})
    recs = pycolmap.incremental_mapping(database, image_dir, models, options=opts)
    if not recs:
        return None
    best = max(recs, key=lambda k: recs[k].num_reg_images())
    sparse = out_dir / "sparse" / "0"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    recs[best].write(sparse)
    shutil.rmtree(models)
    return recs[best]


def _colmap_logs(pycolmap, out_dir: Path, verbose: bool) -> None:
    """COLMAP's log lines go to ``out_dir/colmap.LOG.*`` (as hloc does), and to stderr only
    when ``verbose``; warnings and errors always reach stderr."""
    pycolmap.logging.set_log_destination(pycolmap.logging.INFO, str(out_dir / "colmap.LOG."))
    pycolmap.logging.logtostderr = False
    pycolmap.logging.alsologtostderr = bool(verbose)
    pycolmap.logging.stderrthreshold = pycolmap.logging.INFO if verbose else pycolmap.logging.WARNING


def reconstruct_from_files(image_dir: PathLike, out_dir: PathLike, features_path: PathLike,
                           pairs_path: PathLike, matches_path: PathLike, *, camera_mode: str = "auto",
                           min_match_score: Optional[float] = None, mapper_options: Optional[dict] = None,
                           seed: Optional[int] = 0, timings: Optional[dict] = None, verbose: bool = False):
    """hloc-format features, pairs and matches (ours or hloc's) → COLMAP model.

    Writes ``out_dir/database.db``, ``out_dir/sparse/0/`` and ``out_dir/summary.json``.

    Args:
        image_dir: the images the features were extracted from.
        out_dir: output folder.
        features_path, pairs_path, matches_path: hloc-format inputs.
        camera_mode: ``auto``, ``single``, ``per_folder`` or ``per_image`` (COLMAP's).
        min_match_score: drop matches scored at or below this before verification.
        mapper_options: ``pycolmap.IncrementalPipelineOptions`` fields.
        seed: random seed of COLMAP's RANSAC and mapper (None: COLMAP's own, which varies
            from run to run; seeded runs can still differ slightly with several threads).
        timings: seconds of earlier stages, copied into the summary.
        verbose: show COLMAP's log on stderr (it always goes to ``out_dir/colmap.LOG.*``).
    Returns:
        The largest ``pycolmap.Reconstruction``, or None when nothing could be registered.
    """
    pycolmap = _pycolmap()
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    features_path, pairs_path, matches_path = Path(features_path), Path(pairs_path), Path(matches_path)
    for what, p in (("features_path", features_path), ("pairs_path", pairs_path), ("matches_path", matches_path)):
        if not p.is_file():
            raise FileNotFoundError(f"{what}: no file {p}")
    out_dir.mkdir(parents=True, exist_ok=True)
    _colmap_logs(pycolmap, out_dir, verbose)
    times = dict(timings or {})
    pairs = resolve_pairs(pairs_path)
    names = sorted({n for p in pairs for n in p})
    t = time.time()
    ids = import_into_database(image_dir, out_dir / "database.db", names, features_path, pairs,
                               matches_path, camera_mode, min_match_score)
    times["import_s"] = time.time() - t
    t = time.time()
    verify(pycolmap, out_dir / "database.db", pairs_path, seed)
    times["verification_s"] = time.time() - t
    t = time.time()
    rec = map_incremental(pycolmap, out_dir / "database.db", image_dir, out_dir, mapper_options, seed)
    times["mapping_s"] = time.time() - t
    summary: dict[str, Any] = {"images": len(ids), "pairs": len(pairs)}
    if rec is None:
        summary |= {"registered_images": 0, "points3D": 0}
    else:
        summary |= {"registered_images": rec.num_reg_images(), "points3D": rec.num_points3D(),
                    "mean_track_length": rec.compute_mean_track_length(),
                    "mean_observations_per_image": rec.compute_mean_observations_per_reg_image(),
                    "mean_reprojection_error_px": rec.compute_mean_reprojection_error()}
    summary["seconds"] = {k: round(v, 3) for k, v in times.items()}
    summary["pycolmap"] = pycolmap.__version__
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return rec


def reconstruct(image_dir: PathLike, out_dir: PathLike, *, matcher: Any = "paraformer-xfeat",
                pairs: Any = "exhaustive", max_keypoints: int = 4096, subpixel: bool = True, camera_mode: str = "auto",
                min_match_score: Optional[float] = None, mapper_options: Optional[dict] = None,
                seed: Optional[int] = 0, batch: int = 32, progress: bool = True, verbose: bool = False, backend: str = "local",
                **ray_options):
    """A folder of photos → a COLMAP reconstruction: XFeat, pairs, matching, database import,
    pycolmap's geometric verification and incremental mapping.

    Writes ``out_dir/features.h5``, ``pairs.txt``, ``matches.h5``, ``database.db``,
    ``sparse/0/`` (COLMAP binary model) and ``summary.json`` (registered images, points,
    mean track length, mean reprojection error, seconds per stage). Features and matches
    already in ``out_dir`` are reused (the run resumes).

    Args:
        image_dir: the photos (searched recursively).
        out_dir: output folder.
        matcher: pretrained name, ``mnn``/``nn``/``ratio[:R]``, a weights file or a ``Matcher``.
        pairs: ``"exhaustive"``, ``"sequential:N"``, a pairs file or a list of name pairs.
        max_keypoints: XFeat keypoints per image (4096: on Strecha entry-P10 it took the median
            rotation error from 0.6° at 2048 to 0.3°; ``extract`` alone defaults to 2048).
        subpixel: sub-pixel XFeat keypoints (see ``extract``).
        camera_mode: ``auto``, ``single``, ``per_folder`` or ``per_image``.
        min_match_score: drop matches scored at or below this.
        mapper_options: ``pycolmap.IncrementalPipelineOptions`` fields.
        seed: random seed of COLMAP's RANSAC and mapper (None: COLMAP's own).
        batch: pairs per ``match_many`` call.
        progress: show progress bars.
        verbose: show COLMAP's log on stderr (it always goes to ``out_dir/colmap.LOG.*``).
        backend: ``"local"`` or ``"ray"`` for extraction and matching.
        ray_options: ``address``, ``num_workers``, ``threads_per_worker`` for ``backend="ray"``.
    Returns:
        The largest ``pycolmap.Reconstruction``, or None when nothing could be registered.
    """
    pycolmap = _pycolmap()
    _camera_mode(pycolmap, camera_mode)
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    names = list_images(image_dir)
    if len(names) < 2:
        raise ValueError(f"image_dir: a reconstruction needs at least 2 images, found {len(names)} in {image_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    t = time.time()
    extract(image_dir, out_dir / "features.h5", max_keypoints=max_keypoints, subpixel=subpixel, progress=progress,
            backend=backend, **ray_options)
    times["extract_s"] = time.time() - t
    unknown = sorted({n for p in pairs_from_spec(pairs, names) for n in p} - set(names))
    if unknown:
        raise ValueError(f"pairs: {len(unknown)} image(s) not under {image_dir}: {unknown[:5]}")
    readable = set(list_names(out_dir / "features.h5"))
    skipped = [n for n in names if n not in readable]  # unreadable files, warned about by extract
    names = [n for n in names if n in readable]
    if len(names) < 2:
        raise ValueError(f"image_dir: a reconstruction needs at least 2 readable images, found {len(names)}")
    pair_list = [p for p in resolve_pairs(pairs_from_spec(pairs, names)) if p[0] in readable and p[1] in readable]
    if skipped:
        warnings.warn(f"{len(skipped)} unreadable image(s) left out of the reconstruction: {skipped[:5]}", stacklevel=2)
    write_pairs(pair_list, out_dir / "pairs.txt")
    t = time.time()
    match_pairs(out_dir / "features.h5", pair_list, out_dir / "matches.h5", matcher=matcher, batch=batch,
                progress=progress, backend=backend, **ray_options)
    times["match_s"] = time.time() - t
    return reconstruct_from_files(image_dir, out_dir, out_dir / "features.h5", out_dir / "pairs.txt",
                                  out_dir / "matches.h5", camera_mode=camera_mode,
                                  min_match_score=min_match_score, mapper_options=mapper_options,
                                  seed=seed, timings=times, verbose=verbose)


__all__ = ["reconstruct", "reconstruct_from_files", "import_into_database", "PYCOLMAP_SUPPORTED"]
