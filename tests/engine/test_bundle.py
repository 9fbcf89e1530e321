"""Result bundle I/O: PLY round trip, node validation, scene validation."""

import json

import numpy as np
import pytest

from engine import bundle as B
from engine.errors import InputError


def _gaussians(g=50, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    m = (degree + 1) ** 2
    return B.GaussianArrays(means=rng.normal(size=(g, 3)), quats=rng.normal(size=(g, 4)),
                            log_scales=rng.normal(size=(g, 3)) - 3, opacity_logits=rng.normal(size=g),
                            sh=rng.normal(size=(g, m, 3)))


def _nodes(n=7, k=5, g=50, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, k, 4))
    return B.NodeArrays(centers=rng.normal(size=(n, 3)), radii=rng.uniform(0.1, 1, n),
                        key_times=np.linspace(0, 1, k), pos_keys=rng.normal(size=(n, k, 3)),
                        pos_tangents=rng.normal(size=(n, k, 3)), rot_keys=q / np.linalg.norm(q, axis=-1, keepdims=True),
                        rot_tangents=rng.normal(size=(n, k, 4)), p_dyn=rng.uniform(size=n),
                        bind_idx=rng.integers(0, n, size=(g, 4)), bind_w=np.full((g, 4), 0.25),
                        graph_idx=rng.integers(0, n, size=(n, 3)))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip_is_exact(tmp_path, degree):
    g = _gaussians(degree=degree)
    B.write_ply(tmp_path / "g.ply", g)
    back = B.read_ply(tmp_path / "g.ply")
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(g, name))
    assert back.sh_degree == degree


