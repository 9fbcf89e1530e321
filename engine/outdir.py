"""Output folders of commands: refuse to clobber earlier results, never write into the
input, say when a bundle is a finished run, clear a replaced run's derived files.

Re-exported by :mod:`engine.bundle` (``B.check_output_dir`` ...); stdlib only, so the
add-on can import it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from .errors import InputError

SCENE_FILE = "scene.json"


# what a run derives from its bundle; stale once the bundle is replaced (the priors cache
# in ``cache/`` is keyed by its inputs and stays valid)
RUN_OUTPUTS = ("eval.json", "report", "checkpoints")


def clear_run_outputs(path: str | os.PathLike) -> list[str]:
    """Remove :data:`RUN_OUTPUTS` from a bundle folder about to be replaced (``--overwrite``).

    Without this an overwritten run kept the earlier run's ``eval.json`` (which the report
    and the quality bench then read as the new run's metrics) and its checkpoint (which a
    ``--resume`` after an early Cancel would have continued). Only these names are removed;
    returns the ones that existed.
    """
    import shutil

    path = Path(path)
    removed = []
    for name in RUN_OUTPUTS:
        p = path / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        else:
            continue
        removed.append(name)
    return removed


def check_output_dir(path: str | os.PathLike, overwrite: bool = False, resume: bool = False,
                     resumable: bool = True, option: str = "--out") -> Path:
    """Refuse to write into a folder that already holds results unless asked to.

    Raises :class:`InputError` when ``path`` exists and is a non-empty folder, unless
    ``overwrite`` or ``resume`` is set (earlier results are never clobbered silently).
    ``resumable=False`` (render, export) leaves ``--resume`` out of the advice. The lock
    file of :mod:`engine.lock` does not count as content.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{option} exists and is not a folder", path, f"choose a folder path for {option}")
    if path.is_dir() and any(p.name != ".motion-splats.lock" for p in path.iterdir()) and not (overwrite or resume):
        fix = (f"choose a new {option} folder, pass --resume to continue that run, or --overwrite to replace it"
               if resumable else f"choose a new or empty {option} folder, or pass --overwrite to write into it")
        raise InputError("output folder already holds files", path, fix)
    if resume and not overwrite:
        refuse_finished_resume(path)
    return path


def finished_steps(path: str | os.PathLike) -> int | None:
    """Steps of the finished training run in bundle ``path``, or ``None``.

    A bundle is finished when its ``scene.json`` is a training result (not the ``init``
    stage) whose ``stats.steps`` reached its ``config.steps`` and no checkpoint is left
    to continue (a finished run removes it). Only reads ``scene.json``; never raises.
    """
    path = Path(path)
    if (path / "checkpoints" / "checkpoint.pt").exists():
        return None
    try:
        scene = json.loads((path / SCENE_FILE).read_text(encoding="utf-8"))
        steps, target = scene["stats"]["steps"], scene["config"]["steps"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if scene.get("stage") == "init" or not isinstance(steps, int) or not isinstance(target, int):
        return None
    return steps if steps >= target else None


def refuse_finished_resume(path: str | os.PathLike) -> None:
    """Raise :class:`InputError` when ``--resume`` targets a finished bundle."""
    steps = finished_steps(path)
    if steps is not None:
        raise InputError(f"this bundle is a finished run ({steps} steps); there is no checkpoint to resume", path,
                         "drop --resume to keep it, pass --overwrite to train it again, or choose a new --out")


def check_not_input(out: str | os.PathLike, clip: str | os.PathLike, option: str = "--out") -> None:
    """Refuse an output folder that is the input clip's folder (or holds the input clip).

    A bundle written there would replace the dataset's own files (a Nerfies ``scene.json``)
    and ``--overwrite`` would clear them.
    """
    out_r, clip_r = Path(out).resolve(), Path(clip).resolve()
    inputs = {clip_r} | ({clip_r.parent} if clip_r.is_file() else set())
    if out_r in inputs or out_r in clip_r.parents:
        raise InputError(f"{option} is the input clip's folder (or contains it); the engine never writes into its "
                         "input", out, f"choose a separate {option} folder, e.g. {clip_r.parent / 'run'}")
