"""The result of one render: :class:`RenderOutput`, shared by every backend.

Kept apart from :mod:`.api` so backends (:mod:`.gsplat_backend`) build it without
importing the dispatcher that imports them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch


@dataclass
class RenderOutput:
    """Result of :func:`engine.raster.render`.

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
