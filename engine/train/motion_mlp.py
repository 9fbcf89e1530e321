"""The SC-GS-style deformation MLP: the node-motion baseline the paper improves on.

``TrainConfig.motion = "mlp"``: a field ``(c_i, t) -> (Δp_i, Δq_i)`` of the node centres and
time, in place of the spline keys (:class:`~engine.train.model.DynamicScene` holds it as
``mlp``).
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from ..geometry.quaternion import quat_normalize


def positional_encoding(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """NeRF positional encoding: ``[..., D] -> [..., D (1 + 2 num_freqs)]``."""
    freqs = (2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)) * math.pi
    xf = x[..., None] * freqs
    return torch.cat([x, torch.sin(xf).flatten(-2), torch.cos(xf).flatten(-2)], dim=-1)


class DeformMLP(nn.Module):
    """SC-GS-style node deformation field: ``(c_i, t) -> (Δp_i, Δq_i)``.

    Input positions are normalised by the scene extent; the last layer starts at zero,
    so the field starts as the identity motion.
    """

    def __init__(self, extent: float, width: int = 128, depth: int = 4, pos_freqs: int = 6, time_freqs: int = 6):
        super().__init__()
        self.extent = float(extent)
        self.pos_freqs, self.time_freqs = pos_freqs, time_freqs
        dim_in = 3 * (1 + 2 * pos_freqs) + (1 + 2 * time_freqs)
        layers: list[nn.Module] = []
        for i in range(depth):
            layers += [nn.Linear(dim_in if i == 0 else width, width), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(width, 7)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, centers: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """centers [N, 3], scalar t -> (Δp [N, 3], quaternion [N, 4] wxyz)."""
        n = centers.shape[0]
        tt = torch.full((n, 1), float(t), device=centers.device, dtype=centers.dtype)
        h = torch.cat([positional_encoding(centers / self.extent, self.pos_freqs),
                       positional_encoding(tt, self.time_freqs)], dim=-1)
        out = self.head(self.trunk(h))
        dq = out[:, 3:]
        q = quat_normalize(torch.cat([1.0 + dq[:, :1], dq[:, 1:]], dim=-1))
        return out[:, :3] * self.extent, q
