"""A compact blob's turn (engine.priors.blob_turn): a rolling sphere's rotation from the flow's
tracks inside it, and blob tracks that turn with it."""

import numpy as np

from engine.priors.blob_tracks import blob_tracks
from engine.priors.blob_turn import _rotmat, _rotvec, sphere_points, step_turns, turn_path

F, H, W, R_PX = 24, 80, 160, 12.0
AXIS = np.array([0.3, 1.0, 0.4]) / np.linalg.norm([0.3, 1.0, 0.4])
STEP = np.radians(8.0)  # per frame, about an axis out of the image plane: points go round the back


def _centre(k):
    return np.array([30.0 + 3.5 * k, 40.0 + 0.5 * k])


def _ball(points=400, seed=0):
    """A ball of 12 px radius rolling right, turning 8 degrees a frame: its motion mask, a flat
    depth, each frame's rotation from frame 0 and the flow's tracks (unit-sphere points, seen
    while they face the camera)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    rot = np.stack([_rotmat(AXIS * STEP * k) for k in range(F)])  # [F, 3, 3]
    dynamic = np.zeros((F, H, W), np.float32)
    for k in range(F):
        c = _centre(k)
        dynamic[k][(xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= R_PX ** 2] = 1.0
    unit = rng.normal(size=(points, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    at = np.einsum("fij,pj->pfi", rot, unit)  # [P, F, 3]
    xy = np.stack([_centre(k) for k in range(F)])[None] + R_PX * at[..., :2]
    return dynamic, np.full((F, H, W), 5.0, np.float32), rot, xy.astype(np.float32), at[..., 2] < -0.1


def test_sphere_points_are_the_front_of_the_unit_sphere():
    s = sphere_points(np.array([[0.0, 0.0], [0.6, 0.0], [0.0, -0.8], [2.0, 0.0]]))
    assert np.allclose(np.linalg.norm(s, axis=1), 1.0) and (s[:, 2] <= 0).all()
    assert np.allclose(s[0], [0, 0, -1]) and np.isclose(s[1, 2], -0.8) and np.allclose(s[3], [1.0, 0.0, 0.0])  # clipped onto the outline
    v = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    assert np.allclose(_rotvec(_rotmat(v)), v)


def test_each_steps_turn_is_found_from_the_tracks_inside():
    dynamic, _, _, xy, vis = _ball()
    from scipy import ndimage

    labels = [ndimage.label(d >= 0.5)[0] for d in dynamic]
    centre = np.stack([_centre(k) for k in range(F)])
    steps, gain = step_turns(labels, np.ones(F, np.int64), centre, np.full(F, R_PX), np.ones(F, bool), xy, vis)
    assert np.isfinite(steps).all() and np.median(gain) > 10
    err = np.degrees(np.linalg.norm(steps - AXIS * STEP, axis=1))
    assert np.median(err) < 0.3 and err.max() < 1.0, err
    # composed over the clip: frame k turned k steps from frame 0
    path = turn_path(steps, 0, F - 1)
    expected = np.stack([_rotmat(AXIS * STEP * k) for k in range(F)])
    assert np.degrees(np.linalg.norm(_rotvec(np.einsum("fji,fjk->fik", expected, path)), axis=1)).max() < 2.0
    # steps without a fit take their neighbours' turn; none at all: the turn is unknown
    holed = steps.copy()
    holed[5:9] = np.nan
    assert np.allclose(turn_path(holed, 0, F - 1), path, atol=0.02)
    assert turn_path(np.full_like(steps, np.nan), 0, F - 1) is None
    # frames outside the path keep the identity
    part = turn_path(steps, 4, 10)
    assert np.allclose(part[:5], np.eye(3)) and np.allclose(part[12:], np.eye(3)) and not np.allclose(part[8], np.eye(3))


def test_blob_tracks_turn_with_the_ball():
    dynamic, depth, rot, xy, vis = _ball()
    centre = np.stack([_centre(k) for k in range(F)])

    def errors(tracks):
        """Each track against the ball point under its first seen pixel, turned with the ball (a
        seed near the outline is not seen at its own frame: it faces sideways)."""
        q = tracks.visible.argmax(1)
        seed = sphere_points((tracks.xy[np.arange(len(q)), q] - centre[q]) / R_PX)  # [P, 3] at frame q
        truth = np.einsum("fij,pkj,pk->pfi", rot, rot[q], seed)  # R(t) R(s)^T
        gt_xy = centre[None] + R_PX * truth[..., :2]
        return np.linalg.norm(tracks.xy - gt_xy, axis=-1)[tracks.visible], truth[..., 2][tracks.visible]

    turned = blob_tracks(dynamic, depth, flow_xy=xy, flow_vis=vis)
    moved = blob_tracks(dynamic, depth, flow_xy=xy, flow_vis=vis, turn=False)
    assert turned.translation_only is None and moved.translation_only.all()
    err_turned, facing = errors(turned)
    err_moved, _ = errors(moved)
    assert np.median(err_turned) < 0.5 and np.median(err_moved) > 4.0, (np.median(err_turned), np.median(err_moved))
    # a turned track is seen only while its point faces the camera, so it leaves and comes back
    assert (facing < 0).all() and (turned.visible.sum(1) < F).mean() > 0.5
    # at the blob's depth, or, given the focal length, at its point's depth on the sphere
    assert np.allclose(turned.depth[turned.visible], 5.0, rtol=1e-3)
    deep = blob_tracks(dynamic, depth, flow_xy=xy, flow_vis=vis, focal=np.full(F, 100.0))
    _, facing = errors(deep)
    r3d = R_PX * 5.0 / 100.0
    assert np.median(np.abs(deep.depth[deep.visible] - (5.0 + r3d * (facing + np.sqrt(0.5))))) < 0.02 * r3d


def test_a_blob_that_does_not_turn_keeps_the_translation():
    """The same ball sliding without turning, its flow's tracks off by 0.3 px of noise: the step
    fits are that noise (half a degree a step, which composed would walk the points off); they
    explain the tracks no better than no turn, so the path moves by its centroid alone."""
    dynamic, depth, _, _, _ = _ball()
    rng = np.random.default_rng(3)
    unit = rng.normal(size=(400, 3))
    unit = unit[unit[:, 2] < -0.1] / np.linalg.norm(unit[unit[:, 2] < -0.1], axis=1, keepdims=True)
    centre = np.stack([_centre(k) for k in range(F)])
    xy = (centre[None] + R_PX * unit[:, None, :2] + rng.normal(0, 0.3, (len(unit), F, 2))).astype(np.float32)
    vis = np.ones((len(unit), F), bool)
    from scipy import ndimage

    labels = [ndimage.label(d >= 0.5)[0] for d in dynamic]
    steps, gain = step_turns(labels, np.ones(F, np.int64), centre, np.full(F, R_PX), np.ones(F, bool), xy, vis)
    assert np.isfinite(steps).all() and np.median(gain) < 1.5
    assert turn_path(steps, 0, F - 1, gain) is None and turn_path(steps, 0, F - 1) is not None
    tracks = blob_tracks(dynamic, depth, flow_xy=xy, flow_vis=vis)
    assert tracks.translation_only.all()
