"""A node's path carried on past the end of its own tracks.

:func:`engine.nodes.trajectory.fit_node_trajectories` fits a node's spline to the tracks
nearest it at its *source* frame. On fast parts those tracks live a few frames (the flow
loses a fast limb or a rolling ball within a training interval or two), so outside their
life the node had no sample and its path was held where they left it: on the large-motion
scenes the forearm's nodes had samples of their own in about half the frames and the ball's in
70-80 %, and held, they were about a unit off in the rest (docs/benchmarks.md, *A node's path
past its own tracks*).

:func:`chain_node_paths` follows each node on with the tracks around it *where it is then*:
from its source frame it moves with its own tracks' mean displacement; when those carry less
than ``keep`` of their weight, it takes the tracks nearest its current position (an *anchor*
frame) and goes on with their displacement since the anchor, forwards and backwards in time.
Displacements are measured from the anchor rather than summed frame to frame, so the noise of
a lifted track's depth enters once per anchor instead of accumulating every frame.

:func:`engine.nodes.trajectory.fit_node_trajectories` weighs these samples by
``chain_hop_weight ** hops`` (``hops``: anchors taken since the
source frame): every new set of tracks is another chance to land on another part or on
tracks lifted at the wrong depth, so a path pieced together from many sets is trusted less
than one a node's own tracks support, and the spline's smoothness holds it instead (the
trade is measured in docs/benchmarks.md).
"""

from __future__ import annotations

import torch

from ..geometry.binding import knn_nodes, support_weights


def chain_node_paths(centers: torch.Tensor, source_frame: torch.Tensor, radii: torch.Tensor,
                     tracks3d: torch.Tensor, k_tracks: int = 8, support_radius: float = 2.0,
                     keep: float = 0.5, huber: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Each node's path, carried by its own tracks and then by the tracks around it.

    Parameters
    ----------
    centers : (N, 3) node positions at their source frames; source_frame : (N,) long;
    radii : (N,) node radii ``rho``; tracks3d : (P, F, 3) lifted tracks, NaN = missing.
    k_tracks : tracks per set (RBF weights ``exp(-d^2 / 2 rho^2)``, none beyond
        ``support_radius x rho``, as :func:`engine.nodes.trajectory.fit_node_trajectories`).
    keep : a new set is taken when the visible tracks of the current one carry less than this
        share of its weight.
    huber : a track whose displacement strays from the set's mean by more than this many node
        radii is down-weighted (one Huber reweighting per frame).

    Returns
    -------
    path : (N, F, 3) world positions, NaN where no track carried the node.
    hops : (N, F) long, the anchors taken between the source frame and that frame (0 while the
        node's own tracks carry it).
    """
    n = centers.shape[0]
    p, f, _ = tracks3d.shape
    path = torch.full((n, f, 3), float("nan"))
    path[torch.arange(n), source_frame] = centers.float()
    hops = torch.zeros(n, f, dtype=torch.long)
    kk = min(k_tracks, p)
    if kk == 0 or n == 0:
        return path, hops
    seen = torch.isfinite(tracks3d).all(-1)  # [P, F]
    rows = torch.arange(n)
    for step in (1, -1):  # forwards, then backwards from the source frame
        idx = torch.zeros(n, kk, dtype=torch.long)  # the current set's tracks
        w0 = torch.zeros(n, kk)                      # ... their weights (0: none yet)
        anchor = source_frame.clone()
        hop = torch.full((n,), -1, dtype=torch.long)  # the first set, at the source frame, is hop 0
        alive = torch.ones(n, dtype=torch.bool)
        for fi in (range(0, f - 1) if step == 1 else range(f - 1, 0, -1)):  # loop over frames, not nodes
            nxt = fi + step
            started = (source_frame <= fi) if step == 1 else (source_frame >= fi)
            act = started & alive & torch.isfinite(path[:, fi]).all(-1)
            if not act.any():
                continue
            carried = (w0 * (seen[idx, nxt] & seen[idx, anchor.unsqueeze(1)])).sum(1)
            renew = torch.nonzero(act & ((carried < keep * w0.sum(1)) | (w0.sum(1) <= 0))).squeeze(1)
            candidates = torch.nonzero(seen[:, fi] & seen[:, nxt]).squeeze(1)
            if renew.numel():
                w_new = torch.zeros(renew.numel(), kk)
                i_new = torch.zeros(renew.numel(), kk, dtype=torch.long)
                if candidates.numel():
                    kh = min(kk, candidates.numel())
                    near, d2 = knn_nodes(path[renew, fi], tracks3d[candidates, fi], kh)
                    w_new[:, :kh] = support_weights(d2, radii[renew].unsqueeze(1), support_radius)
                    i_new[:, :kh] = candidates[near]
                idx[renew], w0[renew], anchor[renew] = i_new, w_new, fi
                hop[renew] += 1
            alive &= ~(act & (w0.sum(1) <= 0))  # no track around it: the path ends here
            act &= alive
            w = w0 * (seen[idx, nxt] & seen[idx, anchor.unsqueeze(1)])
            disp = torch.nan_to_num(tracks3d[idx, nxt] - tracks3d[idx, anchor.unsqueeze(1)])  # [N, k, 3]
            mean = (w.unsqueeze(-1) * disp).sum(1) / w.sum(1).clamp_min(1e-12).unsqueeze(-1)
            stray = (disp - mean.unsqueeze(1)).norm(dim=-1)
            thr = huber * radii.unsqueeze(1)
            w = w * torch.where(stray <= thr, torch.ones_like(stray), thr / stray.clamp_min(1e-12))
            ok = act & (w.sum(1) > 0)
            mean = (w.unsqueeze(-1) * disp).sum(1) / w.sum(1).clamp_min(1e-12).unsqueeze(-1)
            upd = ok & ~torch.isfinite(path[:, nxt]).all(-1)
            path[upd, nxt] = path[rows, anchor][upd] + mean[upd]
            hops[upd, nxt] = hop[upd]
            alive &= ok | ~act
    return path, hops
