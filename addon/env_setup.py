# SPDX-License-Identifier: GPL-3.0-or-later
"""Create the engine's Python environment: ``python -m venv`` + ``pip install``.

Two uses, no bpy and no relative imports, so the same file is

* a module of the add-on (paths, the requirement pins, :func:`setup_command`), and
* a script the add-on runs as a background subprocess with the *base Python*::

      <base python> -u addon/env_setup.py --venv <dir> [--requirements <file>]

  It speaks the engine's JSON-lines protocol (version 1) on stdout -- ``progress`` per
  stage, ``log`` for every pip output line, then ``result`` or ``error`` -- so the
  add-on's :class:`~.bridge.EngineProcess` runs it like any engine command.

Why a separate "base Python" rather than Blender's own interpreter: inside Blender,
``sys.executable`` is Blender's bundled Python, which on several platforms/distro
packages ships without ``ensurepip``/``venv`` support files and without the C headers
that source-only wheels need, and whose version is tied to the Blender release (a venv
made from it would break on upgrade). A normal CPython 3.11/3.12 found on ``PATH`` (or
chosen in Preferences) gives the engine a stable environment of its own.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

#: Engine runtime packages, same pins as ``requirements.txt`` minus bpy and test tools.
#: ``requirements-engine.txt`` mirrors this list (a test keeps them equal); the list here
#: is what ships, because the extension build excludes ``requirements*.txt``.
ENGINE_REQUIREMENTS = (
    "torch==2.13.0",
    "numpy==1.26.4",
    "opencv-contrib-python-headless==4.11.0.86",
    "onnxruntime==1.31.1",
    "pycolmap==4.2.1",
    "scipy==1.17.1",
    "numba==0.68.1",
    "tqdm==4.70.1",
)

#: Base interpreters tried on PATH, in order (the engine is tested on 3.11).
BASE_PYTHON_NAMES = ("python3.11", "python3.12", "python3", "python")


def venv_python(venv_dir) -> Path:
    """The interpreter inside a venv folder."""
    venv_dir = Path(venv_dir)
    if os.name == "nt":
        return venv_dir / "Scripts" / "python.exe"
    return venv_dir / "bin" / "python"


def find_base_python() -> str:
    """A Python on PATH for creating the venv ("" when none is found)."""
    for name in BASE_PYTHON_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return ""


def setup_command(base_python: str, venv_dir, requirements=None) -> list[str]:
    """Argument list that runs this file as the setup script."""
    argv = [str(base_python), "-u", str(Path(__file__).resolve()), "--venv", str(venv_dir)]
    if requirements:
        argv += ["--requirements", str(requirements)]
    return argv


# -- the script --------------------------------------------------------------------------
def _emit(event: str, **fields) -> None:
    payload = {"v": 1, "event": event, "time": round(time.time(), 3)}
    payload.update(fields)
    sys.stdout.write(json.dumps(payload) + "\n")
    sys.stdout.flush()


def _run_logged(argv, stage: str, step: int, total: int) -> int:
    _emit("progress", stage=stage, step=step, total=total)
    _emit("log", level="info", message="$ " + " ".join(argv))
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, encoding="utf-8", errors="replace", bufsize=1)
    tail = []
    for line in proc.stdout:
        line = line.rstrip()
        if line:
            tail = (tail + [line])[-20:]
            _emit("log", level="info", message=line[:500])
    code = proc.wait()
    if code != 0:
        sys.stderr.write("\n".join(tail) + "\n")
    return code


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Create the Motion Splats engine environment.")
    parser.add_argument("--venv", required=True, help="folder of the virtual environment to create")
    parser.add_argument("--requirements", default=None, help="requirements file (default: the built-in pins)")
    args = parser.parse_args(argv)
    venv_dir = Path(args.venv)
    total = 3
    try:
        if sys.version_info < (3, 11):
            _emit("error", message=f"Python {sys.version.split()[0]} is too old for the engine (3.11+ needed).",
                  path=sys.executable, fix="Choose a Python 3.11 or 3.12 as Base Python in the add-on preferences.")
            return 2
        py = venv_python(venv_dir)
        if not py.exists():
            code = _run_logged([sys.executable, "-m", "venv", str(venv_dir)], "venv", 0, total)
            if code != 0 or not py.exists():
                _emit("error", message=f"Could not create a virtual environment with {sys.executable}.",
                      path=str(venv_dir), fix="Install the venv module for that Python (e.g. python3-venv) "
                                              "or choose another Base Python in the preferences.")
                return 1
        code = _run_logged([str(py), "-m", "pip", "install", "--upgrade", "pip"], "pip", 1, total)
        if code != 0:
            _emit("log", level="warning", message="could not upgrade pip; continuing with the bundled one")
        if args.requirements:
            reqs = ["-r", str(args.requirements)]
        else:
            reqs = list(ENGINE_REQUIREMENTS)
        code = _run_logged([str(py), "-m", "pip", "install", *reqs], "install", 2, total)
        if code != 0:
            _emit("error", message="pip could not install the engine packages (see the log).",
                  path=str(venv_dir), fix="Check the internet connection and free disk space, then try again.")
            return 1
        _emit("progress", stage="install", step=total, total=total)
        _emit("result", bundle=None, python=str(py), venv=str(venv_dir))
        return 0
    except KeyboardInterrupt:
        _emit("error", message="environment setup cancelled", path=str(venv_dir), fix=None)
        return 130


if __name__ == "__main__":
    sys.exit(main())
