"""Per-phase wall and CPU time of the training step (used by ``python -m engine.bench train``).

``Trainer.phases`` is ``None`` in normal runs (the step then uses :func:`no_phase`, a
shared null context: no timing, no allocation). A bench sets it to a :class:`PhaseTimer`
to split the step into deformation, SH colour, raster forward, losses, backward,
optimizer, densification statistics and the rest.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict

_NULL = contextlib.nullcontext()


def no_phase(name: str):  # noqa: ARG001 - same signature as PhaseTimer.__call__
    """The disabled timer: a shared null context."""
    return _NULL


class PhaseTimer:
    """Accumulates wall (``perf_counter``) and process CPU (``process_time``, all threads)
    seconds per phase name. Phases must not nest (their sums would double count)."""

    def __init__(self):
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)

    def reset(self) -> None:
        self.wall.clear()
        self.cpu.clear()

    @contextlib.contextmanager
    def __call__(self, name: str):
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[name] += time.perf_counter() - w0
            self.cpu[name] += time.process_time() - c0

    def add(self, name: str, wall: float, cpu: float) -> None:
        self.wall[name] += wall
        self.cpu[name] += cpu
