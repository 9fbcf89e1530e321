"""The engine's progress protocol: versioned JSON lines on stdout.

The add-on starts the engine with ``--jsonl`` and reads one JSON object per stdout
line. Every event carries ``"v"`` (:data:`PROTOCOL_VERSION`) and ``"event"``:

``progress``  ``stage`` (str), ``step`` (int), ``total`` (int or null), optional
              ``eta_s`` (measured, see :meth:`Reporter.progress`) and metrics such as
              ``loss``/``psnr``. The stage ``compile`` is the Numba kernels loading or
              compiling (engine/train/warmup.py).
``log``       ``level`` ("debug"|"info"|"warning"), ``message``.
``result``    ``bundle`` (path) and any command-specific fields; the last event of a
              successful run.
``error``     ``message``, optional ``path`` and ``fix``; the last event of a failed run.

Without ``--jsonl`` the same calls draw tqdm bars and log lines on stderr, and the
result is printed to stdout as one JSON object. This module is bpy-free and torch-free:
the add-on imports :func:`parse_event` from it to validate what it reads.
"""

from __future__ import annotations

import json
import math
import sys
import time
from typing import IO, Any

PROTOCOL_VERSION = 1
EVENTS = ("progress", "log", "result", "error")
_REQUIRED = {"progress": ("stage", "step"), "log": ("message",), "result": (), "error": ("message",)}


def _clean(value: Any) -> Any:
    """Make a metric JSON-safe: tensors/np scalars -> float, NaN/inf -> None."""
    if hasattr(value, "item") and callable(value.item):
        try:
            value = value.item()
        except (ValueError, RuntimeError):
            return None
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class Reporter:
    """Emits protocol events (``jsonl=True``) or human output (tqdm + stderr).

    Parameters
    ----------
    jsonl : bool
        Write JSON lines to ``stream`` instead of drawing progress bars.
    stream : file, optional
        Where JSON lines go (default ``sys.stdout``).
    """

    def __init__(self, jsonl: bool = False, stream: IO[str] | None = None, quiet: bool = False):
        self.jsonl = jsonl
        self.stream = stream if stream is not None else sys.stdout
        self.quiet = quiet
        self._bars: dict[str, Any] = {}
        #: per stage: (monotonic time of its first report, that report's step, the last step)
        self._stage_start: dict[str, tuple[float, int, int]] = {}

    # -- low level -------------------------------------------------------------------
    def emit(self, event: str, **fields: Any) -> None:
        if event not in EVENTS:
            raise ValueError(f"unknown event {event!r}")
        payload = {"v": PROTOCOL_VERSION, "event": event, "time": round(time.time(), 3)}
        payload.update({k: _clean(v) for k, v in fields.items()})
        self.stream.write(json.dumps(payload, allow_nan=False) + "\n")
        self.stream.flush()

    # -- events ----------------------------------------------------------------------
    def progress(self, stage: str, step: int, total: int | None = None, **metrics: Any) -> None:
        """Report ``step`` of ``total`` in ``stage``; adds ``eta_s`` when it can.

        The ETA is measured: ``(seconds since the stage's first report) / (steps since it)
        * (steps left)``. A stage's first report starts its clock and has no ETA: a stage
        first reported at a step ``s > 0`` (its start was not reported) gets one from its
        second report on, never a made-up ``0``. A step lower than the previous one
        restarts the clock (a stage name used again)."""
        now = time.monotonic()
        clock = self._stage_start.get(stage)
        if clock is None or step < clock[2]:
            clock = (now, step, step)
        self._stage_start[stage] = clock = (clock[0], clock[1], step)
        start, first, _ = clock
        if total and step > first and "eta_s" not in metrics:
            metrics["eta_s"] = round((now - start) / (step - first) * max(total - step, 0), 1)
        if self.jsonl:
            self.emit("progress", stage=stage, step=int(step), total=None if total is None else int(total), **metrics)
            return
        if self.quiet:
            return
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None:
            bar = self._bars[stage] = tqdm(total=total, desc=stage, file=sys.stderr, dynamic_ncols=True, leave=True)
        bar.n = step
        shown = {k: v for k, v in metrics.items() if k != "eta_s" and isinstance(_clean(v), (int, float))}
        if shown:
            bar.set_postfix({k: f"{_clean(v):.4g}" for k, v in shown.items()}, refresh=False)
        bar.refresh()
        if total is not None and step >= total:
            self.end_stage(stage)

    def end_stage(self, stage: str) -> None:
        bar = self._bars.pop(stage, None)
        if bar is not None:
            bar.close()
        self._stage_start.pop(stage, None)

    def log(self, message: str, level: str = "info") -> None:
        if self.jsonl:
            self.emit("log", level=level, message=message)
        elif not self.quiet or level == "warning":
            print(f"[{level}] {message}" if level != "info" else message, file=sys.stderr, flush=True)

    def result(self, **payload: Any) -> None:
        for stage in list(self._bars):
            self.end_stage(stage)
        if self.jsonl:
            self.emit("result", **payload)
        else:
            print(json.dumps({k: _clean(v) for k, v in payload.items()}, indent=2), flush=True)

    def error(self, message: str, path: str | None = None, fix: str | None = None) -> None:
        for stage in list(self._bars):
            self.end_stage(stage)
        if self.jsonl:
            self.emit("error", message=message, path=path, fix=fix)
        else:
            print(f"error: {message}", file=sys.stderr, flush=True)


def parse_event(line: str | bytes) -> dict | None:
    """Parse one line from the engine; return the event dict, or ``None`` for garbage.

    Anything that is not a JSON object with a known ``event``, a compatible ``v`` and
    the event's required fields is rejected, so a crashing engine or a stray print can
    never be mistaken for progress or a result.
    """
    if isinstance(line, bytes):
        line = line.decode("utf-8", errors="replace")
    line = line.strip()
    if not line.startswith("{"):
        return None
    try:
        obj = json.loads(line)
    except (ValueError, RecursionError):
        return None
    if not isinstance(obj, dict) or obj.get("v") != PROTOCOL_VERSION:
        return None
    event = obj.get("event")
    if event not in EVENTS or any(key not in obj for key in _REQUIRED[event]):
        return None
    return obj
