"""A long clip trains enough steps per frame (``TrainConfig.min_steps_per_frame``,
:func:`engine.train.config.scale_to_frames`): the presets' step counts are set for ~60 frames."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest
import torch

from engine.errors import InputError
from engine.train.config import STEP_SCHEDULE, preset_config, scale_to_frames, steps_per_frame

from .test_holdout import _video


def test_a_long_clip_gets_more_steps_and_the_schedule_keeps_its_shape():
    cfg = preset_config("preview")
    long = scale_to_frames(cfg, 288)  # a long clip (cups.mp4 whole trains 300 frames)
    assert long.steps == 2880 and long.steps / 288 >= cfg.min_steps_per_frame
    factor = long.steps / cfg.steps
    for key in STEP_SCHEDULE:
        assert getattr(long, key) == round(getattr(cfg, key) * factor)  # 0 ("never") stays 0
    # as many densification events, at the same fractions of the run
    events = lambda c: len(range(c.densify_from, c.densify_until, c.densify_every))  # noqa: E731
    assert events(long) == events(cfg)
    assert long.densify_until / long.steps == pytest.approx(cfg.densify_until / cfg.steps, abs=1e-3)


def test_a_short_clip_or_an_explicit_step_count_is_left_as_it_is():
    cfg = preset_config("preview")
    assert scale_to_frames(cfg, 52) is cfg  # 600 steps already give 52 frames ~11 visits each
    assert scale_to_frames(preset_config("standard"), 288).steps == 3000
    explicit = preset_config("preview", steps=30)  # --steps, or "steps" in --config
    assert explicit.min_steps_per_frame == 0 and scale_to_frames(explicit, 288).steps == 30
    both = preset_config("preview", steps=30, min_steps_per_frame=2)  # both given: the floor applies
    assert scale_to_frames(both, 288).steps == 576
    with pytest.raises(InputError, match="min_steps_per_frame"):
        preset_config("preview", min_steps_per_frame=-1)


@pytest.mark.slow
def test_train_runs_the_scaled_steps_and_says_so(tmp_path):
    clip = _video(tmp_path / "clip.avi")
    (tmp_path / "cfg.json").write_text(json.dumps({"steps": 20, "min_steps_per_frame": 3}))
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "engine", "train", str(clip), "--out", str(out), "--width", "96",
                          "--config", str(tmp_path / "cfg.json")], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "training 48 steps, 3 per training frame over 16 frames" in res.stderr + res.stdout
    scene = json.loads((out / "scene.json").read_text())
    assert scene["config"]["steps"] == 48
    assert scene["stats"]["steps"] == 48 and scene["stats"]["history"][-1]["step"] == 48  # what ran


def test_a_run_with_lifespans_gets_its_own_floor_of_steps_per_frame():
    """With lifespans each frame's moving Gaussians learn only on that frame's steps: 52 frames
    train 30 a frame (1560), without lifespans the preset's 600 stay; an explicit step count
    is kept either way, and the lifespan floor never lowers the general one."""
    cfg = preset_config("preview")
    assert steps_per_frame(cfg, lifespans=True) == cfg.lifespan_steps_per_frame == 30
    assert steps_per_frame(cfg, lifespans=False) == cfg.min_steps_per_frame == 10
    assert scale_to_frames(cfg, 52, lifespans=True).steps == 1560
    assert scale_to_frames(cfg, 52, lifespans=False) is cfg
    assert scale_to_frames(cfg, 288, lifespans=True).steps == 8640
    explicit = preset_config("preview", steps=30)
    assert explicit.lifespan_steps_per_frame == 0 and scale_to_frames(explicit, 52, lifespans=True).steps == 30
    low = preset_config("preview", lifespan_steps_per_frame=5)
    assert steps_per_frame(low, lifespans=True) == 10
    off = preset_config("preview", min_steps_per_frame=0)  # 0: steps as given, lifespans or not
    assert scale_to_frames(off, 288, lifespans=True) is off
    with pytest.raises(InputError, match="lifespan_steps_per_frame"):
        preset_config("preview", lifespan_steps_per_frame=-1)


def test_the_lifespan_decision_before_the_model_matches_the_models_own():
    """``run_has_lifespans`` (made on the prior before any model exists, for the step count)
    agrees with what the initial model does: a fixed camera with moving pixels has lifespans;
    the swaying camera of a clip with held-out cameras, a clip whose prior calls nothing moving,
    ``split`` off and ``lifespan off`` have none."""
    from engine.train.init_model import build_model
    from engine.train.lifespan import run_has_lifespans

    from .synthetic_training import make_nodes, make_scene

    cfg = preset_config("preview", gaussians_per_frame=800, init_keyframes=4, num_nodes=25, dynamic_gaussians=600)

    def model_has(data, c):
        model = build_model(data, make_nodes(truth), c, torch.Generator().manual_seed(0))
        return bool((model.gauss_lifespan > 0).any())

    data, truth = make_scene(fixed_camera=True)
    assert run_has_lifespans(cfg, data) and model_has(data, cfg)
    for c in (dataclasses.replace(cfg, lifespan="off"), dataclasses.replace(cfg, split=False)):
        assert not run_has_lifespans(c, data) and not model_has(data, c)
    still = dataclasses.replace(data, fg=torch.zeros_like(data.fg))
    assert not run_has_lifespans(cfg, still) and not model_has(still, cfg)
    swaying, truth = make_scene()
    assert not run_has_lifespans(cfg, swaying) and not model_has(swaying, cfg)
