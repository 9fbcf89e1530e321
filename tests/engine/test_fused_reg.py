"""Fused node regularisers (engine/train/fused_reg.py) against their torch references."""

from __future__ import annotations

import pytest
import torch

from engine.nodes.graph import node_graph
from engine.train import losses as L
from engine.train.fused_reg import fused_arap, fused_key_terms


def _rel(a, b):
    return ((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30)).item()


def _states(n=60, seed=0):
    g = torch.Generator().manual_seed(seed)
    p0 = torch.randn(n, 3, generator=g)
    p1 = p0 + 0.2 * torch.randn(n, 3, generator=g)
    q0 = torch.randn(n, 4, generator=g)
    q1 = q0 + 0.3 * torch.randn(n, 4, generator=g)
    q1[:5] *= 3.0  # not unit: the normalisation's gradient is exercised
    graph = node_graph(p0, 6)[0]
    return p0, q0, p1, q1, graph


@pytest.mark.parametrize("seed", [0, 1])
def test_fused_arap_matches_torch(seed):
    p0, q0, p1, q1, graph = _states(seed=seed)
    ref_in = [x.double().requires_grad_(True) for x in (p0, q0, p1, q1)]
    ref = L.arap_states(ref_in[0], ref_in[1], ref_in[2], ref_in[3], graph)
    (2.5 * ref).backward()
    fus_in = [x.clone().requires_grad_(True) for x in (p0, q0, p1, q1)]
    val = fused_arap(*fus_in, graph)
    (2.5 * val).backward()
    assert val.dtype == torch.float32 and val.shape == ()
    assert abs(float(val.detach()) - float(ref.detach())) <= 1e-6 * abs(float(ref.detach()))
    assert float(ref.detach()) > 1e-2
    for a, b in zip(fus_in, ref_in):
        assert a.grad.dtype == torch.float32
        assert _rel(a.grad, b.grad) <= 1e-6, _rel(a.grad, b.grad)


def test_fused_arap_is_zero_for_a_rigid_motion():
    p0, q0, _, _, graph = _states(seed=3)
    # every node turned by the same rotation about the origin and shifted: edges rotate rigidly
    r = torch.nn.functional.normalize(torch.tensor([0.9, 0.1, -0.3, 0.2]), dim=0)
    from engine.geometry.quaternion import quat_apply, quat_mul, quat_normalize

    p1 = quat_apply(r.expand(len(p0), 4), p0) + torch.tensor([0.5, -1.0, 2.0])
    q1 = quat_mul(r.expand(len(p0), 4), quat_normalize(q0))
    assert float(fused_arap(p0, q0, p1, q1, graph)) < 1e-10
    assert float(fused_arap(p0, q0, p1 + 0.1 * torch.randn(p1.shape), q1, graph)) > 1e-3


@pytest.mark.parametrize("with_ref", [False, True])
def test_fused_key_terms_match_torch(with_ref):
    g = torch.Generator().manual_seed(4)
    n, k, extent = 40, 9, 3.5
    pk = torch.randn(n, k, 3, generator=g)
    rk = torch.randn(n, k, 4, generator=g)
    rk[0, 2] = 0.0  # a zero quaternion: normalised to the identity, no gradient
    kt = torch.sort(torch.rand(k, generator=g)).values
    kt[3] = kt[2]  # a repeated key time: the 1e-6 clamp of the divided differences
    s = torch.rand(n, generator=g)
    arm = torch.rand(n, generator=g) * 0.3
    ref_p = ref_q = None
    if with_ref:
        ref_p = 0.7 * torch.randn(n, k, 3, generator=g)
        ref_q = 0.7 * torch.nn.functional.normalize(torch.randn(n, k, 4, generator=g), dim=-1)
    wts = (3.0, 1e-3, 1e-2)

    rp, rr = pk.double().requires_grad_(True), rk.double().requires_grad_(True)
    st = L.static_motion_keys(rp, rr, s.double(), arm.double(), extent, None if ref_p is None else ref_p.double(),
                              None if ref_q is None else ref_q.double())
    vel, acc = L.spline_smoothness(rp / extent, kt.double())
    (wts[0] * st + wts[1] * vel + wts[2] * acc).backward()

    fp, fr = pk.clone().requires_grad_(True), rk.clone().requires_grad_(True)
    fst, fvel, facc = fused_key_terms(fp, fr, kt, s, arm, extent, ref_p, ref_q)
    (wts[0] * fst + wts[1] * fvel + wts[2] * facc).backward()
    for a, b in ((fst, st), (fvel, vel), (facc, acc)):
        a, b = a.detach(), b.detach()
        assert float(b) > 0
        assert abs(float(a) - float(b)) <= 1e-6 * float(b), (float(a), float(b))
    assert _rel(fp.grad, rp.grad) <= 1e-6
    assert _rel(fr.grad, rr.grad) <= 1e-6
    assert torch.equal(fr.grad[0, 2], torch.zeros(4))


