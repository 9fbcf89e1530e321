# SPDX-License-Identifier: GPL-3.0-or-later
"""Running engine jobs, kept in a module-level registry (not in ``bpy.data``).

A file load replaces ``bpy.data`` but not Python modules, so jobs survive opening
another .blend. A persistent ``bpy.app.timers`` function (:func:`_timer`) calls
:func:`drain` every :data:`INTERVAL_S`: it moves events from each job's
:class:`~.bridge.EngineProcess` into the job's progress fields, tags the UI for redraw
and, when a job ends, calls its completion callback once (on the main thread).

A flood of events never freezes Blender: one :func:`drain` applies events for at most
:data:`TICK_BUDGET_S` (in batches of :data:`BATCH`) and leaves the rest queued in the
process; the timer then comes back after :data:`BACKLOG_INTERVAL_S`. A job completes only
when its process has ended *and* its queue is empty, so the final ``result``/``error``
event is always applied before the completion callback runs.

A silent engine is watched: no output line (stdout or stderr) for the preferences'
*Warn When Silent* seconds while the process is alive puts a message in the job box
(:meth:`Job.silence_lines`; Cancel keeps working); after *Stop Silent Engine After*
seconds (0: never) the run is stopped with a clear error. Environment setup (pip may
download for a long time without printing) only gets the warning.

Timers do not fire in background mode (``blender -b``, the bpy module); tests and
scripts call :func:`drain` themselves (or :func:`wait`).
"""

from __future__ import annotations

import collections
import itertools
import time
from dataclasses import dataclass, field
from typing import Callable

import bpy

from .bridge import EngineProcess

INTERVAL_S = 0.15
#: Seconds of event handling per :func:`drain` (one timer tick); the rest waits for the next tick.
TICK_BUDGET_S = 0.02
#: Events taken from a process per batch (the budget is checked between batches).
BATCH = 200
#: Timer interval while events are still queued (Blender handles its own events in between).
BACKLOG_INTERVAL_S = 0.01
#: Defaults of the watchdog preferences (used when the add-on's preferences are not there).
SILENCE_WARN_S = 120
SILENCE_STOP_S = 3600
#: Job kinds the watchdog only warns about, never stops (pip prints nothing while it downloads).
WARN_ONLY_KINDS = ("env_setup",)
#: Finished jobs kept for the UI (per kind the latest is shown).
KEEP_FINISHED = 8

_JOBS: "collections.OrderedDict[int, Job]" = collections.OrderedDict()
_IDS = itertools.count(1)


@dataclass
class Job:
    """One run of the engine (or of the environment setup) and what the UI shows of it."""

    id: int
    kind: str  # "check_engine", "env_setup", "train", ...
    label: str
    process: EngineProcess
    on_complete: Callable[["Job"], None] | None = None
    stage: str = ""
    step: int = 0
    total: int | None = None
    loss: float | None = None
    psnr: float | None = None
    eta_s: float | None = None
    metrics: dict = field(default_factory=dict)
    logs: collections.deque = field(default_factory=lambda: collections.deque(maxlen=200))
    result: dict | None = None
    error: dict | None = None
    state: str = "running"
    completed: bool = False  # completion callback has run
    callback_error: str | None = None
    #: scene work the completion callback left for when Blender is in Object Mode (see :func:`defer`)
    pending: Callable[[], None] | None = None
    started: float = field(default_factory=time.monotonic)
    ended: float | None = None
    #: when the last event arrived (a long silence after a finished stage is kernel compiling)
    last_event: float = field(default_factory=time.monotonic)
    #: when the last progress event arrived (its ``eta_s`` counts down from there)
    progress_at: float = field(default_factory=time.monotonic)
    #: seconds the process has printed nothing, once that reached the warning limit (else 0)
    silent_s: float = 0.0
    #: the watchdog's limit to stop the run (0: never), as it was at the last drain
    silence_stop_s: float = 0.0

    @property
    def running(self) -> bool:
        return self.state == "running"

    @property
    def factor(self) -> float:
        """Progress of the current stage in [0, 1] (0 when the total is unknown)."""
        if not self.total:
            return 0.0
        return max(0.0, min(1.0, self.step / self.total))

    def error_summary(self) -> list[str]:
        lines = list(self.process.error_summary())
        if self.callback_error:
            lines.append(self.callback_error)
        return lines

    def cancel(self, timeout: float = 5.0) -> None:
        self.process.cancel(timeout=timeout)

    def silence_lines(self) -> list[str]:
        """What the job box says about a silent engine ([] while it talks or has ended)."""
        if not self.running or not self.silent_s or self.process.cancel_requested:
            return []
        lines = [f"The engine has printed nothing for {_duration(self.silent_s)}: it may be hung",
                 "A first run compiles its kernels (about a minute); Cancel stops it"]
        if self.silence_stop_s and self.kind not in WARN_ONLY_KINDS:
            lines.append(f"It is stopped after {_duration(self.silence_stop_s)} of silence (Preferences)")
        return lines

    def apply(self, event: dict) -> None:
        self.last_event = time.monotonic()
        kind = event.get("event")
        if kind == "progress":
            self.progress_at = self.last_event
            self.stage = str(event.get("stage", ""))
            self.step = _as_int(event.get("step"), 0)
            self.total = _as_int(event.get("total"), None)
            self.eta_s = _as_float(event.get("eta_s"))
            for key, value in event.items():
                if key not in ("v", "event", "time", "stage", "step", "total", "eta_s"):
                    self.metrics[key] = value
            self.loss = _as_float(event.get("loss"), self.loss)
            self.psnr = _as_float(event.get("psnr"), self.psnr)
        elif kind == "log":
            self.logs.append(f"[{event.get('level', 'info')}] {event.get('message', '')}")
        elif kind == "result":
            self.result = event
        elif kind == "error":
            self.error = event


