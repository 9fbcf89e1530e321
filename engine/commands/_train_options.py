"""Options shared by `prepare`, `init` and `train` (clip, priors, presets, ablations)."""

from __future__ import annotations


def add_clip_options(parser):
    parser.add_argument("clip", help="clip: Nerfies/HyperNeRF or D-NeRF folder, COLMAP folder, N3DV folder, "
                                     "clip manifest JSON (from Blender), video file or image folder")
    parser.add_argument("--out", required=True, help="result bundle folder")
    parser.add_argument("--preset", default="preview", choices=("preview", "standard", "high"),
                        help="size/steps preset (default preview: minutes on a 2-core CPU)")
    parser.add_argument("--config", help="TrainConfig overrides (keys as in scene.json 'config'): a JSON file, or "
                                         "the JSON object itself, e.g. '{\"max_gaussians\": 60000}'")
    parser.add_argument("--width", type=int, help="training width in pixels (preset default)")
    parser.add_argument("--steps", type=int, help="training steps (preset default)")
    parser.add_argument("--nodes", type=int, dest="num_nodes", help="node budget (preset default)")
    parser.add_argument("--keys", type=int, dest="num_keys",
                        help="spline keyframes per node (default: one per ~4 training frames, at least 4); "
                             "MANI's own settings go in --config as {\"mani\": {\"eta\": ..., \"r_max\": ...}}")
    parser.add_argument("--init", choices=("mani", "fps", "voxel", "tracklet"), help="node initialiser (default mani)")
    parser.add_argument("--motion", choices=("spline", "mlp", "per_frame"), help="node motion model (default spline)")
    parser.add_argument("--motion-init", choices=("auto", "tracks", "rest"),
                        help="starting node trajectories: splines fitted to lifted 2D tracks, or at rest (default "
                             "auto: tracks when the depth comes from --depth-model/--depth-path, else rest)")
    parser.add_argument("--lifespan", choices=("auto", "on", "off"),
                        help="moving Gaussians visible only around the frame they were seeded from (default auto: "
                             "on when the camera does not translate, e.g. a tripod shot)")
    parser.add_argument("--max-frames", type=int, help="sub-sample the clip to at most this many frames")
    parser.add_argument("--holdout", type=int, metavar="N",
                        help="withhold every N-th training frame from training and score it (clips without a "
                             "held-out camera, e.g. any video); the still plate's PSNR is printed beside it")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--backend", choices=("auto", "reference", "cpu", "gsplat"), help="rasteriser backend")
    parser.add_argument("--scale", type=int, default=None, help="dataset downscale folder (Nerfies rgb/{1,2,4}x)")
    parser.add_argument("--fov", type=float, default=None,
                        help="lens field of view in degrees across the long image side, for clips without cameras "
                             "(focal prior of the camera solve; default 60)")
    parser.add_argument("--cache", help="priors cache folder (default: <out>/cache)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bundle in --out")
    pri = parser.add_argument_group("priors (ONNX models and precomputed files; all optional)")
    pri.add_argument("--tokens-model", help="ONNX ViT feature extractor (e.g. DINOv2 ViT-S/14)")
    pri.add_argument("--depth-model", help="ONNX monocular depth model")
    pri.add_argument("--mask-model", help="ONNX segmentation model for the foreground prior")
    pri.add_argument("--tracks-model", help="ONNX point tracker")
    pri.add_argument("--flow-model", help="ONNX optical flow (RAFT contract) for the tracks and the motion mask")
    pri.add_argument("--flow-backend", choices=("auto", "dis", "onnx"),
                     help="optical flow: dis (weight-free, default), onnx (--flow-model or the shipped RAFT-small), "
                          "auto (the shipped RAFT-small when usable, else dis)")
    pri.add_argument("--flow-alone", action="store_true",
                     help="use a learned flow alone (default: per pixel the learned flow or DIS, whichever matches "
                          "the next frame better)")
    pri.add_argument("--depth-output", choices=("inverse", "depth"),
                     help="what --depth-model predicts: inverse (larger = nearer, MiDaS/Depth Anything) or depth "
                          "(larger = farther, e.g. PyDNet); default: the model's sidecar JSON, else inverse")
    pri.add_argument("--depth-sidecar", metavar="JSON",
                     help="--depth-model's input settings when no sidecar JSON sits beside it: a JSON object or "
                          "the path of a JSON file, e.g. '{\"size_multiple\": 64, \"mean\": [0,0,0], "
                          "\"std\": [1,1,1]}' (PyDNet: RGB/255, sides multiples of 64)")
    pri.add_argument("--depth-check", choices=("auto", "off"),
                     help="--depth-model is first scored against the triangulated static points: one that "
                          "explains them less than 10%% better than a flat depth is set aside for the weight-free depth "
                          "(default auto; off: use the model whatever it scores)")
    pri.add_argument("--depth-path", help="precomputed depth (.npy [F,H,W] or folder of 16-bit PNG)")
    pri.add_argument("--mask-path", help="precomputed masks (folder of PNG)")
    pri.add_argument("--tracks-path", help="precomputed tracks (.npz with xy [P,F,2], visible [P,F])")
    pri.add_argument("--resting-objects", choices=("auto", "off"),
                     help="motion mask: things that rest at some times and move at others (a cup set down and "
                          "picked up again) are moving content in every frame (default auto: when the camera does "
                          "not translate; off: only where they move)")
    pri.add_argument("--hinges", choices=("auto", "depth", "off"),
                     help="weight-free depth: a moving object that turns about a static point (a pendulum, an arm "
                          "swung from a still body) takes that point's depth, found by parallax, and long tracks "
                          "along its rings (default auto; depth: the depth only; off: ground contact and occlusion "
                          "order only)")
    pri.add_argument("--blob-tracks", choices=("auto", "off"),
                     help="weight-free depth: a compact moving object (convex, keeping its size: a ball, a box) "
                          "gets long tracks along its outline's path, where the optical flow's tracks end within "
                          "a few frames (default auto; off: none)")
    pri.add_argument("--no-models", action="store_true",
                     help="ignore installed models (python -m engine models): weight-free backends for every "
                          "prior not given above")


