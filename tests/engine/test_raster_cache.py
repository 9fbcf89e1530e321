"""The CPU rasteriser gives the same numbers whether its kernels were just compiled or
loaded from Numba's on-disk cache (a first run after install must train like every later
run of the same command)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

ROOT = Path(__file__).resolve().parents[2]

# forward + backward of a random 3k-Gaussian scene; prints the Numba compilations it took
# and a hash of the image and of every gradient
SCRIPT = r"""
import hashlib, json
import torch
from numba.core import event
from engine.raster import render

torch.set_num_threads(2)
g = torch.Generator().manual_seed(0)
n = 3000
means = (torch.rand(n, 3, generator=g) - 0.5) * 2 + torch.tensor([0.0, 0.0, 4.0])
quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
scales = torch.rand(n, 3, generator=g) * 0.05 + 0.01
opac = torch.rand(n, generator=g)
colors = torch.rand(n, 3, generator=g)
params = [means, quats, scales, opac, colors]
for p in params:
    p.requires_grad_(True)
K = torch.tensor([[120.0, 0, 80], [0, 120.0, 60], [0, 0, 1]])
with event.install_recorder("numba:compile") as rec:
    out = render(means, quats, scales, opac, colors=colors, w2c=torch.eye(4), K=K, width=160, height=120,
                 background=torch.zeros(3), backend="cpu")
    (out.rgb.square().sum() + out.alpha.sum() + out.depth.sum()).backward()
compiled = sum(1 for _t, ev in rec.buffer if ev.kind == "numba:compile" and ev.is_start)
digest = lambda ts: hashlib.sha256(b"".join(t.detach().contiguous().numpy().tobytes() for t in ts)).hexdigest()
print(json.dumps({"compiled": compiled, "image": digest([out.rgb, out.alpha, out.depth]),
                  "grads": {name: digest([p.grad]) for name, p in zip("means quats scales opac colors".split(), params)}}))
"""


def _run(cache_dir: Path) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "PYTHONPATH": str(ROOT)}
    res = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=600, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_compiled_and_cached_kernels_agree_bitwise(tmp_path):
    fresh = _run(tmp_path)  # compiles every kernel it calls into the empty cache
    cached = _run(tmp_path)  # loads them
    assert fresh["compiled"] > 0 and cached["compiled"] == 0
    assert cached["image"] == fresh["image"]
    assert cached["grads"] == fresh["grads"]
