# SPDX-License-Identifier: GPL-3.0-or-later
"""Add-on preferences: engine interpreter, device, ONNX models, cache, engine checks.

Empty path settings mean "automatic"; :func:`engine_python`, :func:`base_python` and
:func:`cache_dir` resolve them with cheap file checks only (nothing imports torch at
start-up). The "Detect" button fills the interpreter; "Check engine" runs
``python -m engine selftest --jsonl`` in the background and shows the versions or the
problems here.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from . import env_setup, jobs
from .bridge import EXTENSION_ROOT

#: The add-on's package name (``bl_ext.<repo>.motion_splats`` in Blender, the root of
#: this sub-package), which is also the preferences' ``bl_idname``.
ROOT_PACKAGE = __package__.rpartition(".")[0] or __package__

#: Environment variable that overrides the user folder (tests, portable setups).
USER_DIR_ENV = "MOTION_SPLATS_USER_DIR"

DEVICE_ITEMS = (
    ("AUTO", "Auto", "CUDA when the engine's torch sees a GPU, else CPU"),
    ("CPU", "CPU", "Always run on the CPU"),
    ("CUDA", "CUDA", "Run on the first CUDA GPU"),
)


# -- paths -------------------------------------------------------------------------------
def user_dir(path: str = "", create: bool = False) -> Path:
    """The extension's writable folder (``extension_path_user``), or a fallback outside
    Blender's extension system (tests: ``$MOTION_SPLATS_USER_DIR``)."""
    override = os.environ.get(USER_DIR_ENV)
    if override:
        base = Path(override)
    else:
        try:
            base = Path(bpy.utils.extension_path_user(ROOT_PACKAGE, path="", create=create))
        except (ValueError, AttributeError):  # not installed as an extension (legacy add-on, tests)
            base = Path(bpy.utils.user_resource("CONFIG")) / "motion_splats"
    out = base / path if path else base
    if create:
        out.mkdir(parents=True, exist_ok=True)
    return out


def engine_venv_dir() -> Path:
    return user_dir("engine-venv")


def _dev_venv_python() -> Path:
    """A development checkout's own venv (``<repo>/.venv``), next to ``engine/``."""
    return env_setup.venv_python(EXTENSION_ROOT / ".venv")


def interpreter_candidates() -> list[str]:
    """Interpreters that may run the engine, best first (existence checks only)."""
    out: list[str] = []
    for cand in (env_setup.venv_python(engine_venv_dir()), _dev_venv_python()):
        if cand.is_file():
            out.append(str(cand))
    # As the bpy module, sys.executable is a normal Python (often the one with torch).
    if not bpy.app.binary_path and sys.executable and Path(sys.executable).is_file():
        out.append(sys.executable)
    found = env_setup.find_base_python()
    if found:
        out.append(found)
    seen, unique = set(), []
    for c in out:
        if c not in seen:
            seen.add(c)
            unique.append(c)
    return unique


