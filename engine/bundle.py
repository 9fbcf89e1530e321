"""Result bundles: the folder the engine writes and the add-on reads.

A bundle holds ``scene.json`` (cameras, frame <-> time map, units, config),
``gaussians.ply`` (standard 3DGS PLY, canonical space) and ``nodes.npz`` (node centres,
radii, Hermite spline keys, binding). See ``docs/architecture.md``.

This module needs only numpy and the standard library, so Blender's Python can import
it. Every reader validates what it loads and raises :class:`~engine.errors.InputError`
naming the file; ``np.load`` never unpickles.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .fsutil import atomic_path, atomic_save_npz, atomic_write_json
from .outdir import (RUN_OUTPUTS, check_not_input, check_output_dir, clear_run_outputs,  # noqa: F401
                     finished_steps, refuse_finished_resume)

BUNDLE_FORMAT = "motion-splats-bundle"
BUNDLE_VERSION = 1
SCENE_FILE = "scene.json"
GAUSSIANS_FILE = "gaussians.ply"
NODES_FILE = "nodes.npz"


# ----------------------------------------------------------------------------------
# Gaussians <-> standard 3DGS PLY
# ----------------------------------------------------------------------------------
@dataclasses.dataclass
class GaussianArrays:
    """Canonical Gaussians as plain arrays (float32).

    Attributes
    ----------
    means : (G, 3)
    quats : (G, 4) rotations, wxyz (need not be normalised; PLY stores them as is).
    log_scales : (G, 3) natural log of the per-axis standard deviations.
    opacity_logits : (G,) inverse-sigmoid of opacity.
    sh : (G, M, 3) spherical-harmonic coefficients, ``M = (degree + 1) ** 2``;
        ``sh[:, 0]`` is the DC term.
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self):
        self.means = np.asarray(self.means, np.float32).reshape(-1, 3)
        g = self.means.shape[0]
        self.quats = np.asarray(self.quats, np.float32).reshape(g, 4)
        self.log_scales = np.asarray(self.log_scales, np.float32).reshape(g, 3)
        self.opacity_logits = np.asarray(self.opacity_logits, np.float32).reshape(g)
        self.sh = np.asarray(self.sh, np.float32).reshape(g, -1, 3)
        m = self.sh.shape[1]
        if int(round(math.sqrt(m))) ** 2 != m or m > 16:
            raise ValueError(f"sh has {m} coefficients per channel; expected 1, 4, 9 or 16")

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.sh.shape[1]))) - 1

    @property
    def opacities(self) -> np.ndarray:
        """Opacity in [0, 1], shape (G,)."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits))

    @property
    def colors(self) -> np.ndarray:
        """View-independent RGB from the DC term (what viewers show), shape (G, 3)."""
        return np.clip(self.sh[:, 0] * SH_C0 + 0.5, 0.0, 1.0)


#: Zeroth-order real spherical harmonic, 1 / (2 sqrt(pi)); colour = SH_C0 * dc + 0.5.
SH_C0 = 0.28209479177387814


def _ply_fields(sh_coeffs: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (sh_coeffs - 1))]
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: str | os.PathLike, gaussians: GaussianArrays) -> None:
    """Write ``gaussians`` as a binary little-endian 3DGS PLY, atomically.

    The layout is the one the original 3DGS code and common splat viewers read:
    ``f_rest_*`` are stored channel-major (all R coefficients, then G, then B).
    """
    g = gaussians
    fields = _ply_fields(g.sh.shape[1])
    data = np.empty((g.count, len(fields)), np.float32)
    data[:, 0:3] = g.means
    data[:, 3:6] = 0.0
    data[:, 6:9] = g.sh[:, 0]
    n_rest = 3 * (g.sh.shape[1] - 1)
    # (G, M-1, 3) -> (G, 3, M-1) -> flat: channel-major, as in 3DGS.
    data[:, 9:9 + n_rest] = g.sh[:, 1:].transpose(0, 2, 1).reshape(g.count, -1)
    o = 9 + n_rest
    data[:, o] = g.opacity_logits
    data[:, o + 1:o + 4] = g.log_scales
    data[:, o + 4:o + 8] = g.quats
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {g.count}"]
    header += [f"property float {name}" for name in fields]
    header += ["end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(data.astype("<f4", copy=False).tobytes())


def read_ply(path: str | os.PathLike) -> GaussianArrays:
    """Read a 3DGS PLY written by :func:`write_ply` or by other 3DGS tools.

    Accepts any property order and extra properties; requires positions, DC colour,
    opacity, three scales and four rotation components, all ``float``.
    """
    path = Path(path)
    fix = "re-export the Gaussians as a standard 3DGS PLY (binary little endian)"
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read Gaussian PLY ({exc.strerror})", path, fix) from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (missing 'ply' magic or 'end_header')", path, fix)
    newline = raw.find(b"\n", end)
    if newline < 0:
        raise InputError("PLY header does not end with a newline after 'end_header' (truncated file)", path, fix)
    body_start = newline + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in [ln.strip() for ln in lines]:
        raise InputError("only binary_little_endian PLY files are supported", path, fix)
    count, names, in_vertex = None, [], False
    type_sizes = {"float": 4, "float32": 4}
    for ln in lines:
        parts = ln.split()
        if not parts:
            continue
        if parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                if len(parts) < 3 or not parts[2].isdigit():
                    raise InputError(f"PLY vertex count {' '.join(parts[2:])!r} is not a non-negative integer",
                                     path, fix)
                count = int(parts[2])
            elif count is not None:
                break  # vertex element comes first in 3DGS files; ignore later ones
        elif parts[0] == "property" and in_vertex:
            if len(parts) < 3:
                raise InputError(f"malformed PLY property line {ln.strip()!r}", path, fix)
            if parts[1] not in type_sizes:
                raise InputError(f"vertex property {parts[-1]!r} has type {parts[1]!r}; expected float", path, fix)
            names.append(parts[2])
    if count is None:
        raise InputError("PLY has no vertex element", path, fix)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in names]
    if missing:
        raise InputError(f"PLY lacks 3DGS properties {missing}", path, fix)
    need = count * len(names) * 4
    if len(raw) - body_start < need:
        raise InputError(f"PLY is truncated: {count} vertices need {need} bytes", path, fix)
    data = np.frombuffer(raw, dtype="<f4", count=count * len(names), offset=body_start).reshape(count, len(names))
    col = {n: i for i, n in enumerate(names)}
    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    m = n_rest // 3 + 1
    if n_rest % 3 or m not in (1, 4, 9, 16):
        raise InputError(f"PLY has {n_rest} f_rest properties; expected 0, 9, 24 or 45", path, fix)
    sh = np.empty((count, m, 3), np.float32)
    sh[:, 0] = data[:, [col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]]]
    if m > 1:
        rest = data[:, [col[f"f_rest_{i}"] for i in range(n_rest)]].reshape(count, 3, m - 1)
        sh[:, 1:] = rest.transpose(0, 2, 1)
    g = GaussianArrays(
        means=data[:, [col["x"], col["y"], col["z"]]],
        quats=data[:, [col[f"rot_{i}"] for i in range(4)]],
        log_scales=data[:, [col[f"scale_{i}"] for i in range(3)]],
        opacity_logits=data[:, col["opacity"]],
        sh=sh,
    )
    check_gaussians(g, path)
    return g


#: largest log-scale a Gaussian may have: exp(20) ~ 5e8 scene units. Beyond it the
#: covariance overflows float32 (``scale_0 = 80`` renders black) -- a broken file, not a splat.
MAX_LOG_SCALE = 20.0


def check_gaussians(g: GaussianArrays, path: str | os.PathLike | None = None) -> None:
    """Refuse non-finite or overflowing Gaussian values, naming the PLY property."""
    fix = "re-export the Gaussians from a finished training run (`python -m engine train`)"
    for name, arr in (("x/y/z", g.means), ("opacity", g.opacity_logits), ("scale_*", g.log_scales),
                      ("rot_*", g.quats), ("f_dc_*/f_rest_*", g.sh)):
        bad = ~np.isfinite(arr)
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise InputError(f"PLY property {name} has NaN or infinite values ({int(bad.sum())}, first at vertex "
                             f"{row})", path, fix)
    if g.count and (g.log_scales > MAX_LOG_SCALE).any():
        row = int(np.argwhere(g.log_scales > MAX_LOG_SCALE)[0][0])
        raise InputError(f"PLY property scale_* is {float(g.log_scales.max()):g} at vertex {row} (log scale above "
                         f"{MAX_LOG_SCALE:g}: the Gaussian would cover everything)", path, fix)
    if g.count and (np.linalg.norm(g.quats, axis=1) < 1e-12).any():
        raise InputError("PLY property rot_* has a zero quaternion", path, fix)


# ----------------------------------------------------------------------------------
# Nodes (nodes.npz)
# ----------------------------------------------------------------------------------
_NODE_REQUIRED = ("centers", "radii", "key_times", "pos_keys", "pos_tangents", "rot_keys", "rot_tangents")
_NODE_OPTIONAL = ("p_dyn", "bind_idx", "bind_w", "graph_idx", "pos_tangents_in", "rot_tangents_in", "key_mask",
                  "gauss_t_center", "gauss_lifespan", "gauss_view_origin", "gauss_view_angle")


@dataclasses.dataclass
class NodeArrays:
    """Control nodes and their spline trajectories (see ``docs/architecture.md``).

    Attributes
    ----------
    centers : (N, 3) canonical node centres ``c_i``.
    radii : (N,) RBF radii ``rho_i``.
    key_times : (K,) increasing key times in engine time ``[0, 1]``.
    pos_keys, pos_tangents : (N, K, 3) Hermite position keys ``p_i(t_k)`` and their
        time derivatives (per engine-time unit).
    rot_keys, rot_tangents : (N, K, 4) quaternion keys (wxyz) and derivatives.
    p_dyn : (N,) optional dynamic score from node initialisation.
    bind_idx, bind_w : (G, K_b) optional Gaussian -> node binding.
    graph_idx : (N, k) optional node neighbourhood graph (for ARAP).
    pos_tangents_in, rot_tangents_in : optional incoming tangents when they differ from
        the outgoing ones (broken Bezier handles edited in Blender).
    key_mask : (N, K) bool, optional; absent means all True. False marks a knot that is
        not one of the node's own keys but an exact split of its Hermite segment (value
        and time derivative of the curve there, :mod:`engine.geometry.hermite_knots`):
        Send Edits adds one to every other node when an artist keys one Empty at a new
        frame, so the key times stay shared while the other curves are unchanged. The
        engine evaluates every knot alike (the curve is the same); Blender gets keyframes
        only where it is True. Every row has a True. Training writes none (all its knots
        are trained); fine-tuning leaves ``nodes.npz`` as it is.
    gauss_t_center, gauss_lifespan : (G,) optional, both or neither, rows as ``bind_idx``:
        a Gaussian's lifespan. Its opacity at engine time ``t`` is
        ``opacity * exp(-0.5 ((t - gauss_t_center) / gauss_lifespan)^2)`` where
        ``gauss_lifespan > 0`` and ``opacity`` where it is 0 (always visible). Training
        writes them when moving Gaussians live around the frame they were seeded from
        (``TrainConfig.lifespan``, :mod:`engine.train.lifespan`).
    gauss_view_origin (G, 3), gauss_view_angle (G,) : optional, both or neither, rows as
        ``bind_idx``: a view-bound Gaussian's seed camera centre (world) and angle scale
        (radians; 0 = not view-bound). Seen from a camera centre ``c`` its opacity is also
        multiplied by ``exp(-0.5 (sin(a) / gauss_view_angle)^2)``, ``a`` the angle at the
        deformed Gaussian between the rays from ``gauss_view_origin`` and from ``c``
        (:mod:`engine.train.shot_detail`: per-frame detail of the moving things, trusted only
        near the camera that saw it).
    """

    centers: np.ndarray
    radii: np.ndarray
    key_times: np.ndarray
    pos_keys: np.ndarray
    pos_tangents: np.ndarray
    rot_keys: np.ndarray
    rot_tangents: np.ndarray
    p_dyn: np.ndarray | None = None
    bind_idx: np.ndarray | None = None
    bind_w: np.ndarray | None = None
    graph_idx: np.ndarray | None = None
    pos_tangents_in: np.ndarray | None = None
    rot_tangents_in: np.ndarray | None = None
    key_mask: np.ndarray | None = None
    gauss_t_center: np.ndarray | None = None
    gauss_lifespan: np.ndarray | None = None
    gauss_view_origin: np.ndarray | None = None
    gauss_view_angle: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.centers.shape[0])

    def own_keys(self) -> np.ndarray:
        """``[N, K]`` bool: the knots that are each node's own keys (:attr:`key_mask`, or all)."""
        if self.key_mask is None:
            return np.ones(self.pos_keys.shape[:2], bool)
        return np.asarray(self.key_mask, bool)

    def to_dict(self) -> dict[str, np.ndarray]:
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is not None:
                out[f.name] = np.asarray(value)
        return out

    @classmethod
    def from_dict(cls, arrays: dict[str, Any], path: str | os.PathLike | None = None) -> "NodeArrays":
        """Build and validate from a mapping of arrays (e.g. an opened ``nodes.npz``)."""
        fix = "re-run `python -m engine init` (or train) to regenerate the node file"
        missing = [k for k in _NODE_REQUIRED if k not in arrays]
        if missing:
            raise InputError(f"node file lacks arrays {missing}", path, fix)
        a = {k: np.asarray(arrays[k]) for k in _NODE_REQUIRED + _NODE_OPTIONAL if k in arrays}
        for key, value in a.items():
            if value.dtype == object:
                raise InputError(f"array {key!r} has dtype object", path, fix)
        n = a["centers"].shape[0] if a["centers"].ndim == 2 else -1
        k = a["key_times"].shape[0] if a["key_times"].ndim == 1 else -1
        expect = {"centers": (n, 3), "radii": (n,), "key_times": (k,), "pos_keys": (n, k, 3),
                  "pos_tangents": (n, k, 3), "rot_keys": (n, k, 4), "rot_tangents": (n, k, 4),
                  "pos_tangents_in": (n, k, 3), "rot_tangents_in": (n, k, 4), "p_dyn": (n,)}
        for key, shape in expect.items():
            if key in a and (a[key].shape != shape or n < 0 or k < 1):
                raise InputError(f"array {key!r} has shape {a[key].shape}; expected {shape}", path, fix)
        if "key_mask" in a:
            mask = a["key_mask"]
            if mask.dtype != np.bool_ or mask.shape != (n, k):
                raise InputError(f"key_mask must be bool of shape {(n, k)}; got {mask.dtype} {mask.shape}", path, fix)
            if n > 0 and not mask.any(axis=1).all():
                raise InputError("key_mask has a node without any key (a row with no True)", path, fix)
        for key in a:
            if key in ("bind_idx", "graph_idx", "key_mask"):
                continue
            if not np.issubdtype(a[key].dtype, np.floating) or not np.isfinite(a[key]).all():
                raise InputError(f"array {key!r} must be finite floating point", path, fix)
            a[key] = a[key].astype(np.float32)
        if k > 1 and not (np.diff(a["key_times"]) > 0).all():
            raise InputError("key_times must be strictly increasing", path, fix)
        if (a["radii"] <= 0).any():
            raise InputError("node radii must be positive", path, fix)
        if "bind_idx" in a:
            idx = a["bind_idx"]
            if idx.ndim != 2 or "bind_w" not in a or a["bind_w"].shape != idx.shape:
                raise InputError("bind_idx and bind_w must both be (G, K_b)", path, fix)
            if not np.issubdtype(idx.dtype, np.integer) or (idx.size and (idx.min() < 0 or idx.max() >= n)):
                raise InputError("bind_idx must hold node indices in [0, N)", path, fix)
            a["bind_idx"] = idx.astype(np.int64)
        if ("gauss_t_center" in a) != ("gauss_lifespan" in a):
            raise InputError("gauss_t_center and gauss_lifespan come together (one is missing)", path, fix)
        if "gauss_lifespan" in a:
            g = a["bind_idx"].shape[0] if "bind_idx" in a else -1
            for key in ("gauss_t_center", "gauss_lifespan"):
                if a[key].shape != (g,):
                    raise InputError(f"array {key!r} has shape {a[key].shape}; expected ({g},) "
                                     "(one value per bound Gaussian)", path, fix)
            if (a["gauss_lifespan"] < 0).any():
                raise InputError("gauss_lifespan must be >= 0 (0 = always visible)", path, fix)
        if ("gauss_view_origin" in a) != ("gauss_view_angle" in a):
            raise InputError("gauss_view_origin and gauss_view_angle come together (one is missing)", path, fix)
        if "gauss_view_angle" in a:
            g = a["bind_idx"].shape[0] if "bind_idx" in a else -1
            for key, shape in (("gauss_view_origin", (g, 3)), ("gauss_view_angle", (g,))):
                if a[key].shape != shape:
                    raise InputError(f"array {key!r} has shape {a[key].shape}; expected {shape} "
                                     "(one per bound Gaussian)", path, fix)
            if (a["gauss_view_angle"] < 0).any():
                raise InputError("gauss_view_angle must be >= 0 (0 = seen alike from everywhere)", path, fix)
        if "graph_idx" in a:
            gi = a["graph_idx"]
            if gi.ndim != 2 or gi.shape[0] != n or not np.issubdtype(gi.dtype, np.integer) or (
                    gi.size and (gi.min() < 0 or gi.max() >= n)):
                raise InputError("graph_idx must be (N, k) node indices", path, fix)
            a["graph_idx"] = gi.astype(np.int64)
        return cls(**a)


