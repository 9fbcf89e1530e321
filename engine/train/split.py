"""Static / dynamic split of nodes and Gaussians.

Why: with one K-nearest-node binding over every node, a Gaussian on a moving object is
blended with the static background nodes next to it (and a background Gaussian with the
moving nodes): at the RBF weights of the demo scenes a moving Gaussian bound to two moving
and two static nodes follows its object at about half speed, so the object smears into a
ghost along its path, and ARAP edges between moving and static nodes pull the moving ones
still. Splitting the model the way Shape of Motion / MoSca do fixes the mechanism:

* every node is *dynamic* or *static* (:func:`node_dynamic_flags`, from the dynamic prior);
  static nodes keep their rest keys (their gradients are zeroed), so the Gaussians they
  carry are undeformed;
* every Gaussian is dynamic or static (where it was seeded: the dynamic prior at its
  pixel), and binds only to nodes of its own class (:func:`bind_within_class`);
* the ARAP graph links nodes of the same class only (:func:`graph_within_class`).

With every flag True the model is the single-class model of before.
"""

from __future__ import annotations

import torch

from ..geometry.binding import bind_gaussians, rbf_weights


def node_dynamic_flags(p_dyn: torch.Tensor, node_fg: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """Dynamic nodes ``[N] bool``: the initialiser's dynamic tendency ``p_dyn`` (the prior
    where the node was seen) or the prior along the node's initial trajectory ``node_fg``
    reaches ``threshold``. Both count: a node that starts at rest on a fast object sees the
    object only in the frames it passes (low ``node_fg``) but was seeded on it (high
    ``p_dyn``); a track-fitted node follows its object (high ``node_fg``)."""
    return torch.maximum(p_dyn, node_fg) >= threshold


def knn_rbf(points: torch.Tensor, nodes: torch.Tensor, radii: torch.Tensor, k: int, fused: bool = True):
    """K nearest ``nodes [M, 3]`` of ``points [P, 3]`` and their normalised RBF weights,
    ``([P, k] long, [P, k])``; ``k`` may exceed M (the nearest node repeats with weight 0).

    ``fused``: on the CPU, the K-NN ranking of :func:`~engine.geometry.binding.bind_gaussians`
    in one Numba pass, without its ``[P, M]`` score matrix and top-k (~3x less CPU at 30k
    Gaussians x 1k nodes); ``bind_gaussians`` is the reference and the GPU path.
    """
    kk = min(k, nodes.shape[0])
    if points.shape[0] == 0:
        return (torch.zeros(0, k, dtype=torch.long, device=points.device),
                torch.zeros(0, k, dtype=points.dtype, device=points.device))
    from .fused import fused_available, fused_knn

    if fused and fused_available(points, nodes):
        idx = fused_knn(points.contiguous(), nodes.contiguous(), kk).to(points.device)
        diff = points.unsqueeze(1) - nodes[idx]
        w = rbf_weights((diff * diff).sum(-1), radii[idx])
    else:
        idx, w = bind_gaussians(points, nodes, radii, kk)
    if kk < k:  # pad: repeat the nearest node with zero weight
        pad = k - kk
        idx = torch.cat([idx, idx[:, :1].expand(-1, pad)], 1)
        w = torch.cat([w, torch.zeros(w.shape[0], pad, dtype=w.dtype, device=w.device)], 1)
    return idx, w


def bind_within_class(points: torch.Tensor, point_dyn: torch.Tensor, nodes: torch.Tensor, node_dyn: torch.Tensor,
                      radii: torch.Tensor, k: int, fused: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Bind each point to its ``k`` nearest nodes *of its own class*.

    Parameters
    ----------
    points : [P, 3] canonical positions; point_dyn : [P] bool;
    nodes : [N, 3] canonical node centres; node_dyn : [N] bool; radii : [N];
    fused : as :func:`knn_rbf`.

    Returns
    -------
    idx : [P, k] long (into all N nodes), w : [P, k] normalised RBF weights. A class
    without nodes falls back to every node (so a scene with no moving node is the
    single-class model).
    """
    idx = torch.zeros(points.shape[0], k, dtype=torch.long, device=points.device)
    w = torch.zeros(points.shape[0], k, dtype=points.dtype, device=points.device)
    all_nodes = torch.arange(nodes.shape[0], device=nodes.device)
    for cls in (True, False):  # two classes, each one vectorised K-NN
        sel_p = point_dyn == cls
        if not bool(sel_p.any()):
            continue
        sel_n = node_dyn == cls
        ids = all_nodes[sel_n] if bool(sel_n.any()) else all_nodes
        i, wi = knn_rbf(points[sel_p], nodes[ids], radii[ids], k, fused)
        idx[sel_p] = ids[i]
        w[sel_p] = wi.to(w.dtype)
    return idx, w


def graph_within_class(centers: torch.Tensor, node_dyn: torch.Tensor | None, k: int,
                       paths: torch.Tensor | None = None) -> torch.Tensor:
    """``[N, k]`` neighbour indices among nodes of the same class (``node_dyn`` None: one
    class; a class smaller than ``k + 1`` repeats its nearest neighbour; a class of one links
    to itself, which ARAP reads as a zero-length edge). With ``paths [N, T, 3]`` (the nodes' positions at their
    keys) neighbours are nearest by the largest distance between their paths
    (:func:`engine.nodes.graph.path_graph`), else by ``centers [N, 3]``."""
    from ..nodes.graph import node_graph, path_graph

    n = centers.shape[0]
    if node_dyn is None:
        node_dyn = torch.ones(n, dtype=torch.bool, device=centers.device)
    out = torch.arange(n, device=centers.device).unsqueeze(1).expand(n, k).clone()
    all_nodes = torch.arange(n, device=centers.device)
    for cls in (True, False):
        ids = all_nodes[node_dyn == cls]
        m = ids.shape[0]
        if m < 2:
            continue
        kk = min(k, m - 1)
        g = (node_graph(centers[ids].cpu(), kk) if paths is None else path_graph(paths[ids].detach().cpu(), kk))[0]
        g = g.to(centers.device)
        if kk < k:
            g = torch.cat([g, g[:, :1].expand(-1, k - kk)], 1)
        out[ids] = ids[g]
    return out


#: a node transform within this of the identity (dual part: times the scene extent) is the
#: identity to float32 rounding: static nodes' rest keys reproduce their centres to ~2e-7
REST_TOL = 1e-6


@torch.no_grad()
def resting_nodes(model, dq_nodes: torch.Tensor) -> torch.Tensor | None:
    """``[N] bool``: the static nodes of ``model`` (a :class:`~engine.train.model.DynamicScene`)
    whose transform ``dq_nodes [N, 8]`` is the identity to float rounding (``REST_TOL``, the
    dual part relative to the scene extent), or None when no node can be (no split, or MLP
    motion, whose static nodes are not frozen).

    Why: static nodes keep their rest keys (:func:`freeze_static_nodes`), so the Gaussians
    bound to them are undeformed by design; blending them anyway was three quarters of the
    deformation's work on a typical scene (the fused deformation passes them through,
    ``engine/train/fused.py``). The transform is still checked, so a static node moved on
    purpose (keys edited in Blender and fine-tuned) deforms its Gaussians as before."""
    if model.mlp is not None or model.pos_keys is None or bool(model.node_dyn.all()):
        return None
    dev = (dq_nodes - dq_nodes.new_tensor([1.0, 0, 0, 0, 0, 0, 0, 0])).abs()
    near = (dev[:, :4].amax(1) <= REST_TOL) & (dev[:, 4:].amax(1) <= REST_TOL * max(1.0, float(model.extent)))
    return ~model.node_dyn & near


def freeze_static_nodes(pos_keys: torch.Tensor | None, rot_keys: torch.Tensor | None, node_dyn: torch.Tensor) -> None:
    """Zero the gradients of static nodes' keys (call between backward and the optimiser
    step): with zero gradients from the first step Adam's moments stay zero, so the keys
    never move and the Gaussians bound to them stay undeformed."""
    static = ~node_dyn
    if not bool(static.any()):
        return
    for keys in (pos_keys, rot_keys):
        if keys is not None and keys.grad is not None:
            keys.grad[static] = 0.0
