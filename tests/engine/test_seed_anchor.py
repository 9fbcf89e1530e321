"""Moving Gaussians held at their seed frame while the node keys train (engine/train/seed_anchor.py)."""
from __future__ import annotations

import dataclasses

import torch

from engine import bundle as B
from engine.train.config import preset_config
from engine.train.init_model import build_model
from engine.train.seed_anchor import (anchored_rows, canonical_view, deform_seed_frame, seed_poses, to_canonical_,
                                      to_seed_frame_)

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


def test_seed_frame_deform_has_deform_values_and_no_key_gradient_at_the_seed_frame():
    _, _, model = _model()
    _jitter_keys_(model, torch.Generator().manual_seed(1))  # keys that are not a plain translation
    rows = anchored_rows(model)
    t_own = float(model.gauss_t_center[rows[0]])
    own = rows[model.gauss_t_center[rows] == t_own]
    everything = torch.arange(model.num_gaussians)
    times = (t_own, t_own + 0.1)
    with torch.no_grad():
        refs = [model.deform(t, index=everything) for t in times]
    weights = torch.randn(len(own), 3, generator=torch.Generator().manual_seed(2))

    def grads(t, held, relative=True):
        model.zero_grad(set_to_none=True)
        x = (deform_seed_frame(model, t, model.node_dq(t), own, relative) if held
             else model.deform(t, index=own))[0]
        (x * weights).sum().backward()
        return model.pos_keys.grad.abs().max().item(), model.means.grad[own].clone(), model.pos_keys.grad.clone()

    plain = grads(t_own, held=False)[0]
    plain_later = grads(t_own + 0.1, held=False)[2]
    to_seed_frame_(model)
    for t, ref in zip(times, refs):
        got = deform_seed_frame(model, t, model.node_dq(t), everything)
        torch.testing.assert_close(got[0], ref[0], atol=2e-6, rtol=0)
        torch.testing.assert_close(got[1], ref[1], atol=2e-6, rtol=0)
    held, means_held, _ = grads(t_own, held=True)
    assert plain > 0.1 and held < 1e-4 * plain  # at its own frame the keys get no pull from it
    torch.testing.assert_close(means_held, weights, atol=1e-5, rtol=0)  # it is its own seed-frame centre
    assert grads(t_own + 0.1, held=True)[0] > 0.01 * plain  # elsewhere its motion teaches the keys
    # not relative: the keys learn through the time's transform alone, as from a canonical Gaussian
    torch.testing.assert_close(grads(t_own + 0.1, held=True, relative=False)[2], plain_later, atol=1e-5, rtol=1e-4)


def test_the_seed_frame_holds_each_gaussian_where_it_was_at_its_seed_frame():
    _, _, model = _model()
    rows = anchored_rows(model)
    assert len(rows) > 100 and len(torch.unique(model.gauss_t_center[rows])) > 5
    x0, q0 = seed_poses(model, rows)
    still = torch.nonzero(model.gauss_lifespan == 0).squeeze(1)
    still_means = model.means[still].detach().clone()
    to_seed_frame_(model)
    _jitter_keys_(model, torch.Generator().manual_seed(3))
    with torch.no_grad():
        for t in torch.unique(model.gauss_t_center[rows])[:4].tolist():  # at its own frame: where it was
            at = rows[model.gauss_t_center[rows] == t]
            got = deform_seed_frame(model, t, model.node_dq(t), at)[0]
            torch.testing.assert_close(got, x0[model.gauss_t_center[rows] == t], atol=1e-5, rtol=0)
    to_canonical_(model)
    x1, q1 = seed_poses(model, rows)  # canonical poses that the new keys put at the seed frames
    torch.testing.assert_close(x1, x0, atol=1e-5, rtol=0)
    torch.testing.assert_close(q1, q0, atol=1e-5, rtol=0)
    torch.testing.assert_close(model.means[still].detach(), still_means)  # Gaussians without a lifespan untouched
    # between their frames they follow the new keys (the seed frame is not a freeze)
    t_mid = float(model.gauss_t_center[rows].unique()[2:4].mean())
    with torch.no_grad():
        moved_now = model.deform(t_mid, index=rows)[0]
        _jitter_keys_(model, torch.Generator().manual_seed(4))
        assert float((model.deform(t_mid, index=rows)[0] - moved_now).norm(dim=1).median()) > 0.01