def test_ply_header_is_standard_3dgs(tmp_path):
    B.write_ply(tmp_path / "g.ply", _gaussians(g=3, degree=3))
    header = (tmp_path / "g.ply").read_bytes().split(b"end_header")[0].decode()
    props = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert props[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def test_ply_rest_coefficients_are_channel_major(tmp_path):
    g = _gaussians(g=1, degree=1)
    g.sh[:] = np.arange(12, dtype=np.float32).reshape(1, 4, 3)  # sh[0, j, c] = 3j + c
    B.write_ply(tmp_path / "g.ply", g)
    raw = (tmp_path / "g.ply").read_bytes()
    body = np.frombuffer(raw[raw.index(b"end_header\n") + 11:], "<f4")
    # f_rest_0..2 are the red channel of coefficients 1..3: 3, 6, 9.
    np.testing.assert_array_equal(body[9:12], [3, 6, 9])


def test_bad_ply_names_the_file(tmp_path):
    p = tmp_path / "broken.ply"
    p.write_bytes(b"not a ply at all")
    with pytest.raises(InputError, match="broken.ply"):
        B.read_ply(p)
    B.write_ply(p, _gaussians())
    p.write_bytes(p.read_bytes()[:-40])
    with pytest.raises(InputError, match="truncated"):
        B.read_ply(p)


def test_bundle_round_trip(tmp_path):
    scene = B.new_scene(1, 48, 24.0, cameras=[{"w2c": np.eye(4), "K": np.eye(3), "width": 8, "height": 6,
                                                 "time": 0.5}], config={"preset": "preview"})
    B.save_bundle(tmp_path / "b", scene, _nodes(), _gaussians())
    bundle = B.load_bundle(tmp_path / "b")
    assert bundle.scene["config"] == {"preset": "preview"}
    assert bundle.nodes.count == 7 and bundle.gaussians.count == 50
    np.testing.assert_allclose(B.frame_of_time(bundle.scene, [0, 1]), [1, 48])
    np.testing.assert_allclose(B.time_of_frame(bundle.scene, 24.5), 0.5)


@pytest.mark.parametrize("mutate,msg", [
    (lambda d: d.pop("radii"), "lacks"),
    (lambda d: d.__setitem__("pos_keys", d["pos_keys"][:, :2]), "pos_keys"),
    (lambda d: d.__setitem__("key_times", d["key_times"][::-1].copy()), "increasing"),
    (lambda d: d.__setitem__("centers", np.full((7, 3), np.nan)), "finite"),
    (lambda d: d.__setitem__("bind_idx", d["bind_idx"] + 100), "bind_idx"),
    (lambda d: d.__setitem__("key_mask", np.ones(d["pos_keys"].shape[:2], np.float32)), "key_mask must be bool"),
    (lambda d: d.__setitem__("key_mask", np.ones((7, 1), bool)), "key_mask must be bool"),
    (lambda d: d.__setitem__("key_mask", np.zeros(d["pos_keys"].shape[:2], bool)), "without any key"),
])
def test_node_validation(tmp_path, mutate, msg):
    arrays = _nodes().to_dict()
    mutate(arrays)
    np.savez(tmp_path / "nodes.npz", **arrays)
    with pytest.raises(InputError, match=msg):
        B.read_nodes(tmp_path / "nodes.npz")


def test_key_mask_round_trips_and_defaults_to_all_keys(tmp_path):
    nodes = _nodes()
    assert nodes.key_mask is None and nodes.own_keys().all() and nodes.own_keys().shape == nodes.pos_keys.shape[:2]
    mask = np.ones(nodes.pos_keys.shape[:2], bool)
    mask[1:, 1] = False
    B.write_nodes(tmp_path / "nodes.npz", B.NodeArrays.from_dict({**nodes.to_dict(), "key_mask": mask}))
    back = B.read_nodes(tmp_path / "nodes.npz")
    assert back.key_mask.dtype == np.bool_ and np.array_equal(back.key_mask, mask)
    assert np.array_equal(back.own_keys(), mask)


def test_pickled_node_file_is_refused(tmp_path):
    arrays = _nodes().to_dict()
    arrays["centers"] = np.array([object()] * 3, dtype=object)
    np.savez(tmp_path / "nodes.npz", **arrays)
    with pytest.raises(InputError, match="nodes.npz"):
        B.read_nodes(tmp_path / "nodes.npz")


@pytest.mark.parametrize("scene,msg", [
    ("[]", "JSON object"),
    ('{"format": "other"}', "format"),
    ('{"format": "motion-splats-bundle", "version": 99}', "version"),
    ('{"format": "motion-splats-bundle", "version": 1, "time": {"frame_start": 1}}', "time"),
    ('{"format": "motion-splats-bundle", "version": 1, "time": {"frame_start": 1, "frame_end": 9, "fps": 24},'
     ' "cameras": [{"w2c": [[1]], "K": [[1,0,0],[0,1,0],[0,0,1]], "width": 4, "height": 4, "time": 0}]}', "w2c"),
    ("{not json", "invalid JSON"),
])
def test_scene_validation_names_file(tmp_path, scene, msg):
    p = tmp_path / "scene.json"
    p.write_text(scene)
    with pytest.raises(InputError, match=msg) as info:
        B.read_scene(p)
    assert "scene.json" in str(info.value)


def test_clear_run_outputs_removes_only_what_a_run_derives(tmp_path):
    out = tmp_path / "out"
    (out / "report").mkdir(parents=True)
    (out / "report" / "report.html").write_text("old")
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / "checkpoint.pt").write_bytes(b"old")
    (out / "eval.json").write_text("{}")
    (out / "cache").mkdir()
    (out / "cache" / "depth.npz").write_bytes(b"keep")
    (out / "notes.txt").write_text("the user's")
    assert sorted(B.clear_run_outputs(out)) == ["checkpoints", "eval.json", "report"]
    assert sorted(p.name for p in out.iterdir()) == ["cache", "notes.txt"]
    assert B.clear_run_outputs(out) == []


def test_output_dir_is_never_clobbered(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "scene.json").write_text(json.dumps({}))
    with pytest.raises(InputError, match="--overwrite"):
        B.check_output_dir(tmp_path / "out")
    assert B.check_output_dir(tmp_path / "out", resume=True) == tmp_path / "out"
    assert B.check_output_dir(tmp_path / "new") == tmp_path / "new"
