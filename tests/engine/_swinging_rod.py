"""A rod swinging from a pivot in the air, seen by a camera sliding sideways in front of a wall:
the scene of the hinge tests (test_priors_hinge.py, test_priors_hinge_tracks.py)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

W, H, FOCAL, WALL = 160, 120, 150.0, 10.0


def _cameras(f, travel):
    """A camera sliding ``travel`` units along +x over ``f`` frames, looking down +z."""
    K = np.tile(np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]]), (f, 1, 1))
    w2c = np.tile(np.eye(4), (f, 1, 1))
    w2c[:, 0, 3] = -np.linspace(-travel / 2, travel / 2, f)
    return K, w2c


def _mask(K, w2c, points, radius_px=2):
    """[F, H, W] float: the projections of ``points [F, P, 3]`` (world, per frame), dilated."""
    f = len(K)
    out = np.zeros((f, H, W), bool)
    for k in range(f):
        cam = points[k] @ w2c[k, :3, :3].T + w2c[k, :3, 3]
        uv = cam @ K[k].T
        u, v = (uv[:, 0] / uv[:, 2]).astype(int), (uv[:, 1] / uv[:, 2]).astype(int)
        ok = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        out[k, v[ok], u[ok]] = True
    grow = np.ones((1, 2 * radius_px + 1, 2 * radius_px + 1), bool)
    return ndimage.binary_dilation(out, structure=grow).astype(np.float32)


def _rod(f, pivot, length=1.2, swing=0.7):
    """Points of a rod hanging from ``pivot`` and swinging in the x-y plane: [F, P, 3]."""
    ang = swing * np.sin(np.linspace(0, 2 * np.pi, f))
    s = np.linspace(0, length, 200)
    return pivot + s[None, :, None] * np.stack([np.sin(ang), np.cos(ang), np.zeros(f)], -1)[:, None]
