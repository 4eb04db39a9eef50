"""Which image pairs to match: exhaustive, sequential, or a pairs file."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence, Union

from .io import read_pairs


def pairs_exhaustive(names: Sequence[str]) -> list[tuple[str, str]]:
    """Every pair of distinct images once, ``(names[i], names[j])`` with ``i < j``.

    Args:
        names: image names.
    Returns:
        ``len(names) * (len(names) - 1) / 2`` pairs.
    """
    names = _names(names)
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]


def pairs_sequential(names: Sequence[str], overlap: int = 10) -> list[tuple[str, str]]:
    """Each image with the ``overlap`` images after it in the given order (video frames).

    Args:
        names: image names in capture order.
        overlap: how many following images each image is paired with.
    Returns:
        The pairs.
    """
    if not isinstance(overlap, int) or isinstance(overlap, bool) or overlap < 1:
        raise ValueError(f"overlap: expected a positive int, got {overlap!r}")
    names = _names(names)
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, min(i + 1 + overlap, len(names)))]


def pairs_from_spec(spec: Union[str, os.PathLike, Sequence[Sequence[str]]], names: Sequence[str]) -> list[tuple[str, str]]:
    """``"exhaustive"``, ``"sequential"`` / ``"sequential:N"``, a pairs file, or a list of pairs."""
    if not isinstance(spec, (str, os.PathLike)):
        return [tuple(p) for p in spec]  # type: ignore[misc]
    text = os.fspath(spec)
    if text == "exhaustive":
        return pairs_exhaustive(names)
    if text == "sequential" or text.startswith("sequential:"):
        n = text.partition(":")[2] or "10"
        if not n.isdigit() or int(n) < 1:
            raise ValueError(f"pairs: expected sequential:N with a positive N, got {text!r}")
        return pairs_sequential(names, int(n))
    if Path(text).is_file():
        return read_pairs(text)
    raise ValueError(f"pairs: expected 'exhaustive', 'sequential:N' or a pairs file, got {text!r} (no such file)")


def _names(names: Sequence[str]) -> list[str]:
    if isinstance(names, (str, bytes)):
        raise ValueError("names: expected a list of image names, got a single string")
    out = list(names)
    for k, n in enumerate(out):
        if not isinstance(n, str) or not n:
            raise ValueError(f"names[{k}]: expected a non-empty str, got {n!r}")
    if len(set(out)) != len(out):
        raise ValueError("names: contains repeated image names")
    return out