def get(context=None):
    """The preferences object, or None when the add-on is not enabled by name."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ROOT_PACKAGE)
    return addon.preferences if addon is not None else None


def engine_python(context=None) -> str:
    """The interpreter to run the engine with ("" when none is known)."""
    prefs = get(context)
    chosen = bpy.path.abspath(prefs.engine_python) if prefs is not None and prefs.engine_python else ""
    if chosen:
        return chosen
    cands = interpreter_candidates()
    return cands[0] if cands else ""


#: What an operator reports when no engine interpreter is known.
NO_ENGINE_MESSAGE = ("No engine interpreter found: set one in the add-on preferences "
                     "or use Create Engine Environment")


def engine_python_or_report(context, op) -> str:
    """:func:`engine_python`, reporting :data:`NO_ENGINE_MESSAGE` on ``op`` when there is none."""
    python = engine_python(context)
    if not python:
        op.report({"ERROR"}, NO_ENGINE_MESSAGE)
    return python


def base_python(context=None) -> str:
    prefs = get(context)
    chosen = bpy.path.abspath(prefs.base_python) if prefs is not None and prefs.base_python else ""
    return chosen or env_setup.find_base_python()


def cache_dir(context=None, create: bool = False) -> Path:
    prefs = get(context)
    if prefs is not None and prefs.cache_dir:
        out = Path(bpy.path.abspath(prefs.cache_dir))
        if create:
            out.mkdir(parents=True, exist_ok=True)
        return out
    return user_dir("cache", create=create)


def results_dir(context=None) -> Path:
    """Where results of an unsaved .blend go: the preference, else ``~/MotionSplats``.

    Never the extension's own folder: uninstalling or updating the extension deletes
    that, and results are the artist's work.
    """
    prefs = get(context)
    if prefs is not None and prefs.results_dir:
        return Path(bpy.path.abspath(prefs.results_dir))
    return Path.home() / "MotionSplats"


def platform_cache_dir() -> Path:
    """The user's cache folder for this program, outside the extension's folders (which
    an uninstall deletes): ``$XDG_CACHE_HOME``/``~/.cache``, ``~/Library/Caches``,
    ``%LOCALAPPDATA%``."""
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "motion_splats"


def numba_cache_dir(context=None) -> Path:
    """The engine's compiled-kernel cache (``NUMBA_CACHE_DIR``): the Cache Folder when one
    is set, else the platform cache. Never beside the engine's sources (an update replaces
    them) nor in the extension's user folder (an uninstall deletes it); compiling the
    kernels again costs the first run about a minute."""
    prefs = get(context)
    if prefs is not None and prefs.cache_dir:
        return cache_dir(context) / "numba"
    return platform_cache_dir() / "numba"


def engine_env(context=None, installed: bool | None = None) -> dict:
    """Environment for engine subprocesses (:func:`.bridge.child_env`).

    An installed extension (package ``bl_ext.*``) gets ``NUMBA_CACHE_DIR`` =
    :func:`numba_cache_dir`; a development checkout keeps Numba's default cache beside
    its sources, which no extension update touches and which its other tools share.
    """
    from .bridge import child_env

    if installed is None:
        installed = ROOT_PACKAGE.startswith("bl_ext.")
    return child_env({"NUMBA_CACHE_DIR": str(numba_cache_dir(context))} if installed else None)


def device(context=None) -> str:
    prefs = get(context)
    return prefs.device.lower() if prefs is not None else "auto"


def onnx_models(context=None) -> dict:
    """The ONNX model paths that are set: ``{"tokens": ..., "depth": ..., ...}``."""
    prefs = get(context)
    if prefs is None:
        return {}
    out = {}
    for key in ("tokens", "depth", "segmentation", "tracker"):
        value = getattr(prefs, f"onnx_{key}")
        if value:
            out[key] = bpy.path.abspath(value)
    return out


# -- the preferences -----------------------------------------------------------------------
def _draw_job(layout, job, ok_text: str):
    if job is None:
        return
    box = layout.box()
    if job.running:
        row = box.row()
        row.label(text=f"{job.label}: {job.stage or 'starting'} {job.step}/{job.total or '?'}", icon="TIME")
        op = row.operator("motion_splats.cancel_job", text="", icon="X")
        op.job_id = job.id
        for i, line in enumerate(job.silence_lines()):
            box.label(text=line[:160], icon="ERROR" if i == 0 else "BLANK1")
        for line in list(job.logs)[-3:]:
            box.label(text=line[:120])
        return
    if job.state == "finished":
        box.label(text=ok_text, icon="CHECKMARK")
    elif job.state == "cancelled":
        box.label(text=f"{job.label}: cancelled", icon="CANCEL")
    else:
        box.label(text=f"{job.label} failed", icon="ERROR")
    return box


def draw_check_result(layout, job) -> None:
    """Show a selftest job: running, the versions, or the problems."""
    if job is None:
        return
    result = job.result or {}
    box = _draw_job(layout, job, "Engine OK")
    if box is None:
        return
    if result:
        col = box.column(align=True)
        col.label(text=f"Engine {result.get('engine', '?')} · Python {result.get('python', '?')} · "
                       f"CUDA {'yes' if result.get('cuda') else 'no'}")
        for name, version in sorted((result.get("versions") or {}).items()):
            col.label(text=f"{name}: {version or 'missing'}", icon="CHECKMARK" if version else "BLANK1")
        for name, problem in sorted((result.get("problems") or {}).items()):
            col.label(text=f"{name}: {problem}"[:160], icon="ERROR")
    if job.state != "finished":
        for line in job.error_summary():
            box.label(text=line[:160])


class MotionSplatsPreferences(bpy.types.AddonPreferences):
    bl_idname = ROOT_PACKAGE

    engine_python: StringProperty(
        name="Engine Interpreter",
        description="Python that runs the engine (needs torch, OpenCV, ...). Empty: the extension's own "
                    "engine environment if it exists, else the first Python found",
        subtype="FILE_PATH", default="",
    )
    base_python: StringProperty(
        name="Base Python",
        description="Python 3.11/3.12 used to create the engine environment. Empty: python3.11, python3.12 "
                    "or python3 on PATH (Blender's bundled Python often lacks venv/pip support)",
        subtype="FILE_PATH", default="",
    )
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="AUTO")
    onnx_tokens: StringProperty(name="Tokens Model", description="Optional ONNX feature/token model",
                                subtype="FILE_PATH", default="")
    onnx_depth: StringProperty(name="Depth Model", description="Optional ONNX monocular depth model",
                               subtype="FILE_PATH", default="")
    onnx_segmentation: StringProperty(name="Segmentation Model", description="Optional ONNX segmentation model",
                                      subtype="FILE_PATH", default="")
    onnx_tracker: StringProperty(name="Tracker Model", description="Optional ONNX point tracker",
                                 subtype="FILE_PATH", default="")
    results_dir: StringProperty(name="Results Folder",
                                description="Where reconstructions of an unsaved .blend go (a saved file keeps "
                                            "them beside itself). Empty: MotionSplats in your home folder",
                                subtype="DIR_PATH", default="")
    cache_dir: StringProperty(name="Cache Folder",
                              description="Where priors and intermediate files are cached. Empty: the "
                                          "extension's user folder",
                              subtype="DIR_PATH", default="")

    silence_warn_s: IntProperty(
        name="Warn When Silent For",
        description="Seconds without any output from a running engine before its job box says it may be hung "
                    "(a first run compiles its kernels for about a minute)",
        default=jobs.SILENCE_WARN_S, min=1, soft_max=3600,
    )
    silence_stop_s: IntProperty(
        name="Stop Silent Engine After",
        description="Seconds without any output after which a running engine is stopped as hung, with an error "
                    "in its job box (environment setup is never stopped). 0: never",
        default=jobs.SILENCE_STOP_S, min=0, soft_max=24 * 3600,
    )

    def draw(self, context):
        layout = self.layout
        col = layout.column()
        col.use_property_split = True
        row = col.row(align=True)
        row.prop(self, "engine_python")
        row.operator("motion_splats.detect_interpreter", text="Detect", icon="VIEWZOOM")
        if not self.engine_python:
            resolved = engine_python(context)
            col.label(text=f"Automatic: {resolved or 'no interpreter found'}", icon="INFO")
        col.prop(self, "device")
        col.prop(self, "results_dir")
        if not self.results_dir:
            col.label(text=f"Automatic: {results_dir(context)}", icon="INFO")
        col.prop(self, "cache_dir")
        if not self.cache_dir:
            col.label(text=f"Automatic: {cache_dir(context)}", icon="INFO")
        col.prop(self, "silence_warn_s")
        col.prop(self, "silence_stop_s")

        sub = layout.column()
        sub.use_property_split = True
        sub.label(text="ONNX models (optional)")
        for key in ("onnx_tokens", "onnx_depth", "onnx_segmentation", "onnx_tracker"):
            sub.prop(self, key)

        layout.separator()
        row = layout.row()
        row.operator("motion_splats.check_engine", icon="CHECKMARK")
        draw_check_result(layout, jobs.latest("check_engine"))

        layout.separator()
        env = layout.column()
        env.use_property_split = True
        env.prop(self, "base_python")
        if not self.base_python:
            env.label(text=f"Automatic: {env_setup.find_base_python() or 'no Python on PATH'}", icon="INFO")
        env.label(text=f"Environment folder: {engine_venv_dir()}")
        env.operator("motion_splats.create_engine_env", icon="CONSOLE")
        if not bpy.app.online_access:
            env.label(text="Online access is off (Preferences > System > Network)", icon="ERROR")
        job = jobs.latest("env_setup")
        box = _draw_job(layout, job, "Engine environment ready")
        if box is not None and job.state != "finished":
            for line in job.error_summary():
                box.label(text=line[:160])
        models_ui.draw(layout, context)


from . import models_ui  # noqa: E402  (the Models box and its operators, issue #20)

CLASSES = (MotionSplatsPreferences, *models_ui.CLASSES)
