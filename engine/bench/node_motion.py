"""Node motion after training: a trained bundle's node splines vs a generated scene's GT.

``engine.bench nodes`` measures the *initial* nodes; this module measures what training
left in ``nodes.npz`` (what Blender keys as F-curves). For every training camera of the
bundle the node splines are evaluated at the camera's time and compared with the GT
trajectories (``gt/trajectories.npz``) at that frame, by the same RBF-blended node-motion
protocol as :func:`engine.bench.nodes.evaluate_gt` (K=4 nearest nodes at reference frames
first / middle / last; each node's rotation turns the point's offset from it). ``traj_ratio_dyn = traj_err_dyn / zero_motion_dyn``: 1 for nodes
that do not move, 0 for nodes that follow the ground truth; < 0.5 is "2x closer than zero
motion". :func:`rotation_error` scores how the nodes on moving objects turn against the
objects' own rigid rotations.
"""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import torch

from .nodes import _rbf_deform_error, _zero_motion_error


def _torch_nodes(nodes) -> types.SimpleNamespace:
    """The spline fields of a ``bundle.NodeArrays`` as float32 tensors (what the error needs)."""
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return types.SimpleNamespace(key_times=as_t(nodes.key_times), pos_keys=as_t(nodes.pos_keys),
                                 pos_tangents=as_t(nodes.pos_tangents), radii=as_t(nodes.radii),
                                 rot_keys=as_t(nodes.rot_keys), rot_tangents=as_t(nodes.rot_tangents))


def trajectory_error(nodes, points: np.ndarray, times: np.ndarray, dynamic: np.ndarray) -> dict:
    """Node-predicted vs GT trajectory error of the dynamic points, and the zero-motion baseline.

    Parameters
    ----------
    nodes : ``bundle.NodeArrays`` (numpy splines: key_times (K,), pos_keys/pos_tangents
        (N, K, 3), rot_keys/rot_tangents (N, K, 4), radii (N,)).
    points : (M, F, 3) GT world positions at the F evaluated frames.
    times : (F,) engine times of those frames.
    dynamic : (M,) bool, the points on moving objects.

    Returns
    -------
    dict: ``traj_err_dyn`` / ``zero_motion_dyn`` (fractions of the scene extent, the
    diagonal of the GT points' bounding box), ``traj_ratio_dyn``, ``*_abs`` in scene units.
    """
    pts = np.asarray(points, np.float32)
    dyn = np.asarray(dynamic, bool)
    if not dyn.any():
        raise ValueError("the ground truth has no dynamic points")
    err = _rbf_deform_error(_torch_nodes(nodes), pts[dyn], np.asarray(times, np.float32))
    zero = _zero_motion_error(pts[dyn])
    flat = pts.reshape(-1, 3)
    ext = float(np.linalg.norm(flat.max(0) - flat.min(0)))
    e, z = float(err.mean()), float(zero.mean())
    return {"traj_err_dyn": e / ext, "zero_motion_dyn": z / ext, "traj_ratio_dyn": e / z if z > 0 else None,
            "traj_err_dyn_abs": e, "zero_motion_dyn_abs": z}


