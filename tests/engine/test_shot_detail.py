"""The shot-detail stage (engine/train/shot_detail.py): per-frame Gaussians of the moving
things, trained after the main run, that give the training views their detail, leave the
trained model as it was and fade from cameras away from their own."""

from __future__ import annotations

import pytest
import torch

from engine import bundle as B
from engine.train import losses as L
from engine.train.config import preset_config
from engine.train.render import render_scene
from engine.train.trainer import Trainer

from .synthetic_training import make_nodes, make_scene

pytestmark = pytest.mark.slow


def _cfg(**kw):
    base = dict(steps=120, gaussians_per_frame=400, init_keyframes=4, num_nodes=25, densify_from=20,
                densify_until=100, densify_every=20, checkpoint_every=0, log_every=10, warmup_static_steps=10,
                dynamic_gaussians=800, detail_steps_per_frame=30)
    base.update(kw)
    return preset_config("preview", **base)


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=12, width=64, height=48)


@pytest.fixture(scope="module")
def runs(scene, tmp_path_factory):
    """The same run without and with the stage (the stage's fade made steep enough to show at
    this size: 0.05 px)."""
    data, truth = scene
    out = {}
    for name, detail in (("plain", "off"), ("detail", "on")):
        t = Trainer(data, make_nodes(truth), _cfg(shot_detail=detail, detail_fade_px=0.05),
                    tmp_path_factory.mktemp(name))
        t.train()
        out[name] = t
    return out


def _render(model, data, f, hide=None):
    with torch.no_grad():
        keep = model.opacity_logits.detach().clone()
        if hide is not None:
            model.opacity_logits.data[hide] = -30.0
        try:
            t = float(data.times[f])
            means, quats = model.deform(t)
            return render_scene(model, means, quats, data.K[f], data.w2c[f], data.width, data.height,
                                time=t).rgb.clamp(0, 1)
        finally:
            model.opacity_logits.data.copy_(keep)


def test_the_stage_leaves_the_trained_model_as_it_was(runs):
    plain, detail = runs["plain"].model, runs["detail"].model
    g = plain.num_gaussians
    bound = detail.gauss_view_angle > 0
    assert int(bound.sum()) > 100 and not bool(bound[:g].any()) and bool(bound[g:].all())
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(detail, name)[:g], getattr(plain, name)), name
    assert torch.equal(detail.pos_keys, plain.pos_keys) and torch.equal(detail.rot_keys, plain.rot_keys)
    # each seed lives around its own frame, on the moving nodes, seen from its own camera
    assert bool((detail.gauss_lifespan[g:] > 0).all()) and bool(detail.gauss_dyn[g:].all())
    assert bool(detail.node_dyn[detail.bind_idx[g:][detail.bind_w[g:] > 0]].all())


def test_detail_sharpens_the_moving_region_of_every_training_view(runs, scene):
    """Inside the dynamic prior each training view gains over the same run without the stage
    (the blob, averaged over the clip by the moving Gaussians, gets each frame's own pixels)."""
    data, _ = scene
    gains = []
    for f in data.train_idx.tolist():
        mask = (data.fg[f] >= 0.5).unsqueeze(-1).to(torch.float32)
        psnr = {name: float(L.psnr(_render(runs[name].model, data, f), data.images[f], mask))
                for name in ("plain", "detail")}
        gains.append(psnr["detail"] - psnr["plain"])
    assert min(gains) > 2.0 and sum(gains) / len(gains) > 4.0, gains


def test_detail_fades_from_the_held_out_cameras(runs, scene):
    """The held-out frames' cameras are half a unit to the side: with a 0.05 px fade the seeds
    of those times are gone there, and the render is the trained model's."""
    data, _ = scene
    m = runs["detail"].model
    bound = m.gauss_view_angle > 0
    for f in data.val_idx.tolist():
        diff = (_render(m, data, f) - _render(m, data, f, hide=bound)).abs().max()
        assert float(diff) < 0.02, (f, float(diff))


class _Killed(Exception):
    """Stands in for SIGKILL: nothing of the trainer's own interrupt handling runs."""


def test_a_run_killed_in_the_stage_resumes_to_the_same_bundle(tmp_path, scene, monkeypatch):
    from engine.train import shot_detail

    data, truth = scene
    cfg = dict(steps=60, densify_until=50, checkpoint_every=25, detail_steps_per_frame=3, shot_detail="on")
    Trainer(data, make_nodes(truth), _cfg(**cfg), tmp_path / "full").run()
    part = Trainer(data, make_nodes(truth), _cfg(**cfg), tmp_path / "part")
    original = shot_detail.keep_only_detail_grads_

    def dying(model):
        if part.step == 80:  # stage steps 60..84: killed after the step-75 checkpoint
            raise _Killed
        original(model)

    monkeypatch.setattr(shot_detail, "keep_only_detail_grads_", dying)
    with pytest.raises(_Killed):
        part.run()
    monkeypatch.setattr(shot_detail, "keep_only_detail_grads_", original)
    assert torch.load(tmp_path / "part/checkpoints/checkpoint.pt", weights_only=True)["step"] == 75
    resumed = Trainer(data, make_nodes(truth), _cfg(**cfg), tmp_path / "part", resume=True)
    assert resumed.step == 75
    resumed.run()
    for name in (B.GAUSSIANS_FILE, B.NODES_FILE):
        assert (tmp_path / "full" / name).read_bytes() == (tmp_path / "part" / name).read_bytes(), name
