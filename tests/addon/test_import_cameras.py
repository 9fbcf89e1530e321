"""Footage import and camera import (COLMAP text/binary models, Blender camera solves).

Projections of known 3D points with the imported cameras — both the engine K/w2c and
the animated Blender camera sampled back through addon.exporters — must match the
source model's projections within 0.5 px. Here the tracking conversion is tested on
arrays plus a real Movie Clip's tracking camera; ``test_tracking_solve.py`` runs a real
headless camera solve (markers from known 3D points, ``clip.solve_camera``) and imports it."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from tests.addon._support import bpy, registered, clean_jobs, user_dir, look_at_w2c  # noqa: F401

W, H = 160, 120


def _matrix_to_qvec(R):
    """Rotation -> (w, x, y, z) in float64 (mathutils is float32)."""
    w = np.sqrt(max(1.0 + np.trace(R), 1e-12)) / 2
    if w > 0.1:
        return [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    v = np.zeros(3)
    v[i] = np.sqrt(1 + R[i, i] - R[j, j] - R[k, k]) / 2
    v[j] = (R[j, i] + R[i, j]) / (4 * v[i])
    v[k] = (R[k, i] + R[i, k]) / (4 * v[i])
    return [(R[k, j] - R[j, k]) / (4 * v[i]), *v]


def _poses(n=5):
    rng = np.random.default_rng(3)
    return [look_at_w2c([4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.3 * rng.standard_normal()])
            for a in np.linspace(0.2, 1.4, n)]


def _points():
    return np.random.default_rng(0).uniform(-0.8, 0.8, (50, 3))


def _write_colmap_text(folder, K, w2cs):
    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text(
        "# Camera list\n# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {W} {H} {K[0, 0]!r} {K[1, 1]!r} {K[0, 2]!r} {K[1, 2]!r}\n", encoding="utf-8")
    lines = ["# Image list", "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    order = list(range(len(w2cs)))[::-1]  # written out of order: the importer sorts by name
    for i in order:
        q = _matrix_to_qvec(w2cs[i][:3, :3])
        t = w2cs[i][:3, 3]
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 "
                     f"frame_{i:04d}.png")
        lines.append("" if i % 2 else "10.5 20.25 -1 30.0 40.0 7")
    (folder / "images.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")


def _write_colmap_binary(folder, K, w2cs):
    folder.mkdir(parents=True)
    with open(folder / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", 1))
        fh.write(struct.pack("<iiQQ", 1, 1, W, H))
        fh.write(struct.pack("<4d", K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    with open(folder / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(w2cs)))
        for i, w2c in enumerate(w2cs):
            fh.write(struct.pack("<i7di", i + 1, *_matrix_to_qvec(w2c[:3, :3]), *w2c[:3, 3], 1))
            fh.write(f"frame_{i:04d}.png".encode() + b"\x00")
            fh.write(struct.pack("<Q", 2))
            fh.write(struct.pack("<ddqddq", 1.0, 2.0, -1, 3.0, 4.0, 5))


def _K():
    return np.array([[150.0, 0, 83.2], [0, 156.0, 57.9], [0, 0, 1]])


def _check_scene_camera(extension, scene, cam_obj, frames, K, w2cs, pts):
    cams = extension.addon.exporters.sample_camera(scene, cam_obj, frames)
    proj = extension.addon.cameras.project
    worst = 0.0
    for c, w2c in zip(cams, w2cs):
        assert (c["width"], c["height"]) == (W, H)
        worst = max(worst, np.abs(proj(c["K"], c["w2c"], pts) - proj(K, w2c, pts)).max())
    assert worst < 0.5, worst
    return worst


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_colmap_import_projects_like_source(extension, registered, tmp_path, kind):
    K, w2cs, pts = _K(), _poses(), _points()
    model = tmp_path / "sparse" / "0"
    (_write_colmap_text if kind == "text" else _write_colmap_binary)(model, K, w2cs)
    cams = extension.addon.cameras.read_colmap_cameras(tmp_path)
    assert cams["names"] == [f"frame_{i:04d}.png" for i in range(len(w2cs))]
    assert (cams["width"], cams["height"]) == (W, H) and cams["dist"] is None
    proj = extension.addon.cameras.project
    for Ki, w2c_i, w2c in zip(cams["K"], cams["w2c"], w2cs):
        assert np.abs(proj(Ki, w2c_i, pts) - proj(K, w2c, pts)).max() < 1e-6
    scene = bpy.context.scene
    scene.frame_start = 5
    assert bpy.ops.motion_splats.import_colmap_camera(directory=str(tmp_path)) == {"FINISHED"}
    cam = scene.camera
    assert cam is not None and cam.name.startswith("COLMAPCamera")
    assert scene.frame_end == 5 + len(w2cs) - 1
    _check_scene_camera(extension, scene, cam, range(5, 5 + len(w2cs)), K, w2cs, pts)


def test_colmap_errors_are_reports(registered, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(RuntimeError, match="no COLMAP model"):
        bpy.ops.motion_splats.import_colmap_camera(directory=str(tmp_path / "empty"))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "cameras.txt").write_text("1 FOV 10 10 1 2 3 4\n")
    (bad / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n")
    with pytest.raises(RuntimeError, match="FOV is not supported"):
        bpy.ops.motion_splats.import_colmap_camera(directory=str(bad))


def _blender_tracking_projection(M, f, pp, pixel_aspect, pts):
    """Projection as Blender's camera solver models it: camera space with y up / -z forward,
    principal point in pixels from the bottom-left corner."""
    X = (np.linalg.inv(M) @ np.c_[pts, np.ones(len(pts))].T).T[:, :3]
    u = f * X[:, 0] / -X[:, 2] + pp[0]
    v_up = f * pixel_aspect * X[:, 1] / -X[:, 2] + pp[1]
    return np.c_[u, H - v_up]


def test_tracking_reconstruction_arrays(extension, registered):
    cams_mod = extension.addon.cameras
    w2cs, pts = _poses(4), _points()
    f, pp, aspect = 140.0, (81.5, 63.25), 1.0
    mats = [cams_mod.blender_matrix_from_w2c(w) @ np.diag([1, 1, 1, 1.0]) for w in w2cs]
    frames = [7, 4, 5, 6]  # unordered, as a solve may list them
    mats = [mats[3], mats[0], mats[1], mats[2]]
    K = cams_mod.tracking_K(f, pp, W, H, aspect)
    out = cams_mod.tracking_cameras(mats, frames, K)
    assert out["frames"] == [4, 5, 6, 7]
    for w2c, M in zip(out["w2c"], [mats[1], mats[2], mats[3], mats[0]]):
        ref = _blender_tracking_projection(M, f, pp, aspect, pts)
        assert np.abs(cams_mod.project(K, w2c, pts) - ref).max() < 1e-6
    scene = bpy.context.scene
    obj = cams_mod.build_animated_camera(scene, "Tracked", K, W, H, out["w2c"], out["frames"])
    assert scene.camera == obj
    ref_w2c = [cams_mod.w2c_from_blender_matrix(M) for M in [mats[1], mats[2], mats[3], mats[0]]]
    _check_scene_camera(extension, scene, obj, out["frames"], K, ref_w2c, pts)
    assert cams_mod.tracking_dist("POLYNOMIAL", 0.1, 0.0, 0.01).tolist() == [0.1, 0.0, 0.0, 0.0, 0.01]
    assert cams_mod.tracking_dist("POLYNOMIAL", 0.0, 0.0, 0.0) is None


def _write_sequence(folder, n=3, w=64, h=48):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = bpy.data.images.new(f"seq{i}", w, h)
        img.pixels.foreach_set(np.full(w * h * 4, 0.25 * (i + 1), np.float32))
        img.filepath_raw = str(folder / f"shot_{i + 1:04d}.png")
        img.file_format = "PNG"
        img.save()
        bpy.data.images.remove(img)
    return folder / "shot_0001.png"


def test_import_footage_sets_scene_up(extension, registered, tmp_path):
    first = _write_sequence(tmp_path / "seq")
    scene = bpy.context.scene
    assert bpy.ops.motion_splats.import_footage(filepath=str(first)) == {"FINISHED"}
    clip = scene.active_clip
    assert clip is not None and tuple(clip.size) == (64, 48)
    assert (scene.frame_start, scene.frame_end) == (1, 3)
    assert (scene.render.resolution_x, scene.render.resolution_y) == (64, 48)
    # image sequences have no frame rate (clip.fps == 0): the scene's stays; videos set theirs
    assert clip.fps == 0 and scene.render.fps == 24
    cam = scene.camera
    assert cam is not None and cam.data.show_background_images
    assert cam.data.background_images[0].clip == clip
    # the clip's tracking camera -> K (y of the principal point flips)
    tcam = clip.tracking.camera
    tcam.focal_length_pixels = 70.0
    tcam.principal_point_pixels = (30.0, 20.0)
    K = extension.addon.cameras.tracking_K(tcam.focal_length_pixels, tcam.principal_point_pixels, 64, 48)
    assert np.allclose(K, [[70, 0, 30], [0, 70, 28], [0, 0, 1]], atol=1e-4)
    # no camera solve yet: a clear report, not a traceback
    assert bpy.ops.motion_splats.import_tracking_camera.poll()
    with pytest.raises(RuntimeError, match="no camera solve"):
        bpy.ops.motion_splats.import_tracking_camera()
    with pytest.raises(RuntimeError, match="footage not found"):
        bpy.ops.motion_splats.import_footage(filepath=str(tmp_path / "nope.mp4"))


_VIDEO_SCRIPT = """
import bpy, sys
bpy.ops.wm.read_factory_settings(use_empty=True)
s = bpy.context.scene
s.render.resolution_x, s.render.resolution_y, s.render.resolution_percentage = 32, 24, 100
s.frame_start, s.frame_end = 1, 4
s.render.fps, s.render.fps_base = 30, 1.001
if hasattr(s.render.image_settings, "media_type"):  # Blender 5: still image vs video first
    s.render.image_settings.media_type = "VIDEO"
