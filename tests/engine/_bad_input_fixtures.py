"""Tiny inputs for the bad-input table (tests/engine/test_bad_input.py): a video, a clip
manifest, D-NeRF / Nerfies / COLMAP folders, a trained-looking bundle. Each builder
writes into a scratch folder in milliseconds; no training, no priors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from engine import bundle as B

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "data" / "demo_clip"
W, H, F = 64, 48, 6


def frames(n: int = F, w: int = W, h: int = H) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    return [np.roll(base, 3 * i, axis=1) for i in range(n)]


def video(path: Path, n: int = F) -> Path:
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 24.0, (W, H))
    for img in frames(n):
        wr.write(img)
    wr.release()
    return path


def image_folder(root: Path, sizes=None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(frames()):
        if sizes and i in sizes:
            img = cv2.resize(img, sizes[i])
        cv2.imwrite(str(root / f"{i:04d}.png"), img)
    return root


def camera(f: float = 50.0) -> dict:
    return {"K": [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]],
            "w2c": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}


def manifest(root: Path, **over) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    image_folder(root / "frames")
    m = {"format": "motion-splats-clip", "version": 1, "video": None,
         "frames": [f"frames/{i:04d}.png" for i in range(F)], "frame_start": 1, "frame_end": F, "fps": 24.0,
         "width": W, "height": H, "cameras": [dict(frame=i + 1, **camera()) for i in range(F)]}
    m.update(over)
    path = root / "clip.json"
    path.write_text(json.dumps(m))
    return path


def dnerf(root: Path, **over) -> Path:
    image_folder(root / "train")
    fr = [{"file_path": f"train/{i:04d}", "time": i / (F - 1),
           "transform_matrix": np.eye(4).tolist()} for i in range(F)]
    js = {"camera_angle_x": 0.8, "frames": fr}
    js.update({k: v for k, v in over.items() if not k.startswith("frame_")})
    for k, v in over.items():
        if k.startswith("frame_"):
            fr[0][k[6:]] = v
    (root / "transforms_train.json").write_text(json.dumps(js))
    return root


def nerfies(root: Path, edit=None) -> Path:
    shutil.copytree(DEMO, root)
    if edit:
        edit(root)
    return root


def colmap(root: Path) -> Path:
    image_folder(root / "images")
    sp = root / "sparse" / "0"
    sp.mkdir(parents=True)
    (sp / "cameras.bin").write_bytes(b"\x00" * 8)
    (sp / "images.bin").write_bytes(b"\x00" * 8)
    (sp / "points3D.bin").write_bytes(b"\xff\xff\xff\x7f")  # 4 bytes claiming 2^31 points
    return root


def bundle(root: Path, g: int = 200, n: int = 8, k: int = 4) -> Path:
    """A small trained-looking bundle (random but valid values)."""
    rng = np.random.default_rng(1)
    centers = rng.normal(size=(n, 3)).astype(np.float32)
    kt = np.linspace(0, 1, k, dtype=np.float32)
    pos = np.repeat(centers[:, None], k, 1)
    rot = np.zeros((n, k, 4), np.float32)
    rot[..., 0] = 1
    idx = np.stack([rng.choice(n, 4, replace=False) for _ in range(g)]).astype(np.int64)
    nodes = B.NodeArrays(centers=centers, radii=np.full(n, 0.5, np.float32), key_times=kt, pos_keys=pos,
                         pos_tangents=np.zeros_like(pos), rot_keys=rot, rot_tangents=np.zeros_like(rot),
                         bind_idx=idx, bind_w=np.full((g, 4), 0.25, np.float32))
    q = np.zeros((g, 4), np.float32)
    q[:, 0] = 1
    gs = B.GaussianArrays(means=rng.normal(size=(g, 3)).astype(np.float32), quats=q,
                          log_scales=np.full((g, 3), -3.0, np.float32), opacity_logits=np.zeros(g, np.float32),
                          sh=rng.normal(size=(g, 1, 3)).astype(np.float32) * 0.1)
    cams = [dict(frame=i + 1, width=W, height=H, time=i / (F - 1), split="train", **camera()) for i in range(F)]
    scene = B.new_scene(1, F, 24.0, cams, config={"steps": 10, "motion": "spline"},
                        stats={"steps": 10}, source={"clip": "nowhere", "width": W})
    B.save_bundle(root, scene, nodes, gs)
    return root


def ply_with_header(path: Path, header_edit) -> None:
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    path.write_bytes(header_edit(raw[:end]) + raw[end:])


def ply_column(path: Path, name: str, value: float) -> None:
    r = B.read_ply(path)
    g = B.GaussianArrays(means=r.means.copy(), quats=r.quats.copy(), log_scales=r.log_scales.copy(),
                         opacity_logits=r.opacity_logits.copy(), sh=r.sh.copy())
    if name == "opacity":
        g.opacity_logits[0] = value
    elif name.startswith("scale"):
        g.log_scales[0, int(name[-1])] = value
    elif name.startswith("rot"):
        g.quats[0, int(name[-1])] = value
    else:
        g.sh[0, 0, 0] = value
    B.write_ply(path, g)


def edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    data = fn(data) or data
    path.write_text(json.dumps(data))