def rotation_error(nodes, points: np.ndarray, times: np.ndarray, object_id: np.ndarray, dynamic: np.ndarray,
                   max_dist: float | None = None) -> dict:
    """How well the nodes on moving objects turn with them.

    Each node is matched, at the middle evaluated frame ``m``, to its nearest ground-truth
    point; nodes whose match is a moving point within ``max_dist`` (default: 2 % of the scene
    extent) are scored. The object's rotation from ``m`` to every frame ``f`` is the rigid
    (Kabsch) fit of its points; the node's is ``q(t_f) ⊗ q(t_m)⁻¹`` of its rotation spline.
    The error is the angle between the two.

    Parameters
    ----------
    nodes : ``bundle.NodeArrays`` (key_times, pos_keys/pos_tangents, rot_keys/rot_tangents).
    points : (M, F, 3) GT; times : (F,) engine times; object_id : (M,) int; dynamic : (M,) bool.

    Returns
    -------
    dict: ``rot_err_dyn_deg`` (median over scored nodes and frames), ``rot_err_dyn_p90_deg``,
    ``rot_gt_dyn_deg`` (median GT turn: the error of never turning), ``rot_nodes`` (nodes
    scored); the angles are None when no node is scored.
    """
    from ..geometry.hermite import hermite_eval, hermite_eval_quat
    from ..geometry.quaternion import quat_conj, quat_from_matrix, quat_identity, quat_mul, quat_normalize
    from ..geometry.rigid import weighted_kabsch

    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    pts, t = as_t(points), as_t(times)
    f = pts.shape[1]
    m = f // 2
    kt = as_t(nodes.key_times)
    pos = hermite_eval(kt, as_t(nodes.pos_keys), as_t(nodes.pos_tangents), t)  # [N, F, 3]
    rot = quat_normalize(hermite_eval_quat(kt, as_t(nodes.rot_keys), as_t(nodes.rot_tangents), t))  # [N, F, 4]
    flat = pts.reshape(-1, 3)
    ext = float((flat.max(0).values - flat.min(0).values).norm())
    max_dist = 0.02 * ext if max_dist is None else max_dist
    d = torch.cdist(pos[:, m], pts[:, m])  # [N, M]
    dist, near = d.min(1)
    dyn = torch.as_tensor(np.asarray(dynamic, bool))
    obj = torch.as_tensor(np.asarray(object_id))
    scored = (dist <= max_dist) & dyn[near]
    empty = {"rot_err_dyn_deg": None, "rot_err_dyn_p90_deg": None, "rot_gt_dyn_deg": None, "rot_nodes": 0}
    if not bool(scored.any()):
        return empty
    errs, gts = [], []
    ident = quat_identity(dtype=torch.float64)
    angle = lambda a, b: 2 * torch.acos((a * b).sum(-1).abs().clamp(max=1.0))  # noqa: E731
    for o in torch.unique(obj[near[scored]]).tolist():  # loop over objects (a handful)
        sel = torch.nonzero(scored & (obj[near] == o)).squeeze(1)
        op = pts[obj == o]  # [Mo, F, 3]
        src = op[:, m].unsqueeze(0).expand(f, -1, -1)
        R, _, ok = weighted_kabsch(src, op.permute(1, 0, 2), torch.ones(f, op.shape[0], dtype=torch.float64))
        q_gt = quat_from_matrix(R)  # [F, 4] turn of the object since frame m
        q_node = quat_mul(rot[sel], quat_conj(rot[sel, m:m + 1]))  # [n, F, 4]
        e = angle(q_node, q_gt.unsqueeze(0).expand_as(q_node))[:, ok]
        errs.append(e.reshape(-1))
        gts.append(angle(q_gt[ok], ident.expand(int(ok.sum()), 4)).repeat(len(sel)))
    e, g = torch.cat(errs), torch.cat(gts)
    deg = lambda x: float(torch.rad2deg(x))  # noqa: E731
    return {"rot_err_dyn_deg": deg(e.median()), "rot_err_dyn_p90_deg": deg(torch.quantile(e, 0.9)),
            "rot_gt_dyn_deg": deg(g.median()), "rot_nodes": int(scored.sum())}


def bundle_train_frames(bundle, scene_dir) -> tuple[list[dict], list[str]]:
    """``(cameras, frame ids)``: a bundle's training cameras and the generated scene's frame
    (``left_NNNNNN``) each one shows -- the camera's clip frame is ``clip_index``, else its frame
    number − the clip's start."""
    from ..io import load_clip

    clip = load_clip(scene_dir)
    start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
    cams = [c for c in bundle.scene["cameras"] if c.get("split", "train") == "train"]
    ids = [str(clip.frame_ids[int(c["clip_index"]) if "clip_index" in c else int(c["frame"]) - start])
           for c in cams]
    return cams, ids


def bundle_train_gt(bundle, scene_dir) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points (M, F, 3), times (F,), dynamic (M,))``: the GT at a bundle's training cameras.

    Each camera's scene frame (:func:`bundle_train_frames`), ``left_NNNNNN``, has the number
    that indexes ``gt/trajectories.npz``.
    """
    cams, ids = bundle_train_frames(bundle, scene_dir)
    idx = [int(i.rsplit("_", 1)[1]) for i in ids]
    times = [float(c["time"]) for c in cams]
    with np.load(Path(scene_dir) / "gt" / "trajectories.npz", allow_pickle=False) as traj:
        points, dynamic = traj["points"][:, idx], traj["is_dynamic"].astype(bool)
    return points, np.asarray(times, np.float32), dynamic


def trained_trajectory_error(bundle_dir, scene_dir) -> dict:
    """:func:`trajectory_error` and :func:`rotation_error` of the bundle's ``nodes.npz`` at
    its training cameras."""
    from ..bundle import load_bundle

    bundle = load_bundle(bundle_dir)
    if bundle.nodes is None:
        raise ValueError(f"{bundle_dir} has no nodes.npz")
    points, times, dynamic = bundle_train_gt(bundle, scene_dir)
    with np.load(Path(scene_dir) / "gt" / "trajectories.npz", allow_pickle=False) as traj:
        object_id = traj["object_id"]
    return {**trajectory_error(bundle.nodes, points, times, dynamic),
            **rotation_error(bundle.nodes, points, times, object_id, dynamic)}
