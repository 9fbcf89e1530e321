"""Result operators: import, send edits, camera path, clip manifest, PLY export."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bpy

from tests.addon._support import fcurves_of
from engine import bundle as bio
from engine.commands._common import load_camera_path
from engine.io.manifest import load_manifest

from tests.addon.test_build_bundle import FE, FS, make_bundle


@pytest.fixture()
def registered(extension, empty_scene):
    extension.register()
    try:
        yield extension
    finally:
        extension.unregister()


def test_import_operator_and_send_edits(registered, tmp_path):
    bdir = tmp_path / "bundle"
    b = make_bundle(bdir, n=20, g=300)
    bpy.context.scene.motion_splats_result.density = 0.5
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir), density=0.5) == {"FINISHED"}
    col = registered.addon.build.bundle_collection(bpy.context)
    empties = registered.addon.build.node_empties(col)
    assert len(empties) == 20
    mesh = [o for o in col.objects if o.type == "MESH"][0]
    assert len(mesh.data.vertices) == 150

    # no edit: the round trip keeps the splines
    assert bpy.ops.motion_splats.send_edits() == {"FINISHED"}
    n1 = bio.read_nodes(bdir / bio.NODES_FILE)
    np.testing.assert_allclose(n1.key_times, b.nodes.key_times, atol=1e-6)
    np.testing.assert_allclose(n1.pos_keys, b.nodes.pos_keys, atol=1e-5)
    np.testing.assert_allclose(n1.rot_tangents, b.nodes.rot_tangents, rtol=1e-4, atol=1e-4)
    assert n1.pos_tangents_in is None and n1.bind_idx.shape == b.nodes.bind_idx.shape

    # move node 3's z key 2 (value and both handles) up by 0.5, and break node 5's x handle at key 1
    fcs = fcurves_of(empties[3])
    kp = fcs.find("location", index=2).keyframe_points[2]
    for attr in ("co", "handle_left", "handle_right"):
        v = getattr(kp, attr)
        setattr(kp, attr, (v[0], v[1] + 0.5))
    fcs5 = fcurves_of(empties[5])
    kp5 = fcs5.find("location", index=0).keyframe_points[1]
    kp5.handle_right = (kp5.handle_right[0], kp5.handle_right[1] + 0.2)
    assert bpy.ops.motion_splats.send_edits() == {"FINISHED"}
    n2 = bio.read_nodes(bdir / bio.NODES_FILE)
    want = b.nodes.pos_keys.copy()
    want[3, 2, 2] += 0.5
    np.testing.assert_allclose(n2.pos_keys, want, atol=1e-5)
    dt = (b.nodes.key_times[2] - b.nodes.key_times[1]) * (FE - FS) / 3  # handle length in frames
    slope_change = 0.2 / dt * (FE - FS)  # per engine-time unit
    assert n2.pos_tangents_in is not None
    assert n2.pos_tangents[5, 1, 0] == pytest.approx(b.nodes.pos_tangents[5, 1, 0] + slope_change, abs=1e-3)
    assert n2.pos_tangents_in[5, 1, 0] == pytest.approx(b.nodes.pos_tangents[5, 1, 0], abs=1e-4)

    # PLY export writes the canonical Gaussians (all of them, not the density subset)
    out = tmp_path / "g.ply"
    assert bpy.ops.motion_splats.export_ply(filepath=str(out)) == {"FINISHED"}
    g = bio.read_ply(out)
    assert g.count == 300
    np.testing.assert_array_equal(g.means, b.gaussians.means)


def test_import_operator_reports_bad_folder(registered, tmp_path):
    with pytest.raises(RuntimeError, match="scene.json not found|bundle folder not found"):
        bpy.ops.motion_splats.import_bundle(directory=str(tmp_path))


def test_export_camera_path_matches_bundle(registered, tmp_path):
    bdir = tmp_path / "bundle"
    b = make_bundle(bdir, n=10, g=100)
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir), with_rig=False) == {"FINISHED"}
    # the render size follows the result's camera after Set Up Render (building leaves it alone)
    assert bpy.ops.motion_splats.setup_render(ellipsoids=False) == {"FINISHED"}
    out = tmp_path / "path.json"
    assert bpy.ops.motion_splats.export_camera_path(filepath=str(out)) == {"FINISHED"}
    data = json.loads(out.read_text())
    assert data["format"] == "motion-splats-camera-path" and data["version"] == 1
    cams = load_camera_path(out)
    assert [c["frame"] for c in cams] == list(range(FS, FE + 1))
    for c in b.scene["cameras"]:
        f = bio.frame_of_time(b.scene, c["time"])
        got = cams[int(round(f)) - FS]
        assert got["frame"] == pytest.approx(f)
        np.testing.assert_allclose(got["K"], c["K"], atol=1e-3)
        np.testing.assert_allclose(got["w2c"], c["w2c"], atol=1e-4)
        assert (got["width"], got["height"]) == (c["width"], c["height"])


def test_export_clip_manifest(registered, tmp_path):
    bdir = tmp_path / "bundle"
    b = make_bundle(bdir, n=10, g=100)
    assert bpy.ops.motion_splats.import_bundle(directory=str(bdir), with_rig=False) == {"FINISHED"}
    frames = tmp_path / "frames"
    frames.mkdir()
    img = bpy.data.images.new("f", 320, 240)
    for i in range(FS, FE + 1):
        img.filepath_raw = str(frames / f"frame_{i:04d}.png")
        img.file_format = "PNG"
        img.save()
    clip = bpy.data.movieclips.load(str(frames / f"frame_{FS:04d}.png"))
    clip.frame_start = FS
    out = tmp_path / "clip.json"
    assert bpy.ops.motion_splats.export_clip_manifest(filepath=str(out), clip=clip.name) == {"FINISHED"}
    m = json.loads(out.read_text())
    assert (m["frame_start"], m["frame_end"], m["width"], m["height"]) == (FS, FE, 320, 240)
    assert m["frames"][0] == "frames/frame_0001.png" and m["video"] is None
    loaded = load_manifest(out)
    c0 = b.scene["cameras"][0]
    np.testing.assert_allclose(loaded.w2c[0], c0["w2c"], atol=1e-4)
    np.testing.assert_allclose(loaded.K[0], c0["K"], atol=1e-3)


class _Layout:
    """Accepts any UI call (headless bpy has no real UILayout to draw into)."""

    def __getattr__(self, name):
        return lambda *a, **k: _Layout()

    def __setattr__(self, name, value):
        pass


def test_result_panel_draws(registered, tmp_path):
    from types import SimpleNamespace

    panel = registered.panels.build_panel.MOTIONSPLATS_PT_result
    fake = SimpleNamespace(layout=_Layout())
    panel.draw(fake, bpy.context)  # nothing built yet
    make_bundle(tmp_path / "b", n=5, g=50)
    bpy.ops.motion_splats.import_bundle(directory=str(tmp_path / "b"))
    panel.draw(fake, bpy.context)
    assert bpy.ops.motion_splats.set_preview.poll()
    bpy.context.scene.motion_splats_result.preview = "ELLIPSOIDS"
    e0 = bpy.data.objects["MS_node_00000"]
    kp = fcurves_of(e0).find("location").keyframe_points[0]
    kp.co.y += 1.0  # an unsent edit survives the rebuild
    assert bpy.ops.motion_splats.set_preview() == {"FINISHED"}
    kp = fcurves_of(e0).find("location").keyframe_points[0]
    want = bio.read_nodes(tmp_path / "b" / bio.NODES_FILE).pos_keys[0, 0, 0] + 1.0
    assert kp.co.y == pytest.approx(want, abs=1e-5)
    meshes = [o for o in bpy.data.objects if o.type == "MESH"]
    assert len(meshes) == 1 and len(meshes[0].data.vertices) == 150 and meshes[0].modifiers[0].object is not None
    cols = [c for c in bpy.data.collections if "ms_bundle" in c]
    assert len(cols) == 1 and cols[0]["ms_preview"] == "ELLIPSOIDS"
    assert len([o for o in bpy.data.objects if o.type == "EMPTY"]) == 5
