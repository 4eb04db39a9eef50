"""XFeat on every image of a folder into an hloc ``features.h5`` (resumable)."""
from __future__ import annotations

import json
import os
import warnings
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Optional, Sequence

from .io import PathLike, open_h5, list_names, write_features
from .progress import bar

FEATURES_ATTR = "paraformer_features"  # file attribute: the extraction settings (JSON)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".pgm", ".ppm", ".pnm", ".pbm", ".bmp", ".tif", ".tiff", ".webp"}


def list_images(image_dir: PathLike) -> list[str]:
    """Image files under ``image_dir`` (recursively), as sorted names relative to it with
    ``/`` separators, the names hloc and COLMAP use."""
    root = Path(image_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"image_dir: {root} is not a folder")
    names = [p.relative_to(root).as_posix() for p in root.rglob("*")
             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    bad = [n for n in names if any(c.isspace() for c in n)]
    if bad:
        raise ValueError(f"image_dir: image names with whitespace cannot go into a pairs file: {bad[:3]}")
    return sorted(names)


def _check_names(image_dir: Path, names: Sequence[str]) -> list[str]:
    out = []
    for n in names:
        if not isinstance(n, str) or not (image_dir / n).is_file():
            raise FileNotFoundError(f"image_list: {n!r} is not a file under {image_dir}")
        out.append(Path(n).as_posix())
    return out


def _named(e: Exception, path: Path) -> Exception:
    """The same exception type with the image path in front of its message (when the type
    can be built from one string; else the original)."""
    if str(path) in str(e):
        return e
    try:
        return type(e)(f"{path}: {e}")
    except Exception:
        return e


def extract(image_dir: PathLike, features_path: PathLike, *, max_keypoints: int = 2048,
            subpixel: bool = True, overwrite: bool = False, image_list: Optional[Sequence[str]] = None,
            num_workers: Optional[int] = None, as_half: bool = False, progress: bool = True,
            backend: str = "local", **ray_options) -> Path:
    """XFeat keypoints and descriptors of every image into hloc's ``features.h5`` layout.

    Images already in the file are skipped unless ``overwrite`` (an interrupted run resumes);
    each image is written as soon as it is done. A file written with other settings
    (``max_keypoints``, ``subpixel``; its ``paraformer_features`` attribute) is a ValueError
    unless ``overwrite``. An unreadable image is skipped with a
    warning naming it; ValueError when no image at all can be read.

    Args:
        image_dir: the folder of images (searched recursively).
        features_path: the h5 file to create or extend.
        max_keypoints: keep at most this many keypoints per image, best score first.
        subpixel: sub-pixel keypoints (``paraformer.extract``'s ``subpixel``): on by
            default here, where they feed triangulation and bundle adjustment.
        overwrite: recompute images already in the file.
        image_list: names relative to ``image_dir`` to extract (default: every image).
        num_workers: images in flight at once (default: 2; each uses the Rust thread pool).
        as_half: store descriptors and scores as float16, as hloc's ``as_half``.
        progress: show a progress bar.
        backend: ``"local"`` (threads in this process) or ``"ray"`` (see ``paraformer.sfm.ray_backend``).
        ray_options: ``address``, ``num_workers``, ``threads_per_worker`` for ``backend="ray"``.
    Returns:
        ``features_path``.
    """
    import paraformer

    if not isinstance(max_keypoints, int) or isinstance(max_keypoints, bool) or max_keypoints < 1:
        raise ValueError(f"max_keypoints: expected a positive int, got {max_keypoints!r}")
    image_dir, features_path = Path(image_dir), Path(features_path)
    names = list_images(image_dir) if image_list is None else _check_names(image_dir, image_list)
    if not names:
        raise FileNotFoundError(f"image_dir: no images ({', '.join(sorted(IMAGE_SUFFIXES))}) under {image_dir}")
    # The settings that shape the features: a resumed run must not mix them (a folder first
    # extracted at 2048 keypoints would silently stay at 2048 when rerun at 4096).
    tag = json.dumps({"extractor": "xfeat", "max_keypoints": max_keypoints, "subpixel": bool(subpixel)}, sort_keys=True)
    done = set() if overwrite else set(list_names(features_path))
    if done:
        with open_h5(features_path, "r") as fd:
            old = fd.attrs.get(FEATURES_ATTR)
        if old is not None and old != tag:
            raise ValueError(f"features_path: {features_path} holds features extracted with {old}, not {tag}; "
                             "pass overwrite=True (extract) or use another file or output folder")
    todo = [n for n in names if n not in done]
    features_path.parent.mkdir(parents=True, exist_ok=True)
    if not todo:
        return features_path
    with open_h5(features_path, "a") as fd:
        fd.attrs[FEATURES_ATTR] = tag
    if backend == "ray":
        from .ray_backend import extract_ray

        return extract_ray(image_dir, features_path, todo, max_keypoints=max_keypoints, subpixel=subpixel,
                           as_half=as_half, progress=progress, **ray_options)
    if backend != "local":
        raise ValueError(f"backend: expected 'local' or 'ray', got {backend!r}")
    if ray_options:
        raise TypeError(f"extract: options {sorted(ray_options)} are for backend='ray'")
    workers = 2 if num_workers is None else num_workers
    if workers < 1:
        raise ValueError(f"num_workers: expected a positive int, got {num_workers!r}")

    def one(name: str) -> dict:
        return paraformer.extract(os.fspath(image_dir / name), max_keypoints=max_keypoints, subpixel=subpixel)

    with ThreadPoolExecutor(workers) as pool, bar(len(todo), "extract", "img", progress) as pb, \
            open_h5(features_path, "a") as fd:
        queue, failed = list(reversed(todo)), []
        pending: dict = {}
        while queue or pending:
            while queue and len(pending) < 2 * workers:
                name = queue.pop()
                pending[pool.submit(one, name)] = name
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                name = pending.pop(fut)
                try:
                    feats = fut.result()
                except (ValueError, OSError) as e:
                    # One unreadable file must not stop a collection: warn, skip, go on.
                    failed.append(name)
                    warnings.warn(f"skipping {_named(e, image_dir / name)}", stacklevel=2)
                    pb.update(1)
                    continue
                write_features(fd, name, feats, as_half)
                fd.flush()
                pb.update(1)
    if len(failed) == len(todo) and not done:
        raise ValueError(f"image_dir: none of the {len(todo)} image(s) under {image_dir} could be read "
                         f"(first: {failed[0]})")
    return features_path
