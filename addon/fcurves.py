# SPDX-License-Identifier: GPL-3.0-or-later
"""Node splines <-> Blender F-curves.

The engine's node trajectories are cubic Hermite splines; a Bézier F-curve whose
handles sit at ``P ± (Δt/3)·dP/dt`` (FREE handles) *is* that spline, so the F-curves
Blender evaluates are exactly the engine's motion, and an artist's Graph Editor edits
read back as Hermite keys with (possibly broken) in/out tangents.

Works with Blender 4.4+ layered actions (one action + slot + channelbag per Empty) and
falls back to ``Action.fcurves`` on 4.2/4.3. All key data goes through
``foreach_set``/``foreach_get``; Python loops run over objects and channels only.
"""

from __future__ import annotations

from collections import Counter

import bpy
import numpy as np

LOCATION = "location"
ROTATION = "rotation_quaternion"
CHANNELS = ((LOCATION, 3), (ROTATION, 4))

# RNA enum values (Blender's BEZT_IPO_BEZ and HD_FREE), written with foreach_set.
_IPO_BEZIER = 2
_HANDLE_FREE = 0


class SplineMismatchError(ValueError):
    """Nodes do not share key frames (e.g. an artist keyed one Empty only)."""


def engine_keys_to_frames(key_times, tangents, frame_start: float, frame_end: float):
    """Map engine time keys to scene frames.

    Parameters
    ----------
    key_times : (K,) engine time in [0, 1].
    tangents : (..., K, C) derivatives per engine-time unit.

    Returns
    -------
    key_frames : (K,) float frames; tangents_per_frame : (..., K, C).
    """
    span = float(frame_end - frame_start)
    key_frames = frame_start + np.asarray(key_times, dtype=np.float64) * span
    scale = 0.0 if span == 0 else 1.0 / span
    return key_frames, np.asarray(tangents, dtype=np.float64) * scale


def frames_to_engine_keys(key_frames, tangents_per_frame, frame_start: float, frame_end: float):
    """Inverse of :func:`engine_keys_to_frames`."""
    span = float(frame_end - frame_start)
    key_times = (np.asarray(key_frames, dtype=np.float64) - frame_start) / (span if span else 1.0)
    return key_times, np.asarray(tangents_per_frame, dtype=np.float64) * span


def _fcurve_container(obj, create: bool):
    """The F-curve collection of ``obj``'s action (channelbag on layered actions)."""
    adt = obj.animation_data
    if adt is None:
        if not create:
            return None
        adt = obj.animation_data_create()
    action = adt.action
    if action is None:
        if not create:
            return None
        action = bpy.data.actions.new(name=f"{obj.name}Action")
        adt.action = action
    if not hasattr(action, "layers"):  # Blender < 4.4: legacy actions
        return action.fcurves
    from bpy_extras.anim_utils import action_ensure_channelbag_for_slot, action_get_channelbag_for_slot

    slot = adt.action_slot
    if slot is None:
        if not create:
            return None
        slot = action.slots.new(id_type="OBJECT", name=obj.name)
        adt.action_slot = slot
    if create:
        return action_ensure_channelbag_for_slot(action, slot).fcurves
    bag = action_get_channelbag_for_slot(action, slot)
    return None if bag is None else bag.fcurves


def _key_spacing(frames, own):
    """Handle x extents ``dl, dr [N, K]``: a third of the interval to the previous / next
    key the node owns (``own [N, K]``); an end key mirrors its one interval, a lone key gets 1."""
    k = frames.shape[0]
    idx = np.broadcast_to(np.arange(k), own.shape)
    prev = np.maximum.accumulate(np.where(own, idx, -1), axis=-1)
    nxt = np.flip(np.minimum.accumulate(np.flip(np.where(own, idx, k), -1), axis=-1), -1)
    # the previous / next owned key strictly before / after each knot
    before = np.concatenate([np.full(own.shape[:-1] + (1,), -1), prev[..., :-1]], axis=-1)
    after = np.concatenate([nxt[..., 1:], np.full(own.shape[:-1] + (1,), k)], axis=-1)
    dl = np.where(before >= 0, frames - frames[np.clip(before, 0, k - 1)], np.nan)
    dr = np.where(after < k, frames[np.clip(after, 0, k - 1)] - frames, np.nan)
    dl, dr = np.where(np.isnan(dl), dr, dl), np.where(np.isnan(dr), dl, dr)
    dl, dr = (np.where(np.isnan(d), 1.0, d / 3.0) for d in (dl, dr))
    return dl, dr


