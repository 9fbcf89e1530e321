"""Fixtures for the Blender-side tests (headless bpy 5.0.1 in the test venv).

The repository root is the extension package; tests import it as ``motion_splats``
through a symlink, like Blender imports an installed extension.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def extension(tmp_path_factory):
    """The repo imported as the package ``motion_splats`` (not registered)."""
    root = tmp_path_factory.mktemp("ext")
    (root / "motion_splats").symlink_to(REPO, target_is_directory=True)
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module("motion_splats")
    finally:
        sys.path.remove(str(root))


@pytest.fixture()
def empty_scene():
    """A fresh, empty factory scene for each test."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene
