"""Evaluate a trained bundle on the held-out views of the clip it was trained on.

Examples::

    python -m engine eval out/run                        # clip path from scene.json
    python -m engine eval out/run --clip data/moved_clip # the clip moved: point at it
    python -m engine eval out/run --lpips-onnx lpips_alex.onnx --json

For every camera of ``--split`` (default ``val``) in ``scene.json`` the bundle is rendered
at that camera and time and compared with the clip's frame, brought to the bundle's
resolution exactly like training did (``engine.pipeline.load_frames_at_width``: full-size
decode, ``cv2.resize`` with ``INTER_AREA``). Metrics per frame and their mean:

* ``psnr`` (dB) and ``ssim`` (Gaussian 11x11 window, as in 3DGS) on the whole image;
* ``masked_psnr`` / ``masked_ssim`` over the pixels marked dynamic, only when the dataset
  ships masks (``clip.masks``, or the synthetic-scene ground truth ``gt/mask/<id>.png``);
  the bundle's own dynamic prior is never used (it does not exist for held-out views);
* ``lpips`` only with ``--lpips-onnx MODEL``; otherwise ``null`` with a note.

LPIPS ONNX contract: the model takes two float32 inputs of shape ``[1, 3, H, W]`` (the
rendered image and the ground truth, RGB, scaled to ``[-1, 1]``), in the order the model
declares them, and returns the distance as its first output, a scalar or any tensor with
one element (e.g. ``[1, 1, 1, 1]``). Lower is better. H and W are the bundle's camera size,
so export the model with dynamic spatial axes.

The result event carries ``frames`` (per-frame metrics) and ``mean``; the same object is
written atomically to ``<bundle>/eval.json``.
"""

from __future__ import annotations

from pathlib import Path

HELP = "held-out PSNR / SSIM (/ masked, / LPIPS with an ONNX model) of a trained bundle"

LPIPS_NOTE = "unavailable: pass --lpips-onnx"


def add_arguments(parser):
    parser.add_argument("bundle", help="result bundle folder (from `train`)")
    parser.add_argument("--clip", help="the clip the bundle was trained on (default: scene.json 'source')")
    parser.add_argument("--lpips-onnx", help="ONNX LPIPS model (two [1,3,H,W] inputs in [-1,1] -> distance)")
    parser.add_argument("--split", default="val", choices=("val", "train"), help="cameras to evaluate (default val)")
    parser.add_argument("--backend", default="auto", help="rasteriser backend (auto, reference, cpu, gsplat)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--sheet", help="write a contact sheet PNG here: ground truth | render | |error| for "
                                        "frames spread over the split (moving regions outlined in red)")
    parser.add_argument("--sheet-frames", type=int, default=6, help="rows of the contact sheet (default 6)")
    parser.add_argument("--json", action="store_true", help="print the result object as JSON on stdout")


# ----------------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------------
def ssim_map(pred, target, window: int = 11, sigma: float = 1.5):
    """Per-pixel SSIM ``[H, W]`` (channel mean) with the window of :func:`engine.train.losses.ssim`."""
    import torch.nn.functional as F

    from ..train.losses import _gaussian_window

    c = pred.shape[-1]
    x = pred.permute(2, 0, 1).unsqueeze(0)
    y = target.permute(2, 0, 1).unsqueeze(0)
    g = _gaussian_window(window, sigma, pred.device, pred.dtype)
    gx = g.view(1, 1, 1, -1).expand(c, 1, 1, window)
    gy = g.view(1, 1, -1, 1).expand(c, 1, window, 1)
    pad = window // 2

    def blur(img):
        return F.conv2d(F.conv2d(img, gx, padding=(0, pad), groups=c), gy, padding=(pad, 0), groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mu_x ** 2, blur(y * y) - mu_y ** 2, blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))
    return m[0].mean(0)


