"""Priors for reconstruction: per-patch tokens, depth, dynamic mask, long 2D tracks.

Each has an ONNX backend (model by path) and a weight-free backend; see docs/priors.md.
"""

from .cache import PriorConfig, Priors, compute_priors
from .depth import anchors_from_tracks, estimate_depth, triangulate_tracks
from .motion import dynamic_mask
from .precomputed import load_depth, load_mask, load_tracks
from .tokens import TokenGrid, extract_tokens
from .tracks import Tracks, track_points

__all__ = ["PriorConfig", "Priors", "compute_priors", "estimate_depth", "anchors_from_tracks",
           "triangulate_tracks", "dynamic_mask", "load_depth", "load_mask", "load_tracks", "TokenGrid",
           "extract_tokens", "Tracks", "track_points"]
