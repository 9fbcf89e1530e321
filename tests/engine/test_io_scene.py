"""Synthetic textured box room rendered with numpy ray casting (helpers for test_io_solve; no tests here)."""

from __future__ import annotations

import numpy as np


def look_at_w2c(center, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """OpenCV w2c [4,4] for a camera at ``center`` looking at ``target`` (world y is down)."""
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z) * -1.0
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ c
    return M


def make_texture(seed: int, size: int = 512) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size, 3), np.float32)
    for cells, amp in ((8, 0.5), (32, 0.35), (128, 0.25)):
        small = rng.random((cells, cells, 3)).astype(np.float32)
        tex += amp * cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return (tex * 255).astype(np.uint8)


class Room:
    """Axis-aligned box ``[-hx,hx]x[-hy,hy]x[-hz,hz]`` with a different texture per wall."""

    def __init__(self, half=(5.0, 3.0, 5.0), seed=0, px_per_unit=50.0):
        self.half = np.asarray(half, float)
        self.tex = [make_texture(seed + k) for k in range(6)]
        self.ppu = px_per_unit

    def render(self, K, w2c, width, height) -> np.ndarray:
        """``uint8 [H,W,3]`` image (continuous pixel convention)."""
        import cv2

        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3)
        d_cam = pix @ np.linalg.inv(K).T
        R, t = w2c[:3, :3], w2c[:3, 3]
        C = -R.T @ t
        d = d_cam @ R  # world directions (R^T d)
        best = np.full(len(d), np.inf)
        face = np.full(len(d), -1)
        for ax in range(3):
            for sgn in (-1, 1):
                with np.errstate(divide="ignore", invalid="ignore"):
                    tt = (sgn * self.half[ax] - C[ax]) / d[:, ax]
                ok = (tt > 0) & (tt < best)
                best = np.where(ok, tt, best)
                face = np.where(ok, 2 * ax + (sgn > 0), face)
        P = C + best[:, None] * d
        out = np.zeros((len(d), 3), np.uint8)
        for f in range(6):
            sel = face == f
            ax = f // 2
            a, b = [k for k in range(3) if k != ax]
            if not sel.any():
                continue
            mx = P[sel, a] * self.ppu
            my = P[sel, b] * self.ppu
            x0, y0 = np.floor(mx), np.floor(my)
            fx, fy = (mx - x0)[:, None], (my - y0)[:, None]
            x0, y0 = x0.astype(int) % 512, y0.astype(int) % 512
            x1, y1 = (x0 + 1) % 512, (y0 + 1) % 512
            T = self.tex[f].astype(np.float32)
            val = (T[y0, x0] * (1 - fx) * (1 - fy) + T[y0, x1] * fx * (1 - fy)
                   + T[y1, x0] * (1 - fx) * fy + T[y1, x1] * fx * fy)
            out[sel] = np.clip(val + 0.5, 0, 255).astype(np.uint8)
        return out.reshape(height, width, 3)


def orbit_cameras(n: int, radius: float = 1.5, height: float = 0.3):
    """``n`` w2c [n,4,4] moving along an arc inside the room, looking outward-ish at a wall."""
    ws = []
    for k in range(n):
        a = 0.9 * k / max(n - 1, 1)
        C = np.array([radius * np.sin(a) - 0.5, height * np.sin(2 * a), -radius * np.cos(a) + 1.0])
        target = np.array([4.0 + 2.0 * np.sin(a), 1.0, 4.0])  # towards a corner: several walls in view
        ws.append(look_at_w2c(C, target))
    return np.stack(ws)
