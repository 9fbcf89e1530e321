"""A trained model rebuilt from a result bundle: the inverse of
:func:`engine.train.export.bundle_arrays`, for everything that renders, evaluates, exports or
fine-tunes a bundle after training (``engine render`` / ``eval`` / ``export`` / ``finetune``).
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError
from .model import DynamicScene


def model_from_bundle(bundle, device="cpu") -> DynamicScene:
    """Rebuild a trained :class:`DynamicScene` from an opened result bundle.

    The bundle's explicit tangents (possibly edited in Blender) are used as they are, so
    renders match what Blender shows. Needs ``gaussians.ply`` and a binding in
    ``nodes.npz`` (i.e. a trained bundle).
    """
    if bundle.gaussians is None or bundle.nodes is None or bundle.nodes.bind_idx is None:
        raise InputError("bundle has no trained Gaussians yet", bundle.path,
                         "run `python -m engine train` to completion (or --resume it) first")
    nd, gs = bundle.nodes, bundle.gaussians
    t = lambda a, dt=torch.float32: torch.tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
    g = gs.count
    cfg = bundle.scene.get("config", {})
    m = DynamicScene(t(gs.means), torch.zeros(g, 3, device=device), torch.ones(g, 3, device=device),
                     torch.full((g,), 0.5, device=device), t(nd.centers), t(nd.radii), t(nd.key_times),
                     t(nd.pos_keys), t(nd.rot_keys), sh_degree=gs.sh_degree, motion="spline",
                     bind_k=nd.bind_idx.shape[1],
                     graph_idx=None if nd.graph_idx is None else t(nd.graph_idx, torch.long),
                     node_p_dyn=None if nd.p_dyn is None else t(nd.p_dyn),
                     extent=float(bundle.scene.get("extent", 1.0)))
    with torch.no_grad():
        m.quats.copy_(t(gs.quats))
        m.log_scales.copy_(t(gs.log_scales))
        m.opacity_logits.copy_(t(gs.opacity_logits))
        m.sh_dc.copy_(t(gs.sh[:, :1]))
        m.sh_rest.copy_(t(gs.sh[:, 1:]))
    m.bind_idx = t(nd.bind_idx, torch.long)
    m.bind_w = t(nd.bind_w)
    m.set_explicit_tangents(t(nd.pos_tangents), t(nd.rot_tangents),
                            None if nd.pos_tangents_in is None else t(nd.pos_tangents_in),
                            None if nd.rot_tangents_in is None else t(nd.rot_tangents_in))
    if nd.gauss_lifespan is not None:
        m.gauss_t_center = t(nd.gauss_t_center)
        m.gauss_lifespan = t(nd.gauss_lifespan)
    if nd.gauss_view_angle is not None:
        m.gauss_view_origin = t(nd.gauss_view_origin)
        m.gauss_view_angle = t(nd.gauss_view_angle)
    m.motion_source = cfg.get("motion", "spline")
    return m
