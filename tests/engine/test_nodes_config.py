"""MANI's settings, the spline key count and the node radius come from the run's typed
config (#19): settable there, recorded in scene.json's config, and used by node
initialisation and by the canonical-time rebuild of the radii."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import engine.nodes as nodes_pkg
from engine import pipeline
from engine.errors import InputError
from engine.nodes.graph import node_radii
from engine.nodes.mani import ManiConfig
from engine.train.config import ManiSettings, TrainConfig
from engine.train.init_model import common_canonical_nodes


def test_mani_settings_mirror_mani_config_defaults():
    # every MANI knob is in the typed config with the algorithm's own default (budget = num_nodes,
    # seed = the run's): a default run is the same run as before
    mani = {f.name: f.default for f in dataclasses.fields(ManiConfig)}
    ours = {f.name: f.default for f in dataclasses.fields(ManiSettings)}
    assert set(mani) - set(ours) == {"budget", "bias", "max_iters", "seed"}
    assert all(mani[k] == v for k, v in ours.items())


def test_config_round_trips_mani_settings_and_refuses_bad_ones():
    cfg = TrainConfig.from_dict({"mani": {"eta": 0.25, "r_max": 0.6, "merge": "mean"}, "num_keys": 7,
                                 "radius_k": 6, "radius_factor": 1.5})
    assert (cfg.mani.eta, cfg.mani.r_max, cfg.mani.merge, cfg.num_keys) == (0.25, 0.6, "mean", 7)
    again = TrainConfig.from_dict(cfg.to_dict())  # what scene.json's "config" holds
    assert again == cfg and again.to_dict()["mani"]["r_max"] == 0.6
    for bad, key in (({"merge": "median"}, "mani.merge"), ({"r_min": 0.5, "r_max": 0.3}, "mani.r_min"),
                     ({"v_init": 0.0}, "mani.v_init"), ({"eta": float("nan")}, "mani.eta"),
                     ({"gamma": 1.0}, "gamma"), ({"alpha": "6"}, "alpha")):
        with pytest.raises(InputError, match=key.replace(".", r"\.")):
            TrainConfig.from_dict({"mani": bad}, "cfg.json")


def test_initial_nodes_uses_the_runs_mani_keys_and_radius(monkeypatch):
    seen = {}

    def fake_initialise_nodes(*args, **kwargs):
        seen["config"] = args[-1]
        raise StopIteration  # only the config matters here

    monkeypatch.setattr(nodes_pkg, "initialise_nodes", fake_initialise_nodes)
    f = 8
    tracks = SimpleNamespace(xy=np.zeros((1, f, 2)), visible=np.zeros((1, f), bool))
    priors = SimpleNamespace(train_order=np.arange(f), depth=np.ones((f, 2, 2)), tracks=tracks,
                             tokens=SimpleNamespace(tokens=None, patch_centers=None), dynamic=np.zeros((f, 2, 2)))
    prep = SimpleNamespace(priors=priors, K=np.zeros((f, 3, 3)), w2c=np.zeros((f, 4, 4)), times=np.linspace(0, 1, f))
    cfg = TrainConfig.from_dict({"motion_init": "rest", "num_nodes": 300, "num_keys": 9, "radius_k": 5,
                                 "radius_factor": 2.0, "mani": {"eta": 0.3, "alpha": 2.0, "beta": 1.0, "r_min": 0.1,
                                                                "r_max": 0.7, "v_init": 0.02, "dv": 0.03,
                                                                "merge": "representative"}})
    with pytest.raises(StopIteration):
        pipeline.initial_nodes(prep, cfg)
    c = seen["config"]
    assert (c.num_keys, c.radius_k, c.radius_factor) == (9, 5, 2.0)
    m = c.mani
    assert (m.budget, m.eta, m.alpha, m.beta, m.r_min, m.r_max, m.v_init, m.dv, m.merge) == (
        300, 0.3, 2.0, 1.0, 0.1, 0.7, 0.02, 0.03, "representative")


def test_canonical_rebuild_uses_the_runs_radius_settings():
    g = torch.Generator().manual_seed(0)
    keys = torch.rand(40, 4, 3, generator=g)
    kt = torch.linspace(0, 1, 4)
    data = SimpleNamespace(times=torch.linspace(0, 1, 8), train_idx=torch.arange(8))
    centers, radii, _ = common_canonical_nodes(data, kt, keys, None, 0.5, None, 6, 2.0)
    assert torch.allclose(radii, node_radii(centers, 6, 2.0))
    assert not torch.allclose(radii, node_radii(centers, 4, 1.0))
