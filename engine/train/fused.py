"""Fused CPU deformation: dual-quaternion blending + application in one Numba pass.

``fused_deform(dq_nodes, idx, w, means, quats_unit)`` computes exactly what
:meth:`DynamicScene.deform` computes with the torch reference
(:func:`~engine.geometry.dualquat.dq_blend`, ``dq_apply_points``,
``dq_apply_rotations``), but per Gaussian in one loop instead of ~100 elementwise
``[G, K, 8]`` torch ops and their autograd graph, with a hand-written backward:

forward (per Gaussian ``g``)
    gather the ``K`` node DQs, align signs with the heaviest neighbour, blend
    ``b = Σ w_k s_k Q_k``, normalise by ``n = |b_r|`` (``q_r = b_r/n``, ``q_d = b_d/n``),
    ``x' = R(q_r) x + 2 vec(q_d ⊗ q_r*)`` and ``q' = normalise(q_r ⊗ q)``.
backward
    to the canonical means and (already normalised) canonical quaternions, and to the
    node DQs ``[N, 8]`` by a serial scatter-add in Gaussian order (deterministic).

The blend weights and the binding carry no gradient (they are buffers). Everything is
float64 inside the kernels; tensors in and out are float32 on the CPU (read and written
in place, no conversion copies). The per-Gaussian passes run in parallel (blocks of rows
dealt to one strand per thread, :data:`ROW_BLOCK`; each Gaussian writes only its own rows);
only the scatter to the nodes is serial. The torch implementation stays the reference;
``tests/engine/test_train.py`` compares both.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from .fused_ssim import kernel_threads

_JIT = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
# The per-Gaussian passes deal blocks of ROW_BLOCK rows round-robin to one strand per thread
# instead of a plain prange: Numba's OpenMP layer splits a prange into one contiguous block per
# thread, and the rows are not uniform work (static Gaussians at rest come first and take the
# short path), so one thread got the cheap half (1.4 of 2 cores busy in the training bench).
ROW_BLOCK = 64


@njit(inline="always", **_JIT)
def _unit(q, g, normalize):
    """Row ``g`` of ``q [G, 4]`` as float64, divided by ``max(|q|, 1e-12)`` when ``normalize``
    (what ``quat_normalize`` does in torch)."""
    aw, ax, ay, az = np.float64(q[g, 0]), np.float64(q[g, 1]), np.float64(q[g, 2]), np.float64(q[g, 3])
    if normalize:
        n = max(np.sqrt(aw * aw + ax * ax + ay * ay + az * az), 1e-12)
        aw, ax, ay, az = aw / n, ax / n, ay / n, az / n
    return aw, ax, ay, az


@njit(inline="always", **_JIT)
def _resting(node_rest, idx, g):
    """Whether every node of Gaussian ``g`` is at rest (``node_rest [N]`` uint8; empty: none)."""
    if node_rest.shape[0] == 0:
        return False
    for k in range(idx.shape[1]):
        if node_rest[idx[g, k]] == 0:
            return False
    return True


@njit(parallel=True, **_JIT)
def _forward(dqn, idx, w, x, q, normalize, node_rest, out_x, out_q, blend, sgn, rest, nstrands):
    """Per Gaussian (rows dealt to ``nstrands`` strands, :data:`ROW_BLOCK`; each writes only
    its own rows). ``x [G, 3]``, ``q [G, 4]``, ``w [G, K]`` float32 read as float64; ``q``
    normalised here when ``normalize``. A Gaussian whose nodes are all at rest
    (``node_rest``) takes the identity as its blend (``rest [G]`` notes it for the backward)."""
    G, K = idx.shape
    nblk = (G + ROW_BLOCK - 1) // ROW_BLOCK
    for strand in prange(nstrands):
        for blk in range(strand, nblk, nstrands):
            for g in range(blk * ROW_BLOCK, min(G, (blk + 1) * ROW_BLOCK)):
                b = blend[g]
                if _resting(node_rest, idx, g):  # (its sgn row is never read: backward and scatter skip it)
                    rest[g] = 1
                    b[0] = 1.0
                    for c in range(1, 8):
                        b[c] = 0.0
                    _apply(b, x, q, g, normalize, out_x, out_q)
                    continue
                rest[g] = 0
                piv = 0
                for k in range(1, K):
                    if w[g, k] > w[g, piv]:
                        piv = k
                p = idx[g, piv]
                for c in range(8):
                    b[c] = 0.0
                for k in range(K):
                    j = idx[g, k]
                    dot = dqn[j, 0] * dqn[p, 0] + dqn[j, 1] * dqn[p, 1] + dqn[j, 2] * dqn[p, 2] + dqn[j, 3] * dqn[p, 3]
                    s = -1.0 if dot < 0 else 1.0
                    sgn[g, k] = s
                    ws = np.float64(w[g, k]) * s
                    for c in range(8):
                        b[c] += ws * dqn[j, c]
                _apply(b, x, q, g, normalize, out_x, out_q)


@njit(inline="always", **_JIT)
def _rotated(rw, rx, ry, rz, aw, ax, ay, az):
    """``r = q_r ⊗ a`` for the unit canonical rotation ``a`` (:func:`_unit`), and ``|r|``."""
    ow = rw * aw - rx * ax - ry * ay - rz * az
    ox = rw * ax + rx * aw + ry * az - rz * ay
    oy = rw * ay - rx * az + ry * aw + rz * ax
    oz = rw * az + rx * ay - ry * ax + rz * aw
    return ow, ox, oy, oz, np.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)


@njit(inline="always", **_JIT)
def _apply(b, x, q, g, normalize, out_x, out_q):
    """Row ``g`` of the outputs from its blended (unnormalised) DQ ``b [8]`` (the rest of
    :func:`_forward`'s per-Gaussian body, shared by the resting and the blended rows)."""
    n = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2] + b[3] * b[3])
    if n < 1e-12:
        n = 1e-12
    rw, rx, ry, rz = b[0] / n, b[1] / n, b[2] / n, b[3] / n
    dw, dx, dy, dz = b[4] / n, b[5] / n, b[6] / n, b[7] / n
    # t = 2 vec(qd ⊗ conj(qr))
    tx = 2.0 * (-dw * rx + dx * rw - dy * rz + dz * ry)
    ty = 2.0 * (-dw * ry + dx * rz + dy * rw - dz * rx)
    tz = 2.0 * (-dw * rz - dx * ry + dy * rx + dz * rw)
    xx, yy, zz = rx * rx, ry * ry, rz * rz
    xy, xz, yz, wx, wy, wz = rx * ry, rx * rz, ry * rz, rw * rx, rw * ry, rw * rz
    px, py, pz = np.float64(x[g, 0]), np.float64(x[g, 1]), np.float64(x[g, 2])
    out_x[g, 0] = (1 - 2 * (yy + zz)) * px + 2 * (xy - wz) * py + 2 * (xz + wy) * pz + tx
    out_x[g, 1] = 2 * (xy + wz) * px + (1 - 2 * (xx + zz)) * py + 2 * (yz - wx) * pz + ty
    out_x[g, 2] = 2 * (xz - wy) * px + 2 * (yz + wx) * py + (1 - 2 * (xx + yy)) * pz + tz
    aw, ax, ay, az = _unit(q, g, normalize)
    ow, ox, oy, oz, on = _rotated(rw, rx, ry, rz, aw, ax, ay, az)
    if on > 1e-12:
        out_q[g, 0], out_q[g, 1], out_q[g, 2], out_q[g, 3] = ow / on, ox / on, oy / on, oz / on
    else:
        out_q[g, 0], out_q[g, 1], out_q[g, 2], out_q[g, 3] = 1.0, 0.0, 0.0, 0.0


