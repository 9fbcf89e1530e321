"""Spline trajectory initialisation from lifted 2D tracks.

Canonical frame: a node's centre ``c_i`` is its merged candidate position, observed at
its (size-weighted, snapped to a frame) source time ``t_i``. Tracks near the node *at
that frame* vote with their displacement since that frame, so ``p_i(t_i) ≈ c_i`` and the
node transform is ~identity at its own source time. Rotations start at identity.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..geometry.binding import knn_nodes
from ..geometry.camera import unproject
from ..geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_fit


def lift_tracks(tracks_xy: torch.Tensor, tracks_vis: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                w2c: torch.Tensor, vis_threshold: float = 0.5, edge_tolerance: float = 0.05) -> torch.Tensor:
    """Lift 2D tracks to world space with depth and cameras.

    Samples are dropped (NaN) where the track is occluded or low-confidence
    (``vis < vis_threshold``), off-image, on invalid depth, or on a depth edge
    (3×3 max/min depth ratio above ``1 + edge_tolerance``, where nearest-pixel depth may
    belong to the other surface).

    Parameters
    ----------
    tracks_xy : (P, F, 2) continuous pixel coords; tracks_vis : (P, F) bool or [0, 1].
    depth : (F, H, W); K : (F, 3, 3); w2c : (F, 4, 4).

    Returns
    -------
    (P, F, 3) world positions, NaN where dropped.
    """
    p, f, _ = tracks_xy.shape
    h, w = depth.shape[1:]
    d = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth)).float()
    dmax = F.max_pool2d(d.unsqueeze(1), 3, 1, 1).squeeze(1)
    dmin = -F.max_pool2d(-torch.where(d > 0, d, torch.full_like(d, float("inf"))).unsqueeze(1), 3, 1, 1).squeeze(1)
    edge = dmax > dmin * (1 + edge_tolerance)
    col = torch.floor(tracks_xy[..., 0]).long()
    row = torch.floor(tracks_xy[..., 1]).long()
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & torch.isfinite(tracks_xy).all(-1)
    fr = torch.arange(f).expand(p, f)
    rc, cc = row.clamp(0, h - 1), col.clamp(0, w - 1)
    z = d[fr, rc, cc]
    ok = inside & (tracks_vis.float() >= vis_threshold) & (z > 0) & ~edge[fr, rc, cc]
    x = unproject(K.float().unsqueeze(0).expand(p, -1, -1, -1), w2c.float().unsqueeze(0).expand(p, -1, -1, -1),
                  tracks_xy.float(), z)
    return torch.where(ok.unsqueeze(-1), x, torch.full_like(x, float("nan")))


def fit_node_trajectories(centers: torch.Tensor, source_frame: torch.Tensor, radii: torch.Tensor,
                          tracks3d: torch.Tensor, times: torch.Tensor, key_times: torch.Tensor,
                          graph_idx: torch.Tensor | None = None, k_tracks: int = 8,
                          support_radius: float = 2.0, smoothness: float = 1e-2, huber: float | None = None,
                          irls_iters: int = 3, fallback: str = "graph", fallback_rounds: int = 10):
    """Least-squares Hermite position keys per node from nearby lifted tracks.

    Each node takes its ``k_tracks`` nearest tracks at its source frame within
    ``support_radius × radius``; weights ``exp(−d²/2ρ²)``. Samples are the tracks'
    displacements since that frame added to ``c_i``. IRLS with Huber weights (threshold
    ``huber``, default the node radius) handles outlier tracks; the velocity penalty
    ``smoothness`` (relative to the total sample weight) keeps weakly supported nodes
    still. Nodes without any supporting sample take the support-weighted mean displacement
    of their graph neighbours (``fallback="graph"``, propagated ``fallback_rounds`` times)
    or stay static (``"static"``).

    Parameters
    ----------
    centers : (N, 3); source_frame : (N,) long; radii : (N,); tracks3d : (P, F, 3) NaN=missing;
    times : (F,); key_times : (K,); graph_idx : (N, k) for the graph fallback.

    Returns
    -------
    pos_keys : (N, K, 3); pos_tangents : (N, K, 3) Catmull-Rom; support : (N,) total weight.
    """
    n = centers.shape[0]
    p, f, _ = tracks3d.shape
    kk = min(k_tracks, p)
    key_times = key_times.float()
    disp_keys = torch.zeros(n, key_times.shape[0], 3)
    support = torch.zeros(n)
    if kk == 0:
        return _finish(centers, disp_keys, support, key_times, graph_idx, fallback, fallback_rounds)
    samples = torch.full((n, kk, f, 3), float("nan"))
    wts = torch.zeros(n, kk)
    for fi in torch.unique(source_frame).tolist():  # loop over frames, not nodes
        sel = torch.nonzero(source_frame == fi).squeeze(1)
        anchor = tracks3d[:, fi]  # [P, 3]
        ok = torch.isfinite(anchor).all(-1)
        if int(ok.sum()) == 0:
            continue
        tid = torch.nonzero(ok).squeeze(1)
        k_here = min(kk, tid.shape[0])
        idx, d2 = knn_nodes(centers[sel], anchor[tid], k_here)
        rho = radii[sel].unsqueeze(1)
        w = torch.exp(-d2 / (2 * rho ** 2)) * (d2 <= (support_radius * rho) ** 2)
        tr = tid[idx]  # [n_sel, k_here]
        samples[sel, :k_here] = tracks3d[tr] - anchor[tr].unsqueeze(2)
        wts[sel, :k_here] = w
    valid = torch.isfinite(samples).all(-1) & (wts.unsqueeze(-1) > 0)  # [N, k, F]
    support = (wts.unsqueeze(-1) * valid).sum((1, 2))
    s = samples.permute(0, 2, 1, 3).reshape(n, f * kk, 3)  # sample order: time-major
    sw = (wts.unsqueeze(-1) * valid).permute(0, 2, 1).reshape(n, f * kk)
    t_s = times.float().repeat_interleave(kk)
    lam = smoothness * support.clamp_min(1e-6).mean()
    thr = radii.unsqueeze(1) if huber is None else torch.full((n, 1), huber)
    robust = torch.ones_like(sw)
    for _ in range(max(1, irls_iters)):  # IRLS iterations
        keys = hermite_fit(key_times, t_s, s, sw * robust, smoothness=float(lam),
                           fallback=torch.zeros(n, key_times.shape[0], 3))
        pred = hermite_eval(key_times, keys, catmull_rom_tangents(key_times, keys), times.float())  # [N, F, 3]
        res = (torch.nan_to_num(s, nan=0.0) - pred.repeat_interleave(kk, dim=1)).norm(dim=-1)
        robust = torch.where(res <= thr, torch.ones_like(res), thr / res.clamp_min(1e-12))
    disp_keys = torch.where((support > 0)[:, None, None], keys, torch.zeros_like(keys))
    return _finish(centers, disp_keys, support, key_times, graph_idx, fallback, fallback_rounds)


def _finish(centers, disp_keys, support, key_times, graph_idx, fallback, rounds):
    if fallback == "graph" and graph_idx is not None and graph_idx.shape[1] > 0:
        known = support > 0
        disp = disp_keys.clone()
        filled = known.clone()
        for _ in range(rounds):  # graph propagation rounds
            nb_ok = filled[graph_idx].float()  # [N, k]
            cnt = nb_ok.sum(1)
            avg = (disp[graph_idx] * nb_ok[..., None, None]).sum(1) / cnt.clamp_min(1)[:, None, None]
            upd = ~known & (cnt > 0)
            disp = torch.where(upd[:, None, None], avg, disp)
            filled = known | upd
        disp_keys = disp
    keys = centers.unsqueeze(1) + disp_keys
    return keys, catmull_rom_tangents(key_times, keys), support
