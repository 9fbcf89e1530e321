"""Training configuration: one typed dataclass, three presets, written into the bundle.

Every hyper-parameter of a reconstruction lives in :class:`TrainConfig`. Presets set
sizes and step counts for the hardware they target:

``preview``   minutes on a 2-core CPU for a ~60-frame clip at ~240 px wide.
``standard``  a longer CPU run / a short GPU run.
``high``      GPU-sized (full resolution, more Gaussians and steps).

A config round-trips through JSON (``to_dict``/``from_dict``); unknown keys or values of
the wrong type are refused with a message naming the key.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Any

from ..errors import InputError

log = logging.getLogger(__name__)

#: Keys older versions wrote (scene.json ``config``) that nothing read; ignored with a warning.
REMOVED_KEYS = ("batch_frames", "eval_every")

INIT_METHODS = ("mani", "fps", "voxel", "tracklet")
MOTION_MODELS = ("spline", "mlp", "per_frame")
MOTION_INITS = ("auto", "tracks", "rest")
#: TrainConfig.lifespan (engine/train/lifespan.py)
LIFESPAN_MODES = ("auto", "on", "off")
#: TrainConfig.frame_order (engine/train/frame_order.py)
FRAME_ORDERS = ("auto", "epochs", "uniform")


@dataclass
class LossWeights:
    """Weights of the composite loss (paper Eq. 'loss'); 0 switches a term off."""

    rgb: float = 1.0          # L1 + D-SSIM photometric
    ssim: float = 0.2         # D-SSIM share inside the photometric term (3DGS uses 0.2)
    mask: float = 0.1         # rendered alpha vs the foreground/dynamic prior on dynamic pixels
    depth: float = 0.05       # scale/shift-invariant depth vs the depth prior
    track: float = 0.05       # projected deformed track points vs 2D tracks (Huber, in % of the image width)
    rgb_dynamic: float = 2.0  # extra L1 weight on pixels the dynamic prior calls moving (1 + this there):
                              # moving objects cover a few % of the image and would get that share of the loss
    rgb_coarse: float = 1.0   # L1 of the 4x and 8x box-downsampled render vs frame (losses.coarse_l1), weighted
                              # like rgb: its cost grows with how far a moving object is rendered off its
                              # place, so nodes that start off it are pulled back (docs/benchmarks.md)
    on_mask: float = 0.3      # dynamic Gaussians projecting off each frame's moving region (losses.on_mask_loss):
                              # pulls back the ones left behind by node trajectories that rest where their
                              # tracks ended (docs/benchmarks.md "Gaussians left behind")
    arap: float = 1.0         # as-rigid-as-possible on the node graph
    velocity: float = 1e-3    # mild spline velocity regulariser
    acceleration: float = 1e-2  # mild spline acceleration regulariser
    static: float = 1536.0    # motion of nodes the dynamic prior calls static, weighted by (1 - score)^static_power;
                              # a mean over nodes since #19 (was a sum at 3.0: the same strength at 512 nodes)
    static_power: float = 1.0  # >1 spares ambiguous nodes (score ~0.5: thin moving parts) more than static ones
    static_init: float = 0.0  # 1: measure that motion relative to each node's initial (track-fitted) trajectory


#: Where a merged MANI node sits (engine/nodes/mani.py module doc).
MANI_MERGES = ("medoid", "representative", "mean")


@dataclass
class ManiSettings:
    """MANI's settings (:class:`engine.nodes.mani.ManiConfig`; its budget is ``num_nodes``).
    Voxel sizes are fractions of the scene's bounding-box diagonal."""

    v_init: float = 0.01      # initial voxel size
    dv: float = 0.01          # voxel growth per iteration
    eta: float = 0.5          # weight of the foreground term in the candidates' similarity
    alpha: float = 6.0        # p_dyn weight of the voxel's mean foreground prior
    beta: float = 4.0         # p_dyn weight of the voxel's mean matched similarity
    r_min: float = 0.2        # merge fraction of a fully dynamic voxel
    r_max: float = 0.4        # merge fraction of a fully static voxel
    merge: str = "medoid"     # merged node position: medoid | representative | mean


