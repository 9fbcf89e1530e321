"""The report's "Camera path" section: where the cameras went and how the solve chose its model.

:func:`camera_path_section` turns ``scene.json`` (``cameras`` and, for a clip solved by the engine,
``camera_solve`` from :func:`engine.io.solve_select.summary`) into self-contained HTML: an inline SVG
of the camera centres seen from above their path (the two principal axes of the centres, coloured by
time, with each camera's viewing direction) and a table of the solve's model, reason and quality.
"""

from __future__ import annotations

import html

import numpy as np

from .geometry.poses import camera_centres

ROWS = (("model", "model"), ("mapper", "SfM mapper"), ("reason", "why"), ("num_registered", "frames registered"),
        ("num_frames", "frames solved"), ("mean_reproj_error", "mean reprojection / transfer error (px)"),
        ("num_points", "sparse points"), ("parallax_px", "parallax at long gaps (px, solve resolution)"),
        ("parallax_floor_px", "parallax between neighbours (px)"), ("fov_deg", "assumed field of view (deg)"),
        ("max_rotation_deg", "largest rotation (deg)"), ("rejected", "rejected candidates"))


def camera_path_svg(w2c: np.ndarray, times: np.ndarray, size: int = 360) -> str:
    """Top-down inline SVG of the camera centres of ``w2c [F,4,4]`` (colour = ``times [F]``).

    The view plane is spanned by the two principal axes of the centres (the third, least spread, is
    dropped); a short tick per camera shows its viewing direction (+z) in that plane. A path that does
    not move (fixed centre) is drawn as one point with the ticks fanning out.
    """
    w2c = np.asarray(w2c, np.float64)
    R = w2c[:, :3, :3]
    C = camera_centres(w2c)
    fwd = R[:, 2, :]  # camera +z in world coordinates
    mu = C.mean(0)
    spread = np.linalg.norm(C - mu, axis=1).max()
    axes = np.linalg.svd(C - mu)[2][:2] if spread > 1e-9 else np.linalg.svd(fwd - fwd.mean(0) + 1e-12)[2][:2]
    xy = (C - mu) @ axes.T
    d = fwd @ axes.T
    half = max(np.abs(xy).max(), 1e-9)
    tick = 0.12 * (2 * half if spread > 1e-9 else 1.0)
    scale = 0.42 * size / (half + tick if spread > 1e-9 else tick)
    px = lambda v: (size / 2 + v[..., 0] * scale, size / 2 - v[..., 1] * scale)  # noqa: E731
    t = np.asarray(times, np.float64)
    t = (t - t.min()) / max(np.ptp(t), 1e-12)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" class="chart">',
             f'<rect width="{size}" height="{size}" fill="none" stroke="#bbb"/>']
    x0, y0 = px(xy)
    x1, y1 = px(xy + tick * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
    for k in range(len(C)):
        col = f"rgb({int(40 + 200 * t[k])},60,{int(240 - 200 * t[k])})"
        parts.append(f'<line x1="{x0[k]:.1f}" y1="{y0[k]:.1f}" x2="{x1[k]:.1f}" y2="{y1[k]:.1f}" stroke="{col}" '
                     'stroke-width="1"/>')
        parts.append(f'<circle cx="{x0[k]:.1f}" cy="{y0[k]:.1f}" r="2.5" fill="{col}"/>')
    parts.append(f'<text x="6" y="14" font-size="11">path length {np.linalg.norm(np.diff(C, axis=0), axis=1).sum():.3g}'
                 " scene units (blue = first frame, red = last)</text></svg>")
    return "".join(parts)


def camera_path_section(scene: dict) -> str:
    """HTML of the "Camera path" section for a ``scene.json`` mapping (empty cameras: a note)."""
    cams = sorted(scene.get("cameras") or [], key=lambda c: float(c.get("time", 0)))
    out = ["<h2>Camera path</h2>"]
    if not cams:
        return out[0] + "<p><em>no cameras in scene.json</em></p>"
    w2c = np.array([c["w2c"] for c in cams], np.float64)
    out.append(camera_path_svg(w2c, np.array([float(c.get("time", 0)) for c in cams])))
    solve = scene.get("camera_solve")
    if not solve:
        out.append("<p>Cameras came with the clip (not solved by the engine).</p>")
        return "".join(out)
    rows = []
    for key, label in ROWS:
        if key in solve and solve[key] not in (None, [], ""):
            v = solve[key]
            v = "; ".join(v) if isinstance(v, list) else v
            v = f"{v:.3g}" if isinstance(v, float) else str(v)
            rows.append(f"<tr><td>{html.escape(label)}</td><td>{html.escape(v)}</td></tr>")
    out.append("<table><tr><th>camera solve</th><th></th></tr>" + "".join(rows) + "</table>")
    return "".join(out)
