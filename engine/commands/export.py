"""Export a trained bundle: standard 3DGS PLY files (canonical, or one per frame).

Examples::

    python -m engine export out/run --ply canonical.ply
    python -m engine export out/run --ply-sequence plys/ --frames 1-48

Per-frame PLYs hold the Gaussians moved by the node splines (positions and rotations),
readable by common splat viewers. A PLY has no view-dependent opacity, so a bundle's
view-bound Gaussians (per-frame shot detail that fades away from its own camera,
``engine/train/shot_detail.py``) are left out of them, which is what a view from elsewhere
shows; ``--shot-camera`` keeps them at the opacity they have from each frame's own camera
(for re-rendering the shot itself).
"""

HELP = "export a bundle as standard 3DGS PLY (canonical or a per-frame sequence)"


def add_arguments(parser):
    parser.add_argument("bundle", help="result bundle folder (from `train`)")
    parser.add_argument("--ply", help="write the canonical Gaussians to this .ply file")
    parser.add_argument("--ply-sequence", help="folder for one PLY per frame")
    parser.add_argument("--frames", default="all", help="frames for --ply-sequence, e.g. 1-48 or 1-48:4")
    parser.add_argument("--shot-camera", action="store_true",
                        help="--ply-sequence: keep the per-frame shot detail as the frame's own camera sees it "
                             "(default: left out, as any other viewpoint sees it)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")


def run(args, reporter):
    from pathlib import Path

    import numpy as np
    import torch

    from .. import bundle as B
    from ..errors import InputError
    from ..train.from_bundle import model_from_bundle
    from ._common import parse_frames

    if not args.ply and not args.ply_sequence:
        raise InputError("nothing to export", None, "pass --ply FILE and/or --ply-sequence DIR")
    bundle = B.load_bundle(args.bundle)
    results = {}
    if args.ply:
        target = Path(args.ply)
        if target.exists() and not args.overwrite:
            raise InputError("file exists", target, "choose another name or pass --overwrite")
        if bundle.gaussians is None:
            raise InputError("bundle has no Gaussians yet", bundle.path, "train first")
        B.write_ply(target, bundle.gaussians)
        results["ply"] = str(target)
    if args.ply_sequence:
        out_dir = B.check_output_dir(args.ply_sequence, overwrite=args.overwrite, resumable=False,
                                     option="--ply-sequence")
        model = model_from_bundle(bundle)
        tm = bundle.scene["time"]
        frames = parse_frames(args.frames, int(tm["frame_start"]), int(tm["frame_end"]))
        shot_centers = {}
        if args.shot_camera:  # each frame's own (training) camera centre
            from ..geometry.camera import camera_centers

            for cam in bundle.scene["cameras"]:
                if cam.get("split", "train") == "train":
                    shot_centers[int(cam["frame"])] = camera_centers(torch.tensor(np.asarray(cam["w2c"]),
                                                                                  dtype=torch.float32))
        out_dir.mkdir(parents=True, exist_ok=True)  # after the checks
        g = bundle.gaussians
        with torch.no_grad():
            for i, f in enumerate(frames):
                t = float(np.clip(B.time_of_frame(bundle.scene, f), 0, 1))
                means, quats = model.deform(t)
                # Gaussians with a lifespan carry their opacity at this frame; view-bound ones
                # the opacity this frame's own camera sees them with, or none
                opacity = model.opacities_at(t, means=means, view_center=shot_centers.get(f))
                if f not in shot_centers:
                    opacity = torch.where(model.gauss_view_angle > 0, torch.zeros_like(opacity), opacity)
                opacity = opacity.clamp(1e-7, 1 - 1e-7)
                moved = B.GaussianArrays(means=means.numpy(), quats=quats.numpy(), log_scales=g.log_scales,
                                         opacity_logits=torch.logit(opacity).numpy(), sh=g.sh)
                B.write_ply(out_dir / f"frame_{f:05d}.ply", moved)
                reporter.progress("export", i + 1, len(frames))
        results["ply_sequence"] = str(out_dir)
        results["frames"] = len(frames)
    reporter.result(**results)
    return 0
