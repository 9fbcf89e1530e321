"""Objects at rest that move at another time become dynamic in every frame (engine/priors/resting.py).

The scene: a fixed camera over a textured table; a red block rests at A, is carried to B
over a few frames (the only frames the motion prior marks), and rests at B. Static Gaussians
seeded at A from the early frames would keep the block there after it left (the ghost of
cups.mp4); the prior must call A and B dynamic at every time, and nothing else.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.priors.cache import PriorConfig, compute_priors
from engine.priors.resting import resting_objects

F, H, W = 40, 48, 64
A, B, SIZE, ROW = 8, 42, 12, 20  # block columns at rest, size, top row
MOVE = range(18, 23)  # frames in which the block travels from A to B


def _table(seed=0):
    rng = np.random.default_rng(seed)
    import cv2

    tex = cv2.resize(rng.uniform(60, 200, (H // 4, W // 4, 3)).astype(np.float32), (W, H),
                     interpolation=cv2.INTER_LINEAR)
    return tex


def _block_x(f: int) -> int:
    if f < MOVE.start:
        return A
    if f >= MOVE.stop:
        return B
    return round(A + (B - A) * (f - MOVE.start + 1) / (len(MOVE) + 1))


def _clip(gain_after=1.0):
    """frames uint8 [F, H, W, 3], motion prior [F, H, W] (1 on the block while it moves)."""
    table = _table()
    frames = np.zeros((F, H, W, 3), np.float32)
    dyn = np.zeros((F, H, W), np.float32)
    for f in range(F):
        img = table.copy()
        x = _block_x(f)
        img[ROW:ROW + SIZE, x:x + SIZE] = (220, 30, 40)
        if f in MOVE:
            dyn[f, ROW:ROW + SIZE, x:x + SIZE] = 1.0
        frames[f] = img * (gain_after if f >= F // 2 else 1.0)
    return np.clip(frames, 0, 255).astype(np.uint8), dyn


def _cams(n=F, translate=0.0):
    K = np.tile(np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]]), (n, 1, 1))
    w2c = np.tile(np.eye(4), (n, 1, 1))
    w2c[:, 0, 3] = np.linspace(0, translate, n)
    return K, w2c


def _region(x):
    return (slice(ROW + 2, ROW + SIZE - 2), slice(x + 2, x + SIZE - 2))


def _far_from_block():
    m = np.ones((H, W), bool)
    m[ROW - 4:ROW + SIZE + 4, A - 4:B + SIZE + 4] = False
    return m


def test_a_block_set_down_elsewhere_is_dynamic_at_every_time_and_the_table_is_not():
    frames, dyn = _clip()
    K, w2c = _cams()
    out, st = resting_objects(frames, dyn, K, w2c, extent=5.0)
    assert st["applied"] and out is not None
    for f in (0, 10, MOVE.stop + 2, F - 1):  # before and after the move, at both places
        assert out[f][_region(A)].min() >= 0.5, f
        assert out[f][_region(B)].min() >= 0.5, f
        assert (out[f][_far_from_block()] < 0.5).mean() > 0.97, f
    # the input prior alone calls both places still outside the move
    assert dyn[0][_region(B)].max() == 0 and dyn[F - 1][_region(A)].max() == 0
    assert np.all(out >= dyn)  # it only adds


def test_exposure_drift_is_not_an_object():
    frames, dyn = _clip(gain_after=1.25)
    K, w2c = _cams()
    out, st = resting_objects(frames, dyn, K, w2c, extent=5.0)
    assert st["applied"]
    assert (out[0][_far_from_block()] < 0.5).mean() > 0.97
    assert out[0][_region(B)].min() >= 0.5


def test_a_translating_camera_or_a_new_picture_leaves_the_prior_alone():
    frames, dyn = _clip()
    K, w2c = _cams(translate=0.5)
    out, st = resting_objects(frames, dyn, K, w2c, extent=5.0)
    assert out is None and st["reason"] == "the camera translates"
    cut = frames.copy()
    cut[2 * F // 3:] = np.clip(_table(seed=7), 0, 255).astype(np.uint8)  # a cut to another view
    out, st = resting_objects(cut, dyn, *_cams(), extent=5.0)
    assert out is None and "whole picture" in st["reason"]


def test_a_turning_camera_is_compared_in_one_view():
    """The camera pans by ~4 px over the clip (a rotation-only solve): the comparison happens
    after the rotation's homography, so the block's two places are found in every frame's
    own pixels, and the textured table does not light up along its edges."""
    import cv2

    frames, dyn = _clip()
    K, _ = _cams()
    w2c = np.tile(np.eye(4), (F, 1, 1))
    ang = np.radians(np.linspace(-2.0, 2.0, F))  # about the y axis: a horizontal pan
    c, s = np.cos(ang), np.sin(ang)
    w2c[:, 0, 0], w2c[:, 0, 2], w2c[:, 2, 0], w2c[:, 2, 2] = c, s, -s, c
    ref = F // 2
    warped, wdyn = frames.copy(), dyn.copy()
    for f in range(F):  # what the turned camera sees: reference view -> frame f
        Hm = K[f] @ w2c[f, :3, :3] @ w2c[ref, :3, :3].T @ np.linalg.inv(K[f])
        warped[f] = cv2.warpPerspective(frames[f], Hm, (W, H), borderMode=cv2.BORDER_REFLECT)
        wdyn[f] = cv2.warpPerspective(dyn[f], Hm, (W, H))
    out, st = resting_objects(warped, wdyn, K, w2c, extent=5.0)
    assert st["applied"]
    for f in (0, F - 1):
        Hm = K[f] @ w2c[f, :3, :3] @ w2c[ref, :3, :3].T @ np.linalg.inv(K[f])
        for x in (A, B):
            centre = Hm @ np.array([x + SIZE / 2, ROW + SIZE / 2, 1.0])
            u, v = (centre[:2] / centre[2]).round().astype(int)
            assert out[f, v - 2:v + 3, u - 2:u + 3].min() >= 0.5, (f, x)
    inner = np.zeros((H, W), bool)
    inner[6:-6, 6:-6] = True  # away from the border the warp leaves uncovered
    assert (out[0][_far_from_block() & inner] < 0.5).mean() > 0.95


@pytest.mark.parametrize("mode", ["auto", "off"])
def test_compute_priors_applies_it_to_the_motion_mask(tmp_path, mode):
    """Through compute_priors (weight-free tracks, depth and motion mask of the synthetic clip):
    'auto' makes the place the block left dynamic in the last frame, 'off' does not."""
    frames, _ = _clip()
    K, w2c = _cams()
    pr = compute_priors(frames, K, w2c, PriorConfig(resting_objects=mode, num_points=200), cache_dir=tmp_path)
    left = pr.dynamic[F - 1][_region(A)].mean()
    if mode == "auto":
        assert left >= 0.5
    else:
        assert left < 0.5


def test_the_option_reaches_the_prior_config_and_a_bad_mode_is_refused(tmp_path):
    from engine.cli import build_parser
    from engine.commands._train_options import prior_config_from_args
    from engine.priors.cache import _with_resting_objects

    parse = lambda *extra: build_parser().parse_args(["train", "clip.mp4", "--out", "o", "--no-models", *extra])  # noqa: E731
    assert prior_config_from_args(parse()).resting_objects == "auto"
    assert prior_config_from_args(parse("--resting-objects", "off")).resting_objects == "off"
    frames, dyn = _clip()
    K, w2c = _cams()
    with pytest.raises(ValueError, match="resting_objects"):
        _with_resting_objects(frames, dyn, K, w2c, np.ones((F, H, W), np.float32), "sometimes", print)
    assert _with_resting_objects(frames, dyn, K, w2c, np.ones((F, H, W), np.float32), "off", print) is dyn


def _train_clip(root, mode):
    """Train the block clip (as a clip manifest with its fixed camera) with ``resting_objects``
    = ``mode``; returns the trainer."""
    import json

    import cv2

    from engine.pipeline import initial_nodes, open_clip, prepare, resolve_motion_init, training_data
    from engine.train.config import preset_config
    from engine.train.trainer import Trainer

    frames, _ = _clip()
    (root / "frames").mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(frames):
        cv2.imwrite(str(root / "frames" / f"{i:04d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    K, _ = _cams()
    cam = {"K": K[0].tolist(), "w2c": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}
    manifest = {"format": "motion-splats-clip", "version": 1, "video": None,
                "frames": [f"frames/{i:04d}.png" for i in range(F)], "frame_start": 1, "frame_end": F,
                "fps": 24.0, "width": W, "height": H, "cameras": [dict(frame=i + 1, **cam) for i in range(F)]}
    (root / "clip.json").write_text(json.dumps(manifest))
    cfg = preset_config("preview", width=W, steps=300, num_nodes=64, densify_from=60, densify_until=240,
                        densify_every=60, checkpoint_every=0, seed=0)
    clip = open_clip(root / "clip.json", solve=False)
    prep = prepare(clip, cfg, PriorConfig(resting_objects=mode, num_points=200), cache_dir=root / "cache")
    cfg = dataclasses.replace(cfg, motion_init=resolve_motion_init(prep, cfg))
    trainer = Trainer(training_data(prep), initial_nodes(prep, cfg), cfg, root / "run")
    trainer.train()
    return trainer


def _render(trainer, i):
    import torch

    from engine.train.render import render_scene

    m, d = trainer.model, trainer.data
    with torch.no_grad():
        means, quats = m.deform(float(d.times[i]))
        out = render_scene(m, means, quats, d.K[i], d.w2c[i], d.width, d.height, time=float(d.times[i]))
    return out.rgb.numpy() * 255


@pytest.mark.slow
def test_the_trained_scene_shows_the_block_where_it_is_and_not_where_it_was(tmp_path):
    """End to end: at the first and the last frame, the block's two places render as the frame
    shows them (block at A then table; table at B then block). With the step off one static
    model holds each place, and it cannot be both: one of the two times is wrong there."""
    frames, _ = _clip()
    err = {}
    for mode in ("auto", "off"):
        tr = _train_clip(tmp_path / mode, mode)
        order = tr.data.train_idx[np.argsort(tr.data.times[tr.data.train_idx].numpy())]
        err[mode] = max(float(np.abs(_render(tr, int(i))[_region(x)] - frames[int(i)][_region(x)]).mean())
                        for i in (order[0], order[-1]) for x in (A, B))
    assert err["auto"] < 20 and err["off"] > 2 * err["auto"], err
