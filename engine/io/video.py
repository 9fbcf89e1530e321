"""Frames without cameras: a video file or a folder of images.

Videos are read with ``cv2.VideoCapture``; ``frame_step`` and ``max_frames`` thin long
clips. Engine times are evenly spaced over the kept frames. Cameras are ``None``: run
:func:`engine.io.solve.solve_cameras` next.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .clip import IMAGE_EXTS, Clip, FrameSource, image_size, list_images, times_from_count


def video_info(path: Path) -> tuple[int, int, int, float]:
    """``(frame_count, width, height, fps)`` of a video; unreadable ones raise InputError."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("video file is missing.", path, "Check the path.")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise InputError("video cannot be opened or decoded.", path,
                             "Check the file plays, or convert it to H.264 MP4 or an image sequence.")
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        ok, fr = cap.read()
        if not ok or fr is None:
            raise InputError("video has no decodable frames.", path,
                             "Check the file plays, or convert it to H.264 MP4 or an image sequence.")
        h, w = fr.shape[:2]
    finally:
        cap.release()
    return max(n, 1), w, h, fps


def load_video(path, frame_step: int = 1, max_frames: int | None = None, frame_start: int = 0,
               scale: int = 1) -> Clip:
    """A clip of frames ``frame_start, frame_start+step, …`` of a video (no cameras)."""
    path = Path(path)
    n, w, h, fps = video_info(path)
    idx = list(range(int(frame_start), n, max(1, int(frame_step))))
    if max_frames:
        idx = idx[: int(max_frames)]
    if not idx:
        raise InputError(f"no frames selected (video has {n}).", path, "Lower frame_start.")
    if len(idx) < 2:  # nothing moves in one frame, and no camera can be solved from it
        raise InputError(f"video has only {len(idx)} usable frame; a reconstruction needs at least 2.", path,
                         "Use a longer clip (or a lower frame step).")
    return Clip(frames=FrameSource(video=path, indices=idx), width=w, height=h,
                fps=fps / max(1, int(frame_step)), times=times_from_count(len(idx)),
                frame_ids=[str(i) for i in idx], source=path, downscale=int(scale))


def load_image_folder(path, frame_step: int = 1, max_frames: int | None = None, fps: float = 0.0,
                      scale: int = 1) -> Clip:
    """A clip of the images in a folder, sorted by name (no cameras)."""
    path = Path(path)
    imgs = list_images(path)[:: max(1, int(frame_step))]
    if max_frames:
        imgs = imgs[: int(max_frames)]
    if not imgs:
        raise InputError(f"no images ({', '.join(IMAGE_EXTS)}) in the folder.", path, "Point at a folder of frames.")
    if len(imgs) < 2:
        raise InputError("the folder has only 1 image; a reconstruction needs at least 2 frames.", path,
                         "Add the clip's other frames.")
    w, h = image_size(imgs[0])
    return Clip(frames=FrameSource(paths=imgs), width=w, height=h, fps=float(fps),
                times=times_from_count(len(imgs)), frame_ids=[p.name for p in imgs], source=path,
                downscale=int(scale))
