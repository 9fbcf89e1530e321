"""Camera solve for clips without cameras (pycolmap on the CPU), and Umeyama alignment.

Pipeline (:func:`solve_cameras`; ``engine.pipeline.open_clip`` turns on everything marked *pipeline*):

0. *pipeline*: at most ``sample_frames`` (60) evenly spaced frames are solved; the others get
   interpolated poses (:func:`interpolate_poses`) and ``registered = False``.
1. Frames are resized so the long side is at most ``max_size`` (default 320 px) and written
   as PNGs to a temporary folder (320 px by default: on the synthetic test room a 60-frame
   640x480 clip solves in ~55 s at 320 px but fails to register at 640 px). With ``masks`` (per frame ``float [H,W]`` in ``[0,1]``,
   1 = dynamic) a COLMAP feature mask is written per frame: pixels with mask ≥ 0.5
   (dilated by ``mask_dilate`` px) get no features, so moving objects do not drive the solve.
   *pipeline* ``auto_masks``: without masks, they come from the motion prior's depth-free path
   (:func:`engine.priors.motion.motion_mask` with ``depth=None``: Sampson residual of DIS flow) on
   rough poses — consecutive-frame essential matrices of LK matches, chained, unit translation
   (the Sampson distance does not depend on its length) — see :func:`camera_free_masks`.
2. SIFT extraction (``max_features`` per frame), one shared camera for all frames
   (``camera_model``, default ``SIMPLE_RADIAL``), sequential matching (``overlap`` neighbours),
   RANSAC seeded. With ``fov_deg`` (or ``global_retry``) the camera gets a focal-length prior:
   ``fov_deg`` (default :data:`DEFAULT_FOV_DEG` = 60°) across the long side.
3. Incremental mapping (initial-pair triangulation angle ≥ ``init_min_tri_angle``, every pycolmap
   ``random_seed`` set to ``seed``); the largest model is kept.
   *pipeline* ``global_retry``: when too few frames register — a panning handheld camera has
   sub-pixel parallax between neighbours (bedroom.mp4: a homography explains ~90 % of the matches
   between frames 30 source frames apart, median parallax 0.2–0.4 px at 320 px), so incremental SfM
   finds no initial pair or cannot extend it — global SfM (GLOMAP: rotation averaging + global
   positioning) runs on the same database with the focal length held at the FOV prior (barely
   observable at low parallax), and the model that registers more frames is kept.
4. Intrinsics are scaled back to full resolution (``K_full = diag(W/w, H/h, 1) · K_small``;
   distortion coefficients act on normalised coordinates and are unchanged).
5. *pipeline* ``static_fallback`` (low parallax): if SfM still registers too few frames and
   consecutive frames are linked by homographies, :func:`fixed_centre_cameras` returns a
   documented fixed-centre model — one camera centre for all frames (the origin), centred pinhole
   with ``fov_deg`` across the long side, per-frame rotations from the homography inliers (Kabsch on
   unit rays, chained; identity rotations = ``model 'static'`` when the whole clip turns by < 0.1°)
   — and a warning event says what was assumed and how to supply real cameras (Blender camera
   track + clip manifest, a COLMAP model, or ``--fov``). Depth is unobservable from one centre, so
   the depth prior is weak on such clips (scale arbitrary, ``scene_scale`` 1, no sparse points).

Registration: if fewer than ``max(3, min_registered · F)`` frames register (and no fallback
applies), an :class:`InputError` says so (typical causes: a near-static camera, no texture, or
mostly moving content) and suggests supplying cameras. Frames that do not register keep their
place: their poses are **interpolated** (camera centre linearly, rotation by slerp)
between the nearest registered frames in time, or copied from the nearest one at the ends.
``clip.meta['solve']`` records ``model`` (``'sfm'`` with ``mapper`` ``'incremental'|'global'``,
or ``'static'`` / ``'rotation'``), ``registered [F] bool``, ``num_registered``,
``mean_reproj_error`` (SfM: px at solve resolution; fixed-centre: mean homography transfer error of
the inlier matches in full-resolution px), ``num_points``, ``solve_scale`` (and for the fallback
``fov_deg``, ``max_rotation_deg``, ``inlier_fraction``, ``reason``, ``warning``; ``sampled`` frame
indices when ``sample_frames`` applied).

Results are reproducible with ``num_threads=1``; with 2 threads COLMAP's matching/mapping can
vary slightly between runs (bedroom.mp4: always 60/60 registered at 0.42–0.45 px, but 18–217
sparse points).

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


DEFAULT_FOV_DEG = 60.0  # degrees across the long image side: a typical phone / camcorder lens at 1x


def default_K(width: int, height: int, fov_deg: float | None = None) -> np.ndarray:
    """Pinhole ``K [3,3]`` with a centred principal point and ``fov_deg`` across the long side."""
    fov = float(fov_deg or DEFAULT_FOV_DEG)
    if not 1.0 <= fov <= 179.0:
        raise InputError(f"field of view {fov} degrees is out of range.", fix="Give --fov between 1 and 179 degrees.")
    f = 0.5 * max(width, height) / np.tan(np.radians(fov) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])


def _track_pair(a, b, max_corners=600):
    """Sparse LK matches ``(p [N,2], q [N,2])`` from gray ``a`` to ``b`` (forward-backward checked)."""
    import cv2

    p = cv2.goodFeaturesToTrack(a, max_corners, 0.01, 7, blockSize=7)
    if p is None or len(p) < 8:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    lk = dict(winSize=(21, 21), maxLevel=4, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p, None, **lk)
    r, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q, None, **lk)
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((r - p)[:, 0], axis=1) < 0.5)
    return p[ok, 0] + 0.5, q[ok, 0] + 0.5  # continuous pixel coordinates


def pair_geometry(gray, K, gaps=(1,), thresh=1.0, rng_seed=0):
    """Two-view geometry between frames ``f`` and ``f + g`` of a gray sequence (LK matches).

    Parameters
    ----------
    gray : ndarray [F,h,w] uint8
    K : ndarray [3,3]  intrinsics at this resolution (a guess is fine)
    gaps : frame gaps to measure
    thresh : RANSAC threshold in px

    Returns
    -------
    list of dict per pair: ``i``, ``j``, ``n`` matches, ``H`` [3,3] or None, ``h_inliers`` fraction of the
    fundamental-matrix inliers that the homography explains (within ``thresh``), ``parallax`` median
    distance (px) of the F-inliers to the homography, ``rel`` [4,4] relative pose from the essential
    matrix (unit translation; identity when it cannot be estimated).
    """
    import cv2

    cv2.setRNGSeed(int(rng_seed))
    F = len(gray)
    out = []
    for g in gaps:
        for i in range(0, F - g):
            j = i + g
            p, q = _track_pair(gray[i], gray[j])
            d = dict(i=i, j=j, n=len(p), p=p, q=q, H=None, h_inliers=0.0, parallax=np.inf, rel=np.eye(4))
            if len(p) >= 15:
                H, mh = cv2.findHomography(p, q, cv2.RANSAC, thresh)
                Fm, mf = cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, thresh, 0.999)
                if H is not None and Fm is not None and mf is not None and Fm.shape == (3, 3):
                    inl = mf[:, 0] > 0
                    ph = cv2.perspectiveTransform(p[inl][None].astype(np.float64), H)[0]
                    r = np.linalg.norm(ph - q[inl], axis=1)
                    d.update(H=H, h_inliers=float((r < thresh).mean()) if len(r) else 0.0,
                             parallax=float(np.median(r)) if len(r) else np.inf)
                E, me = cv2.findEssentialMat(p, q, K, cv2.RANSAC, 0.999, thresh)
                if E is not None and E.shape == (3, 3):
                    _, R, t, _ = cv2.recoverPose(E, p, q, K, mask=me)
                    d["rel"] = np.eye(4)
                    d["rel"][:3, :3], d["rel"][:3, 3] = R, t[:, 0] / max(np.linalg.norm(t), 1e-12)
            out.append(d)
    return out


def rotation_from_homography(H, K):
    """Nearest rotation to ``K⁻¹ H K`` (pure-rotation homography ``x' ~ K R K⁻¹ x``)."""
    M = np.linalg.inv(K) @ H @ K
    M = M / np.cbrt(np.linalg.det(M))
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


def camera_free_masks(small_frames, K_small, pairs):
    """Dynamic masks without cameras: the motion prior's depth-free (Sampson) path on rough poses.

    Consecutive-frame relative poses (essential matrix of LK matches, unit translation: the Sampson
    distance does not depend on the translation's length) are chained into ``w2c`` and handed to
    :func:`engine.priors.motion.motion_mask` with ``depth=None``.
    """
    from ..priors.motion import motion_mask

    F = len(small_frames)
    w2c = np.tile(np.eye(4), (F, 1, 1))
    rel = {d["i"]: d["rel"] for d in pairs if d["j"] == d["i"] + 1}
    for f in range(1, F):
        w2c[f] = rel.get(f - 1, np.eye(4)) @ w2c[f - 1]
    K = np.repeat(K_small[None], F, 0)
    return motion_mask(np.asarray(small_frames), K, w2c, depth=None, max_width=max(small_frames.shape[1:3]))


def solve_cameras(clip: Clip, masks=None, *, max_size: int = 320, max_frames: int | None = None,
                  camera_model: str = "SIMPLE_RADIAL", max_features: int = 4096, overlap: int = 8,
                  min_registered: float = 0.5, mask_dilate: int = 5, num_threads: int = 2,
                  init_min_tri_angle: float = 4.0, seed: int = 0, workdir=None, log_level: int = 1,
                  verify_max_error: float = 4.0, fov_deg: float | None = None, peak_threshold: float | None = None,
                  quadratic_overlap: bool = True, init_max_error: float = 4.0, guided: bool = False,
                  abs_pose_max_error: float = 12.0, filter_max_reproj_error: float = 4.0, refine_focal: bool = True,
                  tri_min_angle: float = 1.5, auto_masks: bool = False, static_fallback: bool = False,
                  reporter=None, global_retry: bool = False, sample_frames: int | None = None) -> Clip:
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
    verify_max_error, init_max_error, abs_pose_max_error, filter_max_reproj_error : float
        COLMAP RANSAC / mapper thresholds in px at solve resolution (COLMAP defaults).
    fov_deg : float, optional
        Lens field of view across the long side: focal prior of the solve and the fallback's ``K``
        (default :data:`DEFAULT_FOV_DEG` where a prior is needed).
    peak_threshold, quadratic_overlap, guided, refine_focal, tri_min_angle :
        SIFT peak threshold, COLMAP's quadratic sequential overlap, guided matching, focal refinement
        in incremental BA, minimum triangulation angle (degrees) for new/kept points.
    auto_masks : bool
        Without ``masks``, mask moving regions with :func:`camera_free_masks` (module doc, step 1).
    global_retry : bool
        Retry with global SfM when incremental SfM registers too few frames (step 3).
    static_fallback : bool
        Fall back to :func:`fixed_centre_cameras` for low-parallax clips (step 5) instead of failing.
    sample_frames : int, optional
        Solve at most this many evenly spaced frames; interpolate the others (step 0).
    reporter : Reporter, optional
        Receives ``log`` events (solve summary; the fallback's warning).

    Returns
    -------
    Clip
        A copy with ``K``, ``w2c``, ``dist``, ``points``, ``scene_center/scale`` and
        ``meta['solve']``.
    """
    import cv2
    import pycolmap

    if sample_frames and clip.num_frames > sample_frames and not (max_frames and max_frames <= sample_frames):
        return _solve_sampled(clip, masks, int(sample_frames), dict(
            max_size=max_size, max_frames=max_frames, camera_model=camera_model, max_features=max_features,
            overlap=overlap, min_registered=min_registered, mask_dilate=mask_dilate, num_threads=num_threads,
            init_min_tri_angle=init_min_tri_angle, seed=seed, workdir=workdir, log_level=log_level,
            verify_max_error=verify_max_error, fov_deg=fov_deg, peak_threshold=peak_threshold,
            quadratic_overlap=quadratic_overlap, init_max_error=init_max_error, guided=guided,
            abs_pose_max_error=abs_pose_max_error, filter_max_reproj_error=filter_max_reproj_error,
            refine_focal=refine_focal, tri_min_angle=tri_min_angle, auto_masks=auto_masks,
            static_fallback=static_fallback, reporter=reporter, global_retry=global_retry))
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
    small = np.empty((F, h, w, 3), np.uint8)
    for i in range(F):
        img = clip.load_frame(i, downscale=1)
        small[i] = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (W, H) else img
    K_guess = default_K(w, h, fov_deg)
    pairs = None
    if auto_masks or static_fallback:
        gray = np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in small])
        pairs = pair_geometry(gray, K_guess, gaps=(1,), rng_seed=seed)
        if masks is None and auto_masks and F >= 2:
            if reporter is not None:
                reporter.log("camera solve: masking moving regions (motion prior on rough two-view poses)")
            masks = list(camera_free_masks(small, K_guess, pairs))
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
            cv2.imwrite(str(imdir / n), small[i][:, :, ::-1])
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
        if fov_deg or global_retry:  # a focal-length prior (COLMAP's own guess is 1.2 x the long side)
            f0 = default_K(w, h, fov_deg)[0, 0]
            extra = {"SIMPLE_PINHOLE": "", "PINHOLE": "", "SIMPLE_RADIAL": ",0", "RADIAL": ",0,0",
                     "OPENCV": ",0,0,0,0"}[camera_model]
            fx = f"{f0},{f0}" if camera_model in ("PINHOLE", "OPENCV") else f"{f0}"
            reader.camera_params = f"{fx},{w / 2},{h / 2}{extra}"
        if masks is not None:
            reader.mask_path = str(mdir)
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = num_threads
        ext.sift.max_num_features = max_features
        ext.use_gpu = False
        if peak_threshold:
            ext.sift.peak_threshold = float(peak_threshold)
        pycolmap.extract_features(db, imdir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        mopt = pycolmap.FeatureMatchingOptions()
        mopt.num_threads = num_threads
        mopt.use_gpu = False
        mopt.guided_matching = bool(guided)
        vopt = pycolmap.TwoViewGeometryOptions()
        vopt.ransac.max_error = float(verify_max_error)
        vopt.ransac.random_seed = int(seed)
        popt = pycolmap.SequentialPairingOptions()
        popt.overlap = overlap
        popt.loop_detection = False
        popt.quadratic_overlap = bool(quadratic_overlap)
        pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt, verification_options=vopt,
                                  device=pycolmap.Device.cpu)
        iopt = pycolmap.IncrementalPipelineOptions()
        iopt.num_threads = num_threads
        iopt.min_model_size = 3
        iopt.multiple_models = False
        iopt.mapper.init_min_tri_angle = float(init_min_tri_angle)
        iopt.mapper.num_threads = num_threads
        iopt.mapper.random_seed = int(seed)
        iopt.random_seed = int(seed)
        iopt.mapper.init_max_error = float(init_max_error)
        iopt.mapper.abs_pose_max_error = float(abs_pose_max_error)
        iopt.mapper.filter_max_reproj_error = float(filter_max_reproj_error)
        iopt.triangulation.random_seed = int(seed)
        _seed_all(iopt, int(seed))
        iopt.ba_refine_focal_length = bool(refine_focal)
        iopt.mapper.abs_pose_refine_focal_length = bool(refine_focal)
        iopt.triangulation.min_angle = float(tri_min_angle)
        iopt.mapper.filter_min_tri_angle = float(tri_min_angle)
        out = work / "sparse"
        out.mkdir(exist_ok=True)
        need = max(3, int(np.ceil(min_registered * F)))
        recs = pycolmap.incremental_mapping(db, imdir, out, options=iopt)
        mapper = "incremental"
        n_inc = max((r.num_reg_images() for r in recs.values()), default=0)
        if n_inc < need and global_retry and F >= 3:
            # low parallax (a panning camera): incremental SfM finds no initial pair with enough triangulation
            # angle, or cannot extend it; global SfM (rotation averaging + global positioning) registers every
            # frame whose rotation is known. The focal length is held at the FOV prior: it is barely observable.
            if reporter is not None:
                reporter.log(f"camera solve: incremental SfM registered {n_inc}/{F} frames; trying global SfM")
            gopt = pycolmap.GlobalPipelineOptions()
            gopt.num_threads = num_threads
            gopt.random_seed = int(seed)
            gopt.mapper.random_seed = int(seed)
            gopt.mapper.bundle_adjustment.refine_focal_length = False
            gopt.mapper.global_positioning.use_gpu = False
            _seed_all(gopt, int(seed))
            gopt.mapper.bundle_adjustment.ceres.use_gpu = False
            out2 = work / "sparse_global"
            out2.mkdir(exist_ok=True)
            grecs = pycolmap.global_mapping(db, imdir, out2, options=gopt)
            if max((r.num_reg_images() for r in grecs.values()), default=0) > n_inc:
                recs, mapper = grecs, "global"
            log.info("camera solve: incremental %d/%d, global %d/%d frames", n_inc, F,
                     max((r.num_reg_images() for r in grecs.values()), default=0), F)
    finally:
        pycolmap.logging.minloglevel = min_level
        if tmp is not None:
            tmp.cleanup()
    fix = ("Supply cameras (export them from Blender or use a dataset with poses), or use footage where "
           "the camera moves (translates) around a textured, mostly static scene.")
    rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
    nreg = rec.num_reg_images() if rec is not None else 0
    if nreg < need:
        why = (f"camera solve failed: no initial pair, no frames registered out of {F} (the camera may barely move, "
               "or the scene lacks texture)." if rec is None else
               f"camera solve registered only {nreg} of {F} frames (need {need}).")
        if static_fallback:
            fb = fixed_centre_cameras(clip, small, pairs, fov_deg=fov_deg, reason=why + " " + _parallax_summary(pairs),
                                      solve_scale=s, emit=False)
            if fb.meta["solve"]["num_registered"] >= need:
                msg = fb.meta["solve"]["warning"]
                log.warning(msg)
                if reporter is not None:
                    reporter.log(msg, level="warning")
                return fb
            why += (f" The fixed-centre (static / rotating camera) model does not fit either: only "
                    f"{fb.meta['solve']['num_registered']} of {F} frames link to their neighbour by a homography.")
        raise InputError(why, clip.source, fix)
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
    meta["solve"] = {"model": "sfm", "mapper": mapper, "registered": registered, "num_registered": int(nreg),
                     "mean_reproj_error": err, "num_points": int(len(xyz)), "solve_scale": s}
    if reporter is not None:
        reporter.log(f"camera solve ({mapper} SfM): {nreg}/{F} frames registered, mean reprojection error {err:.2f} px "
                     f"(at {max(w, h)} px), {len(xyz)} points")
    log.info("camera solve: %d/%d frames registered, mean reprojection error %.3f px, %d points",
             nreg, F, err, len(xyz))
    out_clip = dataclasses.replace(clip, K=Kf, w2c=w2c, dist=dist, points=xyz, point_colors=rgb,
                                   scene_center=c, scene_scale=sc, meta=meta)
    out_clip.validate_cameras()
    return out_clip


def _kabsch_rotation(u, v):
    """Rotation ``R`` minimising ``Σ |v − R u|²`` for unit rays ``u, v [N,3]``."""
    U, _, Vt = np.linalg.svd(v.T @ u)
    return U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def fixed_centre_cameras(clip: Clip, small, pairs, *, fov_deg: float | None = None, reason: str = "",
                         reporter=None, solve_scale: float = 1.0, min_inliers: int = 15, inlier_px: float = 1.0,
                         rotation_min_deg: float = 0.1, emit: bool = True) -> Clip:
    """Low-parallax fallback: every frame shares one camera centre (the world origin).

    Intrinsics: a centred pinhole with ``fov_deg`` (default :data:`DEFAULT_FOV_DEG`) across the long
    side, no distortion. Orientation: from consecutive-frame LK matches (``pairs`` from
    :func:`pair_geometry`, at the resolution of ``small``), the homography's inliers are lifted to unit
    rays with that ``K`` and the relative rotation is the Kabsch fit ``v ≈ R u``; rotations are chained
    from frame 0 (= world axes). When the whole clip turns by less than ``rotation_min_deg`` the camera is
    treated as static (identity rotations, ``model = 'static'``), else ``model = 'rotation'``. A frame
    whose link to its predecessor has fewer than ``min_inliers`` matches keeps the previous rotation
    and counts as unregistered. ``mean_reproj_error`` is the mean transfer error (full-resolution px) of
    the linked frames' inlier matches under the model (``x' ~ K R_j R_iᵀ K⁻¹ x``).

    Depth is unobservable from a fixed centre: the scale is arbitrary (``scene_scale`` 1), there are no
    sparse points, and the depth prior falls back to what it can do without parallax.
    """
    import cv2

    F, h, w = small.shape[:3]
    W, H = clip.width, clip.height
    Ks = default_K(w, h, fov_deg)
    Ki = np.linalg.inv(Ks)
    if pairs is None:
        gray = np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in small])
        pairs = pair_geometry(gray, Ks, gaps=(1,))
    link = {d["i"]: d for d in pairs if d["j"] == d["i"] + 1}
    rays = lambda x: (lambda r: r / np.linalg.norm(r, axis=1, keepdims=True))(  # noqa: E731
        np.c_[x, np.ones(len(x))] @ Ki.T)
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
        Rr = _kabsch_rotation(rays(p[inl]), rays(q[inl]))
        R[f] = Rr @ R[f - 1]
        registered[f] = True
        Hm = Ks @ Rr @ Ki
        pr = cv2.perspectiveTransform(p[inl][None].astype(np.float64), Hm)[0]
        errs.append(np.linalg.norm(pr - q[inl], axis=1) / solve_scale)
        n_inl += int(inl.sum())
        n_all += len(p)
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    model = "rotation" if ang.max() >= rotation_min_deg else "static"
    if model == "static":
        R[:] = np.eye(3)
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[:, :3, :3] = R
    K = default_K(W, H, fov_deg)
    err = float(np.concatenate(errs).mean()) if errs else 0.0
    fov = float(fov_deg or DEFAULT_FOV_DEG)
    meta = dict(clip.meta)
    meta["solve"] = {"model": model, "registered": registered, "num_registered": int(registered.sum()),
                     "mean_reproj_error": err, "num_points": 0, "solve_scale": solve_scale, "fov_deg": fov,
                     "max_rotation_deg": float(ang.max()),
                     "inlier_fraction": float(n_inl / n_all) if n_all else 0.0, "reason": reason}
    what = ("a static camera (all frames share one pose)" if model == "static" else
            f"a camera that only rotates about a fixed centre (up to {ang.max():.1f} degrees)")
    msg = (f"low parallax: {reason} Assuming {what} with a {fov:.0f} degree field of view across the long side "
           f"({int(registered.sum())}/{F} frames linked, mean transfer error {err:.2f} px). Depth cannot be "
           "measured from a fixed viewpoint, so geometry will be weak. For real cameras, track the camera in "
           "Blender and export a clip manifest, pass a COLMAP model, or set the lens with --fov.")
    meta["solve"]["warning"] = msg
    if emit:
        log.warning(msg)
        if reporter is not None:
            reporter.log(msg, level="warning")
    out = dataclasses.replace(clip, K=np.tile(K, (F, 1, 1)), w2c=w2c, dist=None, points=None, point_colors=None,
                              scene_center=np.zeros(3), scene_scale=1.0, meta=meta)
    out.validate_cameras()
    return out


def _parallax_summary(pairs) -> str:
    """One sentence on how well homographies explain consecutive-frame matches (low-parallax evidence)."""
    ok = [d for d in (pairs or []) if d["H"] is not None]
    if not ok:
        return "Too few matches between consecutive frames to measure parallax."
    hin = float(np.median([d["h_inliers"] for d in ok]))
    par = float(np.median([d["parallax"] for d in ok]))
    return (f"A homography explains {100 * hin:.0f}% of the matches between consecutive frames "
            f"(median parallax {par:.2f} px at solve resolution).")


def _solve_sampled(clip: Clip, masks, n: int, kw: dict) -> Clip:
    """Solve ``n`` evenly spaced frames, interpolate the poses of the others (see :func:`interpolate_poses`)."""
    idx = np.unique(np.round(np.linspace(0, clip.num_frames - 1, n)).astype(int))
    sub = solve_cameras(clip.subset(idx), None if masks is None else [masks[i] for i in idx], **kw)
    F = clip.num_frames
    info = dict(sub.meta["solve"])
    registered = np.zeros(F, bool)
    registered[idx] = info["registered"]
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[idx] = sub.w2c
    w2c = interpolate_poses(w2c, registered, clip.times) if registered.any() else w2c
    info.update(registered=registered, sampled=idx)
    meta = dict(clip.meta)
    meta["solve"] = info
    out = dataclasses.replace(clip, K=np.repeat(sub.K[:1], F, 0), w2c=w2c,
                              dist=None if sub.dist is None else np.repeat(sub.dist[:1], F, 0), points=sub.points,
                              point_colors=sub.point_colors, scene_center=sub.scene_center,
                              scene_scale=sub.scene_scale, meta=meta)
    out.validate_cameras()
    return out


def _seed_all(opts, seed: int, depth: int = 0) -> None:
    """Set every ``random_seed`` field of a pycolmap options object and its nested option groups."""
    for name in dir(opts):
        if name.startswith("_") or depth > 4:
            continue
        try:
            val = getattr(opts, name)
        except Exception:  # noqa: BLE001 - properties that cannot be read
            continue
        if name == "random_seed":
            setattr(opts, name, seed)
        elif hasattr(val, "summary") and not callable(val) and type(val).__module__.startswith("pycolmap"):
            _seed_all(val, seed, depth + 1)
