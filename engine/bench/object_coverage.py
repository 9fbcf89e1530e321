"""Do the Gaussians on a moving object stay on it? A trained bundle against a generated scene.

A model can render a moving object in every training frame without following it: each
stretch of time gets its own Gaussians for the object, right near the frames they were
seeded from and elsewhere (floaters, under the floor, out of view) at other times. The
image-space measures do not see that relay; the node trajectories and the Blender rig do
(docs/benchmarks.md, "Gaussians left behind"). :func:`kept_on_objects` measures it: the
opaque Gaussians whose centres project into a moving object at the middle training frame,
and the share of them whose centres still project into that object at every other training
frame where the object is in view.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: opacity above which a Gaussian counts (fainter ones barely render)
MIN_OPACITY = 0.3


def kept_fractions(labels: np.ndarray, visible: np.ndarray, ref: int, objects) -> dict[int, float | None]:
    """Per object, the mean share of its Gaussians at frame ``ref`` still on it at other frames.

    Parameters
    ----------
    labels : (T, G) int, the object id under each Gaussian's projected centre at each frame
        (any id not in ``objects``, e.g. -1, for off-image or behind-camera centres).
    visible : (T, O) bool, whether object ``objects[o]`` has pixels at frame t.
    ref : the reference frame.
    objects : sequence of O object ids.

    Returns
    -------
    ``{id: share in [0, 1]}`` averaged over the frames ≠ ``ref`` where the object is visible;
    None for an object with no Gaussian on it at ``ref`` or never visible elsewhere.
    """
    labels = np.asarray(labels)
    out: dict[int, float | None] = {}
    others = np.arange(labels.shape[0]) != ref
    for o, k in enumerate(objects):  # loop over objects (a handful)
        on = labels[ref] == k
        frames = others & np.asarray(visible)[:, o]
        if not on.any() or not frames.any():
            out[int(k)] = None
            continue
        out[int(k)] = float((labels[frames][:, on] == k).mean())
    return out


def kept_on_objects(bundle_dir, scene_dir) -> dict:
    """:func:`kept_fractions` of a trained bundle at its training cameras, reference = the
    middle one, labels from the scene's ``gt/object_id`` images (ids in ``gt/objects.json``;
    0 is the background).

    Returns
    -------
    dict: ``kept_dyn`` (mean over the moving objects, None when none is scored) and
    ``kept_per_object`` ({name: share or None}).
    """
    import json

    import cv2
    import torch

    from ..bundle import load_bundle
    from ..geometry.camera import project
    from ..train.from_bundle import model_from_bundle
    from .node_motion import bundle_train_frames

    bundle = load_bundle(bundle_dir)
    model = model_from_bundle(bundle)
    ids = json.loads((Path(scene_dir) / "gt" / "objects.json").read_text())["object_ids"]
    names = {int(v): k for k, v in ids.items() if int(v) != 0}
    objects = sorted(names)
    cams, frame_ids = bundle_train_frames(bundle, scene_dir)
    with torch.no_grad():
        # opaque at the reference (middle) frame; a Gaussian with a lifespan is scored by where
        # its nodes carry it, also at frames where it is faded out
        ref_time = float(cams[len(cams) // 2]["time"])
        opaque = (model.opacities_at(ref_time).reshape(-1) > MIN_OPACITY).numpy()
        labels = np.full((len(cams), int(opaque.sum())), -1, np.int64)
        visible = np.zeros((len(cams), len(objects)), bool)
        for t, (c, fid) in enumerate(zip(cams, frame_ids)):  # loop over frames
            path = Path(scene_dir) / "gt" / "object_id" / f"{fid}.png"
            oid = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if oid is None:
                raise FileNotFoundError(path)
            oid = oid if oid.ndim == 2 else oid[..., 0]
            means, _ = model.deform(float(c["time"]))
            uv, z = project(torch.as_tensor(np.asarray(c["K"]), dtype=torch.float32),
                            torch.as_tensor(np.asarray(c["w2c"]), dtype=torch.float32), means[opaque])
            s = oid.shape[1] / float(c["width"])  # the ids may be stored at another resolution
            u, v = np.floor(uv[:, 0].numpy() * s).astype(np.int64), np.floor(uv[:, 1].numpy() * s).astype(np.int64)
            ok = (z.numpy() > 0) & (u >= 0) & (u < oid.shape[1]) & (v >= 0) & (v < oid.shape[0])
            labels[t, ok] = oid[v[ok], u[ok]]
            visible[t] = [(oid == k).any() for k in objects]
    kept = kept_fractions(labels, visible, len(cams) // 2, objects)
    scored = [x for x in kept.values() if x is not None]
    return {"kept_dyn": float(np.mean(scored)) if scored else None,
            "kept_per_object": {names[k]: v for k, v in kept.items()}}
