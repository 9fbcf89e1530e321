"""The raster bench's work count: Gaussian-pixel pairs inside each cut-off ellipse."""

from __future__ import annotations

import math

import torch

from engine.bench.raster import count_evaluations, make_scene
from engine.raster import cpu as C


def test_count_evaluations_matches_a_dense_count():
    scene = make_scene(400, 64, seed=0)
    m2, cn, dz, radii, ext = C.project(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                       scene["w2c"], scene["K"], 64, 64)
    ys, xs = torch.meshgrid(torch.arange(64) + 0.5, torch.arange(64) + 0.5, indexing="ij")
    dense = 0
    for g in torch.nonzero(radii > 0).flatten().tolist():
        dx, dy = xs - m2[g, 0], ys - m2[g, 1]
        sig = 0.5 * (cn[g, 0] * dx * dx + cn[g, 2] * dy * dy) + cn[g, 1] * dx * dy
        dense += int((sig <= math.log(max(255.0 * float(scene["opacities"][g]), 1.0))).sum())
    got = count_evaluations(scene)
    assert dense > 1000
    assert abs(got - dense) <= 0.002 * dense, (got, dense)