def config_from_args(args):
    import json
    from pathlib import Path

    from ..errors import InputError
    from ..train.config import PRESETS, TrainConfig, preset_config

    overrides = {}
    if args.config:
        # an object written on the command line (the docs' one-off overrides) or a file's path
        inline = args.config.lstrip().startswith("{")
        source = "--config" if inline else args.config
        try:
            overrides = json.loads(args.config if inline else Path(args.config).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read config JSON ({exc})", source, "pass a JSON object of TrainConfig keys")
        if not isinstance(overrides, dict):
            raise InputError("config must be a JSON object", source, "e.g. {\"steps\": 2000}")
        # validated on its own first, so its errors name the file (or --config) and the key
        TrainConfig.from_dict({**PRESETS.get(args.preset, {}), **overrides, "preset": args.preset}, source)
    options = {}
    for key in ("width", "steps", "num_nodes", "num_keys", "init", "motion", "motion_init", "seed", "device", "backend",
                "holdout", "lifespan"):
        value = getattr(args, key, None)
        if value is not None:
            options[key] = value
    if getattr(args, "max_frames", None):
        options["max_frames"] = args.max_frames
    preset_config(args.preset, source="command-line options", **options)
    return preset_config(args.preset, **{**overrides, **options})


def prior_config_from_args(args):
    from ..priors import PriorConfig

    cfg = PriorConfig()
    if args.tokens_model:
        cfg.tokens_backend, cfg.tokens_model = "onnx", args.tokens_model
    if args.depth_model:
        cfg.depth_backend, cfg.depth_model = "onnx", args.depth_model
    if args.mask_model:
        cfg.mask_backend, cfg.mask_model = "onnx", args.mask_model
    if args.tracks_model:
        cfg.tracks_backend, cfg.tracks_model = "onnx", args.tracks_model
    if getattr(args, "flow_backend", None):
        cfg.flow_backend = args.flow_backend
    if getattr(args, "flow_model", None):
        cfg.flow_backend, cfg.flow_model = "onnx", args.flow_model
    if getattr(args, "flow_alone", False):
        cfg.flow_fuse_dis = False
    cfg.depth_output = getattr(args, "depth_output", None)
    if getattr(args, "depth_check", None):
        cfg.depth_check = args.depth_check
    if getattr(args, "depth_sidecar", None):
        from ..priors.onnx_util import parse_settings

        cfg.depth_sidecar = parse_settings(args.depth_sidecar)
    if getattr(args, "resting_objects", None):
        cfg.resting_objects = args.resting_objects
    if getattr(args, "hinges", None):
        cfg.hinges = args.hinges
    if getattr(args, "blob_tracks", None):
        cfg.blob_tracks = args.blob_tracks
    cfg.depth_path, cfg.mask_path, cfg.tracks_path = args.depth_path, args.mask_path, args.tracks_path
    given = manifest_priors(args.clip)  # a clip manifest's own precomputed priors, unless an option overrides
    cfg.depth_path = cfg.depth_path or given.get("depth")
    cfg.mask_path = cfg.mask_path or given.get("mask")
    cfg.tracks_path = cfg.tracks_path or given.get("tracks")
    if getattr(args, "no_models", False):
        return cfg
    from ..models import resolve_prior_models  # backend auto: installed models fill the open roles

    return resolve_prior_models(cfg, explicit={"flow"} if getattr(args, "flow_backend", None) else ())


def manifest_priors(clip) -> dict[str, str]:
    """``{"depth"|"mask"|"tracks": path}`` from a clip manifest's ``priors`` (``{}`` for other clips).

    Paths are relative to the manifest and confined like its frames
    (:func:`engine.io.manifest.media_path`).
    """
    from pathlib import Path

    from ..io.clip import load_json
    from ..io.manifest import PRIOR_EXTS, is_manifest, media_path, validate_manifest

    path = Path(clip)
    if not is_manifest(path):
        return {}
    m = load_json(path)
    validate_manifest(m, path)
    return {k: str(media_path(path.parent, v, PRIOR_EXTS, f"priors.{k}", path))
            for k, v in (m.get("priors") or {}).items()}


def clip_options(args) -> dict:
    out = {"scale": args.scale} if args.scale else {}
    if getattr(args, "fov", None):
        out["fov_deg"] = args.fov
    return out


def check_run_output(args) -> None:
    """Everything about ``--out`` that can be checked before minutes of work: not the input,
    not a file, not a finished run for ``--resume``, a readable checkpoint to resume, the
    clip path exists."""
    from pathlib import Path

    from .. import bundle as B
    from ..errors import InputError

    if not Path(args.clip).exists():
        raise InputError("clip path does not exist", args.clip, "check the clip path")
    B.check_not_input(args.out, args.clip)
    resume = getattr(args, "resume", False)
    B.check_output_dir(args.out, overwrite=args.overwrite, resume=resume)
    ckpt = Path(args.out) / "checkpoints" / "checkpoint.pt"
    if resume and ckpt.exists():
        from ..train.checkpoint import load_state

        load_state(ckpt)  # unreadable / pickled / incomplete: refused now, not after the priors