@njit(inline="always", **_JIT)
def _canonical_quat_grad(q, g, normalize, ea, eb, ec, ed, g_q):
    """``g_q[g]`` from the gradient ``e`` of the unit canonical rotation ``a``: through
    ``a = q / max(|q|, eps)`` when ``normalize`` (``(e − a (a·e)) / |q|``), else ``e``."""
    if normalize:
        aw, ax, ay, az = _unit(q, g, True)
        qw, qx, qy, qz = np.float64(q[g, 0]), np.float64(q[g, 1]), np.float64(q[g, 2]), np.float64(q[g, 3])
        qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qn > 1e-12:
            da = aw * ea + ax * eb + ay * ec + az * ed
            ea, eb, ec, ed = (ea - aw * da) / qn, (eb - ax * da) / qn, (ec - ay * da) / qn, (ed - az * da) / qn
        else:
            ea, eb, ec, ed = ea / 1e-12, eb / 1e-12, ec / 1e-12, ed / 1e-12
    g_q[g, 0], g_q[g, 1], g_q[g, 2], g_q[g, 3] = ea, eb, ec, ed


@njit(inline="always", **_JIT)
def _resting_backward(q, g, normalize, gxo, gqo, g_x, g_q):
    """Backward of a resting row (identity blend: ``x' = x``, ``q' = a / |a|``); it sends
    nothing to the nodes, so only ``g_x``, ``g_q`` are written."""
    g_x[g, 0], g_x[g, 1], g_x[g, 2] = gxo[g, 0], gxo[g, 1], gxo[g, 2]
    aw, ax, ay, az = _unit(q, g, normalize)
    on = np.sqrt(aw * aw + ax * ax + ay * ay + az * az)
    if on > 1e-12:
        uw, ux, uy, uz = aw / on, ax / on, ay / on, az / on
        hw, hx, hy, hz = np.float64(gqo[g, 0]), np.float64(gqo[g, 1]), np.float64(gqo[g, 2]), np.float64(gqo[g, 3])
        d = uw * hw + ux * hx + uy * hy + uz * hz
        _canonical_quat_grad(q, g, normalize, (hw - uw * d) / on, (hx - ux * d) / on, (hy - uy * d) / on,
                             (hz - uz * d) / on, g_q)
    else:
        g_q[g, 0], g_q[g, 1], g_q[g, 2], g_q[g, 3] = 0.0, 0.0, 0.0, 0.0


