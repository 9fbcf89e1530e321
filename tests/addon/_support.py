"""Shared helpers and fixtures for the engine-bridge tests (bridge, preferences, engine
operators). Test modules import the fixtures from here (``from tests.addon._support
import ...``) so the shared ``conftest.py`` stays untouched."""

from __future__ import annotations

import json
import sys
import textwrap
import time
from pathlib import Path

import pytest

bpy = pytest.importorskip("bpy")

REPO = Path(__file__).resolve().parents[2]
VENV_PYTHON = REPO / ".venv" / ("Scripts/python.exe" if sys.platform == "win32" else "bin/python")

#: Code every fake engine starts with: an ``emit`` that writes protocol events.
_PRELUDE = textwrap.dedent(
    """
    import json, os, signal, sys, time
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as engine/cli.py does
    def emit(event, **fields):
        payload = {"v": 1, "event": event, "time": time.time()}
        payload.update(fields)
        sys.stdout.write(json.dumps(payload) + "\\n")
        sys.stdout.flush()
    """
)


def fake_engine(tmp_path: Path, name: str, body: str) -> list[str]:
    """Write a fake engine script into ``tmp_path``; return the argv that runs it."""
    path = tmp_path / f"{name}.py"
    path.write_text(_PRELUDE + textwrap.dedent(body), encoding="utf-8")
    return [sys.executable, "-u", str(path)]


def failing_python(tmp_path: Path, delay_s: float = 3.0) -> Path:
    """An executable 'interpreter' in ``tmp_path`` that exits with status 3 after ``delay_s``,
    for an engine job that must fail. Not at once: the Reconstruct operator reports a job that
    has already failed by the time it returns as an error (CANCELLED), and under load (two test
    workers) an instant exit could win that race."""
    fake = tmp_path / "fake_python"
    fake.write_text(f"#!{sys.executable}\nimport sys, time\ntime.sleep({float(delay_s)!r})\nsys.exit(3)\n",
                    encoding="utf-8")
    fake.chmod(0o755)
    return fake


def look_at_w2c(eye, target=(0.0, 0.0, 0.0)):
    """OpenCV world-to-camera ``[4, 4]`` (float64) of a camera at ``eye`` looking at ``target``, z up."""
    import numpy as np

    eye = np.asarray(eye, float)
    z = np.asarray(target) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world (OpenCV: x right, y down, z forward)
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def event_line(event: str, **fields) -> str:
    return json.dumps({"v": 1, "event": event, "time": 0.0, **fields})


def wait_until(predicate, timeout: float = 10.0, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


@pytest.fixture()
def user_dir(tmp_path, monkeypatch):
    """The extension's user folder, redirected into the test's tmp dir."""
    folder = tmp_path / "user"
    monkeypatch.setenv("MOTION_SPLATS_USER_DIR", str(folder))
    return folder


@pytest.fixture()
def clean_jobs(extension):
    """The job registry, emptied (running jobs killed) after the test."""
    jobs = extension.addon.jobs
    yield jobs
    for job in jobs.all_jobs():
        if job.running:
            job.process.kill()
            try:
                job.process.wait(10)
            except TimeoutError:
                pass
    jobs.clear(cancel=False)


@pytest.fixture()
def registered(extension, empty_scene, user_dir, clean_jobs):
    """The extension registered and enabled by name, so its preferences exist.

    Yields the preferences object; unregisters and removes the add-on entry after.
    """
    extension.register()
    addons = bpy.context.preferences.addons
    entry = addons.get(extension.__name__)
    created = entry is None
    if created:
        entry = addons.new()
        entry.module = extension.__name__
    try:
        yield entry.preferences
    finally:
        if created:
            entry = addons.get(extension.__name__)
            if entry is not None:
                addons.remove(entry)
        extension.unregister()


def fcurves_of(obj):
    """The F-curves of ``obj``'s action on any supported Blender: the channelbag of a
    layered action (4.4+), else ``Action.fcurves`` (4.2/4.3)."""
    action = obj.animation_data.action
    if not hasattr(action, "layers"):
        return action.fcurves
    return action.layers[0].strips[0].channelbags[0].fcurves


def render_cycles_exr_animation(scene, filepath: str, frames: tuple[int, int, int], samples: int) -> None:
    """Render ``frames`` = (start, end, step) of ``scene`` with CPU Cycles, ``samples`` samples, no
    denoising, transparent film, at full resolution, to OpenEXR files ``<filepath>NNNN.exr``."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.render.film_transparent = True
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.frame_start, scene.frame_end, scene.frame_step = frames
    scene.render.filepath = filepath
    bpy.ops.render.render(animation=True)
