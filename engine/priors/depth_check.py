"""Does a depth model agree with the clip's own geometry? A check before its depth is used.

A monocular depth network is aligned to each frame's anchors (triangulated static tracks,
:func:`engine.priors.depth.anchors_from_tracks`) by a scale and shift. That only helps when
the network's depth *explains* the anchors: a network that does not read the scene (PyDNet
on the generated checkered rooms: rank correlation with the true depth -0.8 ... +0.4 per
frame) is fitted with a near-zero or negative scale, and its aligned depth is a flat or
inverted copy of the room in which moving objects have a made-up depth
(docs/benchmarks.md, *A depth model the scene contradicts*).

:func:`model_agreement` scores it against the simplest alternative: per frame, fit the
model (robust affine, as the alignment does) on every other anchor and measure the median
relative depth error on the rest, and the same for a flat depth (the fit half's median).
The ratio of the two is well below 1 when the model knows something about the static scene
that a constant does not (noise fitted this way is a flat depth: about 1). :func:`model_is_usable` decides from the median ratio over the checked
frames; a clip without enough anchors (a camera that does not translate) cannot be checked
and keeps the model.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .depth import aligned_depth, at_anchors, fit_alignment

#: a model is used when its held-out anchor error is below this fraction of a flat depth's. Not
#: 1.0: a model whose output is noise is fitted with a scale near 0, which leaves its shift, a
#: flat depth, and scores 0.98-1.0 (tests/engine/test_priors_depth_check.py)
MAX_ERROR_RATIO = 0.9
#: frames need this many anchors to be checked, and a clip this many checked frames
MIN_ANCHORS = 20
MIN_FRAMES = 3


def model_agreement(pred: np.ndarray, kind: str, anchors: list, min_anchors: int = MIN_ANCHORS,
                    seed: int = 0) -> dict:
    """How much better than a flat depth a model's raw prediction explains each frame's anchors.

    Parameters
    ----------
    pred : float [F, H, W] raw model output at the frames' size
        (:func:`engine.priors.depth.model_predictions`).
    kind : 'inverse' (larger = nearer) or 'depth' (larger = farther): the alignment is fitted
        in that kind of value, as :func:`engine.priors.depth.estimate_depth` does.
    anchors : F arrays [A, 3] (u, v, depth) or None.
    seed : the split of each frame's anchors into fit and test halves.

    Returns
    -------
    dict: ``frames`` (checked: at least ``min_anchors`` anchors), ``ratio`` (median over them of
    the model's held-out median relative depth error over a flat depth's; None when no frame
    was checked), ``error`` and ``flat_error`` (the medians of each), ``inverted`` (fraction of
    checked frames whose fitted scale says nearer where the model says farther).
    """
    rng = np.random.default_rng(seed)
    err, flat, inverted = [], [], []
    for f, a in enumerate(anchors):
        if a is None or len(a) < min_anchors:
            continue
        a = np.asarray(a, np.float64)
        a = a[np.isfinite(a).all(1) & (a[:, 2] > 0)]
        if len(a) < min_anchors:
            continue
        p = at_anchors(pred[f], a).astype(np.float64)
        order = rng.permutation(len(a))
        fit, test = order[::2], order[1::2]
        s, t = fit_alignment(p[fit], a[fit, 2], kind)  # as estimate_depth aligns the model
        z = aligned_depth(p[test], s, t, kind)
        truth = a[test, 2]
        err.append(np.median(np.abs(z - truth) / truth))
        flat.append(np.median(np.abs(np.median(a[fit, 2]) - truth) / truth))
        inverted.append(s <= 0)
    if not err:
        return {"frames": 0, "ratio": None, "error": None, "flat_error": None, "inverted": None}
    err, flat = np.asarray(err), np.asarray(flat)
    return {"frames": int(len(err)), "ratio": float(np.median(err / np.maximum(flat, 1e-12))),
            "error": float(np.median(err)), "flat_error": float(np.median(flat)),
            "inverted": float(np.mean(inverted))}


def model_is_usable(agreement: dict, max_ratio: float = MAX_ERROR_RATIO, min_frames: int = MIN_FRAMES) -> bool:
    """True unless enough frames were checked and the model's error at their anchors is not below
    ``max_ratio`` times a flat depth's (:func:`model_agreement`)."""
    if agreement.get("frames", 0) < min_frames or agreement.get("ratio") is None:
        return True
    return agreement["ratio"] < max_ratio


def describe(agreement: dict) -> str:
    """One line for the log: what was measured."""
    if agreement.get("ratio") is None or agreement.get("frames", 0) < MIN_FRAMES:
        return (f"not checked: {agreement.get('frames', 0)} frame(s) with {MIN_ANCHORS}+ triangulated static points "
                "(a camera that does not translate gives none)")
    line = (f"median depth error {agreement['error']:.1%} at triangulated static points it was not fitted to, "
            f"against {agreement['flat_error']:.1%} for a flat depth (ratio {agreement['ratio']:.2f}, "
            f"{agreement['frames']} frames; scale inverted in {agreement['inverted']:.0%})")
    if agreement["inverted"] > 0.5:  # nearer where the model says farther, in most frames
        line += "; is its output the other kind? (--depth-output inverse | depth)"
    return line


def without_depth_model(prior_config):
    """``prior_config`` (a :class:`~engine.priors.cache.PriorConfig`) with its depth model set
    aside for the weight-free depth."""
    return dataclasses.replace(prior_config, depth_backend="sparse", depth_model=None, depth_output=None,
                               depth_sidecar=None)