def _duration(seconds: float) -> str:
    """``"45 s"``, ``"2 min 5 s"``, ``"1 h 0 min"``."""
    seconds = int(max(seconds, 0))
    if seconds < 60:
        return f"{seconds} s"
    m, s = divmod(seconds, 60)
    if m < 60:
        return f"{m} min {s} s"
    h, m = divmod(m, 60)
    return f"{h} h {m} min"


def silence_limits() -> tuple[float, float]:
    """``(warn_s, stop_s)`` of the no-output watchdog, from the add-on's preferences."""
    from . import preferences  # noqa: PLC0415 (preferences imports this module)

    try:
        prefs = preferences.get()
    except (AttributeError, RuntimeError, ReferenceError):
        prefs = None
    if prefs is None:
        return float(SILENCE_WARN_S), float(SILENCE_STOP_S)
    return float(prefs.silence_warn_s), float(prefs.silence_stop_s)


def _as_int(value, default):
    try:
        return int(value)
    except (TypeError, ValueError):
        return default


def _as_float(value, default=None):
    try:
        return float(value) if value is not None else default
    except (TypeError, ValueError):
        return default


# -- registry ----------------------------------------------------------------------------
def start(kind: str, process: EngineProcess, *, label: str = "", on_complete=None) -> Job:
    """Start ``process`` (if not started) and track it as a job; returns the job.

    A process that fails to start (bad interpreter) still becomes a job in state
    'failed', so the UI shows the reason.
    """
    if process.state == "idle":
        process.start()
    job = Job(id=next(_IDS), kind=kind, label=label or kind.replace("_", " ").title(), process=process,
              on_complete=on_complete)
    _JOBS[job.id] = job
    _prune()
    ensure_timer()
    drain()
    return job


def get(job_id: int) -> Job | None:
    return _JOBS.get(int(job_id))


def all_jobs() -> list[Job]:
    return list(_JOBS.values())


def running(kind: str | None = None) -> list[Job]:
    return [j for j in _JOBS.values() if j.running and (kind is None or j.kind == kind)]


def latest(kind: str | None = None) -> Job | None:
    """The newest running job (of ``kind``), else the newest job of that kind."""
    jobs = [j for j in _JOBS.values() if kind is None or j.kind == kind]
    for job in reversed(jobs):
        if job.running:
            return job
    return jobs[-1] if jobs else None


def remove(job_id: int) -> None:
    job = _JOBS.pop(int(job_id), None)
    if job is not None and job.running:
        job.cancel()


def cancel_all(timeout: float = 5.0) -> None:
    for job in running():
        job.cancel(timeout=timeout)


def clear(cancel: bool = True) -> None:
    """Forget every job (cancelling running ones). Used by tests and unregister."""
    if cancel:
        cancel_all()
    _JOBS.clear()


def _prune() -> None:
    finished = [j for j in _JOBS.values() if not j.running]
    for job in finished[:-KEEP_FINISHED] if len(finished) > KEEP_FINISHED else []:
        _JOBS.pop(job.id, None)


# -- the pump ----------------------------------------------------------------------------
_FINAL = ("finished", "failed", "cancelled")


