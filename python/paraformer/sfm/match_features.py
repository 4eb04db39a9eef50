"""Matching image pairs from an hloc ``features.h5`` into an hloc ``matches.h5`` (resumable)."""
from __future__ import annotations

import os
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union


from .io import PathLike, open_h5, has_pair, read_features, read_pairs, write_matches
from ..pipeline import Baseline, load_matcher
from .progress import bar

Pairs = Union[PathLike, Sequence[Sequence[str]]]
def unique_pairs(pairs: Sequence[Sequence[str]]) -> list[tuple[str, str]]:
    """Pairs in order without repeats; (b, a) counts as a repeat of (a, b), as in hloc."""
    seen, out = set(), []
    for k, p in enumerate(pairs):
        if len(p) != 2 or not all(isinstance(n, str) for n in p):
            raise ValueError(f"pairs[{k}]: expected (name0, name1), got {p!r}")
        a, b = p
        if a == b:
            raise ValueError(f"pairs[{k}]: an image paired with itself ({a!r})")
        if (a, b) in seen or (b, a) in seen:
            continue
        seen.add((a, b))
        out.append((a, b))
    return out


def resolve_pairs(pairs: Pairs) -> list[tuple[str, str]]:
    """A pairs argument (a pairs file or a list of name pairs) as unique pairs."""
    if isinstance(pairs, (str, os.PathLike)):
        if not Path(pairs).is_file():
            raise FileNotFoundError(f"pairs: no pairs file {os.fspath(pairs)}")
        pairs = read_pairs(pairs)
    return unique_pairs(pairs)


class FeatureCache:
    """Reads images' features from an open h5 file, keeping the most recent ``capacity``."""

    def __init__(self, fd, capacity: int = 512):
        self.fd, self.capacity = fd, capacity
        self.items: OrderedDict[str, dict] = OrderedDict()

    def __call__(self, name: str) -> dict:
        if name in self.items:
            self.items.move_to_end(name)
            return self.items[name]
        feats = read_features(self.fd, name)
        self.items[name] = feats
        if len(self.items) > self.capacity:
            self.items.popitem(last=False)
        return feats


def matcher_tag(matcher: Any) -> str:
    """What a matches file records of its matcher, so that a resumed run cannot mix two."""
    import json

    import paraformer

    if isinstance(matcher, paraformer.Matcher):
        return "config:" + json.dumps(matcher.config, sort_keys=True)
    if isinstance(matcher, Baseline):
        return f"{matcher.method}:{matcher.ratio}" if matcher.method == "ratio" else matcher.method
    return os.fspath(matcher)


def pending_pairs(pairs: Sequence[tuple[str, str]], matches_path: Path, overwrite: bool,
                  tag: Optional[str] = None) -> list[tuple[str, str]]:
    """The pairs not yet in ``matches_path`` (all of them with ``overwrite``). A file written
    by another matcher (its ``paraformer_matcher`` attribute) is an error unless ``overwrite``."""
    if overwrite or not matches_path.exists():
        return list(pairs)
    with open_h5(matches_path, "r") as fd:
        old = fd.attrs.get("paraformer_matcher")
        if tag is not None and old is not None and old != tag:
            raise ValueError(f"matches_path: {matches_path} holds matches of {old!r}, not {tag!r}; "
                             "pass overwrite=True or another file")
        return [p for p in pairs if not has_pair(fd, *p)]


def check_features(fd, pairs: Sequence[tuple[str, str]], features_path: Path) -> None:
    """Every image of ``pairs`` is in the features file, else KeyError naming the first few."""
    missing = sorted({n for p in pairs for n in p if n not in fd})
    if missing:
        raise KeyError(f"{len(missing)} image(s) of the pairs are not in {features_path}: {missing[:5]}")


def match_pairs(features_path: PathLike, pairs: Pairs, matches_path: PathLike, *,
                matcher: Any = "paraformer-xfeat", batch: int = 32, overwrite: bool = False,
                num_threads: Optional[int] = None, progress: bool = True, backend: str = "local",
                **ray_options) -> Path:
    """Matches image pairs with ``match_many`` in batches into hloc's ``matches.h5`` layout.

    Pairs already in the file (in either order) are skipped unless ``overwrite``; each batch
    is written as soon as it is done, so an interrupted run resumes.

    Args:
        features_path: hloc features file (``extract``'s output or hloc's).
        pairs: a pairs file or a list of ``(name0, name1)``.
        matches_path: the h5 file to create or extend.
        matcher: a pretrained name, ``mnn``/``nn``/``ratio[:R]``, a weights file or a ``Matcher``.
        batch: pairs per ``match_many`` call.
        overwrite: recompute pairs already in the file.
        num_threads: Rust threads for ``match_many`` (default: all cores).
        progress: show a progress bar with pairs/s.
        backend: ``"local"`` or ``"ray"`` (see ``paraformer.sfm.ray_backend``).
        ray_options: ``address``, ``num_workers``, ``threads_per_worker`` for ``backend="ray"``.
    Returns:
        ``matches_path``.
    """
    features_path, matches_path = Path(features_path), Path(matches_path)
    if not features_path.is_file():
        raise FileNotFoundError(f"features_path: no features file {features_path}")
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
        raise ValueError(f"batch: expected a positive int, got {batch!r}")
    if backend not in ("local", "ray"):
        raise ValueError(f"backend: expected 'local' or 'ray', got {backend!r}")
    model = load_matcher(matcher)
    tag = matcher_tag(matcher if isinstance(matcher, (str, os.PathLike)) else model)
    wanted = resolve_pairs(pairs)
    if not wanted:
        # Nothing would be written: the matches file a later step opens would not exist.
        where = os.fspath(pairs) if isinstance(pairs, (str, os.PathLike)) else "the list"
        raise ValueError(f"pairs: no pairs in {where}")
    todo = pending_pairs(wanted, matches_path, overwrite, tag)
    matches_path.parent.mkdir(parents=True, exist_ok=True)
    with open_h5(features_path, "r") as ffd:
        check_features(ffd, todo, features_path)
    if not todo:
        return matches_path
    if backend == "ray":
        from .ray_backend import match_pairs_ray

        return match_pairs_ray(features_path, todo, matches_path, matcher=matcher, tag=tag, batch=batch,
                               progress=progress, **ray_options)
    if ray_options:
        raise TypeError(f"match_pairs: options {sorted(ray_options)} are for backend='ray'")
    with open_h5(features_path, "r") as ffd, \
            open_h5(matches_path, "a") as mfd:
        mfd.attrs["paraformer_matcher"] = tag
        run_batches(todo, FeatureCache(ffd), lambda chunk: model.match_many(chunk, num_threads=num_threads),
                    mfd, batch, progress)
    return matches_path


def run_batches(todo: Sequence[tuple[str, str]], feats: Callable[[str], dict],
                match: Callable[[list], list[dict]], mfd, batch: int, progress: bool) -> None:
    """Matches ``todo`` in batches and writes each result to the open matches file."""
    t0, done = time.time(), 0
    with bar(len(todo), "match", "pair", progress) as pb:
        for start in range(0, len(todo), batch):
            chunk = todo[start:start + batch]
            outs = match([(feats(a), feats(b)) for a, b in chunk])
            for (a, b), out in zip(chunk, outs):
                write_matches(mfd, a, b, out["matches0"], out["matching_scores0"])
            mfd.flush()
            done += len(chunk)
            pb.update(len(chunk))
            pb.set_postfix_str(f"{done / max(time.time() - t0, 1e-9):.1f} pairs/s")
