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
