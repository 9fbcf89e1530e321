"""Numba CPU kernels: projection, tile binning, compositing, and their hand-derived backward.

All arithmetic is float32 (every literal is a module-level ``np.float32`` constant: a bare
Python float literal would silently promote the expression to float64 in Numba and stop
LLVM from vectorising). Kernels are compiled with ``cache=True`` and
``error_model='numpy'`` (no ZeroDivisionError checks in the inner loops).

Pipeline (forward)::

    project_forward   prange over blocks of Gaussians: EWA projection, conic, radii,
                      alpha>=1/255 box (vectorised across Gaussians, see its docstring)
    bin_tiles         parallel counting sort of instances by tile (per-chunk counts and
                      cursors), then per tile (strands of tiles, one per thread,
                      :func:`tile_strands`): depth sort (ties keep the lower
                      Gaussian index) fused with the copy of per-instance data into tile order
    raster_forward    per tile (strands): front-to-back compositing with early stop

Backward mirrors it: ``raster_backward`` walks each tile's list in reverse (as in 3DGS),
recovering the transmittance by division, and writes per-instance gradients in
Gaussian-major order, which ``sum_instances`` sums per Gaussian (contiguous ranges of
Gaussians of equal work, contiguous rows, no write conflicts); ``project_backward`` chains
them to the 3D parameters. Semantics are those of :mod:`engine.raster.reference`.

Why one file for five stages: the kernels share constants (tile size, record fields, the tile
state's layout) and inline helpers, and a cached Numba kernel freezes the globals and
inlined functions it uses while the on-disk cache checks only the kernel's own source file.
Split across files, an edit to a shared constant would leave the other files' cached kernels
running the old value.

Where the time goes (200k Gaussians at 512x512, 2 threads, wall ms, best of 15 per stage,
2026-11-23 on the shared 2-core machine, kernel revision 088fb47; later figures in
docs/benchmarks.md): raster_backward ~32, raster_forward ~14.5,
bin_tiles ~12.5 (per-tile radix sort + copy of the records into tile order ~7.8, cache-miss
bound; counting ~2.7; fill ~1.7), project_forward ~2.3, project_backward ~2.3,
sum_instances ~1.3, Python/torch glue ~4.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np
from numba import get_num_threads, get_parallel_chunksize, njit, prange, set_parallel_chunksize

F0 = np.float32(0.0)
F1 = np.float32(1.0)
F2 = np.float32(2.0)
F3 = np.float32(3.0)
F4 = np.float32(4.0)
HALF = np.float32(0.5)
ALPHA_MIN = np.float32(1.0 / 255.0)
ALPHA_MAX = np.float32(0.99)
T_MIN = np.float32(1e-4)
F255 = np.float32(255.0)
BOX_SCALE = np.float32(1.0001)
BOX_PAD = np.float32(0.01)
TENTH = np.float32(0.1)
FOV_PAD = np.float32(0.3)
TILE = 16
# tile_strands' per-tile work on top of its instance count (reading the tile's pixels in and
# out costs about as much as compositing this many instances)
TILE_FIXED_WORK = 8
# Binning splits the Gaussians into at most MAX_BIN_CHUNKS chunks of >= BIN_CHUNK (each
# chunk has its own tile counts and cursors; few enough that the prefix sums stay tiny).
BIN_CHUNK = 2048
MAX_BIN_CHUNKS = 16


# Chunk size of the projection's prange and its backward's: PROJ_CHUNK blocks (of PF_BLK /
# PB_BLK Gaussians). It only takes effect on a threading layer that hands chunks out as
# threads free up (TBB); Numba's OpenMP and workqueue layers split a prange into one
# contiguous block per thread whatever the chunk size (measured 2026-11-27: a loop whose first
# half holds 90 % of the work ran in the same time with chunk sizes 0, 1 and 4). The
# projection's work is uniform per Gaussian and does not mind; the kernels whose work is not
# uniform balance it themselves (:func:`tile_strands`, :func:`instance_bounds`).
PROJ_CHUNK = 4


def dynamic(kernel, chunk, *args):
    """Call a kernel with its prange chunk size set to ``chunk`` iterations (dynamic hand-out
    on the TBB layer only; see PROJ_CHUNK)."""
    prev = get_parallel_chunksize()
    set_parallel_chunksize(chunk)
    try:
        return kernel(*args)
    finally:
        set_parallel_chunksize(prev)


# Scratch buffers reused across calls. For small scenes glibc hands the freed megabytes
# back to the kernel after every call (heap trimming) and the first write to each page of
# the next call's arrays faults: ~540 faults, ~1 ms of 5 ms per forward+backward at 10k
# Gaussians, 128x128. Large buffers are not pooled: arrays of tens of MB freed every call
# raise malloc's mmap/trim thresholds so everything is recycled without faults, whereas
# pooling them keeps the thresholds low and makes the *other* allocations fault
# (measured at 200k@512: ~4000 faults per call, 20% more CPU).
_POOL: dict = {}
_POOL_PER_KEY = 2
POOL_MAX_BYTES = 4 << 20
_POOL_LOCK = threading.Lock()  # renders from several Python threads must not share a buffer


def pooled(key, size, dtype):
    """A 1-D array of ``size`` elements of ``dtype`` (uninitialised), carved from a pooled
    buffer that nothing else references any more (checked with the reference count, so a
    buffer still held by a tensor, an autograd context or a view is never handed out
    twice); allocates when every pooled buffer for ``key`` is in use, or when the request
    is above POOL_MAX_BYTES."""
    dtype = np.dtype(dtype)
    if size * dtype.itemsize > POOL_MAX_BYTES:
        return np.empty(size, dtype)
    with _POOL_LOCK:
        bufs = _POOL.setdefault(key, [])
        for i in range(len(bufs)):
            b = bufs[i]
            # references: the list, b, getrefcount's argument (no enumerate: its cached
            # result tuple would hold one more)
            if sys.getrefcount(b) == 3 and b.dtype == dtype:
                if b.size < size:
                    b = bufs[i] = np.empty(size + size // 8 + 64, dtype)
                return b[:size]
        b = np.empty(size + size // 8 + 64, dtype)
        if len(bufs) < _POOL_PER_KEY:
            bufs.append(b)
        return b[:size]


_JIT = dict(cache=True, error_model="numpy", nogil=True)


@njit(**_JIT)
def tile_strands(offsets, nstrands):
    """Split the tiles into ``nstrands`` strands of about equal work: longest-processing-time
    first (each tile, heaviest first, to the strand with the least work so far), a tile's
    work taken as its instance count plus TILE_FIXED_WORK. Returns ``order [T]`` int64 (the
    tiles, strand by strand) and ``starts [nstrands + 1]`` int64 (strand s is
    ``order[starts[s]:starts[s+1]]``).

    Why: Numba's OpenMP layer splits a prange statically into contiguous blocks (the
    parallel chunk size does not make it dynamic there), and the tiles' work is anything but
    uniform (moving objects, dense regions), so one thread finished early and idled: 2
    threads kept ~1.65 cores busy in the compositing kernels. The tile kernels therefore run
    a prange over the strands, one per thread."""
    nt = offsets.shape[0] - 1
    work = np.empty(nt, np.int64)
    for t in range(nt):
        work[t] = offsets[t + 1] - offsets[t] + TILE_FIXED_WORK
    by_work = np.argsort(-work, kind="mergesort")
    strand = np.empty(nt, np.int64)
    load = np.zeros(nstrands, np.int64)
    count = np.zeros(nstrands + 1, np.int64)
    for t in by_work:
        s = np.argmin(load)
        strand[t] = s
        load[s] += work[t]
        count[s + 1] += 1
    starts = np.cumsum(count)
    cursor = starts[:-1].copy()
    order = np.empty(nt, np.int64)
    for t in by_work:
        s = strand[t]
        order[cursor[s]] = t
        cursor[s] += 1
    return order, starts


def tile_loop(kernel, offsets, *args):
    """Call a tile kernel ``kernel(offsets, order, starts, *args)`` with the tiles split into
    one strand per thread (:func:`tile_strands`)."""
    order, starts = tile_strands(offsets, get_num_threads())
    return kernel(offsets, order, starts, *args)


# The compositing kernels let LLVM reassociate (their lane sums vectorise) but not contract
# into FMAs: with "contract" the kernel compiled in the running process and the same kernel
# loaded from the on-disk cache gave different gradients (rounding level, 15 % of the
# Gaussians of a 3k-Gaussian probe), so a first run after install or upgrade trained apart
# from every later run of the same command (tests/engine/test_raster_cache.py). ~5 % slower.
_FASTMATH = {"reassoc"}


@njit(inline="always", **_JIT)
def _quat_rot(qw, qx, qy, qz):
    qn = qw * qw + qx * qx + qy * qy + qz * qz
    inv = F1 / math.sqrt(qn if qn > F0 else F0)  # a provably non-negative argument vectorises
    w, x, y, z = qw * inv, qx * inv, qy * inv, qz * inv
    r00 = F1 - F2 * (y * y + z * z)
    r01 = F2 * (x * y - w * z)
    r02 = F2 * (x * z + w * y)
    r10 = F2 * (x * y + w * z)
    r11 = F1 - F2 * (x * x + z * z)
    r12 = F2 * (y * z - w * x)
    r20 = F2 * (x * z - w * y)
    r21 = F2 * (y * z + w * x)
    r22 = F1 - F2 * (x * x + y * y)
    return w, x, y, z, inv, r00, r01, r02, r10, r11, r12, r20, r21, r22


# project_forward's local scratch: PF_BLK entries per field (inputs I_*, outputs O_*)
PF_BLK = 256
(I_MX, I_MY, I_MZ, I_QW, I_QX, I_QY, I_QZ, I_S0, I_S1, I_S2, I_OP,
 O_U, O_V, O_CA, O_CB, O_CC, O_Z, O_EX, O_EY, O_R) = (np.uint64(k * PF_BLK) for k in range(20))
PF_NF = 20


@njit(parallel=True, **_JIT)
def project_forward(means, quats, scales, opac, view, intr, width, height, near, far, eps2d,
                    means2d, conics, depths, radii, extents):
    """EWA projection. Inputs float32: means [N,3], quats [N,4], scales [N,3], opac [N],
    view [4,4], intr [4] = (fx, fy, cx, cy). Outputs (preallocated): means2d [N,2],
    conics [N,3], depths [N], radii [N] int32, extents [N,2]; every entry is written
    (zeros where a Gaussian is culled), so they may come from np.empty.

    Blocks of PF_BLK Gaussians: their inputs are copied into one local scratch array
    (field-major), a branch-free loop computes every field there, and the results are
    copied out. With a single base pointer and constant field offsets LLVM needs no alias
    checks and vectorises the compute loop (8 Gaussians per AVX2 instruction); culled
    Gaussians are handled with selects."""
    n = means.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    W = np.float32(width)
    H = np.float32(height)
    tan_x = HALF * W / fx
    tan_y = HALF * H / fy
    lxp = (W - cx) / fx + FOV_PAD * tan_x
    lxn = -(cx / fx + FOV_PAD * tan_x)
    lyp = (H - cy) / fy + FOV_PAD * tan_y
    lyn = -(cy / fy + FOV_PAD * tan_y)
    v00, v01, v02, v03 = view[0, 0], view[0, 1], view[0, 2], view[0, 3]
    v10, v11, v12, v13 = view[1, 0], view[1, 1], view[1, 2], view[1, 3]
    v20, v21, v22, v23 = view[2, 0], view[2, 1], view[2, 2], view[2, 3]
    nb = (n + PF_BLK - 1) // PF_BLK
    for blk in prange(nb):
        g0 = blk * PF_BLK
        m = min(n, g0 + PF_BLK) - g0
        S = np.empty(PF_NF * PF_BLK, np.float32)
        for t in range(m):
            g = g0 + t
            i = np.uint64(t)
            S[I_MX + i] = means[g, 0]
            S[I_MY + i] = means[g, 1]
            S[I_MZ + i] = means[g, 2]
            S[I_QW + i] = quats[g, 0]
            S[I_QX + i] = quats[g, 1]
            S[I_QY + i] = quats[g, 2]
            S[I_QZ + i] = quats[g, 3]
            S[I_S0 + i] = scales[g, 0]
            S[I_S1 + i] = scales[g, 1]
            S[I_S2 + i] = scales[g, 2]
            S[I_OP + i] = opac[g]
        for i in range(np.uint64(0), np.uint64(m)):
            mx, my, mz = S[I_MX + i], S[I_MY + i], S[I_MZ + i]
            px = v00 * mx + v01 * my + v02 * mz + v03
            py = v10 * mx + v11 * my + v12 * mz + v13
            pz = v20 * mx + v21 * my + v22 * mz + v23
            ok_z = (pz > near) & (pz < far)
            iz = F1 / pz
            u = fx * px * iz + cx
            v = fy * py * iz + cy
            _, _, _, _, _, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_rot(
                S[I_QW + i], S[I_QX + i], S[I_QY + i], S[I_QZ + i])
            s0, s1, s2 = S[I_S0 + i], S[I_S1 + i], S[I_S2 + i]
            m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
            m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
            m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
            c00 = m00 * m00 + m01 * m01 + m02 * m02
            c01 = m00 * m10 + m01 * m11 + m02 * m12
            c02 = m00 * m20 + m01 * m21 + m02 * m22
            c11 = m10 * m10 + m11 * m11 + m12 * m12
            c12 = m10 * m20 + m11 * m21 + m12 * m22
            c22 = m20 * m20 + m21 * m21 + m22 * m22
            xr = px * iz
            xr = xr if xr > lxn else lxn
            xr = xr if xr < lxp else lxp
            yr = py * iz
            yr = yr if yr > lyn else lyn
            yr = yr if yr < lyp else lyp
            tx = pz * xr
            ty = pz * yr
            j00 = fx * iz
            j02 = -fx * tx * iz * iz
            j11 = fy * iz
            j12 = -fy * ty * iz * iz
            a0 = v00 * c00 + v01 * c01 + v02 * c02
            a1 = v00 * c01 + v01 * c11 + v02 * c12
            a2 = v00 * c02 + v01 * c12 + v02 * c22
            b0 = v10 * c00 + v11 * c01 + v12 * c02
            b1 = v10 * c01 + v11 * c11 + v12 * c12
            b2 = v10 * c02 + v11 * c12 + v12 * c22
            d0 = v20 * c00 + v21 * c01 + v22 * c02
            d1 = v20 * c01 + v21 * c11 + v22 * c12
            d2 = v20 * c02 + v21 * c12 + v22 * c22
            w00 = a0 * v00 + a1 * v01 + a2 * v02
            w01 = a0 * v10 + a1 * v11 + a2 * v12
            w02 = a0 * v20 + a1 * v21 + a2 * v22
            w11 = b0 * v10 + b1 * v11 + b2 * v12
            w12 = b0 * v20 + b1 * v21 + b2 * v22
            w22 = d0 * v20 + d1 * v21 + d2 * v22
            q00 = j00 * w00 + j02 * w02
            q01 = j00 * w01 + j02 * w12
            q02 = j00 * w02 + j02 * w22
            q11 = j11 * w11 + j12 * w12
            q12 = j11 * w12 + j12 * w22
            ca = q00 * j00 + q02 * j02 + eps2d
            cb = q01 * j11 + q02 * j12
            cc = q11 * j11 + q12 * j12 + eps2d
            det = ca * cc - cb * cb
            ok_c = ok_z & (det > F0)
            idet = F1 / det
            o = S[I_OP + i]
            o255 = F255 * o
            thr = math.log(o255 if o255 > F1 else F1)
            ea = F2 * thr * ca
            eb = F2 * thr * cc
            ex = math.sqrt(ea if ea > F0 else F0) * BOX_SCALE + BOX_PAD
            ey = math.sqrt(eb if eb > F0 else F0) * BOX_SCALE + BOX_PAD
            onscr = (u + ex > F0) & (u - ex < W) & (v + ey > F0) & (v - ey < H)
            vis = ok_c & (o >= ALPHA_MIN) & onscr
            mid = HALF * (ca + cc)
            dd = mid * mid - det
            lam = mid + math.sqrt(dd if dd > TENTH else TENTH)
            rr = math.ceil(F3 * math.sqrt(lam if lam > F0 else F0))
            S[O_Z + i] = pz
            S[O_U + i] = u if ok_z else F0
            S[O_V + i] = v if ok_z else F0
            S[O_CA + i] = cc * idet if ok_c else F0
            S[O_CB + i] = -cb * idet if ok_c else F0
            S[O_CC + i] = ca * idet if ok_c else F0
            S[O_R + i] = rr if vis else F0
            S[O_EX + i] = ex if vis else F0
            S[O_EY + i] = ey if vis else F0
        for t in range(m):
            g = g0 + t
            i = np.uint64(t)
            depths[g] = S[O_Z + i]
            means2d[g, 0] = S[O_U + i]
            means2d[g, 1] = S[O_V + i]
            conics[g, 0] = S[O_CA + i]
            conics[g, 1] = S[O_CB + i]
            conics[g, 2] = S[O_CC + i]
            radii[g] = np.int32(S[O_R + i])
            extents[g, 0] = S[O_EX + i]
            extents[g, 1] = S[O_EY + i]


# One 64-byte record per Gaussian (``rec``) and per tile instance (``data``), float32 with
# an int32 view of the same memory (``irec`` / ``idata``) for the integer fields. Copying a
# Gaussian into tile order then moves one cache line instead of gathering from six arrays.
NREC = 16
R_MX, R_MY, R_A, R_B, R_C, R_OP, R_R, R_G, R_BL, R_Z, R_E = range(11)  # float fields; R_E: the extra channel
R_X0, R_X1, R_Y0, R_Y1 = 11, 12, 13, 14  # int: pixel box, end exclusive, clipped
R_SLOT = 15  # int: rec -> first slot of the Gaussian's instances in Gaussian-major order
#              data -> that instance's slot (row of the per-instance gradient array)


@njit(parallel=True, **_JIT)
def _pack_count(means2d, conics, depths, colors, extra, opac, extents, radii, width, height, tiles_x,
                rec, irec, ntile, counts):
    """Pass 1 of the binning, prange over chunks of Gaussians.

    Inputs float32: means2d [N,2], conics [N,3], depths [N], colors [N,3], extra [N] or [0]
    (no extra channel: R_E = 0), opac [N], extents [N,2]; radii [N] int32. Writes the records rec/irec [N, NREC] of Gaussians with
    a non-empty pixel box (others are left unset and never read), ntile [N] int64 (tiles
    the box touches, 0 = none) and counts [P, T] int32 (instances of chunk P in tile T)."""
    n = means2d.shape[0]
    nch = counts.shape[0]
    size = (n + nch - 1) // nch
    has_extra = extra.shape[0] == n
    for ch in prange(nch):
        for t in range(counts.shape[1]):
            counts[ch, t] = 0
        for g in range(ch * size, min(n, (ch + 1) * size)):
            ntile[g] = 0
            if radii[g] <= 0:
                continue
            u, v = means2d[g, 0], means2d[g, 1]
            ex, ey = extents[g, 0], extents[g, 1]
            # pixel x whose centre x + 0.5 lies in [u - ex, u + ex]
            x0 = max(0, int(math.ceil(u - ex - HALF)))
            x1 = min(width, int(math.floor(u + ex - HALF)) + 1)
            y0 = max(0, int(math.ceil(v - ey - HALF)))
            y1 = min(height, int(math.floor(v + ey - HALF)) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
            rec[g, R_MX] = u
            rec[g, R_MY] = v
            rec[g, R_A] = conics[g, 0]
            rec[g, R_B] = conics[g, 1]
            rec[g, R_C] = conics[g, 2]
            rec[g, R_OP] = opac[g]
            rec[g, R_R] = colors[g, 0]
            rec[g, R_G] = colors[g, 1]
            rec[g, R_BL] = colors[g, 2]
            rec[g, R_Z] = depths[g]
            rec[g, R_E] = extra[g] if has_extra else F0
            irec[g, R_X0] = x0
            irec[g, R_X1] = x1
            irec[g, R_Y0] = y0
            irec[g, R_Y1] = y1
            tx0, tx1 = x0 // TILE, (x1 - 1) // TILE + 1
            ty0, ty1 = y0 // TILE, (y1 - 1) // TILE + 1
            ntile[g] = (tx1 - tx0) * (ty1 - ty0)
            for ty in range(ty0, ty1):
                for tx in range(tx0, tx1):
                    counts[ch, ty * tiles_x + tx] += 1


@njit(**_JIT)
def _prefix(counts, ntile):
    """Serial prefix sums (T x P and N adds, well under a millisecond): tile offsets [T+1]
    int64, each chunk's first slot per tile cursor [P, T] int64 (chunks in Gaussian order,
    so every tile list comes out in Gaussian index order) and each Gaussian's first slot
    in Gaussian-major instance order gstart [N+1] int64."""
    nch, nt = counts.shape
    offsets = np.empty(nt + 1, np.int64)
    cursor = np.empty((nch, nt), np.int64)
    acc = 0
    for t in range(nt):
        offsets[t] = acc
        for ch in range(nch):
            cursor[ch, t] = acc
            acc += counts[ch, t]
    offsets[nt] = acc
    n = ntile.shape[0]
    gstart = np.empty(n + 1, np.int64)
    acc = 0
    for g in range(n):
        gstart[g] = acc
        acc += ntile[g]
    gstart[n] = acc
    return offsets, cursor, gstart


@njit(parallel=True, **_JIT)
def _fill(irec, ntile, gstart, tiles_x, cursor, inst_gid):
    """Pass 2, prange over the same chunks: each chunk writes its Gaussians into its own
    slots of every tile list (a counting sort without a serial pass), and stores each
    Gaussian's gstart in its record."""
    n = ntile.shape[0]
    nch = cursor.shape[0]
    size = (n + nch - 1) // nch
    for ch in prange(nch):
        for g in range(ch * size, min(n, (ch + 1) * size)):
            if ntile[g] > 0:
                irec[g, R_SLOT] = np.int32(gstart[g])
                for ty in range(irec[g, R_Y0] // TILE, (irec[g, R_Y1] - 1) // TILE + 1):
                    for tx in range(irec[g, R_X0] // TILE, (irec[g, R_X1] - 1) // TILE + 1):
                        t = ty * tiles_x + tx
                        inst_gid[cursor[ch, t]] = g
                        cursor[ch, t] += 1


@njit(**_JIT)
def _radix_sort(keys, vals, tmp_k, tmp_v, hist):
    """Stable LSD radix sort of ``keys [m]`` int64 (values in ``[0, 2^32)``) carrying
    ``vals [m]`` int32, in place; ``tmp_k``/``tmp_v`` [m] and ``hist [256]`` are scratch.
    8-bit digits; a pass whose digit is the same for every key is skipped (depths within
    one power-of-two range share their top bits). For the few hundred entries of a tile
    list this takes about half the time of np.sort on (depth, position) keys."""
    m = keys.shape[0]
    src_k, src_v, dst_k, dst_v = keys, vals, tmp_k, tmp_v
    flipped = False
    for shift in range(0, 32, 8):
        for d in range(256):
            hist[d] = 0
        for i in range(m):
            hist[(src_k[i] >> shift) & 255] += 1
        if hist[(src_k[0] >> shift) & 255] == m:
            continue
        acc = 0
        for d in range(256):
            c = hist[d]
            hist[d] = acc
            acc += c
        for i in range(m):
            d = (src_k[i] >> shift) & 255
            dst_k[hist[d]] = src_k[i]
            dst_v[hist[d]] = src_v[i]
            hist[d] += 1
        src_k, src_v, dst_k, dst_v = dst_k, dst_v, src_k, src_v
        flipped = not flipped
    if flipped:
        for i in range(m):
            keys[i] = src_k[i]
            vals[i] = src_v[i]


@njit(parallel=True, **_JIT)
def _sort_gather(offsets, order, starts, inst_gid, tiles_x, depths, rec, irec, data, idata):
    """Per tile (one strand of tiles per thread, :func:`tile_strands`): stable depth sort of
    the list (it arrives in index order, so ties keep the lower index first, like the
    reference's stable global sort), then copy each Gaussian's record into tile order,
    data/idata [I, NREC], with R_SLOT set to the instance's Gaussian-major slot: gstart[g] +
    rank of this tile in g's tile box (row-major). Sort and copy share one pass over the
    tile's instances."""
    for strand in prange(starts.shape[0] - 1):
        for pos in range(starts[strand], starts[strand + 1]):
            t = order[pos]
            a, b = offsets[t], offsets[t + 1]
            if b <= a:
                continue
            m = b - a
            # Keys: the bits of the (positive) float32 depth, which order like the depths.
            keys = np.empty(m, np.int64)
            ids = inst_gid[a:b].copy()
            for j in range(m):
                d = max(depths[ids[j]], F0)  # the dense array: fewer cache misses than rec
                keys[j] = np.int64(np.float32(d).view(np.int32))
            _radix_sort(keys, ids, np.empty(m, np.int64), np.empty(m, np.int32), np.empty(256, np.int64))
            tyi = t // tiles_x
            txi = t - tyi * tiles_x
            for j in range(m):
                g = ids[j]
                k = a + j
                inst_gid[k] = g
                for f in range(R_X0):
                    data[k, f] = rec[g, f]
                x0, x1, y0 = irec[g, R_X0], irec[g, R_X1], irec[g, R_Y0]
                idata[k, R_X0] = x0
                idata[k, R_X1] = x1
                idata[k, R_Y0] = y0
                idata[k, R_Y1] = irec[g, R_Y1]
                ntx = (x1 - 1) // TILE - x0 // TILE + 1
                idata[k, R_SLOT] = irec[g, R_SLOT] + (tyi - y0 // TILE) * ntx + (txi - x0 // TILE)


_NO_EXTRA = np.zeros(0, np.float32)


def bin_tiles(depths, means2d, conics, colors, opac, extents, radii, width, height, tiles_x, tiles_y, extra=None):
    """Per-tile instance lists in front-to-back order, with the per-instance records.

    Inputs float32: depths [N], means2d [N,2], conics [N,3], colors [N,3], opac [N],
    extents [N,2]; radii [N] int32; optional extra [N] (the extra channel, field R_E). Returns ``offsets [T+1]`` int64 (tile t's instances
    are ``offsets[t]:offsets[t+1]``), ``inst_gid [I]`` int32 Gaussian ids, ``data [I, NREC]``
    float32 and ``idata``, its int32 view (fields R_*), and ``gstart [N+1]`` int64
    (Gaussian g's instances own gradient rows ``gstart[g]:gstart[g+1]``).

    Three parallel passes and two tiny serial prefix sums; the chunk count depends on N
    only, so results never depend on the thread count. (Plain Python on purpose: a
    parallel kernel called from inside another jitted function is not guaranteed to run
    in parallel.)"""
    n = depths.shape[0]
    nch = max(1, min(MAX_BIN_CHUNKS, n // BIN_CHUNK))
    rec = pooled("rec", n * NREC, np.float32).reshape(n, NREC)
    irec = rec.view(np.int32)
    ntile = pooled("ntile", n, np.int64)
    counts = np.empty((nch, tiles_x * tiles_y), np.int32)
    ex = _NO_EXTRA if extra is None else extra
    dynamic(_pack_count, 1, means2d, conics, depths, colors, ex, opac, extents, radii, width, height, tiles_x, rec,
            irec, ntile, counts)
    offsets, cursor, gstart = _prefix(counts, ntile)
    m = int(offsets[-1])
    inst_gid = pooled("inst_gid", m, np.int32)
    dynamic(_fill, 1, irec, ntile, gstart, tiles_x, cursor, inst_gid)
    data = pooled("data", m * NREC, np.float32).reshape(m, NREC)
    idata = data.view(np.int32)
    tile_loop(_sort_gather, offsets, inst_gid, tiles_x, depths, rec, irec, data, idata)
    return offsets, inst_gid, data, idata, gstart


# Per-tile state lives in ONE flat float32 array, one field per block of NPAD entries, and
# the pixel loops index it with unsigned integers: one base pointer means LLVM needs no
# runtime alias checks, and unsigned indices drop Numba's negative-index wraparound, so the
# inner loops vectorise. The loops are branch-free (masks and selects) for the same reason.
#
# An instance's pixel box within a tile (at most TILE = 16 wide) is processed one row at a
# time as one 8-lane chunk (box <= 8 wide) or one 16-lane chunk, starting at the box's first
# column (not at an aligned one). Lanes past the box fall on the next tile row or on the 16
# slack entries that end each field block; they are masked (float compare against the box
# width, no 64-bit integer masks), and every masked write stores back the value it read, so
# they change nothing. Lanes inside the box but outside the Gaussian's alpha >= 1/255
# ellipse are masked by the alpha test. (An exact per-row span with horizontal sums per
# row, the earlier path for boxes wider than 8, cost ~40 % more at 240x180.)
NPX = TILE * TILE
NPAD = NPX + 16
_T, _R, _G, _B, _D, _LAST = (np.uint64(i * NPAD) for i in range(6))  # forward fields
_BT, _BLAST, _BB, _GR, _GG, _GB, _GD, _GA = (np.uint64(i * NPAD) for i in range(8))  # backward fields
U0 = np.uint64(0)
U8 = np.uint64(8)
U16 = np.uint64(16)
LANE = np.arange(16).astype(np.float32)  # lane offsets 0..15 (a frozen constant in the kernels)
# exp(y) on y in [-0.5, 0]: degree-5 least-squares fit on 200 Chebyshev nodes (float64
# relative error 1.3e-8; as accurate in float32 as the degree-7 Taylor series it replaced,
# two FMAs and two constants fewer per lane).
EXP_C = tuple(np.float32(c) for c in (0.9999999915790986, 0.9999987794480075, 0.4999712582985454,
                                      0.1664180017221641, 0.040685229191972684, 0.006506926459413055))
SIXTEENTH = np.float32(1.0 / 16.0)
SIG_MAX = np.float32(8.0)


@njit(inline="always", **_JIT)
def _exp_neg(s):
    """``exp(-s)`` for ``s`` in ``[0, 8]`` (clamped), float32, vectorisable.

    ``exp(-s) = exp(-s/16)^16``: a degree-5 polynomial (EXP_C) for ``exp`` on
    ``[-0.5, 0]`` (1.3e-8 relative before the four squarings, ~2e-6 in float32 after).
    Callers only need it where ``alpha >= 1/255``, i.e. ``s <= ln 255 < 5.6``."""
    y = -min(max(s, F0), SIG_MAX) * SIXTEENTH
    e = EXP_C[5]
    e = e * y + EXP_C[4]
    e = e * y + EXP_C[3]
    e = e * y + EXP_C[2]
    e = e * y + EXP_C[1]
    e = e * y + EXP_C[0]
    e = e * e
    e = e * e
    e = e * e
    return e * e


# raster_forward's per-lane stop counts of an instance, run down its rows: _SP + p,
# after TILE slack entries so that the row above (_SPM + p = _SP + p - TILE) stays inside.
_SPM = np.uint64(6 * NPAD)
_SP = np.uint64(6 * NPAD + TILE)
FWD_SLEN = 6 * NPAD + TILE + NPAD
# the extra channel's accumulator (variant with an extra channel only)
_E = np.uint64(FWD_SLEN)
FWD_SLEN_X = FWD_SLEN + NPAD


@njit(inline="always", **_JIT)
def _composite_lane(S, p, lj, dx0, n_in, a, cyy, bdy, op, r_, g_, b_, z_, e_, kk, xe):
    """One lane of :func:`raster_forward`: composite the instance into pixel ``p`` of the
    tile state ``S`` (lane offset ``lj`` from the chunk's first pixel, ``n_in`` pixels of
    the chunk inside the span). Returns 1 when the pixel stops here (T < T_MIN), else 0.
    ``xe`` (a compile-time constant of the kernel variant) adds the extra channel ``e_``.
    Branch-free selects, so the 8-lane loops around it still vectorise."""
    dx = dx0 + lj
    sig = HALF * a * dx * dx + cyy + bdy * dx
    al = min(ALPHA_MAX, op * _exp_neg(sig))
    tp = S[_T + p]
    tt = tp * (F1 - al)
    live = (lj < n_in) & (sig >= F0) & (al >= ALPHA_MIN) & (tp > F0)
    stop = live & (tt < T_MIN)
    take = live & (tt >= T_MIN)
    w = al * tp if take else F0
    S[_R + p] += w * r_
    S[_G + p] += w * g_
    S[_B + p] += w * b_
    S[_D + p] += w * z_
    if xe:
        S[_E + p] += w * e_
    S[_T + p] = tt if take else (-tp if stop else tp)
    S[_LAST + p] = kk if take else S[_LAST + p]
    return F1 if stop else F0


@njit(inline="always", **_JIT)
def _tile_box(tile, tiles_x, width, height):
    """Pixel origin ``(ox, oy)`` and size ``(tw, th)`` of tile ``tile`` (row-major tiles)."""
    tyi = tile // tiles_x
    ox = (tile - tyi * tiles_x) * TILE
    oy = tyi * TILE
    return ox, oy, min(TILE, width - ox), min(TILE, height - oy)


@njit(inline="always", **_JIT)
def _row(py, oy, ox, bx0, my, b, c):
    """Per-row terms of pixel row ``py`` for an instance at ``my`` with conic ``(a, b, c)``:
    ``dy``, ``c dy² / 2``, ``b dy`` and the state index of the row's first lane (column
    ``bx0`` of the tile at ``(ox, oy)``)."""
    dy = np.float32(py) + HALF - my
    return dy, HALF * c * dy * dy, b * dy, np.uint64((py - oy) * TILE - ox + bx0)


@njit(inline="always", **_JIT)
def _instance(data, idata, k, ox, oy, tw, th):
    """Record ``k`` of a tile list: ``(mx, my, a, b, c, opacity, r, g, b, z, extra)`` and its
    pixel box clipped to the tile at ``(ox, oy)`` of size ``tw x th``: ``y0, y1, bx0, bx1``
    (ends exclusive)."""
    return (data[k, R_MX], data[k, R_MY], data[k, R_A], data[k, R_B], data[k, R_C], data[k, R_OP],
            data[k, R_R], data[k, R_G], data[k, R_BL], data[k, R_Z], data[k, R_E],
            max(idata[k, R_Y0], oy), min(idata[k, R_Y1], oy + th), max(idata[k, R_X0], ox),
            min(idata[k, R_X1], ox + tw))


@njit(inline="always", **_JIT)
def _composite_rows(S, nl, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_, e_, kk, xe):
    """Composite one instance into the tile state ``S``: rows ``y0 <= py < y1``, one chunk of
    ``nl`` lanes (8 or 16, a constant at each call site) per row starting at column ``bx0``,
    lanes past ``bx1`` masked. The per-lane stop counts run down the rows (field _SP, the
    row above at -TILE, as the running sums of :func:`raster_backward`) and are summed
    horizontally once per instance instead of once per row. Returns the number of pixels
    that stopped here."""
    p0 = np.uint64((y0 - oy) * TILE - ox + bx0)
    for j in range(U0, nl):
        S[_SPM + p0 + j] = F0
    n_in = np.float32(bx1 - bx0)
    dx0 = np.float32(bx0) + HALF - mx
    for py in range(y0, y1):
        dy, cyy, bdy, base = _row(py, oy, ox, bx0, my, b, c)
        for j in range(U0, nl):
            p = base + j
            S[_SP + p] = _composite_lane(S, p, LANE[j], dx0, n_in, a, cyy, bdy, op, r_, g_, b_, z_, e_, kk,
                                         xe) + S[_SPM + p]
    stops = F0
    pl = np.uint64((y1 - 1 - oy) * TILE - ox + bx0)
    for j in range(U0, nl):
        stops += S[_SP + pl + j]
    return stops


def _raster_forward_kernel(xe):
    """:func:`raster_forward` without (``xe`` False) or with the extra channel, compiled as
    two kernels: ``xe`` is a closure constant, so the plain variant carries no extra work."""

    @njit(parallel=True, fastmath=_FASTMATH, **_JIT)
    def raster_forward(offsets, order, starts, data, idata, width, height, tiles_x, bg, out_rgb, out_depth, out_T,
                       out_last, out_extra):
        """Front-to-back compositing, tile by tile (``order``/``starts``: one strand of tiles
        per thread, :func:`tile_strands`).

        ``data``/``idata`` [I, NREC]: instance records from :func:`bin_tiles`.
        Outputs (preallocated): out_rgb [H,W,3] (background included), out_depth [H,W]
        (sum w z), out_T [H,W] final transmittance, out_last [H,W] int32 = number of list
        entries of the pixel's tile up to and including its last composited Gaussian, and with
        ``xe`` out_extra [H,W] (sum w e, field R_E; no background)."""
        for strand in prange(starts.shape[0] - 1):
            for pos in range(starts[strand], starts[strand + 1]):
                tile = order[pos]
                ox, oy, tw, th = _tile_box(tile, tiles_x, width, height)
                # A finished pixel keeps its transmittance negated (-T > 0 can never composite
                # again), so no separate "done" field is loaded and stored per lane.
                S = np.zeros(FWD_SLEN_X if xe else FWD_SLEN, np.float32)
                S[:NPAD] = F1
                alive = np.float32(tw * th)
                start = offsets[tile]
                for k in range(start, offsets[tile + 1]):
                    mx, my, a, b, c, op, r_, g_, b_, z_, e_, y0, y1, bx0, bx1 = _instance(data, idata, k, ox, oy, tw,
                                                                                          th)
                    kk = np.float32(k - start + 1)
                    # a box at most 8 pixels wide in this tile takes one 8-lane chunk per row,
                    # a wider one (at most TILE) two; both are compiled with a constant width
                    if bx1 - bx0 <= 8:
                        stops = _composite_rows(S, U8, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_,
                                                e_, kk, xe)
                    else:
                        stops = _composite_rows(S, U16, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_,
                                                e_, kk, xe)
                    alive -= stops
                    if alive <= F0:
                        break
                for yy in range(th):
                    for xx in range(tw):
                        p = yy * TILE + xx
                        Y = oy + yy
                        X = ox + xx
                        tp = abs(S[p])
                        out_rgb[Y, X, 0] = S[_R + p] + tp * bg[0]
                        out_rgb[Y, X, 1] = S[_G + p] + tp * bg[1]
                        out_rgb[Y, X, 2] = S[_B + p] + tp * bg[2]
                        out_depth[Y, X] = S[_D + p]
                        out_T[Y, X] = tp
                        out_last[Y, X] = np.int32(S[_LAST + p])
                        if xe:
                            out_extra[Y, X] = S[_E + p]

    return raster_forward


raster_forward = _raster_forward_kernel(False)
raster_forward_extra = _raster_forward_kernel(True)


@njit(inline="always", **_JIT)
def _unblend_lane(S, p, lj, dx, n_in, kk, a, cyy, bdy, op, r_, g_, b_, z_, e_, xe):
    """One lane of :func:`raster_backward` for the instance ``kk`` (back to front): restore
    the transmittance before it (``S[_BT]``) and the upstream-weighted colour behind it
    (``S[_BB]``; only the sum ``B = sum_ch g_ch B_ch`` matters, it follows the same
    recurrence as each channel, so one state replaces five).

    Returns ``(wgt, gr, gg, gb, gd, u)``: the blend weight ``alpha T``, the pixel's upstream
    gradients (r, g, b, depth) and ``u = dL/dalpha * gau``. Wherever ``u != 0`` the alpha
    is unclamped (``al = op gau``; the 0.99 clamp has zero gradient), so
    ``dL/dsigma = -op u``, which with ``u`` itself is all the conic, mean and opacity
    gradients need. ``xe`` (compile-time) adds the extra channel ``e_`` (upstream gradient in
    ``S[_GE]``) to ``cdot``. Branch-free selects, so the 8-lane loops around it still vectorise."""
    sig = HALF * a * dx * dx + cyy + bdy * dx
    gau = _exp_neg(sig)
    raw = op * gau
    al = min(ALPHA_MAX, raw)
    live = (lj < n_in) & (kk < S[_BLAST + p]) & (sig >= F0) & (al >= ALPHA_MIN)
    alv = al if live else F0
    om = F1 - alv
    tb = S[_BT + p] / om  # transmittance before this Gaussian
    gr, gg, gb = S[_GR + p], S[_GG + p], S[_GB + p]
    gd, ga = S[_GD + p], S[_GA + p]
    cdot = gr * r_ + gg * g_ + gb * b_ + gd * z_ + ga
    if xe:
        cdot += S[_GE + p] * e_
    bdot = S[_BB + p]
    dal = tb * (cdot - bdot)
    S[_BB + p] = alv * cdot + om * bdot
    S[_BT + p] = tb
    dal = dal if (live & (raw <= ALPHA_MAX)) else F0
    return alv * tb, gr, gg, gb, gd, dal * gau


# The backward's per-lane running sums down the rows of an instance (see
# raster_backward): field k at _RS + k * RSTRIDE + p, each block preceded by TILE slack
# entries so that the row above (p - TILE) never leaves the array. _P* = _S* - TILE.
RSTRIDE = NPAD + TILE
_RS = 8 * NPAD + TILE
(_SR, _SG, _SB, _SZ, _SU, _SX, _SXX, _SY, _SXY, _SYY) = (np.uint64(_RS + k * RSTRIDE) for k in range(10))
(_PR, _PG, _PB, _PZ, _PU, _PX, _PXX, _PY, _PXY, _PYY) = (np.uint64(_RS + k * RSTRIDE - TILE) for k in range(10))
SLEN = _RS + 10 * RSTRIDE
_GE = np.uint64(SLEN)  # the extra channel's upstream gradient (variant with an extra channel)
SLEN_X = SLEN + NPAD


@njit(inline="always", **_JIT)
def _unblend_rows(S, nl, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_, e_, kk, xe):
    """Back-to-front step of :func:`raster_backward` for one instance: rows ``y0 <= py < y1``,
    one chunk of ``nl`` lanes (8 or 16, a constant at each call site) per row from column
    ``bx0``, lanes past ``bx1`` masked. Per-lane running sums are carried down the rows in
    ``S`` (row r stores its chunk plus row r-1's sums, an offset of -TILE from the same base,
    so LLVM still sees one base pointer and vectorises): the horizontal reductions happen
    once per instance instead of once per row. Returns the pixel sums
    ``(Σ w g_r, Σ w g_g, Σ w g_b, Σ w g_z, Σ u, Σ u dx, Σ u dx², Σ u dy, Σ u dx dy, Σ u dy²)``
    with ``w`` the blend weight and ``u = dL/dalpha · gau`` (see :func:`_unblend_lane`)."""
    # the row above the first one starts the sums at zero
    p0 = np.uint64((y0 - oy) * TILE - ox + bx0)
    for j in range(U0, nl):
        S[_PR + p0 + j] = F0
        S[_PG + p0 + j] = F0
        S[_PB + p0 + j] = F0
        S[_PZ + p0 + j] = F0
        S[_PU + p0 + j] = F0
        S[_PX + p0 + j] = F0
        S[_PXX + p0 + j] = F0
        S[_PY + p0 + j] = F0
        S[_PXY + p0 + j] = F0
        S[_PYY + p0 + j] = F0
    n_in = np.float32(bx1 - bx0)
    dx0 = np.float32(bx0) + HALF - mx
    for py in range(y0, y1):
        dy, cyy, bdy, base = _row(py, oy, ox, bx0, my, b, c)
        dyy = dy * dy
        for j in range(U0, nl):
            p = base + j
            dx = dx0 + LANE[j]
            wgt, gr, gg, gb, gd, u = _unblend_lane(S, p, LANE[j], dx, n_in, kk, a, cyy, bdy, op, r_, g_, b_, z_,
                                                   e_, xe)
            ux = u * dx
            S[_SR + p] = wgt * gr + S[_PR + p]
            S[_SG + p] = wgt * gg + S[_PG + p]
            S[_SB + p] = wgt * gb + S[_PB + p]
            S[_SZ + p] = wgt * gd + S[_PZ + p]
            S[_SU + p] = u + S[_PU + p]
            S[_SX + p] = ux + S[_PX + p]
            S[_SXX + p] = ux * dx + S[_PXX + p]
            S[_SY + p] = u * dy + S[_PY + p]
            S[_SXY + p] = ux * dy + S[_PXY + p]
            S[_SYY + p] = u * dyy + S[_PYY + p]
    s_r = F0
    s_g = F0
    s_bb = F0
    s_z = F0
    s_o = F0
    t_x = F0
    t_xx = F0
    t_y = F0
    t_xy = F0
    t_yy = F0
    if y1 > y0:  # always, for an instance binned to this tile
        pl = np.uint64((y1 - 1 - oy) * TILE - ox + bx0)  # the last row
        for j in range(U0, nl):
            p = pl + j
            s_r += S[_SR + p]
            s_g += S[_SG + p]
            s_bb += S[_SB + p]
            s_z += S[_SZ + p]
            s_o += S[_SU + p]
            t_x += S[_SX + p]
            t_xx += S[_SXX + p]
            t_y += S[_SY + p]
            t_xy += S[_SXY + p]
            t_yy += S[_SYY + p]
    return s_r, s_g, s_bb, s_z, s_o, t_x, t_xx, t_y, t_xy, t_yy


def _raster_backward_kernel(xe):
    """:func:`raster_backward` without (``xe`` False) or with the extra channel (see
    :func:`_raster_forward_kernel`)."""

    @njit(parallel=True, fastmath=_FASTMATH, **_JIT)
    def raster_backward(offsets, order, starts, data, idata, width, height, tiles_x, bg, out_T, out_last,
                        g_rgb, g_alpha, g_depth, g_extra, grads):
        """Reverse-order backward of :func:`raster_forward` (as in 3DGS).

        ``g_rgb [H,W,3]``, ``g_alpha [H,W]``, ``g_depth [H,W]`` (and with ``xe``
        ``g_extra [H,W]``) are upstream gradients; the extra channel itself gets none.
        Fills and returns ``grads``, the per-instance gradients ``[I, 10]``: (mx, my, a, b, c,
        opacity, r, g, b, z), each instance's row at its R_SLOT (Gaussian-major order, so the per-Gaussian sums read
        contiguous rows). Every instance carries per-lane sums down its rows in 8 or 16
        lanes (:func:`_unblend_rows`). ``reassoc`` lets LLVM vectorise the per-Gaussian sums
        over pixels."""
        for strand in prange(starts.shape[0] - 1):
            for pos in range(starts[strand], starts[strand + 1]):
                tile = order[pos]
                ox, oy, tw, th = _tile_box(tile, tiles_x, width, height)
                # T, last, then B (what lies behind the current Gaussian per unit transmittance
                # after it, dotted with the upstream gradient; starts as g . background), then the
                # upstream gradients. Zeros elsewhere keep masked lanes inert (last = 0 masks them).
                S = np.zeros(SLEN_X if xe else SLEN, np.float32)  # 8 fields, then the 10 running sums
                maxlast = 0
                for yy in range(th):
                    for xx in range(tw):
                        p = yy * TILE + xx
                        Y = oy + yy
                        X = ox + xx
                        S[_BT + p] = out_T[Y, X]
                        S[_BLAST + p] = np.float32(out_last[Y, X])
                        maxlast = max(maxlast, out_last[Y, X])
                        S[_BB + p] = g_rgb[Y, X, 0] * bg[0] + g_rgb[Y, X, 1] * bg[1] + g_rgb[Y, X, 2] * bg[2]
                        S[_GR + p] = g_rgb[Y, X, 0]
                        S[_GG + p] = g_rgb[Y, X, 1]
                        S[_GB + p] = g_rgb[Y, X, 2]
                        S[_GD + p] = g_depth[Y, X]
                        S[_GA + p] = g_alpha[Y, X]
                        if xe:
                            S[_GE + p] = g_extra[Y, X]
                start = offsets[tile]
                # entries past every pixel's last composited one get zero gradient
                for k in range(start + maxlast, offsets[tile + 1]):
                    for f in range(10):
                        grads[idata[k, R_SLOT], f] = F0
                for k in range(start + maxlast - 1, start - 1, -1):
                    mx, my, a, b, c, op, r_, g_, b_, z_, e_, y0, y1, bx0, bx1 = _instance(data, idata, k, ox, oy, tw,
                                                                                          th)
                    kk = np.float32(k - start)
                    # one 8-lane chunk per row for a box at most 8 wide, two for a wider one (at
                    # most TILE): constant widths, compiled separately
                    if bx1 - bx0 <= 8:
                        s_r, s_g, s_bb, s_z, s_o, t_x, t_xx, t_y, t_xy, t_yy = _unblend_rows(
                            S, U8, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_, e_, kk, xe)
                    else:
                        s_r, s_g, s_bb, s_z, s_o, t_x, t_xx, t_y, t_xy, t_yy = _unblend_rows(
                            S, U16, y0, y1, oy, ox, bx0, bx1, mx, my, a, b, c, op, r_, g_, b_, z_, e_, kk, xe)
                    # d sigma / d(mx, my, a, b, c) = (-(a dx + b dy), -(b dx + c dy), dx^2/2, dx dy, dy^2/2)
                    # times dL/dsigma = -op u, summed over the pixels: a t_x + b t_y and so on; the
                    # factor op (and 1/2) is applied once per instance
                    opq = op * HALF
                    s_mx = (a * t_x + b * t_y) * op
                    s_my = (b * t_x + c * t_y) * op
                    s_a = -t_xx * opq
                    s_b = -t_xy * op
                    s_c = -t_yy * opq
                    slot = idata[k, R_SLOT]
                    grads[slot, 0] = s_mx
                    grads[slot, 1] = s_my
                    grads[slot, 2] = s_a
                    grads[slot, 3] = s_b
                    grads[slot, 4] = s_c
                    grads[slot, 5] = s_o
                    grads[slot, 6] = s_r
                    grads[slot, 7] = s_g
                    grads[slot, 8] = s_bb
                    grads[slot, 9] = s_z
        return grads

    return raster_backward


raster_backward = _raster_backward_kernel(False)
raster_backward_extra = _raster_backward_kernel(True)


@njit(**_JIT)
def instance_bounds(gstart, nstrands):
    """Split the Gaussians into ``nstrands`` contiguous ranges of about equal work for
    :func:`sum_instances`: a Gaussian's work taken as its instance count plus one (its
    writes), so the cumulative work up to Gaussian ``g`` is ``gstart[g] + g``, monotone, and
    each bound is a binary search. Returns ``bounds [nstrands + 1]`` int64 (strand s sums
    Gaussians ``bounds[s]:bounds[s+1]``). Why not a plain prange: the OpenMP layer splits it
    into equal Gaussian counts (see GAUSS_CHUNK), and instance counts differ by Gaussian
    size, so one thread summed most of the rows."""
    n = gstart.shape[0] - 1
    total = gstart[n] + n
    bounds = np.empty(nstrands + 1, np.int64)
    bounds[0] = 0
    bounds[nstrands] = n
    for s in range(1, nstrands):
        target = total * s // nstrands
        lo, hi = bounds[s - 1], n  # first g with gstart[g] + g >= target
        while lo < hi:
            mid = (lo + hi) // 2
            if gstart[mid] + mid < target:
                lo = mid + 1
            else:
                hi = mid
        bounds[s] = lo
    return bounds


@njit(parallel=True, **_JIT)
def sum_instances(gstart, bounds, grads, v_means2d, v_conics, v_opac, v_colors, v_depths):
    """Per-Gaussian sums of the per-instance gradients ``grads [I, 10]`` (rows in
    Gaussian-major order: Gaussian g owns ``gstart[g]:gstart[g+1]``), one strand of
    Gaussians per thread (``bounds`` from :func:`instance_bounds`): contiguous reads, no write
    conflicts, fixed summation order. Outputs (preallocated, overwritten): v_means2d [N,2],
    v_conics [N,3], v_opac [N], v_colors [N,3], v_depths [N]."""
    for strand in prange(bounds.shape[0] - 1):
        for g in range(bounds[strand], bounds[strand + 1]):
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = F0
            for k in range(gstart[g], gstart[g + 1]):
                s0 += grads[k, 0]
                s1 += grads[k, 1]
                s2 += grads[k, 2]
                s3 += grads[k, 3]
                s4 += grads[k, 4]
                s5 += grads[k, 5]
                s6 += grads[k, 6]
                s7 += grads[k, 7]
                s8 += grads[k, 8]
                s9 += grads[k, 9]
            v_means2d[g, 0] = s0
            v_means2d[g, 1] = s1
            v_conics[g, 0] = s2
            v_conics[g, 1] = s3
            v_conics[g, 2] = s4
            v_opac[g] = s5
            v_colors[g, 0] = s6
            v_colors[g, 1] = s7
            v_colors[g, 2] = s8
            v_depths[g] = s9


# project_backward's local scratch: PB_BLK entries per field
PB_BLK = 128
(BI_MX, BI_MY, BI_MZ, BI_QW, BI_QX, BI_QY, BI_QZ, BI_S0, BI_S1, BI_S2, BI_VIS, BI_GU, BI_GV, BI_GA, BI_GB, BI_GC,
 BI_GZ, BO_MX, BO_MY, BO_MZ, BO_QW, BO_QX, BO_QY, BO_QZ, BO_S0, BO_S1, BO_S2) = (np.uint64(k * PB_BLK)
                                                                              for k in range(27))
PB_NF = 27


@njit(inline="always", **_JIT)
def _sandwich(v00, v01, v02, v10, v11, v12, v20, v21, v22, a00, a01, a02, a11, a12, a22):
    """Congruence ``B = V^T A V`` for symmetric ``A`` (six entries) and the 3x3 ``V`` given
    by its nine entries (row-major); returns B's six entries (b00 b01 b02 b11 b12 b22).
    Scalars only, so that it vectorises across Gaussians."""
    t00 = a00 * v00 + a01 * v10 + a02 * v20
    t01 = a00 * v01 + a01 * v11 + a02 * v21
    t02 = a00 * v02 + a01 * v12 + a02 * v22
    t10 = a01 * v00 + a11 * v10 + a12 * v20
    t11 = a01 * v01 + a11 * v11 + a12 * v21
    t12 = a01 * v02 + a11 * v12 + a12 * v22
    t20 = a02 * v00 + a12 * v10 + a22 * v20
    t21 = a02 * v01 + a12 * v11 + a22 * v21
    t22 = a02 * v02 + a12 * v12 + a22 * v22
    b00 = v00 * t00 + v10 * t10 + v20 * t20
    b01 = v00 * t01 + v10 * t11 + v20 * t21
    b02 = v00 * t02 + v10 * t12 + v20 * t22
    b11 = v01 * t01 + v11 * t11 + v21 * t21
    b12 = v01 * t02 + v11 * t12 + v21 * t22
    b22 = v02 * t02 + v12 * t12 + v22 * t22
    return b00, b01, b02, b11, b12, b22


@njit(parallel=True, **_JIT)
def project_backward(means, quats, scales, view, intr, width, height, eps2d, radii,
                     v_means2d, v_conics, v_depths, v_means, v_quats, v_scales):
    """Backward of :func:`project_forward` for visible Gaussians (``radii > 0``); the
    depth gradient flows for every Gaussian. Inputs float32 as in the forward plus the
    upstream v_means2d [N,2], v_conics [N,3], v_depths [N]; outputs (preallocated,
    overwritten) v_means [N,3], v_quats [N,4], v_scales [N,3].

    Same layout as the forward: blocks of PB_BLK Gaussians copied into one field-major
    scratch array, a branch-free (select-based) compute loop that LLVM vectorises, and a
    copy out. All 2x2 / 3x3 products are written out as scalars (symmetric ones by their
    six entries)."""
    n = means.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    W = np.float32(width)
    H = np.float32(height)
    tan_x = HALF * W / fx
    tan_y = HALF * H / fy
    lxp = (W - cx) / fx + FOV_PAD * tan_x
    lxn = cx / fx + FOV_PAD * tan_x
    lyp = (H - cy) / fy + FOV_PAD * tan_y
    lyn = cy / fy + FOV_PAD * tan_y
    v00, v01, v02, v03 = view[0, 0], view[0, 1], view[0, 2], view[0, 3]
    v10, v11, v12, v13 = view[1, 0], view[1, 1], view[1, 2], view[1, 3]
    v20, v21, v22, v23 = view[2, 0], view[2, 1], view[2, 2], view[2, 3]
    nb = (n + PB_BLK - 1) // PB_BLK
    for blk in prange(nb):
        g0 = blk * PB_BLK
        m = min(n, g0 + PB_BLK) - g0
        S = np.empty(PB_NF * PB_BLK, np.float32)
        for t in range(m):
            g = g0 + t
            i = np.uint64(t)
            S[BI_MX + i] = means[g, 0]
            S[BI_MY + i] = means[g, 1]
            S[BI_MZ + i] = means[g, 2]
            S[BI_QW + i] = quats[g, 0]
            S[BI_QX + i] = quats[g, 1]
            S[BI_QY + i] = quats[g, 2]
            S[BI_QZ + i] = quats[g, 3]
            S[BI_S0 + i] = scales[g, 0]
            S[BI_S1 + i] = scales[g, 1]
            S[BI_S2 + i] = scales[g, 2]
            S[BI_VIS + i] = F1 if radii[g] > 0 else F0
            S[BI_GU + i] = v_means2d[g, 0]
            S[BI_GV + i] = v_means2d[g, 1]
            S[BI_GA + i] = v_conics[g, 0]
            S[BI_GB + i] = v_conics[g, 1]
            S[BI_GC + i] = v_conics[g, 2]
            S[BI_GZ + i] = v_depths[g]
        for i in range(np.uint64(0), np.uint64(m)):
            vis = S[BI_VIS + i] > F0
            mx, my, mz = S[BI_MX + i], S[BI_MY + i], S[BI_MZ + i]
            px = v00 * mx + v01 * my + v02 * mz + v03
            py = v10 * mx + v11 * my + v12 * mz + v13
            pz = v20 * mx + v21 * my + v22 * mz + v23
            iz = F1 / pz
            iz2 = iz * iz
            gu, gv = S[BI_GU + i], S[BI_GV + i]
            gpx = gu * fx * iz
            gpy = gv * fy * iz
            gpz = -(gu * fx * px + gv * fy * py) * iz2
            w, x, y, z, qinv, r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_rot(
                S[BI_QW + i], S[BI_QX + i], S[BI_QY + i], S[BI_QZ + i])
            s0, s1, s2 = S[BI_S0 + i], S[BI_S1 + i], S[BI_S2 + i]
            m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
            m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
            m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
            c00 = m00 * m00 + m01 * m01 + m02 * m02
            c01 = m00 * m10 + m01 * m11 + m02 * m12
            c02 = m00 * m20 + m01 * m21 + m02 * m22
            c11 = m10 * m10 + m11 * m11 + m12 * m12
            c12 = m10 * m20 + m11 * m21 + m12 * m22
            c22 = m20 * m20 + m21 * m21 + m22 * m22
            # Wc = Rv C3 Rv^T: the congruence with Rt = Rv^T (Rt[r, c] = view[c, r])
            w00, w01, w02, w11, w12, w22 = _sandwich(v00, v10, v20, v01, v11, v21, v02, v12, v22,
                                                 c00, c01, c02, c11, c12, c22)
            xc = px * iz
            yc = py * iz
            cl_x = (xc < -lxn) | (xc > lxp)
            cl_y = (yc < -lyn) | (yc > lyp)
            xr = xc if xc > -lxn else -lxn
            xr = xr if xr < lxp else lxp
            yr = yc if yc > -lyn else -lyn
            yr = yr if yr < lyp else lyp
            tx = pz * xr
            ty = pz * yr
            j00 = fx * iz
            j02 = -fx * tx * iz2
            j11 = fy * iz
            j12 = -fy * ty * iz2
            ca = j00 * (j00 * w00 + j02 * w02) + j02 * (j00 * w02 + j02 * w22) + eps2d
            cb = j11 * (j00 * w01 + j02 * w12) + j12 * (j00 * w02 + j02 * w22)
            cc = j11 * (j11 * w11 + j12 * w12) + j12 * (j11 * w12 + j12 * w22) + eps2d
            idet = F1 / (ca * cc - cb * cb)
            q00 = cc * idet
            q01 = -cb * idet
            q11 = ca * idet
            g00 = -S[BI_GA + i]
            g01 = -HALF * S[BI_GB + i]
            g11 = -S[BI_GC + i]
            t00 = q00 * g00 + q01 * g01
            t01 = q00 * g01 + q01 * g11
            t10 = q01 * g00 + q11 * g01
            t11 = q01 * g01 + q11 * g11
            e00 = t00 * q00 + t01 * q01
            e01 = t00 * q01 + t01 * q11
            e11 = t10 * q01 + t11 * q11
            e0 = e00 * j02 + e01 * j12
            e1 = e01 * j02 + e11 * j12
            dw00 = j00 * e00 * j00
            dw01 = j00 * e01 * j11
            dw02 = j00 * e0
            dw11 = j11 * e11 * j11
            dw12 = j11 * e1
            dw22 = j02 * e0 + j12 * e1
            a0, a1 = e00 * j00, e01 * j11
            b0, b1 = e01 * j00, e11 * j11
            dj00 = F2 * (a0 * w00 + a1 * w01 + e0 * w02)
            dj02 = F2 * (a0 * w02 + a1 * w12 + e0 * w22)
            dj11 = F2 * (b0 * w01 + b1 * w11 + e1 * w12)
            dj12 = F2 * (b0 * w02 + b1 * w12 + e1 * w22)
            d00, d01, d02, d11, d12, d22 = _sandwich(v00, v01, v02, v10, v11, v12, v20, v21, v22,
                                                 dw00, dw01, dw02, dw11, dw12, dw22)
            dm00 = F2 * (d00 * m00 + d01 * m10 + d02 * m20)
            dm01 = F2 * (d00 * m01 + d01 * m11 + d02 * m21)
            dm02 = F2 * (d00 * m02 + d01 * m12 + d02 * m22)
            dm10 = F2 * (d01 * m00 + d11 * m10 + d12 * m20)
            dm11 = F2 * (d01 * m01 + d11 * m11 + d12 * m21)
            dm12 = F2 * (d01 * m02 + d11 * m12 + d12 * m22)
            dm20 = F2 * (d02 * m00 + d12 * m10 + d22 * m20)
            dm21 = F2 * (d02 * m01 + d12 * m11 + d22 * m21)
            dm22 = F2 * (d02 * m02 + d12 * m12 + d22 * m22)
            vs0 = dm00 * r00 + dm10 * r10 + dm20 * r20
            vs1 = dm01 * r01 + dm11 * r11 + dm21 * r21
            vs2 = dm02 * r02 + dm12 * r12 + dm22 * r22
            dR00, dR01, dR02 = dm00 * s0, dm01 * s1, dm02 * s2
            dR10, dR11, dR12 = dm10 * s0, dm11 * s1, dm12 * s2
            dR20, dR21, dR22 = dm20 * s0, dm21 * s1, dm22 * s2
            gw = F2 * (-z * dR01 + y * dR02 + z * dR10 - x * dR12 - y * dR20 + x * dR21)
            gx = F2 * (y * dR01 + z * dR02 + y * dR10 - w * dR12 + z * dR20 + w * dR21
                       - F2 * x * dR11 - F2 * x * dR22)
            gy = F2 * (-F2 * y * dR00 + x * dR01 + w * dR02 + x * dR10 + z * dR12
                       - w * dR20 + z * dR21 - F2 * y * dR22)
            gz = F2 * (-F2 * z * dR00 - w * dR01 + x * dR02 + w * dR10 - F2 * z * dR11
                       + y * dR12 + x * dR20 + y * dR21)
            dot = w * gw + x * gx + y * gy + z * gz
            gpz -= dj00 * fx * iz2 + dj11 * fy * iz2
            lx = tx * iz
            gpx = gpx if cl_x else gpx - dj02 * fx * iz2
            gpz = gpz + dj02 * fx * lx * iz2 if cl_x else gpz + dj02 * F2 * fx * px * iz2 * iz
            ly = ty * iz
            gpy = gpy if cl_y else gpy - dj12 * fy * iz2
            gpz = gpz + dj12 * fy * ly * iz2 if cl_y else gpz + dj12 * F2 * fy * py * iz2 * iz
            gz0 = S[BI_GZ + i]
            gpx = gpx if vis else F0
            gpy = gpy if vis else F0
            gpz = gz0 + gpz if vis else gz0
            S[BO_MX + i] = v00 * gpx + v10 * gpy + v20 * gpz
            S[BO_MY + i] = v01 * gpx + v11 * gpy + v21 * gpz
            S[BO_MZ + i] = v02 * gpx + v12 * gpy + v22 * gpz
            S[BO_QW + i] = (gw - w * dot) * qinv if vis else F0
            S[BO_QX + i] = (gx - x * dot) * qinv if vis else F0
            S[BO_QY + i] = (gy - y * dot) * qinv if vis else F0
            S[BO_QZ + i] = (gz - z * dot) * qinv if vis else F0
            S[BO_S0 + i] = vs0 if vis else F0
            S[BO_S1 + i] = vs1 if vis else F0
            S[BO_S2 + i] = vs2 if vis else F0
        for t in range(m):
            g = g0 + t
            i = np.uint64(t)
            v_means[g, 0] = S[BO_MX + i]
            v_means[g, 1] = S[BO_MY + i]
            v_means[g, 2] = S[BO_MZ + i]
            v_quats[g, 0] = S[BO_QW + i]
            v_quats[g, 1] = S[BO_QX + i]
            v_quats[g, 2] = S[BO_QY + i]
            v_quats[g, 3] = S[BO_QZ + i]
            v_scales[g, 0] = S[BO_S0 + i]
            v_scales[g, 1] = S[BO_S1 + i]
            v_scales[g, 2] = S[BO_S2 + i]
