"""Contact sheets: ground truth | render | |error| for frames spread over a clip.

A number nobody looked at is not a result: a full-frame PSNR is dominated by the
background, so a reconstruction that lost every moving object can still score well. The
sheet puts the evidence next to the number (``engine eval --sheet``, the HTML report).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def error_image(pred: np.ndarray, gt: np.ndarray, gain: float = 4.0) -> np.ndarray:
    """``|pred − gt|`` averaged over channels, times ``gain``, as a grey uint8 ``[H, W, 3]``.

    pred, gt : uint8 ``[H, W, 3]``. A gain of 4 maps an error of 1/4 of the range to white,
    so a missing object shows as a bright silhouette while noise stays dark.
    """
    err = np.abs(pred.astype(np.float32) - gt.astype(np.float32)).mean(-1) * gain
    e = np.clip(err, 0, 255).astype(np.uint8)
    return np.repeat(e[..., None], 3, axis=-1)


def _outline(mask: np.ndarray) -> np.ndarray:
    """One-pixel outline ``[H, W] bool`` of a boolean mask (its 4-neighbour boundary)."""
    m = mask.astype(bool)
    inner = m.copy()
    inner[1:] &= m[:-1]
    inner[:-1] &= m[1:]
    inner[:, 1:] &= m[:, :-1]
    inner[:, :-1] &= m[:, 1:]
    return m & ~inner


def contact_sheet(rows, masks=None, gain: float = 4.0, gap: int = 2) -> np.ndarray:
    """Stack ``(gt, pred)`` pairs into one image, a row each: gt | pred | error.

    Parameters
    ----------
    rows : sequence of ``(gt uint8 [H, W, 3], pred uint8 [H, W, 3])``, all the same size.
    masks : optional sequence of ``[H, W] bool`` dynamic masks (None entries allowed); their
        outline is drawn in red on the error panel so the moving region is easy to find.
    gain : error gain (:func:`error_image`).
    gap : white pixels between panels and rows.

    Returns
    -------
    uint8 ``[R·(H + gap) − gap, 3·W + 2·gap, 3]`` RGB.
    """
    if not rows:
        raise ValueError("contact_sheet needs at least one (gt, pred) pair")
    h, w = rows[0][0].shape[:2]
    out_rows = []
    white_v = np.full((h, gap, 3), 255, np.uint8)
    for n, (gt, pred) in enumerate(rows):
        err = error_image(pred, gt, gain)
        m = None if masks is None else masks[n]
        if m is not None:
            err[_outline(m)] = (255, 0, 0)
        out_rows.append(np.concatenate([gt, white_v, pred, white_v, err], axis=1))
    white_h = np.full((gap, out_rows[0].shape[1], 3), 255, np.uint8)
    stacked = []
    for n, r in enumerate(out_rows):
        if n:
            stacked.append(white_h)
        stacked.append(r)
    return np.concatenate(stacked, axis=0)


def write_png(path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image atomically as PNG; returns the path."""
    import cv2

    from ..fsutil import atomic_path

    path = Path(path)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"could not encode {path.name} as PNG")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buf.tobytes())
    return path
