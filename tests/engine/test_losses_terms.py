"""Direct tests of the track, mask and coarse photometric terms, and of the training step's
gradient flow: every trainable parameter of the model gets a gradient in one step, or is not
trainable (#19: the RBF radius was an optimised parameter that never received one)."""

from __future__ import annotations

import math

import pytest
import torch

from engine.train import losses as L
from engine.train.config import preset_config
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene


# ---------------------------------------------------------------------- coarse_l1
def _textured_object(offset: int, size: int = 64, obj: int = 16) -> torch.Tensor:
    """A square of pixel-scale orange texture on a pixel-scale grey one, ``offset`` px right of centre."""
    g = torch.Generator().manual_seed(0)
    img = 0.3 + 0.2 * (torch.rand(size, size, 3, generator=g) - 0.5)
    texture = torch.tensor([0.8, 0.6, 0.2]) + 0.4 * (torch.rand(obj, obj, 3, generator=g) - 0.5)
    y0, x0 = (size - obj) // 2, (size - obj) // 2 + offset
    img[y0:y0 + obj, x0:x0 + obj] = texture
    return img


def test_coarse_l1_is_the_mean_l1_of_the_pooled_images():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(20, 30, 3, generator=g), torch.rand(20, 30, 3, generator=g)
    assert float(L.coarse_l1(a, a)) == 0.0
    pa = lambda x, k: torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], k, ceil_mode=True)  # noqa: E731
    want = sum(float((pa(a, k) - pa(b, k)).abs().mean()) for k in L.COARSE_POOLS) / len(L.COARSE_POOLS)
    assert math.isclose(float(L.coarse_l1(a, b)), want, rel_tol=1e-5)
    # a weight of ones is the unweighted mean; a weight on one half only sees that half
    assert math.isclose(float(L.coarse_l1(a, b, torch.ones(20, 30, 1))), want, rel_tol=1e-5)
    left = torch.zeros(20, 30, 1)
    left[:, :16] = 1.0
    b2 = b.clone()
    b2[:, :16] = a[:, :16]
    assert float(L.coarse_l1(a, b2, left)) == pytest.approx(0.0, abs=1e-7)


def test_coarse_l1_keeps_telling_how_far_an_offset_textured_object_is():
    """The mechanism the term is for: at full resolution an object offset by 1 px already pays
    the texture-mismatch floor, so the cost says little about how far it is (6 px costs ~2x
    1 px); downsampled, the texture averages out and the cost grows with the offset (~5x)."""
    target = _textured_object(0)
    full = [float(L.l1(_textured_object(d), target)) for d in range(7)]
    coarse = [float(L.coarse_l1(_textured_object(d), target)) for d in range(7)]
    assert full[0] == coarse[0] == 0.0
    assert all(b > a for a, b in zip(coarse[:-1], coarse[1:]))  # grows with every pixel of offset
    assert coarse[6] / coarse[1] > 4.0
    assert full[6] / full[1] < 2.5


# ---------------------------------------------------------------------- track_loss
def test_track_loss_is_zero_on_the_tracks_and_huber_beyond():
    target = torch.tensor([[10.0, 20.0], [30.0, 5.0]])
    vis = torch.tensor([True, True])
    assert float(L.track_loss(target.clone(), target, vis, 100.0)) == 0.0
    # 1 px off in x on one point at scale 100: d = 0.01 < delta 0.05 -> 0.5 d^2, mean over 4 numbers
    off = target.clone()
    off[0, 0] += 1.0
    assert float(L.track_loss(off, target, vis, 100.0)) == pytest.approx(0.5 * 0.01 ** 2 / 4, rel=1e-5)
    # 50 px off at scale 10: d = 5 > delta -> linear, delta (|d| - delta / 2)
    far = target.clone()
    far[1, 1] += 50.0
    assert float(L.track_loss(far, target, vis, 10.0)) == pytest.approx(0.05 * (5.0 - 0.025) / 4, rel=1e-5)


