"""Gaussian lifespans (engine/train/lifespan.py): moving Gaussians visible around their own frame."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from engine import bundle as B
from engine.errors import InputError
from engine.train.config import preset_config
from engine.train.export import bundle_arrays
from engine.train.init_model import build_model
from engine.train.lifespan import camera_translates, lifespan_window, resolve_lifespan
from engine.train.from_bundle import model_from_bundle
from engine.train.render import render_scene

from .synthetic_training import make_nodes, make_scene

REPO = Path(__file__).resolve().parents[2]


def _cfg(**kw):
    return preset_config("preview", gaussians_per_frame=800, init_keyframes=4, num_nodes=25,
                         dynamic_gaussians=600, **kw)


def test_window_is_a_gaussian_in_time_and_one_without_a_lifespan():
    tc = torch.tensor([0.5, 0.5, 0.2])
    life = torch.tensor([0.1, 0.0, 0.05])
    w = lifespan_window(0.7, tc, life)
    torch.testing.assert_close(w, torch.tensor([math.exp(-2.0), 1.0, math.exp(-0.5 * 100.0)]))
    assert lifespan_window(0.5, tc, life)[0] == 1.0


def test_auto_gives_lifespans_unless_a_moving_camera_has_held_out_cameras():
    times = torch.linspace(0, 1, 11)
    eye = torch.eye(4).expand(11, 4, 4).clone()
    turning = eye.clone()  # a camera that only rotates about its centre: still no parallax
    for i, a in enumerate(torch.linspace(0, 0.3, 11)):
        turning[i, 0, 0], turning[i, 0, 2], turning[i, 2, 0], turning[i, 2, 2] = a.cos(), a.sin(), -a.sin(), a.cos()
    moving = eye.clone()
    moving[:, 0, 3] = torch.linspace(0, 0.5, 11)
    assert not camera_translates(eye, 2.0) and not camera_translates(turning, 2.0) and camera_translates(moving, 2.0)
    assert resolve_lifespan("auto", 1.5, times, eye, 2.0) == pytest.approx(0.15)  # 1.5 frame gaps of 0.1
    assert resolve_lifespan("auto", 1.5, times, turning, 2.0) == pytest.approx(0.15)
    assert resolve_lifespan("auto", 1.5, times, moving, 2.0) == 0.0  # held-out cameras by default
    assert resolve_lifespan("auto", 1.5, times, moving, 2.0, held_out_cameras=True) == 0.0
    # a plain video: renders follow the shot, so its moving Gaussians live around their frame
    assert resolve_lifespan("auto", 1.5, times, moving, 2.0, held_out_cameras=False) == pytest.approx(0.15)
    assert resolve_lifespan("off", 1.5, times, moving, 2.0, held_out_cameras=False) == 0.0
    assert resolve_lifespan("on", 1.5, times, moving, 2.0) == pytest.approx(0.15)
    assert resolve_lifespan("off", 1.5, times, eye, 2.0) == 0.0
    with pytest.raises(ValueError):
        resolve_lifespan("sometimes", 1.5, times, eye, 2.0)


def test_fixed_camera_model_gives_moving_gaussians_their_seed_time():
    data, truth = make_scene(fixed_camera=True)
    model = build_model(data, make_nodes(truth), _cfg(), torch.Generator().manual_seed(0))
    dyn, life = model.gauss_dyn, model.gauss_lifespan
    assert bool((life[dyn] > 0).all()) and bool((life[~dyn] == 0).all())
    gap = float(torch.diff(data.times[data.train_idx]).median())
    torch.testing.assert_close(life[dyn], torch.full_like(life[dyn], _cfg().lifespan_frames * gap))
    train_times = set(np.round(data.times[data.train_idx].numpy(), 6).tolist())
    assert set(np.round(model.gauss_t_center[dyn].numpy(), 6).tolist()) <= train_times
    # each frame shows only its own moving Gaussians, so lifespan_seed_factor times as many are seeded
    off = build_model(data, make_nodes(truth), _cfg(lifespan="off"), torch.Generator().manual_seed(0))
    assert int(dyn.sum()) >= 0.9 * _cfg().lifespan_seed_factor * int(off.gauss_dyn.sum())
    assert not bool((off.gauss_lifespan > 0).any())
    # the swaying camera of the same scene: no lifespans (auto), unless asked for
    data2, truth2 = make_scene()
    assert not bool((build_model(data2, make_nodes(truth2), _cfg(), torch.Generator().manual_seed(0))
                     .gauss_lifespan > 0).any())
    forced = build_model(data2, make_nodes(truth2), _cfg(lifespan="on"), torch.Generator().manual_seed(0))
    assert bool((forced.gauss_lifespan[forced.gauss_dyn] > 0).all())


def test_a_render_shows_a_gaussian_with_a_lifespan_only_around_its_time():
    data, truth = make_scene(fixed_camera=True)
    model = build_model(data, make_nodes(truth), _cfg(), torch.Generator().manual_seed(0))
    f = int(data.train_idx[len(data.train_idx) // 2])
    t = float(data.times[f])
    own = model.gauss_dyn & (model.gauss_t_center == t)
    with torch.no_grad():
        model.opacity_logits[~own] = -20.0  # only frame f's moving Gaussians can show, and opaque
        model.opacity_logits[own] = 5.0
        means, quats = model.deform(t)
        near = render_scene(model, means, quats, data.K[f], data.w2c[f], data.width, data.height, time=t)
        far = render_scene(model, means, quats, data.K[f], data.w2c[f], data.width, data.height, time=t + 0.5)
        always = render_scene(model, means, quats, data.K[f], data.w2c[f], data.width, data.height)
    blob = data.fg[f] > 0.5
    assert float(near.alpha[..., 0][blob].mean()) > 0.5
    assert float(far.alpha[..., 0][blob].max()) < 1e-3  # gone half a clip later
    torch.testing.assert_close(always.alpha, near.alpha, atol=0.05, rtol=0)  # windowed at t: itself
    torch.testing.assert_close(model.opacities_at(None), model.opacities())


def test_training_densifies_with_the_lifespans_and_the_bundle_round_trips(tmp_path):
    from engine.train.trainer import Trainer

    data, truth = make_scene(fixed_camera=True)
    cfg = _cfg(steps=30, warmup_static_steps=0, checkpoint_every=0, densify_from=10, densify_every=10,
               densify_until=30, densify_grad_threshold=0.0, max_gaussians=4000)
    trainer = Trainer(data, make_nodes(truth), cfg, tmp_path / "run")
    g0 = trainer.model.num_gaussians
    trainer.train()
    m = trainer.model
    assert m.num_gaussians > g0  # densification ran (threshold 0: every seen Gaussian is hot)
    for name in ("gauss_dyn", "gauss_t_center", "gauss_lifespan"):
        assert getattr(m, name).shape == (m.num_gaussians,)
    assert bool(((m.gauss_lifespan > 0) == m.gauss_dyn).all())  # copies inherit their source's lifespan
    factor = (m.lifespans()[m.gauss_dyn] / m.gauss_lifespan[m.gauss_dyn]).detach()
    assert bool((factor - 1).abs().max() > 1e-3)  # learned ...
    assert bool((factor >= cfg.lifespan_min - 1e-6).all() and (factor <= cfg.lifespan_max + 1e-6).all())  # ... in range
    nodes, gaussians = bundle_arrays(m)
    assert nodes.gauss_lifespan is not None
    trainer.export_bundle()
    bundle = B.load_bundle(tmp_path / "run")
    loaded = model_from_bundle(bundle)
    for t in (0.0, 0.37, 1.0):
        torch.testing.assert_close(loaded.opacities_at(t), m.opacities_at(t).detach(), atol=1e-6, rtol=1e-5)
    # a per-frame PLY export carries each Gaussian's opacity at that frame
    res = subprocess.run([sys.executable, "-m", "engine", "export", str(tmp_path / "run"), "--ply-sequence",
                          str(tmp_path / "seq"), "--frames", "1,9"], cwd=REPO, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    bound = loaded.gauss_view_angle > 0  # shot detail: left out of a PLY (test_bundle_commands.py)
    for frame in (1, 9):
        t = float(np.clip(B.time_of_frame(bundle.scene, frame), 0, 1))
        exported = torch.sigmoid(torch.tensor(np.array(B.read_ply(tmp_path / "seq" / f"frame_{frame:05d}.ply").opacity_logits)))
        torch.testing.assert_close(exported[~bound], loaded.opacities_at(t).float()[~bound], atol=1e-5, rtol=1e-4)
        assert bool(bound.any()) and float(exported[bound].max()) < 1e-6


def test_lifespans_learn_short_where_wrong_and_long_where_right():
    """The lifespan is a parameter: a moving Gaussian that the neighbouring frames do not want
    (its nodes lost the object there) shortens its life, one they want lengthens it, each
    within ``lifespan_min`` .. ``lifespan_max`` of the seeded one; static Gaussians and
    ``lr_lifespan`` 0 keep theirs."""
    from engine.train.lifespan import clamp_lifespans_
    from engine.train.param_edit import make_optimizer

    data, truth = make_scene(fixed_camera=True)
    cfg = _cfg()
    gap = float(torch.diff(data.times[data.train_idx]).median())
    for lr in (cfg.lr_lifespan, 0.0):
        model = build_model(data, make_nodes(truth), dataclasses.replace(cfg, lr_lifespan=lr),
                            torch.Generator().manual_seed(0))
        seeded = model.gauss_lifespan.clone()
        dyn = torch.nonzero(model.gauss_dyn).squeeze(1)
        wrong, right = dyn[0::2], dyn[1::2]
        opt = make_optimizer(model, dataclasses.replace(cfg, lr_lifespan=lr))
        for _ in range(200):
            opt.zero_grad(set_to_none=True)
            # shown one frame off its seed time (t_center + gap): penalised for `wrong`, wanted for `right`
            shown = torch.stack([model.opacities_at(float(t))
                                 for t in model.gauss_t_center[dyn[:2]] + gap])  # two times: one per class
            loss = shown[0, wrong].sum() - shown[1, right].sum()
            loss.backward()
            opt.step()
            clamp_lifespans_(model, cfg)
        factor = (model.lifespans() / seeded.clamp_min(1e-12)).detach()
        if lr == 0:
            torch.testing.assert_close(model.lifespans().detach(), seeded)
            continue
        same_time = lambda idx, k: idx[model.gauss_t_center[idx] == model.gauss_t_center[dyn[k]]]  # noqa: E731
        assert float(factor[same_time(wrong, 0)].max()) == pytest.approx(cfg.lifespan_min, rel=1e-4)
        assert float(factor[same_time(right, 1)].min()) == pytest.approx(cfg.lifespan_max, rel=1e-4)
        assert bool((model.lifespans()[~model.gauss_dyn] == 0).all())  # static: always visible


def test_bundle_refuses_broken_lifespans():
    data, truth = make_scene(fixed_camera=True)
    model = build_model(data, make_nodes(truth), _cfg(), torch.Generator().manual_seed(0))
    arrays = bundle_arrays(model)[0].to_dict()
    B.NodeArrays.from_dict(arrays)  # the model's own arrays are valid
    for change, message in ((lambda a: a.pop("gauss_lifespan"), "come together"),
                            (lambda a: a.__setitem__("gauss_lifespan", -a["gauss_lifespan"] - 1), ">= 0"),
                            (lambda a: a.__setitem__("gauss_t_center", a["gauss_t_center"][:-1]), "one value per"),
                            (lambda a: a.__setitem__("gauss_t_center", a["gauss_t_center"] * np.nan), "finite")):
        broken = dict(arrays)
        change(broken)
        with pytest.raises(InputError, match=message):
            B.NodeArrays.from_dict(broken)
    swaying = build_model(*(lambda d, t: (d, make_nodes(t)))(*make_scene()), _cfg(), torch.Generator().manual_seed(0))
    assert bundle_arrays(swaying)[0].gauss_lifespan is None  # bundles without lifespans stay as they were


def test_the_command_line_sets_the_lifespan():
    import argparse

    from engine.commands._train_options import add_clip_options, config_from_args

    parser = argparse.ArgumentParser()
    add_clip_options(parser)
    args = ["clip", "--out", "run"]
    assert config_from_args(parser.parse_args(args + ["--lifespan", "off"])).lifespan == "off"
    assert config_from_args(parser.parse_args(args)).lifespan == "auto"
    with pytest.raises(SystemExit):
        parser.parse_args(args + ["--lifespan", "sometimes"])


def test_resume_keeps_the_lifespans(tmp_path):
    """A run killed after a periodic checkpoint and resumed ends byte-identical to an
    uninterrupted one, lifespans included (they ride in the model's state)."""
    from engine.train.trainer import Trainer

    data, truth = make_scene(frames=12, width=48, height=36, fixed_camera=True)
    cfg = dict(steps=40, gaussians_per_frame=400, init_keyframes=4, num_nodes=25, dynamic_gaussians=300,
               densify_from=10, densify_until=35, densify_every=10, checkpoint_every=20, warmup_static_steps=5)
    Trainer(data, make_nodes(truth), preset_config("preview", **cfg), tmp_path / "full").run()
    part = Trainer(data, make_nodes(truth), preset_config("preview", **cfg), tmp_path / "part")
    original = part._loss

    def killed_at_30(f):
        if part.step == 30:
            raise RuntimeError("killed")
        return original(f)

    part._loss = killed_at_30
    with pytest.raises(RuntimeError, match="killed"):
        part.run()
    resumed = Trainer(data, make_nodes(truth), preset_config("preview", **cfg), tmp_path / "part", resume=True)
    assert resumed.step == 20 and bool((resumed.model.gauss_lifespan > 0).any())
    resumed.run()
    full, again = B.read_nodes(tmp_path / "full" / B.NODES_FILE), B.read_nodes(tmp_path / "part" / B.NODES_FILE)
    np.testing.assert_array_equal(full.gauss_t_center, again.gauss_t_center)
    np.testing.assert_array_equal(full.gauss_lifespan, again.gauss_lifespan)
    assert (tmp_path / "full" / B.GAUSSIANS_FILE).read_bytes() == (tmp_path / "part" / B.GAUSSIANS_FILE).read_bytes()


def test_lifespan_seeds_do_not_eat_the_densification_budget():
    """With lifespans the extra moving seeds raise the cap by as many Gaussians: densification
    keeps the headroom a run without lifespans has (they used to fill the cap: cups seeded
    32.6k Gaussians against 30k and densified none)."""
    from engine.train.lifespan import gaussian_budget, lifespan_seed_count

    data, truth = make_scene(fixed_camera=True)
    cfg = _cfg(max_gaussians=1000)
    with_life = build_model(data, make_nodes(truth), cfg, torch.Generator().manual_seed(0))
    without = build_model(data, make_nodes(truth), dataclasses.replace(cfg, lifespan="off"),
                          torch.Generator().manual_seed(0))
    assert bool((with_life.gauss_lifespan > 0).any()) and not bool((without.gauss_lifespan > 0).any())
    extra = lifespan_seed_count(cfg) - cfg.dynamic_gaussians
    assert extra > 0
    assert gaussian_budget(cfg, without) == 1000
    assert gaussian_budget(cfg, with_life) == 1000 + extra
    # the headroom over the seeds is the same either way (seeding draws the same frames)
    assert abs((gaussian_budget(cfg, with_life) - with_life.num_gaussians)
               - (gaussian_budget(cfg, without) - without.num_gaussians)) <= len(data.train_idx) + 2


def test_a_long_clip_seeds_as_many_moving_gaussians_per_frame_as_a_short_one():
    """With lifespans a frame shows only its own moving seeds: a clip longer than
    ``lifespan_seed_frames`` seeds proportionally more (the same per frame), and the cap rises by
    as many, so densification keeps its headroom. Without lifespans nothing changes."""
    from engine.train.lifespan import gaussian_budget, lifespan_seed_count

    data, truth = make_scene(fixed_camera=True)  # 16 training frames
    frames = len(data.train_idx)
    cfg = _cfg(max_gaussians=1000)
    short = dataclasses.replace(cfg, lifespan_seed_frames=frames)  # this clip is "short"
    long = dataclasses.replace(cfg, lifespan_seed_frames=frames // 2)  # twice as long as that
    assert lifespan_seed_count(short, frames) == lifespan_seed_count(cfg)
    assert lifespan_seed_count(long, frames) == 2 * lifespan_seed_count(cfg)
    assert lifespan_seed_count(dataclasses.replace(cfg, lifespan_seed_frames=0), 10 * frames) == \
        lifespan_seed_count(cfg)
    # a very long clip stops growing at lifespan_seed_max (never below the short clip's count)
    base = lifespan_seed_count(cfg)
    assert lifespan_seed_count(dataclasses.replace(long, lifespan_seed_max=3 * base), 100 * frames) == 3 * base
    assert lifespan_seed_count(dataclasses.replace(long, lifespan_seed_max=base // 2), 100 * frames) == base
    m_short = build_model(data, make_nodes(truth), short, torch.Generator().manual_seed(0))
    m_long = build_model(data, make_nodes(truth), long, torch.Generator().manual_seed(0))
    n_short, n_long = int(m_short.gauss_dyn.sum()), int(m_long.gauss_dyn.sum())
    assert 1.9 * n_short <= n_long <= 2.1 * n_short
    # per frame: each training frame gets about twice its seeds
    t_short = torch.unique(m_short.gauss_t_center[m_short.gauss_dyn], return_counts=True)[1].float()
    t_long = torch.unique(m_long.gauss_t_center[m_long.gauss_dyn], return_counts=True)[1].float()
    assert 1.8 <= float(t_long.median() / t_short.median()) <= 2.2
    # the extra seeds raise the cap by as many
    assert gaussian_budget(long, m_long, frames) - gaussian_budget(short, m_short, frames) == \
        lifespan_seed_count(long, frames) - lifespan_seed_count(short, frames)
    # no lifespans (a moving camera with held-out cameras): the seeds and the cap stay
    off = dataclasses.replace(long, lifespan="off")
    m_off = build_model(data, make_nodes(truth), off, torch.Generator().manual_seed(0))
    assert gaussian_budget(off, m_off, frames) == 1000
    assert int(m_off.gauss_dyn.sum()) < 0.3 * n_short


def test_a_step_renders_only_the_gaussians_its_time_can_show_with_the_same_gradients(tmp_path, monkeypatch):
    """The cull (lifespan.shown_gaussians) leaves out only Gaussians the rasteriser would skip:
    one training step with it gives every parameter the gradient, and densification the
    statistics, that the step without it gives; the same frame renders the same picture."""
    from engine.train import trainer as T
    from engine.train.lifespan import ALPHA_MIN, shown_gaussians

    data, truth = make_scene(fixed_camera=True)
    cfg = _cfg(steps=24, warmup_static_steps=0, checkpoint_every=0, densify_from=0, densify_until=100,
               lifespan_frames=0.6)
    grads, stats, renders, shares = {}, {}, {}, []
    f = int(data.train_idx[len(data.train_idx) // 2])
    for cull in (True, False):
        monkeypatch.setattr(T, "CULL_HIDDEN", cull)
        trainer = T.Trainer(data, make_nodes(truth), cfg, tmp_path / f"run{cull}")
        m = trainer.model
        with torch.no_grad():  # initial Gaussians are round, whose rotation gradient is exactly 0
            m.log_scales.add_(0.3 * torch.randn(m.log_scales.shape, generator=torch.Generator().manual_seed(1)))
        for g in data.train_idx.tolist():
            o = m.opacities_at(float(data.times[g])).detach()
            shown = shown_gaussians(m, float(data.times[g]))
            assert shown is not None  # short lives: most moving Gaussians are hidden at any one time
            assert int((o >= ALPHA_MIN).sum()) == len(shown) and bool((o[shown] >= ALPHA_MIN).all())
            shares.append(len(shown) / m.num_gaussians)
        trainer.step = 4  # a mask step (every 4th): the dynamic score channel and the on-mask pull
        loss, metrics, out, shown = trainer._loss(f)
        assert (shown is not None) == cull and {"mask", "on_mask", "track"} <= set(metrics)
        trainer.opt.zero_grad(set_to_none=True)
        loss.backward()
        grads[cull] = {n: p.grad.clone() for n, p in m.named_parameters() if p.grad is not None}
        trainer.gaussian_strategy.step_post_backward(trainer.step, out, data.width, data.height, index=shown)
        stats[cull] = (trainer.gaussian_strategy.grad_accum.clone(), trainer.gaussian_strategy.grad_count.clone())
        renders[cull] = trainer.render_frame(f)
    assert max(shares) < 0.7
    assert grads[True].keys() == grads[False].keys() and {"means", "quats", "pos_keys"} <= grads[True].keys()
    for name, g in grads[False].items():
        assert float(g.abs().max()) > 0, name
        torch.testing.assert_close(grads[True][name], g, atol=1e-7 + 1e-5 * float(g.abs().max()), rtol=1e-4,
                                   msg=name)
    assert int(stats[False][1].sum()) > 0
    torch.testing.assert_close(stats[True][1], stats[False][1], atol=0, rtol=0)  # the same Gaussians seen
    torch.testing.assert_close(stats[True][0], stats[False][0], atol=1e-7, rtol=1e-4)
    assert renders[True].radii.shape[0] < renders[False].radii.shape[0]
    torch.testing.assert_close(renders[True].rgb, renders[False].rgb, atol=1e-6, rtol=0)


def test_shown_gaussians_is_none_without_lifespans_or_when_nearly_all_are_shown():
    from engine.train.lifespan import shown_gaussians

    data, truth = make_scene(fixed_camera=True)
    t = float(data.times[data.train_idx[0]])
    off = build_model(data, make_nodes(truth), _cfg(lifespan="off"), torch.Generator().manual_seed(0))
    assert shown_gaussians(off, t) is None
    model = build_model(data, make_nodes(truth), _cfg(lifespan_frames=100.0), torch.Generator().manual_seed(0))
    assert shown_gaussians(model, t) is None  # lives as long as the clip: all shown
    with torch.no_grad():
        model.opacity_logits[::2] = -20.0  # below the floor at any time
    torch.testing.assert_close(shown_gaussians(model, t), torch.arange(1, model.num_gaussians, 2))
