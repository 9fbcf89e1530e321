"""The track term lifts a track that carries its own depth at that depth, not the depth map's."""

import dataclasses

import torch

from engine.geometry.camera import world_to_camera
from engine.train.config import preset_config
from engine.train.trainer import Trainer

from .synthetic_training import blob_offset, make_nodes, make_scene


def _lifted_depth_at_first_frame(trainer, data):
    """Camera depth of each lifted track point, deformed back to its first supervised frame,
    for the tracks whose first supervised frame is frame 0: ``(ids [P], depth [P])``."""
    m, o = trainer.model, trainer.objective
    first = torch.argmax(o.track_vis[o.track_ids].to(torch.int8), dim=1)
    sel = torch.nonzero(first == 0).squeeze(1)
    with torch.no_grad():
        x = m.deform_points(o.track_canon[sel], o.track_idx[sel], o.track_w[sel], float(data.times[0]))
    return o.track_ids[sel], world_to_camera(data.w2c[0], x)[:, 2]


def test_tracks_with_their_own_depth_are_lifted_there_where_the_map_sees_the_wall(tmp_path):
    data, truth = make_scene()
    # the failure the hinge tracks meet: the depth map holds the background behind the moving blob
    wall_depth = data.depth.clone()
    moving = data.fg >= 0.5
    wall_depth[moving] = data.depth[~moving & (data.depth > 0)].median()
    # the moving tracks (rows 200..299 of make_scene) know their true camera depth
    f = data.num_frames
    blob = truth["blob"][:100]
    world = blob[:, None] + blob_offset(data.times)[None]  # [100, F, 3]
    true_z = world_to_camera(data.w2c[None], world)[..., 2]  # [100, F]
    own = torch.full((data.tracks_xy.shape[0], f), float("nan"))
    own[200:300] = true_z
    cfg = preset_config("preview", steps=1, gaussians_per_frame=400, init_keyframes=4, num_nodes=25,
                        checkpoint_every=0, warmup_static_steps=0)
    runs = {}
    for name, tracks_depth in (("map", None), ("own", own)):
        d = dataclasses.replace(data, depth=wall_depth, tracks_depth=tracks_depth)
        trainer = Trainer(d, make_nodes(truth), cfg, tmp_path / name)
        runs[name] = _lifted_depth_at_first_frame(trainer, d)
    ids, z_own = runs["own"]
    ids_map, z_map = runs["map"]
    assert torch.equal(ids_map, ids)
    blob_rows = ids >= 200  # (a few wall tracks the blob passes count as moving too)
    assert int(blob_rows.sum()) >= 50
    truth_z = true_z[ids[blob_rows] - 200, 0]
    assert float(((z_own[blob_rows] - truth_z).abs() / truth_z).max()) < 0.02
    # without it the same tracks sit on the wall behind
    assert float(((z_map[blob_rows] - truth_z) / truth_z).median()) > 0.3
    # tracks without a depth of their own are lifted from the map either way
    assert torch.allclose(z_own[~blob_rows], z_map[~blob_rows])