def test_fused_key_terms_only_the_used_outputs_reach_the_gradient():
    g = torch.Generator().manual_seed(5)
    pk = torch.randn(10, 5, 3, generator=g).requires_grad_(True)
    rk = torch.randn(10, 5, 4, generator=g).requires_grad_(True)
    kt = torch.linspace(0, 1, 5)
    st, vel, acc = fused_key_terms(pk, rk, kt, torch.ones(10), torch.ones(10), 1.0)
    vel.backward()  # velocity only: no rotation gradient, position gradient = the velocity term's
    assert torch.equal(rk.grad, torch.zeros_like(rk))
    ref = pk.detach().clone().requires_grad_(True)
    L.spline_smoothness(ref, kt)[0].backward()
    assert _rel(pk.grad, ref.grad) <= 1e-6
    # two keys: no acceleration; one key: neither
    for kk in (2, 1):
        _, v, a = fused_key_terms(pk[:, :kk].detach(), rk[:, :kk].detach(), kt[:kk], torch.ones(10), torch.ones(10),
                                  1.0)
        assert float(a) == 0.0 and (float(v) > 0) == (kk == 2)


@pytest.mark.parametrize("static_init", [0.0, 1.0])
def test_trainer_terms_are_the_same_fused_or_not(tmp_path, monkeypatch, static_init):
    """One training step's loss terms and node-key gradients with the fused node terms
    and with the torch ones (ARAP, static, velocity, acceleration all live)."""
    from engine.train import objective as O
    from engine.train import trainer as T
    from engine.train.config import preset_config

    from .synthetic_training import make_nodes, make_scene

    data, truth = make_scene(frames=8, width=48, height=36)
    cfg = preset_config("preview", steps=10, gaussians_per_frame=300, init_keyframes=2, num_nodes=25,
                        checkpoint_every=0, warmup_static_steps=0, loss={"static": 1.0, "static_init": static_init})
    res = {}
    for fused in (True, False):
        monkeypatch.setattr(O, "FUSED_REG", fused)
        tr = T.Trainer(data, make_nodes(truth), cfg, tmp_path / str(fused))
        with torch.no_grad():
            tr.model.pos_keys.add_(0.02 * torch.randn(tr.model.pos_keys.shape, generator=torch.Generator().manual_seed(0)))
        tr.step = 5
        loss, metrics, _, _ = tr._loss(int(data.train_idx[1]))
        loss.backward()
        res[fused] = (metrics, tr.model.pos_keys.grad.clone(), tr.model.rot_keys.grad.clone())
    (m1, gp1, gq1), (m0, gp0, gq0) = res[True], res[False]
    for name in ("arap", "static", "velocity", "acceleration"):
        assert m0[name] > 0, name
        assert m1[name] == pytest.approx(m0[name], rel=1e-5, abs=1e-12), name
    assert _rel(gp1, gp0) <= 1e-4 and _rel(gq1, gq0) <= 1e-4


def test_static_term_is_a_mean_over_nodes_like_arap_and_smoothness():
    """The same nodes twice (2N) must cost what they cost once (N): the static-motion term is a
    mean over nodes, so its strength does not grow 4x from 512 to 2048 nodes (#19). The torch
    reference, the fused kernel and the smoothness terms agree on that."""
    g = torch.Generator().manual_seed(6)
    n, k = 30, 7
    pk, rk = torch.randn(n, k, 3, generator=g), torch.randn(n, k, 4, generator=g)
    kt = torch.linspace(0, 1, k)
    s, arm = torch.rand(n, generator=g), torch.rand(n, generator=g)
    twice = [torch.cat([x, x]) for x in (pk, rk)]
    s2, arm2 = torch.cat([s, s]), torch.cat([arm, arm])
    one = L.static_motion_keys(pk.double(), rk.double(), s.double(), arm.double(), 2.0)
    two = L.static_motion_keys(twice[0].double(), twice[1].double(), s2.double(), arm2.double(), 2.0)
    assert float(one) > 0 and abs(float(two) - float(one)) <= 1e-12 * float(one)
    f_one, v_one, _ = fused_key_terms(pk, rk, kt, s, arm, 2.0)
    f_two, v_two, _ = fused_key_terms(*twice, kt, s2, arm2, 2.0)
    assert abs(float(f_two) - float(f_one)) <= 1e-6 * float(f_one)
    assert abs(float(v_two) - float(v_one)) <= 1e-6 * float(v_one)  # the smoothness terms already were means
    # the per-node weight: one node's cost is the torch mean's 1/N share
    single = L.static_motion_keys(pk[:1].double(), rk[:1].double(), s[:1].double(), arm[:1].double(), 2.0)
    e = torch.stack([L.static_motion_keys(pk[i:i + 1].double(), rk[i:i + 1].double(), s[i:i + 1].double(),
                                          arm[i:i + 1].double(), 2.0) for i in range(n)])
    assert float(single) == pytest.approx(float(e[0])) and float(one) == pytest.approx(float(e.mean()))
