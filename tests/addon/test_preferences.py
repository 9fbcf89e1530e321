"""Add-on preferences: defaults after register, path resolution, requirement pins."""

from __future__ import annotations

from pathlib import Path

import bpy
import pytest

from tests.addon._support import REPO, registered, user_dir, clean_jobs  # noqa: F401 (fixtures)


def test_bl_idname_is_root_package(extension):
    prefs_mod = extension.addon.preferences
    assert prefs_mod.ROOT_PACKAGE == extension.__name__ == "motion_splats"
    assert prefs_mod.MotionSplatsPreferences.bl_idname == "motion_splats"
    assert prefs_mod.MotionSplatsPreferences in extension.addon.CLASSES
    # registered before the classes that may read it
    assert extension.addon.CLASSES.index(prefs_mod.MotionSplatsPreferences) == 0


def test_defaults_after_register(extension, registered, user_dir):
    prefs = registered
    assert prefs is not None
    assert prefs.engine_python == "" and prefs.base_python == "" and prefs.cache_dir == ""
    assert prefs.device == "AUTO"
    assert (prefs.onnx_tokens, prefs.onnx_depth, prefs.onnx_segmentation, prefs.onnx_tracker) == ("", "", "", "")
    mod = extension.addon.preferences
    assert mod.get() == prefs
    assert mod.device() == "auto" and mod.onnx_models() == {}
    assert mod.cache_dir() == user_dir / "cache"
    assert not (user_dir / "cache").exists()  # nothing created until needed
    assert mod.cache_dir(create=True).is_dir()
    assert mod.engine_venv_dir() == user_dir / "engine-venv"
    # automatic interpreter: the dev checkout's venv here (cheap file checks, no probing)
    auto = mod.engine_python()
    assert auto and Path(auto).is_file()
    prefs.engine_python = "/opt/py/bin/python"
    prefs.device = "CUDA"
    prefs.onnx_depth = "/models/depth.onnx"
    assert mod.engine_python() == "/opt/py/bin/python"
    assert mod.device() == "cuda" and mod.onnx_models() == {"depth": "/models/depth.onnx"}


def test_engine_venv_preferred_when_present(extension, registered, user_dir):
    mod = extension.addon.preferences
    py = extension.addon.env_setup.venv_python(user_dir / "engine-venv")
    py.parent.mkdir(parents=True)
    py.write_text("")
    assert mod.interpreter_candidates()[0] == str(py)
    assert mod.engine_python() == str(py)


def test_prefs_draw_does_not_fail(extension, registered):
    # draw() needs a real layout; headless we can at least run it against a stub layout.
    class Stub:
        def __getattr__(self, name):
            return lambda *a, **k: Stub()

        def __setattr__(self, name, value):
            pass

    cls = extension.addon.preferences.MotionSplatsPreferences
    holder = type("Holder", (), {})()
    holder.layout = Stub()
    for name in ("engine_python", "base_python", "cache_dir", "results_dir"):
        setattr(holder, name, getattr(registered, name))
    cls.draw(holder, bpy.context)


def test_requirements_engine_matches_env_setup(extension):
    pins = tuple(line.strip() for line in (REPO / "requirements-engine.txt").read_text().splitlines()
                 if line.strip() and not line.startswith("#"))
    assert pins == extension.addon.env_setup.ENGINE_REQUIREMENTS
    full = {line.split("==")[0]: line.strip() for line in (REPO / "requirements.txt").read_text().splitlines()
            if "==" in line and not line.startswith("#")}
    for pin in pins:
        assert full[pin.split("==")[0]] == pin
    assert not {"bpy", "pytest", "hypothesis", "onnx"} & {p.split("==")[0] for p in pins}
