"""View-bound Gaussians (engine/train/shot_detail.py): the parallax fade, its render, the bundle."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from engine import bundle as B
from engine.errors import InputError
from engine.geometry.camera import camera_centers, intrinsics, look_at, ray_parallax_sin
from engine.train.shot_detail import view_fade


def test_ray_parallax_sin_is_the_sine_of_the_angle_between_the_rays():
    points = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    origins = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 2.0, 1.0]])
    # 45 degrees; the same line seen from further back (0); a right angle
    center = torch.tensor([1.0, 0.0, -1.0])
    got = ray_parallax_sin(points[:1], origins[:1], center)
    assert got.item() == pytest.approx(math.sin(math.pi / 4), abs=1e-6)
    assert ray_parallax_sin(points[1:2], origins[1:2], torch.tensor([0.0, 0.0, -5.0])).item() == pytest.approx(0.0, abs=1e-7)
    assert ray_parallax_sin(points[2:], origins[2:], torch.tensor([3.0, 2.0, 3.0])).item() == pytest.approx(1.0, abs=1e-6)


def test_view_fade_is_one_from_the_own_camera_and_falls_with_the_parallax():
    origin = torch.tensor([0.0, 0.0, -5.0])
    means = torch.zeros(4, 3)
    origins = origin.expand(4, 3)
    angle = torch.tensor([0.05, 0.05, 0.05, 0.0])  # the last is not view-bound
    own = view_fade(means, origins, angle, origin)
    assert torch.equal(own, torch.ones(4))
    # a camera 0.25 to the side at depth 5: sin(a) ~ 0.05, one angle scale: exp(-0.5)
    side = torch.tensor([0.25, 0.0, -5.0])
    s = ray_parallax_sin(means[:1], origins[:1], side).item()
    got = view_fade(means, origins, angle, side)
    assert got[0].item() == pytest.approx(math.exp(-0.5 * (s / 0.05) ** 2), rel=1e-5)
    assert got[3].item() == 1.0  # angle 0: seen alike from everywhere, exactly
    far = view_fade(means, origins, angle, torch.tensor([2.0, 0.0, -5.0]))
    assert far[0].item() < 1e-6 < got[0].item() < 1.0


def _one_gaussian_scene(view_angle: float):
    """A model with one Gaussian at the origin, seen from a camera at (0, -4, 0) that is also its
    seed camera (view-bound with ``view_angle``; 0 = not)."""
    from engine.train.model import DynamicScene

    m = DynamicScene(torch.zeros(1, 3), torch.tensor([[0.9, 0.2, 0.1]]), torch.full((1, 3), 0.3),
                     torch.tensor([0.9]), torch.zeros(1, 3), torch.ones(1), torch.tensor([0.0, 1.0]),
                     torch.zeros(1, 2, 3), sh_degree=0)
    own = look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3)).float()
    m.gauss_view_origin = camera_centers(own)[None].clone()
    m.gauss_view_angle = torch.tensor([view_angle])
    return m, own


@pytest.mark.parametrize("view_angle", [0.0, 0.02])
def test_a_view_bound_gaussian_renders_from_its_camera_and_fades_from_another(view_angle):
    from engine.train.render import render_scene

    m, own = _one_gaussian_scene(view_angle)
    other = look_at(torch.tensor([2.0, -3.5, 0.0]), torch.zeros(3)).float()  # ~30 degrees away
    K = intrinsics(40.0, 40.0, 16.0, 12.0, dtype=torch.float32)
    peak = {}
    for name, w2c in (("own", own), ("other", other)):
        with torch.no_grad():
            means, quats = m.deform(0.5)
            out = render_scene(m, means, quats, K, w2c, 32, 24, time=0.5)
        peak[name] = float(out.alpha.max())
    assert peak["own"] > 0.8
    if view_angle > 0:
        assert peak["other"] < 1e-3
    else:
        assert peak["other"] > 0.8


def _nodes_with_view(g=50, **extra):
    rng = np.random.default_rng(0)
    n, k = 7, 5
    q = rng.normal(size=(n, k, 4))
    return B.NodeArrays(centers=rng.normal(size=(n, 3)), radii=rng.uniform(0.1, 1, n), key_times=np.linspace(0, 1, k),
                        pos_keys=rng.normal(size=(n, k, 3)), pos_tangents=rng.normal(size=(n, k, 3)),
                        rot_keys=q / np.linalg.norm(q, axis=-1, keepdims=True), rot_tangents=rng.normal(size=(n, k, 4)),
                        bind_idx=rng.integers(0, n, size=(g, 4)), bind_w=np.full((g, 4), 0.25), **extra)


def test_view_binding_round_trips_through_the_bundle_and_into_the_model(tmp_path):
    from engine.train.from_bundle import model_from_bundle

    g = 50
    origin = np.random.default_rng(1).normal(size=(g, 3)).astype(np.float32)
    angle = np.where(np.arange(g) % 2 == 0, 0.0, 0.04).astype(np.float32)
    nodes = _nodes_with_view(g, gauss_view_origin=origin, gauss_view_angle=angle)
    rng = np.random.default_rng(2)
    gs = B.GaussianArrays(means=rng.normal(size=(g, 3)), quats=rng.normal(size=(g, 4)),
                          log_scales=rng.normal(size=(g, 3)) - 3, opacity_logits=rng.normal(size=g),
                          sh=rng.normal(size=(g, 4, 3)))
    B.save_bundle(tmp_path / "b", B.new_scene(1, 10, 24.0, cameras=[]), nodes, gs)
    b = B.load_bundle(tmp_path / "b")
    np.testing.assert_array_equal(b.nodes.gauss_view_origin, origin)
    np.testing.assert_array_equal(b.nodes.gauss_view_angle, angle)
    m = model_from_bundle(b)
    np.testing.assert_array_equal(m.gauss_view_angle.numpy(), angle)
    np.testing.assert_array_equal(m.gauss_view_origin.numpy(), origin)


@pytest.mark.parametrize("extra,msg", [
    ({"gauss_view_angle": np.zeros(50, np.float32)}, "come together"),
    ({"gauss_view_origin": np.zeros((50, 3), np.float32), "gauss_view_angle": np.zeros(49, np.float32)}, "shape"),
    ({"gauss_view_origin": np.zeros((50, 2), np.float32), "gauss_view_angle": np.zeros(50, np.float32)}, "shape"),
    ({"gauss_view_origin": np.zeros((50, 3), np.float32), "gauss_view_angle": -np.ones(50, np.float32)}, ">= 0"),
    ({"gauss_view_origin": np.full((50, 3), np.inf, np.float32), "gauss_view_angle": np.zeros(50, np.float32)},
     "finite"),
])
def test_bad_view_binding_names_the_node_file(tmp_path, extra, msg):
    arrays = _nodes_with_view().to_dict()
    arrays.update(extra)
    np.savez(tmp_path / "nodes.npz", **arrays)
    with pytest.raises(InputError, match=msg) as err:
        B.read_nodes(tmp_path / "nodes.npz")
    assert "nodes.npz" in str(err.value)


def test_a_long_clip_gets_fewer_detail_seeds_a_frame_within_the_total():
    from engine.train.config import preset_config
    from engine.train.shot_detail import seeds_per_frame

    cfg = preset_config("preview")
    assert seeds_per_frame(cfg, 60) == cfg.detail_seeds  # a preview clip: every moving pixel
    assert seeds_per_frame(cfg, 300) * 300 <= cfg.detail_seed_max < (seeds_per_frame(cfg, 300) + 1) * 300
    assert seeds_per_frame(preset_config("preview", detail_seed_max=10), 60) == 1  # never none
