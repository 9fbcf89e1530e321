"""``gsplat`` backend: gsplat's CUDA rasteriser behind the same contract.

Used by ``backend='auto'`` for CUDA tensors when ``gsplat`` imports. Colours are evaluated
by :mod:`.sh` before this point, so gsplat only sees ``colors [N, 3]``. Settings chosen to
match :mod:`.reference`: ``eps2d=0.3``, ``rasterize_mode='classic'`` (no antialiasing
compensation), ``render_mode='RGB+D'`` (accumulated, un-normalised depth), ``packed=False``.
Known differences from :mod:`.reference` in gsplat 1.5.3 (read from its CUDA sources):
alpha is clamped at 0.999 instead of 0.99; a pixel stops when the transmittance would
reach ``<= 1e-4`` (ours: ``< 1e-4``); ``radii`` are gsplat's opacity-aware culling extents
(``ceil(min(3.33, sqrt(2 ln(255 o))) * sigma)`` per axis, the max of the two is returned)
instead of ``ceil(3 sigma_max)``. Its culling footprint is the same ``alpha >= 1/255``
ellipse bound as ours. ``means2d`` is gsplat's ``[1, N, 2]`` tensor (see
``RenderOutput.grad2d``).
"""

from __future__ import annotations

import torch

from .output import RenderOutput


def render_gsplat(means, quats, scales, opacities, colors, w2c, K, width, height, near, far, background,
                  extra=None):
    """Render with gsplat; returns :class:`engine.raster.output.RenderOutput`. ``extra [N]``
    rides along as a fourth colour channel (background 0, detached)."""
    import gsplat

    dev = means.device
    bg = None if background is None else background.to(dev, means.dtype)
    nc = colors.shape[-1]
    if extra is not None:
        colors = torch.cat([colors, extra.detach().to(colors)[:, None]], -1)
        if bg is not None:
            bg = torch.cat([bg, bg.new_zeros(1)])
    bg = None if bg is None else bg[None]
    rendered, alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, w2c.to(dev, means.dtype)[None], K.to(dev, means.dtype)[None],
        int(width), int(height), near_plane=float(near), far_plane=float(far), render_mode="RGB+D",
        backgrounds=bg, packed=False, eps2d=0.3, rasterize_mode="classic", sh_degree=None)
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 returns per-axis radii [N, 2]
        radii = radii.max(dim=-1).values
    radii = radii.to(torch.int32)
    ex = rendered[0, ..., nc:nc + 1] if extra is not None else None
    return RenderOutput(rgb=rendered[0, ..., :nc], alpha=alphas[0], depth=rendered[0, ..., -1:],
                        radii=radii, means2d=means2d,
                        visible=radii > 0, backend="gsplat", extra=ex)