class OnnxLpips:
    """LPIPS through a user-supplied ONNX model (contract in the module docstring)."""

    def __init__(self, path):
        from ..errors import InputError

        path = Path(path)
        fix = "pass an ONNX LPIPS model with two [1,3,H,W] inputs in [-1,1] and one distance output"
        if not path.is_file():
            raise InputError("LPIPS model not found", path, fix)
        try:
            import onnxruntime as ort

            self.session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types
            raise InputError(f"cannot load the LPIPS ONNX model ({exc})", path, fix) from None
        self.inputs = [i.name for i in self.session.get_inputs()]
        if len(self.inputs) != 2:
            raise InputError(f"LPIPS model must have 2 inputs, it has {len(self.inputs)}", path, fix)
        self.path, self.fix = path, fix

    def __call__(self, pred, target) -> float:
        """``pred``, ``target``: float numpy ``[H, W, 3]`` in [0, 1] -> distance."""
        import numpy as np

        from ..errors import InputError

        def prep(a):
            return np.ascontiguousarray((a.transpose(2, 0, 1)[None] * 2.0 - 1.0).astype(np.float32))

        try:
            out = self.session.run(None, {self.inputs[0]: prep(pred), self.inputs[1]: prep(target)})[0]
        except Exception as exc:
            raise InputError(f"LPIPS model failed to run ({exc})", self.path, self.fix) from None
        out = np.asarray(out, dtype=np.float64)
        if out.size != 1 or not np.isfinite(out).all():
            raise InputError(f"LPIPS model returned shape {list(out.shape)} (need one finite value)", self.path,
                             self.fix)
        return float(out.reshape(-1)[0])


# ----------------------------------------------------------------------------------
# clip + masks
# ----------------------------------------------------------------------------------
def _open_clip_for(bundle, clip_path):
    from ..errors import InputError
    from ..io import load_clip

    src = bundle.scene.get("source") or {}
    path = clip_path or src.get("clip")
    if not path:
        raise InputError("the bundle does not record the clip it was trained on", Path(bundle.path) / "scene.json",
                         "pass --clip PATH")
    if not Path(path).exists():
        raise InputError("the clip this bundle was trained on is missing (moved or deleted)", path,
                         "pass --clip PATH with the clip's new location")
    # only the frames (and masks) are read: the cameras are the bundle's, solved or not
    return load_clip(path), Path(path)


def _camera_frame(clip, cam: dict, start: int, path):
    """The clip frame bundle camera ``cam`` saw, resized to the camera's size: uint8 [H, W, 3].

    Frame numbers follow time (vrig train/held-out pairs share one), so the clip index comes
    from ``clip_index`` when the bundle recorded it, else from the frame number.
    """
    import cv2

    from ..errors import InputError

    i = int(cam["clip_index"]) if "clip_index" in cam else int(cam["frame"]) - start
    if not 0 <= i < clip.num_frames:
        raise InputError(f"bundle frame {cam['frame']} is not in the clip ({clip.num_frames} frames)", path,
                         "pass --clip with the clip this bundle was trained on")
    w, h = int(cam["width"]), int(cam["height"])
    return i, cv2.resize(clip.load_frame(i, downscale=1), (w, h), interpolation=cv2.INTER_AREA)


def _mask_for(clip, i: int):
    """Dynamic mask ``[H, W] bool`` of clip frame ``i`` at full size, or None."""
    import cv2

    p = None
    if clip.masks is not None and i < len(clip.masks):
        p = clip.masks[i]
    elif clip.source is not None:  # synthetic-scene ground truth (tools/synth_scene.py layout)
        cand = Path(clip.source) / "gt" / "mask" / f"{clip.frame_ids[i]}.png"
        p = cand if cand.is_file() else None
    if p is None:
        return None
    m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    return None if m is None else m > 127


