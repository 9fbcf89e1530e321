"""A tiny procedural dynamic scene for training tests (no bpy, seconds to build).

A textured wall of Gaussians plus a blob that translates across it, seen by a camera
that sways; every 4th frame is a held-out view from a rigidly offset camera. Ground
truth images, depth, dynamic masks and 2D tracks come from rendering the true scene.
"""

from __future__ import annotations

import numpy as np
import torch

from engine import bundle as B
from engine.bench.train import render_observation
from engine.geometry.camera import intrinsics, look_at, project
from engine.train.data import TrainingData


def blob_offset(t: torch.Tensor) -> torch.Tensor:
    """True translation of the moving blob at times ``t [T]`` -> ``[T, 3]``."""
    return torch.stack([-0.6 + 1.2 * t, torch.zeros_like(t), 0.25 * torch.sin(np.pi * t)], -1)


def make_scene(frames: int = 16, width: int = 64, height: int = 48, seed: int = 0, fixed_camera: bool = False):
    """A textured wall and a red blob moving across it, seen by a swaying camera (the
    held-out frames half a unit to the side), or with ``fixed_camera`` from one place."""
    g = torch.Generator().manual_seed(seed)
    nw, nb = 2500, 400
    wall = torch.stack([torch.rand(nw, generator=g) * 4 - 2, torch.full((nw,), 1.5),
                        torch.rand(nw, generator=g) * 3 - 1.5], -1)
    # a colour texture: smooth stripes + noise, so photometric error is informative
    wall_col = torch.stack([0.5 + 0.4 * torch.sin(3 * wall[:, 0]), 0.5 + 0.4 * torch.cos(2 * wall[:, 2]),
                            torch.rand(nw, generator=g) * 0.5 + 0.25], -1)
    blob = torch.randn(nb, 3, generator=g) * 0.18
    blob_col = torch.tensor([0.9, 0.2, 0.1]).expand(nb, 3) + 0.05 * torch.randn(nb, 3, generator=g)
    times = torch.linspace(0, 1, frames)
    K = intrinsics(0.9 * width, 0.9 * width, width / 2, height / 2, dtype=torch.float32)
    w2cs, imgs, depths, fgs = [], [], [], []
    val = torch.arange(frames) % 4 == 3
    for f in range(frames):
        t = times[f]
        sway = 0.0 if fixed_camera else 0.6 * torch.sin(2 * np.pi * t)
        eye = torch.tensor([float(sway) + (0.5 if val[f] and not fixed_camera else 0.0), -4.0, 0.3])
        w2c = look_at(eye, torch.tensor([0.0, 1.0, 0.0])).float()
        means = torch.cat([wall, blob + blob_offset(t.reshape(1))[0]])
        cols = torch.cat([wall_col, blob_col]).clamp(0, 1)
        n = len(means)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1
        scales = torch.cat([torch.full((nw, 3), 0.05), torch.full((nb, 3), 0.06)])
        op = torch.full((n,), 0.9)
        dyn = torch.cat([torch.zeros(nw, 3), torch.ones(nb, 3)])
        img, dep, fg = render_observation(means, quats, scales, op, cols, dyn, w2c, K, width, height)
        w2cs.append(w2c)
        imgs.append(img)
        depths.append(dep)
        fgs.append(fg)
    w2c = torch.stack(w2cs)
    # tracks: true surface points (wall subset + blob subset) projected into every frame
    pts_static = wall[:200]
    pts_dyn = blob[:100]
    xy = []
    for f in range(frames):
        pts = torch.cat([pts_static, pts_dyn + blob_offset(times[f:f + 1])[0]])
        uv, _ = project(K, w2c[f], pts)
        xy.append(uv)
    tracks = torch.stack(xy, 1)
    vis = (tracks[..., 0] > 0) & (tracks[..., 0] < width) & (tracks[..., 1] > 0) & (tracks[..., 1] < height)
    idx = torch.arange(frames)
    data = TrainingData(images=torch.stack(imgs), K=K.expand(frames, 3, 3).clone(), w2c=w2c, times=times,
                        train_idx=idx[~val], val_idx=idx[val], depth=torch.stack(depths), fg=torch.stack(fgs),
                        tracks_xy=tracks, tracks_vis=vis, extent=2.0, frame_numbers=idx + 1, fps=24.0)
    return data.validate(), {"wall": wall, "blob": blob}


def make_nodes(truth, key_count: int = 5, moving: bool = True) -> B.NodeArrays:
    """Nodes on a wall grid (static) and in the blob (following the true motion when
    ``moving``, as a perfect track-lifted initialisation would)."""
    gx, gz = torch.meshgrid(torch.linspace(-1.8, 1.8, 5), torch.linspace(-1.3, 1.3, 4), indexing="ij")
    wall_nodes = torch.stack([gx.flatten(), torch.full((20,), 1.5), gz.flatten()], -1)
    blob_nodes = torch.tensor([[0.0, 0, 0], [0.12, 0, 0], [-0.12, 0, 0], [0, 0, 0.12], [0, 0, -0.12]])
    centers = torch.cat([wall_nodes, blob_nodes])
    kt = torch.linspace(0, 1, key_count)
    pos = centers[:, None, :].expand(-1, key_count, 3).clone()
    if moving:
        pos[20:] += blob_offset(kt)[None]
    from engine.geometry.hermite import catmull_rom_tangents

    rot = torch.zeros(len(centers), key_count, 4)
    rot[..., 0] = 1
    radii = torch.cat([torch.full((20,), 0.6), torch.full((5,), 0.15)])
    graph = torch.cdist(centers, centers).topk(4, largest=False).indices[:, 1:]
    p_dyn = torch.cat([torch.zeros(20), torch.ones(5)])
    return B.NodeArrays(centers=centers.numpy(), radii=radii.numpy(), key_times=kt.numpy(), pos_keys=pos.numpy(),
                        pos_tangents=catmull_rom_tangents(kt, pos).numpy(), rot_keys=rot.numpy(),
                        rot_tangents=np.zeros_like(rot.numpy()), p_dyn=p_dyn.numpy(), graph_idx=graph.numpy())


def one_step(out_dir, data, truth, cfg, jitter_keys: float = 0.0):
    """A Trainer on ``data`` / ``make_nodes(truth)`` writing under ``out_dir``, its loss at
    step 5 on the second training frame, backward done; returns ``(trainer, metrics)``.
    ``jitter_keys``: add this much seeded noise to the node position keys first (so the
    motion terms are live). For tests that compare one step with a switch on and off."""
    from engine.train import trainer as T

    tr = T.Trainer(data, make_nodes(truth), cfg, out_dir)
    if jitter_keys:
        with torch.no_grad():
            tr.model.pos_keys.add_(jitter_keys * torch.randn(tr.model.pos_keys.shape,
                                                             generator=torch.Generator().manual_seed(0)))
    tr.step = 5
    loss, metrics, _, _ = tr._loss(int(data.train_idx[1]))
    loss.backward()
    return tr, metrics
