"""Camera-model selection for the solve: evidence for translation, SfM health, one announced line.

Two models compete (see :func:`engine.io.solve.solve_cameras`):

* ``sfm`` — a translating camera from COLMAP (incremental, or global when incremental cannot
  initialise);
* ``rotation`` / ``static`` — the fixed-centre model (:func:`engine.io.solve_fixed.fixed_centre_cameras`).

The simpler fixed-centre model wins when the footage shows no translation: a homography leaves the
static matches (moving regions masked) within ``max(min_parallax_px, floor_ratio x noise floor)`` even
between frames far apart (:func:`translation_evidence`). SfM must otherwise also be *plausible*
(:func:`sfm_problems`): enough frames registered, bundle adjustment converged to a small reprojection
error with a minimum of sparse points, a baseline between neighbouring frames that is small against the
scene depth (scale), and a camera path without jumps. A rejected solve never
changes the result silently: the chosen model and why go into one log line and ``meta['solve']``.
"""

from __future__ import annotations

import numpy as np

from ..geometry.poses import camera_centres

MIN_PARALLAX_PX = 0.1  # px at solve resolution (long side 320): below it no gap shows translation
FLOOR_RATIO = 1.25     # long-gap parallax must exceed the gap-1 floor (noise, blur) by this factor
MAX_REPROJ_PX = 1.5    # mean SfM reprojection error (px at solve resolution) of a healthy bundle adjustment
MIN_POINTS = 10        # sparse points a healthy SfM model keeps
JUMP_RATIO = 8.0       # a step between consecutive registered frames this many times the median step ...
JUMP_DEPTH = 0.05      # ... and longer than this fraction of the median scene depth is a jump
MAX_STEP_DEPTH = 0.5   # median step between consecutive solved frames, in median scene depths


def translation_evidence(ev: dict, min_parallax_px: float = MIN_PARALLAX_PX, floor_ratio: float = FLOOR_RATIO):
    """Does the footage show translation? ``(bool, sentence)`` from :func:`parallax_evidence` output."""
    par, floor = ev.get("parallax_px", np.nan), ev.get("floor_px", np.nan)
    if not np.isfinite(par):
        return True, "too few static matches to measure parallax"
    gap = max((g for g in ev["gaps"] if g > 1), default=1)
    limit = max(min_parallax_px, floor_ratio * floor if np.isfinite(floor) else 0.0)
    fl = f"; noise floor {floor:.2f} px between neighbours" if np.isfinite(floor) else ""
    words = (f"a homography leaves {par:.2f} px of parallax on the static matches up to {gap} frames apart "
             f"(limit {limit:.2f} px{fl})")
    return bool(par >= limit), words


def sfm_problems(cams: dict, need: int, max_reproj_px: float = MAX_REPROJ_PX, min_points: int = MIN_POINTS,
                 jump_ratio: float = JUMP_RATIO, jump_depth: float = JUMP_DEPTH,
                 max_step_depth: float = MAX_STEP_DEPTH) -> list[str]:
    """Why an SfM solution is implausible (empty list: healthy).

    Parameters
    ----------
    cams : dict from :func:`engine.io.solve_colmap.sfm_cameras` (``registered [F]``, ``w2c [F,4,4]``,
        ``points [P,3]``, ``mean_reproj_error``)
    need : int  frames that must register
    """
    out = []
    reg = cams["registered"]
    nreg, F = int(reg.sum()), len(reg)
    if nreg < need:
        out.append(f"registered only {nreg} of {F} frames (need {need})")
        return out
    err = cams["mean_reproj_error"]
    if not np.isfinite(err) or err > max_reproj_px:
        out.append(f"bundle adjustment left a mean reprojection error of {err:.2f} px (limit {max_reproj_px})")
    if len(cams["points"]) < min_points:
        out.append(f"only {len(cams['points'])} sparse points survived (need {min_points})")
    w2c = cams["w2c"][reg]
    C = camera_centres(w2c)
    step = np.linalg.norm(np.diff(C, axis=0), axis=1)
    depth = median_depth(w2c, cams["points"])
    if len(step) >= 3 and np.isfinite(depth):
        k = int(np.argmax(step))
        med = float(np.median(step))
        if med > max_step_depth * depth:  # frames sampled from one video: neighbours share most of the view
            out.append(f"the camera moves {med / depth:.2f} scene depths between neighbouring frames "
                       f"(limit {max_step_depth})")
        if step[k] > jump_ratio * max(med, 1e-12) and step[k] > jump_depth * depth:
            idx = np.flatnonzero(reg)
            out.append(f"the camera jumps {step[k] / depth:.2f} scene depths between frames {idx[k]} and {idx[k + 1]} "
                       f"({step[k] / max(med, 1e-12):.0f}x its median step)")
    return out


def median_depth(w2c, points) -> float:
    """Median depth (camera z) of ``points [P,3]`` seen from cameras ``w2c [F,4,4]`` (in front only)."""
    if len(points) == 0:
        return float("nan")
    z = np.einsum("fj,pj->fp", w2c[:, 2, :3], points) + w2c[:, 2, 3][:, None]
    z = z[z > 0]
    return float(np.median(z)) if len(z) else float("nan")


def sfm_line(info: dict, mapper: str, evidence: str) -> str:
    """The one line announcing an SfM (translating) solve."""
    F = len(info["registered"])
    return (f"camera solve: translating camera ({mapper} SfM) -- {info['num_registered']}/{F} frames registered, "
            f"mean reprojection error {info['mean_reproj_error']:.2f} px, {info['num_points']} points; "
            f"chosen because {evidence}.")


def fixed_line(info: dict, why: str, note: str) -> str:
    """The one line announcing the fixed-centre (rotation-only or static) model, with its caveats."""
    kind = "static camera" if info["model"] == "static" else "rotation-only camera"
    return f"camera solve: {kind} (fixed centre) -- chosen because {why.rstrip('.')}. {note}"


def summary(info: dict) -> dict:
    """JSON-ready camera-solve record for ``scene.json`` (``camera_solve``): model, why, quality."""
    keep = ("model", "mapper", "reason", "num_registered", "mean_reproj_error", "num_points", "fov_deg",
            "max_rotation_deg", "parallax_px", "parallax_floor_px", "rejected", "seed")
    out = {k: info[k] for k in keep if k in info}
    out["num_frames"] = int(len(info["registered"]))
    for k, v in list(out.items()):
        if isinstance(v, (np.floating, np.integer)):
            out[k] = v.item()
    return out