def test_track_loss_ignores_invisible_points_and_is_resolution_free():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(50, 2, generator=g) * 100
    proj = (target + torch.randn(50, 2, generator=g)).requires_grad_(True)
    vis = torch.rand(50, generator=g) > 0.3
    loss = L.track_loss(proj, target, vis, 64.0)
    base = loss.detach()
    wild = proj.detach().clone()
    wild[~vis] += 1e4  # what invisible points do cannot matter
    assert float(L.track_loss(wild, target, vis, 64.0)) == pytest.approx(float(base), rel=1e-6)
    loss.backward()
    assert torch.count_nonzero(proj.grad[~vis]) == 0 and torch.count_nonzero(proj.grad[vis]) > 0
    # twice the resolution, twice the scale: the same loss
    assert float(L.track_loss(2 * proj.detach(), 2 * target, vis, 128.0)) == pytest.approx(float(base), rel=1e-5)
    # nothing visible: 0, still connected to the graph (backward runs, zero gradient)
    none = torch.zeros(50, dtype=torch.bool)
    p = proj.detach().clone().requires_grad_(True)
    z = L.track_loss(p, target, none, 64.0)
    z.backward()
    assert float(z.detach()) == 0.0 and torch.count_nonzero(p.grad) == 0


# ---------------------------------------------------------------------- mask_loss
def test_mask_loss_is_the_binary_cross_entropy_to_the_prior():
    prior = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    alpha = torch.ones(2, 2, 1)
    half = torch.full((2, 2, 1), 0.5)
    assert float(L.mask_loss(alpha, half, prior)) == pytest.approx(math.log(2), rel=1e-6)
    right = prior[..., None].clone()
    wrong = 1 - right
    assert float(L.mask_loss(alpha, right, prior)) < 1e-3
    # a confidently wrong mask costs -ln(1e-4) per pixel (clamped, never inf)
    assert float(L.mask_loss(alpha, wrong, prior)) == pytest.approx(-math.log(1e-4), rel=1e-3)


def test_mask_loss_pulls_the_dynamic_render_toward_the_prior():
    prior = torch.tensor([[1.0, 0.0, 0.7]])
    dyn = torch.full((1, 3, 1), 0.4, requires_grad=True)
    L.mask_loss(torch.ones(1, 3, 1), dyn, prior).backward()
    g = dyn.grad[..., 0]
    # descent raises it where the prior says moving, lowers it where static, and moves it
    # toward a soft prior value
    assert g[0, 0] < 0 and g[0, 1] > 0 and g[0, 2] < 0
    # the total alpha does not enter (the term is on the dynamic channel only)
    a = torch.rand(1, 3, 1, requires_grad=True)
    L.mask_loss(a, dyn, prior).backward()
    assert a.grad is None


# ---------------------------------------------------------------------- on_mask_loss
def test_mask_distance_is_zero_on_moving_pixels_and_the_distance_elsewhere():
    fg = torch.zeros(2, 12, 20)
    fg[0, 5, 7] = 0.9  # one moving pixel in frame 0; frame 1 has none
    fg[0, 9, 2] = 0.4  # below the threshold: not moving
    dist = L.mask_distance(fg, 0.5)
    assert dist.shape == fg.shape and dist.dtype == torch.float32
    assert float(dist[0, 5, 7]) == 0.0
    assert float(dist[0, 5, 10]) == pytest.approx(3.0, abs=0.05)
    assert float(dist[0, 9, 2]) == pytest.approx(math.hypot(4, 5), rel=0.03)
    assert torch.count_nonzero(dist[1]) == 0  # nothing moving: no pull anywhere


def test_on_mask_loss_pulls_points_onto_the_moving_region():
    fg = torch.zeros(1, 40, 60)
    fg[0, 15:25, 30:40] = 1.0
    dist = L.mask_distance(fg, 0.5)[0]
    uv = torch.tensor([[35.0, 20.0],    # inside: free
                       [14.5, 20.5],    # the centre of pixel (20, 14): 16 px left of the region's pixel centres
                       [-5.0, 20.0]],   # off the image: not scored
                      requires_grad=True)
    loss = L.on_mask_loss(uv, dist, 60 / 100.0)
    loss.backward()
    g = uv.grad
    assert torch.count_nonzero(g[0]) == 0 and torch.count_nonzero(g[2]) == 0
    assert g[1, 0] < 0 and abs(float(g[1, 1])) < 1e-6 * abs(float(g[1, 0]))  # descent moves it right, only
    # linear beyond the Huber knee: the far point costs delta (d - delta / 2), averaged over all 3 points
    d = 16.0 / 0.6
    assert float(loss.detach()) == pytest.approx(0.05 * (d - 0.025) / 3, rel=1e-3)
    # gradient descent brings a point from 25 px away onto the region
    p = torch.tensor([[5.0, 2.0]], requires_grad=True)
    opt = torch.optim.SGD([p], lr=2.0)
    for _ in range(200):
        opt.zero_grad()
        L.on_mask_loss(p, dist, 0.6).backward()
        opt.step()
    assert float(dist[int(p[0, 1]), int(p[0, 0])]) <= 1.0


