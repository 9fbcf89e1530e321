"""The reconstruction pipeline: clip -> cameras -> priors -> nodes -> training.

Each stage is a function that the CLI commands (``prepare``, ``init``, ``train``) and the
demo call; stages cache what they can, emit progress through a
:class:`~engine.protocol.Reporter`, and raise :class:`~engine.errors.InputError` for bad
input. Everything runs at the training resolution (``TrainConfig.width``): frames are
downscaled once and the priors are computed on those frames, so all maps and tracks
share one pixel grid.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from . import bundle as B
from .errors import InputError
from .geometry.camera import scene_extent
from .protocol import Reporter
from .train.config import TrainConfig, scale_to_frames, steps_per_frame
from .train.data import TrainingData
from .train.lifespan import run_has_lifespans


@dataclasses.dataclass
class PreparedClip:
    """A clip at training resolution with its priors (all numpy).

    Attributes
    ----------
    frames : (F, H, W, 3) uint8.
    K : (F, 3, 3) intrinsics at this resolution; w2c : (F, 4, 4); times : (F,).
    train_idx, val_idx : frame indices.
    priors : the object returned by :func:`engine.priors.compute_priors`.
    frame_numbers : (F,) scene frame numbers; fps; extent; source path.
    clip_index : (F,) index of each frame in the source clip (for evaluation against it).
    camera_solve : scene.json ``camera_solve`` record when the engine solved the cameras
        (:func:`engine.io.solve_select.summary`: model, why, quality), else None.
    held_out_cameras : the clip has views of its own it does not train on (its ``val`` split;
        frames withheld by ``--holdout`` do not count: they lie on the training camera's path).
    """

    frames: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    times: np.ndarray
    train_idx: np.ndarray
    val_idx: np.ndarray
    priors: object
    frame_numbers: np.ndarray
    fps: float
    extent: float
    source: str
    clip_index: np.ndarray | None = None
    camera_solve: dict | None = None
    held_out_cameras: bool = True


def load_frames_at_width(clip, width: int, reporter: Reporter | None = None, max_frames: int = 0):
    """All frames of ``clip`` resized to ``width`` px wide (aspect kept), with matching K.

    Returns ``frames [F, h, w, 3] uint8``, ``K [F, 3, 3]``, the frame indices used.
    """
    import cv2

    idx = np.arange(clip.num_frames)
    if max_frames and clip.num_frames > max_frames:
        idx = np.unique(np.linspace(0, clip.num_frames - 1, max_frames).round().astype(int))
    if reporter is not None and int(width) > clip.width:  # say so: the config asked for more than the clip has
        reporter.log(f"training width {int(width)} px is wider than the clip ({clip.width} px); training at "
                     f"{clip.width} px", "warning")
    width = min(int(width), clip.width)
    height = max(1, int(round(clip.height * width / clip.width)))
    frames = np.empty((len(idx), height, width, 3), np.uint8)
    for j, i in enumerate(idx):  # one decode + resize per frame (I/O bound)
        img = clip.load_frame(int(i), downscale=1)
        frames[j] = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        if reporter is not None:
            reporter.progress("load frames", j + 1, len(idx))
    K = clip.K[idx].copy()
    K[:, 0, :] *= width / clip.width
    K[:, 1, :] *= height / clip.height
    return frames, K, idx


def training_data(prep: PreparedClip, device="cpu") -> TrainingData:
    """Tensors for :class:`~engine.train.trainer.Trainer` from a prepared clip."""
    pr = prep.priors
    f = lambda a: None if a is None else torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32,  # noqa
                                                         device=device)
    tracks = getattr(pr, "tracks", None)
    return TrainingData(
        images=torch.as_tensor(prep.frames, device=device).float() / 255.0,
        K=f(prep.K), w2c=f(prep.w2c), times=f(prep.times),
        train_idx=torch.as_tensor(prep.train_idx, dtype=torch.long, device=device),
        val_idx=torch.as_tensor(prep.val_idx, dtype=torch.long, device=device),
        depth=f(getattr(pr, "depth", None)), fg=f(getattr(pr, "dynamic", None)),
        tracks_xy=None if tracks is None else f(tracks.xy),
        tracks_vis=None if tracks is None else torch.as_tensor(tracks.visible, dtype=torch.bool, device=device),
        tracks_depth=None if tracks is None else f(getattr(tracks, "depth", None)),
        extent=prep.extent, frame_numbers=torch.as_tensor(prep.frame_numbers), fps=prep.fps,
        clip_index=None if prep.clip_index is None else torch.as_tensor(prep.clip_index),
        held_out_cameras=prep.held_out_cameras,
    ).validate()


def node_arrays_from(nodeset) -> B.NodeArrays:
    """Accept a NodeArrays, or any node set exposing ``to_npz_dict()``."""
    if isinstance(nodeset, B.NodeArrays):
        return nodeset
    return B.NodeArrays.from_dict(nodeset.to_npz_dict())


# ----------------------------------------------------------------------------------
# Stages
# ----------------------------------------------------------------------------------
def open_clip(path, reporter: Reporter | None = None, solve: bool = True, fov_deg: float | None = None, **options):
    """Read a clip (any supported layout); solve cameras with COLMAP when it has none.

    The solve (:func:`engine.io.solve.solve_cameras`, deterministic: same clip, same cameras) sees at
    most 60 evenly spaced frames (the others get interpolated poses), masks moving regions with the
    motion prior, and chooses its model by evidence: a fixed-centre camera (static or rotation-only,
    ``fov_deg`` across the long side, default 60) when the static matches show no parallax, else SfM
    (incremental, global when incremental cannot initialise) that must pass plausibility checks, with
    the fixed centre as the fallback. One line announces the model and why; scene.json records it
    (``camera_solve``).
    """
    from .io import load_clip

    clip = load_clip(path, **options)
    if not clip.has_cameras:
        if not solve:
            raise InputError("clip has no cameras", path, "export cameras from Blender or drop --no-solve")
        from .io.solve import solve_cameras

        if reporter is not None:
            reporter.log("no cameras in the clip: solving them with COLMAP (CPU)")
        clip = solve_cameras(clip, sample_frames=60, auto_masks=True, global_retry=True, static_fallback=True,
                             fov_deg=fov_deg, reporter=reporter)
    clip.validate_cameras()
    return clip


def prepare(clip, cfg: TrainConfig, prior_config=None, cache_dir=None, reporter: Reporter | None = None) -> PreparedClip:
    """Frames at training resolution plus priors computed on the training frames.

    Priors (tracks, depth, dynamic mask, tokens) are computed on the *training* frames
    only, in time order, because they chain optical flow through the monocular sequence;
    held-out frames (another camera) get zero depth/mask and no track samples.
    """
    from .priors import PriorConfig, compute_priors

    reporter = reporter or Reporter(quiet=True)
    frames, K, idx = load_frames_at_width(clip, cfg.width, reporter, cfg.max_frames)
    pos = {int(i): j for j, i in enumerate(idx)}
    train = np.array(sorted(pos[i] for i in clip.split.get("train", range(clip.num_frames)) if i in pos))
    val = np.array(sorted(pos[i] for i in clip.split.get("val", []) if i in pos), dtype=np.int64)
    held_out_cameras = len(val) > 0  # before --holdout adds frames of the training camera's own path
    if cfg.holdout > 1:
        train, withheld = holdout_split(train, clip.times[idx], cfg.holdout)
        val = np.array(sorted(set(val.tolist()) | set(withheld.tolist())), dtype=np.int64)
        reporter.log(f"--holdout {cfg.holdout}: {len(withheld)} of {len(withheld) + len(train)} training frames "
                     "withheld for scoring")
    if len(train) < 2:
        raise InputError(f"only {len(train)} training frame(s) after sub-sampling", clip.source,
                         "use a clip with at least 2 training frames (or raise max_frames)")
    w2c = clip.w2c[idx]
    times = clip.times[idx]
    order = train[np.argsort(times[train], kind="stable")]
    pr = compute_priors(frames[order], K[order], w2c[order], prior_config or PriorConfig(), cache_dir=cache_dir,
                        reporter=reporter)
    f, h, w = frames.shape[:3]
    depth = np.zeros((f, h, w), np.float32)
    dynamic = np.zeros((f, h, w), np.float32)
    prior_config = given_config = prior_config or PriorConfig()
    check = getattr(pr, "depth_check", None)
    if check is not None and not check["used"]:  # the depth model was set aside (engine/priors/depth_check.py)
        from .priors.depth_check import without_depth_model

        prior_config = without_depth_model(prior_config)
    d_source = depth_source(prior_config)
    extent = scene_extent(w2c[train], pr.depth)
    train_depth, moving_record = pr.depth, {}
    if d_source == "weight-free":
        from .priors.dynamic_depth import moving_object_depth

        train_depth, tracks, moving_record = moving_object_depth(pr, prior_config, K[order], w2c[order], extent,
                                                                 reporter)
    else:
        tracks = pr.tracks
    depth[order] = train_depth
    dynamic[order] = pr.dynamic
    full = _tracks_over_all_frames(tracks, order, f)
    priors = _FramePriors(tokens=pr.tokens, tracks=full, depth=depth, dynamic=dynamic, train_order=order,
                          recomputed=list(getattr(pr, "recomputed", [])),
                          depth_source=d_source,
                          sources=_prior_sources(prior_config, moving_record, check, given_config))
    return PreparedClip(frames=frames, K=K, w2c=w2c, times=times, train_idx=train, val_idx=val, priors=priors,
                        frame_numbers=frame_numbers(clip, times), fps=float(clip.fps or 24.0),
                        extent=extent, source=str(clip.source or ""),
                        clip_index=np.asarray(idx, dtype=np.int64), camera_solve=_camera_solve_record(clip),
                        held_out_cameras=held_out_cameras)


def _tracks_over_all_frames(tracks, order: np.ndarray, f: int):
    """``tracks`` of the training frames (in ``order``) laid out over all ``f`` prepared
    frames: invisible, at (0, 0) and without a depth of their own on the others."""
    if not dataclasses.is_dataclass(tracks):
        return tracks
    p = tracks.xy.shape[0]
    xy = np.zeros((p, f, 2), np.float32)
    vis = np.zeros((p, f), bool)
    xy[:, order] = tracks.xy
    vis[:, order] = tracks.visible
    depth = None
    if getattr(tracks, "depth", None) is not None:
        depth = np.full((p, f), np.nan, np.float32)
        depth[:, order] = tracks.depth
    return dataclasses.replace(tracks, xy=xy, visible=vis, depth=depth)


def _camera_solve_record(clip) -> dict | None:
    """The scene.json ``camera_solve`` record of a clip whose cameras the engine solved (else None)."""
    from .io.solve_select import summary

    meta = clip.meta if isinstance(clip.meta, dict) else {}
    return summary(meta["solve"]) if "solve" in meta else None


def holdout_split(train: np.ndarray, times: np.ndarray, every: int) -> tuple[np.ndarray, np.ndarray]:
    """Withhold every ``every``-th training frame in time order (the 2nd, the (every+1)-th, ...:
    never the first or last, so the held-out frames lie inside the trained time range).

    train : int [T] frame indices; times : float [F] every frame's time. Returns the kept and the
    withheld indices, both sorted.
    """
    order = train[np.argsort(times[train], kind="stable")]
    pos = np.arange(len(order))
    withheld = (pos % every == 1) & (pos < len(order) - 1)
    return np.sort(order[~withheld]), np.sort(order[withheld])


def still_plate_psnr(frames: np.ndarray, train: np.ndarray, idx: np.ndarray) -> float | None:
    """Mean PSNR (dB) of the clip's median training frame used as a still plate, against
    frames ``idx``: what a reconstruction that shows the background and nothing that moves
    would score (:mod:`engine.bench.still_plate`, numpy only). frames uint8 [F, H, W, 3];
    None when ``idx`` is empty."""
    from .bench.still_plate import plate_psnr, still_plate

    if len(idx) == 0 or len(train) == 0:
        return None
    plate = still_plate(frames[train])
    return float(np.mean([plate_psnr(plate, f) for f in frames[idx]]))


def frame_numbers(clip, times: np.ndarray) -> np.ndarray:
    """Scene frame number of each frame, from its time.

    Frames that share a time (a training and a held-out camera of a vrig capture) share
    a frame number, so Blender's timeline, the node F-curves and the camera path agree.
    The range is the clip's own (a clip manifest's frame_start..frame_end), else 1..T
    for T distinct times.
    """
    meta = clip.meta if isinstance(clip.meta, dict) else {}
    if "frame_start" in meta and "frame_end" in meta:
        fs, fe = float(meta["frame_start"]), float(meta["frame_end"])
    else:
        fs, fe = 1.0, float(len(np.unique(np.round(clip.times, 9))))
    return np.round(fs + np.asarray(times, np.float64) * (fe - fs)).astype(np.int64)


@dataclasses.dataclass
class _FramePriors:
    """Priors laid out over all prepared frames (zeros / invisible on held-out frames)."""

    tokens: object          # TokenGrid over the training frames in ``train_order``
    tracks: object          # Tracks with xy [P, F, 2], visible [P, F] over all frames
    depth: np.ndarray       # [F, H, W]
    dynamic: np.ndarray     # [F, H, W]
    train_order: np.ndarray  # frame indices of the training frames, in time order
    recomputed: list
    depth_source: str = "weight-free"  # see depth_source()
    sources: dict = dataclasses.field(default_factory=dict)  # scene.json "priors": model + sha256 per prior


def _prior_sources(prior_config, moving_record: dict | None = None, depth_check: dict | None = None,
                   given_config=None) -> dict:
    """Which model (name + SHA-256) or weight-free backend produces each prior (``engine.models``);
    ``moving_record`` (what gave moving objects their weight-free depth) joins ``depth``'s, and so
    does ``depth_check`` (a depth model's check against the triangulated points; a model set
    aside is named under ``set_aside``, from ``given_config``, the PriorConfig as given)."""
    from .models import describe_priors

    out = describe_priors(prior_config)
    if "depth" in out:
        if moving_record:
            out["depth"] = {**out["depth"], **moving_record}
        if depth_check is not None:
            out["depth"]["check"] = {k: v for k, v in depth_check.items() if k != "used"}
            if not depth_check["used"] and given_config is not None:
                out["depth"]["set_aside"] = describe_priors(given_config)["depth"]
    return out


def depth_source(prior_config) -> str:
    """Where the depth prior comes from: ``"file"`` (precomputed ``depth_path``), ``"model"``
    (an ONNX depth network) or ``"weight-free"`` (triangulated track anchors densified
    edge-aware, :func:`engine.priors.estimate_depth`). Only the weight-free depth takes
    moving objects' depth from their static surroundings (its anchors exclude them)."""
    if prior_config.depth_path:
        return "file"
    return "model" if prior_config.depth_backend == "onnx" else "weight-free"


