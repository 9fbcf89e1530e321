"""Readers of engine.io: golden projections on synthetic datasets and malformed inputs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from engine.errors import InputError
from engine.io import (load_clip, load_colmap, load_dnerf, load_manifest, load_n3dv, load_nerfies,
                       load_video, write_manifest)
from engine.io.clip import project_points

RNG = np.random.default_rng(0)


def rot(seed):
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix()


def look_rot(seed):
    """A random rotation that keeps points near the origin in front of a camera at -4z-ish."""
    from scipy.spatial.transform import Rotation

    r = np.random.default_rng(seed)
    return Rotation.from_rotvec(r.normal(0, 0.15, 3)).as_matrix()


def points(n=30, seed=1):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3))


def write_img(path, w, h, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)
    cv2.imwrite(str(path), img)
    return img


# --------------------------------------------------------------------------- Nerfies
def make_nerfies(root: Path, n=4, W=80, H=60, distort=True):
    cams = {}
    ids = [f"f{i:03d}" for i in range(n)]
    for i, fid in enumerate(ids):
        R = look_rot(i)
        C = np.array([0.3 * i, -0.2, -4.0]) @ np.eye(3)
        C = R.T @ np.array([0.1 * i, 0.05, -4.0])  # camera looks at origin-ish
        cam = {"orientation": R.tolist(), "position": C.tolist(), "focal_length": 90.0 + i,
               "pixel_aspect_ratio": 1.02, "principal_point": [W / 2 + 1.5, H / 2 - 2.0], "skew": 0.3,
               "radial_distortion": [0.05, -0.01, 0.002] if distort else [0, 0, 0],
               "tangential_distortion": [0.001, -0.002] if distort else [0, 0], "image_size": [W, H]}
        (root / "camera").mkdir(parents=True, exist_ok=True)
        (root / "camera" / f"{fid}.json").write_text(json.dumps(cam))
        cams[fid] = cam
        for s in (1, 2):
            write_img(root / "rgb" / f"{s}x" / f"{fid}.png", W // s, H // s, i)
    (root / "dataset.json").write_text(json.dumps({"count": n, "ids": ids, "train_ids": ids[::2], "val_ids": ids[1::2]}))
    (root / "metadata.json").write_text(json.dumps({fid: {"warp_id": i, "time_id": i, "camera_id": 0,
                                                          "appearance_id": i} for i, fid in enumerate(ids)}))
    (root / "scene.json").write_text(json.dumps({"scale": 0.5, "center": [0.1, 0.2, -0.3], "near": 0.1, "far": 3.0}))
    return ids, cams


def nerfies_project(cam, X):
    """Nerfies' own camera model (nerfies/camera.py): pixel = f * distorted(x) + pp, centres at +0.5."""
    R = np.asarray(cam["orientation"]); C = np.asarray(cam["position"])
    local = (X - C) @ R.T
    x, y = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
    k1, k2, k3 = cam["radial_distortion"]; p1, p2 = cam["tangential_distortion"]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + k3 * r2))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    f = cam["focal_length"]
    u = f * xd + cam["skew"] * yd + cam["principal_point"][0]
    v = f * cam["pixel_aspect_ratio"] * yd + cam["principal_point"][1]
    return np.stack([u, v], 1)