def test_canonical_view_rebinds_and_keeps_the_seed_frame_poses():
    _, _, model = _model()
    rows = anchored_rows(model)
    _jitter_keys_(model, torch.Generator().manual_seed(5))
    x0, _ = seed_poses(model, rows)
    weights = model.bind_w.clone()
    to_seed_frame_(model)
    with canonical_view(model):
        torch.testing.assert_close(seed_poses(model, rows)[0], x0, atol=1e-5, rtol=0)  # canonical inside
        with torch.no_grad():
            model.node_log_radii.add_(0.7)  # wider RBFs: other weights, other neighbours
        model.rebind()
    assert float((model.bind_w - weights).abs().max()) > 0.05  # the rebind took
    torch.testing.assert_close(model.means[rows].detach(), x0, atol=1e-5, rtol=0)  # seed frame again, same poses
    to_canonical_(model)  # and the new binding's canonical poses put them there too
    torch.testing.assert_close(seed_poses(model, rows)[0], x0, atol=2e-5, rtol=0)


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


def test_an_anchored_run_resumed_from_its_checkpoint_is_byte_identical(tmp_path):
    from engine.train.trainer import Trainer

    from .test_checkpoint import _Killed, _cfg as _ck_cfg, _die_at

    data, truth = make_scene(frames=12, width=48, height=36, fixed_camera=True)

    def cfg():  # densification, a rebind and checkpoints at step 25 and 50, all in the seed frame
        return _ck_cfg(lifespan_anchor=True, lifespan="on", steps=60)

    Trainer(data, make_nodes(truth), cfg(), tmp_path / "full").run()
    part = Trainer(data, make_nodes(truth), cfg(), tmp_path / "part")
    _die_at(part, 40)
    try:
        part.run()
    except _Killed:
        pass
    resumed = Trainer(data, make_nodes(truth), cfg(), tmp_path / "part", resume=True)
    assert resumed.step == 25 and resumed._seed_frame  # the checkpoint was written in the seed frame
    resumed.run()
    for name in (B.GAUSSIANS_FILE, B.NODES_FILE):
        assert (tmp_path / "full" / name).read_bytes() == (tmp_path / "part" / name).read_bytes()


def test_holding_the_rows_in_their_seed_frame_changes_no_loss_term(tmp_path):
    """Every term of a step (the render's and those that deform rows of their own, such as the
    pull onto the moving pixels) sees the held rows where the canonical model puts them."""
    from engine.train.trainer import Trainer

    data, truth = make_scene(fixed_camera=True)
    cfg = _cfg(steps=10, warmup_static_steps=0, checkpoint_every=0, lifespan_anchor=True)
    losses = {}
    for held in (True, False):
        trainer = Trainer(data, make_nodes(truth, key_count=5), dataclasses.replace(cfg, lifespan_anchor=held),
                          tmp_path / f"run{held}")
        _jitter_keys_(trainer.model, torch.Generator().manual_seed(6))
        trainer._sync_seed_frame()
        assert trainer._seed_frame == held
        trainer.objective.gen.manual_seed(7)  # the same draws (the pull's sample of rows)
        losses[held] = trainer._loss(int(data.train_idx[3]))[1]
    assert {"rgb", "on_mask"} <= set(losses[True])
    for name, value in losses[False].items():
        assert abs(losses[True][name] - value) <= 1e-5 * max(1.0, abs(value)), name
