"""Binding Gaussians to nodes: K nearest nodes and normalised RBF weights.

``w_ij = exp(−|x_j − c_i|² / 2ρ_i²) / Σ_{k ∈ V(j)} exp(−|x_j − c_k|² / 2ρ_k²)``
(paper Eq. 2), over the ``K`` nearest nodes ``V(j)``.
"""

from __future__ import annotations

import torch

#: Default working-memory budget of :func:`knn_nodes` (bytes of temporaries per chunk).
DEFAULT_MEMORY_BUDGET = 256 * 1024 * 1024
# Temporaries per (point, node) pair: the distance matrix plus topk's working copy and
# the matmul buffer, each ``itemsize`` bytes.
_BYTES_PER_PAIR_FACTOR = 3


def knn_chunk_size(num_nodes: int, itemsize: int = 4, memory_budget: int = DEFAULT_MEMORY_BUDGET) -> int:
    """Rows per chunk so that one chunk's ``[chunk, N]`` temporaries fit the budget."""
    per_row = max(num_nodes, 1) * itemsize * _BYTES_PER_PAIR_FACTOR
    return max(1, memory_budget // per_row)


def knn_nodes(points: torch.Tensor, nodes: torch.Tensor, k: int, chunk_size: int | None = None,
              memory_budget: int = DEFAULT_MEMORY_BUDGET) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest nodes of every point, processed in memory-bounded chunks.

    Parameters
    ----------
    points : (G, 3)
    nodes : (N, 3)
    k : int, ``1 <= k <= N``.
    chunk_size : rows per chunk; default from ``memory_budget`` (1M points × 5k nodes
        in float32 then needs ~256 MB of temporaries, not 60 GB).

    Returns
    -------
    idx : (G, k) long, nearest first.
    dist2 : (G, k) squared distances, recomputed exactly for the selected pairs.
    """
    n = nodes.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k={k} must be between 1 and the number of nodes ({n})")
    chunk = chunk_size or knn_chunk_size(n, points.element_size(), memory_budget)
    # Rank in coordinates centred on the nodes: |c|² − 2p·c cancels catastrophically in
    # float32 when the scene sits far from the origin; shifting both sets is free and exact.
    origin = nodes.mean(0)
    nodes_c = nodes - origin
    nodes_sq = (nodes_c * nodes_c).sum(-1)  # [N]
    idx_out = torch.empty(points.shape[0], k, dtype=torch.long, device=points.device)
    for start in range(0, points.shape[0], chunk):  # loop over chunks, not points
        p = points[start:start + chunk] - origin
        # |p|² is constant per row, so ranking by |c|² − 2 p·c is enough (one matmul,
        # [chunk, N] temporaries only).
        score = torch.addmm(nodes_sq.unsqueeze(0), p, nodes_c.T, alpha=-2.0)
        idx_out[start:start + chunk] = torch.topk(score, k, dim=1, largest=False, sorted=True).indices
    diff = points.unsqueeze(1) - nodes[idx_out]
    return idx_out, (diff * diff).sum(-1)


def support_weights(dist2: torch.Tensor, radii: torch.Tensor, cutoff: float) -> torch.Tensor:
    """Unnormalised RBF weights ``exp(−d²/2ρ²)``, zero beyond ``cutoff × ρ``: how much each of a
    node's nearest tracks supports it (``engine/nodes/trajectory.py``, ``engine/nodes/path_chain.py``).

    dist2 : (N, K) squared distances; radii : (N, 1) or (N, K) radius ``ρ``. Returns (N, K).
    """
    return torch.exp(-dist2 / (2 * radii ** 2)) * (dist2 <= (cutoff * radii) ** 2)


def rbf_weights(dist2: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Normalised RBF weights over each row's neighbours.

    Parameters
    ----------
    dist2 : (G, K) squared distances to the neighbours.
    radii : (G, K) radius ``ρ`` of each neighbour.

    Returns
    -------
    (G, K) weights summing to 1 per row; computed as a softmax of ``−d²/2ρ²`` so points
    far from every node still get finite weights (no 0/0).
    """
    return torch.softmax(-dist2 / (2.0 * radii * radii).clamp_min(1e-20), dim=-1)


def bind_gaussians(points: torch.Tensor, nodes: torch.Tensor, radii: torch.Tensor, k: int,
                   chunk_size: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """K nearest nodes and RBF weights for ``points [G, 3]``; ``radii [N]``.

    Returns ``idx [G, k]`` (long) and ``w [G, k]``.
    """
    k = min(k, nodes.shape[0])
    idx, d2 = knn_nodes(points, nodes, k, chunk_size)
    return idx, rbf_weights(d2, radii[idx])
