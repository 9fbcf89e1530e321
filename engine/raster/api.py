"""The one rendering entry point: :func:`render` and backend selection."""

from __future__ import annotations

import importlib.util
import logging
from typing import Optional

import torch

from .output import RenderOutput
from .sh import sh_to_colors

BACKENDS = ("reference", "cpu", "gsplat")
#: gsplat version the tests and benchmarks ran (``requirements-gpu.txt`` pins it)
GSPLAT_TESTED = "1.5.3"
DENSE_FALLBACK_WARNING = (
    "gsplat is not installed: CUDA renders fall back to the dense reference rasteriser (O(H*W*N) memory "
    f"and time, far slower); install the tested version with `pip install gsplat=={GSPLAT_TESTED}` "
    "(requirements-gpu.txt) or pass --backend reference to silence this")

log = logging.getLogger(__name__)
_warned_fallback = False


def scales_from_log(log_scales: torch.Tensor) -> torch.Tensor:
    """Linear scales ``[N, 3]`` from log-scales (the PLY / optimiser parameterisation)."""
    return torch.exp(log_scales)


def gsplat_available() -> bool:
    """True when CUDA is usable and ``gsplat`` is importable (without importing it)."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def numba_available() -> bool:
    return importlib.util.find_spec("numba") is not None


def select_backend(name: str, device: torch.device) -> str:
    """Resolve ``name`` (``'auto'`` or one of :data:`BACKENDS`) for tensors on ``device``.

    ``auto``: ``gsplat`` for CUDA tensors when available, ``cpu`` for CPU tensors when Numba
    is installed, else ``reference``. CUDA without gsplat logs
    :data:`DENSE_FALLBACK_WARNING` once per process (the CLI shows it as a warning event).
    """
    if name not in ("auto",) + BACKENDS:
        raise ValueError(f"unknown raster backend {name!r}; choose auto, {', '.join(BACKENDS)}")
    if name != "auto":
        return name
    if device.type == "cuda":
        if gsplat_available():
            return "gsplat"
        _warn_dense_fallback()
        return "reference"
    return "cpu" if numba_available() else "reference"


def _warn_dense_fallback() -> None:
    """Say once per process that ``auto`` picked the dense rasteriser on CUDA (silent, it
    looked like a hang: minutes per frame and tens of GB at training sizes)."""
    global _warned_fallback
    if not _warned_fallback:
        _warned_fallback = True
        log.warning(DENSE_FALLBACK_WARNING)


def render(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
           colors: Optional[torch.Tensor] = None, sh: Optional[torch.Tensor] = None,
           sh_degree: Optional[int] = None, *, w2c: torch.Tensor, K: torch.Tensor, width: int, height: int,
           near: float = 0.01, far: float = 1e4, background: Optional[torch.Tensor] = None,
           extra: Optional[torch.Tensor] = None, backend: str = "auto") -> RenderOutput:
    """Render 3D Gaussians from one pinhole camera (differentiable).

    Parameters
    ----------
    means : Tensor [N, 3]
        World positions.
    quats : Tensor [N, 4]
        Rotations, wxyz; need not be normalised.
    scales : Tensor [N, 3]
        Linear standard deviations along the local axes (see :func:`scales_from_log`).
    opacities : Tensor [N]
        In ``[0, 1]`` (after the sigmoid).
    colors : Tensor [N, 3], optional
        RGB. Give either ``colors`` or ``sh``.
    sh : Tensor [N, M, 3], optional
        SH coefficients, ``M >= (sh_degree + 1) ** 2``; colour = ``max(SH(dir) + 0.5, 0)``
        with ``dir`` from the camera centre to the mean (3DGS convention).
    sh_degree : int, optional
        ``0..3``; default: the largest the coefficients allow.
    w2c : Tensor [4, 4]
        World-to-camera, OpenCV axes (not differentiated).
    K : Tensor [3, 3]
        Intrinsics in continuous pixel coordinates (pixel centres at ``+0.5``).
    width, height : int
    near, far : float
        Gaussians whose mean depth is outside ``(near, far)`` are culled.
    background : Tensor [3], optional
        Colour behind everything; black when None. Differentiable.
    extra : Tensor [N], optional
        A per-Gaussian scalar (e.g. a dynamic score) composited in the same pass as the
        colour, like a fourth colour channel with background 0: ``RenderOutput.extra``.
        It is not differentiated itself (treated as a constant); the gradient of its image
        reaches the geometry and opacities like the colour's does.
    backend : str
        ``'auto'`` (default), ``'reference'``, ``'cpu'`` or ``'gsplat'``.

    Returns
    -------
    RenderOutput
    """
    if (colors is None) == (sh is None):
        raise ValueError("give exactly one of colors or sh")
    if sh is not None:
        if sh_degree is None:
            sh_degree = min(3, int(round(sh.shape[1] ** 0.5)) - 1)
        colors = sh_to_colors(sh, sh_degree, means, w2c)
    name = select_backend(backend, means.device)
    if name == "cpu" and means.device.type != "cpu":
        raise ValueError("the cpu raster backend needs CPU tensors; use 'auto', 'gsplat' or 'reference'")
    if name == "gsplat":
        from .gsplat_backend import render_gsplat

        return render_gsplat(means, quats, scales, opacities, colors, w2c, K, width, height, near, far, background,
                             extra)
    if name == "cpu":
        from . import cpu as mod
    else:
        from . import reference as mod
    means2d, conics, depths, radii, extents = mod.project(means, quats, scales, opacities, w2c, K, width,
                                                          height, near, far)
    if means2d.requires_grad:
        means2d.retain_grad()
    visible = radii > 0
    if extra is not None and extra.shape != (means.shape[0],):
        raise ValueError(f"extra must be one value per Gaussian, shape ({means.shape[0]},); got {tuple(extra.shape)}")
    ex = None
    if name == "cpu":
        rgb, alpha, depth, ex = mod.rasterize(means2d, conics, depths, colors, opacities, radii, extents,
                                              width, height, background, extra)
        dt = means.dtype
        if rgb.dtype != dt:
            rgb, alpha, depth = rgb.to(dt), alpha.to(dt), depth.to(dt)
            ex = None if ex is None else ex.to(dt)
    else:
        res = mod.rasterize(means2d, conics, depths, colors, opacities, visible, width, height, background, extra)
        rgb, alpha, depth = res[:3]
        ex = res[4] if extra is not None else None
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, radii=radii, means2d=means2d, visible=visible,
                        backend=name, extra=ex)
