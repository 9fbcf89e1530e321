"""Camera solve for clips without cameras (pycolmap on the CPU), and Umeyama alignment.

:func:`solve_cameras` runs named steps (``engine.pipeline.open_clip`` turns on everything marked
*pipeline*):

0. *pipeline* ``sample_frames``: at most 60 evenly spaced frames are solved; the others get
   interpolated poses (:func:`interpolate_poses`) and ``registered = False``.
1. :func:`_solve_frames` — frames resized so the long side is at most ``max_size`` (320 px: on the
   synthetic test room a 60-frame 640x480 clip solves in ~55 s at 320 px but fails to register at 640).
2. Moving regions — ``masks`` (per frame ``float [H,W]`` in ``[0,1]``, 1 = dynamic) or, *pipeline*
   ``auto_masks``, :func:`engine.io.solve_twoview.camera_free_masks` (the motion prior's depth-free
   Sampson path on rough two-view poses). Masked pixels give COLMAP no features and the parallax
   evidence no matches.
3. *pipeline* ``static_fallback`` — evidence first
   (:func:`engine.io.solve_twoview.parallax_evidence`, :func:`engine.io.solve_select.translation_evidence`):
   when a homography explains the static matches to within the noise even between frames far apart,
   the footage shows no translation and the fixed-centre model
   (:func:`engine.io.solve_fixed.fixed_centre_cameras`: one centre, rotations from homographies,
   ``fov_deg`` across the long side; ``model 'static'`` below 0.1 degrees of rotation, else
   ``'rotation'``) is chosen without running SfM — whatever SfM would "find" there is translation the
   footage does not show (a fixed-camera clip with moving content once gave global SfM a camera
   moving ~2 units per frame).
4. SfM (:mod:`engine.io.solve_colmap`): SIFT (``max_features``), one shared camera
   (``camera_model``), sequential matching, incremental mapping; *pipeline* ``global_retry``: global
   SfM with the focal length held at the FOV prior when incremental SfM is implausible or
   under-registers (a panning camera has sub-pixel parallax between neighbours). Each candidate must
   pass :func:`engine.io.solve_select.sfm_problems` (registered fraction, reprojection error, point
   count, no jumps in the camera path); the first healthy one is kept.
5. No healthy SfM: the fixed-centre model when ``static_fallback`` and homographies link enough
   frames, else an :class:`InputError` naming what failed and how to supply cameras.

Exactly one line announces the chosen model and why (a warning for the fixed-centre model, whose
geometry is weak) through ``reporter`` and the module logger; the same goes into ``meta['solve']``:
``model`` (``'sfm'`` with ``mapper`` ``'incremental'|'global'``, or ``'static'`` / ``'rotation'``),
``reason``, ``rejected`` (candidates refused and why), ``registered [F] bool``, ``num_registered``,
``mean_reproj_error`` (SfM: px at solve resolution; fixed-centre: mean homography transfer error in
full-resolution px), ``num_points``, ``solve_scale``, ``parallax_px`` / ``parallax_floor_px`` (the
evidence, when measured), ``seed``, fixed-centre extras (``fov_deg``, ``max_rotation_deg``,
``inlier_fraction``, ``warning``) and ``sampled`` frame indices. Frames that do not register keep their
place with **interpolated** poses (centre linearly, rotation by slerp).

Determinism: the same clip and ``seed`` give the same cameras — pycolmap runs single-threaded
(``num_threads=1``) with every random seed set (see :mod:`engine.io.solve_colmap`); OpenCV's RANSAC
is seeded and LK tracking has no randomness. The solved world frame is COLMAP's (arbitrary
similarity); ``scene_center``/``scene_scale`` come from the sparse points.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.poses import camera_centres, interpolate_poses, umeyama_similarity
from . import solve_select as sel
from .clip import Clip, scene_bounds
from .solve_colmap import extract_and_match, global_sfm, incremental_sfm, largest, sfm_cameras, write_inputs
from .solve_fixed import DEFAULT_FOV_DEG, default_K, fixed_centre_cameras, fixed_centre_note
from .solve_twoview import camera_free_masks, pair_geometry, parallax_evidence, parallax_summary

__all__ = ["DEFAULT_FOV_DEG", "default_K", "interpolate_poses", "solve_cameras", "umeyama_similarity"]

log = logging.getLogger(__name__)

NO_CAMERAS_FIX = ("Supply cameras (export them from Blender or use a dataset with poses), or use footage where "
                  "the camera moves (translates) around a textured, mostly static scene.")


def solve_cameras(clip: Clip, masks=None, *, max_size: int = 320, max_frames: int | None = None,
                  camera_model: str = "SIMPLE_RADIAL", max_features: int = 4096, overlap: int = 8,
                  min_registered: float = 0.5, mask_dilate: int = 5, num_threads: int = 1,
                  init_min_tri_angle: float = 4.0, seed: int = 0, workdir=None, log_level: int = 1,
                  verify_max_error: float = 4.0, fov_deg: float | None = None, peak_threshold: float | None = None,
                  quadratic_overlap: bool = True, init_max_error: float = 4.0, guided: bool = False,
                  abs_pose_max_error: float = 12.0, filter_max_reproj_error: float = 4.0, refine_focal: bool = True,
                  tri_min_angle: float = 1.5, auto_masks: bool = False, static_fallback: bool = False,
                  reporter=None, global_retry: bool = False, sample_frames: int | None = None,
                  min_parallax_px: float = sel.MIN_PARALLAX_PX) -> Clip:
    """Solve per-frame cameras (shared intrinsics) for ``clip``; see the module docstring for the steps.

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
    num_threads : int
        pycolmap threads; 1 (default) makes the solve reproducible, more threads can change the result.
    init_min_tri_angle : float
        Minimum triangulation angle (degrees) of the initial pair; lower than COLMAP's
        16° default because video has small baselines between frames.
    seed : int
        Seed of every random choice (COLMAP's PRNG and RANSAC, OpenCV's RANSAC).
    workdir : path, optional
        Keep the COLMAP database/images here (default: a temporary folder, removed).
    log_level : int
        Least severe COLMAP (glog) message shown while solving: 0 info, 1 warning
        (default: COLMAP's per-step INFO lines are hidden), 2 error, 3 fatal only.
    verify_max_error, init_max_error, abs_pose_max_error, filter_max_reproj_error : float
        COLMAP RANSAC / mapper thresholds in px at solve resolution (COLMAP defaults).
    fov_deg : float, optional
        Lens field of view across the long side: focal prior of the solve and the fixed-centre ``K``
        (default :data:`DEFAULT_FOV_DEG` where a prior is needed).
    peak_threshold, quadratic_overlap, guided, refine_focal, tri_min_angle :
        SIFT peak threshold, COLMAP's quadratic sequential overlap, guided matching, focal refinement
        in incremental BA, minimum triangulation angle (degrees) for new/kept points.
    auto_masks : bool
        Without ``masks``, mask moving regions with :func:`camera_free_masks` (step 2).
    global_retry : bool
        Try global SfM when incremental SfM is implausible or registers too few frames (step 4).
    static_fallback : bool
        Let the fixed-centre model compete (steps 3 and 5) instead of failing on low parallax.
    min_parallax_px : float
        Parallax (px at solve resolution) below which the footage shows no translation (step 3).
    reporter : Reporter, optional
        Receives the progress lines and the one line announcing the chosen model.
    sample_frames : int, optional
        Solve at most this many evenly spaced frames and interpolate the others (step 0).

    Returns
    -------
    Clip
        A copy with ``K``, ``w2c``, ``dist``, ``points``, ``scene_center/scale`` and
        ``meta['solve']``.
    """
    kw = dict(max_size=max_size, camera_model=camera_model, max_features=max_features, overlap=overlap,
              min_registered=min_registered, mask_dilate=mask_dilate, num_threads=num_threads,
              init_min_tri_angle=init_min_tri_angle, seed=seed, workdir=workdir, log_level=log_level,
              verify_max_error=verify_max_error, fov_deg=fov_deg, peak_threshold=peak_threshold,
              quadratic_overlap=quadratic_overlap, init_max_error=init_max_error, guided=guided,
              abs_pose_max_error=abs_pose_max_error, filter_max_reproj_error=filter_max_reproj_error,
              refine_focal=refine_focal, tri_min_angle=tri_min_angle, auto_masks=auto_masks,
              static_fallback=static_fallback, reporter=reporter, global_retry=global_retry,
              min_parallax_px=min_parallax_px)
    if sample_frames and clip.num_frames > sample_frames and not (max_frames and max_frames <= sample_frames):
        return _solve_sampled(clip, masks, int(sample_frames), dict(kw, max_frames=max_frames))
    if max_frames and clip.num_frames > max_frames:
        idx = np.unique(np.round(np.linspace(0, clip.num_frames - 1, int(max_frames))).astype(int))
        clip = clip.subset(idx)
        masks = None if masks is None else [masks[i] for i in idx]
    if masks is not None and len(masks) != clip.num_frames:
        raise InputError(f"{len(masks)} masks for {clip.num_frames} frames.", clip.source, "Give one mask per frame.")
    return _solve(clip, masks, kw)


def _solve(clip: Clip, masks, kw: dict) -> Clip:
    """Steps 1-5 of the module docstring on every frame of ``clip``."""
    import cv2

    F, seed = clip.num_frames, int(kw["seed"])
    small, s = _solve_frames(clip, kw["max_size"])
    h, w = small.shape[1:3]
    gray = np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in small])
    need = max(3, int(np.ceil(kw["min_registered"] * F)))
    rep = kw["reporter"]
    pairs, evidence = None, None
    if kw["auto_masks"] or kw["static_fallback"]:
        pairs = pair_geometry(gray, default_K(w, h, kw["fov_deg"]), gaps=(1,), rng_seed=seed)
        if masks is None and kw["auto_masks"] and F >= 2:
            _say(rep, "camera solve: masking moving regions (motion prior on rough two-view poses)")
            masks = list(camera_free_masks(small, default_K(w, h, kw["fov_deg"]), pairs))
    why = "the SfM solve is healthy (parallax not measured)"
    if kw["static_fallback"] and F >= 3:
        evidence = parallax_evidence(gray, _masks_at(masks, h, w), rng_seed=seed)
        moves, why = sel.translation_evidence(evidence, kw["min_parallax_px"])
        if not moves:
            fixed = fixed_centre_cameras(clip, small, pairs, fov_deg=kw["fov_deg"], solve_scale=s)
            if fixed.meta["solve"]["num_registered"] >= need:
                return _announce_fixed(fixed, why, [], evidence, seed, rep)
            why = (f"{why}, but homographies link only {fixed.meta['solve']['num_registered']} of {F} frames "
                   "(fixed-centre model rejected)")
    cams, mapper, rejected = _run_sfm(small, masks, need, kw)
    if cams is not None:
        return _sfm_clip(clip, cams, mapper, s, (w, h), why, rejected, evidence, seed, rep)
    why = "; ".join(rejected) or "no SfM model"
    if kw["static_fallback"]:
        fixed = fixed_centre_cameras(clip, small, pairs, fov_deg=kw["fov_deg"], solve_scale=s)
        if fixed.meta["solve"]["num_registered"] >= need:
            return _announce_fixed(fixed, "no SfM solve is plausible (" + why + "). " + parallax_summary(pairs),
                                   rejected, evidence, seed, rep)
        why += (f". The fixed-centre (static / rotating camera) model does not fit either: only "
                f"{fixed.meta['solve']['num_registered']} of {F} frames link to their neighbour by a homography")
    raise InputError(f"camera solve failed: {why}.", clip.source, NO_CAMERAS_FIX)


def _solve_frames(clip: Clip, max_size: int):
    """Frames at solve resolution: ``(small [F,h,w,3] uint8, scale w / W)``."""
    import cv2

    W, H = clip.width, clip.height
    s = min(1.0, max_size / max(W, H))
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    small = np.empty((clip.num_frames, h, w, 3), np.uint8)
    for i in range(clip.num_frames):
        img = clip.load_frame(i, downscale=1)
        small[i] = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (W, H) else img
    return small, s


def _masks_at(masks, h: int, w: int):
    """``masks`` (any resolution) resized to ``[F,h,w]`` float32, or None."""
    import cv2

    if masks is None:
        return None
    return np.stack([cv2.resize(np.asarray(m, np.float32), (w, h), interpolation=cv2.INTER_LINEAR) for m in masks])


def _run_sfm(small, masks, need: int, kw: dict):
    """Incremental SfM, then (``global_retry``) global SfM; the first healthy candidate wins.

    Returns ``(cams or None, mapper, rejected)`` with ``cams`` from :func:`sfm_cameras` and
    ``rejected`` one sentence per refused candidate.
    """
    import pycolmap

    F = len(small)
    opts = dict(kw, focal_prior=bool(kw["fov_deg"] or kw["global_retry"]))
    tmp = tempfile.TemporaryDirectory(prefix="ms_solve_") if kw["workdir"] is None else None
    work = Path(tmp.name if tmp else kw["workdir"])
    # COLMAP logs every step at INFO to stderr (hundreds of lines); keep warnings and errors
    min_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(int(min_level), int(kw["log_level"]))
    rejected = []
    try:
        names = write_inputs(work, small, masks, kw["mask_dilate"])
        db = extract_and_match(work, names, small.shape[2:0:-1], opts, masks is not None)
        mappers = [("incremental", incremental_sfm)]
        if kw["global_retry"] and F >= 3:
            mappers.append(("global", global_sfm))
        for mapper, run in mappers:
            if mapper == "global":
                _say(kw["reporter"], f"camera solve: incremental SfM rejected ({rejected[-1]}); trying global SfM")
            rec = largest(run(work, db, opts))
            cams = sfm_cameras(rec, names) if rec is not None else None
            problems = sel.sfm_problems(cams, need) if cams is not None else [f"no initial pair (0 of {F} registered)"]
            if not problems:
                return cams, mapper, rejected
            rejected.append(f"{mapper} SfM: " + ", ".join(problems))
            log.info("camera solve: %s", rejected[-1])
    finally:
        pycolmap.logging.minloglevel = min_level
        if tmp is not None:
            tmp.cleanup()
    return None, None, rejected


def _sfm_clip(clip, cams, mapper, s, size, why, rejected, evidence, seed, rep) -> Clip:
    """The SfM cameras at full resolution (unregistered frames interpolated) with ``meta['solve']``."""
    F, (w, h) = clip.num_frames, size
    registered = cams["registered"]
    w2c = interpolate_poses(cams["w2c"], registered, clip.times)
    Kf = np.tile(cams["K"], (F, 1, 1))
    Kf[:, 0, :] *= clip.width / w  # K_full = diag(W/w, H/h, 1) K_small; distortion acts on normalised coords
    Kf[:, 1, :] *= clip.height / h
    dist = None if cams["dist"] is None else np.tile(cams["dist"], (F, 1))
    xyz = cams["points"]
    c, sc = scene_bounds(camera_centres(w2c), xyz)
    info = {"model": "sfm", "mapper": mapper, "registered": registered, "num_registered": int(registered.sum()),
            "mean_reproj_error": cams["mean_reproj_error"], "num_points": int(len(xyz)), "solve_scale": s,
            "rejected": list(rejected), "seed": seed, **_evidence_fields(evidence)}
    info["reason"] = why + ("; " + "; ".join(rejected) if rejected else "")
    _announce(rep, sel.sfm_line(info, mapper, info["reason"]), "info")
    meta = dict(clip.meta)
    meta["solve"] = info
    out = dataclasses.replace(clip, K=Kf, w2c=w2c, dist=dist, points=xyz, point_colors=cams["colors"],
                              scene_center=c, scene_scale=sc, meta=meta)
    out.validate_cameras()
    return out


def _announce_fixed(fixed: Clip, why: str, rejected, evidence, seed, rep) -> Clip:
    """Record why the fixed-centre model was chosen and warn in one line."""
    info = fixed.meta["solve"]
    info.update(reason=why, rejected=list(rejected), seed=seed, **_evidence_fields(evidence))
    line = sel.fixed_line(info, why, fixed_centre_note(info))
    info["warning"] = line
    _announce(rep, line, "warning")
    return fixed


def _evidence_fields(evidence) -> dict:
    """``parallax_px`` / ``parallax_floor_px`` of the measured evidence (empty when not measured)."""
    if evidence is None:
        return {}
    return {"parallax_px": float(evidence["parallax_px"]), "parallax_floor_px": float(evidence["floor_px"])}


def _announce(reporter, line: str, level: str) -> None:
    """The chosen model's one line: to ``reporter`` when given (the logger then keeps it at debug level, so
    a CLI user does not read it twice), else to the module logger at ``level``."""
    if reporter is not None:
        reporter.log(line, level=level)
        log.debug(line)
    else:
        log.log(logging.WARNING if level == "warning" else logging.INFO, line)


def _say(reporter, message: str, level: str = "info") -> None:
    if reporter is not None:
        reporter.log(message, level=level)


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
