"""Motion-adaptive node initialisation (MANI): iterative voxel-local bipartite merging.

Each iteration (vectorised over all voxels):

1. voxelise at size ``v`` (``floor(x/v)`` → unique/inverse);
2. inside each voxel alternate nodes into A (even rank) and B (odd rank) after a seeded
   shuffle, so the split is random but reproducible;
3. match every A node to its most similar B node,
   ``sim = cos(z_i, z_j) − η · M_fg(i, j)`` with ``M_fg = max(m_i, m_j)`` — the *max*, so a
   pair is discouraged as soon as either side looks dynamic (a foreground node must not be
   absorbed into background);
4. per voxel ``p_dyn = σ(α·mean_m − β·mean_sim)`` over its nodes / matched pairs and
   ``r = r_min + (1 − p_dyn)(r_max − r_min)``;
5. merge, per voxel, the ``floor(r · |A_C|)`` most similar pairs (exactly that many; floor
   so a voxel never merges more than requested), ToMe-style: B absorbs all its merged A's
   with size-weighted means of token and prior; the merged node keeps the position and
   source time of one representative (``merge``, below);
6. grow ``v += Δv``; stop at the node budget. The iteration that would cross the budget
   keeps only the globally most similar of its selected pairs, landing exactly on it.

Voxel sizes are fractions of the candidates' bounding-box diagonal.

Where a merged node sits (``ManiConfig.merge``): the paper merges a pair "by retaining one
representative node". Candidates come from several keyframes, so on a moving object one
voxel can hold patches of the same part seen at different times; their size-weighted
centroid (``"mean"``, ToMe's choice for tokens) lies on the part at no time at all, and the
node's track-fitted trajectory and dynamic score then start off the surface. ``"medoid"``
(default) keeps, per final node, the member candidate nearest the cluster's centroid with
that candidate's source time: a real patch centre at a real frame, central in its cluster.
``"representative"`` keeps B's position and time at every merge (the literal ToMe keep).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class ManiConfig:
    """Parameters of :func:`mani_compress` (voxel sizes relative to the bbox diagonal)."""

    budget: int = 2000          #: target node count
    v_init: float = 0.01        #: initial voxel size / scene diagonal
    dv: float = 0.01            #: voxel growth per iteration / scene diagonal
    eta: float = 0.5            #: weight of the foreground term in sim
    alpha: float = 6.0          #: p_dyn weight of the mean foreground prior
    beta: float = 4.0           #: p_dyn weight of the mean matched similarity
    bias: float = 0.0           #: added inside the sigmoid (shifts p_dyn)
    r_min: float = 0.2          #: merge fraction of a fully dynamic voxel (0.3: 2.9× FPS density on the small synth scene)
    r_max: float = 0.4          #: merge fraction of a fully static voxel (1.0 starved the background: its
                                #: nodes' motion over time is worth ~0.5 dB there; see docs/benchmarks.md)
    max_iters: int = 500        #: safety stop
    seed: int = 0               #: A/B split shuffle seed
    merge: str = "medoid"       #: node position: "medoid" | "representative" | "mean" (module doc)


@dataclass
class ManiResult:
    """positions (N,3) and time (N,) source time of each node (per ``ManiConfig.merge``),
    tokens (N,D), fg (N,), sizes (N,) candidates per node, p_dyn (N,), assignment (M,) node
    index of every candidate, iterations int, history list of node counts per iteration."""

    positions: torch.Tensor
    tokens: torch.Tensor
    fg: torch.Tensor
    sizes: torch.Tensor
    time: torch.Tensor
    p_dyn: torch.Tensor
    assignment: torch.Tensor
    iterations: int
    history: list


def voxel_ids(positions: torch.Tensor, voxel: float) -> tuple[torch.Tensor, int]:
    """Dense voxel id ``(N,)`` long of every point and the number of occupied voxels."""
    key = torch.floor(positions / voxel).long()
    key = key - key.min(0).values
    ext = key.max(0).values + 1
    lin = (key[:, 0] * ext[1] + key[:, 1]) * ext[2] + key[:, 2]
    uniq, inv = torch.unique(lin, return_inverse=True)
    return inv, int(uniq.shape[0])


def rank_within_group(group_sorted: torch.Tensor, num_groups: int) -> torch.Tensor:
    """Rank of each element inside its group, for an array already sorted by group."""
    counts = torch.bincount(group_sorted, minlength=num_groups)
    first = torch.cumsum(counts, 0) - counts
    return torch.arange(group_sorted.shape[0]) - first[group_sorted]


def match_within_voxels(tokens_n: torch.Tensor, fg: torch.Tensor, vox: torch.Tensor, num_vox: int,
                        eta: float, gen: torch.Generator, norms: torch.Tensor | None = None):
    """Bipartite soft matching inside every voxel.

    Parameters
    ----------
    tokens_n : (N, D) unit-norm tokens, or any tokens with their norms in ``norms (N,)``
    (the cosine is then formed on the small per-voxel blocks, so the caller need not
    normalise all N × D tokens every iteration); fg : (N,); vox : (N,) voxel id.

    Returns
    -------
    a_idx : (P,) A nodes that have a B partner; b_idx : (P,) their best B; sim : (P,).
    """
    n = vox.shape[0]
    perm = torch.randperm(n, generator=gen)
    order = perm[torch.argsort(vox[perm], stable=True)]  # grouped by voxel, random within
    vs = vox[order]
    rank = rank_within_group(vs, num_vox)
    counts = torch.bincount(vox, minlength=num_vox)
    n_a = (counts + 1) // 2
    n_b = counts // 2
    is_a = rank % 2 == 0
    slot = rank // 2
    # Bucket voxels by ceil(log2 |A|) so padding to [V_b, maxA, maxB] wastes ≤ 4×.
    bucket = torch.ceil(torch.log2(n_a.clamp_min(1).float())).long()
    has_b = n_b > 0
    a_out, b_out, s_out = [], [], []
    for bk in torch.unique(bucket[has_b]).tolist():  # loop over ≤ log2(N) buckets
        vsel = torch.nonzero(has_b & (bucket == bk)).squeeze(1)
        row_of_vox = torch.full((num_vox,), -1, dtype=torch.long)
        row_of_vox[vsel] = torch.arange(vsel.shape[0])
        ma, mb = int(n_a[vsel].max()), int(n_b[vsel].max())
        rows = row_of_vox[vs]
        in_bk = rows >= 0
        sel_a = in_bk & is_a
        sel_b = in_bk & ~is_a
        ida = torch.full((vsel.shape[0], ma), -1, dtype=torch.long)
        idb = torch.full((vsel.shape[0], mb), -1, dtype=torch.long)
        ida[rows[sel_a], slot[sel_a]] = order[sel_a]
        idb[rows[sel_b], slot[sel_b]] = order[sel_b]
        # Gather padded blocks (padding reads node 0; padded A rows are dropped below and
        # padded B columns are masked to −inf).
        za, zb = tokens_n[ida.clamp_min(0)], tokens_n[idb.clamp_min(0)]
        fa, fb = fg[ida.clamp_min(0)], fg[idb.clamp_min(0)]
        cos = torch.bmm(za, zb.transpose(1, 2))
        if norms is not None:
            na, nb = norms[ida.clamp_min(0)], norms[idb.clamp_min(0)]
            cos = cos / (na.unsqueeze(2) * nb.unsqueeze(1)).clamp_min(1e-12)
        sim = cos - eta * torch.maximum(fa.unsqueeze(2), fb.unsqueeze(1))
        sim = sim.masked_fill((idb < 0).unsqueeze(1), float("-inf"))
        best, arg = sim.max(2)  # [Vb, maxA]
        valid = ida >= 0
        a_out.append(ida[valid])
        b_out.append(idb.gather(1, arg)[valid])
        s_out.append(best[valid])
    if not a_out:
        e = torch.zeros(0, dtype=torch.long)
        return e, e, torch.zeros(0)
    return torch.cat(a_out), torch.cat(b_out), torch.cat(s_out)


def mani_compress(positions: torch.Tensor, tokens: torch.Tensor, fg: torch.Tensor,
                  config: ManiConfig = ManiConfig(), time: torch.Tensor | None = None,
                  sizes: torch.Tensor | None = None) -> ManiResult:
    """Compress candidates to ``config.budget`` nodes with motion-adaptive merging.

    Parameters
    ----------
    positions : (M, 3); tokens : (M, D); fg : (M,) in [0, 1];
    time : (M,) source time (carried through merges); sizes : (M,) initial weights (1).

    Returns
    -------
    ManiResult (N = min(M, budget) nodes unless ``max_iters`` was hit).
    """
    if config.merge not in ("medoid", "representative", "mean"):
        raise ValueError(f"unknown MANI merge {config.merge!r}; expected 'medoid', 'representative' or 'mean'")
    gen = torch.Generator().manual_seed(config.seed)
    m0 = positions.shape[0]
    pos = positions.float().clone()
    tok_sum = tokens.float()  # size-weighted token *sums*; never written in place (no copy of the input)
    prior = fg.float().clone()
    tim = torch.zeros(m0) if time is None else time.float().clone()
    size = torch.ones(m0) if sizes is None else sizes.float().clone()
    if sizes is not None:
        tok_sum = tok_sum * size.unsqueeze(1)
    tok_norm = tok_sum.norm(dim=1)  # kept up to date for the merged rows only
    p_dyn = prior.clone()
    assign = torch.arange(m0)
    diag = float((pos.max(0).values - pos.min(0).values).norm()) if m0 > 1 else 1.0
    diag = max(diag, 1e-9)
    history = [m0]
    it = 0
    while pos.shape[0] > config.budget and it < config.max_iters:
        n = pos.shape[0]
        voxel = (config.v_init + it * config.dv) * diag
        it += 1
        vox, nv = voxel_ids(pos, voxel)
        # cos is scale-free (sum ∝ mean): pass the sums and their norms
        a, b, sim = match_within_voxels(tok_sum, prior, vox, nv, config.eta, gen, norms=tok_norm)
        if a.numel() == 0:
            history.append(n)
            continue
        va = vox[a]
        # Per-voxel dynamic tendency: mean prior over all its nodes, mean sim over its pairs.
        cnt = torch.bincount(vox, minlength=nv).float()
        mean_m = torch.zeros(nv).index_add_(0, vox, prior) / cnt
        npair = torch.bincount(va, minlength=nv).float()
        mean_s = torch.zeros(nv).index_add_(0, va, sim) / npair.clamp_min(1)
        pd_vox = torch.sigmoid(config.alpha * mean_m - config.beta * mean_s + config.bias)
        r_vox = config.r_min + (1 - pd_vox) * (config.r_max - config.r_min)
        has_pairs = npair > 0
        p_dyn = torch.where(has_pairs[vox], pd_vox[vox], p_dyn)
        # Top floor(r·|A_C|) pairs per voxel: sort by (voxel, −sim), rank inside voxel.
        o = torch.argsort(-sim, stable=True)
        o = o[torch.argsort(va[o], stable=True)]
        rank = rank_within_group(va[o], nv)
        quota = torch.floor(r_vox * npair + 1e-6).long()
        chosen = o[rank < quota[va[o]]]
        excess = n - chosen.numel() - config.budget
        if excess < 0:  # last iteration: merge only the globally most similar, land on budget
            keep = n - config.budget
            chosen = chosen[torch.argsort(-sim[chosen], stable=True)[:keep]]
        if chosen.numel() == 0:
            history.append(n)
            continue
        ca, cb = a[chosen], b[chosen]
        dest = torch.arange(n)
        dest[ca] = cb  # every merged A goes to its B; B is never an A, so one hop suffices
        survive = torch.ones(n, dtype=torch.bool)
        survive[ca] = False
        new_id = torch.cumsum(survive.long(), 0) - 1
        mapping = new_id[dest]
        nn_ = int(survive.sum())
        # ToMe merge: B absorbs all its A's; size-weighted means for the small per-node
        # fields, token sums updated in place only on the merged rows.
        wsum = torch.zeros(nn_).index_add_(0, mapping, size)
        mean = lambda x: torch.zeros(nn_).index_add_(0, mapping, x * size) / wsum  # noqa: E731
        if config.merge == "representative":  # B survives with its own position and time
            pos, tim = pos[survive], tim[survive]
        else:
            pos = torch.zeros(nn_, 3).index_add_(0, mapping, pos * size.unsqueeze(1)) / wsum.unsqueeze(1)
            tim = mean(tim)
        prior, p_dyn = mean(prior), mean(p_dyn)
        merged = tok_sum[survive]
        merged.index_add_(0, new_id[cb], tok_sum[ca])
        tok_sum = merged
        rows = torch.unique(new_id[cb])
        tok_norm = tok_norm[survive]
        tok_norm[rows] = tok_sum[rows].norm(dim=1)
        size = wsum
        assign = mapping[assign]
        history.append(nn_)
    if config.merge == "medoid" and m0 > 0:
        pos, tim = _medoids(positions.float(), pos, assign, torch.zeros(m0) if time is None else time.float())
    return ManiResult(pos, tok_sum / size.unsqueeze(1), prior, size, tim, p_dyn, assign, it, history)


def _medoids(cand_pos: torch.Tensor, centroid: torch.Tensor, assign: torch.Tensor,
             cand_time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per node the member candidate nearest its centroid.

    cand_pos (M, 3), cand_time (M,), centroid (N, 3), assign (M,) node of every candidate
    -> positions (N, 3), time (N,).
    """
    n = centroid.shape[0]
    d = (cand_pos - centroid[assign]).square().sum(1)  # [M]
    best = torch.full((n,), float("inf")).scatter_reduce(0, assign, d, "amin")
    is_best = d <= best[assign]
    idx = torch.arange(cand_pos.shape[0])
    # ties: the lowest candidate index wins (deterministic)
    pick = torch.full((n,), cand_pos.shape[0], dtype=torch.long).scatter_reduce(
        0, assign[is_best], idx[is_best], "amin")
    return cand_pos[pick], cand_time[pick]
