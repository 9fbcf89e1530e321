"""Differentiable Gaussian rasteriser: one API, three backends.

Public API
----------
:func:`render`
    ``render(means [N,3], quats [N,4] wxyz, scales [N,3] linear, opacities [N] in [0,1],
    colors [N,3] | sh [N,M,3] + sh_degree, *, w2c [4,4], K [3,3], width, height,
    near=0.01, far=1e4, background [3] | None, backend='auto') -> RenderOutput``
:class:`RenderOutput`
    ``rgb [H,W,3]``, ``alpha [H,W,1]``, ``depth [H,W,1]`` (accumulated ``sum w_i z_i``, not
    divided by alpha), ``radii [N]`` int32 (0 = not visible), ``means2d [N,2]`` (retains
    its gradient; ``out.grad2d()`` gives it as ``[N,2]`` after backward, for densification),
    ``visible [N]`` bool, ``backend``.
:func:`engine.raster.reference.project` / ``rasterize`` and :func:`engine.raster.cpu.project`
/ ``rasterize`` are the two composable steps behind :func:`render`.
:func:`scales_from_log`, :func:`select_backend`, :data:`BACKENDS`.

Backends
--------
``reference``
    :mod:`.reference`: readable dense PyTorch on any device/dtype; the oracle.
``cpu``
    :mod:`.cpu` + :mod:`.cpu_numba`: Numba tile rasteriser with a hand-derived backward.
``gsplat``
    :mod:`.gsplat_backend`: gsplat's CUDA kernels, picked by ``auto`` for CUDA tensors.

All backends share the conventions in :mod:`.reference` (EWA projection, 0.3 px low-pass,
``alpha = min(0.99, o exp(-sigma))``, skip ``alpha < 1/255``, stop before transmittance
drops below ``1e-4``) and the SH colour of :mod:`.sh`, evaluated in torch before the
rasteriser so the backward of SH is autograd's.
"""

from .api import BACKENDS, RenderOutput, render, scales_from_log, select_backend

__all__ = ["BACKENDS", "RenderOutput", "render", "scales_from_log", "select_backend"]
