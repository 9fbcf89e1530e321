"""Ground-truth ("oracle") priors of a ``tools/synth_scene.py`` scene, as precomputed-prior files.

The quality bench (``--oracle depth,mask,tracks``) trains on them to separate what the
method can do from what the weight-free priors give it: a run with oracle priors is the
same pipeline fed the priors a perfect depth network, segmenter and point tracker would
give (in the formats of :mod:`engine.priors.precomputed`).

* ``depth``: GT z-depth of the train frames, ``.npy [F,H,W]``.
* ``mask``: GT moving-object mask, ``.npy [F,H,W]`` in {0, 1}.
* ``tracks``: GT 2D tracks, ``.npz``: seeds on a regular grid (every ``cell`` px) in
  ``query_frames`` evenly spaced frames, each carried through every frame by the GT
  (static points fixed in the world, moving points by a per-frame rigid fit of the
  object's GT trajectory points; see :func:`engine.bench.priors.gt_tracks`), visible where
  the GT depth agrees.

Frames are the ``left_*`` (train camera) frames in time order, at the scene's native
size, which must equal the training size (the generated scenes are 240 px wide, the
``preview`` width; the precomputed-prior loaders refuse a mismatch, naming the file).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

KINDS = ("depth", "mask", "tracks")


def grid_seed_tracks(F: int, H: int, W: int, cell: float = 6.0, query_frames: int = 4):
    """Query points on a grid in ``query_frames`` evenly spaced frames (a Tracks with only the seed visible)."""
    from ..priors.tracks import Tracks

    ys, xs = np.meshgrid(np.arange(cell / 2, H, cell), np.arange(cell / 2, W, cell), indexing="ij")
    grid = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float32)  # [G, 2]
    qf = np.unique(np.linspace(0, F - 1, query_frames).round().astype(int))
    P = len(grid) * len(qf)
    xy = np.zeros((P, F, 2), np.float32)
    vis = np.zeros((P, F), bool)
    q = np.repeat(qf, len(grid))
    xy[np.arange(P), q] = np.tile(grid, (len(qf), 1))
    vis[np.arange(P), q] = True
    return Tracks(xy=xy, visible=vis, confidence=vis.astype(np.float32), query_frame=q)


def write_oracle_priors(scene_dir, out_dir, kinds=KINDS) -> dict:
    """Write the GT priors named in ``kinds`` under ``out_dir``.

    Returns ``{"depth_path"|"mask_path"|"tracks_path": Path}`` for the kinds written
    (the keys are ``engine train``'s option names without the leading dashes).
    """
    from ..fsutil import atomic_path, atomic_save_npz
    from .priors import gt_tracks, load_scene

    bad = sorted(set(kinds) - set(KINDS))
    if bad:
        raise ValueError(f"unknown oracle prior(s) {bad}; choose from {', '.join(KINDS)}")
    train, _, gt = load_scene(scene_dir)
    order = np.argsort(np.asarray(train.times), kind="stable")  # the priors' frame order
    F, H, W = gt.depth.shape
    out = Path(out_dir)
    paths = {}

    def save_npy(name, arr):
        with atomic_path(out / name) as tmp:  # keeps the .npy suffix, so np.save adds none
            np.save(tmp, arr, allow_pickle=False)
        return out / name

    if "depth" in kinds:
        d = np.where(np.isfinite(gt.depth) & (gt.depth > 0) & (gt.depth < 1e6), gt.depth, 0)
        paths["depth_path"] = save_npy("depth.npy", d[order].astype(np.float32))
    if "mask" in kinds:
        paths["mask_path"] = save_npy("mask.npy", gt.mask[order].astype(np.float32))
    if "tracks" in kinds:
        import dataclasses

        # GT in time order: reorder the GT arrays once, then build tracks on them
        g = dataclasses.replace(gt, K=gt.K[order], w2c=gt.w2c[order], depth=gt.depth[order],
                                mask=gt.mask[order], object_id=gt.object_id[order], points=gt.points[:, order])
        seeds = grid_seed_tracks(F, H, W)
        G = gt_tracks(seeds, g)
        vis = G["visible"] & G["valid"][:, None]
        keep = vis.sum(1) >= 2
        atomic_save_npz(out / "tracks.npz", xy=np.nan_to_num(G["xy"][keep]).astype(np.float32), visible=vis[keep],
                        query_frame=seeds.query_frame[keep].astype(np.int64))
        paths["tracks_path"] = out / "tracks.npz"
    return paths
