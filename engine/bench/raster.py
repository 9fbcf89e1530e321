"""Rasteriser speed: forward and forward+backward wall time, peak RSS, Gaussian-pixel rate.

Each (backend, gaussians, resolution) row runs in a fresh subprocess so that its
``peak_rss_mb`` belongs to that configuration alone. Times are medians over ``--repeats``
runs after one warm-up; ``first_call_ms`` is the first forward+backward of the process
(Numba kernels are loaded from the on-disk cache, or compiled when the cache is cold) and is
excluded from the timings. ``fwdbwd_ms`` includes SH-free colour input, projection, binning,
compositing and the full backward to means/quats/scales/opacities/colours.
``fwdbwd_min_ms`` is the best forward+backward wall time and ``fwdbwd_cpu_ms`` the median
process CPU time (all threads) of one forward+backward: both help read figures taken on a
shared machine. ``gauss_px_per_s`` = Gaussian-pixel pairs with ``alpha >= 1/255`` (pixel
centres inside each Gaussian's cut-off ellipse, before early stop: a count of the useful
work that does not depend on the kernel; the same count for every backend) divided by
``fwd_ms``. (Before 2026-11-23 17:00 UTC it counted the CPU kernel's row spans, each
widened by a pixel per side for rounding: a few per cent more pairs.) Each row's worker runs with ``OMP_WAIT_POLICY=PASSIVE`` unless the caller set it,
like ``python -m engine`` (recorded as ``omp_wait_policy``).

Scene: N Gaussians uniformly in the view frustum at depth 2..6, random rotations, isotropic-ish
log-normal scales whose projected sigma is about ``0.7 * W / sqrt(N)`` pixels (so image
coverage is similar at every size), opacities uniform in [0.05, 1], random colours.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from .common import machine_description, peak_rss_mb, time_call

HELP = "Gaussian rasteriser forward / forward+backward timings"


def add_arguments(parser) -> None:
    parser.add_argument("--backend", nargs="+", default=None,
                        help="backends to time (default: cpu, plus gsplat when CUDA is present)")
    parser.add_argument("--gaussians", nargs="+", type=int, default=[10_000, 50_000, 200_000])
    parser.add_argument("--res", nargs="+", type=int, default=[128, 256, 512], help="square image sizes")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=None, help="torch/Numba threads (default: torch's)")
    parser.add_argument("--device", default=None, help="torch device (default: cuda for gsplat, else cpu)")
    parser.add_argument("--in-process", action="store_true", help="no subprocess per row (RSS then cumulative)")
    parser.add_argument("--pause", type=float, default=0.0,
                        help="seconds to sleep between rows (lets a throttled/shared VM recover)")
    parser.add_argument("--_worker", nargs=3, metavar=("BACKEND", "N", "RES"), help=argparse_suppress())


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


def make_scene(n: int, res: int, device="cpu", seed: int = 0):
    """Deterministic benchmark scene; returns a dict of render() keyword arguments."""
    import torch

    g = torch.Generator().manual_seed(seed)
    f = 0.9 * res
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    uv = (torch.rand(n, 2, generator=g) - 0.5) * 1.1 * res  # a bit past the borders
    means = torch.stack([uv[:, 0] * z / f, uv[:, 1] * z / f, z], -1)
    sigma_px = 0.7 * res / n ** 0.5
    scales = (sigma_px * z / f)[:, None] * torch.exp(0.4 * torch.randn(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opac = 0.05 + 0.95 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[f, 0, res / 2], [0, f, res / 2], [0, 0, 1.0]])
    dev = torch.device(device)
    return dict(means=means.to(dev), quats=quats.to(dev), scales=scales.to(dev), opacities=opac.to(dev),
                colors=colors.to(dev), w2c=torch.eye(4, device=dev), K=K.to(dev), width=res, height=res,
                background=torch.zeros(3, device=dev))


def count_evaluations(scene) -> int:
    """Gaussian-pixel pairs with ``alpha >= 1/255`` (pixel centres inside the cut-off
    ellipse ``sigma <= ln(255 o)``) over each Gaussian's tiles, before early stop."""
    from ..raster import cpu as C
    from ..raster import cpu_numba as KN

    s = scene
    m2, cn, dz, radii, ext = C.project(s["means"].cpu(), s["quats"].cpu(), s["scales"].cpu(),
                                       s["opacities"].cpu(), s["w2c"].cpu(), s["K"].cpu(), s["width"], s["height"])
    W = H = s["width"]
    t = (W + KN.TILE - 1) // KN.TILE
    off, _, data, idata, _ = KN.bin_tiles(dz.numpy(), m2.numpy(), cn.numpy(), s["colors"].cpu().numpy(),
                                          s["opacities"].cpu().numpy(), ext.numpy(), radii.numpy(), W, H, t, t)
    return int(_count(off, data, idata, W, H, t))


