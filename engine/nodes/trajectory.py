"""Spline trajectory initialisation from lifted 2D tracks.

Source frame: a node's centre ``c_i`` is its candidate position (MANI: its cluster's
medoid), observed at that candidate's source time ``t_i`` snapped to a frame. Tracks near
the node *at that frame* vote with their displacement since that frame, so
``p_i(t_i) ≈ c_i``. Rotations (:func:`fit_node_rotations`) are the rigid rotation of the
same tracks since that frame (identity there), or identity everywhere (the paper's start).
Training then takes canonical centres and rotations at one shared time
(``engine.train.init_model.common_canonical_nodes``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..geometry.binding import knn_nodes, support_weights
from ..geometry.camera import unproject
from ..geometry.hermite import catmull_rom_tangents, hermite_eval, hermite_fit
from ..geometry.quaternion import quat_from_matrix, quat_identity, quat_normalize
from ..geometry.rigid import weighted_kabsch
from .path_chain import chain_node_paths


def lift_tracks(tracks_xy: torch.Tensor, tracks_vis: torch.Tensor, depth: torch.Tensor, K: torch.Tensor,
                w2c: torch.Tensor, vis_threshold: float = 0.5, edge_tolerance: float = 0.05,
                tracks_depth: torch.Tensor | None = None) -> torch.Tensor:
    """Lift 2D tracks to world space with depth and cameras.

    Samples are dropped (NaN) where the track is occluded or low-confidence
    (``vis < vis_threshold``), off-image, on invalid depth, or on a depth edge
    (3×3 max/min depth ratio above ``1 + edge_tolerance``, where nearest-pixel depth may
    belong to the other surface). A sample with a depth of its own (``tracks_depth``
    finite and positive: :mod:`engine.priors.hinge_tracks`) is lifted with it and needs no
    depth map there (a thin link is all depth edge in the map).

    Parameters
    ----------
    tracks_xy : (P, F, 2) continuous pixel coords; tracks_vis : (P, F) bool or [0, 1].
    depth : (F, H, W); K : (F, 3, 3); w2c : (F, 4, 4); tracks_depth : (P, F) camera depth,
    NaN where the map decides, or None.

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
    if tracks_depth is not None:
        own = torch.isfinite(tracks_depth) & (tracks_depth > 0)
        z = torch.where(own, tracks_depth.float(), z)
        ok = ok | (own & inside & (tracks_vis.float() >= vis_threshold))
    x = unproject(K.float().unsqueeze(0).expand(p, -1, -1, -1), w2c.float().unsqueeze(0).expand(p, -1, -1, -1),
                  tracks_xy.float(), z)
    return torch.where(ok.unsqueeze(-1), x, torch.full_like(x, float("nan")))



