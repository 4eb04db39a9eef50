"""Type stubs of the native core (checked by mypy's stubtest in the test suite)."""
import os
from typing import Optional, Union, final

__all__ = ["_Matcher", "flops", "ParaformerError", "WeightsError", "__version__"]

__version__: str

class ParaformerError(Exception): ...
class WeightsError(ParaformerError): ...

_Features = tuple[bytes, bytes, int, Optional[bytes], float, float]

@final
class _Matcher:
    @staticmethod
    def from_file(path: Union[str, os.PathLike[str]], /) -> _Matcher: ...
    @staticmethod
    def from_bytes(data: bytes, /) -> _Matcher: ...
    @staticmethod
    def with_config(config_json: str, weights: Union[bytes, str, os.PathLike[str]], /) -> _Matcher: ...
    @property
    def config_json(self) -> str: ...
    def match_pair(self, features0: _Features, features1: _Features, return_log_assignment: bool = False) -> dict: ...
    def match_many(
        self,
        pairs: list[tuple[_Features, _Features]],
        return_log_assignment: bool = False,
        num_threads: Optional[int] = None,
    ) -> list[dict]: ...

def flops(config_json: str, m: int, n: int) -> tuple[int, int, int]: ...
