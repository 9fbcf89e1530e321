"""A trained model and its training data as result-bundle arrays (:mod:`engine.bundle`).

:meth:`engine.train.trainer.Trainer.export_bundle` writes them with the run's scene.json.
"""

from __future__ import annotations

import torch

from .. import bundle as B
from ..geometry.quaternion import quat_normalize
from .data import TrainingData
from .model import DynamicScene


def bundle_arrays(model: DynamicScene) -> tuple[B.NodeArrays, B.GaussianArrays]:
    """The model's nodes (centres [N, 3], radii [N], Hermite keys and tangents [N, K, ...],
    ``p_dyn``, binding [G, k], graph [N, k] or None, lifespans [G] when any) and Gaussians (means [G, 3],
    normalised quats [G, 4], log-scales, opacity logits, SH [G, C, 3]) as numpy arrays."""
    m = model
    key_times, pos_keys, pos_tan, rot_keys, rot_tan = m.export_splines()
    nodes = B.NodeArrays(
        centers=m.node_centers.cpu().numpy(), radii=m.node_radii().detach().cpu().numpy(),
        key_times=key_times.cpu().numpy(), pos_keys=pos_keys.cpu().numpy(), pos_tangents=pos_tan.cpu().numpy(),
        rot_keys=rot_keys.cpu().numpy(), rot_tangents=rot_tan.cpu().numpy(),
        p_dyn=m.node_p_dyn.cpu().numpy(), bind_idx=m.bind_idx.cpu().numpy(), bind_w=m.bind_w.cpu().numpy(),
        graph_idx=m.graph_idx.cpu().numpy() if m.graph_idx.shape[1] else None)
    if bool((m.gauss_lifespan > 0).any()):  # bundles without lifespans stay as they were
        nodes.gauss_t_center = m.gauss_t_center.cpu().numpy()
        nodes.gauss_lifespan = m.lifespans().detach().cpu().numpy()  # as learned
    if bool((m.gauss_view_angle > 0).any()):  # view-bound Gaussians (shot_detail.py)
        nodes.gauss_view_origin = m.gauss_view_origin.cpu().numpy()
        nodes.gauss_view_angle = m.gauss_view_angle.cpu().numpy()
    gaussians = B.GaussianArrays(means=m.means.detach().cpu().numpy(),
                                 quats=quat_normalize(m.quats.detach()).cpu().numpy(),
                                 log_scales=m.log_scales.detach().cpu().numpy(),
                                 opacity_logits=m.opacity_logits.detach().cpu().numpy(),
                                 sh=m.sh().detach().cpu().numpy())
    return nodes, gaussians


def bundle_cameras(data: TrainingData) -> tuple[torch.Tensor, list[dict]]:
    """``(frame numbers [F], one scene.json camera record per frame)``: w2c [4, 4], K [3, 3],
    size, time, train / val split and index in the clip."""
    d = data
    frames = d.frame_numbers if d.frame_numbers is not None else torch.arange(d.num_frames)
    val = set(d.val_idx.tolist())
    cams = [{"frame": int(frames[i]), "w2c": d.w2c[i].cpu().numpy(), "K": d.K[i].cpu().numpy(),
             "width": d.width, "height": d.height, "time": float(d.times[i]),
             "split": "val" if i in val else "train",
             "clip_index": int(d.clip_index[i]) if d.clip_index is not None else i} for i in range(d.num_frames)]
    return frames, cams
