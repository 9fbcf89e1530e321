"""The one rendering entry point: :func:`render` and backend selection."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Optional

import torch

from .sh import sh_to_colors

BACKENDS = ("reference", "cpu", "gsplat")


@dataclass
class RenderOutput:
    """Result of :func:`render`.

    Attributes
    ----------
    rgb : Tensor [H, W, 3]
        Composited colour, background included (``+ T_final * background``).
    alpha : Tensor [H, W, 1]
        Accumulated opacity ``1 - T_final``.
    depth : Tensor [H, W, 1]
        Accumulated camera depth ``sum_i w_i z_i`` -- *not* divided by alpha; the expected
        depth of the visible surface is ``depth / alpha.clamp_min(eps)``.
    radii : Tensor [N] int32
        Screen radius ``ceil(3 sigma_max)`` in pixels; 0 = not visible.
    means2d : Tensor [N, 2] (``[1, N, 2]`` for gsplat, its own tensor)
        Projected means in pixels; an autograd intermediate with ``retain_grad()`` called,
        so after ``loss.backward()`` its ``.grad`` holds the 2D-mean gradient. Use
        :meth:`grad2d` for a backend-independent ``[N, 2]`` view of it.
    visible : Tensor [N] bool
        ``radii > 0``.
    backend : str
        The backend that ran.
    extra : Tensor [H, W, 1] or None
        ``sum_i w_i e_i`` of the ``extra`` per-Gaussian scalar given to :func:`render`
        (no background), else None.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    radii: torch.Tensor
    means2d: torch.Tensor
    visible: torch.Tensor
    backend: str
    extra: Optional[torch.Tensor] = None

    def grad2d(self) -> Optional[torch.Tensor]:
        """Gradient of the loss w.r.t. the 2D means, ``[N, 2]`` (None before backward)."""
        g = self.means2d.grad
        return None if g is None else g.reshape(-1, 2)


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
    is installed, else ``reference``.
    """
    if name not in ("auto",) + BACKENDS:
        raise ValueError(f"unknown raster backend {name!r}; choose auto, {', '.join(BACKENDS)}")
    if name != "auto":
        return name
    if device.type == "cuda":
        return "gsplat" if gsplat_available() else "reference"
    return "cpu" if numba_available() else "reference"


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
