"""N3DV (Neural 3D Video) multi-camera reader, monocular protocol.

Layout: ``poses_bounds.npy [C,17]`` (LLFF: per camera a 3x5 matrix ``[c2w 3x4 | (H, W, focal)]``
with rotation columns in LLFF axes *(down, right, back)*, then ``near, far``) and videos
``cam00.mp4, cam01.mp4, …`` — row ``i`` of ``poses_bounds.npy`` is the ``i``-th video by name.

Axis conversion to OpenCV: ``x = right = col1``, ``y = down = col0``, ``z = forward = −col2``.
Intrinsics ``fx = fy = focal``, ``cx = W/2``, ``cy = H/2``, rescaled if the video's size differs
from ``(W, H)`` in the file.

Protocol: camera ``train_camera`` (index, default 0 = ``cam00``) is the monocular training
clip; ``eval_cameras`` (names or indices; default: every other camera) become
``Clip.eval_clips`` with the same frame times. The multi-view N3DV protocol holds out
``cam00`` for testing; to mirror it, use ``train_camera=1, eval_cameras=['cam00']``.
``split['train']`` is every frame of the training camera; ``split['test']`` is empty (test
frames live in ``eval_clips``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .clip import VIDEO_EXTS, Clip, FrameSource, finalize, scene_bounds, times_from_count
from .video import video_info


def is_n3dv(path: Path) -> bool:
    return Path(path).is_dir() and (Path(path) / "poses_bounds.npy").is_file()


def llff_to_w2c(pb: np.ndarray):
    """``poses_bounds [C,17]`` → ``w2c [C,4,4]`` (OpenCV), ``(H, W, focal) [C,3]``, ``bounds [C,2]``."""
    P = pb[:, :15].reshape(-1, 3, 5)
    R_llff, t = P[:, :, :3], P[:, :, 3]
    R_cv = np.stack([R_llff[:, :, 1], R_llff[:, :, 0], -R_llff[:, :, 2]], axis=2)
    w2c = np.tile(np.eye(4), (len(pb), 1, 1))
    w2c[:, :3, :3] = np.transpose(R_cv, (0, 2, 1))
    w2c[:, :3, 3] = -np.einsum("cji,cj->ci", R_cv, t)
    return w2c, P[:, :, 4], pb[:, 15:17]


def load_n3dv(path, train_camera: int | str = 0, eval_cameras=None, frame_step: int = 1,
              max_frames: int | None = None, scale: int = 1) -> Clip:
    """Read an N3DV scene; see the module doc for the protocol."""
    root = Path(path)
    pbp = root / "poses_bounds.npy"
    try:
        pb = np.load(pbp, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read poses_bounds.npy ({exc}).", pbp, "Restore the file.") from None
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise InputError(f"poses_bounds.npy has shape {pb.shape}; expected [C,17].", pbp, "Use an LLFF poses_bounds.npy.")
    pb = pb.astype(np.float64)
    if not np.isfinite(pb).all():
        raise InputError("poses_bounds.npy has NaN/inf values.", pbp, "Restore the file.")
    videos = sorted(p for p in root.iterdir() if p.suffix.lower() in VIDEO_EXTS and p.stem.startswith("cam"))
    if len(videos) != len(pb):
        raise InputError(f"{len(videos)} camera videos for {len(pb)} poses.", pbp,
                         "Every row of poses_bounds.npy needs a camNN video.")
    names = [v.stem for v in videos]

    def pick(c):
        if isinstance(c, str):
            if c not in names:
                raise InputError(f"camera {c!r} not found (have {names}).", root, "Use one of the listed names.")
            return names.index(c)
        if not 0 <= int(c) < len(names):
            raise InputError(f"camera index {c} out of range (0..{len(names) - 1}).", root, "Pick another camera.")
        return int(c)

    ti = pick(train_camera)
    ev = [i for i in range(len(names)) if i != ti] if eval_cameras is None else [pick(c) for c in eval_cameras]
    w2c, hwf, bounds = llff_to_w2c(pb)

    def one(i, nframes=None) -> Clip:
        n, w, h, fps = video_info(videos[i])
        H, W, f = hwf[i]
        sx = w / W
        K = np.array([[f * sx, 0, w / 2], [0, f * sx, h / 2], [0, 0, 1.0]])
        idx = list(range(0, n, max(1, int(frame_step))))
        if max_frames:
            idx = idx[: int(max_frames)]
        if nframes is not None:
            idx = idx[:nframes]
        F = len(idx)
        return Clip(frames=FrameSource(video=videos[i], indices=idx), width=w, height=h,
                    fps=fps / max(1, int(frame_step)), times=times_from_count(F), frame_ids=[str(j) for j in idx],
                    K=np.tile(K, (F, 1, 1)), w2c=np.tile(w2c[i], (F, 1, 1)), dist=None, source=pbp,
                    near=float(bounds[i, 0]), far=float(bounds[i, 1]), downscale=int(scale), meta={"camera": names[i]})

    clip = one(ti)
    clip.validate_cameras()
    for i in ev:
        e = one(i, clip.num_frames)
        e.validate_cameras()
        clip.eval_clips[names[i]] = e
    allc = -np.einsum("cji,cj->ci", w2c[:, :3, :3], w2c[:, :3, 3])
    clip.scene_center, clip.scene_scale = scene_bounds(allc)
    clip.split = {"train": list(range(clip.num_frames)), "val": [], "test": []}
    clip.near, clip.far = float(bounds[:, 0].min()), float(bounds[:, 1].max())
    return finalize(clip)
