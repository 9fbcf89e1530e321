"""Fused image terms (engine/train/fused_image.py) against their torch references."""

from __future__ import annotations

import pytest
import torch

from engine.train import losses as L
from engine.train import terms as TM
from engine.train.fused_image import fused_depth_term, fused_l1_terms


def _rel(a, b):
    return ((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30)).item()


def _images(h, w, seed=0, weighted=True):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(h, w, 3, generator=g) * 1.2 - 0.1  # some values outside [0, 1]: the clamp
    target = torch.rand(h, w, 3, generator=g)
    weight = None
    if weighted:
        weight = (1.0 + 2.0 * (torch.rand(h, w, generator=g) > 0.8).float()).unsqueeze(-1)
    return pred, target, weight


@pytest.mark.parametrize("h,w,weighted,pools", [(36, 48, True, (4, 8)), (37, 50, True, (4, 8)),
                                                (37, 50, False, (4, 8)), (30, 41, True, ()),
                                                (19, 23, False, (3,))])
def test_fused_l1_terms_match_torch(h, w, weighted, pools):
    """Values and gradients of the L1, coarse L1 (ceil-mode border cells included) and the
    clamped MSE against l1 / coarse_l1 / psnr in float64."""
    pred, target, weight = _images(h, w, weighted=weighted)
    ref_pred = pred.double().requires_grad_(True)
    wd = None if weight is None else weight.double()
    ref_l1 = L.l1(ref_pred, target.double(), wd)
    ref_coarse = L.coarse_l1(ref_pred, target.double(), wd, pools) if pools else None
    ref_loss = 0.7 * ref_l1 + (1.3 * ref_coarse if pools else 0.0)
    ref_loss.backward()
    ref_psnr = float(L.psnr(pred.double().clamp(0, 1), target.double()))

    fus_pred = pred.clone().requires_grad_(True)
    l1, coarse, mse = fused_l1_terms(fus_pred, target, weight, pools)
    (0.7 * l1 + 1.3 * coarse).backward()
    assert l1.dtype == torch.float32 and l1.shape == () and not mse.requires_grad
    assert float(l1.detach()) == pytest.approx(float(ref_l1.detach()), rel=1e-6)
    if pools:
        assert float(coarse.detach()) > 1e-3
        assert float(coarse.detach()) == pytest.approx(float(ref_coarse.detach()), rel=1e-6)
    else:
        assert float(coarse.detach()) == 0.0
    assert -10.0 * torch.log10(mse.double()).item() == pytest.approx(ref_psnr, abs=1e-5)
    assert _rel(fus_pred.grad, ref_pred.grad) <= 1e-6


def test_image_l1_terms_dispatch_is_the_same_either_way(monkeypatch):
    """The losses-level entry point gives the same three numbers fused or not."""
    pred, target, weight = _images(24, 32, seed=3)
    out = {}
    for fused in (True, False):
        monkeypatch.setattr(TM, "FUSED_TERMS", fused)
        p = pred.clone().requires_grad_(True)
        l1, coarse, mse = TM.image_l1_terms(p, target, weight, L.COARSE_POOLS)
        (l1 + coarse).backward()
        out[fused] = (float(l1.detach()), float(coarse.detach()), float(mse), p.grad)
    for a, b in zip(out[True][:3], out[False][:3]):
        assert a == pytest.approx(b, rel=1e-5)
    assert _rel(out[True][3], out[False][3]) <= 1e-5


def _depth_inputs(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    depth_sum = torch.rand(h, w, generator=g) * 3.0 + 0.5
    alpha = torch.rand(h, w, generator=g)  # about half the pixels are valid (alpha > 0.5)
    prior = 2.0 * depth_sum / alpha.clamp_min(1e-6) + 0.3 + 0.2 * torch.randn(h, w, generator=g)
    prior[torch.rand(h, w, generator=g) > 0.9] = 0.0  # no prior there
    return depth_sum, alpha, prior


@pytest.mark.parametrize("h,w", [(36, 48), (35, 47)])  # even and odd valid counts: the lower median
def test_fused_depth_term_matches_torch(h, w):
    depth_sum, alpha, prior = _depth_inputs(h, w)
    ref_in = depth_sum.clone().requires_grad_(True)
    valid = (prior > 0) & (alpha > 0.5)
    ref = L.depth_shift_scale_invariant(ref_in / alpha.clamp_min(1e-6), prior, valid)
    (1.7 * ref).backward()
    fus_in = depth_sum.clone().requires_grad_(True)
    val = fused_depth_term(fus_in, alpha, prior)
    (1.7 * val).backward()
    assert float(ref.detach()) > 1e-3
    assert float(val.detach()) == pytest.approx(float(ref.detach()), rel=1e-5)
    assert _rel(fus_in.grad, ref_in.grad) <= 1e-5


def test_fused_depth_term_without_enough_valid_pixels_is_zero():
    depth_sum, alpha, prior = _depth_inputs(12, 12)
    alpha = torch.zeros_like(alpha)
    alpha[0, :10] = 1.0  # 10 valid pixels < 16
    x = depth_sum.clone().requires_grad_(True)
    val = fused_depth_term(x, alpha, prior)
    val.backward()
    assert float(val.detach()) == 0.0 and (x.grad is None or float(x.grad.abs().sum()) == 0.0)


def test_trainer_terms_are_the_same_fused_or_not(tmp_path, monkeypatch):
    """One training step's photometric, coarse, depth, on-mask and track terms, PSNR and
    Gaussian gradients with the fused image and point terms and with the torch ones."""
    from engine.train.config import preset_config

    from .synthetic_training import make_scene, one_step

    data, truth = make_scene(frames=8, width=48, height=36)
    assert data.depth is not None
    cfg = preset_config("preview", steps=10, gaussians_per_frame=300, init_keyframes=2, num_nodes=25,
                        checkpoint_every=0, warmup_static_steps=0)
    res = {}
    for fused in (True, False):
        monkeypatch.setattr(TM, "FUSED_TERMS", fused)
        tr, metrics = one_step(tmp_path / str(fused), data, truth, cfg)
        res[fused] = (metrics, tr.model.means.grad.clone(), tr.model.opacity_logits.grad.clone())
    (m1, gm1, go1), (m0, gm0, go0) = res[True], res[False]
    for name in ("rgb", "rgb_coarse", "depth", "psnr", "on_mask", "track"):
        assert m0[name] > 0, name
        assert m1[name] == pytest.approx(m0[name], rel=1e-5), name
    assert _rel(gm1, gm0) <= 1e-4 and _rel(go1, go0) <= 1e-4
