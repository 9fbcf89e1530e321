"""Shared helpers for the bench commands: row printing, peak RSS, timing."""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from typing import Callable, Iterable


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MiB (Linux reports KiB)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / (1024.0 * 1024.0)


def current_rss_mb() -> float:
    """Current resident set size in MiB (from /proc; falls back to the peak)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / (1024.0 * 1024.0)
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()


def time_call(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` runs after ``warmup``."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1000.0)
    samples.sort()
    return samples[len(samples) // 2]


def machine_description() -> dict:
    """A short description of the machine for benchmark records."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version()}


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.3e}"
    return "-" if value is None else str(value)


def print_rows(rows: Iterable[dict], as_json: bool, stream=None) -> None:
    """Print ``rows`` as an aligned table, or one JSON object per row with ``as_json``."""
    stream = stream or sys.stdout
    rows = list(rows)
    if as_json:
        for row in rows:
            stream.write(json.dumps(row) + "\n")
        stream.flush()
        return
    if not rows:
        stream.write("(no rows)\n")
        return
    columns: list[str] = []
    for row in rows:
        columns += [key for key in row if key not in columns]
    cells = [[_fmt(row.get(col)) for col in columns] for row in rows]
    widths = [max(len(col), *(len(r[i]) for r in cells)) for i, col in enumerate(columns)]
    stream.write("  ".join(col.rjust(w) for col, w in zip(columns, widths)) + "\n")
    for r in cells:
        stream.write("  ".join(c.rjust(w) for c, w in zip(r, widths)) + "\n")
    stream.flush()


def run_child(cmd: list[str], cwd) -> tuple[str, str, int, float, float]:
    """Run ``cmd`` (an argument list) to completion in a child process.

    Returns ``(stdout, stderr, returncode, wall_s, peak_rss_mb)`` where the peak RSS is the
    child's own (``os.wait4`` rusage), so a bench row measures its configuration alone.
    stderr goes to a temporary file, not a pipe, so a chatty child cannot block on it.
    """
    import subprocess
    import tempfile

    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=err, text=True)
        out_text = proc.stdout.read()  # until EOF (the child exits)
        proc.stdout.close()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)  # so Popen does not reap it again
        err.seek(0)
        err_text = err.read()
    wall = time.perf_counter() - t0
    rss = usage.ru_maxrss / 1024.0 if sys.platform != "darwin" else usage.ru_maxrss / 2 ** 20
    return out_text, err_text, proc.returncode, wall, rss
