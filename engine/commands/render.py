"""Render a trained bundle: novel views at any time, from its own cameras or a
camera path exported from Blender.

Examples::

    python -m engine render out/run --frames 1-48 --out renders/
    python -m engine render out/run --camera path.json --out renders/
    python -m engine render out/run --camera val --frames 4 --time 0.5 --out still/
"""

HELP = "render novel views of a trained bundle (any time, any camera)"


def add_arguments(parser):
    parser.add_argument("bundle", help="result bundle folder (from `train`)")
    parser.add_argument("--out", required=True, help="folder for the PNG frames (created; never overwritten)")
    parser.add_argument("--camera", default="train",
                        help="'train' / 'val' (the bundle's cameras per frame) or a camera-path JSON from Blender")
    parser.add_argument("--frames", default="all", help="frames to render, e.g. 1-48, 1-48:4, 1,12,24 (default all)")
    parser.add_argument("--time", type=float, default=None, help="freeze time at this engine time in [0,1]")
    parser.add_argument("--backend", default="auto", help="rasteriser backend (auto, reference, cpu, gsplat)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--overwrite", action="store_true", help="allow writing into a non-empty --out folder")


def cameras_for_frames(scene, camera: str, frames):
    """(frame, K, w2c, width, height) per requested frame from the bundle or a path file."""
    import numpy as np

    from ..errors import InputError
    from ._common import load_camera_path

    if camera in ("train", "val"):
        cams = [c for c in scene["cameras"] if c.get("split", "train") == camera] or scene["cameras"]
        if not cams:
            raise InputError("bundle has no cameras", None, "re-run training")
        cam_frames = np.array([c["frame"] for c in cams], dtype=np.float64)
        out = []
        for f in frames:
            c = cams[int(np.argmin(np.abs(cam_frames - f)))]
            out.append((f, np.asarray(c["K"]), np.asarray(c["w2c"]), c["width"], c["height"]))
        return out
    path_cams = load_camera_path(camera)
    wanted = set(frames) if frames else None
    return [(c["frame"], c["K"], c["w2c"], c["width"], c["height"]) for c in path_cams
            if wanted is None or int(round(c["frame"])) in wanted]


def run(args, reporter):
    from pathlib import Path

    import numpy as np
    import torch

    from .. import bundle as B
    from ..bundle import check_output_dir, time_of_frame
    from ..errors import InputError
    from ..fsutil import atomic_path
    from ..train.from_bundle import model_from_bundle
    from ..train.render import render_scene
    from ._common import parse_frames, pick_device

    import cv2

    if args.time is not None and not 0.0 <= args.time <= 1.0:  # also refuses nan
        raise InputError(f"--time {args.time} is outside [0, 1] (engine time: 0 = first frame, 1 = last)", None,
                         "pass a number between 0 and 1, or leave --time out")
    out_dir = check_output_dir(args.out, overwrite=args.overwrite, resumable=False)
    bundle = B.load_bundle(args.bundle)
    scene = bundle.scene
    device = pick_device(args.device)
    model = model_from_bundle(bundle, device)
    tm = scene["time"]
    frames = parse_frames(args.frames, int(tm["frame_start"]), int(tm["frame_end"]))
    if args.camera not in ("train", "val") and args.frames == "all":
        frames = []  # a camera path renders all of its own frames
    views = cameras_for_frames(scene, args.camera, frames)
    if not views:
        raise InputError("no frames to render", Path(args.camera) if args.camera not in ("train", "val") else None,
                         "check --frames against the bundle's frame range")
    out_dir.mkdir(parents=True, exist_ok=True)  # after every check: a refused render creates nothing
    written = []
    with torch.no_grad():
        for i, (frame, K, w2c, w, h) in enumerate(views):
            t = float(args.time) if args.time is not None else float(np.clip(time_of_frame(scene, frame), 0, 1))
            means, quats = model.deform(t)
            out = render_scene(model, means, quats, torch.as_tensor(K, dtype=torch.float32, device=device),
                               torch.as_tensor(w2c, dtype=torch.float32, device=device), int(w), int(h),
                               backend=args.backend, time=t)
            img = (out.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
            path = out_dir / f"frame_{int(round(frame)):05d}.png"
            with atomic_path(path) as tmp:
                if not cv2.imwrite(str(tmp), img[..., ::-1]):
                    raise InputError("could not write PNG (disk full, or the folder is not writable)", path,
                                     "free disk space or choose a writable --out folder")
            written.append(str(path))
            reporter.progress("render", i + 1, len(views))
    reporter.result(out=str(out_dir), frames=len(written), files=written[:3] + (["..."] if len(written) > 3 else []))
    return 0