def resolve_motion_init(prep: "PreparedClip", cfg: TrainConfig) -> str:
    """``cfg.motion_init`` with ``"auto"`` decided: ``"tracks"`` (node splines fitted to 2D
    tracks lifted with the depth prior, the paper's initialisation).

    With the weight-free depth the tracks are lifted at one depth per moving track
    (:func:`engine.priors.dynamic_depth.track_consistent_depth`, applied in :func:`prepare`):
    the per-frame weight-free depth of a moving object is its surroundings' and made the
    lifted motion up (which is why ``auto`` used to mean ``rest`` there), but a node that
    starts at rest on an object crossing the frame never finds it again -- the object went
    missing from the reconstruction (docs/benchmarks.md, "Moving objects").
    """
    if cfg.motion_init != "auto":
        return cfg.motion_init
    return "tracks"


def initial_nodes(prep: PreparedClip, cfg: TrainConfig) -> B.NodeArrays:
    """Run the configured node initialiser (MANI by default) on the training frames."""
    from .nodes import NodeInitConfig, initialise_nodes
    from .nodes.mani import ManiConfig

    order = prep.priors.train_order
    n_train = len(order)
    num_keys = cfg.num_keys or max(4, min(24, n_train // 4))
    trajectory = {"tracks": "spline", "rest": "static"}[resolve_motion_init(prep, cfg)]
    mani = ManiConfig(budget=cfg.num_nodes, **dataclasses.asdict(cfg.mani))  # the run's MANI settings
    init_cfg = NodeInitConfig(method=cfg.init, mani=mani, num_keys=num_keys, num_keyframes=min(12, n_train),
                              seed=cfg.seed, trajectory=trajectory, radius_k=cfg.radius_k,
                              radius_factor=cfg.radius_factor, rotations=cfg.node_rotations,
                              chain_hop_weight=cfg.node_path_chain)
    tr = prep.priors.tracks
    own_depth = getattr(tr, "depth", None)
    nodes = initialise_nodes(prep.priors.depth[order], prep.K[order], prep.w2c[order], prep.times[order],
                             prep.priors.tokens.tokens, prep.priors.tokens.patch_centers,
                             prep.priors.dynamic[order], tr.xy[:, order], tr.visible[:, order], init_cfg,
                             tracks_depth=None if own_depth is None else own_depth[:, order],
                             tracks_translation_only=getattr(tr, "translation_only", None))
    return node_arrays_from(nodes)


def bundle_scene(prep: PreparedClip, cfg: TrainConfig, **extra) -> dict:
    """``scene.json`` content for a prepared clip (cameras of every frame, time map)."""
    val = set(prep.val_idx.tolist())
    h, w = prep.frames.shape[1:3]
    cams = [{"frame": int(prep.frame_numbers[i]), "w2c": prep.w2c[i], "K": prep.K[i], "width": int(w),
             "height": int(h), "time": float(np.clip(prep.times[i], 0, 1)), "split": "val" if i in val else "train",
             "clip_index": int(prep.clip_index[i]) if prep.clip_index is not None else i}
            for i in range(len(prep.times))]
    return B.new_scene(int(prep.frame_numbers.min()), int(prep.frame_numbers.max()), prep.fps, cams,
                       config=cfg.to_dict(), extent=prep.extent, source={"clip": prep.source, "width": int(w)},
                       priors=getattr(prep.priors, "sources", {}), **_solve_extra(prep), **extra)


def _solve_extra(prep: PreparedClip) -> dict:
    """``{"camera_solve": ...}`` for scene.json when the engine solved the cameras, else ``{}``."""
    return {"camera_solve": prep.camera_solve} if getattr(prep, "camera_solve", None) else {}


def reconstruct(clip_path, out_dir, cfg: TrainConfig, reporter: Reporter | None = None, resume: bool = False,
                overwrite: bool = False, cache_dir=None, prior_config=None, clip_options=None) -> dict:
    """The whole job: clip -> cameras -> priors -> nodes -> training -> bundle."""
    from .train.trainer import Trainer

    reporter = reporter or Reporter(quiet=True)
    B.check_not_input(out_dir, clip_path)
    out_dir = B.check_output_dir(out_dir, overwrite=overwrite, resume=resume)
    clip = open_clip(clip_path, reporter, **(clip_options or {}))
    prep = prepare(clip, cfg, prior_config, cache_dir=cache_dir or Path(out_dir) / "cache", reporter=reporter)
    # the bundle's config records what ran: "auto" decided by where the depth came from
    cfg = dataclasses.replace(cfg, motion_init=resolve_motion_init(prep, cfg))
    device = pick_device(cfg.device)
    data = training_data(prep, device)
    lifespans = run_has_lifespans(cfg, data)
    scaled = scale_to_frames(cfg, len(prep.train_idx), lifespans)
    if scaled.steps != cfg.steps:
        why = ("its moving Gaussians each learn only on their own frame's steps" if lifespans
               else f"the {cfg.preset} preset's {cfg.steps} are meant for ~60 frames")
        reporter.log(f"training {scaled.steps} steps, {steps_per_frame(cfg, lifespans):g} per training frame "
                     f"over {len(prep.train_idx)} frames ({why}; --steps N trains exactly N)")
    cfg = scaled
    reporter.log(f"node motion starts from {'lifted tracks' if cfg.motion_init == 'tracks' else 'rest'} "
                 f"(depth prior: {prep.priors.depth_source})")
    if overwrite and not resume:  # the input is read and validated: only now replace the earlier run
        B.clear_run_outputs(out_dir)
    nodes_path = Path(out_dir) / B.NODES_FILE
    if resume and nodes_path.exists():
        nodes = B.read_nodes(nodes_path)
    else:
        reporter.progress("nodes", 0, 1)
        nodes = initial_nodes(prep, cfg)
        # show nodes before training finishes: the add-on can build them right away
        B.save_bundle(out_dir, bundle_scene(prep, cfg, stage="init"), nodes)
        reporter.progress("nodes", 1, 1, nodes=nodes.count)
    # the still plate (median training frame) beside every quality figure: a result that
    # lost everything that moves scores about this
    plate = {"train": still_plate_psnr(prep.frames, prep.train_idx, prep.train_idx),
             "val": still_plate_psnr(prep.frames, prep.train_idx, prep.val_idx)}
    trainer = Trainer(data, nodes, cfg, out_dir, reporter, resume=resume,
                      scene_extra={"source": {"clip": prep.source, "width": int(prep.frames.shape[2])},
                                   "priors": prep.priors.sources, **_solve_extra(prep)}, still_plate=plate)
    return trainer.run()


def pick_device(name: str = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; asking for absent CUDA is an InputError."""
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA was requested but no CUDA device is available", None, "use --device cpu or auto")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
