"""Blob tracks: long tracks on a compact moving blob, moved by its centroid's path."""

import numpy as np

from engine.priors.blob_tracks import blob_tracks
from engine.priors.tracks import Tracks, concat_tracks

F, H, W = 30, 90, 160


def _disc_centre(k):
    return np.array([20.0 + 4.0 * k, 30.0 + 1.0 * k])


def _scene(with_l=True, cross=False):
    """A disc rolling right (coming nearer: radius 8 -> 11 px, depth 5 -> 5 * 8/11), an
    L-shaped blob moving left (not compact), optionally a second disc crossing the first's
    path at frames 12-15 (merged blobs there)."""
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    dynamic = np.zeros((F, H, W), np.float32)
    depth = np.full((F, H, W), 20.0, np.float32)  # the wall behind
    for k in range(F):
        c = _disc_centre(k)
        r = 8.0 + 3.0 * k / (F - 1)
        disc = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= r * r
        dynamic[k][disc] = 1.0
        depth[k][disc] = 5.0 * 8.0 / r
        if with_l:
            x0 = 140 - 3 * k
            dynamic[k, 60:85, x0:x0 + 6] = 1.0
            dynamic[k, 79:85, x0:x0 + 20] = 1.0
        if cross and 12 <= k <= 15:
            dynamic[k][(xx - c[0] - 6) ** 2 + (yy - c[1]) ** 2 <= 100] = 1.0
    return dynamic, depth


def test_a_compact_blob_gets_tracks_that_follow_it_through_the_clip_and_a_non_compact_one_none():
    dynamic, depth = _scene()
    tr = blob_tracks(dynamic, depth)
    assert tr is not None and len(tr.xy) > 0
    assert tr.translation_only is not None and tr.translation_only.all()
    # every track starts on the disc (none on the L) and lives the whole clip
    q = tr.query_frame
    start = tr.xy[np.arange(len(q)), q]
    k = np.arange(F)
    centre = np.stack([_disc_centre(i) for i in k])
    assert np.all(np.linalg.norm(start - centre[q], axis=1) <= 11.5)
    assert np.median(tr.visible.sum(1)) == F
    # a track keeps its offset from the centre, scaled as the disc comes nearer
    off0 = start - centre[q]
    r = 8.0 + 3.0 * k / (F - 1)
    expected = centre[None] + off0[:, None] * (r[None, :] / r[q][:, None])[..., None]
    err = np.linalg.norm(tr.xy - expected, axis=-1)[tr.visible]
    assert np.median(err) < 0.6, np.median(err)
    # the depth is the disc's, smoothed
    z_true = 5.0 * 8.0 / r
    rel = np.abs(tr.depth - z_true[None]) / z_true[None]
    assert np.nanmax(rel[tr.visible]) < 0.03


def test_merged_frames_are_bridged_unseen_and_an_excluded_blob_gets_none():
    dynamic, depth = _scene(with_l=False, cross=True)
    tr = blob_tracks(dynamic, depth)
    assert tr is not None
    seen = tr.visible.any(0)
    # the frames where the second disc touches the first are not seen, the others are, by
    # the same tracks on both sides
    assert not seen[12:16].any() and seen[:12].all() and seen[16:].all()
    assert (tr.visible[:, 5] & tr.visible[:, 25]).sum() > 0
    # a point on the disc in every frame (a hinge's projection) takes it out
    uv = np.stack([_disc_centre(k) for k in range(F)])[:, None]
    assert blob_tracks(dynamic, depth, exclude_uv=uv) is None


def test_a_blob_whose_pixels_do_not_move_with_it_gets_none():
    """The flow's tracks inside the disc move with it: kept; standing still under it (a motion
    mask sliding over things that barely move): dropped."""
    dynamic, depth = _scene(with_l=False)
    k = np.arange(F)
    centre = np.stack([_disc_centre(i) for i in k])
    offsets = np.stack(np.meshgrid(np.linspace(-4, 4, 3), np.linspace(-4, 4, 3)), -1).reshape(-1, 2)
    moving = centre[None] + offsets[:, None]  # [9, F, 2]
    still = np.broadcast_to(centre[:1][None] + offsets[:, None], moving.shape)  # where the disc starts
    vis = np.ones((len(offsets), F), bool)
    assert blob_tracks(dynamic, depth, flow_xy=moving, flow_vis=vis) is not None
    # tracks that stay where the disc began are inside it only at the start: no step counts
    assert blob_tracks(dynamic, depth, flow_xy=still, flow_vis=vis) is None
    # a square mask sliding 3.5 px a frame over things that stand still (tracks on a grid)
    slide = np.zeros_like(dynamic)
    for i in range(F):
        x0 = int(5 + 3.5 * i)
        slide[i, 25:65, x0:x0 + 40] = 1.0
    grid = np.stack(np.meshgrid(np.arange(5, W, 8.0), np.arange(5, H, 8.0)), -1).reshape(-1, 2)
    grid_xy = np.broadcast_to(grid[:, None], (len(grid), F, 2))
    grid_vis = np.ones((len(grid), F), bool)
    assert blob_tracks(slide, depth) is not None  # compact, round, keeps its size
    assert blob_tracks(slide, depth, flow_xy=grid_xy, flow_vis=grid_vis) is None


def test_an_elongated_blob_gets_none():
    """A bar turning as it crosses (a rod, a limb): its centroid is not its points' path."""
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    dynamic = np.zeros((F, H, W), np.float32)
    for k in range(F):
        c, a = _disc_centre(k), 0.05 * k
        u = (xx - c[0]) * np.cos(a) + (yy - c[1]) * np.sin(a)
        v = -(xx - c[0]) * np.sin(a) + (yy - c[1]) * np.cos(a)
        dynamic[k][(np.abs(u) <= 15) & (np.abs(v) <= 3)] = 1.0
    assert blob_tracks(dynamic, np.full((F, H, W), 5.0, np.float32)) is None


def test_concat_marks_the_rows_of_tracks_without_the_flag_as_turning():
    a = Tracks(np.zeros((2, 3, 2), np.float32), np.ones((2, 3), bool), np.ones((2, 3), np.float32), np.zeros(2, np.int64))
    b = Tracks(np.zeros((1, 3, 2), np.float32), np.ones((1, 3), bool), np.ones((1, 3), np.float32), np.zeros(1, np.int64),
               translation_only=np.ones(1, bool))
    assert concat_tracks(a, b).translation_only.tolist() == [False, False, True]
    assert concat_tracks(a, a).translation_only is None
