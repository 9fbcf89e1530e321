"""The common clip data model every reader returns.

A :class:`Clip` is a monocular (or multi-camera, for evaluation) sequence of frames with
optional per-frame cameras. Conventions (see ``docs/architecture.md``):

* ``K [F,3,3] float64`` in continuous pixels (upper-left pixel centre at ``(0.5, 0.5)``),
* ``w2c [F,4,4] float64`` world-to-camera, OpenCV axes (x right, y down, z forward),
* ``dist [F,5] float64`` OpenCV ``(k1, k2, p1, p2, k3)`` or ``None`` (no distortion),
* ``times [F] float64`` engine time in ``[0, 1]`` (first frame 0, last frame 1).

Frames are loaded lazily: a clip stores image paths, or a video path plus frame indices.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".exr")
VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")


def _imread_rgb(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError("image file is missing.", path, "Restore the file or re-export the clip.")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("image cannot be decoded.", path, "Re-export the frame as PNG or JPEG.")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[:, :, :3]
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = (np.clip(img.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(img[:, :, ::-1])


class FrameSource:
    """Lazy frame loader: image paths, or a video file plus frame indices.

    Parameters
    ----------
    paths : list of path, optional
        One image per frame.
    video : path, optional
        A video file; ``indices`` picks frames from it (0-based decode order).
    indices : sequence of int, optional
        Frame indices in ``video``.
    """

    def __init__(self, paths=None, video=None, indices=None):
        if (paths is None) == (video is None):
            raise ValueError("give exactly one of paths or video")
        self.paths = None if paths is None else [Path(p) for p in paths]
        self.video = None if video is None else Path(video)
        self.indices = None if indices is None else [int(i) for i in indices]
        self._cache: dict[int, np.ndarray] = {}
        self._cap = None
        self._pos = 0

    def __getstate__(self):
        return {**self.__dict__, "_cap": None, "_pos": 0, "_cache": {}}

    def __len__(self) -> int:
        return len(self.paths) if self.paths is not None else len(self.indices or [])

    def subset(self, idx) -> "FrameSource":
        """A new source with frames ``idx`` (list of int) of this one."""
        idx = [int(i) for i in idx]
        if self.paths is not None:
            return FrameSource(paths=[self.paths[i] for i in idx])
        return FrameSource(video=self.video, indices=[self.indices[i] for i in idx])

    def _read_video_frame(self, vi: int) -> np.ndarray:
        """Decode video frame ``vi``; sequential access reads each frame once (seeks by re-reading)."""
        import cv2

        if self._cap is None or self._pos > vi:
            if self._cap is not None:
                self._cap.release()
            self._cap = cv2.VideoCapture(str(self.video))
            self._pos = 0
            if not self._cap.isOpened():
                self._cap = None
                raise InputError("video cannot be opened or decoded.", self.video,
                                 "Check the file plays, or convert it to H.264 MP4 or an image sequence.")
        while True:
            ok, bgr = self._cap.read()
            if not ok or bgr is None:
                self._cap.release()
                self._cap = None
                raise InputError(f"video ended or failed to decode at frame {self._pos} (needed {vi}).",
                                 self.video, "Re-encode the video or shorten the frame range.")
            self._pos += 1
            if self._pos - 1 == vi:
                return np.ascontiguousarray(bgr[:, :, ::-1])

    def load(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``uint8 [H,W,3]`` RGB."""
        if self.paths is not None:
            return _imread_rgb(self.paths[i])
        vi = self.indices[i]
        if vi not in self._cache:
            self._cache = {vi: self._read_video_frame(vi)}  # keep only the last frame
        return self._cache[vi]

    def close(self) -> None:
        """Release an open video decoder."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None


@dataclasses.dataclass
class Clip:
    """A frame sequence with (optional) cameras.

    Attributes
    ----------
    frames : FrameSource
        Lazy frame loader, ``F`` frames.
    width, height : int
        Full-resolution frame size in pixels (what ``K`` refers to).
    fps : float
        Frames per second of the source (``0`` if unknown).
    times : ndarray [F] float64
        Engine time in ``[0, 1]``.
    frame_ids : list of str
        Original frame names/ids.
    K : ndarray [F,3,3] float64 or None
        Intrinsics, continuous pixel convention. ``None`` when cameras are unknown.
    w2c : ndarray [F,4,4] float64 or None
        World-to-camera, OpenCV axes.
    dist : ndarray [F,5] float64 or None
        OpenCV distortion ``(k1, k2, p1, p2, k3)``.
    split : dict of str -> list of int
        Frame indices per split: ``'train'``, ``'val'`` (and ``'test'``).
    eval_clips : dict of str -> Clip
        Other cameras for evaluation (multi-camera datasets), keyed by camera name.
    scene_center : ndarray [3] or None
    scene_scale : float or None
        Centre and radius of the camera centres (or points); see :func:`scene_bounds`.
    points, point_colors : ndarray [P,3] float64 / uint8 or None
        Sparse 3D points and their colours.
    masks : list of path or None
        Per-frame mask images (1 = dynamic), if the source provided them.
    priors : dict
        Precomputed prior paths (clip manifest).
    source : Path or None
        The file/folder the clip was read from (used in error messages).
    near, far : float or None
        Depth bounds when the dataset supplies them.
    """

    frames: FrameSource
    width: int
    height: int
    fps: float
    times: np.ndarray
    frame_ids: list
    K: np.ndarray | None = None
    w2c: np.ndarray | None = None
    dist: np.ndarray | None = None
    split: dict = dataclasses.field(default_factory=dict)
    eval_clips: dict = dataclasses.field(default_factory=dict)
    scene_center: np.ndarray | None = None
    scene_scale: float | None = None
    points: np.ndarray | None = None
    point_colors: np.ndarray | None = None
    masks: list | None = None
    priors: dict = dataclasses.field(default_factory=dict)
    source: Path | None = None
    near: float | None = None
    far: float | None = None
    downscale: int = 1
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64)
        if not self.split:
            self.split = {"train": list(range(len(self.frames))), "val": []}

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def has_cameras(self) -> bool:
        return self.K is not None and self.w2c is not None

    def load_frame(self, i: int, downscale: int | None = None) -> np.ndarray:
        """Frame ``i`` as ``uint8 [H,W,3]`` RGB, optionally downscaled by an integer factor.

        The image is resized to ``(width // d, height // d)`` with area averaging; intrinsics
        for it are :meth:`scaled_K` ``(1/d)``.
        """
        img = self.frames.load(i)
        if img.shape[0] != self.height or img.shape[1] != self.width:
            where = self.frames.paths[i] if self.frames.paths is not None else self.frames.video
            raise InputError(f"frame {i} is {img.shape[1]}x{img.shape[0]} but the clip is "
                             f"{self.width}x{self.height}.", where,
                             "All frames must have the size the cameras were calibrated for.")
        d = self.downscale if downscale is None else int(downscale)
        if d > 1:
            import cv2

            img = cv2.resize(img, (self.width // d, self.height // d), interpolation=cv2.INTER_AREA)
        return img

    def camera_centers(self) -> np.ndarray:
        """Camera centres in world coordinates, ``[F,3]``."""
        R = self.w2c[:, :3, :3]
        t = self.w2c[:, :3, 3]
        return -np.einsum("fji,fj->fi", R, t)

    def scaled_K(self, factor: float) -> np.ndarray:
        """Intrinsics for images resized by ``factor`` (continuous convention: scale all)."""
        K = self.K.copy()
        K[:, :2, :] *= factor
        return K

    def subset(self, idx) -> "Clip":
        """A clip with frames ``idx`` only (times are kept, not renormalised)."""
        idx = [int(i) for i in idx]
        pick = lambda a: None if a is None else a[idx]
        return dataclasses.replace(
            self, frames=self.frames.subset(idx), times=self.times[idx],
            frame_ids=[self.frame_ids[i] for i in idx], K=pick(self.K), w2c=pick(self.w2c),
            dist=pick(self.dist), split={"train": list(range(len(idx))), "val": []},
            masks=None if self.masks is None else [self.masks[i] for i in idx], eval_clips={})

    def validate_cameras(self) -> None:
        """Raise :class:`InputError` (naming :attr:`source`) for invalid cameras.

        Rejects wrong shapes, NaN/inf, non-orthonormal or reflecting rotations, a
        bottom row other than ``[0,0,0,1]``, and non-positive focal lengths.
        """
        validate_cameras(self.K, self.w2c, self.dist, self.source, self.num_frames)


def validate_cameras(K, w2c, dist, source, num_frames: int | None = None) -> None:
    """Check camera arrays; see :meth:`Clip.validate_cameras`.

    Parameters
    ----------
    K : ndarray [F,3,3]
    w2c : ndarray [F,4,4]
    dist : ndarray [F,5] or None
    source : path
        Named in the error.
    num_frames : int, optional
        Expected ``F``.
    """
    fix = "Re-export or re-solve the cameras."
    if K is None or w2c is None:
        raise InputError("the clip has no cameras.", source, "Solve cameras first (solve_cameras).")
    K = np.asarray(K)
    w2c = np.asarray(w2c)
    F = K.shape[0] if K.ndim == 3 else -1
    if K.shape != (F, 3, 3) or w2c.shape != (F, 4, 4):
        raise InputError(f"camera arrays have shapes K {K.shape}, w2c {w2c.shape}; "
                         "expected [F,3,3] and [F,4,4].", source, fix)
    if num_frames is not None and F != num_frames:
        raise InputError(f"{F} cameras for {num_frames} frames.", source, "Give one camera per frame.")
    bad = ~(np.isfinite(K).all(axis=(1, 2)) & np.isfinite(w2c).all(axis=(1, 2)))
    if dist is not None:
        dist = np.asarray(dist)
        if dist.shape != (F, 5):
            raise InputError(f"distortion has shape {dist.shape}; expected [F,5].", source, fix)
        bad |= ~np.isfinite(dist).all(axis=1)
    if bad.any():
        raise InputError(f"camera {int(np.argmax(bad))} has NaN or infinite values.", source, fix)
    fx, fy = K[:, 0, 0], K[:, 1, 1]
    bad = (fx <= 0) | (fy <= 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"camera {i} has a non-positive focal length (fx={fx[i]:g}, fy={fy[i]:g}).",
                         source, fix)
    R = w2c[:, :3, :3]
    err = np.abs(np.einsum("fij,fkj->fik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > 1e-4) | (det < 0.5)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"camera {i} has a singular, scaled or reflecting rotation "
                         f"(|R R^T - I| = {err[i]:.3g}, det = {det[i]:.3g}).", source, fix)
    bottom = np.abs(w2c[:, 3, :] - np.array([0, 0, 0, 1.0])).max(axis=1)
    if (bottom > 1e-9).any():
        i = int(np.argmax(bottom > 1e-9))
        raise InputError(f"camera {i}'s w2c bottom row is not [0,0,0,1].", source, fix)


def scene_bounds(centers: np.ndarray, points: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Scene centre and scale.

    With points: centre = median point, scale = 90th percentile distance of the points
    to it. Without: centre = mean camera centre, scale = 1.1 × max camera distance from
    it (the 3DGS "cameras extent"); ``1.0`` if all cameras coincide.

    Parameters
    ----------
    centers : ndarray [F,3]
    points : ndarray [P,3], optional

    Returns
    -------
    center : ndarray [3]
    scale : float
    """
    if points is not None and len(points) >= 10:
        c = np.median(points, axis=0)
        s = float(np.percentile(np.linalg.norm(points - c, axis=1), 90))
    else:
        c = centers.mean(axis=0)
        s = 1.1 * float(np.linalg.norm(centers - c, axis=1).max()) if len(centers) else 0.0
    return c, (s if s > 1e-12 else 1.0)


def times_from_count(n: int) -> np.ndarray:
    """``[n]`` evenly spaced engine times, ``0`` … ``1`` (``[0.]`` for one frame)."""
    return np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(n)


def normalise_times(t) -> np.ndarray:
    """Map arbitrary increasing times to ``[0, 1]`` (constant → zeros)."""
    t = np.asarray(t, dtype=np.float64)
    lo, hi = t.min(), t.max()
    return (t - lo) / (hi - lo) if hi > lo else np.zeros_like(t)


def project_points(K: np.ndarray, w2c: np.ndarray, X: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Project world points with one camera (numpy reference, for tests and readers).

    Parameters
    ----------
    K : ndarray [3,3]
    w2c : ndarray [4,4]
    X : ndarray [N,3]
    dist : ndarray [5] or None, OpenCV (k1,k2,p1,p2,k3)

    Returns
    -------
    uv : ndarray [N,2] continuous pixel coordinates
    """
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    x = Xc[:, 0] / Xc[:, 2]
    y = Xc[:, 1] / Xc[:, 2]
    if dist is not None:
        k1, k2, p1, p2, k3 = dist
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    return np.stack([u, v], axis=1)


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder`` sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())


def load_json(path: Path) -> Any:
    """Read JSON; missing/bad files raise :class:`InputError` naming ``path``."""
    import json

    path = Path(path)
    if not path.is_file():
        raise InputError("file is missing.", path, "Check the dataset folder is complete.")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"invalid JSON ({exc}).", path, "Fix or re-export the file.") from None


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file (decodes it)."""
    img = _imread_rgb(Path(path))
    return img.shape[1], img.shape[0]


def finalize(clip: Clip) -> Clip:
    """Validate cameras (if any) and fill scene centre/scale."""
    if clip.has_cameras:
        clip.validate_cameras()
        if clip.scene_center is None:
            c, s = scene_bounds(clip.camera_centers(), clip.points)
            clip.scene_center, clip.scene_scale = c, s
    return clip