@pytest.mark.parametrize("scale", [1, 2])
def test_nerfies_projection_golden(tmp_path, scale):
    ids, cams = make_nerfies(tmp_path)
    clip = load_clip(tmp_path, scale=scale)
    assert clip.frame_ids == ids and clip.split == {"train": [0, 2], "val": [1, 3]}
    assert (clip.width, clip.height) == (80 // scale, 60 // scale)
    np.testing.assert_allclose(clip.times, [0, 1 / 3, 2 / 3, 1])
    X = points()
    Xn = (X - np.array([0.1, 0.2, -0.3])) * 0.5  # scene.json normalisation
    for i, fid in enumerate(ids):
        got = project_points(clip.K[i], clip.w2c[i], Xn, clip.dist[i])
        np.testing.assert_allclose(got, nerfies_project(cams[fid], X) / scale, atol=1e-6)
    assert clip.load_frame(0).shape == (60 // scale, 80 // scale, 3)
    assert clip.near == 0.1 and clip.far == 3.0


def test_nerfies_errors(tmp_path):
    ids, cams = make_nerfies(tmp_path)
    (tmp_path / "camera" / f"{ids[1]}.json").unlink()
    with pytest.raises(InputError) as e:
        load_nerfies(tmp_path)
    assert f"{ids[1]}.json" in e.value.path
    make_nerfies(tmp_path)
    (tmp_path / "camera" / f"{ids[2]}.json").write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON") as e:
        load_nerfies(tmp_path)
    assert e.value.path.endswith(f"{ids[2]}.json")
    make_nerfies(tmp_path)
    c = dict(cams[ids[0]]); c["orientation"] = np.zeros((3, 3)).tolist()
    (tmp_path / "camera" / f"{ids[0]}.json").write_text(json.dumps(c))
    with pytest.raises(InputError, match="singular"):
        load_nerfies(tmp_path)
    make_nerfies(tmp_path)
    write_img(tmp_path / "rgb" / "1x" / f"{ids[0]}.png", 50, 40)
    with pytest.raises(InputError, match="50x40") as e:
        load_nerfies(tmp_path)
    assert e.value.path.endswith(f"{ids[0]}.png") and e.value.fix
    with pytest.raises(InputError, match="rgb/4x"):
        load_nerfies(tmp_path, scale=4)


# --------------------------------------------------------------------------- D-NeRF
def make_dnerf(root: Path, W=64, H=48, n=(3, 2, 2), ext=False):
    ang = 0.8
    out = {}
    k = 0
    for name, cnt in zip(("train", "val", "test"), n):
        frames = []
        for j in range(cnt):
            Rc = look_rot(10 + k)  # cv camera-to-world rotation, looking +z
            C = Rc @ np.array([0.0, 0.0, -4.0])
            c2w_cv = np.eye(4); c2w_cv[:3, :3] = Rc; c2w_cv[:3, 3] = C
            c2w_gl = c2w_cv @ np.diag([1.0, -1, -1, 1])
            write_img(root / name / f"r_{j:03d}.png", W, H, k)
            frames.append({"file_path": f"./{name}/r_{j:03d}" + (".png" if ext else ""),
                           "transform_matrix": c2w_gl.tolist(), "time": k / 6})
            out[k] = c2w_gl
            k += 1
        (root / f"transforms_{name}.json").write_text(json.dumps({"camera_angle_x": ang, "frames": frames}))
    return out, 0.5 * W / np.tan(0.5 * ang)


@pytest.mark.parametrize("ext", [False, True])
def test_dnerf_projection_golden(tmp_path, ext):
    c2ws, f = make_dnerf(tmp_path, ext=ext)
    clip = load_clip(tmp_path)
    assert clip.split == {"train": [0, 1, 2], "val": [3, 4], "test": [5, 6]}
    np.testing.assert_allclose(clip.times, np.arange(7) / 6)
    X = points()
    for i, M in c2ws.items():
        # OpenGL camera: looks down -z, y up; pixel rows go down
        p = (X - M[:3, 3]) @ M[:3, :3]
        u = f * p[:, 0] / -p[:, 2] + 32
        v = f * -p[:, 1] / -p[:, 2] + 24
        np.testing.assert_allclose(project_points(clip.K[i], clip.w2c[i], X), np.stack([u, v], 1), atol=1e-6)
    assert clip.load_frame(3).shape == (48, 64, 3)


def test_dnerf_errors(tmp_path):
    make_dnerf(tmp_path)
    (tmp_path / "val" / "r_001.png").unlink()
    with pytest.raises(InputError, match="r_001") as e:
        load_dnerf(tmp_path)
    assert e.value.path.endswith("transforms_val.json")
    make_dnerf(tmp_path)
    js = json.loads((tmp_path / "transforms_train.json").read_text())
    js["frames"][1]["transform_matrix"] = np.zeros((4, 4)).tolist()
    (tmp_path / "transforms_train.json").write_text(json.dumps(js))
    with pytest.raises(InputError, match="singular"):
        load_dnerf(tmp_path)
    (tmp_path / "transforms_train.json").write_text('{"frames": [')
    with pytest.raises(InputError, match="invalid JSON") as e:
        load_dnerf(tmp_path)
    assert e.value.path.endswith("transforms_train.json")


# --------------------------------------------------------------------------- COLMAP
CAMS = {
    "PINHOLE": [70.0, 72.0, 33.0, 23.5],
    "SIMPLE_PINHOLE": [70.0, 32.0, 24.0],
    "SIMPLE_RADIAL": [70.0, 32.0, 24.0, 0.05],
    "RADIAL": [70.0, 32.0, 24.0, 0.05, -0.01],
    "OPENCV": [70.0, 71.0, 31.0, 25.0, 0.05, -0.01, 0.002, -0.001],
}


def qvec(R):
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [w, x, y, z]


def make_colmap(root: Path, model: str, binary: bool, W=64, H=48, n=3):
    sp = root / "sparse" / "0"
    sp.mkdir(parents=True)
    (sp / "cameras.txt").write_text(f"1 {model} {W} {H} " + " ".join(map(str, CAMS[model])) + "\n")
    lines, truth = [], {}
    names = [f"img_{k}.png" for k in (2, 0, 1)][:n]  # out of order on purpose
    for k, name in enumerate(names):
        R = look_rot(20 + k)
        t = np.array([0.1 * k, -0.1, 4.0])
        lines.append(f"{k + 1} " + " ".join(map(repr, qvec(R))) + " " + " ".join(map(repr, t)) + f" 1 {name}\n\n")
        M = np.eye(4); M[:3, :3] = R; M[:3, 3] = t
        truth[name] = M
        write_img(root / "images" / name, W, H, k)
    (sp / "images.txt").write_text("".join(lines))
    (sp / "points3D.txt").write_text("")
    if binary:
        import pycolmap

        rec = pycolmap.Reconstruction(str(sp))
        for f in ("cameras", "images", "points3D"):
            (sp / f"{f}.txt").unlink()
        rec.write_binary(str(sp))
    return truth


@pytest.mark.parametrize("model", list(CAMS))
@pytest.mark.parametrize("binary", [False, True])
def test_colmap_projection_golden(tmp_path, model, binary):
    truth = make_colmap(tmp_path, model, binary)
    clip = load_clip(tmp_path)
    assert clip.frame_ids == sorted(truth)
    p = CAMS[model]
    if model in ("PINHOLE", "OPENCV"):
        Kt = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
    else:
        Kt = np.array([[p[0], 0, p[1]], [0, p[0], p[2]], [0, 0, 1]])
    dt = {"SIMPLE_RADIAL": lambda: [p[3], 0, 0, 0, 0], "RADIAL": lambda: [p[3], p[4], 0, 0, 0],
          "OPENCV": lambda: [p[4], p[5], p[6], p[7], 0]}.get(model, lambda: [0, 0, 0, 0, 0])()
    X = points() * 0.5
    for i, name in enumerate(clip.frame_ids):
        M = truth[name]
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(M[:3, :3])[0], M[:3, 3], Kt, np.asarray(dt, float))
        d = None if clip.dist is None else clip.dist[i]
        np.testing.assert_allclose(project_points(clip.K[i], clip.w2c[i], X, d), ref[:, 0], atol=1e-6)
    np.testing.assert_allclose(clip.times, [0, 0.5, 1])


def test_colmap_errors(tmp_path):
    make_colmap(tmp_path, "PINHOLE", False)
    (tmp_path / "images" / "img_1.png").unlink()
    with pytest.raises(InputError) as e:
        load_colmap(tmp_path)
    assert e.value.path.endswith("img_1.png")
    write_img(tmp_path / "images" / "img_1.png", 30, 30)
    load_colmap(tmp_path)  # only the first frame's size is checked at load time ...
    clip = load_colmap(tmp_path)
    with pytest.raises(InputError, match="30x30"):  # ... the rest when loaded
        clip.load_frame(clip.frame_ids.index("img_1.png"))
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text("1 FOV 64 48 70 32 24 0.1\n")
    with pytest.raises(InputError):
        load_colmap(tmp_path)


# --------------------------------------------------------------------------- manifest
def manifest_cams(n, W=64, H=48):
    cams = []
    for i in range(n):
        M = np.eye(4); M[:3, :3] = look_rot(30 + i); M[:3, 3] = [0.1 * i, 0, 4]
        cams.append({"frame": 10 + i, "K": [[60.0, 0, W / 2], [0, 61.0, H / 2], [0, 0, 1]], "w2c": M,
                     "dist": [0.01, 0, 0, 0, 0] if i == 1 else None})
    return cams


def test_manifest_roundtrip_images(tmp_path):
    for i in range(4):
        write_img(tmp_path / "frames" / f"{i:04d}.png", 64, 48, i)
    cams = manifest_cams(4)
    mpath = tmp_path / "clip" / "clip.json"
    m = write_manifest(mpath, width=64, height=48, fps=24, frame_start=10, frame_end=13,
                       frames=[tmp_path / "frames" / f"{i:04d}.png" for i in range(4)], cameras=cams,
                       priors={"depth": tmp_path / "priors" / "depth.npz"})
    assert m["frames"][0] == "../frames/0000.png" and m["priors"]["depth"] == "../priors/depth.npz"
    clip = load_clip(mpath)
    np.testing.assert_allclose(clip.times, [0, 1 / 3, 2 / 3, 1])
    X = points()
    for i, c in enumerate(cams):
        np.testing.assert_array_equal(clip.w2c[i], c["w2c"])
        d = np.zeros(5) if c["dist"] is None else np.asarray(c["dist"])
        ref = project_points(np.asarray(c["K"]), c["w2c"], X, d)
        np.testing.assert_allclose(project_points(clip.K[i], clip.w2c[i], X, clip.dist[i]), ref, atol=1e-9)
    assert clip.load_frame(2).shape == (48, 64, 3)
    assert clip.priors["depth"] == (tmp_path / "priors" / "depth.npz").resolve() or \
        clip.priors["depth"].resolve() == (tmp_path / "priors" / "depth.npz").resolve()


def write_video(path, n=6, W=64, H=48):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 24, (W, H))
    assert vw.isOpened()
    for i in range(n):
        img = np.full((H, W, 3), 20 * i, np.uint8)
        img[:, : W // 2] = 255 - 20 * i
        vw.write(img)
    vw.release()


def test_manifest_video_and_time_mapping(tmp_path):
    write_video(tmp_path / "v.mp4")
    mpath = tmp_path / "clip.json"
    write_manifest(mpath, width=64, height=48, fps=24, frame_start=1, frame_end=5, video=tmp_path / "v.mp4",
                   time={"frame_start": 1, "frame_end": 9})
    clip = load_manifest(mpath)
    assert not clip.has_cameras and clip.num_frames == 5
    np.testing.assert_allclose(clip.times, np.arange(5) / 8)
    assert clip.load_frame(4).shape == (48, 64, 3)


@pytest.mark.parametrize("mutate, match", [
    (lambda m: m.update(format="other"), "format"),
    (lambda m: m.update(version=2), "version"),
    (lambda m: m.update(video="x.mp4"), "exactly one"),
    (lambda m: m["cameras"][0].update(K=[[1, 0], [0, 1]]), "'K'"),
    (lambda m: m["cameras"].pop(), "cameras for"),
    (lambda m: m.update(fps=0), "fps"),
])
def test_manifest_schema_errors(tmp_path, mutate, match):
    for i in range(4):
        write_img(tmp_path / f"{i}.png", 64, 48, i)
    mpath = tmp_path / "clip.json"
    m = write_manifest(mpath, width=64, height=48, fps=24, frame_start=10, frame_end=13,
                       frames=[tmp_path / f"{i}.png" for i in range(4)], cameras=manifest_cams(4))
    mutate(m)
    mpath.write_text(json.dumps(m))
    with pytest.raises(InputError, match=match) as e:
        load_manifest(mpath)
    assert e.value.path == str(mpath) and e.value.fix


@pytest.mark.parametrize("bad, match", [("nan", "NaN"), ("singular", "singular"), ("focal", "focal")])
def test_manifest_bad_cameras(tmp_path, bad, match):
    for i in range(4):
        write_img(tmp_path / f"{i}.png", 64, 48, i)
    mpath = tmp_path / "clip.json"
    m = write_manifest(mpath, width=64, height=48, fps=24, frame_start=10, frame_end=13,
                       frames=[f"{i}.png" for i in range(4)], cameras=manifest_cams(4))
    c = m["cameras"][2]
    if bad == "nan":
        c["w2c"][0][3] = float("nan")
    elif bad == "singular":
        c["w2c"][1][:3] = [0.0, 0.0, 0.0]
    else:
        c["K"][0][0] = -5.0
    mpath.write_text(json.dumps(m))  # json writes NaN as a literal
    with pytest.raises(InputError, match=match) as e:
        load_clip(mpath)
    assert e.value.path == str(mpath)


# --------------------------------------------------------------------------- video / folders
def test_video_and_folder(tmp_path):
    write_video(tmp_path / "v.mp4", n=7)
    clip = load_clip(tmp_path / "v.mp4", frame_step=2)
    assert clip.num_frames == 4 and clip.frame_ids == ["0", "2", "4", "6"] and not clip.has_cameras
    f = clip.load_frame(3)
    assert f.shape == (48, 64, 3) and f.dtype == np.uint8
    assert abs(int(f[10, 50, 0]) - 120) < 12 and abs(int(f[10, 5, 0]) - 135) < 12  # RGB from frame 6
    assert clip.load_frame(1, downscale=2).shape == (24, 32, 3)
    for i in range(3):
        write_img(tmp_path / "imgs" / f"{i:03d}.jpg", 40, 30, i)
    c2 = load_clip(tmp_path / "imgs")
    assert c2.num_frames == 3 and (c2.width, c2.height) == (40, 30)


def test_corrupt_video(tmp_path):
    p = tmp_path / "bad.mp4"
    p.write_bytes(np.random.default_rng(0).integers(0, 255, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="video") as e:
        load_video(p)
    assert e.value.path == str(p) and e.value.fix
    with pytest.raises(InputError, match="does not exist"):
        load_clip(tmp_path / "nothing.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a recognised"):
        load_clip(tmp_path / "empty")


# --------------------------------------------------------------------------- N3DV
def test_n3dv_projection_golden(tmp_path):
    W, H, f = 64, 48, 55.0
    rows, truth = [], []
    for c in range(3):
        Rc = look_rot(40 + c)  # cv c2w rotation
        C = np.array([0.3 * c, 0.0, -4.0])
        llff = np.stack([Rc[:, 1], Rc[:, 0], -Rc[:, 2], C, [H, W, f]], axis=1)  # down, right, back
        rows.append(np.concatenate([llff.ravel(), [0.5, 9.0]]))
        M = np.eye(4); M[:3, :3] = Rc.T; M[:3, 3] = -Rc.T @ C
        truth.append(M)
        write_video(tmp_path / f"cam{c:02d}.mp4", n=5, W=W, H=H)
    np.save(tmp_path / "poses_bounds.npy", np.asarray(rows))
    clip = load_clip(tmp_path, train_camera=1, eval_cameras=["cam00"])
    assert clip.meta["camera"] == "cam01" and list(clip.eval_clips) == ["cam00"]
    assert clip.num_frames == 5 and clip.eval_clips["cam00"].num_frames == 5
    X = points()
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    np.testing.assert_allclose(project_points(clip.K[0], clip.w2c[3], X), project_points(K, truth[1], X), atol=1e-9)
    e = clip.eval_clips["cam00"]
    np.testing.assert_allclose(project_points(e.K[0], e.w2c[0], X), project_points(K, truth[0], X), atol=1e-9)
    assert clip.near == 0.5 and clip.far == 9.0
    assert len(load_n3dv(tmp_path).eval_clips) == 2
    np.save(tmp_path / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(InputError, match=r"\[C,17\]") as ex:
        load_n3dv(tmp_path)
    assert ex.value.path.endswith("poses_bounds.npy")
