"""MANI compression: per-voxel fractions, similarity priority, fg adaptivity, budget, seed."""

import math

import torch

from engine.nodes.mani import ManiConfig, mani_compress


def _clusters(num_vox, per_vox, dim=16, seed=0, spacing=10.0):
    """Tight clusters centred in unit voxels ``spacing`` apart along x; returns pos, tok, vox, v_init."""
    g = torch.Generator().manual_seed(seed)
    vox = torch.arange(num_vox).repeat_interleave(per_vox)
    pos = torch.stack([vox * spacing + 0.5, torch.full_like(vox, 0.5, dtype=torch.float32) * 1.0,
                       torch.full((vox.shape[0],), 0.5)], 1).float()
    pos = pos + 0.01 * torch.randn(pos.shape, generator=g)
    tok = torch.randn(vox.shape[0], dim, generator=g)
    diag = float((pos.max(0).values - pos.min(0).values).norm())
    return pos, tok, vox, 1.0 / diag  # v_init so that one voxel = 1 world unit


def test_merges_exactly_requested_fraction_per_voxel():
    pos, tok, vox, v = _clusters(num_vox=6, per_vox=9)  # |A| = 5, |B| = 4 per voxel
    for r in (0.2, 0.4, 0.6, 1.0):
        cfg = ManiConfig(budget=0, v_init=v, dv=0.0, r_min=r, r_max=r, max_iters=1, eta=0.0)
        res = mani_compress(pos, tok, torch.zeros(len(pos)), cfg)
        nodes_vox = torch.zeros(res.positions.shape[0], dtype=torch.long)
        nodes_vox[res.assignment] = vox  # a node's candidates all share its voxel
        survivors_per_voxel = torch.bincount(nodes_vox, minlength=6)
        expected = 9 - math.floor(r * 5 + 1e-6)
        assert survivors_per_voxel.tolist() == [expected] * 6, (r, survivors_per_voxel)
        # candidates never leave their voxel
        assert torch.all(nodes_vox[res.assignment] == vox)


