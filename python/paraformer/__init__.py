"""Sparse feature matching with ParaFormer, ParaFormer-U and SuperGlue (Rust core).

>>> import paraformer
>>> m = paraformer.Matcher.from_file("weights.safetensors")          # doctest: +SKIP
>>> out = m.match(kpts0, desc0, kpts1, desc1, size0=(640, 480), size1=(640, 480))  # doctest: +SKIP
>>> out["matches0"]                                                   # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
from typing import Any, Mapping, Sequence, Union

import numpy as np

from ._paraformer import ParaformerError, ResourceError, WeightsError, _Matcher, __version__
from ._paraformer import memory_limit, set_memory_limit
from ._paraformer import extract as _extract
from ._paraformer import extract_file as _extract_file
from ._paraformer import check_extract_memory as _check_extract_memory
from ._paraformer import flops as _flops
from ._paraformer import pretrained_names
from . import features, geometry

__all__ = ["Matcher", "ParaformerError", "ResourceError", "WeightsError", "extract", "features", "flops",
           "geometry", "match_images", "memory_limit", "pretrained_names", "set_memory_limit", "__version__"]

ArrayLike = Any
Output = dict[str, np.ndarray]


def _float_array(value: ArrayLike, name: str, shape: str, integers: bool = False) -> np.ndarray:
    """``value`` as a float32 or float64 array, or ValueError naming ``name`` and the expected shape.

    float16 (a GPU extractor's half precision) widens exactly to float32, and with ``integers``
    (pixel coordinates, scores) integer arrays widen to float64; bool, complex, text and
    objects stay errors. Descriptors take no integers: uint8 ones are binary (ORB, BRIEF).
    """
    kinds = "a float16, float32 or float64" + (" (or integer)" if integers else "")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, RuntimeError) as e:  # RuntimeError: a torch tensor that requires grad
        raise ValueError(f"{name}: expected {kinds} array of shape {shape}: {e}") from None
    if arr.dtype == np.float16:
        return arr.astype(np.float32)
    if integers and np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float64)
    if arr.dtype not in (np.float32, np.float64):
        raise ValueError(f"{name}: expected {kinds} array of shape {shape}, got dtype {arr.dtype}")
    return arr


def _check_finite(arr: np.ndarray, name: str) -> None:
    if arr.size and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name}: contains NaN or Inf (first at index {tuple(int(i) for i in bad)})")


def _le32(arr: np.ndarray) -> bytes:
    # A float64 beyond float32's range becomes Inf, which the core then names by row: no
    # numpy overflow warning ahead of that error.
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(arr, dtype="<f4").tobytes()


def _image(i: int, kpts: ArrayLike, desc: ArrayLike, scores: ArrayLike | None, size: Any, dim: int) -> tuple:
    """Validates one image's inputs and packs them for the Rust core."""
    k = _float_array(kpts, f"kpts{i}", "[K, 2]", integers=True)
    if k.ndim != 2 or k.shape[1] != 2:
        raise ValueError(f"kpts{i}: expected shape [K, 2], got {list(k.shape)}")
    n = k.shape[0]
    d = _float_array(desc, f"desc{i}", f"[{n}, {dim}]")
    if d.ndim != 2 or d.shape != (n, dim):
        raise ValueError(f"desc{i}: expected shape [{n}, {dim}] (K keypoints × descriptor_dim), got {list(d.shape)}")
    s = None
    if scores is not None:
        s = _float_array(scores, f"scores{i}", f"[{n}]", integers=True)
        if s.shape != (n,):
            raise ValueError(f"scores{i}: expected shape [{n}], got {list(s.shape)}")
    try:
        raw = np.asarray(size)
        # None for a complex size: a float cast would drop its imaginary part without a word.
        sz = None if np.iscomplexobj(raw) else raw.astype(np.float64).reshape(-1)
    except (ValueError, TypeError):
        sz = None
    if sz is None:
        raise ValueError(f"size{i}: expected (width, height), got {size!r}")
    if sz.shape != (2,) or not np.isfinite(sz).all() or (sz <= 0).any():
        raise ValueError(f"size{i}: expected a positive (width, height), got {size!r}")
    for arr, name in ((k, f"kpts{i}"), (d, f"desc{i}"), (s, f"scores{i}")):
        if arr is not None:
            _check_finite(arr, name)
    return (_le32(k), _le32(d), dim, None if s is None else _le32(s), float(sz[0]), float(sz[1]))


def _unpack(raw: dict) -> Output:
    out: Output = {
        "matches0": np.frombuffer(raw["matches0"], dtype="<i8").astype(np.int64, copy=False),
        "matches1": np.frombuffer(raw["matches1"], dtype="<i8").astype(np.int64, copy=False),
        "matching_scores0": np.frombuffer(raw["matching_scores0"], dtype="<f4").astype(np.float32, copy=False),
        "matching_scores1": np.frombuffer(raw["matching_scores1"], dtype="<f4").astype(np.float32, copy=False),
    }
    if "log_assignment" in raw:
        data, rows, cols = raw["log_assignment"]
        out["log_assignment"] = np.frombuffer(data, dtype="<f4").astype(np.float32, copy=False).reshape(rows, cols)
    return out


def _feature_dict(feats: Mapping[str, Any], i: int, dim: int) -> tuple:
    """LightGlue-style dict (optionally batched with B = 1) → packed image ``i``."""
    if not isinstance(feats, Mapping):
        raise ValueError(f"feats{i}: expected a dict with keypoints, descriptors, image_size")
    missing = [key for key in ("keypoints", "descriptors", "image_size") if key not in feats]
    if missing:
        raise ValueError(f"feats{i}: missing {', '.join(missing)}")

    def unbatch(v: Any, ndim: int) -> Any:
        a = np.asarray(v) if not isinstance(v, np.ndarray) else v
        return a[0] if a.ndim == ndim + 1 and a.shape[0] == 1 else v

    scores = feats.get("scores", feats.get("keypoint_scores"))
    return _image(
        i,
        unbatch(feats["keypoints"], 2),
        unbatch(feats["descriptors"], 2),
        None if scores is None else unbatch(scores, 1),
        unbatch(feats["image_size"], 1),
        dim,
    )


def _precision(precision: object) -> str:
    if not isinstance(precision, str):
        raise ValueError(f"precision: expected \"fp32\" or \"bf16\", got {type(precision).__name__}")
    return precision


class Matcher:
    """A ParaFormer, ParaFormer-U or SuperGlue matcher. Thread-safe; the GIL is released
    while it computes.

    Args:
        config: SPEC §9 config fields (absent ones take the defaults).
        weights: path of a safetensors weights file, or its bytes.
        precision: ``"fp32"`` (default, SPEC's numbers) or ``"bf16"``: the heavy products
            take bf16 operands with fp32 sums, 1.3–1.8× faster on CPUs with AVX-512 BF16
            with ≥ 99% of matches unchanged; elsewhere it runs as fp32 (see
            ``Matcher.precision``).
    """

    __slots__ = ("_inner", "_dim")

    def __init__(self, config: Mapping[str, Any], weights: Union[str, os.PathLike, bytes], *,
                 precision: str = "fp32"):
        if not isinstance(config, Mapping):
            raise ValueError(f"config: expected a dict, got {type(config).__name__}")
        self._set(_Matcher.with_config(json.dumps(dict(config)), weights, _precision(precision)))

    def _set(self, inner: _Matcher) -> None:
        self._inner = inner
        self._dim = int(json.loads(inner.config_json)["descriptor_dim"])

    @classmethod
    def from_file(cls, path: Union[str, os.PathLike], *, precision: str = "fp32") -> "Matcher":
        """Loads a weights file whose ``paraformer.config`` metadata holds the config.

        Args:
            path: path of a safetensors weights file.
            precision: ``"fp32"`` or ``"bf16"`` (see ``Matcher``).
        Returns:
            The matcher.
        """
        m = cls.__new__(cls)
        m._set(_Matcher.from_file(os.fspath(path), _precision(precision)))
        return m

    @classmethod
    def pretrained(cls, name: str = "paraformer-xfeat", *, precision: str = "fp32") -> "Matcher":
        """Trained weights shipped inside the package (for XFeat features).

        Args:
            name: one of ``paraformer.pretrained_names()``.
            precision: ``"fp32"`` or ``"bf16"`` (see ``Matcher``).
        Returns:
            The matcher.
        """
        if not isinstance(name, str):
            raise ValueError(f"name: expected a str, got {type(name).__name__}")
        m = cls.__new__(cls)
        m._set(_Matcher.pretrained(name, _precision(precision)))
        return m

    @classmethod
    def from_bytes(cls, data: bytes, *, precision: str = "fp32") -> "Matcher":
        """Like ``from_file``, from the bytes of a weights file."""
        m = cls.__new__(cls)
        m._set(_Matcher.from_bytes(bytes(data), _precision(precision)))
        return m

    @property
    def precision(self) -> str:
        """The attention precision that runs here: ``"fp32"``, or ``"bf16"`` when asked for
        and the CPU has AVX-512 BF16."""
        return self._inner.precision[1]

    @property
    def config(self) -> dict:
        """The config (SPEC §9 fields, every one written out); a fresh dict each time."""
        return json.loads(self._inner.config_json)

    def __repr__(self) -> str:
        c = self.config
        return (f"paraformer.Matcher(model={c['model']!r}, descriptor_dim={c['descriptor_dim']}, "
                f"precision={self.precision!r})")

    def match(self, kpts0: ArrayLike, desc0: ArrayLike, kpts1: ArrayLike, desc1: ArrayLike, *,
              size0: Sequence[float], size1: Sequence[float],
              scores0: ArrayLike | None = None, scores1: ArrayLike | None = None,
              return_log_assignment: bool = False) -> Output:
        """Matches the keypoints of two images.

        Args:
            kpts0, kpts1: ``[M, 2]`` / ``[N, 2]`` pixel coordinates (x, y), float or integer,
                inside the image (at most 10% of its larger side outside).
            desc0, desc1: ``[M, D]`` / ``[N, D]`` float descriptors (float16, 32 or 64),
                ``D = config["descriptor_dim"]``.
            size0, size1: image sizes ``(width, height)``.
            scores0, scores1: optional ``[M]`` / ``[N]`` detection scores (default 1.0).
            return_log_assignment: also return the ``[M+1, N+1]`` log assignment.
        Returns:
            ``matches0`` int64 ``[M]`` (−1 = unmatched), ``matches1`` int64 ``[N]``,
            ``matching_scores0/1`` float32, and ``log_assignment`` float32 when asked for.
        """
        f0 = _image(0, kpts0, desc0, scores0, size0, self._dim)
        f1 = _image(1, kpts1, desc1, scores1, size1, self._dim)
        return _unpack(self._inner.match_pair(f0, f1, bool(return_log_assignment)))

    def profile(self, kpts0: ArrayLike, desc0: ArrayLike, kpts1: ArrayLike, desc1: ArrayLike, *,
                size0: Sequence[float], size1: Sequence[float],
                scores0: ArrayLike | None = None, scores1: ArrayLike | None = None) -> dict[str, float]:
        """Runs ``match`` once and reports where the time went.

        Args:
            kpts0, desc0, kpts1, desc1, size0, size1, scores0, scores1: as for ``match``.
        Returns:
            Seconds per part (``encoder``, ``layers``, ``final_projection``, ``sinkhorn``,
            ``extraction``, ``total``) and ``macs``, the multiply-accumulates performed.
        """
        f0 = _image(0, kpts0, desc0, scores0, size0, self._dim)
        f1 = _image(1, kpts1, desc1, scores1, size1, self._dim)
        return dict(self._inner.profile(f0, f1))

    def match_dicts(self, feats0: Mapping[str, Any], feats1: Mapping[str, Any], *,
                    return_log_assignment: bool = False) -> Output:
        """Matches LightGlue-style feature dicts.

        Args:
            feats0, feats1: dicts with ``keypoints`` ``[K, 2]``, ``descriptors`` ``[K, D]``,
                ``image_size`` ``(width, height)`` and optional ``scores`` (or
                ``keypoint_scores``); a leading batch axis of size 1 is accepted.
            return_log_assignment: also return the log assignment.
        Returns:
            The dict that ``match`` returns.
        """
        f0, f1 = _feature_dict(feats0, 0, self._dim), _feature_dict(feats1, 1, self._dim)
        return _unpack(self._inner.match_pair(f0, f1, bool(return_log_assignment)))

    def memory_needed(self, m: int, n: int) -> int:
        """Bytes a match of ``m`` × ``n`` keypoints needs at its peak; a call needing more than
        ``paraformer.memory_limit()`` raises ``paraformer.ResourceError`` before allocating.

        Args:
            m: keypoints of image 0.
            n: keypoints of image 1.
        Returns:
            The estimate in bytes.
        """
        for name, v in (("m", m), ("n", n)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name}: expected a non-negative int, got {v!r}")
            if v >= 2**64:  # beyond what the native count holds (the estimate saturates below it)
                raise ValueError(f"{name}: {v} keypoints is beyond any memory")
        return int(self._inner.memory_needed(int(m), int(n)))

    def match_many(self, pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]], *,
                   return_log_assignment: bool = False, num_threads: int | None = None) -> list[Output]:
        """Matches many pairs of feature dicts, in parallel in Rust.

        Args:
            pairs: ``(feats0, feats1)`` tuples of dicts as ``match_dicts`` takes.
            return_log_assignment: also return each log assignment.
            num_threads: worker threads (default: the number of cores).
        Returns:
            One output dict per pair, in order.
        """
        packed = []
        for k, pair in enumerate(pairs):
            try:
                feats0, feats1 = pair
                packed.append((_feature_dict(feats0, 0, self._dim), _feature_dict(feats1, 1, self._dim)))
            except (TypeError, ValueError) as e:
                raise ValueError(f"pairs[{k}]: {e}") from None
        if num_threads is not None and num_threads < 1:
            raise ValueError(f"num_threads: expected a positive int, got {num_threads}")
        raw = self._inner.match_many(packed, bool(return_log_assignment), num_threads)
        return [_unpack(r) for r in raw]


