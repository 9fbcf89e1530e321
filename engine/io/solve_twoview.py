"""Two-view evidence for the camera solve: LK matches, homography vs epipolar fits, parallax.

Everything here works on gray frames at solve resolution (long side ``max_size``, 320 px by default)
and is deterministic: LK tracking and OpenCV's RANSAC (seeded with ``cv2.setRNGSeed``) have no
thread-dependent randomness.

* :func:`pair_geometry` — per frame pair: matches, homography, how much of the matches it explains,
  the residual parallax, and a rough relative pose (essential matrix).
* :func:`camera_free_masks` — dynamic masks without cameras (the motion prior's Sampson path on
  rough poses chained from consecutive-frame essential matrices).
* :func:`parallax_evidence` — what the solve's model selection reads: the median parallax that a
  homography leaves on the static (homography-inlier) matches at short and long frame gaps.
"""

from __future__ import annotations

import numpy as np

INLIER_PX = 1.0  # RANSAC threshold (px at solve resolution) of the homography / fundamental fits


def track_pair(a, b, max_corners=600):
    """Sparse LK matches from gray ``a [h,w]`` to ``b [h,w]`` (forward-backward checked).

    Returns
    -------
    p, q : ndarray [N,2] float32
        Matched points in continuous pixel coordinates (pixel centres at ``+0.5``).
    """
    import cv2

    p = cv2.goodFeaturesToTrack(a, max_corners, 0.01, 7, blockSize=7)
    if p is None or len(p) < 8:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    lk = dict(winSize=(21, 21), maxLevel=4, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p, None, **lk)
    r, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q, None, **lk)
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((r - p)[:, 0], axis=1) < 0.5)
    return p[ok, 0] + 0.5, q[ok, 0] + 0.5


def _pair_fit(p, q, K, thresh):
    """Homography / fundamental / essential fits of one pair's matches ``p, q [N,2]``."""
    import cv2

    d = dict(H=None, h_inliers=0.0, parallax=np.inf, rel=np.eye(4))
    H, _ = cv2.findHomography(p, q, cv2.RANSAC, thresh)
    Fm, mf = cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, thresh, 0.999)
    if H is not None and Fm is not None and mf is not None and Fm.shape == (3, 3):
        inl = mf[:, 0] > 0
        r = homography_residual(H, p[inl], q[inl])
        d.update(H=H, h_inliers=float((r < thresh).mean()) if len(r) else 0.0,
                 parallax=float(np.median(r)) if len(r) else np.inf)
    E, me = cv2.findEssentialMat(p, q, K, cv2.RANSAC, 0.999, thresh)
    if E is not None and E.shape == (3, 3):
        _, R, t, _ = cv2.recoverPose(E, p, q, K, mask=me)
        d["rel"] = np.eye(4)
        d["rel"][:3, :3], d["rel"][:3, 3] = R, t[:, 0] / max(np.linalg.norm(t), 1e-12)
    return d


def homography_residual(H, p, q) -> np.ndarray:
    """Transfer distance ``|H p − q|`` (px) of matches ``p, q [N,2]`` -> ``[N]``."""
    x = np.c_[p, np.ones(len(p))] @ np.asarray(H, np.float64).T
    return np.linalg.norm(x[:, :2] / x[:, 2:3] - q, axis=1)


def pair_geometry(gray, K, gaps=(1,), thresh=INLIER_PX, rng_seed=0):
    """Two-view geometry between frames ``f`` and ``f + g`` of a gray sequence (LK matches).

    Parameters
    ----------
    gray : ndarray [F,h,w] uint8
    K : ndarray [3,3]  intrinsics at this resolution (a guess is fine)
    gaps : frame gaps to measure
    thresh : RANSAC threshold in px

    Returns
    -------
    list of dict per pair: ``i``, ``j``, ``n`` matches, ``p``/``q`` [n,2] the matches, ``H`` [3,3] or
    None, ``h_inliers`` fraction of the fundamental-matrix inliers that the homography explains (within
    ``thresh``), ``parallax`` median distance (px) of the F-inliers to the homography, ``rel`` [4,4]
    relative pose from the essential matrix (unit translation; identity when it cannot be estimated).
    """
    import cv2

    cv2.setRNGSeed(int(rng_seed))
    out = []
    for g in gaps:
        for i in range(0, len(gray) - g):
            p, q = track_pair(gray[i], gray[i + g])
            d = dict(i=i, j=i + g, n=len(p), p=p, q=q, H=None, h_inliers=0.0, parallax=np.inf, rel=np.eye(4))
            if len(p) >= 15:
                d.update(_pair_fit(p, q, K, thresh))
            out.append(d)
    return out


