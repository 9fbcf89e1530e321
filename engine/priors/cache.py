"""Versioned per-clip prior cache and :func:`compute_priors` (dependency order + progress).

Layout: ``<cache_dir>/priors-v{CACHE_VERSION}/<name>-<key>.npz``. A prior's key is a
SHA-256 over (cache version, clip identity, the prior's own parameters, the keys of the
priors it depends on). Changing a parameter therefore invalidates exactly that prior and
its dependents: tokens and tracks depend on nothing; the first depth pass depends on tracks
(anchors); the motion mask depends on it; the depth handed on depends on both. Files are
written atomically, read with ``allow_pickle=False``.

Order: tracks -> first depth pass (``depth_pass1``: anchored on every triangulated track)
-> dynamic mask (rigid-flow residual needs depth) -> depth (anchors on moving pixels
dropped) -> tokens. Why two depth passes: a point on a moving object fails triangulation
only when its motion is not explainable by a static point; a short track on a child
walking toward a translating camera fits a static point a few units in front of the lens
within the 2-px test, and in inverse depth one such anchor outweighs hundreds of static
ones around it (bedroom.mp4: 83 of the last frame's 295 anchors sat under 0.3x the room's
median depth, down to 1/900 of it, and pulled the whole frame's median depth from ~850 to 92).
The motion mask is what tells those anchors apart, and it needs a depth first; the first
pass is good enough for it (the rigid-flow residual is large on moving pixels whichever
depth they carry). A depth model runs once; each pass only aligns its output to that pass's
anchors. A *precomputed* mask is known before depth: one pass, masked.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fsutil import atomic_save_npz
from ..geometry.camera import scene_extent
from . import depth as _depth
from . import depth_check as _check
from . import flow as _flow
from . import motion as _motion
from . import onnx_util as _onnx
from . import precomputed as _pre
from . import resting as _resting
from . import tokens as _tokens
from . import tracks as _tracks

CACHE_VERSION = 1
RESTING_MODES = ("auto", "off")
ALGO_VERSIONS = {"tokens": 1, "tracks": 3, "depth_check": 1, "depth_pass1": 3, "dynamic": 9, "depth": 5}


@dataclass
class PriorConfig:
    """All prior settings. ``*_path`` fields load precomputed files instead of computing."""

    tokens_backend: str = "handcrafted"
    tokens_model: str | None = None
    patch_size: int | None = None
    tracks_backend: str = "flow"
    tracks_model: str | None = None
    tracks_path: str | None = None
    num_points: int = 2000
    flow_width: int = 480
    fb_thresh: float = 1.0
    flow_backend: str = "dis"  # 'auto' (shipped RAFT when usable, else DIS) | 'dis' | 'onnx' (flow_model)
    flow_model: str | None = None
    flow_model_width: int = 240  # working width of a learned flow (shared by tracks and the motion mask)
    # a learned flow is fused with DIS per pixel (the lower photometric residual wins,
    # engine.priors.flow.FusedFlowSource); False: the learned flow alone
    flow_fuse_dis: bool = True
    flow_fine: bool = True  # DIS (tracks and motion mask): fuse with the finest-scale flow (follows small fast objects; ~4x the flow time)
    dense_moving: bool = False  # tracks: re-seed at half the grid cell in moving regions (see docs/benchmarks.md)
    depth_backend: str = "sparse"
    # weight-free depth of moving objects: 'contact' (ground contact + occlusion order, then
    # one depth per track) | 'track' (one depth per track from the prior alone); see
    # engine/priors/dynamic_depth.py
    moving_depth: str = "contact"
    # ... and, with 'contact', a moving object that turns about a static point takes that
    # point's depth and long tracks along its rings ('auto'), the depth only ('depth') or
    # neither ('off'); engine/priors/hinge.py, engine/priors/hinge_tracks.py
    hinges: str = "auto"
    # ... and a compact moving blob (convex, keeping its size: a ball, a box) gets long tracks
    # along its centroid's path ('auto') or none ('off'); engine/priors/blob_tracks.py
    blob_tracks: str = "auto"
    # weight-free depth: a moving pixel is no nearer than 1/ratio of the static surface
    # behind it (engine.priors.depth.merge_moving_depth)
    moving_depth_ratio: float = 4.0
    # ... and one the first pass puts at or behind that surface goes to this fraction of its
    # depth: in front of what it covers
    moving_depth_front: float = 0.9
    depth_model: str | None = None
    depth_path: str | None = None
    depth_width: int = 320
    depth_output: str | None = None  # ONNX depth: 'inverse' | 'depth' (larger = farther); None: sidecar, else inverse
    # ONNX depth: sidecar keys (input size, mean/std, size_multiple, ...) laid over the model's
    # sidecar file, for a model without one (engine.priors.onnx_util.model_settings)
    depth_sidecar: dict | None = None
    # ONNX depth: checked against the triangulated static points first ('auto'): a model that
    # explains them less than 10% better than a flat depth is set aside for the weight-free depth
    # (engine/priors/depth_check.py); 'off' uses the model whatever it says
    depth_check: str = "auto"
    mask_backend: str = "motion"
    mask_model: str | None = None
    mask_path: str | None = None
    mask_width: int = 320
    foreground_classes: list | None = field(default=None)
    # motion mask: objects that rest at some times and move at others are dynamic in every
    # frame when the camera does not translate ('auto') or never ('off'); engine/priors/resting.py
    resting_objects: str = "auto"


@dataclass
class Priors:
    """Results of :func:`compute_priors`. ``recomputed`` lists priors that were not cached."""

    tokens: _tokens.TokenGrid
    tracks: _tracks.Tracks
    depth: np.ndarray
    depth_confidence: np.ndarray
    dynamic: np.ndarray
    keys: dict
    recomputed: list
    # a depth model's check (engine.priors.depth_check.model_agreement) and whether its depth
    # was used ("used"); None when no model was checked
    depth_check: dict | None = None


def clip_identity(frames, K, w2c) -> str:
    """Hash of the clip content (a strided subsample of the pixels, shapes, all cameras)."""
    h = hashlib.sha256()
    h.update(str(frames.shape).encode())
    h.update(np.ascontiguousarray(frames[:, ::7, ::7]).tobytes())
    h.update(np.asarray(K, np.float64).tobytes()); h.update(np.asarray(w2c, np.float64).tobytes())
    return h.hexdigest()


def _file_id(path):
    if path is None:
        return None
    p = Path(path)
    st = p.stat() if p.exists() else None
    return [str(p.resolve()), st.st_mtime_ns if st else None, st.st_size if st else None]


def prior_key(name, clip_id, params, upstream=()) -> str:
    blob = json.dumps({"v": CACHE_VERSION, "algo": ALGO_VERSIONS[name], "name": name, "clip": clip_id,
                       "params": params, "up": list(upstream)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _load(cache, name, key):
    if cache is None:
        return None
    p = cache / f"{name}-{key}.npz"
    if not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception:  # noqa: BLE001 - a broken cache entry is recomputed
        return None


def _save(cache, name, key, **arrays):
    if cache is not None:
        atomic_save_npz(cache / f"{name}-{key}.npz", **arrays)


def _with_resting_objects(frames, dyn, K, w2c, depth, mode, log):
    """The motion prior with objects at rest that move at other times made dynamic in every
    frame (:mod:`engine.priors.resting`) when ``mode`` is 'auto' and it applies; else as given."""
    if mode not in RESTING_MODES:
        raise ValueError(f"PriorConfig.resting_objects must be one of {RESTING_MODES}, not {mode!r}")
    if mode == "off":
        return dyn
    out, st = _resting.resting_objects(frames, dyn, K, w2c, scene_extent(w2c, depth))
    if out is None:
        if st["reason"] and st["reason"] != "the camera translates":
            log(f"dynamic prior: objects at rest left as they were ({st['reason']})")
        return dyn
    log(f"dynamic prior: {st['share']:.0%} of the view holds something still at some times and not at others "
        f"(in {st['frames_needed']}+ frames): dynamic in every frame")
    return out


def compute_priors(frames, K, w2c, config: PriorConfig | None = None, cache_dir=None, reporter=None) -> Priors:
    """Compute (or load from cache) tracks, depth, dynamic mask and tokens for a clip.

    Parameters
    ----------
    frames : uint8 [F,H,W,3]; K : [F,3,3]; w2c : [F,4,4]
    config : PriorConfig
    cache_dir : folder for the cache (None = no caching)
    reporter : engine.protocol.Reporter, optional

    Returns
    -------
    Priors
    """
    cfg = config or PriorConfig()
    frames = np.asarray(frames); K = np.asarray(K, np.float64); w2c = np.asarray(w2c, np.float64)
    F, H, W, _ = frames.shape
    cache = None if cache_dir is None else Path(cache_dir) / f"priors-v{CACHE_VERSION}"
    cid = clip_identity(frames, K, w2c)
    keys, recomputed = {}, []
    log = reporter.log if reporter is not None else (lambda *_a, **_k: None)

    # one flow for the tracker and the motion mask: the mask on the tracker's fine-scale fused
    # DIS finds the moving parts better than on its own plain DIS at 320 px (large-motion
    # scenes: IoU 0.64 -> 0.72, 0.60 -> 0.70; docs/benchmarks.md, Priors)
    fbk, fmodel = _flow.resolve_flow_backend(cfg.flow_backend, cfg.flow_model)
    fid = [fbk, _file_id(fmodel), cfg.flow_model_width if fbk == "onnx" else None]
    source = None  # None: the tracker's and the mask's own plain DIS
    if fbk == "onnx":
        source = _flow.FlowSource(frames, "onnx", fmodel, cfg.flow_model_width)
        if cfg.flow_fuse_dis:  # at the DIS tracker's working size, with its fine-scale fusion
            fid.append("fused-dis")
            source = _flow.FusedFlowSource(
                _flow.FlowSource(frames, "dis", None, cfg.flow_width, 400, fuse_fine=cfg.flow_fine), source)
    elif cfg.flow_fine:
        source = _flow.FlowSource(frames, "dis", None, cfg.flow_width, 400, fuse_fine=True)

    # tracks
    tp = {"backend": cfg.tracks_backend, "model": _file_id(cfg.tracks_model), "path": _file_id(cfg.tracks_path),
          "n": cfg.num_points, "w": cfg.flow_width, "fb": cfg.fb_thresh, "flow": fid + [bool(cfg.flow_fine)], "dense": bool(cfg.dense_moving)}
    keys["tracks"] = k = prior_key("tracks", cid, tp)
    z = _load(cache, "tracks", k)
    if z is not None:
        tracks = _tracks.Tracks(z["xy"], z["visible"], z["confidence"], z["query_frame"])
    else:
        recomputed.append("tracks")
        if cfg.tracks_path:
            tracks = _pre.load_tracks(cfg.tracks_path, F)
        else:
            tracks = _tracks.track_points(frames, cfg.num_points, cfg.tracks_backend, cfg.tracks_model,
                                          cfg.flow_width, cfg.fb_thresh, reporter=reporter, source=source,
                                          dense_moving=cfg.dense_moving)
        # a tracker's tracks carry no depth of their own (hinge tracks are made after the cache)
        _save(cache, "tracks", k, **{n: a for n, a in dataclasses.asdict(tracks).items() if a is not None})
    log(f"tracks: {tracks.xy.shape[0]} points")
    if isinstance(source, _flow.FusedFlowSource) and "tracks" in recomputed:
        log(f"flow: the learned flow beat DIS at {source.picked:.0%} of the pixels")

    # a precomputed mask is known before depth: its dynamic regions give no anchors
    pre_mask = _pre.load_mask(cfg.mask_path, (F, H, W)) if cfg.mask_path else None
    model_out = []  # a depth model's raw output: run once, aligned to each pass's anchors
    check = None
    if cfg.depth_check not in ("auto", "off"):
        raise ValueError(f"PriorConfig.depth_check must be 'auto' or 'off', not {cfg.depth_check!r}")
    if cfg.depth_backend == "onnx" and not cfg.depth_path and cfg.depth_check == "auto":
        check = _depth_model_check(cfg, cid, frames, K, w2c, tracks, pre_mask, cache, keys, recomputed, model_out,
                                   reporter)
        name = Path(cfg.depth_model).name
        if check["used"]:
            log(f"depth model {name}: {_check.describe(check)}")
        else:
            log(f"depth model {name} set aside: {_check.describe(check)}; using the weight-free depth "
                "(--depth-check off uses the model anyway)", level="warning")
            cfg = _check.without_depth_model(cfg)
            model_out.clear()

    # depth, first pass (depends on tracks unless precomputed): what the motion mask needs
    dp = _depth_params(cfg)
    dp2 = dict(dp, ratio=cfg.moving_depth_ratio, front=cfg.moving_depth_front)
    up = () if cfg.depth_path else (keys["tracks"], _file_id(cfg.mask_path))
    keys["depth_pass1"] = k = prior_key("depth_pass1", cid, dp, up)

    def estimate(dynamic):
        if cfg.depth_path:
            d = _pre.load_depth(cfg.depth_path, (F, H, W))
            return d, np.ones_like(d)
        if cfg.depth_backend == "onnx" and not model_out:
            model_out.append(_depth.model_predictions(frames, cfg.depth_model, cfg.depth_width, cfg.depth_output,
                                                      reporter, cfg.depth_sidecar))
        return _depth.estimate_depth(frames, K, w2c, cfg.depth_backend, cfg.depth_model, tracks=tracks,
                                     dynamic=dynamic, max_width=cfg.depth_width, reporter=reporter,
                                     output=cfg.depth_output, predictions=model_out[0] if model_out else None,
                                     settings=cfg.depth_sidecar)

    def cached_depth(name, key, compute):
        z = _load(cache, name, key)
        if z is not None:
            return z["depth"], z["confidence"]
        recomputed.append(name)
        d, c = compute()
        _save(cache, name, key, depth=d, confidence=c)
        return d, c

    depth, dconf = cached_depth("depth_pass1", k, lambda: estimate(pre_mask))

    # dynamic mask (motion backend depends on depth)
    mp = {"backend": cfg.mask_backend, "model": _file_id(cfg.mask_model), "path": _file_id(cfg.mask_path),
          "w": cfg.mask_width, "fg": cfg.foreground_classes,
          "flow": fid + [bool(cfg.flow_fine)] if cfg.mask_backend == "motion" else None,
          "resting": cfg.resting_objects if cfg.mask_backend == "motion" else None}
    up = (keys["depth_pass1"],) if (cfg.mask_backend == "motion" and not cfg.mask_path) else ()
    keys["dynamic"] = k = prior_key("dynamic", cid, mp, up)
    z = _load(cache, "dynamic", k)
    if z is not None:
        dyn = z["dynamic"]
    else:
        recomputed.append("dynamic")
        if pre_mask is not None:
            dyn = pre_mask
        else:
            dyn = _motion.dynamic_mask(frames, K, w2c, depth, cfg.mask_backend, cfg.mask_model, cfg.mask_width,
                                       cfg.foreground_classes, reporter=reporter, source=source)
            if cfg.mask_backend == "motion":
                dyn = _with_resting_objects(frames, dyn, K, w2c, depth, cfg.resting_objects, log)
        _save(cache, "dynamic", k, dynamic=dyn)

    # depth handed on: anchored on static tracks only (module docstring); a file or a mask
    # known before the first pass already gave it
    if not cfg.depth_path and pre_mask is None:
        keys["depth"] = k = prior_key("depth", cid, dp2, (keys["depth_pass1"], keys["dynamic"]))

        def second_pass(first=depth):
            static, conf = estimate(dyn)
            if cfg.depth_backend == "sparse":  # a depth model sees moving things itself
                static = _depth.merge_moving_depth(first, static, dyn, max_ratio=cfg.moving_depth_ratio,
                                                   front=cfg.moving_depth_front)
            return static, conf

        depth, dconf = cached_depth("depth", k, second_pass)
    else:
        keys["depth"] = keys["depth_pass1"]

    # tokens
    tkp = {"backend": cfg.tokens_backend, "model": _file_id(cfg.tokens_model), "patch": cfg.patch_size}
    keys["tokens"] = k = prior_key("tokens", cid, tkp)
    z = _load(cache, "tokens", k)
    if z is not None:
        tok = _tokens.TokenGrid(z["tokens"], z["patch_centers"], tuple(z["patch_size_px"].tolist()))
    else:
        recomputed.append("tokens")
        tok = _tokens.extract_tokens(frames, cfg.tokens_backend, cfg.tokens_model, cfg.patch_size)
        _save(cache, "tokens", k, tokens=tok.tokens, patch_centers=tok.patch_centers,
              patch_size_px=np.asarray(tok.patch_size_px, np.float64))
    if reporter is not None:
        reporter.progress("priors", 4, 4)
    return Priors(tok, tracks, depth, dconf, dyn, keys, recomputed, check)


def _depth_params(cfg) -> dict:
    """The depth settings a depth prior's cache key holds (a model's sidecar settings included)."""
    dp = {"backend": cfg.depth_backend, "model": _file_id(cfg.depth_model), "path": _file_id(cfg.depth_path),
          "w": cfg.depth_width, "out": cfg.depth_output}
    if cfg.depth_backend == "onnx" and cfg.depth_model:  # the sidecar file's settings and the given ones
        side = _onnx.model_settings(cfg.depth_model, cfg.depth_sidecar) if Path(cfg.depth_model).is_file() else {}
        if side:
            dp["side"] = side
    return dp


def _depth_model_check(cfg, cid, frames, K, w2c, tracks, pre_mask, cache, keys, recomputed, model_out, reporter):
    """The depth model's agreement with the triangulated static points (cached;
    :func:`engine.priors.depth_check.model_agreement`) with ``"used"``: whether its depth is used.
    Runs the model into ``model_out`` when the check is not cached."""
    keys["depth_check"] = k = prior_key("depth_check", cid, _depth_params(cfg), (keys["tracks"], _file_id(cfg.mask_path)))
    z = _load(cache, "depth_check", k)
    if z is not None:
        record = json.loads(str(z["record"]))
    else:
        recomputed.append("depth_check")
        model_out.append(_depth.model_predictions(frames, cfg.depth_model, cfg.depth_width, cfg.depth_output,
                                                  reporter, cfg.depth_sidecar))
        anchors = _depth.anchors_from_tracks(tracks, K, w2c, pre_mask, frames.shape[1:3], _check.MIN_ANCHORS)
        record = _check.model_agreement(*model_out[0], anchors)
        _save(cache, "depth_check", k, record=np.array(json.dumps(record)))
    return {**record, "used": _check.model_is_usable(record)}
