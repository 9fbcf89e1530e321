"""Binding Gaussians to nodes (engine/geometry/binding.py): chunked K-NN and RBF weights."""

import pytest
import torch

from engine.geometry import binding


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


def test_knn_matches_brute_force_and_chunking_is_invisible():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(3000, 3, generator=g)
    nodes = torch.randn(257, 3, generator=g)
    idx, d2 = binding.knn_nodes(pts, nodes, 5)
    brute = torch.cdist(pts.double(), nodes.double()) ** 2
    ref_d, ref_i = torch.topk(brute, 5, largest=False)
    torch.testing.assert_close(d2.double(), ref_d, atol=1e-4, rtol=1e-4)
    assert (idx == ref_i).float().mean() > 0.999  # ties aside
    idx2, d22 = binding.knn_nodes(pts, nodes, 5, chunk_size=77)
    assert torch.equal(idx, idx2) and torch.equal(d2, d22)


def test_rbf_weights_normalised_and_finite_far_away():
    nodes = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    radii = torch.tensor([0.1, 0.1, 0.2])
    pts = torch.tensor([[0.1, 0, 0], [1e4, 1e4, 0.0]])
    idx, w = binding.bind_gaussians(pts, nodes, radii, 3)
    assert torch.isfinite(w).all()
    torch.testing.assert_close(w.sum(-1), torch.ones(2))
    assert int(idx[0, 0]) == 0 and float(w[0, 0]) > 0.99
    # matches the paper's formula on a well-conditioned point
    d2 = ((pts[:1, None] - nodes[idx[:1]]) ** 2).sum(-1)
    raw = torch.exp(-d2 / (2 * radii[idx[:1]] ** 2))
    torch.testing.assert_close(w[:1], raw / raw.sum(-1, keepdim=True))


def test_knn_memory_bound_for_a_million_gaussians():
    chunk = binding.knn_chunk_size(5000, itemsize=4)
    temporaries = chunk * 5000 * 4 * 3
    assert temporaries <= binding.DEFAULT_MEMORY_BUDGET <= 2 * 1024**3
    assert chunk >= 1000  # still large chunks: few Python iterations for 1M points


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bind_gaussians_device_and_dtype(device, dtype):
    g = torch.Generator().manual_seed(1)
    pts = torch.randn(500, 3, generator=g, dtype=dtype)
    nodes = torch.randn(40, 3, generator=g, dtype=dtype)
    radii = torch.rand(40, generator=g, dtype=dtype) + 0.1
    idx, w = binding.bind_gaussians(pts.to(device), nodes.to(device), radii.to(device), 4, chunk_size=64)
    assert idx.dtype == torch.long and idx.shape == (500, 4) and w.dtype == dtype and w.device.type == device
    ref_i, ref_w = binding.bind_gaussians(pts, nodes, radii, 4)
    assert (idx.cpu() == ref_i).float().mean() > 0.99
    torch.testing.assert_close(w.sum(-1).cpu(), torch.ones(500, dtype=dtype))


def test_knn_float32_far_from_origin_keeps_the_true_neighbours():
    # a scene 1 km from the origin with nodes ~cm apart: |c|² - 2p·c would cancel in float32
    g = torch.Generator().manual_seed(3)
    offset = torch.tensor([1000.0, -2000.0, 500.0], dtype=torch.float64)
    nodes64 = offset + 0.05 * torch.randn(300, 3, generator=g, dtype=torch.float64)
    pts64 = offset + 0.05 * torch.randn(2000, 3, generator=g, dtype=torch.float64)
    idx, d2 = binding.knn_nodes(pts64.float(), nodes64.float(), 4)
    # reference on the float32-rounded inputs, in float64
    ref_d, ref_i = torch.topk(torch.cdist(pts64.float().double(), nodes64.float().double()) ** 2, 4, largest=False)
    assert (idx == ref_i).float().mean() > 0.99
    torch.testing.assert_close(d2.double(), ref_d, atol=1e-3, rtol=0)
