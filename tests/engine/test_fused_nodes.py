"""Fused node state (engine/train/fused_nodes.py) against the torch spline and transforms."""

from __future__ import annotations

import pytest
import torch

from engine.geometry.dualquat import node_transforms_dq
from engine.train import model as M
from engine.train.fused_nodes import fused_node_state


def _rel(a, b):
    return ((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30)).item()


def _keys(n=40, k=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    centers = torch.randn(n, 3, generator=g)
    pos = centers[:, None] + 0.3 * torch.randn(n, k, 3, generator=g)
    rot = torch.randn(n, k, 4, generator=g)  # not unit: both normalisations are exercised
    return centers, pos, rot


@pytest.mark.parametrize("t", [0.0, 0.37, 0.93, 1.0])
def test_fused_node_state_matches_torch(t):
    """Positions, rotations and dual quaternions and the key gradients of a loss on all
    three, against the Catmull-Rom basis sum + quat_normalize + node_transforms_dq."""
    centers, pos, rot = _keys()
    times = torch.linspace(0, 1, pos.shape[1])
    model = M.DynamicScene.__new__(M.DynamicScene)  # only spline_basis's inputs are needed
    torch.nn.Module.__init__(model)
    model.key_times, model.pos_keys = times, pos
    lo, hi, b = M.DynamicScene.spline_basis(model, t)
    g = torch.Generator().manual_seed(7)
    wp, wr, wd = torch.randn(pos.shape[0], 3, generator=g), torch.randn(pos.shape[0], 4, generator=g), \
        torch.randn(pos.shape[0], 8, generator=g)

    ref_p, ref_r = pos.double().requires_grad_(True), rot.double().requires_grad_(True)
    bb = b.double()[None, :, None]
    p_ref = (ref_p[:, lo:hi] * bb).sum(1)
    from engine.geometry.quaternion import quat_normalize

    r_ref = quat_normalize((ref_r[:, lo:hi] * bb).sum(1))
    dq_ref = node_transforms_dq(centers.double(), p_ref, r_ref)
    ((p_ref * wp).sum() + (r_ref * wr).sum() + (dq_ref * wd).sum()).backward()

    fp, fr = pos.clone().requires_grad_(True), rot.clone().requires_grad_(True)
    p, r, dq = fused_node_state(fp, fr, lo, b, centers)
    ((p * wp).sum() + (r * wr).sum() + (dq * wd).sum()).backward()
    for a, ref in ((p, p_ref), (r, r_ref), (dq, dq_ref)):
        assert a.dtype == torch.float32
        assert _rel(a.detach(), ref.detach()) <= 1e-6
    assert _rel(fp.grad, ref_p.grad) <= 1e-6 and _rel(fr.grad, ref_r.grad) <= 1e-6
    # keys outside the segment get exactly nothing
    outside = torch.ones(pos.shape[1], dtype=torch.bool)
    outside[lo:hi] = False
    assert float(fp.grad[:, outside].abs().sum()) == 0.0 and float(fr.grad[:, outside].abs().sum()) == 0.0


def test_trainer_step_is_the_same_fused_or_not(tmp_path, monkeypatch):
    """One training step's loss terms and key gradients with the fused node state and with
    the torch ops."""
    from engine.train.config import preset_config

    from .synthetic_training import make_scene, one_step

    data, truth = make_scene(frames=8, width=48, height=36)
    cfg = preset_config("preview", steps=10, gaussians_per_frame=300, init_keyframes=2, num_nodes=25,
                        checkpoint_every=0, warmup_static_steps=0)
    res = {}
    for fused in (True, False):
        monkeypatch.setattr(M, "FUSED_NODES", fused)
        tr, metrics = one_step(tmp_path / str(fused), data, truth, cfg, jitter_keys=0.02)
        res[fused] = (metrics, tr.model.pos_keys.grad.clone(), tr.model.rot_keys.grad.clone())
    (m1, gp1, gq1), (m0, gp0, gq0) = res[True], res[False]
    for name in ("rgb", "arap", "track"):
        assert m0[name] > 0, name
        assert m1[name] == pytest.approx(m0[name], rel=1e-5), name
    assert float(gp0.abs().sum()) > 0
    assert _rel(gp1, gp0) <= 1e-5 and _rel(gq1, gq0) <= 1e-5


def test_quaternion_thresholds_agree():
    """fused_nodes keeps its own copy of quat_normalize's threshold (a cached Numba kernel
    must not read another file's globals: the cache would not notice an edit there)."""
    import inspect

    from engine.geometry.quaternion import quat_normalize
    from engine.train import fused_nodes, fused_reg

    eps = inspect.signature(quat_normalize).parameters["eps"].default
    assert fused_nodes.EPS == fused_reg.EPS == eps
