"""Progress bars: tqdm when installed (it comes with the ``sfm`` extra), else nothing."""
from __future__ import annotations

from typing import Any


class _Silent:
    def __init__(self, *_: Any, **__: Any) -> None:
        pass

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> "_Silent":
        return self

    def __exit__(self, *exc: Any) -> None:
        pass


def bar(total: int, desc: str, unit: str, show: bool = True) -> Any:
    """A progress bar over ``total`` items (``unit``/s shown by tqdm)."""
    if not show:
        return _Silent()
    try:
        from tqdm import tqdm
    except ImportError:
        return _Silent()
    return tqdm(total=total, desc=desc, unit=unit, smoothing=0.1)