@dataclass
class TrainConfig:
    """All hyper-parameters of one reconstruction run."""

    preset: str = "preview"
    seed: int = 0
    device: str = "auto"                 # auto | cpu | cuda
    backend: str = "auto"                # rasteriser backend: auto | reference | cpu | gsplat

    # data
    width: int = 240                     # training resolution (long side is scaled to this width)
    max_frames: int = 0                  # 0 = all frames of the training split
    holdout: int = 0                     # N > 1: withhold every N-th training frame (time order) and score it;
                                         # the held-out protocol for clips without a second camera

    # representation
    init: str = "mani"                   # node initialiser: mani | fps | voxel | tracklet
    motion: str = "spline"               # node motion model: spline | mlp | per_frame
    motion_init: str = "auto"            # starting node trajectories: tracks (2D tracks lifted with the depth
                                         # prior) | rest (every node still; the track loss teaches the motion) |
                                         # auto (tracks when the depth prior comes from a model or a file, rest
                                         # with the weight-free depth, which cannot see moving objects)
    split: bool = True                   # static / dynamic split (engine/train/split.py): static nodes rest and
                                         # carry undeformed static Gaussians; dynamic Gaussians bind to dynamic
                                         # nodes only and are seeded from the moving pixels of every frame
    dynamic_threshold: float = 0.5       # dynamic prior at or above this = moving (nodes, Gaussians, tracks)
    dynamic_gaussians: int = 6000        # Gaussians seeded on moving pixels, spread over all training frames
    lifespan: str = "auto"               # moving Gaussians visible around their seed frame only (engine/train/
                                         # lifespan.py): on | off | auto (on unless the camera translates and the
                                         # clip has held-out cameras of its own)
    lifespan_frames: float = 1.0         # ... the lifespan's sigma in training-frame intervals (docs/benchmarks.md)
    lifespan_seed_factor: float = 4.0    # ... and dynamic_gaussians times this many moving Gaussians seeded (each
                                         # frame shows only its own few)
    lifespan_seed_frames: int = 60       # ... for a clip of up to this many training frames; a longer one seeds
                                         # proportionally more (the same per frame; 0 = never more),
    lifespan_seed_max: int = 120_000     # ... up to this many in all (~300 frames' worth: the step time grows
                                         # with every Gaussian, shown or not; a longer clip gets fewer per frame)
    lifespan_seed_opacity: float = 0.8   # ... each seeded at this opacity (0.3 the others: docs/benchmarks.md,
                                         # *Seeds that cover their frame*)
    lifespan_anchor: bool = False        # ... each one held at its seed frame while the node keys train (engine/train/
                                         # seed_anchor.py): sharp training frames; the keys learn motion between frames
    lifespan_min: float = 0.5            # ... each one's lifespan is learned (lr_lifespan), within these factors of
    lifespan_max: float = 4.0            # lifespan_frames: short where its nodes lose the object, long where they
                                         # follow it (engine/train/lifespan.py)
    shot_detail: str = "on"              # per-frame Gaussians of the moving things after training, fading with the
                                         # parallax from the camera that saw them (engine/train/shot_detail.py): on | off
    detail_steps_per_frame: float = 15.0 # ... trained this many steps per training frame (the seeds alone)
    detail_seeds: int = 3000             # ... at most this many a frame, one per moving pixel before any twice,
    detail_seed_max: int = 200_000       # ... and this many in all (a long clip gets fewer a frame: each costs memory)
    detail_opacity: float = 0.8          # ... each seeded at this opacity
    detail_lifespan_frames: float = 0.5  # ... shown around its own frame (sigma in training-frame intervals)
    detail_depth_error: float = 0.05     # ... its depth's relative uncertainty, and the parallax shift in pixels
    detail_fade_px: float = 0.5          # (focal * depth_error * sin(angle)) at which it fades to exp(-0.5)
    num_nodes: int = 512                 # node budget for initialisation
    num_keys: int = 0                    # spline keyframes; 0 = one per ~4 frames, at least 4
    node_rotations: str = "tracks"       # initial node rotations: "tracks" (rigid rotation of each node's lifted
                                         # tracks; a rolling or swinging part turns its texture) or "identity"
    node_path_chain: float = 0.5         # past its own tracks a node's initial path follows the tracks around it
                                         # (engine/nodes/path_chain.py), each new set of them weighted by this
                                         # factor once more; 0: held where its own tracks end
    arap_graph: str = "paths"            # ARAP neighbours: nearest "paths" (the largest distance between two nodes'
                                         # key positions, engine.nodes.graph.path_graph: parts that move apart, either
                                         # side of an elbow, are not tied) or nearest canonical "centres"
    radius_k: int = 4                    # node RBF radius from the distance to this many nearest nodes
    radius_factor: float = 1.0           # ... times this factor
    bind_k: int = 4                      # nodes per Gaussian (K in the paper)
    canonical_time: float = 0.5          # canonical node centres: initial positions at this point of the
                                         # training frames (0..1); -1 = each node's own source frame
    rebind_every: int = 200              # refresh binding every N steps (0 = never)
    sh_degree: int = 1
    gaussians_per_frame: int = 3000      # back-projected at init from each keyframe (static pixels, with the split)
    init_keyframes: int = 8              # frames sampled for Gaussian initialisation
    max_gaussians: int = 30000           # budget cap for densification

    # optimisation
    steps: int = 600
    min_steps_per_frame: float = 10.0    # a long clip trains at least this many steps per training frame (steps
                                         # and the step schedule scaled up, scale_to_frames); 0 = steps as given,
                                         # which an explicit steps value implies (preset_config)
    lifespan_steps_per_frame: float = 30.0  # ... and a run with lifespans at least this many (each frame's moving
                                         # Gaussians learn only on its own steps; scale_to_frames)
    frame_order: str = "auto"            # the frame each step draws (engine/train/frame_order.py): epochs | uniform |
                                         # auto (epochs when the moving Gaussians have lifespans, else uniform)
    warmup_static_steps: int = 50        # first steps train appearance with motion frozen
    track_frames: int = 5                # frames whose 2D tracks each step's track term scores: the rendered one and
                                         # track_frames - 1 training frames drawn at random, each weighted by
                                         # loss.track (the photometric step moves only the keys near its own frame;
                                         # tracks at other times hold the rest of each path: docs/benchmarks.md)
    lr_means: float = 1.6e-4             # relative to scene extent
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacity: float = 5e-2
    lr_sh: float = 2.5e-3
    lr_lifespan: float = 2e-2            # log of each moving Gaussian's lifespan factor; 0 = lifespans as seeded
    # relative to scene extent; spline keys decay log-linearly from lr_node_keys to
    # lr_node_keys_final, like the means. 1e-3 -> 1e-5 was set when every node trained and the
    # static ones drifted; with the split static nodes are frozen and only moving ones use it:
    # 3e-3 -> 3e-4 lets them follow fast objects (large-motion scene masked PSNR train/held-out
    # +0.6/+0.4 dB, node trajectory ratio 0.84 -> 0.74; docs/benchmarks.md "Moving objects")
    lr_node_keys: float = 3e-3
    lr_node_keys_final: float = 3e-4
    lr_node_rot: float = 1e-3
    lr_node_rot_final: float = 1e-5
    lr_mlp: float = 1e-3
    lr_mlp_final: float = 1e-5           # the MLP decays log-linearly too, like the spline keys

    # densification (3DGS-style, scaled to the run length)
    densify_from: int = 100
    densify_until: int = 450
    densify_every: int = 50
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    opacity_prune: float = 0.005
    opacity_reset_every: int = 0         # 0 = never (short runs do better without)
    # node densification/pruning at the Gaussian densification steps
    node_densify: bool = True
    node_spawn_factor: float = 2.5       # a Gaussian farther than this x its node's radius asks for a node
    node_add_max: int = 32               # new nodes per densification step
    max_nodes_factor: float = 1.5        # node cap = factor x num_nodes
    node_prune_weight: float = 1e-3      # nodes whose summed binding weight is below this are removed

    # bookkeeping
    checkpoint_every: int = 200
    log_every: int = 10

    loss: LossWeights = field(default_factory=LossWeights)
    mani: ManiSettings = field(default_factory=ManiSettings)

    # ------------------------------------------------------------------------------
    def validate(self, source: str | None = None) -> "TrainConfig":
        def bad(key, why):
            raise InputError(f"config value {key!r} {why}", source, "see `python -m engine train --help` for valid values")

        if self.init not in INIT_METHODS:
            bad("init", f"must be one of {INIT_METHODS}")
        if self.motion not in MOTION_MODELS:
            bad("motion", f"must be one of {MOTION_MODELS}")
        if self.motion_init not in MOTION_INITS:
            bad("motion_init", f"must be one of {MOTION_INITS}")
        if self.node_rotations not in ("tracks", "identity"):
            bad("node_rotations", "must be tracks or identity")
        if self.lifespan not in LIFESPAN_MODES:
            bad("lifespan", f"must be one of {LIFESPAN_MODES}")
        if self.frame_order not in FRAME_ORDERS:
            bad("frame_order", f"must be one of {FRAME_ORDERS}")
        if self.device not in ("auto", "cpu", "cuda"):
            bad("device", "must be auto, cpu or cuda")
        if self.backend not in ("auto", "reference", "cpu", "gsplat"):
            bad("backend", "must be auto, reference, cpu or gsplat")
        if not 0 <= self.sh_degree <= 3:
            bad("sh_degree", "must be 0..3")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                bad(f.name, f"must be a finite number, got {value!r}")
        for key in ("width", "steps", "num_nodes", "bind_k", "gaussians_per_frame", "init_keyframes",
                    "max_gaussians", "log_every", "densify_every", "track_frames"):
            if getattr(self, key) < 1:
                bad(key, "must be >= 1")
        for key in ("max_frames", "num_keys", "rebind_every", "checkpoint_every", "opacity_reset_every",
                    "warmup_static_steps", "densify_from", "densify_until", "node_add_max"):
            if getattr(self, key) < 0:
                bad(key, "must be >= 0")
        for key, limit in LIMITS.items():
            if getattr(self, key) > limit:
                bad(key, f"is {getattr(self, key)}, above the largest sensible value {limit}")
        for key in [f.name for f in dataclasses.fields(self) if f.name.startswith("lr_")] + [
                "densify_grad_threshold", "percent_dense", "opacity_prune", "node_spawn_factor",
                "max_nodes_factor", "node_prune_weight", "lifespan_frames", "lifespan_seed_factor",
                "lifespan_seed_frames", "lifespan_seed_max", "min_steps_per_frame", "lifespan_steps_per_frame"]:
            if getattr(self, key) < 0:
                bad(key, "must be >= 0")
        if self.shot_detail not in ("on", "off"):
            bad("shot_detail", "must be 'on' or 'off'")
        for key in ("detail_steps_per_frame", "detail_seeds", "detail_seed_max", "detail_lifespan_frames",
                    "detail_depth_error", "detail_fade_px"):
            if not getattr(self, key) > 0:
                bad(key, "must be > 0")
        if not 0 < self.detail_opacity < 1:  # stored as a logit
            bad("detail_opacity", "must be between 0 and 1 (exclusive)")
        if not 0 < self.lifespan_seed_opacity < 1:  # stored as a logit
            bad("lifespan_seed_opacity", "must be between 0 and 1 (exclusive)")
        if not 0 < self.lifespan_min <= 1 <= self.lifespan_max:
            bad("lifespan_min", "and lifespan_max must satisfy 0 < lifespan_min <= 1 <= lifespan_max")
        if not 0 <= self.node_path_chain <= 1:
            bad("node_path_chain", "must be in [0, 1] (0: off)")
        if not (0 <= self.canonical_time <= 1 or self.canonical_time == -1):
            bad("canonical_time", "must be in [0, 1] (fraction of the training frames) or -1 (source frames)")
        if self.arap_graph not in ("centres", "paths"):
            bad("arap_graph", "must be 'centres' or 'paths'")
        if self.bind_k > self.num_nodes:
            bad("bind_k", "cannot exceed num_nodes")
        self._validate_nodes(bad)
        for f in dataclasses.fields(self.loss):
            value = getattr(self.loss, f.name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                bad(f"loss.{f.name}", f"must be a finite number, got {value!r}")
            if value < 0:
                bad(f"loss.{f.name}", "must be >= 0")
        return self

    def _validate_nodes(self, bad) -> None:
        """Node-initialisation settings: radius and MANI (``bad(key, why)`` raises)."""
        if self.radius_k < 1:
            bad("radius_k", "must be >= 1")
        if not self.radius_factor > 0:
            bad("radius_factor", "must be > 0")
        m = self.mani
        for f in dataclasses.fields(m):
            value = getattr(m, f.name)
            if f.name != "merge" and (not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0):
                bad(f"mani.{f.name}", f"must be a finite number >= 0, got {value!r}")
        if m.merge not in MANI_MERGES:
            bad("mani.merge", f"must be one of {MANI_MERGES}")
        if not (m.v_init > 0 and m.dv > 0):
            bad("mani.v_init" if m.v_init <= 0 else "mani.dv", "must be > 0 (voxels must grow from a positive size)")
        if not m.r_min <= m.r_max <= 1:
            bad("mani.r_min", "needs 0 <= r_min <= r_max <= 1 (merge fractions)")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str | None = None) -> "TrainConfig":
        if not isinstance(data, dict):
            raise InputError("training config must be a JSON object", source, "see docs for the config format")
        known = {f.name: f for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key in REMOVED_KEYS:  # an older bundle's or user's config: nothing ever read it
                log.warning(f"config key {key!r} is no longer used and was ignored ({source or 'config'})")
                continue
            if key not in known:
                raise InputError(f"unknown config key {key!r}", source, f"valid keys: {sorted(known)}")
            if key == "loss":
                kwargs["loss"] = _loss_from_dict(value, source)
                continue
            if key == "mani":
                kwargs["mani"] = _mani_from_dict(value, source)
                continue
            default = getattr(cls(), key)
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise InputError(f"config key {key!r} must be true or false, got {value!r}", source,
                                     "fix the value's type")
                kwargs[key] = value
            elif not isinstance(default, (int, float, str)):
                kwargs[key] = value
            elif isinstance(default, float) and isinstance(value, (int, float)) and not isinstance(value, bool):
                kwargs[key] = float(value)
            elif type(value) is not type(default):
                raise InputError(f"config key {key!r} must be {type(default).__name__}, got {value!r}", source,
                                 "fix the value's type")
            else:
                kwargs[key] = value
        return cls(**kwargs).validate(source)


def _mani_from_dict(data: Any, source: str | None) -> ManiSettings:
    if isinstance(data, ManiSettings):
        return data
    if not isinstance(data, dict):
        raise InputError("config key 'mani' must be an object", source, "e.g. {\"r_max\": 0.5}")
    fields = {f.name: f for f in dataclasses.fields(ManiSettings)}
    for key, value in data.items():
        if key not in fields:
            raise InputError(f"unknown MANI setting {key!r}", source, f"valid: {sorted(fields)}")
        want_str = key == "merge"
        ok = isinstance(value, str) if want_str else (isinstance(value, (int, float)) and not isinstance(value, bool))
        if not ok:
            raise InputError(f"MANI setting {key!r} must be {'a string' if want_str else 'a number'}, got {value!r}",
                             source, "fix the value's type")
    return ManiSettings(**{k: v if k == "merge" else float(v) for k, v in data.items()})


def _loss_from_dict(data: Any, source: str | None) -> LossWeights:
    if not isinstance(data, dict):
        raise InputError("config key 'loss' must be an object", source, "e.g. {\"depth\": 0.1}")
    known = {f.name for f in dataclasses.fields(LossWeights)}
    for key, value in data.items():
        if key not in known:
            raise InputError(f"unknown loss weight {key!r}", source, f"valid: {sorted(known)}")
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise InputError(f"loss weight {key!r} must be a finite number, got {value!r}", source, "fix the value")
    return LossWeights(**{k: float(v) for k, v in data.items()})


#: Upper bounds: beyond them a run cannot finish on any machine this engine targets (a
#: typo such as ``steps: 10**12`` or ``width: 100000`` is refused instead of accepted).
LIMITS: dict[str, int] = {"width": 8192, "steps": 10_000_000, "num_nodes": 200_000, "num_keys": 10_000,
                          "bind_k": 64, "gaussians_per_frame": 2_000_000, "init_keyframes": 1000,
                          "max_gaussians": 20_000_000, "max_frames": 100_000,
                          "node_add_max": 100_000, "lifespan_seed_factor": 100, "track_frames": 1000}

PRESETS: dict[str, dict[str, Any]] = {
    "preview": {},
    "standard": dict(width=480, num_nodes=1024, steps=3000, gaussians_per_frame=6000, dynamic_gaussians=24000,
                     init_keyframes=12,
                     max_gaussians=150_000, densify_from=300, densify_until=2200, densify_every=100,
                     checkpoint_every=500, rebind_every=500, sh_degree=2, warmup_static_steps=200),
    "high": dict(width=960, num_nodes=2048, steps=20000, gaussians_per_frame=22500, dynamic_gaussians=120000,
                 init_keyframes=16,
                 max_gaussians=1_000_000, densify_from=500, densify_until=15000, densify_every=100,
                 opacity_reset_every=3000, checkpoint_every=1000, rebind_every=1000, sh_degree=3,
                 warmup_static_steps=500, device="auto"),
}


def preset_config(name: str, source: str | None = None, **overrides: Any) -> TrainConfig:
    """The config of preset ``name`` with ``overrides`` applied (validated; errors name ``source``,
    e.g. the ``--config`` file the overrides came from)."""
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}", None, f"choose one of {sorted(PRESETS)}")
    values = dict(PRESETS[name])
    given = {k: v for k, v in overrides.items() if v is not None}
    if "steps" in given:  # a step count asked for is kept as it is
        for key in ("min_steps_per_frame", "lifespan_steps_per_frame"):
            given.setdefault(key, 0.0)
    values.update(given)
    values["preset"] = name
    loss = values.pop("loss", None)
    cfg = TrainConfig.from_dict(values, source)
    if loss is not None:
        cfg.loss = loss if isinstance(loss, LossWeights) else _loss_from_dict(loss, source)
    return cfg.validate(source)


