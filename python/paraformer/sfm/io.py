"""hloc's file layouts: ``features.h5``, ``matches.h5`` and pairs files.

Features: one group per image name (relative to the image folder, ``/`` separators) with
``keypoints`` ``[N, 2]`` (pixel centres at integers, hloc's convention), ``descriptors``
``[D, N]``, ``scores`` ``[N]`` and ``image_size`` ``[W, H]``. Matches: one group per pair,
``names_to_pair(name0, name1)``, with ``matches0`` ``[N0]`` (−1 = unmatched) and
``matching_scores0`` ``[N0]``. Pairs files: one ``name0 name1`` per line.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Sequence, Union

import numpy as np

PathLike = Union[str, os.PathLike]


def _h5py():
    try:
        import h5py
    except ImportError:
        raise ImportError("paraformer.sfm needs h5py: pip install 'paraformer[sfm]'") from None
    return h5py


def open_h5(path: PathLike, mode: str = "r"):
    """``h5py.File`` that names the file when it is not HDF5 (corrupt, truncated, foreign)."""
    h5py = _h5py()
    try:
        return h5py.File(str(path), mode, libver="latest")
    except OSError as e:
        if not Path(path).exists() and mode == "r":
            raise FileNotFoundError(f"no such file: {path}") from None
        raise ValueError(f"{path}: not a readable HDF5 file ({e})") from None


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's group name of a pair in ``matches.h5``."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def names_to_pair_old(name0: str, name1: str) -> str:
    """hloc's older pair naming (``_`` separator), still read by hloc."""
    return names_to_pair(name0, name1, separator="_")


def read_pairs(path: PathLike) -> list[tuple[str, str]]:
    """Reads a pairs file: ``name0 name1`` per line; blank lines and ``#`` comments skipped.

    Args:
        path: the pairs file.
    Returns:
        The pairs in file order.
    """
    pairs = []
    with open(path, "r", encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 2:
                raise ValueError(f"{path}:{lineno}: expected 'name0 name1', got {line!r}")
            pairs.append((parts[0], parts[1]))
    return pairs


def write_pairs(pairs: Iterable[Sequence[str]], path: PathLike) -> Path:
    """Writes a pairs file (``name0 name1`` per line).

    Args:
        pairs: name pairs.
        path: the file to write.
    Returns:
        The path written.
    """
    path = Path(path)
    lines = []
    for k, p in enumerate(pairs):
        if len(p) != 2 or not all(isinstance(n, str) and n and not any(c.isspace() for c in n) for n in p):
            raise ValueError(f"pairs[{k}]: expected two image names without whitespace, got {p!r}")
        lines.append(f"{p[0]} {p[1]}\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(lines), encoding="utf-8")
    return path


def list_names(path: PathLike) -> list[str]:
    """Image names held by a features file (groups that have ``keypoints``)."""
    h5py = _h5py()
    names: list[str] = []
    if not Path(path).exists():
        return names
    with open_h5(path) as fd:
        def visit(name: str, obj) -> None:
            if isinstance(obj, h5py.Dataset) and name.endswith("/keypoints"):
                names.append(name[: -len("/keypoints")])
        fd.visititems(visit)
    return sorted(names)


def write_features(fd, name: str, feats: dict, as_half: bool = False) -> None:
    """Writes one image's features (``paraformer.extract``'s dict) in hloc's layout into an
    open h5 file, replacing any group of that name."""
    if name in fd:
        del fd[name]
    grp = fd.create_group(name)
    dt = np.float16 if as_half else np.float32
    grp.create_dataset("keypoints", data=np.asarray(feats["keypoints"], np.float32))
    grp.create_dataset("descriptors", data=np.ascontiguousarray(np.asarray(feats["descriptors"], dt).T))
    grp.create_dataset("scores", data=np.asarray(feats["scores"], dt))
    grp.create_dataset("image_size", data=np.asarray(feats["image_size"]).astype(np.int64))
    # hloc stores each keypoint's detection noise in pixels; XFeat at full resolution: 1 px.
    grp["keypoints"].attrs["uncertainty"] = 1.0


def read_features(fd, name: str) -> dict:
    """One image's features from an open hloc features file, as the dict ``Matcher.match_dicts``
    takes (descriptors transposed back to ``[N, D]``)."""
    if name not in fd:
        raise KeyError(f"image {name!r} is not in the features file {fd.filename}")
    grp = fd[name]
    for key in ("keypoints", "descriptors", "image_size"):
        if key not in grp:
            raise ValueError(f"features file {fd.filename}: image {name!r} has no '{key}' dataset")
    kpts = np.asarray(grp["keypoints"][()], np.float32)
    desc = np.asarray(grp["descriptors"][()], np.float32)
    if desc.ndim != 2 or desc.shape[1] != kpts.shape[0]:
        raise ValueError(f"features file {fd.filename}: image {name!r}: descriptors {list(desc.shape)} "
                         f"are not [D, {kpts.shape[0]}] for {kpts.shape[0]} keypoints")
    out = {"keypoints": kpts, "descriptors": np.ascontiguousarray(desc.T),
           "image_size": np.asarray(grp["image_size"][()], np.float32).reshape(-1)[:2]}
    if "scores" in grp:
        out["scores"] = np.asarray(grp["scores"][()], np.float32)
    return out


def write_matches(fd, name0: str, name1: str, matches0: np.ndarray, scores0: np.ndarray) -> None:
    """Writes one pair's matches in hloc's layout (int16 indices as hloc writes them, int32
    when image 1 has more keypoints than int16 holds; float16 scores)."""
    pair = names_to_pair(name0, name1)
    if pair in fd:
        del fd[pair]
    grp = fd.create_group(pair)
    m = np.asarray(matches0)
    dt = np.int16 if m.size == 0 or m.max() < np.iinfo(np.int16).max else np.int32
    grp.create_dataset("matches0", data=m.astype(dt))
    grp.create_dataset("matching_scores0", data=np.asarray(scores0).astype(np.float16))


def find_pair(fd, name0: str, name1: str) -> tuple[str, bool]:
    """The group of a pair in a matches file and whether it is stored reversed (hloc's rule,
    both namings)."""
    for make in (names_to_pair, names_to_pair_old):
        if make(name0, name1) in fd:
            return make(name0, name1), False
        if make(name1, name0) in fd:
            return make(name1, name0), True
    raise KeyError(f"pair ({name0}, {name1}) is not in the matches file {fd.filename}")


def has_pair(fd, name0: str, name1: str) -> bool:
    """Whether a matches file holds a pair, in either order or naming."""
    try:
        find_pair(fd, name0, name1)
        return True
    except KeyError:
        return False


def read_matches(fd, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    """A pair's matches from an open matches file as ``[K, 2]`` index pairs (image 0, image 1)
    and their ``[K]`` scores."""
    pair, reverse = find_pair(fd, name0, name1)
    m0 = np.asarray(fd[pair]["matches0"][()]).astype(np.int64)
    s0 = (np.asarray(fd[pair]["matching_scores0"][()], np.float32) if "matching_scores0" in fd[pair]
          else np.ones(m0.shape, np.float32))
    idx = np.nonzero(m0 >= 0)[0]
    matches = np.stack([idx, m0[idx]], -1)
    if reverse:
        matches = matches[:, ::-1]
    return np.ascontiguousarray(matches), s0[idx]
