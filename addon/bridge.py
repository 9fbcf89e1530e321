# SPDX-License-Identifier: GPL-3.0-or-later
"""Run the engine as a subprocess and read its JSON-lines events without blocking Blender.

This module is bpy-free (stdlib + ``engine.protocol``), so it is unit-tested without
Blender. :class:`EngineProcess` starts a command with ``subprocess.Popen`` (argument list,
never ``shell=True``) in a new process group, reads stdout on a thread (each line is
validated with :func:`engine.protocol.parse_event`; anything else is kept as log text),
keeps the last stderr lines in a ring buffer, and hands events to the UI through
:meth:`EngineProcess.poll_events` (optionally a capped batch: the rest stays queued,
:attr:`EngineProcess.pending_events`). :attr:`EngineProcess.last_output` is when the last
line arrived (the add-on's no-output watchdog). :meth:`EngineProcess.cancel` escalates
SIGINT -> SIGTERM -> SIGKILL on a background thread and returns at once.
"""

from __future__ import annotations

import collections
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from ..engine.protocol import PROTOCOL_VERSION, parse_event

#: The extension root: the folder that holds ``engine/`` (cwd of ``python -m engine``).
EXTENSION_ROOT = Path(__file__).resolve().parents[1]

#: States of an :class:`EngineProcess`.
STATES = ("idle", "running", "finished", "failed", "cancelled")

#: Longest stdout line kept (characters); longer lines are cut and never parsed as events.
MAX_LINE_CHARS = 1 << 20
#: Seconds to wait for the reader threads after the process exited (a grandchild may
#: keep the pipes open).
READER_GRACE_S = 2.0

_WINDOWS = os.name == "nt"
_PREFS_HINT = "Set the engine interpreter in Preferences > Add-ons > Motion Splats (or use Detect / Create engine environment)."


def engine_command(python: str, command: str, args=()) -> list[str]:
    """The argument list that runs ``python -m engine <command> --jsonl <args...>``."""
    return [str(python), "-m", "engine", str(command), "--jsonl", *(str(a) for a in args)]


