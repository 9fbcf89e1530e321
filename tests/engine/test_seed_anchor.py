"""Moving Gaussians held at their seed frame while the node keys train (engine/train/seed_anchor.py)."""
from __future__ import annotations

import dataclasses

import torch

from engine.train.config import preset_config
from engine.train.init_model import build_model
from engine.train.seed_anchor import (anchor_to_seed_time_, anchored_rows, deform_seed_relative, seed_poses,
                                      seed_poses_kept)

from .synthetic_training import make_nodes, make_scene


def _cfg(**kw):
    return preset_config("preview", gaussians_per_frame=800, init_keyframes=4, num_nodes=25,
                         dynamic_gaussians=600, **kw)


def _model():
    data, truth = make_scene(fixed_camera=True)
    model = build_model(data, make_nodes(truth), _cfg(), torch.Generator().manual_seed(0))
    return data, truth, model


def _jitter_keys_(model, gen, size=0.05):
    """Move the moving nodes' keys at random (what training steps do)."""
    dyn = model.node_dyn[:, None, None].to(model.pos_keys.dtype)
    with torch.no_grad():
        model.pos_keys.add_(torch.randn(model.pos_keys.shape, generator=gen) * size * dyn)
        model.rot_keys.add_(torch.randn(model.rot_keys.shape, generator=gen) * size * dyn)


def test_relative_deform_has_deform_values_and_no_key_gradient_at_the_seed_frame():
    data, _, model = _model()
    _jitter_keys_(model, torch.Generator().manual_seed(1))  # keys that are not a plain translation
    rows = anchored_rows(model)
    t_own = float(model.gauss_t_center[rows[0]])
    own = rows[model.gauss_t_center[rows] == t_own]
    everything = torch.arange(model.num_gaussians)
    for t in (t_own, t_own + 0.1):
        ref = model.deform(t, index=everything)
        got = deform_seed_relative(model, t, model.node_dq(t), everything)
        torch.testing.assert_close(got[0], ref[0], atol=2e-6, rtol=0)
        torch.testing.assert_close(got[1], ref[1], atol=2e-6, rtol=0)
    weights = torch.randn(len(own), 3, generator=torch.Generator().manual_seed(2))

    def key_grad(t, relative):
        model.zero_grad(set_to_none=True)
        x = (deform_seed_relative(model, t, model.node_dq(t), own) if relative else model.deform(t, index=own))[0]
        (x * weights).sum().backward()
        return model.pos_keys.grad.abs().max().item(), model.means.grad[own].clone()

    plain, means_plain = key_grad(t_own, relative=False)
    held, means_held = key_grad(t_own, relative=True)
    assert plain > 0.1 and held < 1e-4 * plain  # at its own frame the keys get no pull from it
    torch.testing.assert_close(means_held, means_plain)  # its centre learns as before
    assert key_grad(t_own + 0.1, relative=True)[0] > 0.01 * plain  # elsewhere its motion teaches the keys


def test_anchoring_keeps_each_gaussian_where_it_was_at_its_seed_frame():
    _, _, model = _model()
    rows = anchored_rows(model)
    assert len(rows) > 100 and len(torch.unique(model.gauss_t_center[rows])) > 5
    x0, q0 = seed_poses(model, rows)
    still = torch.nonzero(model.gauss_lifespan == 0).squeeze(1)
    still_means = model.means[still].detach().clone()
    keys = (model.pos_keys.detach().clone(), model.rot_keys.detach().clone())
    _jitter_keys_(model, torch.Generator().manual_seed(3))
    moved = (seed_poses(model, rows)[0] - x0).norm(dim=1)
    assert float(moved.median()) > 0.01  # the keys' change moves them at their own frames ...
    anchor_to_seed_time_(model, *keys)
    x1, q1 = seed_poses(model, rows)
    torch.testing.assert_close(x1, x0, atol=1e-5, rtol=0)  # ... and the anchor puts them back
    torch.testing.assert_close(q1, q0, atol=1e-5, rtol=0)
    torch.testing.assert_close(model.means[still].detach(), still_means)  # Gaussians without a lifespan untouched
    # between their frames they follow the new keys (the anchor is not a freeze)
    t_mid = float(model.gauss_t_center[rows].unique()[2:4].mean())
    with torch.no_grad():
        moved_now = model.deform(t_mid, index=rows)[0]
        _jitter_keys_(model, torch.Generator().manual_seed(4))
        assert float((model.deform(t_mid, index=rows)[0] - moved_now).norm(dim=1).median()) > 0.01


def test_seed_poses_survive_a_rebind():
    _, _, model = _model()
    rows = anchored_rows(model)
    _jitter_keys_(model, torch.Generator().manual_seed(5))
    x0, _ = seed_poses(model, rows)
    with torch.no_grad():
        model.node_log_radii.add_(0.7)  # wider RBFs: other weights, other neighbours
    model.rebind()
    assert float((seed_poses(model, rows)[0] - x0).norm(dim=1).max()) > 1e-3  # a rebind alone moves them
    x1, _ = seed_poses(model, rows)
    with seed_poses_kept(model):
        model.node_log_radii.sub_(1.2)
        model.rebind()
    torch.testing.assert_close(seed_poses(model, rows)[0], x1, atol=2e-5, rtol=0)


def test_training_holds_the_moving_gaussians_at_their_seed_frames(tmp_path):
    from engine.train.trainer import Trainer

    data, truth = make_scene(fixed_camera=True)
    # centres and rotations do not learn here, so whatever moves a Gaussian is the node keys
    cfg = _cfg(steps=40, warmup_static_steps=0, checkpoint_every=0, densify_from=0, densify_until=0,
               rebind_every=15, lr_means=0.0, lr_means_final=0.0, lr_quats=0.0, lifespan_anchor=True)
    runs = {}
    for anchor in (True, False):
        trainer = Trainer(data, make_nodes(truth, key_count=5), dataclasses.replace(cfg, lifespan_anchor=anchor),
                          tmp_path / f"run{anchor}")
        rows = anchored_rows(trainer.model)
        before, keys0 = seed_poses(trainer.model, rows)[0], trainer.model.pos_keys.detach().clone()
        trainer.train()
        m = trainer.model
        runs[anchor] = (float((seed_poses(m, rows)[0] - before).norm(dim=1).max()),
                        float((m.pos_keys.detach() - keys0).abs().max()))
    held, free = runs[True], runs[False]
    assert held[1] > 1e-3 and free[1] > 1e-3  # the keys trained in both runs
    assert held[0] < 1e-4 < free[0]  # only the anchored run kept its Gaussians on their seed pixels
