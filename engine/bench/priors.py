"""Priors + camera-solve bench against the ground truth of ``tools/synth_scene.py`` scenes.

Per scene (generated fresh with ``--preset``, or existing folders given with ``--scene``)
it evaluates the train camera (``left_*``) frames at their native resolution and prints
one row per metric group:

``sfm``
    pycolmap camera solve from the frames alone (cameras removed; ``--solve-masks gt``
    excludes GT dynamic regions from the features instead): registered frames, mean
    reprojection error (px at solve resolution), camera-centre error after a similarity
    (Umeyama) alignment of the registered centres to GT, as % of the scene extent
    (``centre_err_pct``, target ≤ 2 %: diagonal of the bounding box of the GT camera
    centres and the GT surface points seen by the clip) and of the camera path extent
    (``centre_err_pct_path``: largest distance between two GT camera centres), rotation
    error (degrees, after alignment) and focal-length error (%).
``depth``
    The weight-free ``sparse`` depth prior, computed with the GT cameras (so in scene
    units) vs GT z-depth: AbsRel ``mean(|d − d*| / d*)`` on static pixels, all pixels and
    dynamic pixels, and δ < 1.25 on static pixels.
``dynamic``
    The ``motion`` mask (p ≥ 0.5) vs the GT mask: IoU pooled over all pixels of the clip
    (target ≥ 0.5), per-frame mean IoU, precision, recall.
``tracks``
    The ``flow`` tracker vs GT 2D tracks. GT: the track's first frame pixel is lifted
    with the GT depth (bilinear, only where the 2×2 neighbourhood is one surface) and GT
    camera. Static surface (object id 0): that world point is fixed and is projected into
    every frame. Moving objects: the nearest GT trajectory points of the same object
    (≤ 8 within 0.25 units) give a per-frame rigid fit (Kabsch) that carries the point
    along. A GT position is *visible* when its depth agrees with the GT depth map (2 %
    on the 2×2 neighbourhood), *occluded* when the surface is clearly in front, else
    ambiguous (not scored). End-point error (px) over (track, frame) pairs after the
    track's first frame where the track says visible and GT is visible (``epe_median_1f`` /
    ``_8f``: 1 / 8 frames after it); ``within_2px``;
    ``false_visible`` = fraction of the track's visible pairs that GT says are occluded;
    ``survival`` = tracks alive at frame 0 still alive at the last frame (``survival_gt``:
    the fraction of them whose GT point is still visible there — the ceiling);
    ``alive_ratio`` = live tracks at the last frame ÷ at frame 0 (re-seeding included).
``object_tracks``
    The tracks the trainer gets (with the weight-free depth the flow's plus those of the
    hinges and the compact moving blobs, :mod:`engine.priors.dynamic_depth`) per moving object
    of the scene: ``tracks_<name>``, the median frames each is visible (``len_<name>``), the
    median end-point error after its first frame (``epe_<name>``, px; the same ground truth:
    a rolling ball's translation-only blob tracks miss its turn) and ``tracked8_<name>``. The
    large-motion family (``--kind large``): the thin fast forearm's tracks are the short ones.
``runtime``
    Seconds per prior stage (tracks, depth, dynamic mask, tokens), the solve and the GT
    evaluation, plus the machine (CPU, cores, Python) and the 1-minute load average.

``--json`` prints one JSON object per row (the keys above); the text table is in long
format (``scene, clip, group, metric, value``) because the groups have different keys.

Needs bpy (only to generate scenes; ``--scene`` skips that) and pycolmap (``sfm`` row).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import numpy as np

HELP = "priors + camera solve vs ground truth on tools/synth_scene.py scenes"

REPO = Path(__file__).resolve().parents[2]
GENERATOR = REPO / "tools" / "synth_scene.py"


def add_arguments(parser) -> None:
    parser.add_argument("--scene", action="append", metavar="DIR",
                        help="existing generated scene folder (repeatable); default: generate one with --preset")
    parser.add_argument("--preset", choices=("tiny", "small"), default="small")
    parser.add_argument("--frames", type=int, default=None,
                        help="frames to generate (with --scene: use the first N train frames)")
    parser.add_argument("--seed", type=int, default=0, help="generator seed")
    parser.add_argument("--kind", default="all", choices=("all", "articulated", "large", "nonrigid", "rigid"),
                        help="generated scene family (tools/synth_scene.py --kind; 'large': the large-motion family)")
    parser.add_argument("--keep", metavar="DIR", help="generate into DIR and keep it (default: a temp folder)")
    parser.add_argument("--num-points", type=int, default=None, help="track density (PriorConfig.num_points)")
    parser.add_argument("--solve-masks", choices=("none", "gt"), default="none",
                        help="masks for the camera solve: none (frames alone) or the GT dynamic masks")
    parser.add_argument("--skip-solve", action="store_true", help="no sfm row")
    parser.add_argument("--flow-backend", choices=("auto", "dis", "onnx"), default=None,
                        help="optical flow for tracks and mask (PriorConfig.flow_backend; default dis)")
    parser.add_argument("--flow-model", help="RAFT-contract ONNX flow model (implies --flow-backend onnx)")
    parser.add_argument("--flow-width", type=int, default=None, help="working width of the learned flow")
    parser.add_argument("--flow-alone", action="store_true",
                        help="use the learned flow alone, not fused with DIS per pixel (PriorConfig.flow_fuse_dis)")
    parser.add_argument("--depth-model", help="ONNX monocular depth model (research weights: benchmark only)")
    parser.add_argument("--depth-output", choices=("inverse", "depth"), default=None,
                        help="what --depth-model predicts (default: its sidecar, else inverse)")
    parser.add_argument("--depth-check", choices=("auto", "off"), default=None,
                        help="check --depth-model against the triangulated static points and set it aside when it "
                             "explains them less than 10%% better than a flat depth (auto, the engine's default) or use it "
                             "whatever it scores (off: measures the model itself)")
    parser.add_argument("--depth-sidecar", metavar="JSON",
                        help="input settings for --depth-model, as its sidecar JSON's keys (a JSON object or a file; "
                             "e.g. '{\"size_multiple\": 64, \"mean\": [0,0,0], \"std\": [1,1,1]}')")


# ----------------------------------------------------------------------------------------
# scene generation and ground truth


def generate(out_dir, preset: str = "small", frames: int | None = None, seed: int = 0, kind: str = "all") -> Path:
    """Run ``tools/synth_scene.py`` (needs bpy) in a subprocess; returns the scene folder."""
    if not GENERATOR.is_file():
        raise FileNotFoundError(f"{GENERATOR} is missing: pass an existing scene with --scene")
    cmd = [sys.executable, str(GENERATOR), "--out", str(out_dir), "--preset", preset, "--seed", str(seed), "--quiet"]
    if kind != "all":
        cmd += ["--kind", kind]
    if frames:
        cmd += ["--frames", str(int(frames))]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=str(REPO))
    lines = [ln for ln in proc.stdout.strip().splitlines() if ln.strip()]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"scene generator failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return Path(json.loads(lines[-1])["out"])


@dataclasses.dataclass
class SceneGT:
    """Ground truth of the train frames: ``K [F,3,3]``, ``w2c [F,4,4]``, ``depth [F,H,W]``,
    ``mask [F,H,W] bool``, ``object_id [F,H,W]``, ``points [M,F,3]``, ``point_object [M]``."""

    K: np.ndarray
    w2c: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    object_id: np.ndarray
    points: np.ndarray
    point_object: np.ndarray
    info: dict


def load_scene(scene_dir, frames: int | None = None):
    """``(train clip, frames uint8 [F,H,W,3], SceneGT)`` for the ``left_*`` frames."""
    import cv2

    from ..io import load_clip

    scene_dir = Path(scene_dir)
    clip = load_clip(scene_dir)
    idx = list(clip.split["train"])
    if frames:
        idx = idx[: int(frames)]
    train = clip.subset(idx)
    fi = [int(str(i).rsplit("_", 1)[1]) for i in train.frame_ids]
    gt = scene_dir / "gt"
    cams = np.load(gt / "cameras.npz", allow_pickle=False)
    traj = np.load(gt / "trajectories.npz", allow_pickle=False)
    depth = np.stack([np.load(gt / "depth" / f"{i}.npy", allow_pickle=False) for i in train.frame_ids])
    mask = np.stack([cv2.imread(str(gt / "mask" / f"{i}.png"), cv2.IMREAD_UNCHANGED) > 127 for i in train.frame_ids])
    oid = np.stack([cv2.imread(str(gt / "object_id" / f"{i}.png"), cv2.IMREAD_UNCHANGED) for i in train.frame_ids])
    info = json.loads((gt / "objects.json").read_text())
    sgt = SceneGT(K=cams["K"][fi].astype(np.float64), w2c=cams["w2c_train"][fi].astype(np.float64),
                  depth=depth.astype(np.float32), mask=mask, object_id=oid.astype(np.int32),
                  points=traj["points"][:, fi].astype(np.float64), point_object=traj["object_id"].astype(np.int32),
                  info=info)
    imgs = np.stack([train.load_frame(i, downscale=1) for i in range(train.num_frames)])
    return train, imgs, sgt


def _centres(w2c):
    return -np.einsum("fji,fj->fi", w2c[:, :3, :3], w2c[:, :3, 3])


def _project(K, w2c, X):
    """World points ``X [P,F,3]`` (or [P,3]) in every frame → ``uv [P,F,2]``, ``z [P,F]``."""
    X = np.asarray(X, np.float64)
    if X.ndim == 2:
        X = np.broadcast_to(X[:, None], (X.shape[0], len(w2c), 3))
    Xc = np.einsum("fij,pfj->pfi", w2c[:, :3, :3], X) + w2c[None, :, :3, 3]
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = np.einsum("fij,pfj->pfi", K, Xc)
        uv = uvw[..., :2] / uvw[..., 2:3]
    return uv, z


def _sample_depth(depth, f, uv, tol):
    """GT depth around continuous pixel ``uv`` in frame(s) ``f``.

    Pixel centres are at +0.5; the 2×2 neighbourhood of centres around ``uv`` is used.
    Returns ``(depth, planar, dmin, dmax, inside)``: depth interpolated bilinearly in
    *inverse* depth (exact on a plane), ``planar`` where the four samples lie on one plane
    (inverse depth affine within ``tol``, i.e. no silhouette in between), the min / max of
    the four samples, and whether ``uv`` is in the image.
    """
    F, H, W = depth.shape
    x, y = uv[..., 0] - 0.5, uv[..., 1] - 0.5
    inside = (np.isfinite(x) & np.isfinite(y) & (uv[..., 0] >= 0) & (uv[..., 0] < W)
              & (uv[..., 1] >= 0) & (uv[..., 1] < H))
    x = np.clip(np.where(inside, x, 0), 0, W - 1)
    y = np.clip(np.where(inside, y, 0), 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(int), W - 2)
    y0 = np.minimum(np.floor(y).astype(int), H - 2)
    ax, ay = x - x0, y - y0
    i00, i01 = 1.0 / depth[f, y0, x0], 1.0 / depth[f, y0, x0 + 1]
    i10, i11 = 1.0 / depth[f, y0 + 1, x0], 1.0 / depth[f, y0 + 1, x0 + 1]
    inv = (i00 * (1 - ax) + i01 * ax) * (1 - ay) + (i10 * (1 - ax) + i11 * ax) * ay
    planar = np.abs(i00 + i11 - i01 - i10) <= tol * inv
    stack = 1.0 / np.stack([i00, i01, i10, i11], -1)
    return 1.0 / inv, planar, stack.min(-1), stack.max(-1), inside


def visible_points(gt: SceneGT, tol: float = 0.01) -> np.ndarray:
    """``[M] bool``: GT trajectory points visible in at least one frame."""
    uv, z = _project(gt.K, gt.w2c, gt.points)
    F = len(gt.w2c)
    f = np.broadcast_to(np.arange(F), z.shape)
    d, planar, _, _, inside = _sample_depth(gt.depth, f, uv, tol)
    return (inside & planar & (z > 0) & (np.abs(z - d) < tol * np.abs(z))).any(1)


def _kabsch(src, dst):
    """Batched rigid fit ``dst ≈ R·src + t``: ``src, dst [..., n, 3]`` → ``R [...,3,3]``, ``t [...,3]``, rms."""
    ms, md = src.mean(-2, keepdims=True), dst.mean(-2, keepdims=True)
    cov = np.einsum("...ni,...nj->...ij", dst - md, src - ms)
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    S = np.broadcast_to(np.eye(3), U.shape).copy()
    S[..., 2, 2] = d
    R = U @ S @ Vt
    t = md[..., 0, :] - np.einsum("...ij,...j->...i", R, ms[..., 0, :])
    res = dst - (np.einsum("...ij,...nj->...ni", R, src) + t[..., None, :])
    return R, t, np.sqrt((res ** 2).sum(-1).mean(-1))


def gt_tracks(tracks, gt: SceneGT, tol: float = 0.02, radius: float = 0.25, k: int = 8, max_fit_rms: float = 0.02):
    """Ground-truth 2D positions for predicted tracks (see the module docstring).

    Returns a dict: ``xy [P,F,2]`` GT positions, ``visible [P,F]`` / ``occluded [P,F]`` bool
    (neither = ambiguous or unknown), ``f0 [P]`` first frame, ``valid [P]`` (a GT could be
    built), ``dynamic [P]`` (seeded on a moving object), ``object [P]`` the object id under the seed.
    """
    P, F = tracks.visible.shape
    depth = gt.depth
    vis = np.asarray(tracks.visible, bool)
    q = np.asarray(tracks.query_frame, int).clip(0, F - 1)
    first = np.where(vis.any(1), vis.argmax(1), q)
    f0 = np.where(vis[np.arange(P), q], q, first)
    uv0 = tracks.xy[np.arange(P), f0].astype(np.float64)
    z0, planar0, _, _, inside = _sample_depth(depth, f0, uv0, tol)
    H, W = depth.shape[1:]
    col = np.clip(np.floor(uv0[:, 0]).astype(int), 0, W - 1)
    row = np.clip(np.floor(uv0[:, 1]).astype(int), 0, H - 1)
    obj = gt.object_id[f0, row, col]
    # one surface under the seed: the 2x2 depths lie on one plane and their object ids agree
    x0 = np.clip(np.floor(uv0[:, 0] - 0.5).astype(int), 0, W - 2)
    y0 = np.clip(np.floor(uv0[:, 1] - 0.5).astype(int), 0, H - 2)
    ids = np.stack([gt.object_id[f0, y0, x0], gt.object_id[f0, y0, x0 + 1], gt.object_id[f0, y0 + 1, x0],
                    gt.object_id[f0, y0 + 1, x0 + 1]], -1)
    valid = inside & planar0 & (ids == ids[:, :1]).all(1)
    obj = np.where(valid, ids[:, 0], obj)
    # lift to world at f0
    Kinv = np.linalg.inv(gt.K[f0])
    ray = np.einsum("pij,pj->pi", Kinv, np.concatenate([uv0, np.ones((P, 1))], 1))
    Xc = ray * z0[:, None]
    R0, t0 = gt.w2c[f0, :3, :3], gt.w2c[f0, :3, 3]
    X0 = np.einsum("pji,pj->pi", R0, Xc - t0)
    Xw = np.repeat(X0[:, None], F, 1)  # static: fixed
    dynamic = valid & (obj > 0)
    fit_ok = np.ones((P, F), bool)
    for f in np.unique(f0[dynamic]):
        sel = np.flatnonzero(dynamic & (f0 == f))
        for o in np.unique(obj[sel]):
            s = sel[obj[sel] == o]
            cand = np.flatnonzero(gt.point_object == o)
            if len(cand) < 3:
                valid[s] = False
                continue
            d = np.linalg.norm(X0[s, None] - gt.points[cand, f][None], axis=-1)  # [S, C]
            kk = min(k, len(cand))
            nn = np.argpartition(d, kk - 1, axis=1)[:, :kk]
            dn = np.take_along_axis(d, nn, 1)
            ok = (dn <= radius).sum(1) >= 3
            valid[s[~ok]] = False
            s, nn, dn = s[ok], nn[ok], dn[ok]
            if not len(s):
                continue
            # far neighbours: replace by the nearest (duplicates keep the fit well-posed)
            nn = np.where(dn <= radius, nn, nn[np.arange(len(s)), dn.argmin(1)][:, None])
            pts = gt.points[cand[nn]]  # [S, k, F, 3]
            src = np.broadcast_to(pts[:, :, f][:, None], (len(s), F, kk, 3))
            dst = pts.transpose(0, 2, 1, 3)  # [S, F, k, 3]
            Rf, tf, rms = _kabsch(src, dst)
            Xw[s] = np.einsum("sfij,sj->sfi", Rf, X0[s]) + tf
            # near-collinear neighbours leave the rotation about their line undetermined
            sv = np.linalg.svd(src[:, 0] - src[:, 0].mean(1, keepdims=True), compute_uv=False)
            fit_ok[s] = (rms <= max_fit_rms) & (sv[:, 1:2] > 0.1 * sv[:, :1])
    uv, z = _project(gt.K, gt.w2c, Xw)
    fr = np.broadcast_to(np.arange(F), z.shape)
    d, planar, dmin, dmax, inside = _sample_depth(depth, fr, uv, tol)
    front = inside & (z > 0)
    gvis = front & planar & (np.abs(z - d) <= tol * z) & fit_ok & valid[:, None]
    gocc = front & (dmax < z * (1 - tol)) & fit_ok & valid[:, None]
    gocc |= ~inside & valid[:, None] & fit_ok  # left the image: should not be visible either
    return {"xy": uv, "visible": gvis, "occluded": gocc, "f0": f0, "valid": valid, "dynamic": dynamic & valid,
            "object": obj}


# ----------------------------------------------------------------------------------------
# metric groups


def solve_metrics(train, gt: SceneGT, masks=None) -> dict:
    """Camera solve from frames alone vs GT cameras (``sfm`` row, without the scene name)."""
    from ..errors import InputError
    from ..io.solve import solve_cameras, umeyama_similarity

    bare = dataclasses.replace(train, K=None, w2c=None, dist=None, points=None, point_colors=None,
                               scene_center=None, scene_scale=None, meta=dict(train.meta))
    F = train.num_frames
    t0 = time.perf_counter()
    try:
        solved = solve_cameras(bare, masks=masks)
    except InputError as exc:
        return {"registered": 0, "frames": F, "error": str(exc).splitlines()[0],
                "time_s": time.perf_counter() - t0}
    dt = time.perf_counter() - t0
    meta = solved.meta["solve"]
    reg = np.asarray(meta["registered"], bool)
    C_gt = _centres(gt.w2c)
    C = solved.camera_centers()
    s, R, t = umeyama_similarity(C[reg], C_gt[reg])
    C_al = s * C @ R.T + t
    err = np.linalg.norm(C_al - C_gt, axis=1)
    pts = gt.points[visible_points(gt)]
    allp = np.concatenate([C_gt, pts.reshape(-1, 3)]) if len(pts) else C_gt
    scene_ext = float(np.linalg.norm(allp.max(0) - allp.min(0)))
    path_ext = float(np.max(np.linalg.norm(C_gt[:, None] - C_gt[None], axis=-1)))
    # rotation: solved camera rotation expressed in the GT world is R_est @ R^T
    Rw = np.einsum("fij,kj->fik", solved.w2c[:, :3, :3], R)
    rel = np.einsum("fij,fkj->fik", gt.w2c[:, :3, :3], Rw)
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    f_est = 0.5 * (solved.K[:, 0, 0] + solved.K[:, 1, 1])
    f_gt = 0.5 * (gt.K[:, 0, 0] + gt.K[:, 1, 1])
    return {"registered": int(reg.sum()), "frames": F, "reproj_px": float(meta["mean_reproj_error"]),
            "sfm_points": int(meta["num_points"]),
            "centre_err_pct": float(100 * err[reg].mean() / scene_ext),
            "centre_err_max_pct": float(100 * err[reg].max() / scene_ext),
            "centre_err_pct_path": float(100 * err[reg].mean() / path_ext),
            "centre_err_all_pct": float(100 * err.mean() / scene_ext),
            "rot_err_deg": float(ang[reg].mean()),
            "focal_err_pct": float(100 * np.mean(np.abs(f_est - f_gt) / f_gt)),
            "scene_extent": scene_ext, "path_extent": path_ext, "time_s": dt}


def depth_metrics(depth, gt: SceneGT) -> dict:
    d, g = np.asarray(depth, np.float64), gt.depth.astype(np.float64)
    rel = np.abs(d - g) / g
    ratio = np.maximum(d / g, g / np.maximum(d, 1e-9))
    st, dy = ~gt.mask, gt.mask
    return {"absrel_static": float(rel[st].mean()), "absrel_all": float(rel.mean()),
            "absrel_dynamic": float(rel[dy].mean()) if dy.any() else None,
            "medrel_static": float(np.median(rel[st])),
            "delta1_static": float((ratio[st] < 1.25).mean()),
            "medrel_dynamic": float(np.median(rel[dy])) if dy.any() else None,
            "delta1_dynamic": float((ratio[dy] < 1.25).mean()) if dy.any() else None}


def mask_metrics(dynamic, gt: SceneGT, thresh: float = 0.5) -> dict:
    pred = np.asarray(dynamic) >= thresh
    g = gt.mask
    tp = float((pred & g).sum()); fp = float((pred & ~g).sum()); fn = float((~pred & g).sum())
    inter = (pred & g).sum((1, 2)); union = (pred | g).sum((1, 2))
    per = inter[union > 0] / union[union > 0]
    return {"iou": tp / max(tp + fp + fn, 1.0), "iou_frame_mean": float(per.mean()) if len(per) else None,
            "precision": tp / max(tp + fp, 1.0), "recall": tp / max(tp + fn, 1.0),
            "f1": 2 * tp / max(2 * tp + fp + fn, 1.0), "gt_dynamic_frac": float(g.mean()), "pred_dynamic_frac": float(pred.mean())}


def _eight_frames_on(vis, epe, G) -> tuple[np.ndarray, np.ndarray]:
    """``(reach [P], there [P])``: a moving track whose point the ground truth sees 8 frames
    after its first; and whether the track is there then (visible, within 3 px)."""
    P, F = vis.shape
    at8 = np.minimum(G["f0"] + 8, F - 1)
    reach = G["dynamic"] & (G["f0"] + 8 < F) & G["visible"][np.arange(P), at8]
    return reach, vis[np.arange(P), at8] & (epe[np.arange(P), at8] < 3.0)


def track_metrics(tracks, gt: SceneGT) -> dict:
    P, F = tracks.visible.shape
    G = gt_tracks(tracks, gt)
    vis = np.asarray(tracks.visible, bool)
    off = np.arange(F)[None] - G["f0"][:, None]  # frames since the track's first frame
    after = off > 0
    pairs = vis & G["visible"] & after
    epe = np.linalg.norm(tracks.xy.astype(np.float64) - G["xy"], axis=-1)
    e = epe[pairs]
    dyn = G["dynamic"][:, None] & pairs
    sta = ~G["dynamic"][:, None] & pairs
    judged = vis & after & (G["visible"] | G["occluded"])
    start = vis[:, 0]
    n0 = int(start.sum())
    end_alive = start & vis[:, -1]
    stat = lambda a, fn: float(fn(a)) if len(a) else None  # noqa: E731
    # moving parts: is the track there (visible and within 3 px) where GT says the point is visible?
    good = vis & (epe < 3.0)
    gdyn = G["dynamic"][:, None] & G["visible"] & after
    d8, there8 = _eight_frames_on(vis, epe, G)
    return {"tracks": int(P), "tracks_dynamic": int(G["dynamic"].sum()), "gt_valid": float(G["valid"].mean()),
            "pairs": int(pairs.sum()),
            "epe_median": stat(e, np.median), "epe_mean": stat(e, np.mean),
            "epe_p90": stat(e, lambda a: np.percentile(a, 90)),
            "epe_median_static": stat(epe[sta], np.median), "epe_median_dynamic": stat(epe[dyn], np.median),
            "epe_median_1f": stat(epe[pairs & (off == 1)], np.median),
            "epe_median_8f": stat(epe[pairs & (off == 8)], np.median),
            "within_2px": stat(e, lambda a: (a < 2).mean()),
            "false_visible": float((judged & G["occluded"]).sum() / max(judged.sum(), 1)),
            "survival": float(end_alive.sum() / max(n0, 1)),
            "survival_gt": float((start & G["visible"][:, -1]).sum() / max(n0, 1)),
            "alive_ratio": float(vis[:, -1].sum() / max(n0, 1)),
            "epe_mean_dynamic": stat(epe[dyn], np.mean), "within_2px_dynamic": stat(epe[dyn], lambda a: (a < 2).mean()),
            "false_visible_dynamic": float((judged & G["occluded"] & G["dynamic"][:, None]).sum()
                                           / max((judged & G["dynamic"][:, None]).sum(), 1)),
            "coverage_dynamic": float((good & gdyn).sum() / max(gdyn.sum(), 1)),
            "tracked8_dynamic": float(there8[d8].mean()) if d8.any() else None,
            "track_len_dynamic": stat((vis[G["dynamic"]].sum(1)).astype(float), np.median)}


def object_track_metrics(tracks, gt: SceneGT) -> dict:
    """Per moving object (``gt.info["object_ids"]``), the tracks seeded on it: ``tracks_<name>``
    their count, ``len_<name>`` the median frames each is visible, ``epe_<name>`` the median
    end-point error (px) over its visible pairs after its first frame where the ground truth
    sees the point, ``tracked8_<name>`` the share still there (visible, within 3 px) 8 frames
    later where the ground truth sees it (None where no such track reaches). What the node paths
    of each object are fitted to: a thin fast part whose tracks live a frame or two gets paths
    that follow it only near those frames."""
    F = tracks.visible.shape[1]
    G = gt_tracks(tracks, gt)
    vis = np.asarray(tracks.visible, bool)
    after = np.arange(F)[None] > G["f0"][:, None]
    epe = np.linalg.norm(tracks.xy.astype(np.float64) - G["xy"], axis=-1)
    obj = G["object"]
    reach8, good8 = _eight_frames_on(vis, epe, G)
    out = {}
    for name, oid in sorted(gt.info.get("object_ids", {}).items(), key=lambda kv: kv[1]):
        if int(oid) == 0:  # the static scene: the "tracks" row's static figures
            continue
        on = G["dynamic"] & (obj == int(oid))
        pairs = vis & G["visible"] & after & on[:, None]
        out[f"tracks_{name}"] = int(on.sum())
        out[f"len_{name}"] = float(np.median(vis[on].sum(1))) if on.any() else None
        out[f"epe_{name}"] = float(np.median(epe[pairs])) if pairs.any() else None
        out[f"tracked8_{name}"] = float(good8[on & reach8].mean()) if (on & reach8).any() else None
    return out


def moving_object_tracks(pri, cfg, gt: SceneGT):
    """The tracks the trainer gets: with the weight-free depth, those of
    :func:`engine.priors.dynamic_depth.moving_object_depth` (the flow's plus the hinges' and the
    compact blobs'), with the ground-truth cameras; with a depth model or file, the flow's."""
    from ..geometry.camera import scene_extent
    from ..pipeline import depth_source
    from ..priors.dynamic_depth import moving_object_depth
    from ..protocol import Reporter

    if depth_source(cfg) != "weight-free":
        return pri.tracks
    _, tracks, _ = moving_object_depth(pri, cfg, gt.K, gt.w2c, scene_extent(gt.w2c, pri.depth), Reporter(quiet=True))
    return tracks


@contextmanager
def _stage_timer(times: dict):
    """Time the four prior stages inside :func:`engine.priors.compute_priors`."""
    from ..priors import cache as C

    targets = [(C._tracks, "track_points", "tracks"), (C._depth, "estimate_depth", "depth"),
               (C._depth, "model_predictions", "depth"),  # a depth model runs once, outside both passes
               (C._motion, "dynamic_mask", "dynamic"), (C._tokens, "extract_tokens", "tokens")]
    patches = []
    for mod, name, key in targets:
        fn = getattr(mod, name)

        def timed(*a, __fn=fn, __key=key, **kw):
            t0 = time.perf_counter()
            try:
                return __fn(*a, **kw)
            finally:
                times[__key] = times.get(__key, 0.0) + time.perf_counter() - t0

        patches.append(mock.patch.object(mod, name, timed))
    for p in patches:
        p.start()
    try:
        yield times
    finally:
        for p in patches:
            p.stop()


def prior_config(args):
    """PriorConfig from the bench's prior options."""
    from ..priors import PriorConfig

    cfg = PriorConfig()
    if getattr(args, "num_points", None):
        cfg.num_points = int(args.num_points)
    if getattr(args, "flow_backend", None):
        cfg.flow_backend = args.flow_backend
    if getattr(args, "flow_model", None):
        cfg.flow_backend, cfg.flow_model = "onnx", args.flow_model
    if getattr(args, "flow_width", None):
        cfg.flow_model_width = int(args.flow_width)
    if getattr(args, "flow_alone", False):
        cfg.flow_fuse_dis = False
    if getattr(args, "depth_model", None):
        from ..priors.onnx_util import parse_settings

        cfg.depth_backend, cfg.depth_model = "onnx", str(Path(args.depth_model).resolve())
        cfg.depth_output = args.depth_output
        if args.depth_sidecar:
            cfg.depth_sidecar = parse_settings(args.depth_sidecar)
        if getattr(args, "depth_check", None):
            cfg.depth_check = args.depth_check
    return cfg


def bench_scene(scene_dir, frames: int | None = None, num_points: int | None = None, solve: bool = True,
                solve_masks: str = "none", cfg=None) -> list[dict]:
    """All rows for one generated scene folder (``cfg``: PriorConfig, default weight-free)."""
    from ..priors import PriorConfig, compute_priors
    from ..priors.flow import resolve_flow_backend

    load_avg0 = os.getloadavg()[0]
    train, imgs, gt = load_scene(scene_dir, frames)
    F, H, W = imgs.shape[:3]
    preset, name = str(gt.info.get("preset", "")), Path(scene_dir).name
    base = {"scene": name if name == preset or not preset else f"{preset}:{name}",
            "frames": F, "res": f"{W}x{H}"}
    rows = []
    if solve:
        m = solve_metrics(train, gt, masks=list(gt.mask.astype(np.float32)) if solve_masks == "gt" else None)
        m.pop("frames", None)
        rows.append({**base, "group": "sfm" if solve_masks == "none" else "sfm(gt masks)", **m})
    if cfg is None:
        cfg = PriorConfig() if num_points is None else PriorConfig(num_points=int(num_points))
    fbk, fmodel = resolve_flow_backend(cfg.flow_backend, cfg.flow_model)
    learned = (f":{Path(fmodel).stem}@{cfg.flow_model_width}" + ("+dis" if cfg.flow_fuse_dis else "")) if fmodel else ""
    base["priors"] = ",".join([f"flow={fbk}{learned}",
                               f"depth={cfg.depth_backend}" + (f":{Path(cfg.depth_model).stem}" if cfg.depth_model else "")])
    stages: dict = {}
    t0 = time.perf_counter()
    with _stage_timer(stages):
        pri = compute_priors(imgs, gt.K, gt.w2c, cfg, cache_dir=None)
    total = time.perf_counter() - t0
    check = getattr(pri, "depth_check", None) or {}  # a depth model's check (engine/priors/depth_check.py)
    rows.append({**base, "group": "depth", **depth_metrics(pri.depth, gt), "time_s": stages.get("depth"),
                 **({"model_used": check["used"], "model_ratio": check["ratio"]} if check else {})})
    rows.append({**base, "group": "dynamic", **mask_metrics(pri.dynamic, gt), "time_s": stages.get("dynamic")})
    t1 = time.perf_counter()
    tm = track_metrics(pri.tracks, gt)
    gt_s = time.perf_counter() - t1
    rows.append({**base, "group": "tracks", **tm, "time_s": stages.get("tracks")})
    t2 = time.perf_counter()
    moving = moving_object_tracks(pri, cfg, gt)
    moving_s = time.perf_counter() - t2
    rows.append({**base, "group": "object_tracks", "tracks": int(len(moving.xy)),
                 **object_track_metrics(moving, gt), "time_s": moving_s})
    rows.append({**base, "group": "runtime", "tracks_s": stages.get("tracks"), "depth_s": stages.get("depth"),
                 "dynamic_s": stages.get("dynamic"), "tokens_s": stages.get("tokens"), "priors_total_s": total,
                 "solve_s": rows[0].get("time_s") if solve else None, "gt_eval_s": gt_s,
                 "load_avg_1m": f"{load_avg0:.1f}->{os.getloadavg()[0]:.1f}"})
    return rows


def run(args) -> list[dict]:
    from .common import machine_description

    rows = []
    scenes = [Path(s) for s in (args.scene or [])]
    tmp = None
    try:
        if not scenes:
            if args.keep:
                out = Path(args.keep)
            else:
                tmp = tempfile.TemporaryDirectory(prefix="ms_bench_priors_")
                out = Path(tmp.name) / args.preset
            t0 = time.perf_counter()
            scenes = [generate(out, args.preset, args.frames, args.seed, args.kind)]
            gen_s = time.perf_counter() - t0
            print(f"generated {args.preset} scene in {gen_s:.1f} s: {scenes[0]}", file=sys.stderr)
        cfg = prior_config(args)
        for sc in scenes:
            rows += bench_scene(sc, frames=args.frames if args.scene else None, num_points=args.num_points,
                                solve=not args.skip_solve, solve_masks=args.solve_masks, cfg=cfg)
    finally:
        if tmp is not None:
            tmp.cleanup()
    rows.append({"group": "machine", **machine_description()})
    return rows if args.json else text_rows(rows)


def text_rows(rows: list[dict]) -> list[dict]:
    """Long format for the text table (groups have different keys): ``scene, group, metric, value``."""
    out = []
    for row in rows:
        clip = f"{row['frames']}f {row['res']}" if "frames" in row else "-"
        for k, v in row.items():
            if k in ("scene", "group", "frames", "res", "priors"):
                continue
            label = row.get("scene", "-") + (f" [{row['priors']}]" if "priors" in row else "")
            out.append({"scene": label, "clip": clip, "group": row["group"], "metric": k,
                        "value": v if isinstance(v, (int, float)) or v is None else str(v)})
    return out