@njit(parallel=True, **_JIT)
def _backward(dqn, idx, w, x, q, normalize, blend, sgn, rest, gxo, gqo, gbs, g_x, g_q, nstrands):
    """Per Gaussian (strands of row blocks as in :func:`_forward`): gradients to ``x``, ``q``
    (through the normalisation when ``normalize``) and to the blended DQ, ``gbs [G, 8]``;
    :func:`_scatter_nodes` then sums those into the node DQs serially. Resting rows
    (``rest [G]``) take the short path."""
    G, K = idx.shape
    nblk = (G + ROW_BLOCK - 1) // ROW_BLOCK
    for strand in prange(nstrands):
        for blk in range(strand, nblk, nstrands):
            for g in range(blk * ROW_BLOCK, min(G, (blk + 1) * ROW_BLOCK)):
                if rest[g]:
                    _resting_backward(q, g, normalize, gxo, gqo, g_x, g_q)
                    continue
                gb = gbs[g]
                b = blend[g]
                n = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2] + b[3] * b[3])
                if n < 1e-12:
                    n = 1e-12
                rw, rx, ry, rz = b[0] / n, b[1] / n, b[2] / n, b[3] / n
                dw, dx, dy, dz = b[4] / n, b[5] / n, b[6] / n, b[7] / n
                px, py, pz = np.float64(x[g, 0]), np.float64(x[g, 1]), np.float64(x[g, 2])
                gx, gy, gz = np.float64(gxo[g, 0]), np.float64(gxo[g, 1]), np.float64(gxo[g, 2])
                # --- points: y = R(qr) p + t
                xx, yy, zz = rx * rx, ry * ry, rz * rz
                xy, xz, yz, wx, wy, wz = rx * ry, rx * rz, ry * rz, rw * rx, rw * ry, rw * rz
                r00, r01, r02 = 1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)
                r10, r11, r12 = 2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)
                r20, r21, r22 = 2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)
                g_x[g, 0] = r00 * gx + r10 * gy + r20 * gz
                g_x[g, 1] = r01 * gx + r11 * gy + r21 * gz
                g_x[g, 2] = r02 * gx + r12 * gy + r22 * gz
                # G_ij = gy_i p_j ; g_q_c = sum G_ij dR_ij/dq_c
                G00, G01, G02 = gx * px, gx * py, gx * pz
                G10, G11, G12 = gy * px, gy * py, gy * pz
                G20, G21, G22 = gz * px, gz * py, gz * pz
                grw = 2 * (-rz * G01 + ry * G02 + rz * G10 - rx * G12 - ry * G20 + rx * G21)
                grx = 2 * (ry * G01 + rz * G02 + ry * G10 - 2 * rx * G11 - rw * G12 + rz * G20 + rw * G21
                           - 2 * rx * G22)
                gry = 2 * (-2 * ry * G00 + rx * G01 + rw * G02 + rx * G10 + rz * G12 - rw * G20 + rz * G21
                           - 2 * ry * G22)
                grz = 2 * (-2 * rz * G00 - rw * G01 + rx * G02 + rw * G10 - 2 * rz * G11 + ry * G12 + rx * G20
                           + ry * G21)
                # --- translation t = vec(P), P = 2 qd ⊗ c, c = conj(qr); g_P = (0, g)
                # g_qd = 2 g_P ⊗ conj(c) = 2 g_P ⊗ qr
                ew, ex, ey, ez = 0.0, gx, gy, gz
                gdw = 2 * (ew * rw - ex * rx - ey * ry - ez * rz)
                gdx = 2 * (ew * rx + ex * rw + ey * rz - ez * ry)
                gdy = 2 * (ew * ry - ex * rz + ey * rw + ez * rx)
                gdz = 2 * (ew * rz + ex * ry - ey * rx + ez * rw)
                # g_c = 2 conj(qd) ⊗ g_P ; g_qr += conj(g_c)
                aw, ax, ay, az = dw, -dx, -dy, -dz
                cw = 2 * (aw * ew - ax * ex - ay * ey - az * ez)
                cx = 2 * (aw * ex + ax * ew + ay * ez - az * ey)
                cy = 2 * (aw * ey - ax * ez + ay * ew + az * ex)
                cz = 2 * (aw * ez + ax * ey - ay * ex + az * ew)
                grw += cw
                grx -= cx
                gry -= cy
                grz -= cz
                # --- rotations: o = r/|r|, r = qr ⊗ a
                aw, ax, ay, az = _unit(q, g, normalize)
                ow, ox, oy, oz, on = _rotated(rw, rx, ry, rz, aw, ax, ay, az)
                if on > 1e-12:
                    uw, ux, uy, uz = ow / on, ox / on, oy / on, oz / on
                    hw, hx = np.float64(gqo[g, 0]), np.float64(gqo[g, 1])
                    hy, hz = np.float64(gqo[g, 2]), np.float64(gqo[g, 3])
                    d = uw * hw + ux * hx + uy * hy + uz * hz
                    hw, hx, hy, hz = (hw - uw * d) / on, (hx - ux * d) / on, (hy - uy * d) / on, (hz - uz * d) / on
                    # g_qr += h ⊗ conj(a)
                    bw, bx, by, bz = aw, -ax, -ay, -az
                    grw += hw * bw - hx * bx - hy * by - hz * bz
                    grx += hw * bx + hx * bw + hy * bz - hz * by
                    gry += hw * by - hx * bz + hy * bw + hz * bx
                    grz += hw * bz + hx * by - hy * bx + hz * bw
                    # g_a = conj(qr) ⊗ h
                    cw_, cx_, cy_, cz_ = rw, -rx, -ry, -rz
                    ea = cw_ * hw - cx_ * hx - cy_ * hy - cz_ * hz
                    eb = cw_ * hx + cx_ * hw + cy_ * hz - cz_ * hy
                    ec = cw_ * hy - cx_ * hz + cy_ * hw + cz_ * hx
                    ed = cw_ * hz + cx_ * hy - cy_ * hx + cz_ * hw
                    _canonical_quat_grad(q, g, normalize, ea, eb, ec, ed, g_q)
                else:
                    g_q[g, 0], g_q[g, 1], g_q[g, 2], g_q[g, 3] = 0.0, 0.0, 0.0, 0.0
                # --- normalisation: qr = br/n, qd = bd/n
                dr = rw * grw + rx * grx + ry * gry + rz * grz
                dd = dw * gdw + dx * gdx + dy * gdy + dz * gdz
                gb[0] = (grw - rw * dr - rw * dd) / n
                gb[1] = (grx - rx * dr - rx * dd) / n
                gb[2] = (gry - ry * dr - ry * dd) / n
                gb[3] = (grz - rz * dr - rz * dd) / n
                gb[4], gb[5], gb[6], gb[7] = gdw / n, gdx / n, gdy / n, gdz / n