def write_nodes(path: str | os.PathLike, nodes: NodeArrays) -> None:
    """Validate and write ``nodes`` to ``path`` (npz, atomic)."""
    NodeArrays.from_dict(nodes.to_dict(), path)  # refuse to write what we could not read
    atomic_save_npz(path, **nodes.to_dict())


def read_nodes(path: str | os.PathLike) -> NodeArrays:
    """Read and validate ``nodes.npz`` (never unpickles)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise InputError("node file not found", path, "point to a bundle folder written by the engine") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise InputError(f"cannot read node file: corrupt or truncated ({type(exc).__name__}: {exc})", path,
                         "re-run the engine to regenerate it (or restore it from a backup)") from None
    return NodeArrays.from_dict(arrays, path)


# ----------------------------------------------------------------------------------
# scene.json
# ----------------------------------------------------------------------------------
def _is_matrix(value: Any, rows: int, cols: int) -> bool:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return arr.shape == (rows, cols) and bool(np.isfinite(arr).all())


#: largest image side a camera may ask for (a 16K frame); beyond it a render cannot be allocated
MAX_IMAGE_SIDE = 16384


def camera_problem(K, w2c, width: int, height: int) -> str | None:
    """What is wrong with one pinhole camera (``K [3,3]``, ``w2c [4,4]`` OpenCV), or ``None``.

    Checks a positive focal length, a rotation block that is a rotation (det 1, orthonormal
    to 1e-3) and an image size within :data:`MAX_IMAGE_SIDE`.
    """
    K, w2c = np.asarray(K, dtype=np.float64), np.asarray(w2c, dtype=np.float64)
    if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
        return "has NaN or infinite values in K or w2c"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"has a non-positive focal length (fx={K[0, 0]:g}, fy={K[1, 1]:g}) in K"
    R = w2c[:3, :3]
    if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        return "has a w2c whose 3x3 block is not a rotation (singular, scaled or mirrored)"
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        return f"asks for a {width}x{height} image; width and height must be 1..{MAX_IMAGE_SIDE}"
    return None


def validate_scene(scene: Any, path: str | os.PathLike | None = None) -> dict:
    """Check a ``scene.json`` mapping; return it or raise :class:`InputError`."""
    fix = "the file must be written by the Motion Splats engine (`python -m engine init|train`)"
    if not isinstance(scene, dict):
        raise InputError("scene description must be a JSON object", path, fix)
    if scene.get("format") != BUNDLE_FORMAT:
        raise InputError(f"'format' is {scene.get('format')!r}; expected {BUNDLE_FORMAT!r}", path, fix)
    version = scene.get("version")
    if not isinstance(version, int) or version > BUNDLE_VERSION or version < 1:
        raise InputError(f"unsupported bundle version {version!r} (this build reads 1..{BUNDLE_VERSION})", path,
                         "update the Motion Splats add-on/engine")
    tm = scene.get("time")
    if not isinstance(tm, dict) or not all(isinstance(tm.get(k), (int, float)) for k in
                                           ("frame_start", "frame_end", "fps")):
        raise InputError("'time' must have numeric frame_start, frame_end and fps", path, fix)
    if not tm["frame_end"] >= tm["frame_start"] or not tm["fps"] > 0:
        raise InputError("'time' needs frame_end >= frame_start and fps > 0", path, fix)
    cams = scene.get("cameras", [])
    if not isinstance(cams, list):
        raise InputError("'cameras' must be a list", path, fix)
    for i, cam in enumerate(cams):
        if not isinstance(cam, dict):
            raise InputError(f"camera {i} is not an object", path, fix)
        if not _is_matrix(cam.get("w2c"), 4, 4) or not _is_matrix(cam.get("K"), 3, 3):
            raise InputError(f"camera {i} needs finite 'w2c' (4x4) and 'K' (3x3)", path, fix)
        w, h, t = cam.get("width"), cam.get("height"), cam.get("time")
        if not (isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0):
            raise InputError(f"camera {i} needs positive integer width/height", path, fix)
        if not isinstance(t, (int, float)) or not 0.0 <= t <= 1.0:
            raise InputError(f"camera {i} time {t!r} is outside [0, 1]", path, fix)
        problem = camera_problem(cam["K"], cam["w2c"], w, h)
        if problem:
            raise InputError(f"camera {i} {problem}", path, fix)
    units = scene.get("units", 1.0)
    if not isinstance(units, (int, float)) or not units > 0:
        raise InputError("'units' must be a positive number", path, fix)
    return scene


def new_scene(frame_start: int, frame_end: int, fps: float, cameras: list[dict] | None = None,
              units: float = 1.0, **extra: Any) -> dict:
    """A valid ``scene.json`` mapping; ``cameras`` items need w2c, K, width, height, time."""
    scene = {"format": BUNDLE_FORMAT, "version": BUNDLE_VERSION, "units": float(units),
             "time": {"frame_start": frame_start, "frame_end": frame_end, "fps": float(fps)},
             "cameras": [_jsonable(c) for c in (cameras or [])]}
    scene.update(_jsonable(extra))
    return validate_scene(scene)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def frame_of_time(scene: dict, t):
    """Map engine time ``t`` (scalar or array in [0,1]) to scene frames (float)."""
    tm = scene["time"]
    return tm["frame_start"] + np.asarray(t, dtype=np.float64) * (tm["frame_end"] - tm["frame_start"])


def time_of_frame(scene: dict, frame):
    """Map scene frames to engine time; a one-frame clip maps everything to 0."""
    tm = scene["time"]
    span = tm["frame_end"] - tm["frame_start"]
    f = np.asarray(frame, dtype=np.float64)
    return np.zeros_like(f) if span == 0 else (f - tm["frame_start"]) / span


def write_scene(path: str | os.PathLike, scene: dict) -> None:
    atomic_write_json(path, validate_scene(_jsonable(scene), path))


def read_scene(path: str | os.PathLike) -> dict:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("scene.json not found", path, "point to a bundle folder written by the engine") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read scene file ({exc})", path, "re-run the engine to regenerate it") from None
    try:
        scene = json.loads(text)
    except ValueError as exc:
        raise InputError(f"invalid JSON ({exc})", path, "re-run the engine to regenerate it") from None
    return validate_scene(scene, path)


# ----------------------------------------------------------------------------------
# The bundle folder
# ----------------------------------------------------------------------------------
@dataclasses.dataclass
class Bundle:
    """An opened result bundle. ``gaussians`` is ``None`` before training."""

    path: Path
    scene: dict
    nodes: NodeArrays | None
    gaussians: GaussianArrays | None


def save_bundle(path: str | os.PathLike, scene: dict, nodes: NodeArrays | None = None,
                gaussians: GaussianArrays | None = None) -> Path:
    """Write the given parts of a bundle into folder ``path`` (each file atomically).

    ``scene.json`` is written last, so a folder with a ``scene.json`` always has the
    node and Gaussian files it was written with.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if nodes is not None:
        write_nodes(path / NODES_FILE, nodes)
    if gaussians is not None:
        write_ply(path / GAUSSIANS_FILE, gaussians)
    write_scene(path / SCENE_FILE, scene)
    return path


def load_bundle(path: str | os.PathLike) -> Bundle:
    """Open and validate a bundle folder; missing optional parts load as ``None``."""
    path = Path(path)
    if not path.is_dir():
        raise InputError("bundle folder not found", path, "pass the folder given to `python -m engine train --out`")
    scene = read_scene(path / SCENE_FILE)
    nodes = read_nodes(path / NODES_FILE) if (path / NODES_FILE).exists() else None
    gaussians = read_ply(path / GAUSSIANS_FILE) if (path / GAUSSIANS_FILE).exists() else None
    if nodes is not None and gaussians is not None and nodes.bind_idx is not None \
            and nodes.bind_idx.shape[0] != gaussians.count:
        raise InputError(f"binding covers {nodes.bind_idx.shape[0]} Gaussians but the PLY has {gaussians.count}",
                         path / NODES_FILE, "re-run training so nodes.npz and gaussians.ply match")
    return Bundle(path=path, scene=scene, nodes=nodes, gaussians=gaussians)
