"""Hinges (engine.priors.hinge): a moving object that turns about a static point takes that
point's depth; a camera that does not translate, or an object whose motion mimics a static
one, gives no hinge."""

from __future__ import annotations

import numpy as np
import pytest

from engine.priors.hinge import find_hinges, hinge_depth
from engine.priors.tracks import Tracks

from ._swinging_rod import WALL, H, W, _cameras, _mask, _rod


def test_a_swinging_rod_takes_its_pivots_depth():
    f = 24
    K, w2c = _cameras(f, travel=2.0)
    pivot = np.array([0.0, -0.6, 4.0])
    dynamic = _mask(K, w2c, _rod(f, pivot))
    depth = np.full((f, H, W), WALL, np.float32)  # the prior sees only the wall behind the rod
    hinges = find_hinges(depth, dynamic, K, w2c)
    assert len(hinges.points) >= 1
    assert np.linalg.norm(hinges.points[0] - pivot) < 0.15
    painted, stats = hinge_depth(hinges, dynamic, K, w2c)
    on = dynamic >= 0.5
    share = np.isfinite(painted[on]).mean()
    assert share > 0.8 and stats["frames"] >= f // 2
    # the pivot's camera depth is 4 in every frame (the camera slides sideways)
    assert np.allclose(np.nanmedian(painted[on]), 4.0, rtol=0.05)
    assert not np.isfinite(painted[~on]).any()


def test_a_camera_that_does_not_translate_finds_no_hinge():
    f = 24
    K, w2c = _cameras(f, travel=0.0)
    dynamic = _mask(K, w2c, _rod(f, np.array([0.0, -0.6, 4.0])))
    depth = np.full((f, H, W), WALL, np.float32)
    assert len(find_hinges(depth, dynamic, K, w2c).points) == 0


def test_an_object_whose_motion_mimics_a_static_one_is_no_hinge():
    """A block gliding sideways at constant speed under a sliding camera projects exactly as a
    static block at another depth would: every point of it passes, so it is not a pivot."""
    f = 24
    K, w2c = _cameras(f, travel=2.0)
    gy, gx = np.mgrid[-0.3:0.3:20j, -0.3:0.3:20j]
    block = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 4.0)], -1)
    drift = np.linspace(-0.75, 0.75, f)[:, None] * np.array([-1.0, 0.0, 0.0])
    dynamic = _mask(K, w2c, block[None] + drift[:, None])
    depth = np.full((f, H, W), WALL, np.float32)
    assert len(find_hinges(depth, dynamic, K, w2c).points) == 0


def test_no_moving_pixels_no_hinge():
    K, w2c = _cameras(8, travel=1.0)
    hinges = find_hinges(np.full((8, H, W), WALL, np.float32), np.zeros((8, H, W), np.float32), K, w2c)
    assert len(hinges.points) == 0
    painted, stats = hinge_depth(hinges, np.zeros((8, H, W), np.float32), K, w2c)
    assert stats["hinges"] == 0 and not np.isfinite(painted).any()


def test_the_weight_free_depth_stage_gives_the_rod_its_pivots_depth():
    """engine.pipeline.prepare's stage (dynamic_depth.moving_object_depth): with hinges the
    rod's tracks and pixels take the pivot's depth; without, the wall's; the record says which."""
    from types import SimpleNamespace

    from engine.priors import PriorConfig
    from engine.geometry.camera import scene_extent
    from engine.priors.dynamic_depth import moving_object_depth
    from engine.protocol import Reporter

    f = 24
    K, w2c = _cameras(f, travel=2.0)
    rod = _rod(f, np.array([0.0, -0.6, 4.0]))
    dynamic = _mask(K, w2c, rod)
    cam = np.einsum("fij,fpj->fpi", w2c[:, :3, :3], rod[:, ::10]) + w2c[:, None, :3, 3]
    uv = np.einsum("fij,fpj->fpi", K, cam)
    xy = (uv[..., :2] / uv[..., 2:]).transpose(1, 0, 2).astype(np.float32)  # tracks on the rod [P, F, 2]
    vis = np.ones(xy.shape[:2], bool)
    tracks = Tracks(xy, vis, vis.astype(np.float32), np.zeros(len(xy), np.int64))
    pr = SimpleNamespace(depth=np.full((f, H, W), WALL, np.float32), dynamic=dynamic, tracks=tracks)
    on = dynamic >= 0.5
    with_hinges, more, record = moving_object_depth(pr, PriorConfig(), K, w2c, scene_extent(w2c, pr.depth),
                                                    Reporter(quiet=True))
    assert record["moving_objects"] == "contact" and record["hinges"] >= 1
    assert abs(np.median(with_hinges[on]) - 4.0) < 0.3
    # ... and long tracks along the rod's rings, appended with a depth of their own
    assert record["hinge_tracks"] > 0 and len(more.xy) == len(xy) + record["hinge_tracks"]
    assert np.isnan(more.depth[:len(xy)]).all() and np.nanmedian(more.depth[len(xy):]) == pytest.approx(4.0, rel=0.05)
    depth_only, same, record = moving_object_depth(pr, PriorConfig(hinges="depth"), K, w2c,
                                                   scene_extent(w2c, pr.depth), Reporter(quiet=True))
    assert record["hinges"] >= 1 and "hinge_tracks" not in record and same is tracks
    assert np.array_equal(depth_only, with_hinges)
    without, same, record = moving_object_depth(pr, PriorConfig(hinges="off"), K, w2c,
                                                scene_extent(w2c, pr.depth), Reporter(quiet=True))
    assert "hinges" not in record and np.median(without[on]) > 8.0 and same is tracks


def test_a_prior_that_already_sees_the_object_keeps_it():
    """Only parts the prior puts well behind the hinge are painted: where the prior already
    gives the rod about its pivot's depth (it saw the rod itself), nothing changes."""
    f = 24
    K, w2c = _cameras(f, travel=2.0)
    dynamic = _mask(K, w2c, _rod(f, np.array([0.0, -0.6, 4.0])))
    wall = np.full((f, H, W), WALL, np.float32)
    hinges = find_hinges(wall, dynamic, K, w2c)
    assert len(hinges.points) >= 1
    seen = np.where(dynamic >= 0.5, 4.4, WALL).astype(np.float32)
    painted, stats = hinge_depth(hinges, dynamic, K, w2c, depth=seen)
    assert stats["painted_px"] == 0 and not np.isfinite(painted).any()
    painted, stats = hinge_depth(hinges, dynamic, K, w2c, depth=wall)
    assert stats["painted_px"] > 0


def test_the_stage_skips_the_search_for_a_camera_that_does_not_translate():
    from types import SimpleNamespace

    from engine.priors import PriorConfig
    from engine.geometry.camera import scene_extent
    from engine.priors.dynamic_depth import moving_object_depth
    from engine.protocol import Reporter

    f = 12
    K, w2c = _cameras(f, travel=0.0)
    dynamic = _mask(K, w2c, _rod(f, np.array([0.0, -0.6, 4.0])))
    tracks = Tracks(np.zeros((0, f, 2), np.float32), np.zeros((0, f), bool), np.zeros((0, f), np.float32),
                    np.zeros(0, np.int64))
    pr = SimpleNamespace(depth=np.full((f, H, W), WALL, np.float32), dynamic=dynamic, tracks=tracks)
    _, _, record = moving_object_depth(pr, PriorConfig(), K, w2c, scene_extent(w2c, pr.depth),
                                       Reporter(quiet=True))
    # (the rod is elongated: no blob tracks either)
    assert record == {"moving_objects": "contact", "hinges": 0, "blob_tracks": 0}
