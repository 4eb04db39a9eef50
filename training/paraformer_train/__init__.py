"""PyTorch model of the project: the reference for parity tests and the model that is trained."""
from .model import DEFAULTS, Matcher, resolve_config, log_optimal_transport, extract_matches
from .io import load_safetensors, save_safetensors

__all__ = ["DEFAULTS", "Matcher", "resolve_config", "log_optimal_transport", "extract_matches",
           "load_safetensors", "save_safetensors"]
