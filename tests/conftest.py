"""Suite-wide fixtures and paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Tests that train in-process run under the thread settings of `python -m engine`
# (engine/__main__.py), set before anything imports torch. Without it, libgomp's spinning
# idle threads in one pytest worker take the cores the other worker needs: a 64x48 training
# of many small ops took 429 s beside one busy torch process instead of 65 s alone.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MOTION_SPLATS_SHARED", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` (models, clips, paper); tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip("../shared is not present")
    return SHARED


@pytest.fixture(autouse=True, scope="session")
def _empty_model_cache(tmp_path_factory):
    """Point the model cache at an empty folder for the whole run (subprocesses inherit it):
    with backend ``auto`` a run picks up any model installed in the user's cache, so results
    would depend on the machine. Tests that want a model install it or pass its path."""
    old = os.environ.get("MOTION_SPLATS_MODELS")
    os.environ["MOTION_SPLATS_MODELS"] = str(tmp_path_factory.mktemp("model-cache"))
    yield
    if old is None:
        os.environ.pop("MOTION_SPLATS_MODELS", None)
    else:
        os.environ["MOTION_SPLATS_MODELS"] = old
