"""Camera solve for clips without cameras (pycolmap on the CPU), and Umeyama alignment.

Pipeline (:func:`solve_cameras`):

1. Frames are resized so the long side is at most ``max_size`` (default 320 px) and written
   as PNGs to a temporary folder (320 px by default: on the synthetic test room a 60-frame
   640x480 clip solves in ~55 s at 320 px but fails to register at 640 px). With ``masks`` (per frame ``float [H,W]`` in ``[0,1]``,
   1 = dynamic) a COLMAP feature mask is written per frame: pixels with mask ≥ 0.5
   (dilated by ``mask_dilate`` px) get no features, so moving objects do not drive the solve.
2. SIFT extraction (``max_features`` per frame), one shared camera for all frames
   (``camera_model``, default ``SIMPLE_RADIAL``), sequential matching (``overlap`` neighbours).
3. Incremental mapping (initial-pair triangulation angle ≥ ``init_min_tri_angle``, fixed
   seed); the largest model is kept.
4. Intrinsics are scaled back to full resolution (``K_full = diag(W/w, H/h, 1) · K_small``;
   distortion coefficients act on normalised coordinates and are unchanged).

Registration: if fewer than ``max(3, min_registered · F)`` frames register, an
:class:`InputError` says so (typical causes: a near-static camera, no texture, or mostly
moving content) and suggests supplying cameras. Frames that do not register keep their
place: their poses are **interpolated** (camera centre linearly, rotation by slerp)
between the nearest registered frames in time, or copied from the nearest one at the ends.
``clip.meta['solve']`` records ``registered [F] bool``, ``num_registered``,
``mean_reproj_error`` (px at solve resolution), ``num_points``, ``solve_scale``.

The solved world frame is COLMAP's (arbitrary similarity); ``scene_center``/``scene_scale``
come from the sparse points.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from .clip import Clip, scene_bounds
from .colmap import reconstruction_cameras

log = logging.getLogger(__name__)


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
    C = -np.einsum("fji,fj->fi", R, w2c[reg, :3, 3])
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


def solve_cameras(clip: Clip, masks=None, *, max_size: int = 320, max_frames: int | None = None,
                  camera_model: str = "SIMPLE_RADIAL", max_features: int = 4096, overlap: int = 8,
                  min_registered: float = 0.5, mask_dilate: int = 5, num_threads: int = 2,
                  init_min_tri_angle: float = 4.0, seed: int = 0, workdir=None, log_level: int = 1) -> Clip:
    """Solve per-frame cameras (shared intrinsics) for ``clip`` with pycolmap.

    Parameters
    ----------
    clip : Clip
        Frames to solve (existing cameras are ignored and replaced).
    masks : sequence of ndarray [H,W] float, optional
        Per-frame dynamic masks in ``[0,1]`` (1 = dynamic), full or any resolution.
    max_size : int
        Long side (px) of the frames the solver sees.
    max_frames : int, optional
        Use only this many evenly spaced frames (the result has only those frames).
    camera_model : str
        ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` or ``OPENCV``.
    min_registered : float
        Fraction of frames that must register (and at least 3).
    init_min_tri_angle : float
        Minimum triangulation angle (degrees) of the initial pair; lower than COLMAP's
        16° default because video has small baselines between frames.
    seed : int
        Mapper random seed (deterministic results).
    workdir : path, optional
        Keep the COLMAP database/images here (default: a temporary folder, removed).
    log_level : int
        Least severe COLMAP (glog) message shown while solving: 0 info, 1 warning
        (default: COLMAP's per-step INFO lines are hidden), 2 error, 3 fatal only.

    Returns
    -------
    Clip
        A copy with ``K``, ``w2c``, ``dist``, ``points``, ``scene_center/scale`` and
        ``meta['solve']``.
    """
    import cv2
    import pycolmap

    if max_frames and clip.num_frames > max_frames:
        idx = np.unique(np.round(np.linspace(0, clip.num_frames - 1, int(max_frames))).astype(int))
        clip = clip.subset(idx)
        if masks is not None:
            masks = [masks[i] for i in idx]
    F = clip.num_frames
    if masks is not None and len(masks) != F:
        raise InputError(f"{len(masks)} masks for {F} frames.", clip.source, "Give one mask per frame.")
    W, H = clip.width, clip.height
    s = min(1.0, max_size / max(W, H))
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    tmp = tempfile.TemporaryDirectory(prefix="ms_solve_") if workdir is None else None
    work = Path(tmp.name if tmp else workdir)
    # COLMAP logs every step at INFO to stderr (hundreds of lines); keep warnings and errors
    min_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(int(min_level), int(log_level))
    try:
        imdir, mdir = work / "images", work / "masks"
        imdir.mkdir(parents=True, exist_ok=True)
        names = [f"{i:06d}.png" for i in range(F)]
        for i, n in enumerate(names):
            img = clip.load_frame(i, downscale=1)
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (W, H) else img
            cv2.imwrite(str(imdir / n), img[:, :, ::-1])
            if masks is not None:
                mdir.mkdir(exist_ok=True)
                m = np.asarray(masks[i], dtype=np.float32)
                if m.ndim != 2:
                    raise InputError(f"mask {i} has shape {m.shape}; expected [H,W].", clip.source, "Give 2D masks.")
                m = cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)
                dyn = (m >= 0.5).astype(np.uint8)
                if mask_dilate > 0:
                    dyn = cv2.dilate(dyn, np.ones((2 * mask_dilate + 1,) * 2, np.uint8))
                cv2.imwrite(str(mdir / (n + ".png")), np.where(dyn > 0, 0, 255).astype(np.uint8))
        db = work / "database.db"
        if db.exists():
            db.unlink()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        if masks is not None:
            reader.mask_path = str(mdir)
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = num_threads
        ext.sift.max_num_features = max_features
        ext.use_gpu = False
        pycolmap.extract_features(db, imdir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        mopt = pycolmap.FeatureMatchingOptions()
        mopt.num_threads = num_threads
        mopt.use_gpu = False
        popt = pycolmap.SequentialPairingOptions()
        popt.overlap = overlap
        popt.loop_detection = False
        pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt, device=pycolmap.Device.cpu)
        iopt = pycolmap.IncrementalPipelineOptions()
        iopt.num_threads = num_threads
        iopt.min_model_size = 3
        iopt.multiple_models = False
        iopt.mapper.init_min_tri_angle = float(init_min_tri_angle)
        iopt.mapper.num_threads = num_threads
        iopt.mapper.random_seed = int(seed)
        out = work / "sparse"
        out.mkdir(exist_ok=True)
        recs = pycolmap.incremental_mapping(db, imdir, out, options=iopt)
    finally:
        pycolmap.logging.minloglevel = min_level
        if tmp is not None:
            tmp.cleanup()
    need = max(3, int(np.ceil(min_registered * F)))
    fix = ("Supply cameras (export them from Blender or use a dataset with poses), or use footage where "
           "the camera moves (translates) around a textured, mostly static scene.")
    if not recs:
        raise InputError(f"camera solve failed: no frames registered out of {F} (the camera may barely move, "
                         "or the scene lacks texture).", clip.source, fix)
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    nreg = rec.num_reg_images()
    if nreg < need:
        raise InputError(f"camera solve registered only {nreg} of {F} frames (need {need}).", clip.source, fix)
    try:
        rnames, K, w2c_r, dist_r, _ = reconstruction_cameras(rec)
    except ValueError as exc:
        raise InputError(f"unsupported camera model {exc}.", clip.source, "Use SIMPLE_RADIAL or OPENCV.") from None
    pos = [names.index(n) for n in rnames]
    registered = np.zeros(F, dtype=bool)
    registered[pos] = True
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[pos] = w2c_r
    w2c = interpolate_poses(w2c, registered, clip.times)
    Kf = np.tile(K[0], (F, 1, 1))
    Kf[:, 0, :] *= W / w
    Kf[:, 1, :] *= H / h
    dist = None if dist_r is None else np.tile(dist_r[0], (F, 1))
    pts = rec.points3D
    xyz = np.array([p.xyz for p in pts.values()], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts.values()], dtype=np.uint8).reshape(-1, 3)
    err = float(rec.compute_mean_reprojection_error())
    centers = -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])
    c, sc = scene_bounds(centers, xyz)
    meta = dict(clip.meta)
    meta["solve"] = {"registered": registered, "num_registered": int(nreg), "mean_reproj_error": err,
                     "num_points": int(len(xyz)), "solve_scale": s}
    log.info("camera solve: %d/%d frames registered, mean reprojection error %.3f px, %d points",
             nreg, F, err, len(xyz))
    out_clip = dataclasses.replace(clip, K=Kf, w2c=w2c, dist=dist, points=xyz, point_colors=rgb,
                                   scene_center=c, scene_scale=sc, meta=meta)
    out_clip.validate_cameras()
    return out_clip
