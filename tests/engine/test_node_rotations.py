"""Node rotations from lifted tracks: the weighted rigid fit, the per-node key fit and the
re-basing to the canonical time."""

import pytest
import torch

from engine.geometry.quaternion import quat_from_axis_angle, quat_to_matrix
from engine.geometry.rigid import weighted_kabsch
from engine.nodes.trajectory import fit_node_rotations, fit_node_trajectories, node_frame_rotations
from engine.train.init_model import canonical_rotations


def _rot_z(angle):
    return quat_to_matrix(quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]), torch.tensor(float(angle))))


def _angle_between(qa, qb):
    """Rotation angle (radians) between unit quaternions ``[..., 4]``."""
    return 2 * torch.acos((qa * qb).sum(-1).abs().clamp(max=1.0))


def test_weighted_kabsch_recovers_rotation_and_ignores_zero_weight_outliers():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 12, 3, generator=g, dtype=torch.float64)
    R_true = torch.stack([_rot_z(0.7), _rot_z(-2.5)]).double()
    t_true = torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5]], dtype=torch.float64)
    dst = torch.einsum("bij,bpj->bpi", R_true, src) + t_true[:, None]
    dst[:, :2] += 5.0  # outliers ...
    w = torch.ones(2, 12, dtype=torch.float64)
    w[:, :2] = 0  # ... with zero weight
    dst[0, 5] = float("nan")  # a missing sample
    R, t, ok = weighted_kabsch(src, dst, w)
    assert ok.all()
    assert torch.allclose(R, R_true, atol=1e-7) and torch.allclose(t, t_true, atol=1e-7)  # float64 SVD
    assert torch.allclose(torch.linalg.det(R), torch.ones(2, dtype=torch.float64))


def test_weighted_kabsch_refuses_too_few_or_collinear_points():
    line = torch.linspace(0, 1, 6).unsqueeze(1) * torch.tensor([[1.0, 0.0, 0.0]])
    R, t, ok = weighted_kabsch(line, line @ _rot_z(0.3).T, torch.ones(6))
    assert not ok and torch.equal(R, torch.eye(3))
    pts = torch.randn(2, 3)
    assert not weighted_kabsch(pts, pts + 1, torch.ones(2))[2]


def _spinning_tracks(num_frames=21, omega=0.15, centre=(0.0, 0.0, 5.0), n_pts=40):
    """Points on a disc turning about z at ``omega`` rad/frame while drifting in x."""
    g = torch.Generator().manual_seed(1)
    local = torch.randn(n_pts, 3, generator=g) * torch.tensor([0.3, 0.3, 0.05])
    frames = []
    for f in range(num_frames):
        R = _rot_z(omega * f)
        frames.append(local @ R.T + torch.tensor(centre) + torch.tensor([0.02 * f, 0.0, 0.0]))
    return torch.stack(frames, 1), local  # [P, F, 3]


def test_fit_node_rotations_follow_a_spinning_part_across_half_a_turn():
    F, omega = 21, 0.15  # 3 rad over the clip: past the +-pi/2 where a naive sign choice flips
    tracks3d, _ = _spinning_tracks(F, omega)
    times = torch.linspace(0, 1, F)
    key_times = torch.linspace(0, 1, 11)  # keys on frames 0, 2, 4, ...
    source = torch.tensor([10])
    centers = tracks3d[:1, 10].clone()  # a node on the disc, seen at frame 10
    R, ok = node_frame_rotations(centers, source, torch.tensor([1.0]), tracks3d, k_tracks=12)
    q, rotated = fit_node_rotations(R, ok, times, key_times)
    assert rotated.all() and q.shape == (1, 11, 4)
    want = torch.stack([quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]), torch.tensor(omega * (2 * k - 10)))
                        for k in range(11)])
    err = _angle_between(q[0], want)
    # interior keys average a symmetric window (exact for a steady turn); the end keys see
    # one side only and lag by a third of a frame's turn
    assert err[1:-1].max() < 1e-3, err
    assert err[[0, -1]].max() < omega / 2, err
    # sign-continuous keys: neighbours never point to opposite hemispheres
    assert ((q[0, 1:] * q[0, :-1]).sum(-1) > 0).all()


def test_fit_node_rotations_keep_identity_without_support_and_fill_gaps():
    tracks3d, _ = _spinning_tracks(11, 0.1)
    times = torch.linspace(0, 1, 11)
    key_times = torch.linspace(0, 1, 6)
    tracks3d[:, 6:9] = float("nan")  # the tracks vanish for three frames
    far = torch.tensor([[100.0, 0.0, 5.0]])  # a node with no track in reach
    centers = torch.cat([tracks3d[:1, 0], far])
    R, ok = node_frame_rotations(centers, torch.tensor([0, 0]), torch.tensor([1.0, 1.0]), tracks3d, k_tracks=12)
    assert ok[0, :6].all() and not ok[0, 6:9].any() and not ok[1].any()
    q, rotated = fit_node_rotations(R, ok, times, key_times)
    assert rotated.tolist() == [True, False]
    assert torch.equal(q[1], torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(6, 4))
    assert torch.isfinite(q).all()
    # keys 3 and 4 (frames 6 and 8) lost their own frames: each is the one fitted frame in
    # its hat window (frame 5: 0.5 rad, frame 9: 0.9 rad), not a blend with missing ones
    one = torch.tensor([1.0, 0.0, 0.0, 0.0])
    assert abs(float(_angle_between(q[0, 3], one)) - 0.5) < 1e-3
    assert abs(float(_angle_between(q[0, 4], one)) - 0.9) < 1e-3


