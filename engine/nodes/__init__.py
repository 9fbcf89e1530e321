"""Node initialisation: MANI (motion-adaptive merging of patch candidates), baselines,
radii / graph, and spline trajectories from lifted tracks.

Entry point: :func:`initialise_nodes` (plain tensors in, :class:`NodeSet` out).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..geometry.hermite import catmull_rom_tangents
from ..geometry.quaternion import quat_identity
from .baselines import farthest_point_sampling, tracklet_clusters, uniform_voxel_centres
from .candidates import Candidates, build_candidates, choose_keyframes
from .graph import node_graph, node_radii
from .mani import ManiConfig, ManiResult, mani_compress
from .nodeset import NodeSet
from .trajectory import clean_tracks3d, fit_node_rotations, fit_node_trajectories, lift_tracks, node_frame_rotations

__all__ = ["NodeInitConfig", "ManiConfig", "ManiResult", "assemble_nodeset", "NodeSet", "Candidates", "initialise_nodes", "build_candidates",
           "choose_keyframes", "mani_compress", "node_graph", "node_radii", "lift_tracks", "clean_tracks3d",
           "fit_node_trajectories", "farthest_point_sampling", "uniform_voxel_centres", "tracklet_clusters",
           "METHODS"]

#: Initialisers selectable through ``NodeInitConfig.method``.
METHODS = ("mani", "fps", "voxel", "tracklet")


@dataclass
class NodeInitConfig:
    """Everything :func:`initialise_nodes` needs besides the data.

    method : one of :data:`METHODS`; trajectory : ``"spline"`` (fit from tracks) or
    ``"static"`` (keys = centre, for ablations).
    """

    method: str = "mani"
    mani: ManiConfig = field(default_factory=ManiConfig)
    num_keyframes: int = 12        #: frames whose patches become candidates
    dynamic_density: int = 3       #: > 1: moving pixels also become candidates on a grid this much finer than the patches
    num_keys: int = 10             #: spline keys, evenly spaced in [0, 1]
    graph_k: int = 8               #: neighbours in graph_idx
    radius_k: int = 4              #: neighbours for the radius
    radius_factor: float = 1.0
    trajectory: str = "spline"
    rotations: str = "tracks"      #: "tracks": rigid rotation of each node's tracks; "identity": the paper's start
    vis_threshold: float = 0.5
    edge_tolerance: float = 0.05   #: lifted samples on a depth edge (3×3 max/min ratio above 1 + this) are dropped
    clean_tracks: bool = True      #: split / drop / freeze / filter lifted tracks (``clean_tracks3d``)
    jump_tol: float = 0.1          #: log-depth step that splits a track
    min_track_len: int = 4         #: shorter track pieces are dropped
    depth_window: int = 5          #: median filter (frames) on moving tracks' depth
    static_fg: float = 0.5         #: tracks with a lower median dynamic prior are frozen
    k_tracks: int = 8
    support_radius: float = 2.0    #: tracks within this many node radii support a node
    smoothness: float = 1e-2       #: velocity penalty relative to the mean support
    irls_iters: int = 3
    fallback: str = "graph"        #: "graph" or "static" for nodes without tracks
    max_residual_ratio: float | None = 1.0  #: fall back when fit residual > this × explained motion (None: off)
    chain_hop_weight: float = 0.5  #: past its own tracks a node follows the tracks around it (path_chain), each new set of
                                   #: tracks weighted by this factor once more; 0: held where its own tracks end
    seed: int = 0


def _snap_frame(t: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    return (t.unsqueeze(1) - times.float().unsqueeze(0)).abs().argmin(1)


def initialise_nodes(depth, K, w2c, times, tokens, patch_centers, fg, tracks_xy, tracks_vis,
                     config: NodeInitConfig = NodeInitConfig(), tracks_depth=None,
                     tracks_translation_only=None) -> NodeSet:
    """Build the initial node set.

    Parameters
    ----------
    depth : (F, H, W); K : (F, 3, 3); w2c : (F, 4, 4) OpenCV; times : (F,) engine time.
    tokens : (F, Gh, Gw, D); patch_centers : (Gh, Gw, 2) pixels of the depth image.
    fg : (F, H, W) dynamic prior; tracks_xy : (P, F, 2); tracks_vis : (P, F); tracks_depth : (P, F)
    a depth the tracks carry themselves (NaN where the depth map decides) or None;
    tracks_translation_only : (P,) bool or None: tracks that follow their object's translation
    alone (``Tracks.translation_only``), left out of the node rotations.
    config : NodeInitConfig (``config.mani.budget`` is the node budget for every method).

    Returns
    -------
    NodeSet with ``p_dyn`` (MANI: per-voxel tendency; baselines: the nearest candidate's
    foreground prior).
    """
    depth, K, w2c, times = (torch.as_tensor(x).float() for x in (depth, K, w2c, times))
    keyframes = choose_keyframes(depth.shape[0], config.num_keyframes)
    cand = build_candidates(depth, K, w2c, times, torch.as_tensor(tokens).float(),
                            torch.as_tensor(patch_centers).float(), torch.as_tensor(fg).float(), keyframes, config.dynamic_density)
    tracks3d = lift_tracks(torch.as_tensor(tracks_xy).float(), torch.as_tensor(tracks_vis), depth, K, w2c,
                           config.vis_threshold, config.edge_tolerance,
                           None if tracks_depth is None else torch.as_tensor(tracks_depth).float())
    turns = None if tracks_translation_only is None else ~torch.as_tensor(tracks_translation_only, dtype=torch.bool)
    if config.clean_tracks:
        tracks3d, src = clean_tracks3d(tracks3d, torch.as_tensor(tracks_xy).float(), K, w2c, torch.as_tensor(fg).float(),
                                     config.jump_tol, config.min_track_len, config.depth_window, config.static_fg)
        turns = None if turns is None else turns[src]
    budget = config.mani.budget
    if config.method == "mani":
        res = mani_compress(cand.positions, cand.tokens, cand.fg, config.mani, time=cand.time)
        centers, src_time, p_dyn = res.positions, res.time, res.p_dyn
    else:
        if config.method == "fps":
            sel = farthest_point_sampling(cand.positions, budget, config.seed)
            centers, src_time = cand.positions[sel], cand.time[sel]
        elif config.method == "voxel":
            centers = uniform_voxel_centres(cand.positions, budget)
            src_time = None
        elif config.method == "tracklet":
            centers = tracklet_clusters(tracks3d, budget, ref_frame=0, seed=config.seed)
            src_time = torch.full((centers.shape[0],), float(times[0]))
        else:
            raise ValueError(f"unknown node initialiser {config.method!r}; expected one of {METHODS}")
        from ..geometry.binding import knn_nodes
        nearest, _ = knn_nodes(centers, cand.positions, 1)
        p_dyn = cand.fg[nearest[:, 0]]
        if src_time is None:  # voxel means mix frames: take the nearest candidate's frame
            src_time = cand.time[nearest[:, 0]]
    return assemble_nodeset(centers, src_time, p_dyn, tracks3d, times, config, turns)


def assemble_nodeset(centers, src_time, p_dyn, tracks3d, times, config: NodeInitConfig,
                     turns: torch.Tensor | None = None) -> NodeSet:
    """Radii, graph and trajectories for given centres (shared by every initialiser).

    ``turns [P]`` bool or None: the tracks of ``tracks3d`` whose motion shows how their object
    turns; the node rotations are fitted to those alone (None: all)."""
    n = centers.shape[0]
    key_times = torch.linspace(0, 1, max(2, config.num_keys))
    radii = node_radii(centers, config.radius_k, config.radius_factor)
    graph_idx, _ = node_graph(centers, config.graph_k)
    if config.rotations not in ("tracks", "identity"):
        raise ValueError(f"unknown rotation init {config.rotations!r}; expected 'tracks' or 'identity'")
    rot_keys = quat_identity(n, key_times.shape[0])
    rot_tan = torch.zeros_like(rot_keys)
    if config.trajectory == "spline":
        frame = _snap_frame(src_time, times)
        frame_rot = None
        if config.rotations == "tracks":
            # a track that follows its object's translation alone would say it never turns
            turning = tracks3d if turns is None else tracks3d[turns]
            frame_rot, frame_ok = node_frame_rotations(centers, frame, radii, turning, config.k_tracks,
                                                       config.support_radius)
            rot_keys, _ = fit_node_rotations(frame_rot, frame_ok, times, key_times)
            rot_tan = catmull_rom_tangents(key_times, rot_keys)
        pos_keys, pos_tan, support = fit_node_trajectories(
            centers, frame, radii, tracks3d, times, key_times, graph_idx,
            config.k_tracks, config.support_radius, config.smoothness, None, config.irls_iters,
            config.fallback, max_residual_ratio=config.max_residual_ratio, frame_rot=frame_rot,
            chain_hop_weight=config.chain_hop_weight)
    elif config.trajectory == "static":
        pos_keys = centers.unsqueeze(1).expand(-1, key_times.shape[0], -1).clone()
        pos_tan = torch.zeros_like(pos_keys)
        support = torch.zeros(n)
    else:
        raise ValueError(f"unknown trajectory init {config.trajectory!r}; expected 'spline' or 'static'")
    return NodeSet(centers.float(), radii.float(), key_times, pos_keys.float(), pos_tan.float(), rot_keys.float(),
                   rot_tan.float(), p_dyn.float(), graph_idx, src_time.float(), config.method,
                   {"support": support})
