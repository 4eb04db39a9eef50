"""Shared fixtures: the test-data folders and a reader for pair files with expected outputs."""
import json
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data"


def load_case(path: Path) -> dict:
    from safetensors.numpy import load_file
    return {k: np.asarray(v) for k, v in load_file(str(path)).items()}


def index(folder: str) -> list:
    d = DATA / folder
    return [(d, e) for e in json.loads((d / "index.json").read_text())]


@pytest.fixture(scope="session")
def golden_weights() -> Path:
    return DATA / "golden" / "paraformer.weights.safetensors"


@pytest.fixture(scope="session")
def golden_case() -> dict:
    return load_case(DATA / "golden" / "paraformer.case0.safetensors")
