"""A long clip trains enough steps per frame (``TrainConfig.min_steps_per_frame``,
:func:`engine.train.config.scale_to_frames`): the presets' step counts are set for ~60 frames."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from engine.errors import InputError
from engine.train.config import STEP_SCHEDULE, preset_config, scale_to_frames

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