def test_identical_tokens_in_static_voxel_merge_first():
    g = torch.Generator().manual_seed(1)
    num_vox = 10
    pos, _, vox, v = _clusters(num_vox=num_vox, per_vox=2)
    tok = torch.randn(2 * num_vox, 32, generator=g)  # random pairs: cos ≈ 0
    tok[7] = tok[6]  # voxel 3 holds two identical tokens
    # r = 1 everywhere: every voxel offers its pair; the budget cap must pick the best one.
    cfg = ManiConfig(budget=2 * num_vox - 1, v_init=v, dv=0.0, eta=0.5, r_min=1.0, r_max=1.0)
    res = mani_compress(pos, tok, torch.zeros(2 * num_vox), cfg)
    assert res.positions.shape[0] == 2 * num_vox - 1
    assert res.assignment[6] == res.assignment[7]
    assert len(torch.unique(res.assignment[torch.arange(2 * num_vox) // 2 != 3])) == 2 * num_vox - 2


def test_foreground_voxel_keeps_more_nodes_than_background():
    pos, tok, vox, v = _clusters(num_vox=2, per_vox=32)
    tok[32:] = tok[:32]  # identical token content in both voxels
    fg = (vox == 1).float()
    cfg = ManiConfig(budget=0, v_init=v, dv=0.0, max_iters=1)
    res = mani_compress(pos, tok, fg, cfg)
    nodes_vox = torch.zeros(res.positions.shape[0], dtype=torch.long)
    nodes_vox[res.assignment] = vox
    counts = torch.bincount(nodes_vox, minlength=2)
    assert counts[1] > counts[0], counts
    assert res.p_dyn[nodes_vox == 1].min() > res.p_dyn[nodes_vox == 0].max()


def test_terminates_exactly_at_budget_and_conserves_mass():
    g = torch.Generator().manual_seed(3)
    pos = torch.rand(5000, 3, generator=g)
    tok = torch.randn(5000, 24, generator=g)
    fg = (pos[:, 0] < 0.3).float()
    res = mani_compress(pos, tok, fg, ManiConfig(budget=300, merge="mean"))
    assert res.positions.shape[0] == 300
    assert res.history[-1] == 300 and all(a >= b for a, b in zip(res.history, res.history[1:]))
    assert torch.isclose(res.sizes.sum(), torch.tensor(5000.0))
    assert torch.equal(torch.unique(res.assignment), torch.arange(300))
    # merge="mean": merged positions are size-weighted means of their candidates
    mean = torch.zeros(300, 3).index_add_(0, res.assignment, pos) / res.sizes.unsqueeze(1)
    assert torch.allclose(mean, res.positions, atol=1e-4)
    # dynamic region gets denser nodes than the static one
    dyn_nodes = (res.positions[:, 0] < 0.3).float().mean()
    assert dyn_nodes > 0.3 * 1.5


def test_deterministic_under_seed():
    g = torch.Generator().manual_seed(4)
    pos, tok, fg = torch.rand(3000, 3, generator=g), torch.randn(3000, 8, generator=g), torch.rand(3000, generator=g)
    a = mani_compress(pos, tok, fg, ManiConfig(budget=200, seed=7))
    b = mani_compress(pos, tok, fg, ManiConfig(budget=200, seed=7))
    c = mani_compress(pos, tok, fg, ManiConfig(budget=200, seed=8))
    assert torch.equal(a.assignment, b.assignment) and torch.equal(a.positions, b.positions)
    assert not torch.equal(a.assignment, c.assignment)


def test_matching_with_norms_equals_matching_normalised_tokens():
    from engine.nodes.mani import match_within_voxels, voxel_ids

    g = torch.Generator().manual_seed(3)
    pos = torch.rand(500, 3, generator=g)
    tok = torch.randn(500, 16, generator=g) * torch.rand(500, 1, generator=g) * 5  # token sums, varied scale
    fg = torch.rand(500, generator=g)
    vox, nv = voxel_ids(pos, 0.3)
    a1, b1, s1 = match_within_voxels(torch.nn.functional.normalize(tok, dim=1), fg, vox, nv, 0.5,
                                     torch.Generator().manual_seed(0))
    a2, b2, s2 = match_within_voxels(tok, fg, vox, nv, 0.5, torch.Generator().manual_seed(0), norms=tok.norm(dim=1))
    assert torch.equal(a1, a2) and torch.equal(b1, b2)
    assert torch.allclose(s1, s2, atol=1e-5)


def test_mani_does_not_modify_its_inputs():
    g = torch.Generator().manual_seed(4)
    pos, tok, fg = torch.rand(400, 3, generator=g), torch.randn(400, 8, generator=g), torch.rand(400, generator=g)
    copies = [x.clone() for x in (pos, tok, fg)]
    mani_compress(pos, tok, fg, ManiConfig(budget=50))
    assert all(torch.equal(x, c) for x, c in zip((pos, tok, fg), copies))


def test_medoid_and_representative_nodes_are_member_candidates():
    g = torch.Generator().manual_seed(5)
    pos, tok, fg = torch.rand(3000, 3, generator=g), torch.randn(3000, 8, generator=g), torch.rand(3000, generator=g)
    time = torch.rand(3000, generator=g)
    mean = mani_compress(pos, tok, fg, ManiConfig(budget=200, merge="mean"), time=time)
    for merge in ("medoid", "representative"):
        res = mani_compress(pos, tok, fg, ManiConfig(budget=200, merge=merge), time=time)
        if merge == "medoid":
            # medoids are picked after the clustering: the same clusters as "mean"
            assert torch.equal(res.assignment, mean.assignment)
        else:
            # the representative's position feeds the next iteration's voxels, so the
            # clusters differ from "mean"'s (it is a different algorithm, not a relabelling)
            assert not torch.equal(res.assignment, mean.assignment)
            assert int(res.assignment.max()) == 199 and len(torch.unique(res.assignment)) == 200
        d = (res.positions[res.assignment] - pos).norm(dim=1)  # [M] member to its node
        hit = torch.zeros(200, dtype=torch.bool).index_fill_(0, res.assignment[d < 1e-6], True)
        assert hit.all(), merge  # every node sits exactly on one of its own candidates
        member = res.assignment[d < 1e-6]  # ... and carries that candidate's source time
        assert torch.allclose(res.time[member], time[d < 1e-6])
    # medoid: the member nearest the cluster centroid
    med = mani_compress(pos, tok, fg, ManiConfig(budget=200), time=time)
    dc = (pos - mean.positions[med.assignment]).norm(dim=1)
    best = torch.full((200,), float("inf")).scatter_reduce(0, med.assignment, dc, "amin")
    assert torch.allclose((med.positions - mean.positions).norm(dim=1), best, atol=1e-6)


def test_moving_part_seen_at_two_times_keeps_nodes_on_the_part():
    """A thin bar back-projected at two keyframes, moved 3 widths between them, in one voxel:
    the centroid of a merged pair lies between the two bars (on the part at no time), the
    medoid on one of them, with that keyframe's time."""
    g = torch.Generator().manual_seed(6)
    n = 200
    y = torch.rand(2 * n, generator=g)
    x = torch.where(torch.arange(2 * n) < n, 0.0, 0.03) + 0.01 * torch.rand(2 * n, generator=g)  # width 0.01
    pos = torch.stack([x, y, torch.zeros(2 * n)], 1)
    time = (torch.arange(2 * n) >= n).float()
    tok = torch.ones(2 * n, 8) + 0.01 * torch.randn(2 * n, 8, generator=g)  # same part: same token
    fg = torch.ones(2 * n)

    def on_bar(res):
        bar0 = (res.positions[:, 0] <= 0.01 + 1e-6) & (res.time == 0)
        bar1 = (res.positions[:, 0] >= 0.03 - 1e-6) & (res.time == 1)
        return (bar0 | bar1).float().mean()

    cfg = dict(budget=40, v_init=0.1, dv=0.05)
    assert on_bar(mani_compress(pos, tok, fg, ManiConfig(merge="mean", **cfg), time=time)) < 0.9
    assert on_bar(mani_compress(pos, tok, fg, ManiConfig(**cfg), time=time)) == 1.0
    assert on_bar(mani_compress(pos, tok, fg, ManiConfig(merge="representative", **cfg), time=time)) == 1.0


def test_unknown_merge_mode_is_refused():
    import pytest

    with pytest.raises(ValueError, match="merge"):
        mani_compress(torch.rand(10, 3), torch.randn(10, 4), torch.zeros(10), ManiConfig(budget=5, merge="centre"))