def _running_nanmedian(x: torch.Tensor, window: int) -> torch.Tensor:
    """Centred running median of ``x [P, F]`` along F (NaN = missing, kept NaN).

    The window shrinks symmetrically near the ends of a track and next to gaps (the
    largest half-width ≤ ``window // 2`` with every sample present), so a steady trend is
    passed unchanged everywhere, while an isolated spike is removed wherever the window
    has at least 3 samples.
    """
    out = x.clone()
    fin = torch.isfinite(x)
    for h in range(1, window // 2 + 1):  # loop over half-widths, not tracks
        pad = torch.full((x.shape[0], h), float("nan"), dtype=x.dtype)
        win = torch.cat([pad, x, pad], 1).unfold(1, 2 * h + 1, 1)  # [P, F, 2h + 1]
        full = torch.isfinite(win).all(-1) & fin
        out = torch.where(full, win.median(-1).values, out)
    return out


def clean_tracks3d(tracks3d: torch.Tensor, tracks_xy: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                   fg: torch.Tensor | None = None, jump_tol: float = 0.1, min_len: int = 4,
                   depth_window: int = 5, static_fg: float = 0.5):
    """Make lifted tracks fit for the spline fit (every step vectorised over tracks).

    1. **Split at depth jumps.** Where a track's camera depth changes by more than
       ``jump_tol`` in log depth (~10 %) from its previous sample, the 2D track crossed a
       depth discontinuity (it slid onto an occluder / the background, or the depth map
       switched surface); the rest becomes a separate track, so a node anchored before the
       jump never sees the other surface. Real motion of 10 % of the depth in one frame
       (≈ 2.4 depths/s at 24 fps) is far beyond a typical clip.
    2. **Drop short pieces** (fewer than ``min_len`` samples): they carry no reliable
       motion and are mostly fragments between jumps.
    3. **Static pieces are static.** A piece whose median dynamic prior ``fg`` (sampled at
       its pixels) is below ``static_fg`` is a static surface: its samples are replaced by
       their median world position, so depth noise there cannot become motion. (0.5 is the
       threshold the depth prior uses to exclude dynamic pixels from its anchors.)
    4. **Median-filter the depth of moving pieces** over ``depth_window`` frames (log
       depth, then re-lifted along the same rays): the weight-free depth of moving objects is
       interpolated from the static surroundings and flickers frame to frame; the filter
       removes single-frame spikes without smearing the 2D motion.

    Parameters
    ----------
    tracks3d : (P, F, 3) world, NaN = missing (from :func:`lift_tracks`); tracks_xy : (P, F, 2)
    pixels; K : (F, 3, 3); w2c : (F, 4, 4); fg : (F, H, W) dynamic prior or None (no step 3).

    Returns
    -------
    (P', F, 3) cleaned tracks and (P',) index of each one's source track.
    """
    p, f, _ = tracks3d.shape
    dev = tracks3d.device
    if p == 0:
        return tracks3d, torch.zeros(0, dtype=torch.long, device=dev)
    valid = torch.isfinite(tracks3d).all(-1)
    R, t = w2c[:, :3, :3].float(), w2c[:, :3, 3].float()
    cam = torch.einsum("fij,pfj->pfi", R, torch.nan_to_num(tracks3d)) + t
    logz = torch.where(valid & (cam[..., 2] > 0), cam[..., 2].clamp_min(1e-9).log(), torch.full_like(cam[..., 2], float("nan")))
    valid = torch.isfinite(logz)
    fr = torch.arange(f, device=dev).expand(p, f)
    last = torch.where(valid, fr, torch.full_like(fr, -1)).cummax(1).values
    prev = torch.cat([torch.full((p, 1), -1, dtype=torch.long, device=dev), last[:, :-1]], 1)
    prev_logz = logz.gather(1, prev.clamp_min(0))
    jump = valid & (prev >= 0) & ((logz - prev_logz).abs() > jump_tol)
    seg = jump.long().cumsum(1)
    key = torch.arange(p, device=dev).unsqueeze(1) * (f + 1) + seg
    uniq, inv = torch.unique(key[valid], return_inverse=True)
    count = torch.bincount(inv, minlength=uniq.shape[0])
    keep = count >= min_len
    new_id = torch.cumsum(keep.long(), 0) - 1
    n_new = int(keep.sum())
    src = uniq[keep] // (f + 1)
    pi, fi = torch.nonzero(valid, as_tuple=True)
    sk = keep[inv]
    pi, fi, ni = pi[sk], fi[sk], new_id[inv][sk]
    lz = torch.full((n_new, f), float("nan"), device=dev)
    lz[ni, fi] = logz[pi, fi]
    xy = tracks_xy.float()[src]  # [P', F, 2]
    out = torch.full((n_new, f, 3), float("nan"), device=dev)
    out[ni, fi] = tracks3d[pi, fi].float()
    if n_new == 0:
        return out, src
    static = torch.zeros(n_new, dtype=torch.bool, device=dev)
    if fg is not None:
        h, w = fg.shape[1:]
        col = xy[..., 0].floor().long().clamp(0, w - 1)
        row = xy[..., 1].floor().long().clamp(0, h - 1)
        m = fg.float()[torch.arange(f, device=dev).expand(n_new, f), row, col]
        m = torch.where(torch.isfinite(lz), m, torch.full_like(m, float("nan")))
        static = m.nanmedian(1).values < static_fg
    zs = _running_nanmedian(lz, depth_window).exp()
    moved = unproject(K.float().unsqueeze(0).expand(n_new, -1, -1, -1), w2c.float().unsqueeze(0).expand(n_new, -1, -1, -1),
                      xy, torch.nan_to_num(zs, nan=1.0))
    ok = torch.isfinite(lz).unsqueeze(-1)
    moved = torch.where(ok, moved, torch.full_like(moved, float("nan")))
    still = out.nanmedian(1).values.unsqueeze(1).expand(-1, f, -1)
    still = torch.where(ok, still, torch.full_like(still, float("nan")))
    return torch.where(static[:, None, None], still, moved), src



def _support_tracks(centers, source_frame, radii, tracks3d, k, support_radius):
    """Each node's ``k`` nearest tracks at its source frame and their weights
    ``exp(−d²/2ρ²)`` (zero beyond ``support_radius × ρ`` or where there is no track)."""
    n = centers.shape[0]
    tr = torch.zeros(n, k, dtype=torch.long)
    wts = torch.zeros(n, k)
    for fi in torch.unique(source_frame).tolist():  # loop over frames, not nodes
        sel = torch.nonzero(source_frame == fi).squeeze(1)
        anchor = tracks3d[:, fi]  # [P, 3]
        tid = torch.nonzero(torch.isfinite(anchor).all(-1)).squeeze(1)
        if tid.numel() == 0:
            continue
        k_here = min(k, tid.shape[0])
        idx, d2 = knn_nodes(centers[sel], anchor[tid], k_here)
        rho = radii[sel].unsqueeze(1)
        tr[sel, :k_here] = tid[idx]
        wts[sel, :k_here] = support_weights(d2, rho, support_radius)
    return tr, wts


def fit_node_trajectories(centers: torch.Tensor, source_frame: torch.Tensor, radii: torch.Tensor,
                          tracks3d: torch.Tensor, times: torch.Tensor, key_times: torch.Tensor,
                          graph_idx: torch.Tensor | None = None, k_tracks: int = 8,
                          support_radius: float = 2.0, smoothness: float = 1e-2, huber: float | None = None,
                          irls_iters: int = 3, fallback: str = "graph", fallback_rounds: int = 10,
                          max_residual_ratio: float | None = 1.0, frame_rot: torch.Tensor | None = None,
                          chain_hop_weight: float = 0.0):
    """Least-squares Hermite position keys per node from nearby lifted tracks.

    Each node takes its ``k_tracks`` nearest tracks at its source frame within
    ``support_radius × radius``; weights ``exp(−d²/2ρ²)``. Samples are the tracks'
    displacements since that frame added to ``c_i``. IRLS with Huber weights (threshold
    ``huber``, default the node radius) handles outlier tracks; the velocity penalty
    ``smoothness`` (relative to the total sample weight) keeps weakly supported nodes
    still. Nodes without any supporting sample take the support-weighted mean displacement
    of their graph neighbours (``fallback="graph"``, propagated ``fallback_rounds`` times)
    or stay static (``"static"``). With ``frame_rot`` (:func:`node_frame_rotations`) a track
    places the node where the turned offset from it puts it, ``x_j(f) + R_i(f)(c_i − a_j)``
    (``a_j`` its position at the source frame), instead of shifting the centre by the
    track's displacement: on a turning part the two differ by the turn of that offset.
    With ``chain_hop_weight > 0``, in the frames where none of its own tracks is seen the node
    also takes the path :func:`engine.nodes.path_chain.chain_node_paths` carries it along (the
    tracks around it there), weighted by the node's mean per-frame support times
    ``chain_hop_weight ** hops``; 0 holds it where its own tracks leave it.

    Parameters
    ----------
    centers : (N, 3); source_frame : (N,) long; radii : (N,); tracks3d : (P, F, 3) NaN=missing;
    times : (F,); key_times : (K,); graph_idx : (N, k) for the graph fallback;
    frame_rot : (N, F, 3, 3) or None; chain_hop_weight : float in [0, 1].

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
    tr, wts = _support_tracks(centers, source_frame, radii, tracks3d, kk, support_radius)
    anchor = tracks3d[tr, source_frame.unsqueeze(1)]  # [N, k, 3] (NaN where no track)
    samples = tracks3d[tr] - anchor.unsqueeze(2)  # [N, k, F, 3]
    if frame_rot is not None:  # x_j(f) + R(f)(c - a_j) - c = (x_j(f) - a_j) + (R(f) - I)(c - a_j)
        off = centers.unsqueeze(1) - anchor  # [N, k, 3]
        turn = torch.einsum("nfij,nkj->nkfi", frame_rot - torch.eye(3), off)
        samples = samples + turn
    valid = torch.isfinite(samples).all(-1) & (wts.unsqueeze(-1) > 0)  # [N, k, F]
    sample_w = wts.unsqueeze(-1) * valid  # [N, k, F]
    support = sample_w.sum((1, 2))
    if chain_hop_weight > 0:
        # where none of its own tracks is seen, the node goes on with the tracks around it
        path, hops = chain_node_paths(centers, source_frame, radii, tracks3d, kk, support_radius)
        own = valid.any(1)  # [N, F]
        own_w = torch.where(own.any(1), support / own.sum(1).clamp_min(1), torch.ones_like(support))  # per frame
        chained = torch.isfinite(path).all(-1) & ~own
        rel = torch.where(chained.unsqueeze(-1), path - centers.unsqueeze(1), torch.full_like(path, float("nan")))
        samples = torch.cat([samples, rel.unsqueeze(1)], 1)
        chain_w = own_w.unsqueeze(1) * chained * chain_hop_weight ** hops.float()  # [N, F]
        sample_w = torch.cat([sample_w, chain_w.unsqueeze(1)], 1)
        support = support + (own_w.unsqueeze(1) * chained).sum(1)
        kk = kk + 1
    s = samples.permute(0, 2, 1, 3).reshape(n, f * kk, 3)  # sample order: time-major
    sw = sample_w.permute(0, 2, 1).reshape(n, f * kk)
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
    supported = support > 0
    if max_residual_ratio is not None:
        # a fit whose robust residual exceeds the motion it explains is noise, not motion
        wr = sw * robust
        den = wr.sum(1).clamp_min(1e-12)
        resid = ((wr * res ** 2).sum(1) / den).sqrt()
        mot = ((wr * pred.repeat_interleave(kk, dim=1).norm(dim=-1) ** 2).sum(1) / den).sqrt()
        supported &= resid <= max_residual_ratio * mot
    disp_keys = torch.where(supported[:, None, None], keys, torch.zeros_like(keys))
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


def _fill_along(x: torch.Tensor, ok: torch.Tensor, dim: int) -> torch.Tensor:
    """Fill entries of ``x`` where ``ok`` is False with the nearest earlier ``ok`` entry along
    ``dim`` (later one before the first); all-False slices take their last entry (callers
    replace those).
    ``x [..., L, C]`` with ``dim`` the L axis (negative), ``ok [..., L]``."""
    n = ok.shape[dim]
    ar = torch.arange(n, device=ok.device).expand_as(ok)
    last = torch.where(ok, ar, torch.full_like(ar, -1)).cummax(dim).values
    first_ok = torch.where(ok, ar, torch.full_like(ar, n)).flip(dim).cummin(dim).values.flip(dim)
    src = torch.where(last >= 0, last, first_ok).clamp(max=n - 1)
    return torch.gather(x, dim - 1, src.unsqueeze(-1).expand_as(x))


def node_frame_rotations(centers: torch.Tensor, source_frame: torch.Tensor, radii: torch.Tensor,
                         tracks3d: torch.Tensor, k_tracks: int = 8, support_radius: float = 2.0,
                         min_tracks: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-frame rotation of each node's supporting tracks since its source frame.

    The supporting tracks are those of :func:`fit_node_trajectories` (the node's
    ``k_tracks`` nearest at its source frame, RBF weights); per frame a weighted Kabsch fit
    of their positions at the source frame to those at that frame gives ``R_i(f)`` (the
    identity at the source frame). Frames with fewer than ``min_tracks`` usable tracks, or
    collinear ones, are not ``ok`` and hold the identity.

    Returns ``R [N, F, 3, 3]`` (frames in ``tracks3d`` order) and ``ok [N, F]``.
    """
    n = centers.shape[0]
    p, f, _ = tracks3d.shape
    kk = min(k_tracks, p)
    if kk < min_tracks or n == 0:
        return torch.eye(3).expand(n, f, 3, 3).clone(), torch.zeros(n, f, dtype=torch.bool)
    tr, wts = _support_tracks(centers, source_frame, radii, tracks3d, kk, support_radius)
    dst = tracks3d[tr].permute(0, 2, 1, 3)  # [N, F, k, 3]
    src = tracks3d[tr, source_frame.unsqueeze(1)].unsqueeze(1).expand_as(dst)
    R, _, ok = weighted_kabsch(src, dst, wts.unsqueeze(1).expand(n, f, kk), min_tracks)
    return R, ok


def fit_node_rotations(frame_rot: torch.Tensor, frame_ok: torch.Tensor, times: torch.Tensor,
                       key_times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation keys per node from its per-frame rotations (:func:`node_frame_rotations`).

    A rolling ball or a swinging limb turns its surface; nodes that only translate carry
    their Gaussians' texture without turning it, and the photometric gradient alone does
    not find rotations of tens of degrees (docs/benchmarks.md, "Moving objects").
    Frames that are not ``ok`` take the nearest fitted frame; quaternions are made
    sign-continuous in time and each key is the hat-weighted mean (over the key spacing)
    of the fitted frames around it (a steady turn is kept exactly inside the clip; the end
    keys see one side of their window and lag by about a third of a frame's turn).

    Parameters
    ----------
    frame_rot : (N, F, 3, 3); frame_ok : (N, F) bool; times : (F,); key_times : (K,) increasing.

    Returns
    -------
    rot_keys : (N, K, 4) unit quaternions (w, x, y, z); rotated : (N,) bool, nodes with at
    least one fitted frame (the others keep the identity).
    """
    n, f = frame_ok.shape
    k_n = key_times.shape[0]
    ident = quat_identity(n, k_n)
    if n == 0 or f == 0:
        return ident, torch.zeros(n, dtype=torch.bool)
    order = torch.argsort(times.float(), stable=True)  # work in time order
    ok = frame_ok[:, order]
    q = _fill_along(quat_from_matrix(frame_rot[:, order]), ok, -1)  # [N, F, 4]
    # sign continuity along time: flip where a frame's quaternion points away from the previous one
    dots = (q[:, 1:] * q[:, :-1]).sum(-1)
    flips = torch.cat([torch.ones(n, 1), torch.where(dots < 0, -1.0, 1.0)], 1).cumprod(1)
    q = q * flips.unsqueeze(-1)
    t_sorted = times.float()[order]
    spacing = (key_times[1:] - key_times[:-1]).clamp_min(1e-6).min() if k_n > 1 else torch.tensor(1.0)
    hat = (1.0 - (t_sorted.unsqueeze(0) - key_times.float().unsqueeze(1)).abs() / spacing).clamp_min(0)  # [K, F]
    wk = hat.unsqueeze(0) * ok.float().unsqueeze(1)  # [N, K, F]
    keys = torch.einsum("nkf,nfc->nkc", wk, q)
    keys = _fill_along(quat_normalize(keys), wk.sum(-1) > 0, -1)
    rotated = ok.any(1)
    return torch.where(rotated[:, None, None], keys, ident), rotated
