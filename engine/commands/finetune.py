"""Fine-tune a trained bundle's appearance with its node trajectories locked.

Examples::

    python -m engine finetune out/run --steps 300            # update out/run, back up the old files
    python -m engine finetune out/run --out out/run_ft       # write a new bundle instead
    python -m engine finetune out/run --clip data/moved_clip # the clip moved: point at it

The artist's workflow: edit node F-curves in Blender, *Send edits* (the bundle's
``nodes.npz`` now holds the edited keys and tangents), then fine-tune. The motion is
exactly the bundle's splines (explicit tangents, incoming ones too when the Bézier
handles were broken) and is never optimised; the Gaussians' canonical centres and their
binding stay fixed too, so ``nodes.npz`` and the positions in ``gaussians.ply`` are
unchanged bit for bit and Blender's rig keeps working. Only appearance is trained:
rotations, scales, opacities and SH colours, with the photometric loss (L1 + D-SSIM) on
the bundle's training views (the clip recorded in ``scene.json``, frames brought to the
bundle's resolution as in training).

Output: by default the bundle is updated in place, after copying the files it replaces
(``gaussians.ply``, ``scene.json``, a stale ``eval.json``) into
``<bundle>/backups/finetune-<time>/``; ``--no-backup`` skips that copy. ``--out DIR``
writes a new bundle (``nodes.npz`` copied) and leaves the input untouched; a non-empty
``DIR`` needs ``--overwrite``. Every file is written atomically. When the fine-tuned
appearance does not improve the training-view PSNR the original is kept (a warning says
so). Ctrl-C / Cancel stops without changing anything.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

HELP = "fine-tune appearance (colour, opacity, scale, rotation) with the node motion locked"

#: appearance parameters of engine.train.model.DynamicScene trained here
APPEARANCE = ("quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
#: training views used for the before/after PSNR (evenly spread)
EVAL_VIEWS = 16


def add_arguments(parser):
    parser.add_argument("bundle", help="trained result bundle folder (from `train`, edits sent from Blender)")
    parser.add_argument("--steps", type=int, default=200, help="optimisation steps (default 200)")
    parser.add_argument("--clip", help="the clip the bundle was trained on (default: scene.json 'source')")
    parser.add_argument("--out", help="write a new bundle here instead of updating BUNDLE in place")
    parser.add_argument("--overwrite", action="store_true", help="with --out: replace a non-empty folder")
    parser.add_argument("--no-backup", action="store_true",
                        help="in place: do not copy the replaced files to <bundle>/backups/")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--backend", default="auto", help="rasteriser backend (auto, reference, cpu, gsplat)")


# ----------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------
def training_views(bundle, clip_path=None, device="cpu", reporter=None) -> list[dict]:
    """The bundle's training cameras with their clip frames at the bundle's resolution.

    Each view: ``{"frame", "time", "K" [3,3], "w2c" [4,4], "width", "height", "image" [H,W,3]}``
    (tensors on ``device``, image float in [0, 1]).
    """
    import numpy as np
    import torch

    from ..errors import InputError
    from .eval import _camera_frame, _open_clip_for

    cams = [c for c in bundle.scene["cameras"] if c.get("split", "train") == "train"]
    if not cams:
        raise InputError("the bundle has no training cameras", Path(bundle.path) / "scene.json",
                         "fine-tune a bundle written by `python -m engine train`")
    clip, path = _open_clip_for(bundle, clip_path)
    start = int(clip.meta.get("frame_start", 1)) if isinstance(clip.meta, dict) else 1
    views = []
    for n, c in enumerate(cams):
        _, img = _camera_frame(clip, c, start, path)
        w, h = int(c["width"]), int(c["height"])
        as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
        views.append({"frame": int(c["frame"]), "time": float(c["time"]), "K": as_t(c["K"]), "w2c": as_t(c["w2c"]),
                      "width": w, "height": h, "image": as_t(img) / 255.0})
        if reporter is not None:
            reporter.progress("load frames", n + 1, len(cams))
    return views


# ----------------------------------------------------------------------------------
# optimisation
# ----------------------------------------------------------------------------------
def _render(model, view, backend):
    from ..train.render import render_scene

    means, quats = model.deform(view["time"])
    return render_scene(model, means, quats, view["K"], view["w2c"], view["width"], view["height"], backend=backend,
                        time=view["time"])


def mean_psnr(model, views, backend="auto") -> float:
    import numpy as np
    import torch

    from ..train import losses as L

    with torch.no_grad():
        return float(np.mean([float(L.psnr(_render(model, v, backend).rgb.clamp(0, 1), v["image"])) for v in views]))


def finetune_appearance(model, views, steps: int, config=None, seed: int = 0, backend: str = "auto",
                        reporter=None) -> dict:
    """Optimise ``model``'s appearance on ``views`` for ``steps`` steps; motion and centres stay fixed.

    ``model`` must have locked trajectories (:func:`engine.train.from_bundle.model_from_bundle`
    sets the bundle's explicit tangents). Returns ``{"steps", "psnr_before", "psnr_after",
    "kept_original", "seconds"}``; when the training-view PSNR got worse the original
    appearance is restored (``kept_original``).
    """
    import torch

    from ..train import losses as L
    from ..train.config import TrainConfig

    cfg = config or TrainConfig()
    if model.mlp is not None or getattr(model, "explicit_tangents", None) is None:
        raise ValueError("finetune_appearance needs a model with locked spline trajectories (model_from_bundle)")
    for p in model.parameters():
        p.requires_grad_(False)
    params = {name: getattr(model, name) for name in APPEARANCE}
    lrs = {"quats": cfg.lr_quats, "log_scales": cfg.lr_scales, "opacity_logits": cfg.lr_opacity,
           "sh_dc": cfg.lr_sh, "sh_rest": cfg.lr_sh / 20}
    groups = []
    for name, p in params.items():
        if p.numel():
            p.requires_grad_(True)
            groups.append({"name": name, "params": [p], "lr": lrs[name]})
    original = {name: p.detach().clone() for name, p in params.items()}
    opt = torch.optim.Adam(groups, eps=1e-15)
    gen = torch.Generator().manual_seed(int(seed))
    picks = torch.linspace(0, len(views) - 1, min(EVAL_VIEWS, len(views))).round().long().unique().tolist()
    eval_views = [views[i] for i in picks]
    before = mean_psnr(model, eval_views, backend)
    t0 = time.perf_counter()
    log_every = max(1, min(10, steps // 50))  # the UI sees progress within seconds
    for step in range(1, steps + 1):
        v = views[int(torch.randint(0, len(views), (1,), generator=gen))]
        out = _render(model, v, backend)
        loss = L.photometric(out.rgb, v["image"], cfg.loss.ssim)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if reporter is not None and (step % log_every == 0 or step == steps):
            with torch.no_grad():
                psnr = float(L.psnr(out.rgb.detach().clamp(0, 1), v["image"]))
            reporter.progress("finetune", step, steps, loss=float(loss), psnr=psnr)
    seconds = time.perf_counter() - t0
    for p in params.values():
        p.requires_grad_(False)
    after = mean_psnr(model, eval_views, backend)
    kept = after < before
    if kept:
        with torch.no_grad():
            for name, p in params.items():
                p.copy_(original[name])
    return {"steps": steps, "psnr_before": before, "psnr_after": after, "kept_original": kept,
            "seconds": round(seconds, 2), "views": len(views)}


# ----------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------
def _backup(bundle_dir: Path, names) -> Path:
    """Copy the files about to be replaced into ``backups/finetune-<time>/`` (new folder)."""
    import shutil

    base = bundle_dir / "backups"
    stamp = time.strftime("%Y%m%d-%H%M%S")
    dest, n = base / f"finetune-{stamp}", 1
    while dest.exists():
        n += 1
        dest = base / f"finetune-{stamp}-{n}"
    # copied into a hidden sibling, renamed when complete: a full disk or a kill leaves no
    # truncated backup that looks whole
    partial = base / f".{dest.name}.partial"
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    try:
        for name in names:
            src = bundle_dir / name
            if src.is_file():
                shutil.copy2(src, partial / name)
                with open(partial / name, "rb") as fh:
                    os.fsync(fh.fileno())
        os.replace(partial, dest)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return dest


def write_finetuned(bundle, model, summary: dict, out=None, overwrite: bool = False, backup: bool = True) -> dict:
    """Write the fine-tuned appearance (see the module docstring); returns paths written."""
    import shutil

    from .. import bundle as B
    from ..fsutil import atomic_path
    from ..geometry.quaternion import quat_normalize

    src = Path(bundle.path)
    gs = bundle.gaussians
    if summary.get("kept_original"):
        new = gs  # the file's own values, bit for bit
    else:
        new = B.GaussianArrays(means=gs.means,  # centres are not trained: the exact original values
                               quats=quat_normalize(model.quats.detach()).cpu().numpy(),
                               log_scales=model.log_scales.detach().cpu().numpy(),
                               opacity_logits=model.opacity_logits.detach().cpu().numpy(),
                               sh=model.sh().detach().cpu().numpy())
    scene = dict(bundle.scene)
    stats = dict(scene.get("stats") or {})
    history = list(stats.get("finetune") or [])
    history.append({k: summary[k] for k in ("steps", "psnr_before", "psnr_after", "kept_original", "seconds")}
                   | {"time": time.strftime("%Y-%m-%dT%H:%M:%S")})
    stats["finetune"] = history
    scene["stats"] = stats
    written = {"backup": None}
    if out is None:
        dest = src
        replaced = [B.GAUSSIANS_FILE, B.SCENE_FILE, "eval.json"]
        if backup:
            written["backup"] = str(_backup(src, replaced))
        stale = src / "eval.json"  # metrics of the previous appearance
        if stale.is_file():
            stale.unlink()
    else:
        dest = B.check_output_dir(out, overwrite=overwrite)
        if dest.resolve() == src.resolve():
            from ..errors import InputError

            raise InputError("--out is the input bundle", dest, "leave out --out to update the bundle in place")
        if overwrite:
            B.clear_run_outputs(dest)
        dest.mkdir(parents=True, exist_ok=True)
        with atomic_path(dest / B.NODES_FILE) as tmp:
            shutil.copyfile(src / B.NODES_FILE, tmp)  # the locked motion, byte for byte
    B.save_bundle(dest, scene, None, new)  # gaussians.ply, then scene.json
    written["bundle"] = str(dest)
    return written


def run(args, reporter):
    from .. import bundle as B
    from ..errors import InputError
    from ..lock import hold

    if args.steps < 1:
        raise InputError(f"--steps must be at least 1 (got {args.steps})", None, "e.g. --steps 200")
    if args.no_backup and args.out:
        raise InputError("--no-backup only applies to in-place updates", None, "drop --no-backup when using --out")
    if args.out is not None:  # refuse early, before minutes of work
        B.check_output_dir(args.out, overwrite=args.overwrite, resumable=False)
    if not Path(args.bundle).is_dir():
        raise InputError("bundle folder not found", args.bundle, "pass the folder given to `engine train --out`")
    with hold(args.out or args.bundle):  # one writer: no train or other fine-tune in the same folder
        return _finetune(args, reporter)


def _finetune(args, reporter):
    import torch

    from .. import bundle as B
    from ..errors import Cancelled
    from ..train.config import TrainConfig
    from ..train.from_bundle import model_from_bundle
    from ..train.warmup import warm_kernels
    from ._common import pick_device

    bundle = B.load_bundle(args.bundle)
    device = pick_device(args.device)
    torch.manual_seed(args.seed)
    model = model_from_bundle(bundle, device)
    # the learning rates come from the bundle's config: an invalid one is refused (its error
    # names scene.json and the key), never silently replaced by defaults
    cfg = TrainConfig.from_dict(bundle.scene.get("config") or {}, str(Path(args.bundle) / B.SCENE_FILE))
    views = training_views(bundle, args.clip, device, reporter)
    reporter.log(f"fine-tuning appearance of {model.num_gaussians} Gaussians on {len(views)} views, "
                 f"{model.num_nodes} nodes locked, {args.steps} steps")
    warm_kernels(reporter, device, args.backend)  # the `compile` stage (a first run compiles)
    try:
        summary = finetune_appearance(model, views, args.steps, cfg, args.seed, args.backend, reporter)
    except KeyboardInterrupt:
        raise Cancelled("fine-tuning stopped; the bundle was not changed") from None
    if summary["kept_original"]:
        reporter.log(f"fine-tuning lowered the training-view PSNR ({summary['psnr_before']:.2f} -> "
                     f"{summary['psnr_after']:.2f} dB); the original appearance is kept", "warning")
    written = write_finetuned(bundle, model, summary, args.out, args.overwrite, backup=not args.no_backup)
    reporter.result(bundle=written["bundle"], backup=written["backup"], gaussians=model.num_gaussians,
                    nodes=model.num_nodes, **summary)
    return 0
