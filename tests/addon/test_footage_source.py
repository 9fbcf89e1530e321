"""Issue #18.2: Import Footage -> Reconstruct never trains on a camera that does not move,
accepts the dataset folders the engine accepts, and the Movie Clip / Clip Path inputs never
silently override each other. The engine here is a fake interpreter (the manifest the add-on
writes is what is checked), so these tests take seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.addon._support import bpy, clean_jobs, failing_python, look_at_w2c, registered, user_dir  # noqa: F401


def _sequence(folder: Path, n: int = 4) -> Path:
    folder.mkdir(parents=True)
    for i in range(n):
        img = bpy.data.images.new(f"f{i}", 32, 24)
        img.pixels.foreach_set(np.full(32 * 24 * 4, 0.2 + 0.1 * i, np.float32))
        img.filepath_raw = str(folder / f"shot_{i + 1:04d}.png")
        img.file_format = "PNG"
        img.save()
        bpy.data.images.remove(img)
    return folder / "shot_0001.png"


def _setup(prefs, tmp_path):
    prefs.engine_python = str(failing_python(tmp_path))
    prefs.results_dir = str(tmp_path / "results")
    prefs.cache_dir = str(tmp_path / "cache")
    return bpy.context.scene.motion_splats_result


def _manifest(jobs) -> dict:
    job = jobs.latest("train")
    argv = job.process.argv
    path = Path(argv[argv.index("train") + 2])
    assert path.suffix == ".json", argv
    return json.loads(path.read_text()), job


def _static_factory_camera(scene):
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    cam.location = (7.4, -6.5, 5.3)  # the factory camera: placed, never animated or tracked
    scene.camera = cam
    return cam


def test_static_scene_camera_is_not_sent(registered, tmp_path, clean_jobs):
    s = _setup(registered, tmp_path)
    scene = bpy.context.scene
    _static_factory_camera(scene)
    assert bpy.ops.motion_splats.import_footage(filepath=str(_sequence(tmp_path / "seq"))) == {"FINISHED"}
    assert s.use_scene_camera  # the default
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    data, job = _manifest(clean_jobs)
    assert not data.get("cameras"), "a camera that does not move was sent as the footage's cameras"
    assert any("does not move" in line and "Movie Clip Editor" in line for line in job.logs), list(job.logs)


def test_moving_scene_camera_is_sent(extension, registered, tmp_path, clean_jobs):
    _setup(registered, tmp_path)
    scene = bpy.context.scene
    assert bpy.ops.motion_splats.import_footage(filepath=str(_sequence(tmp_path / "seq"))) == {"FINISHED"}
    w2cs = [look_at_w2c([4 * np.cos(a), 4 * np.sin(a), 1.0]) for a in np.linspace(0.2, 0.8, 4)]
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    extension.addon.cameras.build_animated_camera(scene, "Moving", K, 32, 24, w2cs, range(1, 5))
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    data, job = _manifest(clean_jobs)
    got = np.array([c["w2c"] for c in data["cameras"]])
    assert np.allclose(got, np.stack(w2cs), atol=1e-4)


def test_import_footage_accepts_a_dataset_folder(registered, tmp_path, clean_jobs):
    """A Nerfies folder is what the engine reads best: Import Footage selects it for Reconstruct
    and leaves the scene alone."""
    folder = tmp_path / "capture"
    (folder / "camera").mkdir(parents=True)
    (folder / "dataset.json").write_text("{}", encoding="utf-8")
    s = _setup(registered, tmp_path)
    scene = bpy.context.scene
    before = (scene.frame_start, scene.frame_end, scene.render.resolution_x)
    assert bpy.ops.motion_splats.import_footage(filepath=str(folder)) == {"FINISHED"}
    assert s.source == "PATH" and Path(s.clip_path) == folder
    assert (scene.frame_start, scene.frame_end, scene.render.resolution_x) == before
    (tmp_path / "empty").mkdir()
    with pytest.raises(RuntimeError, match="not a clip layout"):
        bpy.ops.motion_splats.import_footage(filepath=str(tmp_path / "empty"))
    with pytest.raises(RuntimeError, match="footage not found"):
        bpy.ops.motion_splats.import_footage(filepath=str(tmp_path / "nope.mp4"))


def test_movie_clip_and_clip_path_never_override_each_other(registered, tmp_path, clean_jobs):
    s = _setup(registered, tmp_path)
    other = tmp_path / "other.mp4"
    other.write_bytes(b"not read")
    s.clip_path = str(other)
    assert s.source == "PATH"  # typing a path chooses it
    assert bpy.ops.motion_splats.import_footage(filepath=str(_sequence(tmp_path / "seq"))) == {"FINISHED"}
    assert s.source == "MOVIE_CLIP"  # importing footage chooses it
    assert bpy.ops.motion_splats.reconstruct() == {"FINISHED"}
    data, job = _manifest(clean_jobs)
    assert "other.mp4" not in job.process.argv and data.get("frames"), job.process.argv
    clean_jobs.wait(job, 20)
    # Clip Path chosen but empty: an error naming both fixes, not a fall back to the Movie Clip
    s.clip_path = ""
    s.source = "PATH"
    with pytest.raises(RuntimeError, match="Clip Path not found.*Source to Movie Clip"):
        bpy.ops.motion_splats.reconstruct()


def test_export_clip_manifest_never_writes_a_still_camera(registered, tmp_path, clean_jobs):
    import json

    _setup(registered, tmp_path)
    _static_factory_camera(bpy.context.scene)
    assert bpy.ops.motion_splats.import_footage(filepath=str(_sequence(tmp_path / "seq"))) == {"FINISHED"}
    out = tmp_path / "clip.json"
    assert bpy.ops.motion_splats.export_clip_manifest(filepath=str(out)) == {"FINISHED"}
    assert not json.loads(out.read_text()).get("cameras")