def _bezier_handles(frames, values, tan_out, tan_in, own=None):
    """Handle coordinates for one channel of many keys.

    ``frames [K]``, ``values/tan_out/tan_in [N, C, K]``, ``own [N, K]`` (default all) ->
    ``left, right [N, C, K, 2]``. A handle reaches a third of the way to the neighbouring
    key the node owns; end keys mirror the neighbouring interval (the handle that is
    never evaluated still gets a sensible length for editing).
    """
    own = np.ones((values.shape[0], frames.shape[0]), bool) if own is None else np.asarray(own, bool)
    dl, dr = (d[:, None, :] for d in _key_spacing(frames, own))  # [N, 1, K]
    left = np.stack([np.broadcast_to(frames - dl, values.shape), values - tan_in * dl], axis=-1)
    right = np.stack([np.broadcast_to(frames + dr, values.shape), values + tan_out * dr], axis=-1)
    return left, right


def write_node_fcurves(objects, key_frames, loc_keys, loc_tangents, rot_keys, rot_tangents,
                       loc_tangents_in=None, rot_tangents_in=None, key_mask=None) -> None:
    """Write location and quaternion F-curves for one Empty per node.

    Parameters
    ----------
    objects : sequence of N ``bpy.types.Object``
    key_frames : (K,) scene frames (float) shared by all nodes.
    loc_keys, loc_tangents : (N, K, 3) positions and d/dframe tangents.
    rot_keys, rot_tangents : (N, K, 4) quaternions (wxyz) and d/dframe tangents.
    loc_tangents_in, rot_tangents_in : optional incoming tangents (default: same as out).
    key_mask : (N, K) bool, optional
        Which knots are each node's own keys (``nodes.npz`` ``key_mask``; default all):
        a node gets keyframes only there. The knots it does not own are exact splits of
        its curve (``engine/geometry/hermite_knots.py``), so the Bézier between its own
        keys is the same curve; its handles reach a third of the way to its own
        neighbouring keys.

    Existing location/rotation_quaternion F-curves of these objects are replaced; the
    objects' ``rotation_mode`` becomes ``'QUATERNION'``. Handles are FREE at
    ``P ∓ (Δt/3)·tangent`` with Δt the interval to the previous / next key; the first
    key's left handle and the last key's right handle (never evaluated inside the key
    range) mirror the neighbouring interval length. Enum fields go through
    ``foreach_set`` as their integer RNA values (BEZIER = 2, FREE = 0).
    """
    key_frames = np.asarray(key_frames, dtype=np.float64)
    k = key_frames.shape[0]
    data = {LOCATION: (np.asarray(loc_keys, np.float64), np.asarray(loc_tangents, np.float64),
                       np.asarray(loc_tangents if loc_tangents_in is None else loc_tangents_in, np.float64)),
            ROTATION: (np.asarray(rot_keys, np.float64), np.asarray(rot_tangents, np.float64),
                       np.asarray(rot_tangents if rot_tangents_in is None else rot_tangents_in, np.float64))}
    n = len(objects)
    for path, (vals, tout, tin) in data.items():
        if vals.shape[:2] != (n, k):
            raise ValueError(f"{path} keys have shape {vals.shape}; expected ({n}, {k}, C)")
    own = np.ones((n, k), bool) if key_mask is None else np.asarray(key_mask, bool)
    if own.shape != (n, k) or not own.any(axis=1).all():
        raise ValueError(f"key_mask must be ({n}, {k}) with a key on every node")
    handles = {path: _bezier_handles(key_frames, v.transpose(0, 2, 1), to.transpose(0, 2, 1), ti.transpose(0, 2, 1),
                                     own)
               for path, (v, to, ti) in data.items()}  # each [N, C, K, 2]
    # float32 C-contiguous per (node, channel): foreach_set then copies without converting
    f32 = {}
    for path, (v, _, _) in data.items():
        vt = v.transpose(0, 2, 1)  # [N, C, K]
        co = np.stack([np.broadcast_to(key_frames, vt.shape), vt], axis=-1)
        f32[path] = tuple(np.ascontiguousarray(a, dtype=np.float32) for a in (co, *handles[path]))
    ipo = np.full(k, _IPO_BEZIER, dtype=np.int32)
    free = np.full(k, _HANDLE_FREE, dtype=np.int32)
    every = own.all(axis=1)
    for i, obj in enumerate(objects):  # per object and channel; keys go in bulk
        obj.rotation_mode = "QUATERNION"
        curves = _fcurve_container(obj, create=True)
        cols = slice(None) if every[i] else np.flatnonzero(own[i])
        m = k if every[i] else len(cols)
        for path, size in CHANNELS:
            co, left, right = f32[path]
            for c in range(size):
                fc = curves.find(path, index=c)
                if fc is not None:
                    curves.remove(fc)
                fc = curves.new(path, index=c)
                kp = fc.keyframe_points
                kp.add(m)
                kp.foreach_set("co", co[i, c, cols].ravel())
                kp.foreach_set("interpolation", ipo[:m])
                # FREE before update(): update() would otherwise recompute AUTO handles
                kp.foreach_set("handle_left_type", free[:m])
                kp.foreach_set("handle_right_type", free[:m])
                kp.foreach_set("handle_left", left[i, c, cols].ravel())
                kp.foreach_set("handle_right", right[i, c, cols].ravel())
                fc.update()


