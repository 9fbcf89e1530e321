"""Process-wide torch settings, applied once where a process starts.

``engine/cli.py`` (``python -m engine``) and ``engine/bench/__main__.py`` call
:func:`configure_torch` before any work; library objects (the trainer, the rasteriser)
never switch global state themselves. Tests that train in-process call it once
(``tests/engine/conftest.py``).
"""

from __future__ import annotations


def configure_torch(threads: int | None = None, deterministic: bool | None = None) -> None:
    """Set torch's thread count and deterministic mode for this process.

    Parameters
    ----------
    threads : int, optional
        Intra-op threads (the CPU rasteriser's Numba kernels follow torch's count);
        None keeps torch's default (all cores).
    deterministic : bool, optional
        ``torch.use_deterministic_algorithms(..., warn_only=True)``. On the CPU the
        index_put / scatter accumulations are otherwise thread-order dependent and
        ``--resume`` must reproduce an uninterrupted run bit for bit. Default: on unless
        CUDA is usable (CUDA's deterministic kernels cost speed and warn on cuBLAS; pass
        True for a CPU run on a CUDA machine).
    """
    import torch

    if threads:
        torch.set_num_threads(int(threads))
    if deterministic is None:
        deterministic = not torch.cuda.is_available()
    torch.use_deterministic_algorithms(bool(deterministic), warn_only=True)
