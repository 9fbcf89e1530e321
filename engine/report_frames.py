"""Report section: what the model shows at its own training cameras, over the whole clip.

A number nobody looked at is not a result (issue #17): a reconstruction that lost every
moving object still scores a fair full-frame PSNR. This section of the HTML report puts
``SHEET_FRAMES`` training frames spread over the clip as ground truth | render | |error|
rows (:func:`engine.viz.contact_sheet`, moving region outlined in red when the clip has
masks) and the node overlay at ``OVERLAY_TIMES`` times side by side, so a missing or frozen
object is seen at a glance. Cheap by design: it renders only the picked frames (it runs at
the end of every ``engine train``).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

SHEET_FRAMES = 6
OVERLAY_TIMES = 4


def spread(items: list, n: int) -> list:
    """``n`` items spread evenly over ``items`` (first and last included), in order."""
    if not items:
        return []
    idx = np.unique(np.linspace(0, len(items) - 1, min(n, len(items))).round().astype(int))
    return [items[i] for i in idx]


def training_cameras(scene: dict) -> list[dict]:
    """The bundle's training cameras in time order (all cameras when none is marked train)."""
    cams = [c for c in scene["cameras"] if c.get("split", "train") == "train"] or list(scene["cameras"])
    return sorted(cams, key=lambda c: float(c["time"]))


def render_training_rows(bundle, cams: list[dict], clip_path=None, device: str = "auto", backend: str = "auto"):
    """Render ``cams`` and load their clip frames and masks.

    Returns a list of ``(camera, gt uint8 [H, W, 3], render uint8 [H, W, 3], mask [H, W] bool or None)``.
    Raises :class:`engine.errors.InputError` when the clip is missing.
    """
    import cv2
    import torch

    from .commands._common import pick_device
    from .commands.eval import _camera_frame, _mask_for, _open_clip_for
    from .train.from_bundle import model_from_bundle
    from .train.render import render_scene

    clip, path = _open_clip_for(bundle, clip_path)
    start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
    dev = pick_device(device)
    model = model_from_bundle(bundle, dev)
    rows = []
    with torch.no_grad():
        for c in cams:
            i, gt = _camera_frame(clip, c, start, path)
            w, h = int(c["width"]), int(c["height"])
            means, quats = model.deform(float(c["time"]))
            out = render_scene(model, means, quats, torch.as_tensor(np.asarray(c["K"]), dtype=torch.float32, device=dev),
                               torch.as_tensor(np.asarray(c["w2c"]), dtype=torch.float32, device=dev), w, h,
                               backend=backend, time=float(c["time"]))
            pred = (out.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
            m = _mask_for(clip, i)
            if m is not None:
                m = cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            rows.append((c, gt, pred, m))
    return rows


def _psnr_u8(a: np.ndarray, b: np.ndarray, mask=None) -> float:
    err = ((a.astype(np.float64) - b.astype(np.float64)) / 255.0) ** 2
    mse = err[mask].mean() if mask is not None else err.mean()
    return float(-10 * np.log10(max(mse, 1e-12)))


def contact_sheet_section(bundle, folder: Path, clip_path=None, device: str = "auto", backend: str = "auto",
                          notes: list | None = None) -> str:
    """Write ``contact_sheet.png`` into ``folder``; returns the section's HTML."""
    from .errors import InputError
    from .viz import contact_sheet, write_png

    head = "<h2>Training frames (ground truth | render | |error|)</h2>"
    cams = spread(training_cameras(bundle.scene), SHEET_FRAMES)
    if bundle.gaussians is None or bundle.nodes is None or bundle.nodes.bind_idx is None or not cams:
        return head + "<p><em>no trained model in this bundle</em></p>"
    try:
        rows = render_training_rows(bundle, cams, clip_path, device, backend)
    except InputError as exc:
        if notes is not None:
            notes.append(f"contact sheet skipped: {exc}")
        return head + "<p><em>no contact sheet (clip not available)</em></p>"
    masks = [m if m is not None and m.sum() > 16 else None for *_, m in rows]
    write_png(folder / "contact_sheet.png", contact_sheet([(gt, pred) for _, gt, pred, _ in rows], masks))
    lines = []
    for (c, gt, pred, _), m in zip(rows, masks):
        s = f"frame {c['frame']} (time {float(c['time']):.3f}): PSNR {_psnr_u8(pred, gt):.2f} dB"
        lines.append(s + (f", inside the moving region {_psnr_u8(pred, gt, m):.2f} dB" if m is not None else ""))
    cap = ("rows top to bottom: " + "; ".join(lines) +
           ". Error ×4; red outline = the clip's moving-region mask.")
    return head + f'<figure><img class="sheet" src="contact_sheet.png"><figcaption>{html.escape(cap)}</figcaption></figure>'


def node_overlay_section(bundle, folder: Path, clip_path=None, notes: list | None = None) -> str:
    """Write ``nodes_overlay.png`` (the overlay at ``OVERLAY_TIMES`` times side by side)."""
    import torch

    from .report import _frame_image, _imwrite, _node_positions, node_overlay

    head = "<h2>Node allocation over time</h2>"
    cams = spread(training_cameras(bundle.scene), OVERLAY_TIMES)
    if bundle.nodes is None or not cams:
        return head + "<p><em>no nodes in this bundle</em></p>"
    panels, blank = [], False
    for cam in cams:
        base = _frame_image(bundle, cam, clip_path)
        if base is None:
            base = np.full((int(cam["height"]), int(cam["width"]), 3), 40, np.uint8)
            blank = True
        pos = _node_positions(bundle, float(cam["time"]), torch)
        panels.append(node_overlay(base, cam["K"], cam["w2c"], pos, bundle.nodes.p_dyn))
    h = max(p.shape[0] for p in panels)
    gap = np.full((h, 4, 3), 255, np.uint8)
    strip = []
    for n, p in enumerate(panels):
        if p.shape[0] < h:
            p = np.concatenate([p, np.full((h - p.shape[0], p.shape[1], 3), 255, np.uint8)])
        strip += ([gap] if n else []) + [p]
    _imwrite(folder / "nodes_overlay.png", np.concatenate(strip, axis=1))
    if blank and notes is not None:
        notes.append("node overlay drawn on blank frames (clip not available)")
    when = ", ".join(f"{c['frame']} (time {float(c['time']):.3f})" for c in cams)
    cap = (f"{bundle.nodes.count} nodes at frames {when}, left to right; colour = p_dyn "
           "(blue static → red dynamic)")
    return head + f'<figure><img class="sheet" src="nodes_overlay.png"><figcaption>{html.escape(cap)}</figcaption></figure>'