def child_env(extra: dict | None = None) -> dict:
    """Environment for the engine: ours, minus Blender's Python variables, unbuffered UTF-8."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "PYTHONPATH", "PYTHONSTARTUP")}
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONIOENCODING"] = "utf-8"
    if extra:
        env.update({str(k): str(v) for k, v in extra.items()})
    return env


def strip_tracebacks(lines) -> list[str]:
    """Drop ``Traceback (most recent call last):`` blocks, keeping each final exception line."""
    out: list[str] = []
    in_tb = False
    for raw in lines:
        line = raw.rstrip("\n")
        if line.startswith("Traceback (most recent call last)") or line.startswith("During handling of the above") \
                or line.startswith("The above exception was the direct cause"):
            in_tb = True
            continue
        if in_tb:
            if not line.strip() or line.startswith((" ", "\t")):
                continue  # frames, source lines and carets are indented
            in_tb = False  # the first unindented line is the exception itself
        if line.strip():
            out.append(line)
    return out


class EngineProcess:
    """One engine (or other JSON-lines) subprocess.

    Parameters
    ----------
    argv : list of str
        The full command line (see :func:`engine_command`; tests pass fake engines).
    cwd : path, optional
        Working directory (default: the extension root, so ``-m engine`` resolves).
    env : dict, optional
        Environment (default :func:`child_env`).
    stderr_lines : int
        How many trailing stderr lines to keep for error reports.
    label : str
        What to call the program in messages (default: the interpreter path).
    """

    def __init__(self, argv, *, cwd=None, env=None, stderr_lines: int = 200, stdout_lines: int = 200,
                 label: str | None = None):
        if not argv:
            raise ValueError("argv must not be empty")
        self.argv = [str(a) for a in argv]
        self.cwd = str(cwd) if cwd is not None else str(EXTENSION_ROOT)
        self.env = env if env is not None else child_env()
        self.label = label or self.argv[0]
        self.stderr_tail: collections.deque[str] = collections.deque(maxlen=stderr_lines)
        self.text_lines: collections.deque[str] = collections.deque(maxlen=stdout_lines)  # non-event stdout
        self.result: dict | None = None
        self.error_event: dict | None = None
        self.last_progress: dict | None = None
        self.returncode: int | None = None
        self.start_error: str | None = None
        self.failure: str | None = None  # our own message when the run failed without an error event
        self.started_at: float | None = None
        self.ended_at: float | None = None
        self._state = "idle"
        self._events: queue.Queue = queue.Queue()
        self._proc: subprocess.Popen | None = None
        self._threads: list[threading.Thread] = []
        self._cancel_requested = False
        self._stop_reason: str | None = None  # why the add-on (not the user) stopped the run
        self._cancel_thread: threading.Thread | None = None
        #: monotonic time the last stdout or stderr line arrived (the start time before any)
        self.last_output: float | None = None
        self._exited_at: float | None = None
        self._lock = threading.Lock()

    @classmethod
    def for_engine(cls, python: str, command: str, args=(), **kwargs) -> "EngineProcess":
        """An (unstarted) process for ``python -m engine <command> --jsonl <args>``."""
        kwargs.setdefault("label", f"engine interpreter {python!r}")
        return cls(engine_command(python, command, args), **kwargs)

    # -- life cycle --------------------------------------------------------------------
    def start(self) -> "EngineProcess":
        """Start the process. Never raises for a bad interpreter: the state becomes 'failed'."""
        if self._state != "idle":
            raise RuntimeError("process already started")
        self.started_at = time.monotonic()
        kwargs = dict(stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                      encoding="utf-8", errors="replace", bufsize=1, cwd=self.cwd, env=self.env)
        if _WINDOWS:
            kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP | getattr(subprocess, "CREATE_NO_WINDOW", 0)
        else:
            kwargs["start_new_session"] = True
        exe = self.argv[0]
        try:
            if not Path(exe).is_absolute() and os.sep not in exe and (os.altsep is None or os.altsep not in exe):
                pass  # a bare name is looked up on PATH by Popen
            elif not Path(exe).exists():
                raise FileNotFoundError(exe)
            self._proc = subprocess.Popen(self.argv, **kwargs)  # noqa: S603 (argument list, no shell)
        except (OSError, ValueError) as exc:
            self.start_error = self._start_failure_message(exc)
            self.failure = self.start_error
            self._state = "failed"
            self.ended_at = time.monotonic()
            return self
        self._state = "running"
        self.last_output = time.monotonic()
        self._threads = [
            threading.Thread(target=self._read_stdout, name="motion-splats-stdout", daemon=True),
            threading.Thread(target=self._read_stderr, name="motion-splats-stderr", daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def _start_failure_message(self, exc: BaseException) -> str:
        exe = self.argv[0]
        if isinstance(exc, FileNotFoundError):
            why = "was not found"
        elif isinstance(exc, PermissionError):
            why = "is not executable (permission denied)"
        else:
            why = f"could not be started ({type(exc).__name__}: {exc})"
        return f"The Python interpreter {exe!r} {why}. {_PREFS_HINT}"

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def state(self) -> str:
        """'idle' | 'running' | 'finished' | 'failed' | 'cancelled' (updated without blocking)."""
        self._update()
        return self._state

    @property
    def done(self) -> bool:
        return self.state in ("finished", "failed", "cancelled")

    @property
    def exit_code(self) -> int | None:
        self._update()
        return self.returncode

    @property
    def cancel_requested(self) -> bool:
        return self._cancel_requested

    @property
    def pending_events(self) -> int:
        """Events read but not yet handed out by :meth:`poll_events`."""
        return self._events.qsize()

    def poll_events(self, max_events: int | None = None) -> list[dict]:
        """Events read since the last call, in order (never blocks).

        With ``max_events`` at most that many; the rest stay queued for the next call
        (:attr:`pending_events`), so nothing is ever dropped. Note that :attr:`state` may
        already be final while events are still queued: a caller that caps the batch must
        keep polling until :attr:`pending_events` is 0 (``addon.jobs.drain`` does).
        """
        out: list[dict] = []
        limit = None if max_events is None else max(int(max_events), 0)

        def take():
            while limit is None or len(out) < limit:
                try:
                    out.append(self._events.get_nowait())
                except queue.Empty:
                    return

        take()
        self._update()
        # Events that arrived while we updated the state belong to this batch too.
        take()
        return out

    def wait(self, timeout: float | None = None) -> str:
        """Block until the run is over (tests and scripts; never from the UI). Returns the state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.done:
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"{self.label} still running after {timeout} s")
            time.sleep(0.02)
        return self._state

    def cancel(self, timeout: float = 5.0, reason: str | None = None) -> None:
        """Ask the engine to stop: SIGINT (it checkpoints), SIGTERM after ``timeout``/2,
        SIGKILL after ``timeout``. Returns at once; escalation runs on a thread.

        ``reason``: the add-on stops the run itself (the no-output watchdog of
        ``addon.jobs``); the run then ends 'failed' with ``reason`` as its first error
        line instead of 'cancelled'."""
        with self._lock:
            if self._proc is None or self._cancel_requested or self._proc.poll() is not None:
                return
            self._cancel_requested = True
            self._stop_reason = reason
            self._cancel_thread = threading.Thread(target=self._escalate, args=(float(timeout),),
                                                   name="motion-splats-cancel", daemon=True)
            self._cancel_thread.start()

    def kill(self) -> None:
        """Kill the process group now."""
        self._signal("kill")

    # -- internals ---------------------------------------------------------------------
    def _signal(self, which: str) -> None:
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        try:
            if _WINDOWS:
                if which == "int":
                    proc.send_signal(signal.CTRL_BREAK_EVENT)
                elif which == "term":
                    proc.terminate()
                else:
                    proc.kill()
            else:
                sig = {"int": signal.SIGINT, "term": signal.SIGTERM, "kill": signal.SIGKILL}[which]
                try:
                    os.killpg(proc.pid, sig)  # the engine and any children it started
                except (ProcessLookupError, PermissionError):
                    proc.send_signal(sig)
        except (OSError, ValueError):
            pass

    def _escalate(self, timeout: float) -> None:
        proc = self._proc
        steps = (("int", timeout / 2), ("term", timeout / 2), ("kill", 2.0))
        for which, wait_s in steps:
            self._signal(which)
            try:
                proc.wait(timeout=max(wait_s, 0.05))
                return
            except subprocess.TimeoutExpired:
                continue
            except Exception:  # noqa: BLE001 (never let the thread die noisily)
                return

    @staticmethod
    def _capped_lines(stream):
        """Yield ``(line, cut)`` from ``stream``; a line longer than ``MAX_LINE_CHARS`` is
        yielded once, truncated, with ``cut=True`` and the rest discarded up to its newline.
        Closes the stream when it ends or breaks."""
        try:
            while True:
                line = stream.readline(MAX_LINE_CHARS)
                if not line:
                    break
                cut = not line.endswith("\n") and len(line) >= MAX_LINE_CHARS
                if cut:
                    while True:
                        rest = stream.readline(MAX_LINE_CHARS)
                        if not rest or rest.endswith("\n"):
                            break
                yield line, cut
        except (OSError, ValueError):
            pass
        finally:
            try:
                stream.close()
            except (OSError, ValueError):
                pass

    def _read_stdout(self) -> None:
        for line, cut in self._capped_lines(self._proc.stdout):
            self.last_output = time.monotonic()
            if cut:  # a huge line is never parsed as an event; keep its head as text
                self.text_lines.append(line[:2000] + f"... [line cut at {MAX_LINE_CHARS} characters]")
                continue
            event = parse_event(line)
            if event is None:
                text = line.rstrip("\r\n")
                if text.strip():
                    self.text_lines.append(text[:2000])
                continue
            kind = event["event"]
            if kind == "result":
                self.result = event
            elif kind == "error":
                self.error_event = event
            elif kind == "progress":
                self.last_progress = event
            self._events.put(event)

    def _read_stderr(self) -> None:
        for line, cut in self._capped_lines(self._proc.stderr):
            self.last_output = time.monotonic()
            if cut:
                line = line[:2000] + " ..."
            text = line.rstrip("\r\n")
            # tqdm redraws with carriage returns: keep the last frame only.
            self.stderr_tail.append(text.rsplit("\r", 1)[-1][:2000])

    def _update(self) -> None:
        if self._state != "running":
            return
        proc = self._proc
        code = proc.poll()
        if code is None:
            return
        now = time.monotonic()
        if self._exited_at is None:
            self._exited_at = now
        readers_alive = any(t.is_alive() for t in self._threads)
        if readers_alive and now - self._exited_at < READER_GRACE_S:
            return  # let the readers drain the pipes first
        with self._lock:
            if self._state != "running":
                return
            self.returncode = code
            self.ended_at = now
            self._state = self._final_state(code)

    def _final_state(self, code: int) -> str:
        if self._cancel_requested and self.result is None:
            if self._stop_reason:
                self.failure = self._stop_reason
                return "failed"
            return "cancelled"
        if self.error_event is not None:
            return "failed"
        if self.result is not None:
            if code == 0:
                return "finished"
            self.failure = f"{self.label} reported a result but exited with code {code}."
            return "failed"
        if code == 0:
            self.failure = (f"The engine exited without a result ({self.label}). "
                            "It may be an older or different program; check the engine interpreter in Preferences.")
        elif code < 0 and not _WINDOWS:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            self.failure = f"The engine was killed by {name}" + (" (out of memory?)." if name == "SIGKILL" else ".")
        elif code == 130:
            self.failure = "The engine was interrupted."
        else:
            self.failure = f"The engine stopped with exit code {code}."
        return "failed"

    # -- reporting ---------------------------------------------------------------------
    def error_summary(self, max_lines: int = 6) -> list[str]:
        """User-facing lines explaining a failure (empty while running or after success).

        The engine's own ``error`` event (message, path, fix) wins; otherwise our message
        plus the last stderr lines with tracebacks reduced to their exception line.
        """
        state = self.state
        if state in ("idle", "running", "finished"):
            return []
        if state == "cancelled":
            return ["Cancelled."]
        lines: list[str] = []
        if self._stop_reason and self.failure == self._stop_reason:
            lines.append(self._stop_reason)  # the engine's own "interrupted" error is a consequence
            return lines
        if self.error_event is not None:
            ev = self.error_event
            lines.append(str(ev.get("message") or "The engine failed."))
            if ev.get("path"):
                lines.append(f"File: {ev['path']}")
            if ev.get("fix"):
                lines.append(f"Fix: {ev['fix']}")
            return lines
        if self.failure:
            lines.append(self.failure)
        tail = strip_tracebacks(self.stderr_tail) or strip_tracebacks(self.text_lines)
        tail = [t for t in tail if not _is_progress_bar(t)]
        room = max(max_lines - len(lines), 1)
        lines.extend(tail[-room:])
        return lines or [f"{self.label} failed."]


def _is_progress_bar(line: str) -> bool:
    return "%|" in line and "it/s" in line or line.count("█") > 3


__all__ = ["EngineProcess", "engine_command", "child_env", "strip_tracebacks", "EXTENSION_ROOT", "STATES",
           "PROTOCOL_VERSION", "MAX_LINE_CHARS"]