# ----------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------
def evaluate_bundle(bundle_dir, clip_path=None, lpips_onnx=None, split: str = "val", backend: str = "auto",
                    device: str = "auto", reporter=None, write: bool = True, keep_images: bool = False,
                    sheet=None, sheet_frames: int = 6) -> dict:
    """Evaluate ``bundle_dir`` on its ``split`` cameras; returns the eval.json object.

    With ``keep_images`` the result also holds ``_images``: a list of
    ``(frame, pred uint8 [H,W,3], gt uint8 [H,W,3])`` (not written to eval.json).
    With ``sheet`` (a path) a contact sheet of ``sheet_frames`` frames spread over the
    split is written there (:func:`engine.viz.contact_sheet`) and named in the result.
    """
    import cv2
    import numpy as np
    import torch

    from .. import bundle as B
    from ..errors import InputError
    from ..fsutil import atomic_write_json
    from ..train import losses as L
    from ..train.from_bundle import model_from_bundle
    from ..train.render import render_scene
    from ._common import pick_device

    bundle = B.load_bundle(bundle_dir)
    scene = bundle.scene
    cams = [c for c in scene["cameras"] if c.get("split", "train") == split]
    if not cams:
        raise InputError(f"the bundle has no '{split}' cameras", Path(bundle_dir) / "scene.json",
                         "train on a clip with held-out views (e.g. a Nerfies vrig capture) or use --split train")
    lp = OnnxLpips(lpips_onnx) if lpips_onnx else None
    clip, path = _open_clip_for(bundle, clip_path)
    start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
    dev = pick_device(device)
    model = model_from_bundle(bundle, dev)
    per = []
    images = []
    sheet_rows, sheet_masks = [], []
    n_sheet = max(1, min(int(sheet_frames), len(cams))) if sheet else 0
    sheet_pick = set(np.linspace(0, len(cams) - 1, n_sheet).round().astype(int).tolist()) if sheet else set()
    with torch.no_grad():
        for n, c in enumerate(cams):
            i, gt = _camera_frame(clip, c, start, path)
            w, h = int(c["width"]), int(c["height"])
            means, quats = model.deform(float(c["time"]))
            out = render_scene(model, means, quats, torch.as_tensor(np.asarray(c["K"]), dtype=torch.float32,
                                                                  device=dev),
                               torch.as_tensor(np.asarray(c["w2c"]), dtype=torch.float32, device=dev), w, h,
                               backend=backend, time=float(c["time"]))
            pred = out.rgb.clamp(0, 1)
            target = torch.as_tensor(gt, device=dev).float() / 255.0
            row = {"frame": int(c["frame"]), "time": float(c["time"]),
                   "psnr": float(L.psnr(pred, target)), "ssim": float(L.ssim(pred, target))}
            mask = _mask_for(clip, i)
            if mask is not None:
                mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            if mask is not None and mask.sum() > 16:
                mt = torch.as_tensor(mask, device=dev)
                row["masked_psnr"] = float(L.psnr(pred, target, mt.to(pred.dtype).unsqueeze(-1)))
                row["masked_ssim"] = float(ssim_map(pred, target)[mt].mean())
            row["lpips"] = lp(pred.cpu().numpy(), target.cpu().numpy()) if lp else None
            per.append(row)
            if keep_images or n in sheet_pick:
                pred_u8 = (pred.cpu().numpy() * 255 + 0.5).astype(np.uint8)
            if keep_images:
                images.append((int(c["frame"]), pred_u8, gt))
            if n in sheet_pick:
                sheet_rows.append((gt, pred_u8))
                sheet_masks.append(mask if mask is not None and mask.sum() > 16 else None)
            if reporter is not None:
                reporter.progress("eval", n + 1, len(cams), psnr=row["psnr"])
    mean = {"frames": len(per)}
    for key in ("psnr", "ssim", "masked_psnr", "masked_ssim", "lpips"):
        vals = [r[key] for r in per if r.get(key) is not None]
        mean[key] = float(np.mean(vals)) if vals else None
    result = {"bundle": str(bundle_dir), "clip": str(path), "split": split,
              "width": int(cams[0]["width"]), "height": int(cams[0]["height"]),
              "mean": mean, "frames": per,
              "lpips_model": str(lpips_onnx) if lpips_onnx else None,
              "notes": [] if lp else [f"lpips {LPIPS_NOTE}"]}
    if not any("masked_psnr" in r for r in per):
        result["notes"].append("masked metrics unavailable: the dataset provides no dynamic masks")
    if sheet:
        from ..viz import contact_sheet, write_png

        result["sheet"] = str(write_png(sheet, contact_sheet(sheet_rows, sheet_masks)))
    if write:
        atomic_write_json(Path(bundle_dir) / "eval.json", result)
        result["eval_json"] = str(Path(bundle_dir) / "eval.json")
    if keep_images:
        result["_images"] = images
    return result


def run(args, reporter):
    import json

    result = evaluate_bundle(args.bundle, args.clip, args.lpips_onnx, args.split, args.backend, args.device,
                             reporter=None if args.json else reporter, sheet=args.sheet,
                             sheet_frames=args.sheet_frames)
    if args.json:
        print(json.dumps(result))
        return 0
    m = result["mean"]
    reporter.log(f"{m['frames']} {args.split} frames: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}"
                 + (f", masked PSNR {m['masked_psnr']:.2f} dB" if m.get("masked_psnr") is not None else "")
                 + (f", LPIPS {m['lpips']:.4f}" if m["lpips"] is not None else f", LPIPS {LPIPS_NOTE}"))
    if result.get("sheet"):
        reporter.log(f"contact sheet: {result['sheet']}")
    fields = {k: v for k, v in result.items() if k != "bundle"}
    reporter.result(bundle=result["bundle"], **fields)
    return 0
