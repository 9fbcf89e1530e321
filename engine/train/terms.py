"""The training step's per-pixel and per-point loss terms, each through one fused CPU pass
where it applies and through the torch references of :mod:`.losses` elsewhere (the GPU path,
float64, and the tests' comparisons).

The fused passes (``engine/train/fused_image.py``, ``engine/train/fused_points.py``) replace
the ~40 small torch ops of these terms and their backward per step (most of their cost at
the preview size was per-op overhead); ``FUSED_TERMS = False`` switches them off.
"""

from __future__ import annotations

import torch

from ..geometry.camera import project
from . import losses as L
from .fused_image import fused_depth_term, fused_image_available, fused_l1_terms
from .fused_points import fused_on_mask, fused_track

#: the image / point terms through engine/train/fused_image.py and fused_points.py on the
#: CPU (tests switch it off to compare with the torch versions)
FUSED_TERMS = True


def image_l1_terms(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
                   pools: tuple[int, ...] = ()) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(l1(pred, target, weight), coarse_l1(pred, target, weight, pools), mse)`` with
    ``mse`` the mean squared error of ``clamp(pred, 0, 1)`` (for the PSNR metric, no
    gradient); ``coarse`` is 0 when ``pools`` is empty. Images ``[H, W, C]``, ``weight
    [H, W, 1]`` or None. CPU float32 images go through one fused pass (:mod:`.fused_image`),
    everything else through :func:`~.losses.l1` / :func:`~.losses.coarse_l1` (the references)."""
    if FUSED_TERMS and fused_image_available(pred, target, *([] if weight is None else [weight])):
        return fused_l1_terms(pred, target, weight, tuple(pools))
    coarse = L.coarse_l1(pred, target, weight, tuple(pools)) if pools else pred.new_zeros(())
    with torch.no_grad():
        mse = ((pred.detach().clamp(0, 1) - target) ** 2).mean()
    return L.l1(pred, target, weight), coarse, mse


def depth_term(depth_sum: torch.Tensor, alpha: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """The training loss's depth term: :func:`~.losses.depth_shift_scale_invariant` of the rendered
    expected depth ``depth_sum / alpha`` (the rasteriser accumulates ``Σ w_i z_i``) against
    ``prior``, over the pixels with ``prior > 0`` and ``alpha > 0.5``. All ``[H, W]``;
    ``alpha`` is taken as a constant. CPU float32 goes through the fused kernel
    (:mod:`.fused_image`), everything else through the torch ops below (the reference)."""
    alpha = alpha.detach()
    if FUSED_TERMS and fused_image_available(depth_sum, alpha, prior):
        return fused_depth_term(depth_sum, alpha, prior)
    valid = (prior > 0) & (alpha > 0.5)
    return L.depth_shift_scale_invariant(depth_sum / alpha.clamp_min(1e-6), prior, valid)


def track_term(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, target_uv: torch.Tensor,
               scale: float) -> torch.Tensor:
    """:func:`~.losses.track_loss` of world points ``points [P, 3]`` projected by the camera ``K [3, 3]``,
    ``w2c [4, 4]`` against their tracks' pixels ``target_uv [P, 2]``, every point visible. CPU
    float32 goes through one fused pass (:mod:`.fused_points`), everything else through
    :func:`~engine.geometry.camera.project` and :func:`~.losses.track_loss` (the reference)."""
    if FUSED_TERMS and fused_image_available(points, K, w2c, target_uv):
        return fused_track(points, K, w2c, target_uv, scale)
    uv, _ = project(K, w2c, points)
    return L.track_loss(uv, target_uv, torch.ones(points.shape[0], dtype=torch.bool, device=points.device), scale)


def on_mask_term(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, dist: torch.Tensor,
                 scale: float) -> torch.Tensor:
    """:func:`~.losses.on_mask_loss` of world points ``points [P, 3]`` projected by the camera ``K [3, 3]``,
    ``w2c [4, 4]``; points behind the camera are not scored (they count 0). CPU float32 goes
    through one fused pass (:mod:`.fused_points`), everything else through
    :func:`~engine.geometry.camera.project` and :func:`~.losses.on_mask_loss` (the reference)."""
    if FUSED_TERMS and fused_image_available(points, K, w2c, dist):
        return fused_on_mask(points, K, w2c, dist, scale)
    uv, z = project(K, w2c, points)
    uv = torch.where((z > 0).unsqueeze(-1), uv, uv.new_tensor(-1.0))  # behind the camera: not scored
    return L.on_mask_loss(uv, dist, scale)
