"""Canonical node centres at one shared time (``TrainConfig.canonical_time``)."""

import numpy as np
import torch

from engine import bundle as B
from engine.train.config import preset_config
from engine.train.trainer import build_model, initial_gaussians

from .synthetic_training import blob_offset, make_nodes, make_scene


def _cfg(**kw):
    # the single-class model: the round trip below pairs each model Gaussian with the point
    # initial_gaussians seeded it from, which the static / dynamic split re-seeds (its
    # round trip is tests/engine/test_split.py's)
    return preset_config("preview", gaussians_per_frame=800, init_keyframes=4, num_nodes=25, split=False, **kw)


def _mixed_time_nodes(truth):
    """make_nodes' nodes, but each blob node seated where the blob was at its own source
    time (0 or 1, alternately), as an initialiser places nodes seen at different keyframes;
    its keys still follow the true motion, so its spline passes through its centre there."""
    d = make_nodes(truth).to_dict()
    c = torch.as_tensor(d["centers"]).clone()
    c[20:] += blob_offset(torch.tensor([0.0, 1.0, 0.0, 1.0, 0.0]))
    d["centers"] = c.numpy()
    return B.NodeArrays(**d)


def _round_trip_error(data, nodes, canonical_time):
    """Largest distance between a back-projected point and its Gaussian deformed back to the
    time it was observed at (canonical mapping, canonical K-NN binding, then deformation)."""
    cfg = _cfg(canonical_time=canonical_time)
    model = build_model(data, nodes, cfg, torch.Generator().manual_seed(0))
    pts, _, _, tms = initial_gaussians(data, cfg, torch.Generator().manual_seed(0))
    err = torch.zeros(len(pts))
    with torch.no_grad():
        for t in torch.unique(tms).tolist():
            sel = tms == t
            err[sel] = (model.deform(t)[0][sel] - pts[sel]).norm(dim=1)
    return err, model


def test_shared_canonical_time_maps_observed_points_back_exactly():
    data, truth = make_scene()
    nodes = _mixed_time_nodes(truth)
    err_mixed, _ = _round_trip_error(data, nodes, -1.0)
    err_shared, model = _round_trip_error(data, nodes, 0.5)
    # mixed source times: blob Gaussians bind, in canonical space, to a blend of two blob
    # copies 1.2 apart (and to wall nodes) and do not come back where they were seen
    assert float(err_mixed.max()) > 0.05, float(err_mixed.max())
    # one shared time: the blob moves rigidly, so every point comes back exactly
    assert float(err_shared.max()) < 1e-3, float(err_shared.max())
    # centres are the nodes' initial positions at the training frame nearest mid-clip
    times = torch.sort(data.times[data.train_idx]).values
    t_c = float(times[round(0.5 * (len(times) - 1))])
    expect = torch.as_tensor(make_nodes(truth).centers).clone()
    expect[20:] += blob_offset(torch.tensor([t_c]))
    torch.testing.assert_close(model.node_centers, expect, atol=2e-3, rtol=0)  # spline vs true sine
    # the ARAP graph is rebuilt there: every blob node's neighbours include the other blob nodes
    g = model.graph_idx[20:]
    assert bool((g >= 20).sum(1).ge(3).all()), g


def test_mlp_motion_keeps_source_centres():
    data, truth = make_scene()
    nodes = _mixed_time_nodes(truth)
    model = build_model(data, nodes, _cfg(motion="mlp"), torch.Generator().manual_seed(0))
    np.testing.assert_allclose(model.node_centers.numpy(), nodes.centers, atol=1e-6)