#: step-counted schedule settings that :func:`scale_to_frames` scales with ``steps``
STEP_SCHEDULE = ("warmup_static_steps", "densify_from", "densify_until", "densify_every", "rebind_every",
                 "checkpoint_every", "opacity_reset_every")


def steps_per_frame(cfg: TrainConfig, lifespans: bool) -> float:
    """The fewest steps per training frame ``cfg`` asks for: ``min_steps_per_frame``, and with
    ``lifespans`` (the run's moving Gaussians have them: :func:`engine.train.lifespan.resolve_lifespan`
    > 0) at least ``lifespan_steps_per_frame``; 0 when ``min_steps_per_frame`` is 0 (steps as given).

    Why more with lifespans: a frame's moving Gaussians draw only around their own time, so they
    learn only on the steps that draw their frame (~11 at the preview's 600 steps over 52 frames),
    whereas the static scene learns on every step. At 10 steps a frame the hands and the moving cups
    of cups.mp4 render as ghosts on the training frames themselves; 20 / 30 steps a frame take its
    training frames from +8.5 to +10.2 / +11.2 dB over the still plate, bedroom.mp4's from +8.9 to
    +10.9 at 30 (docs/benchmarks.md, *Steps per frame*). Larger learning rates for those Gaussians
    do not replace the steps (the same section).
    """
    if cfg.min_steps_per_frame <= 0:
        return 0.0
    return max(cfg.min_steps_per_frame, cfg.lifespan_steps_per_frame if lifespans else 0.0)