def _raw_curve(fc) -> np.ndarray:
    """``[3, K, 2]`` float32: co, handle_left, handle_right of every key (foreach_get)."""
    kp = fc.keyframe_points  # re-fetched after any update(); never cached across calls
    k = len(kp)
    raw = np.empty((3, k, 2), dtype=np.float32)
    kp.foreach_get("co", raw[0].ravel())
    kp.foreach_get("handle_left", raw[1].ravel())
    kp.foreach_get("handle_right", raw[2].ravel())
    return raw


def _slopes(raw):
    """Frames, values, out- and in-slopes from ``raw [..., 3, K, 2]`` (float64).

    A handle on the wrong side of its key (zero or negative x extent) reads as slope 0.
    """
    raw = np.asarray(raw, dtype=np.float64)
    co, hl, hr = raw[..., 0, :, :], raw[..., 1, :, :], raw[..., 2, :, :]
    dx_out = hr[..., 0] - co[..., 0]
    dx_in = co[..., 0] - hl[..., 0]
    t_out = np.divide(hr[..., 1] - co[..., 1], dx_out, out=np.zeros_like(dx_out), where=dx_out > 0)
    t_in = np.divide(co[..., 1] - hl[..., 1], dx_in, out=np.zeros_like(dx_in), where=dx_in > 0)
    return co[..., 0], co[..., 1], t_out, t_in


