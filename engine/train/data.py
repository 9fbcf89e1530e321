"""Training data: the tensors one reconstruction run needs, at training resolution."""

from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass
class TrainingData:
    """Frames, cameras and priors of one clip, on one device, at training resolution.

    Attributes
    ----------
    images : (F, H, W, 3) float in [0, 1].
    K : (F, 3, 3) intrinsics in pixels of this resolution (continuous pixel coords).
    w2c : (F, 4, 4) world-to-camera, OpenCV axes.
    times : (F,) engine time in [0, 1].
    train_idx, val_idx : long indices into the F frames (val may be empty).
    depth : (F, H, W) optional depth prior (scene units; 0 = unknown).
    fg : (F, H, W) optional foreground/dynamic prior in [0, 1].
    tracks_xy : (P, F, 2) optional 2D tracks in pixels of this resolution.
    tracks_vis : (P, F) bool, where a track is visible.
    tracks_depth : (P, F) optional camera depth a track carries of its own (NaN: the depth
        prior decides; e.g. tracks along a hinge's rings, at the hinge's depth, where the
        prior sees the background behind a thin moving part).
    extent : scene extent (radius of the camera/point cloud bounds) in scene units.
    frame_numbers : (F,) Blender/scene frame number of each frame (for the bundle).
    clip_index : (F,) index of each frame in its source clip (evaluation reloads it).
    held_out_cameras : whether the clip comes with cameras it does not train on (a dataset's
        held-out views, e.g. a Nerfies vrig's second camera): there views off the training
        camera's path matter, and with a moving camera ``lifespan auto`` stays off
        (:func:`engine.train.lifespan.resolve_lifespan`). True unless the caller knows better:
        the pipeline sets False for a clip without such cameras (a video, an image folder).
    """

    images: torch.Tensor
    K: torch.Tensor
    w2c: torch.Tensor
    times: torch.Tensor
    train_idx: torch.Tensor
    val_idx: torch.Tensor
    depth: torch.Tensor | None = None
    fg: torch.Tensor | None = None
    tracks_xy: torch.Tensor | None = None
    tracks_vis: torch.Tensor | None = None
    tracks_depth: torch.Tensor | None = None
    extent: float = 1.0
    frame_numbers: torch.Tensor | None = None
    fps: float = 24.0
    clip_index: torch.Tensor | None = None
    held_out_cameras: bool = True

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    def to(self, device) -> "TrainingData":
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to(device) if isinstance(v, torch.Tensor) else v
        return TrainingData(**out)

    def validate(self) -> "TrainingData":
        f, h, w = self.images.shape[:3]
        checks = {"K": (f, 3, 3), "w2c": (f, 4, 4), "times": (f,)}
        for name, shape in checks.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"TrainingData.{name} has shape {tuple(getattr(self, name).shape)}; expected {shape}")
        for name in ("depth", "fg"):
            v = getattr(self, name)
            if v is not None and tuple(v.shape) != (f, h, w):
                raise ValueError(f"TrainingData.{name} has shape {tuple(v.shape)}; expected {(f, h, w)}")
        if self.tracks_xy is not None:
            p = self.tracks_xy.shape[0]
            if tuple(self.tracks_xy.shape) != (p, f, 2) or tuple(self.tracks_vis.shape) != (p, f):
                raise ValueError("tracks_xy must be (P, F, 2) and tracks_vis (P, F)")
            if self.tracks_depth is not None and tuple(self.tracks_depth.shape) != (p, f):
                raise ValueError("tracks_depth must be (P, F) like tracks_vis")
        if len(self.train_idx) == 0:
            raise ValueError("no training frames")
        return self
