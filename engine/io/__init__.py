"""Clip ingest: dataset readers and the camera solver.

``load_clip(path, **options)`` detects the layout:

==================================== ====================================
path                                 reader
==================================== ====================================
``*.json`` with motion-splats-clip    :func:`manifest.load_manifest`
video file                           :func:`video.load_video`
folder with ``dataset.json``+camera/ :func:`nerfies.load_nerfies`
folder with ``transforms_*.json``    :func:`dnerf.load_dnerf`
folder with ``poses_bounds.npy``     :func:`n3dv.load_n3dv`
folder with a COLMAP model           :func:`colmap.load_colmap`
folder of images                     :func:`video.load_image_folder`
==================================== ====================================
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .clip import Clip, FrameSource, project_points, scene_bounds, validate_cameras
from .colmap import is_colmap, load_colmap
from .dnerf import is_dnerf, load_dnerf
from .manifest import is_manifest, load_manifest, validate_manifest, write_manifest
from .n3dv import is_n3dv, load_n3dv
from .nerfies import is_nerfies, load_nerfies
from .video import load_image_folder, load_video
from .clip import VIDEO_EXTS, list_images

__all__ = ["Clip", "FrameSource", "load_clip", "load_nerfies", "load_dnerf", "load_colmap", "load_manifest",
           "write_manifest", "validate_manifest", "load_n3dv", "load_video", "load_image_folder",
           "validate_cameras", "scene_bounds", "project_points"]


def load_clip(path, **options) -> Clip:
    """Read a clip from any supported layout (see module doc); options go to the reader.

    A reader that trips over a malformed file in a way it does not check itself (a value
    of the wrong type deep in a dataset) still ends in one :class:`InputError` naming the
    clip, never a traceback.
    """
    try:
        clip = _load_clip(path, **options)
    except (ValueError, TypeError, KeyError, IndexError, AttributeError) as exc:
        raise InputError(f"malformed clip data ({type(exc).__name__}: {str(exc)[:160]}).", path,
                         "Check the dataset files against the documented layout (docs/clip_manifest.md).") from None
    if clip.source is not None:  # recorded in scene.json: eval/finetune from another folder must find it
        clip.source = Path(clip.source).resolve()
    return clip


def _load_clip(path, **options) -> Clip:
    p = Path(path)
    if not p.exists():
        raise InputError("path does not exist.", p, "Check the clip path.")
    if p.is_file():
        if p.suffix.lower() == ".json":
            if is_manifest(p):
                return load_manifest(p, **options)
            if p.name.startswith("transforms_"):
                return load_dnerf(p.parent, **options)
            if p.name == "dataset.json":
                return load_nerfies(p.parent, **options)
            raise InputError("JSON file is not a motion-splats clip manifest.", p,
                             "Export the clip from Blender or point at the dataset folder.")
        if p.suffix.lower() in VIDEO_EXTS:
            return load_video(p, **options)
        raise InputError(f"unsupported file type '{p.suffix}'.", p, "Give a video, manifest, or dataset folder.")
    for test, reader in ((is_nerfies, load_nerfies), (is_dnerf, load_dnerf), (is_n3dv, load_n3dv),
                         (is_colmap, load_colmap)):
        if test(p):
            return reader(p, **options)
    if list_images(p):
        return load_image_folder(p, **options)
    raise InputError("folder is not a recognised clip layout.", p,
                     "Use a Nerfies, D-NeRF, COLMAP, N3DV or image folder, a video, or a clip manifest.")