s.render.image_settings.file_format = "FFMPEG"
s.render.ffmpeg.format, s.render.ffmpeg.codec = "MPEG4", "H264"
s.render.engine = "BLENDER_WORKBENCH"
s.render.filepath = sys.argv[-1]
cam = bpy.data.objects.new("c", bpy.data.cameras.new("c"))
s.collection.objects.link(cam)
s.camera = cam
bpy.ops.render.render(animation=True)
"""


def test_import_video_sets_fps(registered, tmp_path):
    import subprocess
    import sys

    script = tmp_path / "mkvid.py"
    script.write_text(_VIDEO_SCRIPT, encoding="utf-8")
    subprocess.run([sys.executable, str(script), str(tmp_path / "vid" / "out")], check=True, capture_output=True,
                   timeout=120)
    video = next((tmp_path / "vid").glob("out*.mp4"))
    scene = bpy.context.scene
    assert bpy.ops.motion_splats.import_footage(filepath=str(video)) == {"FINISHED"}
    clip = scene.active_clip
    assert clip.source == "MOVIE" and tuple(clip.size) == (32, 24)
    assert (scene.frame_start, scene.frame_end) == (1, 4)
    assert abs(scene.render.fps / scene.render.fps_base - clip.fps) < 1e-3
    assert abs(clip.fps - 30 / 1.001) < 1e-2