@njit(**_JIT)
def _scatter_nodes(idx, w, sgn, gbs, rest, g_dqn):
    """Blend backward: scatter ``gbs [G, 8]`` to the node DQs in Gaussian order (serial, so
    the float sums are deterministic); resting rows (``rest [G]``) send nothing."""
    G, K = idx.shape
    for g in range(G):
        if rest[g]:
            continue
        for k in range(K):
            j = idx[g, k]
            ws = np.float64(w[g, k]) * sgn[g, k]
            for c in range(8):
                g_dqn[j, c] += ws * gbs[g, c]


def _f32(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()  # no copy for float32 tensors


class _FusedDeform(torch.autograd.Function):
    @staticmethod
    def forward(ctx, dq_nodes, idx, w, means, quats, normalize, node_rest):
        dqn = dq_nodes.detach().double().contiguous().numpy()  # [N, 8]: small
        idx_np = idx.detach().contiguous().numpy()
        w_np, x, q = _f32(w), _f32(means), _f32(quats)
        G, K = idx_np.shape
        rest_np = (np.zeros(0, np.uint8) if node_rest is None
                   else node_rest.detach().to(torch.uint8).contiguous().numpy())
        out_x = np.empty((G, 3), np.float32)
        out_q = np.empty((G, 4), np.float32)
        blend = np.empty((G, 8))  # every row is written by _forward
        sgn = np.empty((G, K))
        rest = np.empty(G, np.uint8)
        with kernel_threads():
            _forward(dqn, idx_np, w_np, x, q, bool(normalize), rest_np, out_x, out_q, blend, sgn, rest,
                     numba.get_num_threads())
        ctx.saved = (dqn, idx_np, w_np, x, q, bool(normalize), blend, sgn, rest, dq_nodes.shape[0])
        return torch.from_numpy(out_x), torch.from_numpy(out_q)

    @staticmethod
    def backward(ctx, g_out_x, g_out_q):
        dqn, idx_np, w_np, x, q, normalize, blend, sgn, rest, n_nodes = ctx.saved
        G = x.shape[0]
        gxo = np.zeros((G, 3), np.float32) if g_out_x is None else _f32(g_out_x)
        gqo = np.zeros((G, 4), np.float32) if g_out_q is None else _f32(g_out_q)
        gbs = np.empty((G, 8))
        g_dqn = np.zeros((n_nodes, 8))
        g_x = np.empty((G, 3), np.float32)
        g_q = np.empty((G, 4), np.float32)
        with kernel_threads():
            _backward(dqn, idx_np, w_np, x, q, normalize, blend, sgn, rest, gxo, gqo, gbs, g_x, g_q,
                      numba.get_num_threads())
        _scatter_nodes(idx_np, w_np, sgn, gbs, rest, g_dqn)
        return (torch.from_numpy(g_dqn).to(torch.float32), None, None, torch.from_numpy(g_x),
                torch.from_numpy(g_q), None, None)


def fused_deform(dq_nodes: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, means: torch.Tensor,
                 quats: torch.Tensor, normalize: bool = False,
                 node_rest: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """DQB-deform canonical Gaussians (CPU, float32).

    Parameters
    ----------
    dq_nodes : (N, 8) unit node dual quaternions (differentiable).
    idx : (G, K) long binding; w : (G, K) blend weights (no gradient).
    means : (G, 3) canonical centres; quats : (G, 4) canonical rotations, unit unless
        ``normalize`` (then divided by their norm inside the kernel, as ``quat_normalize``
        would, gradient included: no [G, 4] torch ops and their backward per step).
    node_rest : (N,) bool or None: nodes whose transform is taken as the identity. A Gaussian
        bound only to such nodes is not blended (its centre and rotation pass through, to
        the float rounding of the rest transform) and sends no gradient to the node DQs.

    Returns
    -------
    means_t (G, 3), quats_t (G, 4): same values as ``dq_apply_points(dq, means)`` and
    ``dq_apply_rotations(dq, quats_unit)`` with ``dq = dq_blend(dq_nodes, idx, w)``.
    """
    return _FusedDeform.apply(dq_nodes, idx, w, means, quats, normalize, node_rest)


def fused_available(*tensors: torch.Tensor) -> bool:
    """The fused path handles CPU float32 tensors."""
    return all(t.device.type == "cpu" and (not t.is_floating_point() or t.dtype == torch.float32) for t in tensors)


KNN_CHUNK = 256  # points per task of _knn (each task owns one score buffer)


@njit(parallel=True, **_JIT)
def _knn(points, cx, cy, cz, nodes_sq, origin, k, out):
    """``out [G, k]``: the ``k`` nodes with the smallest ``|c|² − 2 p·c`` per point (centred
    coordinates, the ranking of :func:`engine.geometry.binding.knn_nodes`), nearest first,
    ties to the lower node index. Per point, the scores of all nodes go into a buffer in one
    vectorised pass (node coordinates ``cx, cy, cz [N]`` as separate arrays), then one scan
    keeps a sorted ``k``-slot list: no ``[G, N]`` score matrix and no top-k over it."""
    G = points.shape[0]
    N = cx.shape[0]
    for ch in prange((G + KNN_CHUNK - 1) // KNN_CHUNK):
        score = np.empty(N, np.float32)
        best = np.empty(k, np.float32)
        bidx = np.empty(k, np.int64)
        for g in range(ch * KNN_CHUNK, min(G, (ch + 1) * KNN_CHUNK)):
            px = points[g, 0] - origin[0]
            py = points[g, 1] - origin[1]
            pz = points[g, 2] - origin[2]
            two = np.float32(2.0)
            for j in range(N):
                score[j] = nodes_sq[j] - two * (px * cx[j] + py * cy[j] + pz * cz[j])
            for m in range(k):
                best[m] = np.inf
                bidx[m] = 0
            for j in range(N):
                s = score[j]
                if s < best[k - 1]:
                    m = k - 1
                    while m > 0 and s < best[m - 1]:
                        best[m] = best[m - 1]
                        bidx[m] = bidx[m - 1]
                        m -= 1
                    best[m] = s
                    bidx[m] = j
            for m in range(k):
                out[g, m] = bidx[m]


def fused_knn(points: torch.Tensor, nodes: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``[G, k]`` (long) of the ``k`` nearest ``nodes [N, 3]`` of ``points [G, 3]``
    (CPU float32), nearest first: the ranking of ``engine.geometry.binding.knn_nodes`` in
    one Numba pass (the binding refresh runs it at every densification / rebind step)."""
    origin = nodes.mean(0)
    nodes_c = nodes - origin
    nodes_sq = (nodes_c * nodes_c).sum(-1)
    out = np.empty((points.shape[0], k), np.int64)
    c = _f32(nodes_c)
    with kernel_threads():
        _knn(_f32(points), np.ascontiguousarray(c[:, 0]), np.ascontiguousarray(c[:, 1]),
             np.ascontiguousarray(c[:, 2]), _f32(nodes_sq), _f32(origin), int(k), out)
    return torch.from_numpy(out)