def scale_to_frames(cfg: TrainConfig, train_frames: int, lifespans: bool = False) -> TrainConfig:
    """``cfg`` with at least :func:`steps_per_frame` steps per training frame.

    Why: each frame's moving Gaussians (lifespans) and the node keys near its time learn only
    on the steps that draw that frame. The presets' step counts are set for a clip of ~60
    frames (preview: 600 steps, ~11 per frame); over a whole 300-frame clip the same 600 left
    each frame two visits, and cups.mp4 trained +4.55 dB over the still plate instead of +8
    (its moving cups misplaced and smeared; 3000 steps with the schedule scaled: +7.31,
    docs/benchmarks.md). The
    steps rise to ``ceil(steps_per_frame(cfg, lifespans) * train_frames)`` and
    :data:`STEP_SCHEDULE` (warm-up, densification window and interval, rebinding, checkpoints)
    by the same factor, so the run keeps the preset's shape. A config that already gives enough
    steps, or sets ``min_steps_per_frame`` 0 (any explicit ``steps``: :func:`preset_config`), is
    returned as it is.
    """
    per_frame = steps_per_frame(cfg, lifespans)
    want = int(math.ceil(per_frame * max(int(train_frames), 0)))
    if per_frame <= 0 or want <= cfg.steps:
        return cfg
    factor = want / cfg.steps
    scaled = {key: int(round(getattr(cfg, key) * factor)) for key in STEP_SCHEDULE if getattr(cfg, key) > 0}
    return dataclasses.replace(cfg, steps=want, **scaled).validate()
