"""A node's path past the end of its own tracks (engine/nodes/path_chain.py)."""

import torch

from engine.geometry.hermite import hermite_eval
from engine.nodes.path_chain import chain_node_paths
from engine.nodes.trajectory import fit_node_trajectories

FRAMES = 30


def _motion(f):
    """The object's translation at frame(s) ``f`` (a fast sweep with a turn back)."""
    f = torch.as_tensor(f, dtype=torch.float32)
    return torch.stack([0.08 * f, 0.4 * torch.sin(f / 4), 0.01 * f], -1)


def _short_tracks(per_group=12, life=6, every=4, seed=0):
    """Tracks on a translating cloud, each seen for ``life`` frames only: group g lives in
    frames [every*g, every*g + life), so consecutive groups overlap by life - every frames and
    no track spans more than a few frames (a fast part's flow tracks)."""
    g = torch.Generator().manual_seed(seed)
    groups = (FRAMES + every - 1) // every
    offsets = (torch.rand(groups * per_group, 3, generator=g) - 0.5) * 0.3
    tracks = offsets.unsqueeze(1) + _motion(torch.arange(FRAMES)).unsqueeze(0)  # [P, F, 3]
    start = (torch.arange(groups * per_group) // per_group) * every
    fr = torch.arange(FRAMES).unsqueeze(0)
    alive = (fr >= start.unsqueeze(1)) & (fr < start.unsqueeze(1) + life)
    return torch.where(alive.unsqueeze(-1), tracks, torch.full_like(tracks, float("nan")))


def test_a_node_is_carried_through_the_clip_by_tracks_that_live_a_few_frames():
    tracks = _short_tracks()
    src = 14
    centers = _motion(src).unsqueeze(0)  # on the cloud's centre at its source frame
    path, hops = chain_node_paths(centers, torch.tensor([src]), torch.tensor([0.2]), tracks)
    assert torch.isfinite(path).all()
    err = (path[0] - _motion(torch.arange(FRAMES))).norm(dim=-1)
    assert err.max() < 1e-3, err
    # the own set carries it near the source frame; each new set counts one hop more
    assert hops[0, src] == 0 and hops[0, src + 1] == 0
    assert hops[0, 0] >= 3 and hops[0, -1] >= 3
    assert (hops[0, :src].diff() <= 0).all() and (hops[0, src:].diff() >= 0).all()


def test_a_stray_track_does_not_carry_the_node_off():
    tracks = _short_tracks()
    tracks[30, :11] += torch.tensor([1.0, 0.0, 0.0])  # jumps onto another surface after the backward chain takes it (frame 12)
    src = 14
    path, _ = chain_node_paths(_motion(src).unsqueeze(0), torch.tensor([src]), torch.tensor([0.2]), tracks)
    err = (path[0] - _motion(torch.arange(FRAMES))).norm(dim=-1)
    assert err.max() < 0.03, err


def test_the_path_ends_where_no_track_is_around():
    tracks = _short_tracks()
    far = torch.tensor([[20.0, 20.0, 20.0]])
    path, _ = chain_node_paths(far, torch.tensor([5]), torch.tensor([0.2]), tracks)
    assert torch.isfinite(path[0, 5]).all() and torch.isfinite(path[0]).all(-1).sum() == 1


def test_the_spline_fit_follows_the_chained_path_where_its_own_tracks_end():
    tracks = _short_tracks()
    src = 14
    times = torch.linspace(0, 1, FRAMES)
    key_times = torch.linspace(0, 1, 16)
    centers = _motion(src).unsqueeze(0)
    truth = _motion(torch.arange(FRAMES))
    args = (centers, torch.tensor([src]), torch.tensor([0.2]), tracks, times, key_times)

    held_keys, held_tan, _ = fit_node_trajectories(*args, smoothness=1e-4)
    held = (hermite_eval(key_times, held_keys, held_tan, times)[0] - truth).norm(dim=-1)
    chained_keys, chained_tan, _ = fit_node_trajectories(*args, smoothness=1e-4, chain_hop_weight=0.5)
    chained = (hermite_eval(key_times, chained_keys, chained_tan, times)[0] - truth).norm(dim=-1)
    # its own tracks live frames 12..17: without the chain it stands still outside them
    assert held[0] > 0.5 and held[-1] > 0.5
    assert chained.max() < 0.05, chained
    # where its own tracks are seen, the chain changes nothing it needs to
    own = slice(13, 17)
    assert (chained[own] - held[own]).abs().max() < 0.02
