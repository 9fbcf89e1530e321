"""Moving objects are reconstructed: they are in the training views at every time, where the
footage shows them, and the nodes on them move with them (issue: "Reconstruct what moves").

Full-frame PSNR cannot see this (the background dominates the image), so these tests look
at the moving region itself: the silhouette the *dynamic* Gaussians render against the
ground-truth mask, and the trained nodes' paths against the ground-truth trajectories.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained_large(tmp_path_factory):
    """A tiny large-motion scene (rolling ball + fast pendulum, 12 frames, 96x72) trained on
    its ground-truth priors at the preview preset (fewer steps): the model's machinery on
    its own, without the weight-free priors' errors."""
    from engine.bench.oracle import write_oracle_priors
    from engine.pipeline import initial_nodes, open_clip, prepare, resolve_motion_init, training_data
    from engine.priors import PriorConfig
    from engine.train.config import preset_config
    from engine.train.trainer import Trainer
    from tools.synth_scene import generate_scene

    root = tmp_path_factory.mktemp("large")
    scene = generate_scene(root / "scene", preset="tiny", kind="large", seed=0)
    paths = write_oracle_priors(scene, root / "oracle")
    pc = PriorConfig(depth_path=str(paths["depth_path"]), mask_path=str(paths["mask_path"]),
                     tracks_path=str(paths["tracks_path"]))
    # a key per frame: 12 frames of a pendulum swinging at 2 Hz over the clip alias at fewer
    cfg = preset_config("preview", width=96, steps=400, num_nodes=128, num_keys=12, densify_from=60,
                        densify_until=320, densify_every=60, checkpoint_every=0, warmup_static_steps=20)
    clip = open_clip(scene, solve=False)
    prep = prepare(clip, cfg, pc, cache_dir=root / "cache")
    prep.frame_ids = [clip.frame_ids[int(j)] for j in prep.clip_index]
    cfg = dataclasses.replace(cfg, motion_init=resolve_motion_init(prep, cfg))
    nodes = initial_nodes(prep, cfg)
    trainer = Trainer(training_data(prep), nodes, cfg, root / "run")
    trainer.train()
    return scene, prep, trainer


def _gt_mask(scene, prep, i):
    import cv2

    fid = prep.frame_ids[i]
    m = cv2.imread(str(scene / "gt" / "mask" / f"{fid}.png"), cv2.IMREAD_GRAYSCALE) > 127
    h, w = prep.frames.shape[1:3]
    return cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0


def silhouette_iou(model, which, time, K, w2c, width, height, gt) -> float:
    """IoU of the silhouette (alpha > 0.5) the Gaussians ``which [G] bool`` render at ``time``
    through camera ``K``, ``w2c`` with the ground-truth mask ``gt [H, W] bool``."""
    from engine.train.render import render_scene

    with torch.no_grad():
        means, quats = model.deform(float(time))
        out = render_scene(model, means, quats, torch.as_tensor(K, dtype=torch.float32),
                           torch.as_tensor(w2c, dtype=torch.float32), int(width), int(height),
                           extra=which.to(means.dtype).contiguous())
    sil = out.extra[..., 0].numpy() > 0.5
    return float((sil & gt).sum() / max((sil | gt).sum(), 1))


def test_dynamic_silhouette_overlaps_the_moving_objects_at_three_times(trained_large):
    scene, prep, trainer = trained_large
    m, d = trainer.model, trainer.data
    assert m.is_split and int(m.gauss_dyn.sum()) > 100
    train = d.train_idx[torch.argsort(d.times[d.train_idx])]
    ious = []
    for i in (train[1], train[len(train) // 2], train[-2]):  # three different times
        i = int(i)
        ious.append(silhouette_iou(m, m.gauss_dyn, d.times[i], d.K[i], d.w2c[i], d.width, d.height,
                                   _gt_mask(scene, prep, i)))
    assert min(ious) >= 0.6, ious


def test_nodes_on_the_moving_objects_move_with_them(trained_large):
    """Dynamic nodes' trained paths: at least 2x closer to the nearest ground-truth point's
    path than standing still would be."""
    scene, prep, trainer = trained_large
    m, d = trainer.model, trainer.data
    gt = np.load(scene / "gt" / "trajectories.npz")
    pts, dyn = gt["points"], gt["is_dynamic"]  # [M, F, 3]
    times = np.sort(prep.times[prep.train_idx])
    frames = np.rint(times * (pts.shape[1] - 1)).astype(int)  # GT frame f is at time f / (F - 1)
    with torch.no_grad():
        pos, _ = m.node_states(times.tolist(), torch.nonzero(m.node_dyn).squeeze(1))  # [S, T, 3]
    pos = pos.numpy()
    moving = pts[dyn][:, frames]  # [Md, T, 3]
    # pair each dynamic node with the GT point nearest to it at the canonical time
    tc = len(times) // 2
    dist = np.linalg.norm(pos[:, None, tc] - moving[None, :, tc], axis=-1)
    near = dist.argmin(1)
    ok = dist.min(1) < 0.15  # nodes that sit on a moving object
    assert ok.sum() >= 10
    err = np.linalg.norm(pos[ok] - moving[near[ok]], axis=-1).mean()
    still = np.linalg.norm(moving[near[ok]][:, tc:tc + 1] - moving[near[ok]], axis=-1).mean()
    assert err < 0.5 * still, (err, still)
