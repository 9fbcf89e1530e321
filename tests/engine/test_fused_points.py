"""Fused on-mask term (engine/train/fused_points.py) against project + on_mask_loss."""

from __future__ import annotations

import pytest
import torch

from engine.geometry.camera import project
from engine.train import losses as L
from engine.train import terms as TM
from engine.train.fused_points import fused_on_mask


def _setup(seed=0, p=600, h=30, w=40):
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[35.0, 0.3, 20.5], [0.0, 33.0, 14.5], [0.0, 0.0, 1.0]])
    ang = 0.2
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[1.0, 0.0, 0.0], [0.0, torch.cos(torch.tensor(ang)), -torch.sin(torch.tensor(ang))],
                                [0.0, torch.sin(torch.tensor(ang)), torch.cos(torch.tensor(ang))]])
    w2c[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    # points spread so that some land outside the image and some behind the camera
    pts = torch.randn(p, 3, generator=g) * torch.tensor([0.9, 0.7, 1.5]) + torch.tensor([0.0, 0.0, 2.0])
    fg = torch.zeros(1, h, w)
    fg[0, 8:18, 12:25] = 1.0
    dist = L.mask_distance(fg, 0.5)[0]
    return pts, K, w2c, dist


def _reference(pts, K, w2c, dist, scale):
    uv, z = project(K, w2c, pts)
    uv = torch.where((z > 0).unsqueeze(-1), uv, uv.new_tensor(-1.0))
    return L.on_mask_loss(uv, dist, scale)


@pytest.mark.parametrize("seed,scale", [(0, 0.4), (1, 3.0)])  # mostly quadratic / mostly linear Huber
def test_fused_on_mask_matches_torch(seed, scale):
    pts, K, w2c, dist = _setup(seed)
    uv, z = project(K, w2c, pts)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < dist.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < dist.shape[0])
    assert 50 < int(inside.sum()) < len(pts) - 50 and int((z <= 0).sum()) > 0
    ref_in = pts.double().requires_grad_(True)
    ref = _reference(ref_in, K.double(), w2c.double(), dist.double(), scale)
    (2.0 * ref).backward()
    fus_in = pts.clone().requires_grad_(True)
    val = fused_on_mask(fus_in, K, w2c, dist, scale)
    (2.0 * val).backward()
    assert float(ref.detach()) > 1e-3
    assert float(val.detach()) == pytest.approx(float(ref.detach()), rel=1e-5)
    rel = float((fus_in.grad.double() - ref_in.grad).norm() / ref_in.grad.norm())
    assert rel <= 1e-4
    assert float(fus_in.grad[~inside].abs().sum()) == 0.0


def test_on_mask_term_dispatch_is_the_same_either_way(monkeypatch):
    pts, K, w2c, dist = _setup(2)
    out = {}
    for fused in (True, False):
        monkeypatch.setattr(TM, "FUSED_TERMS", fused)
        x = pts.clone().requires_grad_(True)
        v = TM.on_mask_term(x, K, w2c, dist, 0.4)
        v.backward()
        out[fused] = (float(v.detach()), x.grad)
    assert out[True][0] == pytest.approx(out[False][0], rel=1e-5)
    assert float((out[True][1] - out[False][1]).norm() / out[False][1].norm()) <= 1e-4


def test_no_point_in_view_gives_zero():
    pts, K, w2c, dist = _setup(3)
    x = (pts * 0.0 + torch.tensor([0.0, 0.0, -5.0])).requires_grad_(True)  # all behind the camera
    v = fused_on_mask(x, K, w2c, dist, 0.4)
    v.backward()
    assert float(v.detach()) == 0.0 and float(x.grad.abs().sum()) == 0.0


@pytest.mark.parametrize("scale", [0.4, 40.0])  # mostly linear / mostly quadratic Huber
def test_fused_track_matches_torch(scale):
    from engine.train.fused_points import fused_track

    pts, K, w2c, _ = _setup(4, p=300)
    pts = pts[project(K, w2c, pts)[1] > 0.05]  # the track term scores points in front
    g = torch.Generator().manual_seed(9)
    target = project(K, w2c, pts)[0] + 3.0 * torch.randn(len(pts), 2, generator=g)
    ref_in = pts.double().requires_grad_(True)
    uv, _ = project(K.double(), w2c.double(), ref_in)
    ref = L.track_loss(uv, target.double(), torch.ones(len(pts), dtype=torch.bool), scale)
    (1.5 * ref).backward()
    fus_in = pts.clone().requires_grad_(True)
    val = fused_track(fus_in, K, w2c, target, scale)
    (1.5 * val).backward()
    assert float(ref.detach()) > 1e-4
    assert float(val.detach()) == pytest.approx(float(ref.detach()), rel=1e-5)
    assert float((fus_in.grad.double() - ref_in.grad).norm() / ref_in.grad.norm()) <= 1e-4
