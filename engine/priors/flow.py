"""Dense optical flow (cv2.DISOpticalFlow) and vectorised bilinear sampling."""

from __future__ import annotations

import numpy as np


def to_gray_small(frames, max_width=480):
    """uint8 RGB [F,H,W,3] -> (uint8 gray [F,h,w], scale = w/W) with w <= max_width."""
    import cv2

    F, H, W, _ = frames.shape
    s = min(1.0, float(max_width) / W)
    w, h = max(8, int(round(W * s))), max(8, int(round(H * s)))
    gray = np.stack([cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), (w, h), interpolation=cv2.INTER_AREA)
                     if (w, h) != (W, H) else cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames])
    return gray, w / W


def dis_flow(a, b, preset="medium"):
    """Flow [h,w,2] (dx, dy) from gray ``a`` to gray ``b`` (pixel (i,j) centre at (j+.5, i+.5))."""
    import cv2

    p = {"fast": cv2.DISOPTICAL_FLOW_PRESET_FAST, "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
         "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}[preset]
    dis = cv2.DISOpticalFlow_create(p)
    return dis.calc(a, b, None)


def bilinear(img, xy):
    """Sample ``img [h,w,C]`` at continuous coords ``xy [P,2]`` (edge-clamped) -> [P,C]."""
    h, w = img.shape[:2]
    x = np.clip(xy[:, 0] - 0.5, 0, w - 1)
    y = np.clip(xy[:, 1] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy).astype(np.float32)