def _count(off, data, idata, W, H, tiles_x):
    import math

    from numba import njit

    from ..raster.cpu_numba import R_OP, R_X0, R_X1, R_Y0, R_Y1, TILE

    @njit(cache=False)
    def count(off, data, idata, W, H, tiles_x):
        total = 0
        for tile in range(off.shape[0] - 1):
            oy = (tile // tiles_x) * TILE
            ox = (tile % tiles_x) * TILE
            for k in range(off[tile], off[tile + 1]):
                mx, my = data[k, 0], data[k, 1]
                a, b, c = data[k, 2], data[k, 3], data[k, 4]
                thr = math.log(max(255.0 * data[k, R_OP], 1.0))  # sigma <= thr <=> alpha >= 1/255
                lo, hi = max(idata[k, R_X0], ox), min(idata[k, R_X1], ox + TILE, W)
                for py in range(max(idata[k, R_Y0], oy), min(idata[k, R_Y1], oy + TILE, H)):
                    dy = float(py) + 0.5 - my
                    # pixel centres x + 0.5 of the row inside the ellipse sigma <= thr
                    disc = b * b * dy * dy - a * (c * dy * dy - 2.0 * thr)
                    if disc < 0:
                        continue
                    r = math.sqrt(disc) / a
                    cen = mx - b * dy / a - 0.5
                    x0 = max(lo, int(math.ceil(cen - r)))
                    x1 = min(hi, int(math.floor(cen + r)) + 1)
                    total += max(0, x1 - x0)
        return total

    return count(off, data, idata, W, H, tiles_x)


def run_one(backend: str, n: int, res: int, repeats: int, device: str | None) -> dict:
    """Time one configuration in this process."""
    import time

    import torch

    from ..raster import render

    dev = device or ("cuda" if backend == "gsplat" else "cpu")
    scene = make_scene(n, res, dev)
    params = [scene[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    rest = {k: scene[k] for k in ("w2c", "K", "width", "height", "background")}
    sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)

    def fwd():
        with torch.no_grad():
            out = render(*params[:4], colors=params[4], backend=backend, **rest)
        sync()
        return out

    def fwdbwd():
        out = render(*params[:4], colors=params[4], backend=backend, **rest)
        (out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        for p in params:
            p.grad = None
        sync()

    t0 = time.perf_counter()
    fwdbwd()
    first = (time.perf_counter() - t0) * 1000.0
    fwd_ms = time_call(fwd, repeats=repeats)
    fb_ms = time_call(fwdbwd, repeats=repeats)
    # On a shared machine the median wall time is inflated by other processes; the best
    # wall time and the process CPU time per call (all threads) are less sensitive to that.
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fwdbwd()
        walls.append((time.perf_counter() - w0) * 1000.0)
        cpus.append((time.process_time() - c0) * 1000.0)
    cpus.sort()
    try:
        evals = count_evaluations(scene)
    except Exception:  # noqa: BLE001 - counting is informational only
        evals = None
    return {"backend": backend, "gaussians": n, "width": res, "height": res, "threads": torch.get_num_threads(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default"), "device": dev, "fwd_ms": round(fwd_ms, 3), "fwdbwd_ms": round(fb_ms, 3),
            "fwdbwd_min_ms": round(min(walls), 3), "fwdbwd_cpu_ms": round(cpus[len(cpus) // 2], 3),
            "first_call_ms": round(first, 1), "peak_rss_mb": round(peak_rss_mb(), 1),
            "gauss_px_evals": evals,
            "gauss_px_per_s": None if not evals else float(f"{evals / (fwd_ms / 1000.0):.4g}")}


def run(args) -> list[dict]:
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    if args._worker:
        b, n, r = args._worker
        row = run_one(b, int(n), int(r), args.repeats, args.device)
        sys.stdout.write("ROW " + json.dumps(row) + "\n")
        return []
    backends = args.backend
    if backends is None:
        from ..raster.api import gsplat_available

        backends = ["cpu"] + (["gsplat"] if gsplat_available() else [])
    rows = []
    for b in backends:
        for r in args.res:
            for n in args.gaussians:
                if b == "reference" and n * r * r > 20_000_000:
                    # dense O(N*H*W) oracle: tens of GB at these sizes
                    rows.append({"backend": b, "gaussians": n, "width": r, "height": r,
                                 "error": "skipped: reference is dense O(N*H*W), too large"})
                    continue
                if rows and args.pause > 0:
                    time.sleep(args.pause)
                if args.in_process:
                    rows.append(run_one(b, n, r, args.repeats, args.device))
                    continue
                cmd = [sys.executable, "-m", "engine.bench", "raster", "--_worker", b, str(n), str(r),
                       "--repeats", str(args.repeats)]
                if args.threads:
                    cmd += ["--threads", str(args.threads)]
                if args.device:
                    cmd += ["--device", args.device]
                pkg_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
                env = dict(os.environ, PYTHONPATH=pkg_root + os.pathsep + os.environ.get("PYTHONPATH", ""))
                # What `python -m engine` sets (engine/__main__.py): with OpenMP's default active
                # waiting, idle torch and Numba workers spin between kernels and, on a busy
                # 2-core machine, starve the thread doing the work (10k@128 measured 160 ms
                # instead of 29 ms at load 6). Override by setting OMP_WAIT_POLICY yourself.
                env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("ROW ")]
                if proc.returncode != 0 or not lines:
                    rows.append({"backend": b, "gaussians": n, "width": r, "height": r,
                                 "error": (proc.stderr.strip().splitlines() or ["failed"])[-1]})
                    continue
                rows.append(json.loads(lines[-1][4:]))
    sys.stderr.write(f"machine: {machine_description()}\n")
    return rows
