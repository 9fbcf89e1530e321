"""The withheld-frame protocol (``--holdout N``) and the still-plate baseline."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from engine.pipeline import holdout_split, still_plate_psnr


def test_holdout_withholds_every_nth_frame_inside_the_clip():
    train = np.array([5, 0, 3, 1, 2, 4, 6, 7, 8])
    times = np.linspace(0, 1, 9)
    kept, withheld = holdout_split(train, times, 4)
    assert withheld.tolist() == [1, 5]  # positions 1 and 5 in time order
    assert sorted(kept.tolist() + withheld.tolist()) == list(range(9))
    assert 0 in kept and 8 in kept  # never the ends: held-out frames lie inside the trained range
    _, none = holdout_split(np.arange(2), np.linspace(0, 1, 2), 2)
    assert len(none) == 0


def test_still_plate_is_perfect_on_a_still_clip_and_not_on_a_moving_one():
    rng = np.random.default_rng(0)
    still = np.repeat(rng.integers(0, 255, (1, 16, 16, 3), dtype=np.uint8), 6, axis=0)
    assert still_plate_psnr(still, np.arange(6), np.arange(6)) > 100
    moving = still.copy()
    for f in range(6):  # a bright square crossing the frame
        moving[f, 4:8, 2 * f:2 * f + 4] = 255
    assert still_plate_psnr(moving, np.arange(6), np.arange(6)) < 30
    assert still_plate_psnr(moving, np.arange(6), np.arange(0)) is None


def _video(path, frames=16, w=96, h=72):
    import cv2

    rng = np.random.default_rng(1)
    bg = cv2.resize(rng.integers(0, 255, (h // 4, w // 4, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 24, (w, h))
    for f in range(frames):
        img = bg.copy()
        x = 8 + 4 * f
        img[20:40, x:x + 16] = (40, 200, 250)
        vw.write(img)
    vw.release()
    return path


@pytest.mark.slow
def test_video_clip_trains_with_holdout_and_evaluates_both_splits(tmp_path):
    """A camera-less video: ``--holdout 4`` scores withheld frames with the still plate beside
    them, and ``engine eval --split train`` works from the bundle's solved cameras (it used to
    fail with "clip has no cameras")."""
    clip = _video(tmp_path / "clip.avi")
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "engine", "train", str(clip), "--out", str(out), "--steps", "30",
                          "--holdout", "4", "--width", "96"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "held-out frames: PSNR" in res.stderr + res.stdout and "still plate" in res.stderr + res.stdout
    scene = json.loads((out / "scene.json").read_text())
    splits = [c["split"] for c in scene["cameras"]]
    assert splits.count("val") == 4 and splits.count("train") == 12
    stats = scene["stats"]
    assert stats["still_plate"]["val"] is not None and stats["eval"]["frames"] == 4
    for split in ("train", "val"):
        ev = subprocess.run([sys.executable, "-m", "engine", "eval", str(out), "--split", split, "--json"],
                            capture_output=True, text=True, timeout=300)
        assert ev.returncode == 0, ev.stderr[-2000:]
        assert json.loads(ev.stdout)["mean"]["frames"] == (12 if split == "train" else 4)


def test_prepare_tells_held_out_cameras_from_withheld_frames(tmp_path):
    """``lifespan auto`` keeps lifespans off for a moving camera only when the clip has cameras
    of its own it does not train on; frames withheld by ``--holdout`` lie on the training
    camera's path and do not count."""
    from engine.pipeline import open_clip, prepare, training_data
    from engine.train.config import preset_config

    clip = open_clip(_video(tmp_path / "clip.avi", frames=8))
    cfg = preset_config("preview", width=48, holdout=4)
    plain = prepare(clip, cfg, cache_dir=tmp_path / "cache")
    assert len(plain.val_idx) == 2 and plain.held_out_cameras is False
    assert training_data(plain).held_out_cameras is False
    clip.split = {"train": [0, 1, 2, 3, 4, 5], "val": [6, 7]}  # a dataset's own held-out views
    split = prepare(clip, dataclasses.replace(cfg, holdout=0), cache_dir=tmp_path / "cache2")
    assert split.held_out_cameras is True and training_data(split).held_out_cameras is True
