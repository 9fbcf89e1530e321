"""Fixed-centre camera model for low-parallax clips: one camera centre, per-frame rotations.

Chosen by :mod:`engine.io.solve_select` when the clip shows no measurable translation (or SfM fails
or is implausible). Depth is unobservable from one centre: the scale is arbitrary (``scene_scale`` 1)
and there are no sparse points.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry.poses import kabsch_rotation
from .clip import Clip
from .solve_twoview import INLIER_PX, homography_residual, pair_geometry

DEFAULT_FOV_DEG = 60.0  # degrees across the long image side: a typical phone / camcorder lens at 1x


def default_K(width: int, height: int, fov_deg: float | None = None) -> np.ndarray:
    """Pinhole ``K [3,3]`` with a centred principal point and ``fov_deg`` across the long side."""
    from ..errors import InputError

    fov = float(fov_deg or DEFAULT_FOV_DEG)
    if not 1.0 <= fov <= 179.0:
        raise InputError(f"field of view {fov} degrees is out of range.", fix="Give --fov between 1 and 179 degrees.")
    f = 0.5 * max(width, height) / np.tan(np.radians(fov) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])


def fixed_centre_cameras(clip: Clip, small, pairs=None, *, fov_deg: float | None = None, solve_scale: float = 1.0,
                         min_inliers: int = 15, inlier_px: float = INLIER_PX, rotation_min_deg: float = 0.1) -> Clip:
    """Every frame shares one camera centre (the world origin); rotations from homographies.

    Intrinsics: a centred pinhole with ``fov_deg`` (default :data:`DEFAULT_FOV_DEG`) across the long
    side, no distortion. Orientation: from consecutive-frame LK matches (``pairs`` from
    :func:`pair_geometry`, at the resolution of ``small``), the homography's inliers are lifted to unit
    rays with that ``K`` and the relative rotation is the Kabsch fit ``v ≈ R u``; rotations are chained
    from frame 0 (= world axes). When the whole clip turns by less than ``rotation_min_deg`` the camera is
    treated as static (identity rotations, ``model = 'static'``), else ``model = 'rotation'``. A frame
    whose link to its predecessor has fewer than ``min_inliers`` matches keeps the previous rotation
    and counts as unregistered. ``mean_reproj_error`` is the mean transfer error (full-resolution px) of
    the linked frames' inlier matches under the model (``x' ~ K R_j R_iᵀ K⁻¹ x``).

    Parameters
    ----------
    clip : Clip  (``F`` frames, full resolution ``W x H``)
    small : ndarray [F,h,w,3] uint8  the frames at solve resolution
    pairs : list of dict, optional  :func:`pair_geometry` output with the gap-1 pairs (computed if None)
    solve_scale : float  ``w / W``

    Returns
    -------
    Clip with ``K [F,3,3]``, ``w2c [F,4,4]`` (centres at the origin), no points, ``scene_scale`` 1 and
    ``meta['solve']`` (``model``, ``registered``, ``num_registered``, ``mean_reproj_error``, ``num_points``
    0, ``solve_scale``, ``fov_deg``, ``max_rotation_deg``, ``inlier_fraction``).
    """
    import cv2

    F, h, w = small.shape[:3]
    Ks = default_K(w, h, fov_deg)
    Ki = np.linalg.inv(Ks)
    if pairs is None:
        gray = np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in small])
        pairs = pair_geometry(gray, Ks, gaps=(1,))
    link = {d["i"]: d for d in pairs if d["j"] == d["i"] + 1}
    R = np.tile(np.eye(3), (F, 1, 1))
    registered = np.zeros(F, bool)
    registered[0] = True
    errs, n_inl, n_all = [], 0, 0
    for f in range(1, F):
        R[f] = R[f - 1]
        d = link.get(f - 1)
        if d is None or d["n"] < min_inliers:
            continue
        p, q = d["p"], d["q"]
        _, mh = cv2.findHomography(p, q, cv2.RANSAC, inlier_px)
        inl = mh[:, 0] > 0 if mh is not None else np.zeros(len(p), bool)
        if inl.sum() < min_inliers:
            continue
        Rr = kabsch_rotation(_rays(p[inl], Ki), _rays(q[inl], Ki))
        R[f] = Rr @ R[f - 1]
        registered[f] = True
        errs.append(homography_residual(Ks @ Rr @ Ki, p[inl], q[inl]) / solve_scale)
        n_inl += int(inl.sum())
        n_all += len(p)
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    model = "rotation" if ang.max() >= rotation_min_deg else "static"
    if model == "static":
        R[:] = np.eye(3)
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[:, :3, :3] = R
    meta = dict(clip.meta)
    meta["solve"] = {"model": model, "registered": registered, "num_registered": int(registered.sum()),
                     "mean_reproj_error": float(np.concatenate(errs).mean()) if errs else 0.0, "num_points": 0,
                     "solve_scale": solve_scale, "fov_deg": float(fov_deg or DEFAULT_FOV_DEG),
                     "max_rotation_deg": float(ang.max()),
                     "inlier_fraction": float(n_inl / n_all) if n_all else 0.0}
    K = default_K(clip.width, clip.height, fov_deg)
    out = dataclasses.replace(clip, K=np.tile(K, (F, 1, 1)), w2c=w2c, dist=None, points=None, point_colors=None,
                              scene_center=np.zeros(3), scene_scale=1.0, meta=meta)
    out.validate_cameras()
    return out


def _rays(x, Ki):
    """Unit viewing rays ``[N,3]`` of pixels ``x [N,2]`` under ``K⁻¹``."""
    r = np.c_[x, np.ones(len(x))] @ Ki.T
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def fixed_centre_note(info: dict) -> str:
    """What the fixed-centre model assumes and how to give real cameras (the warning's second half)."""
    what = ("a static camera (all frames share one pose)" if info["model"] == "static" else
            f"a camera that only rotates about a fixed centre (up to {info['max_rotation_deg']:.1f} degrees)")
    return (f"Assuming {what} with a {info['fov_deg']:.0f} degree field of view across the long side "
            f"({info['num_registered']}/{len(info['registered'])} frames linked, mean transfer error "
            f"{info['mean_reproj_error']:.2f} px). Depth cannot be measured from a fixed viewpoint, so geometry "
            "will be weak. For real cameras, track the camera in Blender and export a clip manifest, pass a "
            "COLMAP model, or set the lens with --fov.")
