"""Ground-truth ("oracle") priors for the quality bench, on the tiny synthetic scene (bpy, ~5 s)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("bpy")
pytest.importorskip("cv2")

from engine.bench import priors as bench  # noqa: E402
from engine.bench.oracle import write_oracle_priors  # noqa: E402
from engine.priors.precomputed import load_depth, load_mask, load_tracks  # noqa: E402

pytestmark = pytest.mark.slow  # long end-to-end: `pytest -m "not slow"` skips it


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return bench.generate(tmp_path_factory.mktemp("bench_oracle") / "tiny", preset="tiny")


def test_oracle_priors_are_the_ground_truth_in_the_precomputed_formats(scene, tmp_path):
    paths = write_oracle_priors(scene, tmp_path / "oracle")
    assert set(paths) == {"depth_path", "mask_path", "tracks_path"}
    train, _, gt = bench.load_scene(scene)
    order = np.argsort(np.asarray(train.times), kind="stable")
    F, H, W = gt.depth.shape
    # readable by the engine's own loaders, with the clip's shape
    depth = load_depth(paths["depth_path"], (F, H, W))
    mask = load_mask(paths["mask_path"], (F, H, W))
    tracks = load_tracks(paths["tracks_path"], F)
    np.testing.assert_array_equal(depth, gt.depth[order])
    np.testing.assert_array_equal(mask > 0.5, gt.mask[order])
    # each visible track sample sits on one object all along the track, and both the
    # static room and moving objects carry tracks
    vis = tracks.visible
    assert vis.sum(1).min() >= 2 and len(vis) > 100
    u = np.clip(tracks.xy[..., 0].astype(int), 0, W - 1)
    v = np.clip(tracks.xy[..., 1].astype(int), 0, H - 1)
    oid = gt.object_id[order][np.arange(F)[None], v, u]  # [P, F]
    first = oid[np.arange(len(oid)), vis.argmax(1)]
    same = (oid == first[:, None]) | ~vis
    assert same.all(1).mean() > 0.9  # pixel rounding at silhouettes aside
    moving = first > 0
    assert moving.sum() > 10 and (~moving).sum() > 10
    # moving-object tracks really move
    travel = np.nanmax(np.where(vis[..., None], tracks.xy, np.nan), 1) - np.nanmin(
        np.where(vis[..., None], tracks.xy, np.nan), 1)
    assert np.median(np.linalg.norm(travel[moving], axis=-1)) > 2.0


def test_oracle_kinds_are_checked(scene, tmp_path):
    with pytest.raises(ValueError, match="unknown oracle"):
        write_oracle_priors(scene, tmp_path, ["normals"])
    assert set(write_oracle_priors(scene, tmp_path / "d", ["depth"])) == {"depth_path"}


def _rigid_fit(src, dst):
    """Least-squares rotation and translation with ``dst ~ R @ src + t`` (``[M, 3]`` each)."""
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def test_oracle_priors_match_the_scene_files_and_the_rigid_motion(scene, tmp_path):
    """Known answers read straight from the generated scene's files (not through the bench's
    loader): depth and mask are ``gt/depth/*.npy`` and ``gt/mask/*.png`` of the train camera in
    time order, and every track seeded on a rigid moving part (the cube, the arm's links) moves exactly as
    that part does: one part-fixed 3D point, triangulated from the track with the known
    cameras and the part's motion (a rigid fit to all its ground-truth points), reprojects
    onto the track in every frame where it is visible."""
    import cv2

    paths = write_oracle_priors(scene, tmp_path / "oracle")
    cams = np.load(scene / "gt" / "cameras.npz")
    order = np.argsort(cams["times"], kind="stable")
    depth, mask = np.load(paths["depth_path"]), np.load(paths["mask_path"])
    assert depth.shape[0] == mask.shape[0] == len(order) == 12
    for f, i in enumerate(order):
        d = np.load(scene / "gt" / "depth" / f"left_{i:06d}.npy")
        m = cv2.imread(str(scene / "gt" / "mask" / f"left_{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        np.testing.assert_array_equal(depth[f], np.where(np.isfinite(d) & (d > 0) & (d < 1e6), d, 0))
        np.testing.assert_array_equal(mask[f] > 0.5, m)
        assert 0 < m.sum() < m.size

    K, w2c = cams["K"][order], cams["w2c_train"][order]
    traj = np.load(scene / "gt" / "trajectories.npz")
    F = len(order)
    oid = np.stack([cv2.imread(str(scene / "gt" / "object_id" / f"left_{i:06d}.png"), cv2.IMREAD_UNCHANGED)
                    for i in order])
    tr = np.load(paths["tracks_path"])
    xy, vis, q = tr["xy"], tr["visible"], tr["query_frame"]
    H, W = depth.shape[1:]
    seed = xy[np.arange(len(q)), q]
    obj = oid[q, np.clip(seed[:, 1].astype(int), 0, H - 1), np.clip(seed[:, 0].astype(int), 0, W - 1)]
    resid, travel = [], []
    for o in (1, 2, 3, 4):  # the rigid cube and the arm's three rigid links (the flag bends)
        pts = traj["points"][traj["object_id"] == o][:, order]  # [M, F, 3]
        motion = [_rigid_fit(pts[:, 0], pts[:, f]) for f in range(F)]  # frame 0 -> frame f
        P = [K[f] @ w2c[f, :3] @ np.vstack([np.c_[R, t], [0, 0, 0, 1]]) for f, (R, t) in enumerate(motion)]
        for p in np.flatnonzero((obj == o) & (vis.sum(1) >= 3)):
            fs = np.flatnonzero(vis[p])
            A = np.concatenate([[xy[p, f, 0] * P[f][2] - P[f][0], xy[p, f, 1] * P[f][2] - P[f][1]] for f in fs])
            X = np.linalg.svd(A)[2][-1]
            uv = np.stack([P[f] @ X for f in fs])
            resid.append(np.linalg.norm(uv[:, :2] / uv[:, 2:] - xy[p, fs], axis=1).max())
            travel.append(np.linalg.norm(xy[p, fs].max(0) - xy[p, fs].min(0)))
    resid, travel = np.array(resid), np.array(travel)
    assert len(resid) >= 10 and np.median(travel) > 2.0, (len(resid), travel)  # the parts move in the image
    assert resid.max() < 0.01, (len(resid), resid.max())  # measured 1.5e-5 px