def drain(budget_s: float | None = None) -> bool:
    """Apply pending events to every running job; finish jobs whose process ended.

    Handles events for about ``budget_s`` seconds (default :data:`TICK_BUDGET_S`; each
    job gets at least one batch); what is left stays queued for the next call
    (:func:`backlog`). A job completes only once its process has ended and every event
    of it was applied. Returns True when anything changed (the UI was tagged for redraw).
    """
    budget = TICK_BUDGET_S if budget_s is None else budget_s
    deadline = time.monotonic() + budget
    changed = False
    limits = None
    for job in list(_JOBS.values()):
        if job.completed:
            changed |= _run_pending(job)
            continue
        # The state first: once it is final the readers are done, so every event is queued.
        state = job.process.state
        applied = 0
        while True:
            events = job.process.poll_events(BATCH)
            for event in events:
                job.apply(event)
            applied += len(events)
            if len(events) < BATCH or time.monotonic() >= deadline:
                break
        changed |= bool(applied)
        if state not in _FINAL:
            if limits is None:
                limits = silence_limits()
            changed |= _watch(job, *limits)
            continue
        if job.process.pending_events:
            continue  # the rest of its events first; the result/error event is among them
        job.state = state
        job.silent_s = 0.0
        job.completed = True
        job.ended = time.monotonic()
        if job.error is None and job.process.error_event is not None:
            job.error = job.process.error_event
        if job.on_complete is not None:
            try:
                job.on_complete(job)
            except Exception as exc:  # noqa: BLE001 (a builder bug must not kill the timer)
                job.callback_error = f"Building the result failed: {type(exc).__name__}: {exc}"
        changed = True
    if changed:
        tag_redraw()
    return changed


def _watch(job: Job, warn_s: float, stop_s: float) -> bool:
    """The no-output watchdog for one running job; True when what the box shows changed."""
    last = job.process.last_output
    if last is None:
        return False
    silent = time.monotonic() - last
    was = job.silent_s
    job.silent_s = silent if warn_s > 0 and silent >= warn_s else 0.0
    job.silence_stop_s = stop_s
    if job.silent_s and not was:
        job.logs.append(f"[warning] The engine has printed nothing for {_duration(silent)}")
    if stop_s > 0 and silent >= stop_s and job.kind not in WARN_ONLY_KINDS and not job.process.cancel_requested:
        job.process.cancel(reason=(
            f"The engine printed nothing for {_duration(silent)} and was stopped as hung. If a step really "
            "takes that long, raise 'Stop Silent Engine After' in the add-on preferences (0: never)."))
        job.logs.append("[warning] Stopping the silent engine")
        return True
    return bool(job.silent_s) or bool(was)


def backlog() -> int:
    """Events read from engines but not yet applied (a flood is applied over several ticks)."""
    return sum(j.process.pending_events for j in _JOBS.values() if not j.completed)


def object_mode() -> bool:
    """Whether scene building (armature edit bones need a mode switch) may run now."""
    return getattr(bpy.context, "mode", "OBJECT") in ("OBJECT", None)


def defer(job: Job, work: Callable[[], None], why: str) -> None:
    """Run ``work`` from :func:`drain` once Blender is in Object Mode (a timer must not
    switch the artist out of Edit or Pose Mode); ``why`` goes to the job's log."""
    job.pending = work
    job.logs.append(f"[info] {why}")
    ensure_timer()


def _run_pending(job: Job) -> bool:
    if job.pending is None or not object_mode():
        return False
    work, job.pending = job.pending, None
    try:
        work()
    except Exception as exc:  # noqa: BLE001 (a builder bug must not kill the timer)
        job.callback_error = f"Building the result failed: {type(exc).__name__}: {exc}"
    return True


def wait(job: Job, timeout: float = 60.0, step: float = 0.05) -> Job:
    """Pump :func:`drain` until ``job`` completed (tests/scripts; blocks)."""
    deadline = time.monotonic() + timeout
    while not job.completed or (job.pending is not None and object_mode()):
        drain()
        if job.completed:
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {job.label} still running after {timeout} s")
        if not backlog():
            time.sleep(step)
    return job


def tag_redraw() -> None:
    """Redraw the sidebar and the preferences wherever they are shown."""
    wm = getattr(bpy.context, "window_manager", None)
    if wm is None:
        return
    try:
        for window in wm.windows:
            screen = window.screen
            if screen is None:
                continue
            for area in screen.areas:
                if area.type in ("VIEW_3D", "PREFERENCES", "PROPERTIES", "CLIP_EDITOR"):
                    area.tag_redraw()
    except (AttributeError, ReferenceError, RuntimeError):
        pass


def _timer():
    try:
        drain()
    except Exception as exc:  # noqa: BLE001 (keep the pump alive)
        print(f"Motion Splats: job update failed: {type(exc).__name__}: {exc}")
    # Keep ticking while anything runs or waits to be built; stop otherwise (start() re-arms it).
    # A backlog of events comes back soon, after Blender handled its own events.
    if backlog():
        return BACKLOG_INTERVAL_S
    return INTERVAL_S if running() or any(j.pending for j in _JOBS.values()) else None


def ensure_timer() -> None:
    if not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=INTERVAL_S, persistent=True)


@bpy.app.handlers.persistent
def _on_load_post(*_args):
    """After a file load: jobs live on in this module; make sure the pump still runs."""
    if running():
        ensure_timer()
    tag_redraw()


def register() -> None:
    if _on_load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_on_load_post)
    if running():
        ensure_timer()


def unregister() -> None:
    # Disabling the add-on stops its engines instead of leaving orphans behind.
    cancel_all()
    if _on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load_post)
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
