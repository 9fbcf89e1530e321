"""Model manager: the registry of known ONNX models, the per-user cache, fetch / verify /
remove, and backend ``auto`` (installed models fill the priors the user left open).

``registry`` and ``store`` use the standard library only (the add-on imports them);
``download`` needs nothing more; ``resolve`` reads PriorConfig dataclasses.
"""

from .download import DownloadError, fetch
from .registry import ROLES, ModelSpec, get_spec, load_registry
from .resolve import describe_priors, resolve_prior_models
from .store import ModelState, ModelStore, default_root, sha256_file

__all__ = ["DownloadError", "fetch", "ROLES", "ModelSpec", "get_spec", "load_registry", "describe_priors",
           "resolve_prior_models", "ModelState", "ModelStore", "default_root", "sha256_file"]
