"""pycolmap structure-from-motion for the camera solve: inputs, deterministic options, SfM runs.

Determinism: every run calls ``pycolmap.set_random_seed(seed)``, seeds every ``random_seed`` field of
the option objects (RANSAC, mapper, triangulation, global pipeline) and uses ``num_threads`` (1 by
default): COLMAP's multi-threaded matching, mapping and Ceres solves are where run-to-run differences
came from (bedroom.mp4 with 2 threads: 60/60 registered every time, but 18-217 sparse points and a
different world on re-runs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .colmap import reconstruction_cameras
from .solve_fixed import default_K

CAMERA_EXTRA = {"SIMPLE_PINHOLE": "", "PINHOLE": "", "SIMPLE_RADIAL": ",0", "RADIAL": ",0,0", "OPENCV": ",0,0,0,0"}


def write_inputs(work: Path, small, masks, mask_dilate: int, source=None) -> list[str]:
    """Write frames ``small [F,h,w,3]`` (and feature masks from ``masks``) as PNGs under ``work``.

    A mask pixel ``≥ 0.5`` (dilated by ``mask_dilate`` px) is dynamic: COLMAP extracts no feature there.
    Returns the image names.
    """
    import cv2

    F, h, w = small.shape[:3]
    imdir, mdir = work / "images", work / "masks"
    imdir.mkdir(parents=True, exist_ok=True)
    names = [f"{i:06d}.png" for i in range(F)]
    for i, n in enumerate(names):
        cv2.imwrite(str(imdir / n), small[i][:, :, ::-1])
        if masks is None:
            continue
        mdir.mkdir(exist_ok=True)
        m = np.asarray(masks[i], dtype=np.float32)
        if m.ndim != 2:
            raise InputError(f"mask {i} has shape {m.shape}; expected [H,W].", source, "Give 2D masks.")
        dyn = (cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR) >= 0.5).astype(np.uint8)
        if mask_dilate > 0:
            dyn = cv2.dilate(dyn, np.ones((2 * mask_dilate + 1,) * 2, np.uint8))
        cv2.imwrite(str(mdir / (n + ".png")), np.where(dyn > 0, 0, 255).astype(np.uint8))
    return names


def extract_and_match(work: Path, names, size, opts: dict, use_masks: bool) -> Path:
    """SIFT features (one shared camera) and sequential matching into ``work/database.db``.

    ``size`` is ``(w, h)``; ``opts`` holds ``camera_model``, ``focal_prior``, ``fov_deg``,
    ``max_features``, ``peak_threshold``, ``num_threads``, ``guided``, ``verify_max_error``, ``seed``,
    ``overlap``, ``quadratic_overlap`` (see :func:`engine.io.solve.solve_cameras`).
    """
    import pycolmap

    w, h = size
    db = work / "database.db"
    if db.exists():
        db.unlink()
    model = opts["camera_model"]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    if opts["focal_prior"]:  # COLMAP's own guess is 1.2 x the long side
        f0 = default_K(w, h, opts["fov_deg"])[0, 0]
        fx = f"{f0},{f0}" if model in ("PINHOLE", "OPENCV") else f"{f0}"
        reader.camera_params = f"{fx},{w / 2},{h / 2}{CAMERA_EXTRA[model]}"
    if use_masks:
        reader.mask_path = str(work / "masks")
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts["num_threads"]
    ext.sift.max_num_features = opts["max_features"]
    ext.use_gpu = False
    if opts["peak_threshold"]:
        ext.sift.peak_threshold = float(opts["peak_threshold"])
    pycolmap.extract_features(db, work / "images", image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = opts["num_threads"]
    mopt.use_gpu = False
    mopt.guided_matching = bool(opts["guided"])
    vopt = pycolmap.TwoViewGeometryOptions()
    vopt.ransac.max_error = float(opts["verify_max_error"])
    _seed_all(vopt, int(opts["seed"]))
    popt = pycolmap.SequentialPairingOptions()
    popt.overlap = opts["overlap"]
    popt.loop_detection = False
    popt.quadratic_overlap = bool(opts["quadratic_overlap"])
    pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt, verification_options=vopt,
                              device=pycolmap.Device.cpu)
    return db


def incremental_sfm(work: Path, db: Path, opts: dict) -> dict:
    """COLMAP incremental mapping (one model); returns ``{id: Reconstruction}``."""
    import pycolmap

    n, seed = opts["num_threads"], int(opts["seed"])
    iopt = pycolmap.IncrementalPipelineOptions()
    iopt.num_threads = n
    iopt.min_model_size = 3
    iopt.multiple_models = False
    iopt.mapper.num_threads = n
    iopt.mapper.init_min_tri_angle = float(opts["init_min_tri_angle"])
    iopt.mapper.init_max_error = float(opts["init_max_error"])
    iopt.mapper.abs_pose_max_error = float(opts["abs_pose_max_error"])
    iopt.mapper.filter_max_reproj_error = float(opts["filter_max_reproj_error"])
    iopt.ba_refine_focal_length = bool(opts["refine_focal"])
    iopt.mapper.abs_pose_refine_focal_length = bool(opts["refine_focal"])
    iopt.triangulation.min_angle = float(opts["tri_min_angle"])
    iopt.mapper.filter_min_tri_angle = float(opts["tri_min_angle"])
    _seed_all(iopt, seed)
    out = work / "sparse"
    out.mkdir(exist_ok=True)
    pycolmap.set_random_seed(seed)
    return pycolmap.incremental_mapping(db, work / "images", out, options=iopt)


def global_sfm(work: Path, db: Path, opts: dict) -> dict:
    """GLOMAP-style global mapping (rotation averaging + global positioning), focal held at its prior.

    Low parallax (a panning camera) leaves incremental SfM without an initial pair; global SfM
    registers every frame whose rotation is known. The focal length is barely observable then, so it
    stays at the FOV prior.
    """
    import pycolmap

    seed = int(opts["seed"])
    gopt = pycolmap.GlobalPipelineOptions()
    gopt.num_threads = opts["num_threads"]
    gopt.mapper.num_threads = opts["num_threads"]
    gopt.mapper.bundle_adjustment.refine_focal_length = False
    gopt.mapper.global_positioning.use_gpu = False
    gopt.mapper.bundle_adjustment.ceres.use_gpu = False
    _seed_all(gopt, seed)
    out = work / "sparse_global"
    out.mkdir(exist_ok=True)
    pycolmap.set_random_seed(seed)
    return pycolmap.global_mapping(db, work / "images", out, options=gopt)


def largest(recs: dict):
    """The reconstruction with the most registered images (None when there is none)."""
    return max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None


def sfm_cameras(rec, names: list[str]) -> dict:
    """Cameras and points of a reconstruction, laid out over ``names`` (solve resolution).

    Returns
    -------
    dict with ``registered [F] bool``, ``w2c [F,4,4]`` (identity where not registered), ``K [3,3]``,
    ``dist [k]`` or None, ``points [P,3]``, ``colors [P,3] uint8``, ``mean_reproj_error`` (px).
    """
    try:
        rnames, K, w2c_r, dist_r, _ = reconstruction_cameras(rec)
    except ValueError as exc:
        raise InputError(f"unsupported camera model {exc}.", None, "Use SIMPLE_RADIAL or OPENCV.") from None
    F = len(names)
    pos = [names.index(n) for n in rnames]
    registered = np.zeros(F, dtype=bool)
    registered[pos] = True
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[pos] = w2c_r
    pts = rec.points3D
    return {"registered": registered, "w2c": w2c, "K": K[0], "dist": None if dist_r is None else dist_r[0],
            "points": np.array([p.xyz for p in pts.values()], dtype=np.float64).reshape(-1, 3),
            "colors": np.array([p.color for p in pts.values()], dtype=np.uint8).reshape(-1, 3),
            "mean_reproj_error": float(rec.compute_mean_reprojection_error())}


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
