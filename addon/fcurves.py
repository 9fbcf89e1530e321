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


def _bezier_handles(frames, values, tan_out, tan_in):
    """Handle coordinates for one channel of many keys.

    ``frames [K]``, ``values/tan_out/tan_in [..., K]`` -> ``left, right [..., K, 2]``.
    End keys mirror the neighbouring interval (the handle that is never evaluated still
    gets a sensible length for editing).
    """
    k = frames.shape[0]
    if k > 1:
        d = np.diff(frames)
        dl = np.concatenate([d[:1], d]) / 3.0
        dr = np.concatenate([d, d[-1:]]) / 3.0
    else:
        dl = dr = np.ones(1)
    left = np.stack([np.broadcast_to(frames - dl, values.shape), values - tan_in * dl], axis=-1)
    right = np.stack([np.broadcast_to(frames + dr, values.shape), values + tan_out * dr], axis=-1)
    return left, right


def write_node_fcurves(objects, key_frames, loc_keys, loc_tangents, rot_keys, rot_tangents,
                       loc_tangents_in=None, rot_tangents_in=None) -> None:
    """Write location and quaternion F-curves for one Empty per node.

    Parameters
    ----------
    objects : sequence of N ``bpy.types.Object``
    key_frames : (K,) scene frames (float) shared by all nodes.
    loc_keys, loc_tangents : (N, K, 3) positions and d/dframe tangents.
    rot_keys, rot_tangents : (N, K, 4) quaternions (wxyz) and d/dframe tangents.
    loc_tangents_in, rot_tangents_in : optional incoming tangents (default: same as out).

    Existing location/rotation_quaternion F-curves of these objects are replaced.
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
    handles = {path: _bezier_handles(key_frames, v.transpose(0, 2, 1), to.transpose(0, 2, 1), ti.transpose(0, 2, 1))
               for path, (v, to, ti) in data.items()}  # each [N, C, K, 2]
    ipo = np.full(k, _IPO_BEZIER, dtype=np.int32)
    free = np.full(k, _HANDLE_FREE, dtype=np.int32)
    for i, obj in enumerate(objects):  # per object and channel; keys go in bulk
        obj.rotation_mode = "QUATERNION"
        curves = _fcurve_container(obj, create=True)
        for path, size in CHANNELS:
            vals = data[path][0]
            left, right = handles[path]
            for c in range(size):
                fc = curves.find(path, index=c)
                if fc is not None:
                    curves.remove(fc)
                fc = curves.new(path, index=c)
                kp = fc.keyframe_points
                kp.add(k)
                co = np.stack([key_frames, vals[i, :, c]], axis=-1)
                kp.foreach_set("co", co.ravel())
                kp.foreach_set("interpolation", ipo)
                # FREE before update(): update() would otherwise recompute AUTO handles
                kp.foreach_set("handle_left_type", free)
                kp.foreach_set("handle_right_type", free)
                kp.foreach_set("handle_left", left[i, c].ravel())
                kp.foreach_set("handle_right", right[i, c].ravel())
                fc.update()


def _read_curve(fc):
    kp = fc.keyframe_points  # re-fetched after any update(); never cached across calls
    k = len(kp)
    co = np.empty(2 * k)
    hl = np.empty(2 * k)
    hr = np.empty(2 * k)
    kp.foreach_get("co", co)
    kp.foreach_get("handle_left", hl)
    kp.foreach_get("handle_right", hr)
    co, hl, hr = co.reshape(k, 2), hl.reshape(k, 2), hr.reshape(k, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_out = np.where(hr[:, 0] > co[:, 0], (hr[:, 1] - co[:, 1]) / (hr[:, 0] - co[:, 0]), 0.0)
        t_in = np.where(co[:, 0] > hl[:, 0], (co[:, 1] - hl[:, 1]) / (co[:, 0] - hl[:, 0]), 0.0)
    return co[:, 0], co[:, 1], t_out, t_in


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
        When nodes do not share key frames, evaluate every curve at the union of all
        key frames (tangents from ``fcurve.evaluate`` central differences) instead of
        raising :class:`SplineMismatchError`.

    Returns
    -------
    dict with ``key_frames [K]``, ``loc_keys [N,K,3]``, ``loc_tangents_out``,
    ``loc_tangents_in``, ``rot_keys [N,K,4]``, ``rot_tangents_out``, ``rot_tangents_in``.
    """
    per_obj = []
    frame_sets = []
    for obj in objects:
        curves = _fcurve_container(obj, create=False)
        if curves is None:
            raise SplineMismatchError(f"'{obj.name}' has no animation; re-import the reconstruction")
        chans = {}
        for path, size in CHANNELS:
            for c in range(size):
                fc = curves.find(path, index=c)
                if fc is None or len(fc.keyframe_points) == 0:
                    raise SplineMismatchError(f"'{obj.name}' lacks the {path}[{c}] F-curve")
                chans[(path, c)] = fc
                frame_sets.append(_read_curve(fc)[0])
        per_obj.append(chans)
    ref = frame_sets[0]
    shared = all(len(f) == len(ref) and np.allclose(f, ref, atol=1e-6) for f in frame_sets)
    if not shared and not resample:
        odd = next(i for i, f in enumerate(frame_sets) if len(f) != len(ref) or not np.allclose(f, ref, atol=1e-6))
        name = objects[odd // 7].name
        raise SplineMismatchError(f"'{name}' has keys on other frames than '{objects[0].name}'; "
                                  "key all nodes on the same frames or read with resample=True")
    frames = ref if shared else np.unique(np.concatenate(frame_sets))
    n, k = len(objects), len(frames)
    out = {"key_frames": frames}
    for path, size in CHANNELS:
        keys = np.empty((n, k, size))
        t_out = np.empty((n, k, size))
        t_in = np.empty((n, k, size))
        for i, chans in enumerate(per_obj):
            for c in range(size):
                fc = chans[(path, c)]
                if shared:
                    _, keys[i, :, c], t_out[i, :, c], t_in[i, :, c] = _read_curve(fc)
                else:
                    h = 1e-3
                    keys[i, :, c] = [fc.evaluate(f) for f in frames]
                    t_out[i, :, c] = [(fc.evaluate(f + h) - fc.evaluate(f)) / h for f in frames]
                    t_in[i, :, c] = [(fc.evaluate(f) - fc.evaluate(f - h)) / h for f in frames]
        prefix = "loc" if path == LOCATION else "rot"
        out[f"{prefix}_keys"] = keys
        out[f"{prefix}_tangents_out"] = t_out
        out[f"{prefix}_tangents_in"] = t_in
    return out
