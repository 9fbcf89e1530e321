"""A self-contained HTML report for one trained bundle.

``write_report(bundle_dir)`` writes ``<bundle>/report/report.html`` plus PNG images next to
it (no external assets, no plotting dependency: curves are inline SVG, images are written
with OpenCV):

* training loss / PSNR curves from ``scene.json`` ``stats.history``;
* held-out renders next to the ground truth (needs the clip; see ``engine eval``);
* a contact sheet of training frames spread over the clip (ground truth | render |
  |error|) and the node allocation overlay (node positions projected into their frame,
  coloured by ``p_dyn``: blue = static, red = dynamic) at several times
  (:mod:`engine.report_frames`);
* metrics (initial vs final held-out eval from ``stats``, plus ``engine eval`` results);
* the camera path and, for a solved clip, the camera model chosen and why
  (:mod:`engine.report_camera`);
* the training config.

Used by ``python -m engine train`` (at the end) and ``python -m engine report``.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

MAX_RENDERS = 4


def _svg_curve(points, title: str, color: str, width: int = 420, height: int = 220) -> str:
    """An inline SVG line chart of ``points`` [(x, y), ...] with min/max axis labels."""
    pts = [(float(x), float(y)) for x, y in points if y is not None and np.isfinite(y)]
    if len(pts) < 2:
        return f"<p><em>{html.escape(title)}: not enough points</em></p>"
    xs, ys = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    x0, x1 = xs.min(), max(xs.max(), xs.min() + 1e-9)
    y0, y1 = ys.min(), ys.max()
    if y1 - y0 < 1e-12:
        y0, y1 = y0 - 0.5, y1 + 0.5
    ml, mr, mt, mb = 52, 10, 24, 28
    pw, ph = width - ml - mr, height - mt - mb
    sx = lambda x: ml + (x - x0) / (x1 - x0) * pw  # noqa: E731
    sy = lambda y: mt + (1 - (y - y0) / (y1 - y0)) * ph  # noqa: E731
    poly = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in pts)
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" class="chart">'
            f'<text x="{ml}" y="15" font-size="13" font-weight="bold">{html.escape(title)}</text>'
            f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="#bbb"/>'
            f'<polyline fill="none" stroke="{color}" stroke-width="1.6" points="{poly}"/>'
            f'<text x="{ml - 4}" y="{mt + 10}" font-size="10" text-anchor="end">{y1:.4g}</text>'
            f'<text x="{ml - 4}" y="{mt + ph}" font-size="10" text-anchor="end">{y0:.4g}</text>'
            f'<text x="{ml}" y="{height - 8}" font-size="10">{x0:.0f}</text>'
            f'<text x="{ml + pw}" y="{height - 8}" font-size="10" text-anchor="end">step {x1:.0f}</text>'
            "</svg>")


def _table(rows: list[list], header: list[str]) -> str:
    def cell(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return "—" if v is None else html.escape(str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _imwrite(path: Path, rgb: np.ndarray) -> None:
    import cv2

    from .fsutil import atomic_path

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"could not write {path}")


def node_overlay(image: np.ndarray, K, w2c, positions: np.ndarray, p_dyn: np.ndarray | None) -> np.ndarray:
    """Draw ``positions [N, 3]`` (world) into ``image [H, W, 3]`` RGB, coloured by ``p_dyn``."""
    import cv2

    img = np.ascontiguousarray(image.copy())
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    cam = positions @ w2c[:3, :3].T + w2c[:3, 3]
    ok = cam[:, 2] > 1e-6
    uv = (cam[:, :2] / np.maximum(cam[:, 2:3], 1e-6)) @ K[:2, :2].T + K[:2, 2]
    p = np.zeros(len(positions)) if p_dyn is None else np.clip(np.asarray(p_dyn, np.float64), 0, 1)
    r = max(2, int(round(img.shape[1] / 160)))
    for (u, v), pd, good in zip(uv, p, ok):
        if not good or not (0 <= u < img.shape[1] and 0 <= v < img.shape[0]):
            continue
        color = (int(255 * pd), 40, int(255 * (1 - pd)))  # RGB: red = dynamic, blue = static
        cv2.circle(img, (int(u), int(v)), r, color, -1, lineType=cv2.LINE_AA)
        cv2.circle(img, (int(u), int(v)), r, (255, 255, 255), 1, lineType=cv2.LINE_AA)
    return img


def write_report(bundle_dir, out_html=None, eval_result=None, clip_path=None, device: str = "auto",
                 backend: str = "auto") -> Path:
    """Write the HTML report of ``bundle_dir``; returns the path of ``report.html``.

    ``eval_result`` is an :func:`engine.commands.eval.evaluate_bundle` result with
    ``_images`` (held-out renders); when None the evaluation is run here (it needs the
    clip; without it the report says so and skips the renders) on ``device`` with the
    raster ``backend`` (``engine train`` passes its own, so a ``--device cpu`` run never
    touches a GPU).
    """
    from . import bundle as B
    from .errors import InputError

    bundle_dir = Path(bundle_dir)
    bundle = B.load_bundle(bundle_dir)
    scene = bundle.scene
    out_html = Path(out_html) if out_html else bundle_dir / "report" / "report.html"
    folder = out_html.parent
    folder.mkdir(parents=True, exist_ok=True)
    stats = scene.get("stats", {}) or {}
    notes = []

    if eval_result is None or "_images" not in eval_result:
        try:
            from .commands.eval import evaluate_bundle

            eval_result = evaluate_bundle(bundle_dir, clip_path, keep_images=True, device=device, backend=backend,
                                          write=not (bundle_dir / "eval.json").exists())
        except InputError as exc:
            notes.append(f"held-out evaluation skipped: {exc.message if hasattr(exc, 'message') else exc}")
            eval_result = None

    parts = [f"<h1>Motion Splats report — {html.escape(bundle_dir.name)}</h1>",
             f"<p>bundle <code>{html.escape(str(bundle_dir.resolve()))}</code>; clip "
             f"<code>{html.escape(str((scene.get('source') or {}).get('clip', '?')))}</code></p>"]

    # curves
    hist = stats.get("history") or []
    parts.append("<h2>Training curves</h2>")
    parts.append(_svg_curve([(h["step"], h.get("loss")) for h in hist], "loss", "#c0392b")
                 + _svg_curve([(h["step"], h.get("psnr")) for h in hist], "train PSNR (dB)", "#2471a3"))

    # metrics
    parts.append("<h2>Metrics</h2>")
    ei, ef = stats.get("eval_init") or {}, stats.get("eval") or {}
    rows = [[k, ei.get(k), ef.get(k)] for k in ("frames", "psnr", "ssim", "masked_psnr") if k in ei or k in ef]
    parts.append("<p>Held-out evaluation during training (initialisation vs final):</p>")
    parts.append(_table(rows, ["metric", "initial", "final"]))
    parts.append(_table([[k, stats.get(k)] for k in ("steps", "gaussians", "nodes", "train_seconds",
                                                     "iterations_per_s") if k in stats], ["stat", "value"]))
    if eval_result is not None:
        m = eval_result["mean"]
        parts.append(f"<p><code>engine eval</code> on {m['frames']} '{html.escape(eval_result['split'])}' "
                     "frames (bundle re-rendered from disk):</p>")
        parts.append(_table([[k, m.get(k)] for k in ("psnr", "ssim", "masked_psnr", "masked_ssim", "lpips")],
                            ["metric", "mean"]))
        for n in eval_result.get("notes", []):
            notes.append(n)

    # held-out renders
    parts.append("<h2>Held-out views (render | ground truth)</h2>")
    imgs = (eval_result or {}).get("_images") or []
    if not imgs:
        parts.append("<p><em>no held-out renders (no clip or no held-out cameras)</em></p>")
    pick = np.unique(np.linspace(0, len(imgs) - 1, min(MAX_RENDERS, len(imgs))).round().astype(int)) if imgs else []
    per = {r["frame"]: r for r in (eval_result or {}).get("frames", [])}
    for j in pick:
        frame, pred, gt = imgs[int(j)]
        _imwrite(folder / f"val_{frame:05d}_render.png", pred)
        _imwrite(folder / f"val_{frame:05d}_gt.png", gt)
        r = per.get(frame, {})
        cap = f"frame {frame}: PSNR {r.get('psnr', float('nan')):.2f} dB, SSIM {r.get('ssim', float('nan')):.3f}"
        parts.append(f'<figure><img src="val_{frame:05d}_render.png"><img src="val_{frame:05d}_gt.png">'
                     f"<figcaption>{html.escape(cap)}</figcaption></figure>")

    # training frames: contact sheet + node overlay at several times (engine/report_frames.py)
    from .report_frames import contact_sheet_section, node_overlay_section

    parts.append(contact_sheet_section(bundle, folder, clip_path, device, backend, notes))
    parts.append(node_overlay_section(bundle, folder, clip_path, notes))

    # priors: which model (name + SHA-256) or weight-free backend produced each (engine/models)
    parts.append("<h2>Priors</h2>")
    parts.append(_table(_prior_rows(scene.get("priors") or {}), ["prior", "backend", "model", "sha256", "licence"])
                 if scene.get("priors") else "<p><em>not recorded (bundle written before the model manager)</em></p>")

    from .report_camera import camera_path_section

    parts.append(camera_path_section(scene))

    # config
    parts.append("<h2>Config</h2>")
    cfg = scene.get("config") or {}
    parts.append(_table([[k, json.dumps(v) if isinstance(v, (dict, list)) else v] for k, v in sorted(cfg.items())],
                        ["key", "value"]))
    if notes:
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")

    style = ("body{font-family:sans-serif;margin:24px;max-width:1100px}table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:left}"
             "img{image-rendering:pixelated;width:360px;margin-right:6px}img.sheet{width:auto;max-width:100%}"
             "figure{margin:10px 0}"
             "svg.chart{margin-right:12px}")
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>Motion Splats report</title>"
           f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
    from .fsutil import atomic_write_text

    atomic_write_text(out_html, doc)
    return out_html


def _prior_rows(priors: dict) -> list[list]:
    """One table row per prior from scene.json ``priors``: weight-free backends name no model."""
    rows = []
    for role, src in priors.items():
        model = src.get("model") or (src.get("file") if src.get("backend") == "file" else "weight-free")
        backend = src.get("backend")
        if src.get("moving_objects"):  # the weight-free depth's own depth for moving objects (pipeline.prepare)
            found = f", {src['hinges']} hinge(s)" if "hinges" in src else ""
            if src.get("hinge_tracks"):
                found += f" with {src['hinge_tracks']} tracks along their rings"
            if src.get("blob_tracks"):
                found += f", {src['blob_tracks']} tracks along compact blobs' paths"
            backend = f"{backend}; moving objects: {src['moving_objects']}{found}"
        check = src.get("check") or {}
        if src.get("set_aside"):  # a depth model less than 10% better than flat at the static points
            backend += (f"; depth model {src['set_aside'].get('model')} set aside (its error at triangulated "
                        f"static points {check.get('ratio', float('nan')):.2f}x a flat depth's)")
        elif check.get("ratio") is not None:
            backend += f"; checked: error at triangulated static points {check['ratio']:.2f}x a flat depth's"
        rows.append([role, backend, model, src.get("sha256") or "", src.get("license") or ""])
    return rows


def _frame_image(bundle, cam, clip_path):
    """The clip frame of camera ``cam`` at the bundle's resolution, or None."""
    try:
        import cv2

        from .commands.eval import _open_clip_for

        clip, _ = _open_clip_for(bundle, clip_path)
        start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
        i = int(cam["clip_index"]) if "clip_index" in cam else int(cam["frame"]) - start
        img = clip.load_frame(i, downscale=1)
        return cv2.resize(img, (int(cam["width"]), int(cam["height"])), interpolation=cv2.INTER_AREA)
    except Exception:  # noqa: BLE001 - the overlay falls back to a blank frame
        return None


def _node_positions(bundle, t: float, torch) -> np.ndarray:
    """Node positions [N, 3] at engine time ``t`` from the bundle's splines."""
    from .geometry.hermite import hermite_eval

    nd = bundle.nodes
    kt = torch.as_tensor(np.asarray(nd.key_times), dtype=torch.float32)
    keys = torch.as_tensor(np.asarray(nd.pos_keys), dtype=torch.float32)
    tan = torch.as_tensor(np.asarray(nd.pos_tangents), dtype=torch.float32)
    out = hermite_eval(kt, keys, tan, torch.tensor([t], dtype=torch.float32))
    return out.reshape(keys.shape[0], -1, 3)[:, 0].numpy().astype(np.float64)
