"""Import of a *real* Blender camera solve (headless bpy 5.0.1).

Blender's Python API cannot create reconstructed cameras directly
(``MovieTrackingReconstructedCameras`` has no ``new()``), but it can make a real solve:

1. a Movie Clip loaded from rendered (flat) PNG frames;
2. its tracking camera set to known intrinsics (off-centre principal point, so the
   y-up → y-down flip of ``principal_point_pixels`` is exercised);
3. one track per known 3D point (``clip.tracking.tracks.new``), with a marker on every
   frame at the point's projection by a known camera path
   (``track.markers.insert_frame``, normalised marker coordinates, y up);
4. ``bpy.ops.clip.solve_camera()`` run under ``context.temp_override`` with a Movie Clip
   editor area made from the factory screen (the operator's ``exec`` solves
   synchronously; its ``invoke`` would start a background job).

The solve's world frame and scale are its own (gauge freedom), so the acceptance is
checked in image space: every track's reconstructed 3D point (``track.bundle``) projected
with the *imported* engine cameras (``K``, OpenCV ``w2c``) and with the animated scene
camera sampled back through the exporter lands within 0.5 px of its marker, i.e. of the
projection of the known 3D point by the source camera. The solved cameras are also
compared with the ground-truth path after a similarity alignment.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.addon._support import bpy, clean_jobs, registered, user_dir, look_at_w2c  # noqa: F401

W, H, N_FRAMES = 160, 120, 24
F_PX, CX, CY = 150.0, 83.5, 57.25  # engine convention: y down from the top edge


def _ground_truth():
    K = np.array([[F_PX, 0, CX], [0, F_PX, CY], [0, 0, 1.0]])
    pts = np.random.default_rng(0).uniform(-1, 1, (40, 3))
    w2cs = [look_at_w2c([5 * np.cos(a), 5 * np.sin(a), 1.0 + 0.2 * np.sin(3 * a)])
            for a in np.linspace(0.0, 0.8, N_FRAMES)]
    return K, w2cs, pts


def _project(K, w2c, pts):
    X = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = X @ K.T
    return uv[:, :2] / uv[:, 2:3]


def _solved_clip(folder):
    """A Movie Clip with markers from known points and a real camera solve."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(N_FRAMES):
        img = bpy.data.images.new(f"frame{i}", W, H)
        img.pixels.foreach_set(np.full(W * H * 4, 0.5, np.float32))
        img.filepath_raw = str(folder / f"frame_{i + 1:04d}.png")
        img.file_format = "PNG"
        img.save()
        bpy.data.images.remove(img)
    clip = bpy.data.movieclips.load(str(folder / "frame_0001.png"))
    assert tuple(clip.size) == (W, H) and clip.frame_duration == N_FRAMES
    K, w2cs, pts = _ground_truth()
    cam = clip.tracking.camera
    cam.sensor_width = 36.0
    cam.units = "PIXELS"
    cam.focal_length_pixels = F_PX
    cam.principal_point_pixels = (CX, H - CY)  # Blender: y up from the bottom edge
    cam.k1 = cam.k2 = cam.k3 = 0.0
    markers = np.stack([_project(K, w2c, pts) for w2c in w2cs], 1)  # [P, F, 2] pixels, y down
    for j in range(len(pts)):
        track = clip.tracking.tracks.new(name=f"P{j:02d}", frame=1)
        for i in range(N_FRAMES):
            u, v = markers[j, i]
            track.markers.insert_frame(i + 1, co=(u / W, 1.0 - v / H))
    obj = clip.tracking.objects.active
    obj.keyframe_a, obj.keyframe_b = 1, N_FRAMES // 2
    settings = clip.tracking.settings
    settings.refine_intrinsics_focal_length = False
    settings.refine_intrinsics_principal_point = False
    window = bpy.context.window_manager.windows[0]
    area = window.screen.areas[0]
    old_type = area.type
    area.type = "CLIP_EDITOR"
    try:
        space = area.spaces.active
        space.clip = clip
        region = next(r for r in area.regions if r.type == "WINDOW")
        with bpy.context.temp_override(window=window, area=area, region=region, space_data=space):
            assert bpy.ops.clip.solve_camera.poll()
            assert bpy.ops.clip.solve_camera() == {"FINISHED"}
    finally:
        area.type = old_type
    recon = obj.reconstruction
    assert recon.is_valid and len(recon.cameras) == N_FRAMES, "camera solve failed"
    assert recon.average_error < 0.05, recon.average_error
    return clip, markers, (K, w2cs, pts)


def _umeyama(src, dst):
    """Similarity (s, R, t) with dst ≈ s R src + t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / a.var(0).sum()
    return s, R, mu_d - s * R @ mu_s


def test_real_tracking_solve_imports_within_half_pixel(extension, registered, tmp_path):
    clip, markers, (K_gt, w2cs_gt, pts_gt) = _solved_clip(tmp_path / "frames")
    scene = bpy.context.scene
    scene.active_clip = clip
    scene.frame_start, scene.frame_end = 1, N_FRAMES
    cams_mod = extension.addon.cameras

    cams = cams_mod.read_tracking_reconstruction(clip)
    assert cams["frames"] == list(range(1, N_FRAMES + 1))
    assert cams["average_error"] < 0.05
    assert (cams["width"], cams["height"]) == (W, H) and cams["dist"] is None
    assert np.allclose(cams["K"][0], K_gt, atol=1e-3), cams["K"][0]
    bundles = np.array([t.bundle[:] for t in clip.tracking.tracks], dtype=np.float64)  # solve's 3D points
    worst = max(np.abs(cams_mod.project(cams["K"][i], cams["w2c"][i], bundles) - markers[:, i]).max()
                for i in range(N_FRAMES))
    assert worst < 0.5, f"engine cameras reproject the solve {worst:.3f} px off the markers"

    # the same up to the solve's gauge: aligned to the ground-truth points, the solved
    # cameras project the known 3D points where the source cameras do
    s, R, t = _umeyama(bundles, pts_gt)
    for i, w2c_gt in enumerate(w2cs_gt):
        w2c = cams["w2c"][i]
        # world_gt -> world_solve: x_s = R^T (x_gt - t) / s; scale leaves projections unchanged
        pts_solve = (pts_gt - t) @ R / s
        err = np.abs(cams_mod.project(cams["K"][i], w2c, pts_solve) - _project(K_gt, w2c_gt, pts_gt)).max()
        assert err < 0.5, (i, err)

    # the operator: an animated scene camera reproducing the solve
    assert bpy.ops.motion_splats.import_tracking_camera() == {"FINISHED"}
    cam_obj = scene.camera
    assert cam_obj is not None and cam_obj.name.startswith("Tracked_")
    sampled = extension.addon.exporters.sample_camera(scene, cam_obj, range(1, N_FRAMES + 1))
    worst_scene = 0.0
    for i, c in enumerate(sampled):
        assert (c["width"], c["height"]) == (W, H)
        worst_scene = max(worst_scene, np.abs(cams_mod.project(c["K"], c["w2c"], bundles) - markers[:, i]).max())
    assert worst_scene < 0.5, f"scene camera reprojects the solve {worst_scene:.3f} px off the markers"
