"""Checkpoint identity and loading: a resume continues *this* run or is refused.

A checkpoint stores, next to the trainer's state, the identity of the run that wrote it:
a hash of the training data (images, cameras, times, splits) and a hash of the training
config. ``--resume`` with another clip, another ``--width`` or another config would
otherwise continue (or crash in ``load_state_dict``) with state that belongs to a
different run; :func:`check_identity` refuses that in one line. A finished run removes
its checkpoint (:func:`discard`), and its bundle says it is finished
(:func:`engine.bundle.finished_steps`).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

from ..errors import InputError

#: Keys every checkpoint holds (a file without them is not a complete training state).
REQUIRED_KEYS = ("step", "model", "optimizer", "gen", "torch_rng", "grad_accum", "grad_count", "history")
#: Config keys that change where or how often things happen, never what is computed.
VOLATILE_CONFIG_KEYS = ("device", "backend", "checkpoint_every", "log_every")

_FIX = "pass --overwrite to start that run over, or a new --out folder"


def _digest(parts) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(part)
    return h.hexdigest()[:16]


def data_hash(data) -> str:
    """Hash of what a run trains on: images, K, w2c, times and the train/val split.

    Parameters
    ----------
    data : TrainingData
        ``images [F, H, W, 3]``, ``K [F, 3, 3]``, ``w2c [F, 4, 4]``, ``times [F]``, index tensors.
    """
    tensors = (data.images, data.K, data.w2c, data.times, data.train_idx, data.val_idx)
    parts = []
    for t in tensors:
        a = t.detach().cpu().contiguous().numpy()
        parts += [str((a.dtype.str, a.shape)).encode(), a.tobytes()]
    return _digest(parts)


def config_hash(cfg) -> str:
    """Hash of the config's canonical JSON, without :data:`VOLATILE_CONFIG_KEYS`."""
    d = {k: v for k, v in cfg.to_dict().items() if k not in VOLATILE_CONFIG_KEYS}
    return _digest([json.dumps(d, sort_keys=True, allow_nan=True).encode()])


def run_identity(data, cfg) -> dict:
    """``{"data": hash, "config": hash}`` of one run (stored in its checkpoints)."""
    return {"data": data_hash(data), "config": config_hash(cfg)}


def check_identity(state: dict, identity: dict, path: str | os.PathLike) -> None:
    """Refuse a checkpoint written by another run (other clip/width or other config).

    A checkpoint without an identity (written before identities existed) is accepted.
    """
    stored = state.get("identity")
    if not isinstance(stored, dict):
        return
    if stored.get("data") != identity["data"]:
        raise InputError("checkpoint belongs to a run on different frames (another clip, --width, --max-frames "
                         "or split); --resume cannot continue it", path, _FIX)
    if stored.get("config") != identity["config"]:
        raise InputError("checkpoint belongs to a run with a different training config (--config, --preset, "
                         "--steps, --motion, ...); --resume cannot continue it",
                         path, "resume with the options of the interrupted run, or " + _FIX)


def load_state(path: str | os.PathLike) -> dict:
    """``torch.load`` a checkpoint as tensors only and check it is complete.

    Raises :class:`InputError` naming the file for anything unreadable, foreign or
    incomplete (never suggesting to allow pickled code).
    """
    path = Path(path)
    fix = "delete the checkpoints folder to start over, or pass --overwrite"
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt, truncated, foreign, or a pickle with code in it
        kind = "contains objects other than tensors" if "weights_only" in str(exc) else "is corrupt or truncated"
        raise InputError(f"cannot load checkpoint: the file {kind} ({type(exc).__name__})", path, fix) from None
    if not isinstance(state, dict):
        raise InputError("checkpoint is not a training state", path, fix)
    missing = [k for k in REQUIRED_KEYS if k not in state]
    if missing or not isinstance(state.get("model"), dict):
        raise InputError(f"checkpoint lacks {missing or ['model']}; it is incomplete or from another program",
                         path, fix)
    return state


def without_groups(opt_state: dict, names: tuple[str, ...]) -> dict:
    """An optimiser ``state_dict`` without the parameter groups called ``names`` (and their
    moments): checkpoints from before ``node_log_radii`` became a buffer (#19) had a group
    for it."""
    groups = opt_state["param_groups"]
    drop = {i for g in groups if g.get("name") in names for i in g["params"]}
    if not drop:
        return opt_state
    return {"state": {i: v for i, v in opt_state["state"].items() if i not in drop},
            "param_groups": [g for g in groups if g.get("name") not in names]}


def model_from_state(sd: dict, cfg, extent: float, device):
    """The :class:`~engine.train.model.DynamicScene` a checkpoint's model ``state_dict``
    describes: built with its shapes (``means [G, 3]``, ``node_centers [N, 3]``, ``key_times
    [K]``, ...), then loaded with its exact values. Fills in (in ``sd``) the tensors that
    checkpoints from before the static-motion score, the static / dynamic split and the
    Gaussian lifespans lack.
    """
    from .model import DynamicScene

    dev = device
    rot_keys = sd.get("rot_keys")
    if "node_fg" not in sd:  # a checkpoint from before the static-motion score
        sd["node_fg"] = torch.zeros_like(sd["node_p_dyn"])
    # a checkpoint from before the static / dynamic split: one class
    sd.setdefault("node_dyn", torch.ones(sd["node_p_dyn"].shape, dtype=torch.bool))
    sd.setdefault("gauss_dyn", torch.ones(sd["means"].shape[0], dtype=torch.bool))
    # a checkpoint from before Gaussian lifespans: every Gaussian always visible
    sd.setdefault("gauss_t_center", torch.zeros(sd["means"].shape[0]))
    sd.setdefault("gauss_lifespan", torch.zeros(sd["means"].shape[0]))
    sd.setdefault("lifespan_log_scale", torch.zeros(sd["means"].shape[0]))  # before learned lifespans
    # before view-bound Gaussians (shot_detail.py): none
    sd.setdefault("gauss_view_origin", torch.zeros(sd["means"].shape[0], 3))
    sd.setdefault("gauss_view_angle", torch.zeros(sd["means"].shape[0]))
    g = sd["means"].shape[0]
    # Rebuild the model with the checkpoint's shapes, then load exact values.
    nodes_keys = sd.get("pos_keys")
    model = DynamicScene(sd["means"].to(dev), torch.zeros(g, 3, device=dev), torch.ones(g, 3, device=dev),
                         torch.full((g,), 0.5, device=dev), sd["node_centers"].to(dev),
                         torch.exp(sd["node_log_radii"]).to(dev), sd["key_times"].to(dev),
                         (nodes_keys if nodes_keys is not None else
                          sd["node_centers"][:, None].expand(-1, len(sd["key_times"]), 3)).to(dev),
                         None if rot_keys is None else rot_keys.to(dev),
                         sh_degree=cfg.sh_degree, motion=cfg.motion, bind_k=cfg.bind_k,
                         graph_idx=sd["graph_idx"].to(dev), node_p_dyn=sd["node_p_dyn"].to(dev),
                         extent=extent)
    model.load_state_dict({k: v.to(dev) for k, v in sd.items()})
    return model


def discard(path: str | os.PathLike) -> None:
    """Remove a finished run's checkpoint (and its folder when that is left empty)."""
    path = Path(path)
    try:
        path.unlink()
    except FileNotFoundError:
        pass
    try:
        path.parent.rmdir()
    except OSError:
        pass  # not empty (user files) or absent
