"""Camera-pose math on numpy arrays (no torch, no bpy): centres, similarity alignment, rotation fits,
pose interpolation. The camera solve (``engine.io.solve*``), its report and benches use these.

Conventions: ``w2c [F,4,4]`` OpenCV world-to-camera (x right, y down, z forward); a camera centre is
``C = -Rᵀ t``.
"""

from __future__ import annotations

import numpy as np


def camera_centres(w2c: np.ndarray) -> np.ndarray:
    """Camera centres ``[F,3]`` of ``w2c [F,4,4]`` (``C = -Rᵀ t``)."""
    w2c = np.asarray(w2c, np.float64)
    return -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])


def kabsch_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotation ``R [3,3]`` (det +1) minimising ``Σ |v − R u|²`` for rays ``u, v [N,3]``."""
    U, _, Vt = np.linalg.svd(v.T @ u)
    return U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def umeyama_similarity(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """Least-squares similarity ``dst ≈ s · R · src + t`` (Umeyama 1991).

    Parameters
    ----------
    src, dst : ndarray [N,3]
        Corresponding points, ``N ≥ 3`` (not all collinear for a unique rotation).
    with_scale : bool
        Estimate ``s`` (else ``s = 1``).

    Returns
    -------
    s : float
    R : ndarray [3,3]  proper rotation (det +1)
    t : ndarray [3]
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need matching [N>=3,3] arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def interpolate_poses(w2c: np.ndarray, registered: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Fill unregistered poses: slerp rotation + lerp centre between registered neighbours in time.

    Parameters
    ----------
    w2c : ndarray [F,4,4]  (rows of unregistered frames are ignored)
    registered : ndarray [F] bool
    times : ndarray [F]

    Returns
    -------
    ndarray [F,4,4]
    """
    from scipy.spatial.transform import Rotation, Slerp

    out = w2c.copy()
    reg = np.flatnonzero(registered)
    R = w2c[reg, :3, :3]
    C = camera_centres(w2c[reg])
    tr = times[reg]
    q = np.clip(times, tr[0], tr[-1])
    if len(reg) == 1:
        Ri = np.repeat(R, len(times), 0)
        Ci = np.repeat(C, len(times), 0)
    else:
        Ri = Slerp(tr, Rotation.from_matrix(R))(q).as_matrix()
        Ci = np.stack([np.interp(q, tr, C[:, k]) for k in range(3)], axis=1)
    miss = ~registered
    out[miss, :3, :3] = Ri[miss]
    out[miss, :3, 3] = -np.einsum("fij,fj->fi", Ri[miss], Ci[miss])
    out[miss, 3] = [0, 0, 0, 1.0]
    return out