class _Data:
    def __init__(self, times):
        self.times = times
        self.train_idx = torch.arange(len(times))


def test_canonical_rotations_are_identity_at_the_canonical_time_and_keep_relative_motion():
    key_times = torch.linspace(0, 1, 5)
    angles = torch.tensor([0.0, 0.4, 0.8, 1.2, 1.6])
    keys = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]).expand(5, 3), angles).unsqueeze(0)  # [1, 5, 4]
    data = _Data(torch.linspace(0, 1, 9))  # t_c = 0.5 = key 2
    out = canonical_rotations(data, key_times, keys, 0.5)
    assert _angle_between(out[0, 2], torch.tensor([1.0, 0.0, 0.0, 0.0])) < 1e-5
    want = quat_from_axis_angle(torch.tensor([0.0, 0.0, 1.0]).expand(5, 3), angles - 0.8)
    assert (_angle_between(out[0], want) < 1e-5).all()
    ident = torch.zeros(3, 5, 4)
    ident[..., 0] = 1
    assert torch.allclose(canonical_rotations(data, key_times, ident, 0.5), ident)


def test_node_rotations_reach_the_node_set_and_identity_option_keeps_the_papers_start():
    from engine.nodes import NodeInitConfig, assemble_nodeset

    tracks3d, _ = _spinning_tracks(11, 0.1)
    times = torch.linspace(0, 1, 11)
    centers = tracks3d[:3, 5].clone()
    src_time = torch.full((3,), 0.5)
    p_dyn = torch.ones(3)
    base = dict(num_keys=6, k_tracks=12, graph_k=2, radius_k=2)
    turned = assemble_nodeset(centers, src_time, p_dyn, tracks3d, times, NodeInitConfig(**base))
    still = assemble_nodeset(centers, src_time, p_dyn, tracks3d, times, NodeInitConfig(rotations="identity", **base))
    key1_angle = _angle_between(turned.rot_keys[:, 1], torch.tensor([1.0, 0.0, 0.0, 0.0]))
    assert torch.allclose(key1_angle, torch.full((3,), 0.3), atol=1e-3)  # key 1 = frame 2, 3 frames before
    assert torch.equal(still.rot_keys[..., 0], torch.ones(3, 6))
    with pytest.raises(ValueError, match="rotation init"):
        assemble_nodeset(centers, src_time, p_dyn, tracks3d, times, NodeInitConfig(rotations="spin", **base))
    assert float(turned.rot_tangents.abs().sum()) > 0 and not still.rot_tangents.any()  # Catmull-Rom of the keys


def test_turned_offsets_put_an_off_centre_node_on_its_circle():
    """A node off its tracks' centroid turns with them: the translation vote alone would
    keep it on a straight line beside the part."""
    F, omega = 21, 0.15
    tracks3d, _ = _spinning_tracks(F, omega)
    times = torch.linspace(0, 1, F)
    key_times = torch.linspace(0, 1, 21)  # a key per frame: the spline itself adds no error
    centre0 = torch.tensor([0.0, 0.0, 5.0])
    node = centre0 + torch.tensor([0.25, 0.0, 0.0])  # inside the disc, off its centre
    source, radii = torch.tensor([0]), torch.tensor([1.0])
    R, ok = node_frame_rotations(node[None], source, radii, tracks3d, k_tracks=40)
    want = torch.stack([centre0 + torch.tensor([0.02 * f, 0.0, 0.0]) + _rot_z(omega * f) @ (node - centre0)
                        for f in range(F)])
    kw = dict(k_tracks=40, support_radius=10.0, smoothness=0.0, fallback="static", max_residual_ratio=None)
    turned, _, _ = fit_node_trajectories(node[None], source, radii, tracks3d, times, key_times, frame_rot=R, **kw)
    shifted, _, _ = fit_node_trajectories(node[None], source, radii, tracks3d, times, key_times, **kw)
    assert (turned[0] - want).norm(dim=-1).max() < 1e-4
    assert (shifted[0] - want).norm(dim=-1).max() > 0.2  # the centroid's path, not the node's


def test_translation_only_tracks_are_left_out_of_the_node_rotations():
    """Tracks that follow their object's centre alone (blob tracks) sit beside a spinning
    part's own tracks; with them in the fit the nodes would turn less, without them as much
    as the part."""
    from engine.nodes import NodeInitConfig, assemble_nodeset

    spin, _ = _spinning_tracks(11, 0.1)
    centre = spin.mean(0, keepdim=True)  # [1, F, 3]: the part's centre path (a drift in x)
    shifted = spin[:, 5:6] + (centre - centre[:, 5:6])  # each point kept at its frame-5 place
    tracks3d = torch.cat([spin, shifted, shifted])  # twice as many translation-only tracks
    turns = torch.cat([torch.ones(len(spin), dtype=torch.bool), torch.zeros(2 * len(spin), dtype=torch.bool)])
    times = torch.linspace(0, 1, 11)
    centers = spin[:3, 5].clone()
    args = (centers, torch.full((3,), 0.5), torch.ones(3), tracks3d, times,
            NodeInitConfig(num_keys=6, k_tracks=12, graph_k=2, radius_k=2))
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0])
    with_turns = _angle_between(assemble_nodeset(*args, turns).rot_keys[:, 1], ident)
    mixed = _angle_between(assemble_nodeset(*args).rot_keys[:, 1], ident)
    assert torch.allclose(with_turns, torch.full((3,), 0.3), atol=1e-3)
    assert bool((mixed < 0.2).all()), mixed