def extract(image: Union[str, os.PathLike, ArrayLike], max_keypoints: int = 2048, *,
            subpixel: bool = False) -> dict[str, np.ndarray]:
    """XFeat keypoints and 64-d descriptors of one image (the Rust port of XFeat's sparse
    ``detectAndCompute``), as the dict that ``Matcher.match_dicts`` takes.

    Args:
        image: a path (PNG, JPEG, PNM, BMP, TIFF, WebP) or a numpy array ``[H, W]`` or
            ``[H, W, C]`` (C = 1, 2, 3 or 4; uint8 0–255, float 0–255 or a wider integer
            type such as uint16, which gives the keypoints of its 8-bit version because XFeat
            normalises contrast; colour is averaged over R, G, B, alpha ignored).
        max_keypoints: keep at most this many keypoints, best score first.
        subpixel: refine each keypoint to sub-pixel precision (a Gaussian fit of XFeat's
            heatmap across its peak, within ±0.5 px; descriptors sampled there). Off:
            whole pixels, as the original XFeat.
    Returns:
        ``keypoints`` ``[K, 2]`` float32 (x, y), ``scores`` ``[K]``, ``descriptors``
        ``[K, 64]`` (unit length) and ``image_size`` ``(width, height)``.
    """
    if not isinstance(max_keypoints, (int, np.integer)) or isinstance(max_keypoints, bool) or max_keypoints < 1:
        raise ValueError(f"max_keypoints: expected a positive int, got {max_keypoints!r}")
    if isinstance(image, (str, os.PathLike)):
        raw = _extract_file(os.fspath(image), int(max_keypoints), bool(subpixel))
    else:
        arr = np.asarray(image)
        if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
            raise ValueError(f"image: expected an integer or float array [H, W] or [H, W, C] "
                             f"(uint8 0–255 is the usual), got dtype {arr.dtype}")
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
            raise ValueError(f"image: expected shape [H, W] or [H, W, C] with C in 1..4, got {list(np.shape(image))}")
        h, w, c = arr.shape
        # Before any copy: the copies alone of a huge array could exhaust the memory.
        _check_extract_memory(h, w, c, 1 if arr.dtype == np.uint8 else 4)
        if arr.dtype == np.uint8:
            # Passed as is: a quarter of the bytes, converted in Rust.
            raw = _extract(np.ascontiguousarray(arr).tobytes(), h, w, c, int(max_keypoints), "u8", bool(subpixel))
        else:
            if not np.issubdtype(arr.dtype, np.integer):
                _check_finite(arr.astype(np.float32, copy=False), "image")
            raw = _extract(_le32(arr), h, w, c, int(max_keypoints), "f32", bool(subpixel))
    kpts, scores, desc, width, height = raw
    return {
        "keypoints": np.frombuffer(kpts, "<f4").reshape(-1, 2).astype(np.float32),
        "scores": np.frombuffer(scores, "<f4").astype(np.float32),
        "descriptors": np.frombuffer(desc, "<f4").reshape(-1, 64).astype(np.float32),
        "image_size": np.array([width, height], np.float32),
    }


def flops(config_or_matcher: Union[Matcher, Mapping[str, Any]], m: int, n: int) -> int:
    """Multiply-accumulates of one forward pass (SPEC §10; the paper's "FLOPs").

    The count is the config's: weights whose parallel layers close a branch (all-zero
    ``fuse.0`` columns, as the serial LighterGlue transplant has) run less, which
    ``Matcher.profile`` counts.

    Args:
        config_or_matcher: a ``Matcher`` or a config dict.
        m: keypoints of image 0.
        n: keypoints of image 1.
    Returns:
        The MAC count (0 when ``m`` or ``n`` is 0: the network is not run).
    """
    cfg = config_or_matcher.config if isinstance(config_or_matcher, Matcher) else dict(config_or_matcher)
    for name, v in (("m", m), ("n", n)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
            raise ValueError(f"{name}: expected a non-negative int, got {v!r}")
    return sum(_flops(json.dumps(cfg), int(m), int(n)))


from .pipeline import match_images  # noqa: E402  (uses Matcher and extract defined above)