# ---------------------------------------------------------------------- gradient flow
@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=8, width=48, height=36)


@pytest.mark.parametrize("motion,split", [("spline", False), ("spline", True), ("mlp", False)])
def test_every_trainable_parameter_gets_a_gradient_in_a_step(tmp_path, scene, motion, split):
    """One training step with every term on (mask step included): each parameter the
    optimiser updates has a non-zero gradient, and every ``requires_grad`` parameter of the
    model is in the optimiser. The RBF radius is a buffer, not a parameter."""
    data, truth = scene
    cfg = preset_config("preview", steps=10, gaussians_per_frame=200, init_keyframes=2, num_nodes=25,
                        densify_until=0, checkpoint_every=0, warmup_static_steps=0, motion=motion, split=split,
                        loss={"mask": 0.1, "track": 0.05, "depth": 0.05, "arap": 1.0, "static": 1.0,
                              "velocity": 1e-3, "acceleration": 1e-2})
    trainer = Trainer(data, make_nodes(truth), cfg, tmp_path / "run")
    m = trainer.model
    with torch.no_grad():  # initial Gaussians are round, whose rotation gradient is exactly 0
        m.log_scales.add_(0.3 * torch.randn(m.log_scales.shape, generator=torch.Generator().manual_seed(1)))
    f = int(data.train_idx[0])
    trainer.step = 4  # a mask step (every 4th), past the warm-up
    loss, metrics, _, _ = trainer._loss(f)
    assert {"rgb", "mask", "depth", "arap", "static"} <= set(metrics)
    assert ("on_mask" in metrics) == split  # the dynamic Gaussians exist with the split only
    if motion != "mlp":
        assert "track" in metrics and "velocity" in metrics
    trainer.opt.zero_grad(set_to_none=True)
    loss.backward()
    in_opt = {id(p): g["name"] for g in trainer.opt.param_groups for p in g["params"]}
    for name, p in m.named_parameters():
        if p.requires_grad:
            assert id(p) in in_opt, f"{name} is trainable but not optimised"
    for group in trainer.opt.param_groups:
        if group["name"] == "lifespan_log_scale" and not bool((m.gauss_lifespan > 0).any()):
            # lifespans off (this camera translates): the window is skipped, nothing to learn
            # (with lifespans: tests/engine/test_lifespan.py)
            assert all(p.grad is None for p in group["params"])
            continue
        for p in group["params"]:
            assert p.grad is not None, f"{group['name']} gets no gradient"
        # (the MLP's zero-initialised head leaves its trunk a zero first gradient: per group)
        assert any(torch.count_nonzero(p.grad) > 0 for p in group["params"]), f"{group['name']}: zero gradient"
    assert "node_log_radii" not in dict(m.named_parameters())
    assert "node_log_radii" in dict(m.named_buffers())


def test_a_checkpoint_optimiser_with_the_old_radius_group_still_loads():
    """Checkpoints from before the radius became a buffer have an Adam group for it; resume
    drops that group (and its moments) and loads the rest unchanged."""
    from engine.train.checkpoint import without_groups

    a, r, b = (torch.nn.Parameter(torch.randn(3)) for _ in range(3))
    old = torch.optim.Adam([{"name": "means", "params": [a]}, {"name": "node_log_radii", "params": [r]},
                            {"name": "pos_keys", "params": [b]}])
    (a.sum() + b.sum()).backward()
    old.step()
    state = old.state_dict()
    new = torch.optim.Adam([{"name": "means", "params": [a]}, {"name": "pos_keys", "params": [b]}])
    with pytest.raises(ValueError):
        new.load_state_dict(state)
    new.load_state_dict(without_groups(state, ("node_log_radii",)))
    assert torch.equal(new.state[b]["exp_avg"], old.state[b]["exp_avg"])
    assert [g["name"] for g in new.param_groups] == ["means", "pos_keys"]
