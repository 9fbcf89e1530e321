"""Hinge tracks (engine.priors.hinge_tracks): long tracks on a body that turns about a hinge,
followed along its rings from the moving pixels alone."""

from __future__ import annotations

import numpy as np
import pytest

from engine.priors.hinge import Hinges, find_hinges
from engine.priors.hinge_tracks import hinge_tracks
from ._swinging_rod import WALL, H, W, _cameras, _mask, _rod


def _project(K, w2c, points):
    """``points [F, P, 3]`` -> pixels ``[P, F, 2]``."""
    cam = np.einsum("fij,fpj->fpi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    uv = np.einsum("fij,fpj->fpi", K, cam)
    return (uv[..., :2] / uv[..., 2:]).transpose(1, 0, 2)


def test_tracks_follow_a_swinging_rod_through_the_clip():
    """Tracks seeded on the rod stay on the point they started from in every frame, the rod's
    pivot depth with them, where optical flow on a thin fast part lives a frame or two."""
    f = 24
    K, w2c = _cameras(f, travel=2.0)
    pivot = np.array([0.0, -0.6, 4.0])
    rod = _rod(f, pivot)
    dynamic = _mask(K, w2c, rod)
    hinges = find_hinges(np.full((f, H, W), WALL, np.float32), dynamic, K, w2c)
    assert len(hinges.points) >= 1
    tracks = hinge_tracks(hinges, dynamic, K, w2c)
    assert tracks is not None and len(tracks.xy) >= 100
    life = tracks.visible.sum(1)
    assert np.median(life) >= 0.8 * f
    truth = _project(K, w2c, rod)  # [200 rod points, F, 2]
    errors = []
    for p in range(len(tracks.xy)):  # test-side loop over a few hundred tracks
        q = tracks.query_frame[p]
        nearest = np.linalg.norm(truth[:, q] - tracks.xy[p, q], axis=1).argmin()
        seen = tracks.visible[p]
        errors.append(np.median(np.linalg.norm(tracks.xy[p, seen] - truth[nearest, seen], axis=1)))
    assert np.median(errors) < 2.0 and np.quantile(errors, 0.9) < 3.5  # the rod is 5 px wide
    # against standing still at the query frame's place: the rod swings +-0.7 rad
    still = [np.median(np.linalg.norm(truth[n, tracks.visible[p]] - truth[n, tracks.query_frame[p]], axis=-1))
             for p, n in ((p, np.linalg.norm(truth[:, tracks.query_frame[p]] - tracks.xy[p, tracks.query_frame[p]],
                                             axis=1).argmin()) for p in range(len(tracks.xy)))]
    assert np.median(still) > 5 * np.median(errors)
    assert np.allclose(tracks.depth[tracks.visible], 4.0, rtol=0.02)
    assert np.isnan(tracks.depth[~tracks.visible]).all()


def test_no_hinge_no_tracks():
    f = 12
    K, w2c = _cameras(f, travel=2.0)
    dynamic = _mask(K, w2c, _rod(f, np.array([0.0, -0.6, 4.0])))
    none = Hinges(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert hinge_tracks(none, dynamic, K, w2c) is None
    # a hinge off every moving blob holds nothing
    away = Hinges(np.array([[3.0, 2.0, 4.0]], np.float32), np.array([50]), np.array([6]))
    assert hinge_tracks(away, dynamic, K, w2c) is None


def test_a_band_whose_turn_disagrees_with_its_neighbours_is_cut():
    """The rigidity check: a ring that turns unlike the rings next to it (a part sliding along
    it, a cloth) ends there; rings that agree run on."""
    from engine.priors.hinge_tracks import _rigid, _run_through

    f = 10
    turn = np.linspace(0, 0.8, f)
    band = np.arange(7)
    ang = np.tile(turn, (7, 1)) + 0.02 * band[:, None]  # a rigid body: the bands turn together
    ang[3, 6:] += 0.5  # band 3 slides from frame 6 on
    ok = _run_through(_rigid(ang, band, ang[:, 0], tol=0.15), seed=0)
    assert ok[[0, 1, 2, 4, 5, 6]].all()
    assert ok[3, :6].all() and not ok[3, 6:].any()
    # a band with no neighbour has nothing to disagree with
    lone = _rigid(np.vstack([ang, ang[3]]), np.r_[band, 20], np.r_[ang[:, 0], ang[3, 0]], tol=0.15)
    assert lone[-1].all()
