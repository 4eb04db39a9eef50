"""The features file that feeds ``paraformer eval`` and ``paraformer draw``.

A safetensors file holding, for every image name, ``{name}::keypoints`` float32 [K, 2],
``{name}::scores`` [K], ``{name}::descriptors`` [K, D] and ``{name}::image_size`` [2]
(width, height). Any extractor can write it; hloc-style ``.h5`` files (one group per
image with ``keypoints``, ``descriptors`` [D, K], ``scores``, ``image_size``) convert
both ways when ``h5py`` is installed.
"""
from __future__ import annotations

import json
import struct
from typing import Any, Mapping

import numpy as np

__all__ = ["write", "read", "read_h5", "write_h5"]

_FIELDS = ("keypoints", "scores", "descriptors", "image_size")


def _arrays(name: str, f: Mapping[str, Any]) -> dict[str, np.ndarray]:
    missing = [key for key in ("keypoints", "descriptors", "image_size") if key not in f]
    if missing:
        raise ValueError(f"{name}: missing {', '.join(missing)}")
    k = np.asarray(f["keypoints"], dtype="<f4")
    if k.size == 0:
        k = k.reshape(0, 2)
    # Not reshaped: a [K, 3] array would silently become [3K/2, 2] points.
    if k.ndim != 2 or k.shape[1] != 2:
        raise ValueError(f"{name}: keypoints must be [K, 2], got {list(k.shape)}")
    d = np.asarray(f["descriptors"], dtype="<f4")
    if d.ndim != 2 or d.shape[0] != len(k):
        raise ValueError(f"{name}: descriptors must be [K, D] with K = {len(k)}, got {list(d.shape)}")
    s = np.ones(len(k), "<f4") if f.get("scores") is None else np.asarray(f["scores"], dtype="<f4").reshape(-1)
    size = np.asarray(f["image_size"], dtype="<f4").reshape(-1)
    if len(s) != len(k) or size.shape != (2,):
        raise ValueError(f"{name}: scores must be [{len(k)}] and image_size (width, height)")
    for field, arr in (("keypoints", k), ("scores", s), ("descriptors", d), ("image_size", size)):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: {field} contains NaN or Inf")
    return {"keypoints": k, "scores": s, "descriptors": d, "image_size": size}


def write(path: str, features: Mapping[str, Mapping[str, Any]]) -> None:
    """Writes ``{image name: {keypoints, descriptors, image_size, scores?}}`` to ``path``."""
    header: dict[str, Any] = {"__metadata__": {"format": "paraformer.features"}}
    blobs, offset = [], 0
    for name in sorted(features):
        for field, arr in _arrays(name, features[name]).items():
            data = np.ascontiguousarray(arr).tobytes()
            header[f"{name}::{field}"] = {"dtype": "F32", "shape": list(arr.shape), "data_offsets": [offset, offset + len(data)]}
            blobs.append(data)
            offset += len(data)
    head = json.dumps(header, separators=(",", ":")).encode()
    head += b" " * (-len(head) % 8)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<Q", len(head)))
        fh.write(head)
        for b in blobs:
            fh.write(b)


def read(path: str) -> dict[str, dict[str, np.ndarray]]:
    """Reads a features file into ``{image name: {keypoints, scores, descriptors, image_size}}``."""
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        (n,) = struct.unpack("<Q", raw[:8])
        header = json.loads(raw[8:8 + n])
        out: dict[str, dict[str, np.ndarray]] = {}
        for key, info in header.items():
            if key == "__metadata__":
                continue
            name, field = key.rsplit("::", 1)
            a, b = info["data_offsets"]
            if info["dtype"] != "F32" or not 0 <= a <= b <= len(raw) - 8 - n:
                raise ValueError(f"{key}: dtype {info['dtype']} or offsets {a}..{b} out of range")
            out.setdefault(name, {})[field] = np.frombuffer(raw[8 + n + a:8 + n + b], dtype="<f4").reshape(info["shape"]).copy()
    except (struct.error, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as e:
        # json.JSONDecodeError is a ValueError; a header of the wrong shape raises the others.
        raise ValueError(f"{path}: not a features file ({type(e).__name__}: {e})") from None
    return out


def read_h5(path: str) -> dict[str, dict[str, np.ndarray]]:
    """Reads an hloc-style ``.h5`` features file (needs ``h5py``)."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Group) and "keypoints" in obj:
                d = {k: np.asarray(obj[k]) for k in obj}
                out[name] = {"keypoints": d["keypoints"], "descriptors": d["descriptors"].T,
                             "scores": d.get("scores"), "image_size": d["image_size"]}
        f.visititems(visit)
    return out


def write_h5(path: str, features: Mapping[str, Mapping[str, Any]]) -> None:
    """Writes an hloc-style ``.h5`` features file (needs ``h5py``)."""
    import h5py

    with h5py.File(path, "w") as f:
        for name, feats in features.items():
            a = _arrays(name, feats)
            g = f.create_group(name)
            g["keypoints"], g["descriptors"] = a["keypoints"], a["descriptors"].T
            g["scores"], g["image_size"] = a["scores"], a["image_size"]
