# SPDX-License-Identifier: GPL-3.0-or-later
"""What a footage path is, and whether a set of cameras moves (no bpy).

Import Footage and Reconstruct accept what the engine's ``load_clip`` accepts; the
layout tests are the engine's own (``engine.io``, numpy-only at import time), so the
add-on and the engine never disagree about a folder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..engine.errors import InputError

#: Footage kinds: a Movie Clip can show ``video``/``image``/``images``; ``dataset`` and
#: ``manifest`` are read by the engine only (they carry their own cameras or splits).
MOVIE_KINDS = ("video", "image", "images")

#: A camera whose poses differ by less than this (metres / radians) over the clip is static.
STATIC_TOL = 1e-5


def classify(path) -> tuple[str, str]:
    """``(kind, description)`` of a footage path.

    ``kind`` is ``'video'`` (a movie file), ``'image'`` (one image of a sequence),
    ``'images'`` (a folder of images), ``'dataset'`` (a Nerfies / D-NeRF / N3DV / COLMAP
    folder) or ``'manifest'`` (a clip manifest JSON). Raises :class:`InputError` naming
    the path and the fix for anything the engine cannot read.
    """
    from ..engine.io import clip as clip_io
    from ..engine.io import is_colmap, is_dnerf, is_manifest, is_n3dv, is_nerfies

    p = Path(path)
    if not p.exists():
        raise InputError("footage not found.", str(p), "pick a video, an image, an image folder or a dataset folder.")
    if p.is_file():
        ext = p.suffix.lower()
        if ext in clip_io.VIDEO_EXTS:
            return "video", "video"
        if ext in clip_io.IMAGE_EXTS:
            return "image", "image sequence"
        if ext == ".json" and is_manifest(p):
            return "manifest", "clip manifest"
        if ext == ".json" and (p.name.startswith("transforms_") or p.name == "dataset.json"):
            return "dataset", "dataset"
        raise InputError(f"unsupported footage file type '{p.suffix}'.", str(p),
                         "pick a video, an image of a sequence, a clip manifest or a dataset folder.")
    for test, name in ((is_nerfies, "Nerfies/HyperNeRF"), (is_dnerf, "D-NeRF"), (is_n3dv, "N3DV"),
                       (is_colmap, "COLMAP")):
        if test(p):
            return "dataset", f"{name} dataset"
    if clip_io.list_images(p):
        return "images", "image folder"
    raise InputError("the folder is not a clip layout the engine reads.", str(p),
                     "pick a Nerfies, D-NeRF, COLMAP, N3DV or image folder, a video or a clip manifest.")


def cameras_move(w2cs, tol: float = STATIC_TOL) -> bool:
    """Whether world-to-camera matrices ``w2cs [F, 4, 4]`` differ anywhere over the clip.

    A camera that was never animated or tracked exports identical poses; training on
    them is training on a guess.
    """
    w2cs = np.asarray(w2cs, dtype=np.float64).reshape(-1, 4, 4)
    if len(w2cs) < 2:
        return False
    return bool(np.abs(w2cs - w2cs[:1]).max() > tol)
