"""Training config validation and the loss terms."""

import math

import numpy as np
import pytest
import torch

from engine.errors import InputError
from engine.train import losses as L
from engine.train.config import PRESETS, TrainConfig, preset_config


def test_presets_are_valid_and_round_trip():
    for name in PRESETS:
        cfg = preset_config(name)
        assert cfg.preset == name
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize("data,msg", [
    ({"stepz": 3}, "unknown config key 'stepz'"),
    ({"steps": "many"}, "steps"),
    ({"init": "random"}, "init"),
    ({"motion": "grid"}, "motion"),
    ({"loss": {"rgb": "x"}}, "rgb"),
    ({"loss": {"photo": 1}}, "photo"),
    ({"sh_degree": 7}, "sh_degree"),
    ({"canonical_time": 1.5}, "canonical_time"),
    ({"canonical_time": -0.5}, "canonical_time"),
    ({"motion_init": "still"}, "motion_init"),
    ({"arap_graph": "knn"}, "arap_graph"),
])
def test_bad_config_is_refused_with_the_key(data, msg):
    with pytest.raises(InputError, match=msg):
        TrainConfig.from_dict(data, "cfg.json")


def test_ssim_identity_and_decrease():
    torch.manual_seed(0)
    img = torch.rand(32, 40, 3)
    assert float(L.ssim(img, img)) == pytest.approx(1.0, abs=1e-5)
    noisy = (img + 0.2 * torch.randn_like(img)).clamp(0, 1)
    assert float(L.ssim(img, noisy)) < 0.9


def test_psnr_matches_definition():
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)
    assert float(L.psnr(a, b)) == pytest.approx(20.0, abs=1e-4)
    mask = torch.zeros(8, 8, 1)
    mask[:4] = 1
    b2 = b.clone()
    b2[4:] = 1.0  # errors outside the mask are ignored
    assert float(L.psnr(a, b2, mask)) == pytest.approx(20.0, abs=1e-4)


def test_depth_loss_is_affine_invariant():
    torch.manual_seed(0)
    d = torch.rand(20, 20) + 1.0
    valid = torch.ones(20, 20, dtype=torch.bool)
    assert float(L.depth_shift_scale_invariant(d, 3.0 * d + 0.5, valid)) < 1e-5
    assert float(L.depth_shift_scale_invariant(d, torch.rand(20, 20), valid)) > 1e-2


def test_arap_zero_for_rigid_motion_positive_otherwise():
    torch.manual_seed(0)
    p0 = torch.randn(30, 3)
    ang = 0.7
    R = torch.tensor([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1.0]])
    p1 = p0 @ R.T + torch.tensor([1.0, 2.0, 3.0])
    graph = torch.randint(0, 30, (30, 4))
    rot = R.expand(30, 3, 3)
    assert float(L.arap_loss(p0, p1, rot, graph)) < 1e-10
    assert float(L.arap_loss(p0, p1 * 1.5, rot, graph)) > 1e-3


def test_spline_smoothness_zero_for_linear_motion():
    kt = torch.tensor([0.0, 0.2, 0.5, 1.0])
    keys = (kt[None, :, None] * torch.tensor([1.0, -2.0, 0.5])).expand(5, 4, 3)
    vel, acc = L.spline_smoothness(keys, kt)
    assert float(acc) < 1e-10 and float(vel) > 0


@pytest.mark.parametrize("size", [(48, 64), (7, 5)])
def test_fused_ssim_matches_torch_reference_value_and_gradient(size):
    """engine/train/fused_ssim.py (the CPU training path) against the torch SSIM."""
    torch.manual_seed(0)
    y = torch.rand(*size, 3)
    x = (y + 0.1 * torch.randn_like(y)).clamp(0, 1).requires_grad_(True)
    ref = L.ssim_torch(x, y)
    (g_ref,) = torch.autograd.grad(ref, x)
    out = L.ssim(x, y)
    (g_out,) = torch.autograd.grad(out, x)
    assert float(out) == pytest.approx(float(ref), abs=1e-6)
    assert torch.allclose(g_out, g_ref, atol=1e-7, rtol=1e-4)
    # deterministic: same bits twice
    assert torch.equal(torch.autograd.grad(L.ssim(x, y), x)[0], g_out)


@pytest.mark.parametrize("degree", [0, 1])
def test_fused_sh_colours_match_the_rasteriser_sh(degree):
    """engine/train/fused_sh.py against engine.raster.sh.sh_to_colors (values and gradients)."""
    from engine.raster.sh import sh_to_colors
    from engine.train.fused_sh import fused_sh_colors

    torch.manual_seed(1)
    g, m = 500, (degree + 1) ** 2
    means = (2 * torch.randn(g, 3)).requires_grad_(True)
    dc = torch.randn(g, 1, 3).requires_grad_(True)
    rest = torch.randn(g, m - 1, 3).requires_grad_(True)
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.3, -0.2, 5.0])
    up = torch.randn(g, 3)
    res = []
    for fn in (lambda: sh_to_colors(torch.cat([dc, rest], 1), degree, means, w2c),
               lambda: fused_sh_colors(means, dc, rest, degree, w2c)):
        col = fn()
        grads = torch.autograd.grad((col * up).sum(), (means, dc, rest), allow_unused=True)
        res.append([col] + [torch.zeros(1) if gr is None else gr for gr in grads])
    for a, b in zip(*res):
        if a.numel() == b.numel():
            assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)
        else:  # degree 0: no gradient to the means in torch, zeros in the kernel
            assert float(b.abs().max()) == 0.0


def test_depth_loss_masked_mean_matches_gathered_mean():
    torch.manual_seed(2)
    pred = (torch.rand(30, 40) + 1).requires_grad_(True)
    target = torch.rand(30, 40)
    valid = torch.rand(30, 40) > 0.3
    loss = L.depth_shift_scale_invariant(pred, target, valid)
    p, t = pred[valid], target[valid]
    a = np.stack([t.double().numpy(), np.ones(len(t))], 1)  # float64 least squares (numpy)
    sol = np.linalg.lstsq(a, p.detach().double().numpy(), rcond=None)[0]
    ref = (p - (float(sol[0]) * t + float(sol[1]))).abs().mean() / p.detach().median()
    assert float(loss) == pytest.approx(float(ref), rel=1e-5)
    (g1,) = torch.autograd.grad(loss, pred)
    (g2,) = torch.autograd.grad(ref, pred)
    assert torch.allclose(g1, g2, rtol=1e-5, atol=1e-9)


def test_config_overrides_come_from_a_file_or_the_command_line_itself(tmp_path):
    import argparse
    import json

    from engine.commands._train_options import config_from_args

    path = tmp_path / "over.json"
    path.write_text(json.dumps({"max_gaussians": 12345, "loss": {"on_mask": 0.1}}))
    for given in (str(path), ' {"max_gaussians": 12345, "loss": {"on_mask": 0.1}}'):
        cfg = config_from_args(argparse.Namespace(preset="preview", config=given))
        assert cfg.max_gaussians == 12345 and cfg.loss.on_mask == 0.1
    assert config_from_args(argparse.Namespace(preset="preview", config=None)).max_gaussians != 12345