def read_node_fcurves(objects, resample: bool = False) -> dict:
    """Read node F-curves back as Hermite keys and tangents (per frame).

    Tangents come from the handle slopes, so keys written by
    :func:`write_node_fcurves` read back exactly; a handle an artist dragged off the
    1/3 spacing is read by its slope (the Hermite spline through it matches the
    F-curve at the keys, with the same slopes).

    Parameters
    ----------
    objects : sequence of N Empties written by :func:`write_node_fcurves`.
    resample : bool
        When nodes do not share key frames, read every curve at the union of all key
        frames instead of raising :class:`SplineMismatchError` (subclass of
        ``ValueError``; its message names the first odd object and channel). A curve's
        own keys keep their exact values and (possibly broken) handle slopes; at the
        other frames the Hermite spline through its own keys (the engine's reading of
        the curve) gives the value and slope, an exact split of that segment
        (:func:`engine.geometry.hermite_knots.fill_knots`, no Blender evaluation), so
        the result is a finer spline through the same motion (Blender's own curve too
        where the handles sit at 1/3 spacing, as :func:`write_node_fcurves` puts them).

    Returns
    -------
    dict with ``key_frames [K]``, ``loc_keys [N,K,3]``, ``loc_tangents_out``,
    ``loc_tangents_in``, ``rot_keys [N,K,4]``, ``rot_tangents_out``, ``rot_tangents_in``,
    and ``own [N, 7, K]`` bool: which frames are keys of each curve (location x, y, z,
    then rotation w, x, y, z).
    """
    n = len(objects)
    if n == 0:
        raise ValueError("read_node_fcurves needs at least one object")
    fcs = []  # [N * 7] F-curves in (object, path, channel) order
    for obj in objects:
        curves = _fcurve_container(obj, create=False)
        if curves is None:
            raise SplineMismatchError(f"'{obj.name}' has no animation; re-import the reconstruction")
        for path, size in CHANNELS:
            for c in range(size):
                fc = curves.find(path, index=c)
                if fc is None or len(fc.keyframe_points) == 0:
                    raise SplineMismatchError(f"'{obj.name}' lacks the {path}[{c}] F-curve")
                fcs.append(fc)
    raws = [_raw_curve(fc) for fc in fcs]
    # fast path: written curves share bit-identical key frames. The reference is the
    # most common key-frame set, so the error names the odd node even when the artist
    # keyed the first one.
    sigs = [r[0, :, 0].tobytes() for r in raws]
    ref_sig = Counter(sigs).most_common(1)[0][0]
    ref = raws[sigs.index(ref_sig)][0, :, 0].astype(np.float64)
    odd = [j for j, sg in enumerate(sigs) if sg != ref_sig
           and not (len(raws[j][0]) == len(ref) and np.allclose(raws[j][0, :, 0], ref, atol=_FRAME_TOL))]
    labels = [(path, c) for path, size in CHANNELS for c in range(size)]
    if odd and not resample:
        j = odd[0]
        path, c = labels[j % 7]
        raise SplineMismatchError(f"'{objects[j // 7].name}' has {path}[{c}] keys on other frames than the "
                                  "other nodes; key all nodes on the same frames or read with resample=True")
    if not odd:
        frames = ref
        _, vals, t_out, t_in = _slopes(np.stack(raws).reshape(n, 7, 3, len(ref), 2))  # [N, 7, K]
        own = np.ones(vals.shape, bool)
    else:
        vals, t_out, t_in, own, frames = _on_union(raws)
        vals, t_out, t_in, own = (a.reshape(n, 7, -1) for a in (vals, t_out, t_in, own))
    out = {"key_frames": frames, "own": own}
    start = 0
    for path, size in CHANNELS:
        prefix = "loc" if path == LOCATION else "rot"
        sl = slice(start, start + size)
        out[f"{prefix}_keys"] = vals[:, sl].transpose(0, 2, 1).copy()
        out[f"{prefix}_tangents_out"] = t_out[:, sl].transpose(0, 2, 1).copy()
        out[f"{prefix}_tangents_in"] = t_in[:, sl].transpose(0, 2, 1).copy()
        start += size
    return out


_FRAME_TOL = 1e-6


def _merge_frames(frames):
    """Sorted unique frames, merging values closer than ``_FRAME_TOL``."""
    f = np.sort(frames)
    keep = np.concatenate([[True], np.diff(f) > _FRAME_TOL])
    return f[keep]


def _on_union(raws):
    """Every curve of ``raws`` (``[3, K_j, 2]`` each) on the union of their key frames:
    ``vals, t_out, t_in [J, K]`` (float64), ``own [J, K]`` and the frames ``[K]``. A curve's
    own keys keep their values and handle slopes; the other frames are exact splits of
    the Hermite through its own keys (:func:`~engine.geometry.hermite_knots.fill_knots`)."""
    from ..engine.geometry.hermite_knots import fill_knots

    frames = _merge_frames(np.concatenate([r[0, :, 0] for r in raws]).astype(np.float64))
    k = len(frames)
    counts = np.array([r.shape[1] for r in raws])
    curve = np.repeat(np.arange(len(raws)), counts)
    f, v, to, ti = (np.concatenate(a) for a in zip(*(_slopes(r) for r in raws)))
    hi = np.clip(np.searchsorted(frames, f), 0, k - 1)
    lo = np.clip(hi - 1, 0, k - 1)
    col = np.where(np.abs(frames[hi] - f) <= np.abs(frames[lo] - f), hi, lo)  # nearest merged frame
    vals = np.zeros((len(raws), k))
    t_out, t_in = np.zeros_like(vals), np.zeros_like(vals)
    own = np.zeros(vals.shape, bool)
    vals[curve, col], t_out[curve, col], t_in[curve, col], own[curve, col] = v, to, ti, True
    vals, t_out, t_in = (a[..., 0] for a in fill_knots(frames, own, vals[..., None], t_out[..., None],
                                                            t_in[..., None]))
    return vals, t_out, t_in, own, frames