def camera_free_masks(small_frames, K_small, pairs):
    """Dynamic masks without cameras: the motion prior's depth-free (Sampson) path on rough poses.

    Consecutive-frame relative poses (essential matrix of LK matches, unit translation: the Sampson
    distance does not depend on the translation's length) are chained into ``w2c`` and handed to
    :func:`engine.priors.motion.motion_mask` with ``depth=None``.

    Parameters
    ----------
    small_frames : ndarray [F,h,w,3] uint8
    K_small : ndarray [3,3]
    pairs : list of dict from :func:`pair_geometry` (gap-1 pairs are used)

    Returns
    -------
    ndarray [F,h,w] float32, 1 = dynamic
    """
    from ..priors.motion import motion_mask

    F = len(small_frames)
    w2c = np.tile(np.eye(4), (F, 1, 1))
    rel = {d["i"]: d["rel"] for d in pairs if d["j"] == d["i"] + 1}
    for f in range(1, F):
        w2c[f] = rel.get(f - 1, np.eye(4)) @ w2c[f - 1]
    K = np.repeat(K_small[None], F, 0)
    return motion_mask(np.asarray(small_frames), K, w2c, depth=None, max_width=max(small_frames.shape[1:3]))


def evidence_gaps(num_frames: int) -> tuple[int, ...]:
    """Frame gaps the parallax evidence is measured at: 1 (the noise floor) and up to half the clip."""
    return tuple(sorted({g for g in (1, num_frames // 8, num_frames // 4, num_frames // 2) if g >= 1}))


def parallax_evidence(gray, masks=None, gaps=None, thresh=INLIER_PX, max_pairs=12, rng_seed=0) -> dict:
    """How much parallax a homography leaves on the static matches, per frame gap.

    For each gap ``g`` at most ``max_pairs`` evenly spaced pairs ``(i, i + g)`` are matched (LK);
    matches that start in a dynamic region (``masks[i] ≥ 0.5``) are dropped, a homography is fitted
    (RANSAC, ``thresh`` px) and its inliers — the static majority — give the pair's parallax, the
    median transfer distance. A camera that only rotates leaves the noise floor at every gap; a
    translating camera's parallax grows with the baseline, so the long gaps carry the evidence.

    Parameters
    ----------
    gray : ndarray [F,h,w] uint8  frames at solve resolution
    masks : ndarray [F,h,w] float, optional  1 = dynamic
    gaps : frame gaps (default :func:`evidence_gaps`)

    Returns
    -------
    dict with ``gaps`` {gap: {"pairs", "parallax_px", "h_inliers"}} (medians over the pairs; pairs
    with fewer than 15 static matches are skipped), ``floor_px`` (gap 1: mostly tracking noise and
    blur), ``parallax_px`` (the largest per-gap median over gaps > 1: the clip's evidence for
    translation) and ``h_inliers`` (the smallest per-gap median inlier fraction over those gaps).
    """
    import cv2

    cv2.setRNGSeed(int(rng_seed))
    F = len(gray)
    per = {}
    for g in gaps or evidence_gaps(F):
        if g >= F:
            continue
        starts = np.unique(np.round(np.linspace(0, F - 1 - g, min(max_pairs, F - g))).astype(int))
        par, hin = [], []
        for i in starts:
            p, q = track_pair(gray[i], gray[i + g])
            if masks is not None and len(p):
                m = np.asarray(masks[i])
                r = np.clip(p[:, 1].astype(int), 0, m.shape[0] - 1)
                c = np.clip(p[:, 0].astype(int), 0, m.shape[1] - 1)
                p, q = p[m[r, c] < 0.5], q[m[r, c] < 0.5]
            if len(p) < 15:
                continue
            H, _ = cv2.findHomography(p, q, cv2.RANSAC, thresh)
            if H is None:
                continue
            r = homography_residual(H, p, q)
            inl = r < thresh
            if inl.sum() < 8:
                continue
            par.append(float(np.median(r[inl])))
            hin.append(float(inl.mean()))
        if par:
            per[int(g)] = {"pairs": len(par), "parallax_px": float(np.median(par)), "h_inliers": float(np.median(hin))}
    long = [v for g, v in per.items() if g > 1] or list(per.values())
    return {"gaps": per,
            "floor_px": per[1]["parallax_px"] if 1 in per else float("nan"),
            "parallax_px": max((v["parallax_px"] for v in long), default=float("nan")),
            "h_inliers": min((v["h_inliers"] for v in long), default=float("nan"))}


def parallax_summary(pairs) -> str:
    """One sentence on how well homographies explain consecutive-frame matches (low-parallax evidence)."""
    ok = [d for d in (pairs or []) if d["H"] is not None]
    if not ok:
        return "Too few matches between consecutive frames to measure parallax."
    hin = float(np.median([d["h_inliers"] for d in ok]))
    par = float(np.median([d["parallax"] for d in ok]))
    return (f"A homography explains {100 * hin:.0f}% of the matches between consecutive frames "
            f"(median parallax {par:.2f} px at solve resolution).")
