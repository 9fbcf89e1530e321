"""The static / dynamic split (engine/train/split.py, engine/train/init_model.py)."""

from __future__ import annotations

import numpy as np
import torch

from engine.train.config import preset_config
from engine.train.init_model import build_model, dynamic_gaussians, initial_gaussians
from engine.train.split import bind_within_class, freeze_static_nodes, graph_within_class

from .synthetic_training import make_nodes, make_scene


def _cfg(**kw):
    return preset_config("preview", gaussians_per_frame=800, init_keyframes=4, num_nodes=25,
                         dynamic_gaussians=600, **kw)


def test_points_bind_only_to_nodes_of_their_class_even_when_others_are_nearer():
    nodes = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0], [5.1, 0, 0], [5.2, 0, 0]])
    node_dyn = torch.tensor([False, False, True, True, True])
    pts = torch.tensor([[0.05, 0, 0], [0.05, 0.01, 0]])  # both right next to the static nodes
    idx, w = bind_within_class(pts, torch.tensor([True, False]), nodes, node_dyn, torch.ones(5), 3)
    assert set(idx[0].tolist()) <= {2, 3, 4}  # the dynamic point: dynamic nodes only
    assert set(idx[1].tolist()) <= {0, 1}  # the static one: static nodes (2 of them, padded)
    torch.testing.assert_close(w.sum(1), torch.ones(2))
    assert float(w[1][idx[1] == idx[1, 0]].sum()) > 0 and float(w[1, 2]) == 0.0  # the pad weighs nothing


def test_graph_links_nodes_within_their_class():
    g = torch.Generator().manual_seed(0)
    centers = torch.rand(30, 3, generator=g)
    node_dyn = torch.arange(30) % 3 == 0
    graph = graph_within_class(centers, node_dyn, 4)
    assert bool((node_dyn[graph] == node_dyn[:, None]).all())
    assert bool((graph != torch.arange(30)[:, None]).all())  # no self-edges while a class has > 1 node


def test_path_graph_does_not_link_parts_that_move_apart():
    """Two links of an arm: the forearm starts held out sideways and folds up against the
    upper link. At the last key every forearm node sits next to an upper-link node, so nearest
    centres there link across the elbow; nearest paths (the largest distance over the keys)
    link each node within its own link."""
    from engine.nodes.graph import path_graph

    t = torch.linspace(0, 1, 9)
    upper = torch.stack([torch.zeros(5), torch.zeros(5), -torch.linspace(0.1, 0.5, 5)], 1)  # [5, 3], still
    along = torch.linspace(0.2, 0.6, 5)[:, None]  # from the elbow at (0, 0, -0.5)
    angle = 0.5 * torch.pi * t[None]  # sideways -> up, beside the upper link
    fore = torch.stack([0.03 + along * torch.cos(angle), torch.zeros(5, 9), -0.5 + along * torch.sin(angle)], -1)
    paths = torch.cat([upper[:, None].expand(5, 9, 3), fore])  # [10, 9, 3]
    node_dyn = torch.ones(10, dtype=torch.bool)
    part = torch.arange(10) >= 5
    by_centres = graph_within_class(paths[:, -1], node_dyn, 2)
    by_paths = graph_within_class(paths[:, -1], node_dyn, 2, paths=paths)
    assert bool((part[by_centres] != part[:, None]).any())
    assert bool((part[by_paths] == part[:, None]).all())
    idx, d2 = path_graph(paths, 3)
    far = ((paths[:, None] - paths[None]) ** 2).sum(-1).amax(-1)  # brute force [10, 10]
    torch.testing.assert_close(d2, far.gather(1, idx))
    assert bool((idx != torch.arange(10)[:, None]).all())
    torch.testing.assert_close(path_graph(paths, 3, max_elements=3 * 10 * 9 * 3)[1], d2)  # blocks of 3 rows: the same


def test_freeze_zeroes_static_gradients_only():
    keys = torch.nn.Parameter(torch.zeros(4, 3, 3))
    (keys * torch.arange(1.0, 5.0)[:, None, None]).sum().backward()
    freeze_static_nodes(keys, None, torch.tensor([True, False, True, False]))
    assert float(keys.grad[[1, 3]].abs().sum()) == 0.0 and float(keys.grad[[0, 2]].abs().min()) > 0


def test_split_model_classes_rest_and_round_trip():
    """Wall nodes are static and at rest, blob nodes dynamic; moving Gaussians are seeded on
    the blob in every training frame and, deformed back to the time they were seen, land
    where they were seen; static Gaussians sit on the wall and are never moved."""
    data, truth = make_scene()
    cfg = _cfg()
    model = build_model(data, make_nodes(truth), cfg, torch.Generator().manual_seed(0))
    assert model.is_split
    assert model.node_dyn.tolist() == [False] * 20 + [True] * 5
    torch.testing.assert_close(model.pos_keys[:20], model.node_centers[:20, None].expand(-1, model.pos_keys.shape[1], 3))
    gen = torch.Generator().manual_seed(0)  # replay build_model's draws
    s_pts = initial_gaussians(data, cfg, gen, static_only=True)[0]
    d_pts, _, _, d_tms = dynamic_gaussians(data, cfg, gen)
    assert model.num_gaussians == len(s_pts) + len(d_pts) and int(model.gauss_dyn.sum()) == len(d_pts)
    assert len(torch.unique(d_tms)) == len(data.train_idx)  # every training frame contributes
    dyn = model.gauss_dyn
    # dynamic Gaussians bind to dynamic nodes, static ones to static nodes
    assert bool(model.node_dyn[model.bind_idx[dyn]].all()) and not bool(model.node_dyn[model.bind_idx[~dyn]].any())
    with torch.no_grad():
        err = torch.zeros(len(d_pts))
        for t in torch.unique(d_tms).tolist():
            sel = d_tms == t
            err[sel] = (model.deform(t)[0][dyn][sel] - d_pts[sel]).norm(dim=1)
        assert float(err.max()) < 1e-3, float(err.max())
        for t in (0.0, 0.5, 1.0):  # static Gaussians never move
            torch.testing.assert_close(model.deform(t)[0][~dyn], model.means[~dyn], atol=1e-5, rtol=0)


def test_a_training_step_moves_no_static_node(tmp_path):
    from engine.train.trainer import Trainer

    data, truth = make_scene()
    trainer = Trainer(data, make_nodes(truth), _cfg(steps=8, warmup_static_steps=0, checkpoint_every=0,
                                                   densify_from=100), tmp_path / "run")
    before = trainer.model.pos_keys.detach().clone()
    trainer.train()
    after = trainer.model.pos_keys.detach()
    assert torch.equal(after[:20], before[:20])  # static: untouched
    assert float((after[20:] - before[20:]).abs().max()) > 0  # dynamic: trained
    assert np.isfinite(after.numpy()).all()
