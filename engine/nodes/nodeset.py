"""The node set handed from initialisation to training (``nodes.npz`` fields)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class NodeSet:
    """Control nodes with Hermite trajectories (see docs/architecture.md, "Node transform").

    Attributes
    ----------
    centers : (N, 3) canonical centres ``c_i`` (world units).
    radii : (N,) RBF radii.
    key_times : (K,) shared key times in engine time [0, 1].
    pos_keys, pos_tangents : (N, K, 3) position spline ``p_i(t)``.
    rot_keys, rot_tangents : (N, K, 4) quaternion spline ``q_i(t)`` (wxyz).
    p_dyn : (N,) dynamic tendency in [0, 1].
    graph_idx : (N, k) long, k nearest other nodes (for ARAP).
    source_time : (N,) engine time at which ``centers`` was observed (provenance).
    method : str, the initialiser that produced the nodes (provenance).
    """

    centers: torch.Tensor
    radii: torch.Tensor
    key_times: torch.Tensor
    pos_keys: torch.Tensor
    pos_tangents: torch.Tensor
    rot_keys: torch.Tensor
    rot_tangents: torch.Tensor
    p_dyn: torch.Tensor
    graph_idx: torch.Tensor
    source_time: torch.Tensor | None = None
    method: str = "mani"
    extras: dict = field(default_factory=dict)

    @property
    def num_nodes(self) -> int:
        return int(self.centers.shape[0])

    def to_npz_dict(self) -> dict[str, np.ndarray]:
        """Arrays for ``nodes.npz`` (float32 / int64), bundle field names."""
        f32 = lambda x: x.detach().cpu().numpy().astype(np.float32)  # noqa: E731
        return {
            "centers": f32(self.centers), "radii": f32(self.radii), "key_times": f32(self.key_times),
            "pos_keys": f32(self.pos_keys), "pos_tangents": f32(self.pos_tangents),
            "rot_keys": f32(self.rot_keys), "rot_tangents": f32(self.rot_tangents),
            "p_dyn": f32(self.p_dyn), "graph_idx": self.graph_idx.detach().cpu().numpy().astype(np.int64),
        }

    @classmethod
    def from_npz_dict(cls, d) -> "NodeSet":
        """Inverse of :meth:`to_npz_dict` (extra keys such as ``bind_idx`` are ignored)."""
        t = lambda k: torch.as_tensor(np.asarray(d[k]), dtype=torch.float32)  # noqa: E731
        n = np.asarray(d["centers"]).shape[0]
        p_dyn = t("p_dyn") if "p_dyn" in d else torch.zeros(n)
        graph = torch.as_tensor(np.asarray(d["graph_idx"]), dtype=torch.long) if "graph_idx" in d \
            else torch.zeros(n, 0, dtype=torch.long)
        return cls(t("centers"), t("radii"), t("key_times"), t("pos_keys"), t("pos_tangents"),
                   t("rot_keys"), t("rot_tangents"), p_dyn, graph, method="loaded")
