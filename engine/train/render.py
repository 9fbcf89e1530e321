"""Rendering a :class:`~engine.train.model.DynamicScene` through :mod:`engine.raster`.

Training, evaluation, the ``render`` command and the demo all render through
:func:`render_scene`, so they agree on colour (SH), background and backend choice.
"""

from __future__ import annotations

import torch

from .. import raster
from ..geometry.camera import camera_centers
from ..raster.sh import sh_to_colors

#: use the fused Numba SH colour (engine/train/fused_sh.py) where it applies
FUSED_SH = True


def scene_colors(model, means: torch.Tensor, w2c: torch.Tensor, index: torch.Tensor | None = None) -> torch.Tensor:
    """The 3DGS colours ``[G, 3]`` of ``model``'s SH at deformed ``means [G, 3]`` seen from
    ``w2c [4, 4]`` -- what :func:`render_scene` computes from the SH -- through the fused
    CPU kernel for degrees 0-1 (same values to float rounding), else
    :func:`engine.raster.sh.sh_to_colors`. ``index [L]``: the rows of the model ``means``
    belong to (then ``means [L, 3]`` -> ``[L, 3]``)."""
    sh_dc, sh_rest = model.sh_dc, model.sh_rest
    if index is not None:
        sh_dc, sh_rest = sh_dc[index], sh_rest[index]
    if FUSED_SH:
        try:
            from .fused_sh import fused_sh_available, fused_sh_colors
        except ImportError:  # no numba
            pass
        else:
            if fused_sh_available(model.sh_degree, means, sh_dc, sh_rest):
                return fused_sh_colors(means, sh_dc, sh_rest, model.sh_degree, w2c)
    return sh_to_colors(model.sh(index), model.sh_degree, means, w2c)


def render_scene(model, means: torch.Tensor, quats: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                 width: int, height: int, colors: torch.Tensor | None = None, backend: str = "auto",
                 background: torch.Tensor | None = None, extra: torch.Tensor | None = None,
                 time: float | None = None, index: torch.Tensor | None = None):
    """Render deformed Gaussians of ``model`` from one camera.

    Parameters
    ----------
    model : DynamicScene
        Supplies scales, opacities and SH coefficients (canonical, time-independent).
    means : (G, 3) deformed centres at the render time.
    quats : (G, 4) deformed rotations (wxyz).
    K : (3, 3), w2c : (4, 4) camera.
    colors : (G, 3), optional
        Render these colours instead of the model's SH (e.g. a dynamic-score mask).
    backend : str
        Rasteriser backend name (``auto`` picks the fastest available).
    extra : (G,), optional
        A per-Gaussian scalar composited in the same pass (``RenderOutput.extra [H, W, 1]``),
        e.g. the dynamic score of the mask term; see :func:`engine.raster.render`.
    time : float, optional
        Engine time of the render: Gaussians with a lifespan are windowed around their own
        time (:meth:`~engine.train.model.DynamicScene.opacities_at`); None = every Gaussian
        at full opacity.
    index : (L,) long, optional
        Render only these rows of the model (:func:`~engine.train.lifespan.shown_gaussians`):
        ``means`` / ``quats`` / ``colors`` / ``extra`` are then ``[L, ...]``, and so are the
        output's ``radii`` and ``means2d``.

    Returns
    -------
    raster.RenderOutput with ``rgb [H, W, 3]``, ``alpha [H, W, 1]``, ``depth [H, W, 1]``,
    ``radii [G]`` and ``means2d [G, 2]`` (its ``.grad`` feeds densification).
    """
    # (the view-bound Gaussians fade with the parallax from their own camera: shot_detail.py)
    scales = model.scales(index)
    opacities = model.opacities_at(time, index, means=means, view_center=camera_centers(w2c))
    kwargs = dict(means=means, quats=quats, scales=scales, opacities=opacities, w2c=w2c, K=K,
                  width=width, height=height, background=background, backend=backend, extra=extra)
    if colors is not None:
        return raster.render(colors=colors, **kwargs)
    return raster.render(sh=model.sh(index), sh_degree=model.sh_degree, **kwargs)
