"""Synthetic scene for the prior tests (imported by test_priors_*.py) + sanity checks of it.

A textured fronto-parallel plane at depth ``Z_BG`` seen by a camera translating along +x,
and a textured square at depth ``Z_SQ`` moving on its own. Ground-truth depth, dynamic
mask and the projection of static points are exact.
"""

from __future__ import annotations

import cv2
import numpy as np

W, H, F = 160, 120, 8
FX = 150.0
Z_BG, Z_SQ = 4.0, 3.0
CAM_STEP = 0.05
SQ_HALF = 0.3
SQ_VEL = np.array([0.12, 0.04])


def _texture(seed, n=1024):
    rng = np.random.default_rng(seed)
    t = np.zeros((n, n, 3), np.float32)
    for s, a in ((2, 0.5), (6, 0.35), (20, 0.25)):
        noise = rng.random((n, n, 3)).astype(np.float32)
        t += a * cv2.GaussianBlur(noise, (0, 0), s)
    t -= t.min((0, 1)); t /= t.max((0, 1))
    return t


def cameras(F=F):
    K = np.tile(np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]], np.float64), (F, 1, 1))
    w2c = np.tile(np.eye(4), (F, 1, 1))
    w2c[:, 0, 3] = -CAM_STEP * np.arange(F)  # camera centre at x = CAM_STEP * f
    return K, w2c


def square_center(f):
    return np.array([0.3, -0.1]) + SQ_VEL * f


def render(F=F, seed=0, moving=True, flat=False):
    """Returns frames uint8 [F,H,W,3], depth [F,H,W], mask [F,H,W] bool, K, w2c.

    ``moving=False``: the square stays at its frame-0 place (a static object in front of the
    plane; the mask is then all False). ``flat``: a texture-less band on the plane
    (world x in [-1.6, 0], about 38 % of the first frame)."""
    K, w2c = cameras(F)
    bg, fg = _texture(seed), _texture(seed + 1)
    if flat:
        bg[:, int(512 - 1.6 * 200):int(512 + 0.0 * 200)] = bg.mean((0, 1))
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rx, ry = (xs - W / 2) / FX, (ys - H / 2) / FX
    frames = np.empty((F, H, W, 3), np.uint8)
    depth = np.empty((F, H, W), np.float32)
    mask = np.empty((F, H, W), bool)
    tex_scale = 200.0  # texels per world unit
    for f in range(F):
        cx = CAM_STEP * f
        Xb, Yb = cx + rx * Z_BG, ry * Z_BG
        img = cv2.remap(bg, (Xb * tex_scale + 512).astype(np.float32), (Yb * tex_scale + 512).astype(np.float32),
                        cv2.INTER_LINEAR)
        Xs, Ys = cx + rx * Z_SQ, ry * Z_SQ
        c = square_center(f if moving else 0)
        lx, ly = Xs - c[0], Ys - c[1]
        m = (np.abs(lx) < SQ_HALF) & (np.abs(ly) < SQ_HALF)
        sq = cv2.remap(fg, (lx * tex_scale + 512).astype(np.float32), (ly * tex_scale + 512).astype(np.float32),
                       cv2.INTER_LINEAR)
        img = np.where(m[..., None], sq, img)
        frames[f] = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
        depth[f] = np.where(m, Z_SQ, Z_BG)
        mask[f] = m & moving
    return frames, depth, mask, K, w2c


def static_track(xy0, f0, F=F):
    """Ground-truth image positions [P,F,2] of background points seen at ``xy0`` in frame ``f0``."""
    X = CAM_STEP * f0 + (xy0[:, 0] - W / 2) / FX * Z_BG
    u = FX * (X[:, None] - CAM_STEP * np.arange(F)[None]) / Z_BG + W / 2
    v = np.repeat(xy0[:, 1:2], F, 1)
    return np.stack([u, v], -1)


def test_scene_is_consistent():
    frames, depth, mask, K, w2c = render()
    assert frames.shape == (F, H, W, 3) and mask.any() and (~mask).any()
    # a static background pixel moves by the predicted flow
    gt = static_track(np.array([[20.5, 20.5]]), 0)
    assert np.isclose(gt[0, 1, 0] - gt[0, 0, 0], -FX * CAM_STEP / Z_BG)
