"""Node neighbourhood graph and radii from neighbour spacing."""

from __future__ import annotations

import torch

from ..geometry.binding import knn_nodes


def node_graph(centers: torch.Tensor, k: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest *other* nodes of every node.

    Parameters
    ----------
    centers : (N, 3)
    k : int, clamped to ``N − 1``.

    Returns
    -------
    idx : (N, k') long, nearest first, never the node itself (k' = min(k, N−1)).
    dist2 : (N, k') squared distances.
    """
    n = centers.shape[0]
    kk = min(k, n - 1)
    if kk <= 0:
        return (torch.zeros(n, 0, dtype=torch.long, device=centers.device),
                torch.zeros(n, 0, dtype=centers.dtype, device=centers.device))
    idx, d2 = knn_nodes(centers, centers, kk + 1)
    # Drop self: usually column 0, but with duplicate centres self may sit elsewhere.
    not_self = idx != torch.arange(n, device=idx.device).unsqueeze(1)
    order = torch.argsort((~not_self).to(torch.int8), dim=1, stable=True)[:, :kk]
    return idx.gather(1, order), d2.gather(1, order)


def path_graph(paths: torch.Tensor, k: int = 8, max_elements: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest *other* nodes of every node by the distance between their paths: the
    largest distance between the two over time (MoSca's curve distance).

    Two nodes that are near at one time but part later (either side of an elbow, a hand
    and the table it leaves) are far on this measure, so an as-rigid-as-possible term on
    this graph does not tie parts that move apart; nodes that move together stay near.

    Parameters
    ----------
    paths : (N, T, 3) node positions at T shared times (e.g. the spline keys).
    k : int, clamped to ``N − 1``.
    max_elements : the rows are taken in blocks whose ``[rows, N, T, 3]`` differences hold at
        most this many values (64 MB in float32: one key per frame of a long clip stays bounded).

    Returns
    -------
    idx : (N, k') long, nearest first, never the node itself (k' = min(k, N−1)).
    dist2 : (N, k') squared curve distances.
    """
    n = paths.shape[0]
    kk = min(k, n - 1)
    if kk <= 0:
        return (torch.zeros(n, 0, dtype=torch.long, device=paths.device),
                torch.zeros(n, 0, dtype=paths.dtype, device=paths.device))
    idx, d2 = [], []
    chunk = max(1, int(max_elements) // max(n * paths.shape[1] * 3, 1))
    for a in range(0, n, chunk):  # row blocks (a few): [chunk, N, T, 3] at a time
        rows = paths[a:a + chunk]
        far = ((rows[:, None] - paths[None]) ** 2).sum(-1).amax(-1)  # [c, N]
        far[torch.arange(len(rows), device=paths.device), torch.arange(a, a + len(rows), device=paths.device)] = float("inf")
        v, i = torch.topk(far, kk, dim=1, largest=False)
        idx.append(i); d2.append(v)
    return torch.cat(idx), torch.cat(d2)


def node_radii(centers: torch.Tensor, k: int = 4, factor: float = 1.0, min_radius: float = 1e-4) -> torch.Tensor:
    """Radius = ``factor`` × mean distance to the ``k`` nearest other nodes (``(N,)``).

    Dense (dynamic) regions get small radii, sparse (static) ones large, so RBF
    weights overlap a few neighbours everywhere.
    """
    _, d2 = node_graph(centers, k)
    if d2.shape[1] == 0:
        return torch.full((centers.shape[0],), 1.0, dtype=centers.dtype, device=centers.device)
    return (factor * d2.clamp_min(0).sqrt().mean(1)).clamp_min(min_radius)
