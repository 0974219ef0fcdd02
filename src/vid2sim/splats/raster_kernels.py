"""Compiled CPU kernels of the rasteriser's compositing (numba), the CPU's default since they are faster.

They composite the same depth-sorted tile lists (:class:`~vid2sim.splats.rasterize.TileBins`) with the same semantics
as the tensor-op path of :mod:`vid2sim.splats.rasterize` (its module docstring): per pixel, Gaussians in depth order,
α = min(0.999, o · exp(−σ')) skipped below 1/255, compositing stopped before the first Gaussian that would bring the
transmittance to 1e-4 or below. What differs is how much is evaluated: the tensor path evaluates every pixel of a tile
for every Gaussian listed in it (at the small preset's footprints a fifth of those pairs reach α ≥ 1/255), a kernel
only the pixels inside the bounding box of the Gaussian's α ≥ 1/255 ellipse, and a pixel stops at its own
termination. Tiles run in parallel (``prange``) on ``threads`` threads. The gain is largest for small splats (the
small preset's 3 px: a render forward + backward 1.5–1.8× faster) and small for large ones, whose tiles the tensor
path fills with useful work (the full preset's 8.5 px at 448²: 1.0–1.2×).

The backward kernel replays a tile's compositing front to back with the same rule as the tensor path
(``∂L/∂α_k = (g·f_k) T_k − (Σ_{j>k} (g·f_j) w_j) / (1 − α_k)``, the suffix sum being the pixel's total less the running
prefix) and writes each intersection's gradients (``∂L/∂[μx, μy, a, b, c, log o]`` and ``∂L/∂f``) into a row of its
own, so tiles never write the same memory; the caller sums the rows per Gaussian entry.

The arrays are numpy views of the caller's tensors (no copies). The kernels compile on first use and are cached on
disk beside this module (numba's ``cache=True``): about 6 s for a float32 render and its backward pass on one thread,
9 s on several, 28 s for all eight variants, once per machine and release.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

_LOG_255 = math.log(255.0)
_LOG_255_BELOW = -_LOG_255 - 1e-3
_MAX_ALPHA = 0.999
_T_EPS = 1e-4


@njit(cache=True, error_model="numpy", inline="always")
def _window(mx: float, my: float, a: float, b: float, c: float, log_o: float, x0: int, y0: int,
            ts: int) -> tuple[int, int, int, int]:
    """The tile-local pixel rows and columns (i0, i1, j0, j1, inclusive; empty when i0 > i1) that can hold α ≥ 1/255:
    the bounding box of the ellipse ½ dᵀ[[a, b], [b, c]]d ≤ ln 255 + log o, widened a little (the per-pixel test
    decides). A Gaussian of opacity below 1/255 reaches no pixel; a degenerate conic gets the whole tile."""
    reach = 2.0 * (_LOG_255 + log_o)
    if reach < 0.0:  # opacity below 1/255 (at exactly 1/255 the centre itself may reach it)
        return 0, -1, 0, -1
    det = a * c - b * b
    if not det > 0.0:  # degenerate (or NaN): let the per-pixel test decide everywhere
        return 0, ts - 1, 0, ts - 1
    reach = reach * (1.0 + 1e-4) + 1e-6
    ex = math.sqrt(reach * c / det) + 1e-3
    ey = math.sqrt(reach * a / det) + 1e-3
    last = ts - 1.0  # clamped as floats first: a huge extent must not overflow the integer conversion
    i0 = int(max(0.0, math.ceil(mx - ex - x0 - 0.5)))
    i1 = int(min(last, math.floor(mx + ex - x0 - 0.5)))
    j0 = int(max(0.0, math.ceil(my - ey - y0 - 0.5)))
    j1 = int(min(last, math.floor(my + ey - y0 - 0.5)))
    return i0, i1, j0, j1


@njit(cache=True, error_model="numpy", inline="always")
def _alpha(mx: float, my: float, a: float, b: float, c: float, log_o: float, px: float, py: float,
           alpha_th: float) -> tuple[float, float, float, bool]:
    """(α, dx, dy, clamped) at pixel centre (px, py); α = 0 where it is not above ``alpha_th``."""
    dx = px - mx
    dy = py - my
    exponent = log_o - (0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    if exponent < _LOG_255_BELOW:  # surely below 1/255 (by a margin that rounding cannot cross): no exp needed
        return 0.0, dx, dy, False
    vis = math.exp(exponent)
    clamped = vis > _MAX_ALPHA
    alpha = _MAX_ALPHA if clamped else vis
    if alpha <= alpha_th:
        alpha = 0.0
    return alpha, dx, dy, clamped


@njit(cache=True, error_model="numpy", inline="always")
def _weight(alpha: float, trans: np.ndarray, done: np.ndarray, p: int) -> float:
    """The compositing weight α T of a Gaussian (α > 0) at pixel p, advancing the pixel's transmittance
    ``trans[p]`` to T (1 − α); −1 where the Gaussian ends the pixel instead (T would fall to 1e-4 or below: the pixel
    is marked ``done`` and takes nothing more). The rule both kernels composite by."""
    t_next = trans[p] * (1.0 - alpha)
    if t_next <= _T_EPS:
        done[p] = True
        return -1.0
    w = alpha * trans[p]
    trans[p] = t_next
    return w


@njit(cache=True, error_model="numpy", inline="always")
def _tile_origin(t: int, tiles_x: int, tiles_y: int, ts: int) -> tuple[int, int]:
    """The pixel coordinates (x0, y0) of tile t's corner in its view."""
    local = t % (tiles_x * tiles_y)
    return (local % tiles_x) * ts, (local // tiles_x) * ts


@njit(cache=True, error_model="numpy")
def _forward_tile(t: int, params: np.ndarray, feat1: np.ndarray, entry: np.ndarray, tile_start: np.ndarray,
                  tile_count: np.ndarray, tiles_x: int, tiles_y: int, ts: int, alpha_th: float,
                  out: np.ndarray) -> None:
    """Composite tile t into ``out[t]`` (:func:`composite_forward`)."""
    count = tile_count[t]
    if count == 0:
        return
    P = ts * ts
    C1 = feat1.shape[1]
    x0, y0 = _tile_origin(t, tiles_x, tiles_y, ts)
    trans = np.ones(P, dtype=np.float64)
    done = np.zeros(P, dtype=np.bool_)
    n_done = 0
    for k in range(count):
        e = entry[tile_start[t] + k]
        mx, my, a, b, c, lo = params[e, 0], params[e, 1], params[e, 2], params[e, 3], params[e, 4], params[e, 5]
        i0, i1, j0, j1 = _window(mx, my, a, b, c, lo, x0, y0, ts)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                p = j * ts + i
                if done[p]:
                    continue
                alpha, _, _, _ = _alpha(mx, my, a, b, c, lo, x0 + i + 0.5, y0 + j + 0.5, alpha_th)
                if alpha == 0.0:
                    continue
                w = _weight(alpha, trans, done, p)
                if w < 0.0:
                    n_done += 1
                    continue
                for ch in range(C1):
                    out[t, ch, p] += feat1[e, ch] * w
        if n_done == P:
            return


@njit(cache=True, error_model="numpy")
def _backward_tile(t: int, params: np.ndarray, feat1: np.ndarray, entry: np.ndarray, tile_start: np.ndarray,
                   tile_count: np.ndarray, tiles_x: int, tiles_y: int, ts: int, alpha_th: float,
                   grad: np.ndarray, acc: np.ndarray, d_isect: np.ndarray) -> None:
    """The gradients of tile t's intersections into their rows of ``d_isect`` (:func:`composite_backward`)."""
    count = tile_count[t]
    if count == 0:
        return
    P = ts * ts
    C1 = feat1.shape[1]
    x0, y0 = _tile_origin(t, tiles_x, tiles_y, ts)
    trans = np.ones(P, dtype=np.float64)
    done = np.zeros(P, dtype=np.bool_)
    rest = np.zeros(P, dtype=np.float64)  # Σ_{j>k} (g·f_j) w_j: the total, less the running prefix
    for p in range(P):
        for ch in range(C1):
            rest[p] += grad[t, ch, p] * acc[t, ch, p]
    n_done = 0
    for k in range(count):
        row = tile_start[t] + k
        e = entry[row]
        mx, my, a, b, c, lo = params[e, 0], params[e, 1], params[e, 2], params[e, 3], params[e, 4], params[e, 5]
        i0, i1, j0, j1 = _window(mx, my, a, b, c, lo, x0, y0, ts)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                p = j * ts + i
                if done[p]:
                    continue
                alpha, dx, dy, clamped = _alpha(mx, my, a, b, c, lo, x0 + i + 0.5, y0 + j + 0.5, alpha_th)
                if alpha == 0.0:
                    continue
                t_before = trans[p]
                w = _weight(alpha, trans, done, p)
                if w < 0.0:
                    n_done += 1
                    continue
                gf = 0.0
                for ch in range(C1):
                    gf += grad[t, ch, p] * feat1[e, ch]
                rest[p] -= gf * w
                for ch in range(C1 - 1):
                    d_isect[row, 6 + ch] += w * grad[t, ch, p]
                if not clamped:
                    n = alpha * (gf * t_before - rest[p] / (1.0 - alpha))  # ∂L/∂(−σ')
                    d_isect[row, 0] += n * (a * dx + b * dy)
                    d_isect[row, 1] += n * (b * dx + c * dy)
                    d_isect[row, 2] -= 0.5 * n * dx * dx
                    d_isect[row, 3] -= n * dx * dy
                    d_isect[row, 4] -= 0.5 * n * dy * dy
                    d_isect[row, 5] += n
        if n_done == P:
            return


@njit(parallel=True, cache=True, error_model="numpy")
def _forward_parallel(params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, out):
    for t in prange(tile_start.shape[0]):
        _forward_tile(t, params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, out)


@njit(cache=True, error_model="numpy")
def _forward_serial(params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, out):
    for t in range(tile_start.shape[0]):
        _forward_tile(t, params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, out)


@njit(parallel=True, cache=True, error_model="numpy")
def _backward_parallel(params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, grad, acc,
                       d_isect):
    for t in prange(tile_start.shape[0]):
        _backward_tile(t, params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, grad, acc,
                       d_isect)


@njit(cache=True, error_model="numpy")
def _backward_serial(params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, grad, acc,
                     d_isect):
    for t in range(tile_start.shape[0]):
        _backward_tile(t, params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, grad, acc,
                       d_isect)


def composite_forward(params: np.ndarray, feat1: np.ndarray, entry: np.ndarray, tile_start: np.ndarray,
                      tile_count: np.ndarray, tiles_x: int, tiles_y: int, ts: int, alpha_th: float,
                      out: np.ndarray, threads: int) -> None:
    """Composite every tile into ``out`` (n_tiles, C1, ts²), zero-initialised by the caller: channels Σ f w.

    Args:
        params: (M, 6) [μx, μy, a, b, c, log o] per entry; feat1: (M, C1) features, the last one 1 (so its channel
            is Σ w); entry: (I,) the intersections' entries, per tile depth-sorted from ``tile_start`` for
            ``tile_count``; alpha_th: the largest value below 1/255 in the arrays' dtype.
        threads: tiles in parallel on this many threads (at most numba's pool); 1 runs serially and never starts
            numba's thread pool (a process that later forks must not have one, as with torch's own).
    """
    args = (params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, out)
    if threads > 1:
        numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
        _forward_parallel(*args)
    else:
        _forward_serial(*args)


def composite_backward(params: np.ndarray, feat1: np.ndarray, entry: np.ndarray, tile_start: np.ndarray,
                       tile_count: np.ndarray, tiles_x: int, tiles_y: int, ts: int, alpha_th: float,
                       grad: np.ndarray, acc: np.ndarray, d_isect: np.ndarray, threads: int) -> None:
    """The gradients of :func:`composite_forward`, per intersection, into ``d_isect`` (I, 6 + C), zero-initialised:
    columns ∂L/∂[μx, μy, a, b, c, log o] and ∂L/∂f for the C = C1 − 1 features (not the constant last one).

    Args:
        grad: (n_tiles, C1, ts²) ∂L/∂out; acc: the forward's ``out``; the rest as :func:`composite_forward`.
    """
    args = (params, feat1, entry, tile_start, tile_count, tiles_x, tiles_y, ts, alpha_th, grad, acc, d_isect)
    if threads > 1:
        numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
        _backward_parallel(*args)
    else:
        _backward_serial(*args)


@njit(cache=True, error_model="numpy")
def sum_rows(index: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """``out[index[r]] += rows[r]`` for every row r (one thread: rows of one index may be anywhere)."""
    for r in range(rows.shape[0]):
        i = index[r]
        for col in range(rows.shape[1]):
            out[i, col] += rows[r, col]


# ---- binning -------------------------------------------------------------------------------------

_SIGN32 = np.uint64(0x80000000)
_MASK32 = np.uint64(0xFFFFFFFF)
_SIGN64 = np.uint64(0x8000000000000000)
_ALL64 = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, error_model="numpy")
def _depth_keys32(depth):
    """Unsigned keys (M,) that order float32 depths as torch's sort does: −0 equal to +0, NaN last (all equal)."""
    bits = (depth + np.float32(0.0)).view(np.uint32)  # + 0 turns −0 into +0
    keys = np.empty(depth.shape[0], np.uint64)
    for i in range(depth.shape[0]):
        u = np.uint64(bits[i])
        if depth[i] != depth[i]:
            keys[i] = _MASK32
        elif u & _SIGN32:
            keys[i] = ~u & _MASK32
        else:
            keys[i] = u | _SIGN32
    return keys


@njit(cache=True, error_model="numpy")
def _depth_keys64(depth):
    """:func:`_depth_keys32` for float64 depths."""
    bits = (depth + 0.0).view(np.uint64)
    keys = np.empty(depth.shape[0], np.uint64)
    for i in range(depth.shape[0]):
        u = bits[i]
        if depth[i] != depth[i]:
            keys[i] = _ALL64
        elif u & _SIGN64:
            keys[i] = ~u
        else:
            keys[i] = u | _SIGN64
    return keys


@njit(cache=True, error_model="numpy")
def _stable_argsort(keys, passes):
    """The permutation (M,) that sorts unsigned ``keys`` stably (equal keys in index order): a least-significant-digit
    radix sort, ``passes`` passes of 16 bits."""
    n = keys.shape[0]
    idx, tmp = np.arange(n), np.empty(n, np.int64)
    k_now, k_tmp = keys.copy(), np.empty(n, np.uint64)
    counts = np.empty(65537, np.int64)
    for p in range(passes):
        shift = np.uint64(16 * p)
        counts[:] = 0
        for i in range(n):
            counts[np.int64((k_now[i] >> shift) & np.uint64(0xFFFF)) + 1] += 1
        if counts.max() == n:  # every key has the same digit here: the pass would not move anything
            continue
        for d in range(1, 65537):
            counts[d] += counts[d - 1]
        for i in range(n):
            d = np.int64((k_now[i] >> shift) & np.uint64(0xFFFF))
            tmp[counts[d]] = idx[i]
            k_tmp[counts[d]] = k_now[i]
            counts[d] += 1
        idx, tmp = tmp, idx
        k_now, k_tmp = k_tmp, k_now
    return idx


@njit(cache=True, error_model="numpy", inline="always")
def _entry_tiles(i, mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y, view,
                 out, start):
    """Tile ids (global) of the tiles in entry i's bounding box that pass the circle test, written from ``out[start]``
    when ``out`` is not empty; returns how many. The test is :func:`~vid2sim.splats.rasterize.bin_gaussians`'s:
    the squared distance from the centre to the tile's nearest pixel centre, in the arrays' dtype, at most reach²."""
    n = 0
    mx, my = mux[i], muy[i]
    for ty in range(ty0[i], ty0[i] + ny[i]):
        dy = min(max(my, row_lo[ty]), row_hi[ty]) - my
        for tx in range(tx0[i], tx0[i] + nx[i]):
            dx = min(max(mx, col_lo[tx]), col_hi[tx]) - mx
            if dx * dx + dy * dy <= reach2[i]:
                if out.shape[0] > 0:
                    out[start + n] = (view[i] * tiles_y + ty) * tiles_x + tx  # < 2³¹: checked by the caller
                n += 1
    return n


@njit(cache=True, error_model="numpy", inline="always")
def _bin_count(i, args, kept):
    mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y, view = args
    kept[i] = _entry_tiles(i, mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y,
                           view, kept[:0], 0)


@njit(cache=True, error_model="numpy", inline="always")
def _bin_fill(i, args, first, tile_of):
    mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y, view = args
    _entry_tiles(i, mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y, view,
                 tile_of, first[i])


@njit(cache=True, error_model="numpy")
def _group_by_tile(order, first, tile_of, n_tiles):
    """(entry (I,), tile_start, tile_count (n_tiles,)): the intersections (``tile_of[first[i]:first[i + 1]]`` the
    tiles of entry i) grouped by tile, within each tile in the order of the entries in ``order`` (a counting sort,
    which keeps that order)."""
    tile_count = np.zeros(n_tiles, np.int64)
    for j in range(tile_of.shape[0]):
        tile_count[tile_of[j]] += 1
    tile_start = np.empty(n_tiles, np.int64)
    total = 0
    for t in range(n_tiles):
        tile_start[t] = total
        total += tile_count[t]
    cursor = tile_start.copy()
    entry = np.empty(tile_of.shape[0], np.int64)
    for k in range(order.shape[0]):
        i = order[k]
        for j in range(first[i], first[i + 1]):
            t = tile_of[j]
            entry[cursor[t]] = i
            cursor[t] += 1
    return entry, tile_start, tile_count


@njit(parallel=True, cache=True, error_model="numpy")
def _bin_parallel(args, order, n_tiles):
    M = order.shape[0]
    kept = np.empty(M, np.int64)
    for i in prange(M):
        _bin_count(i, args, kept)
    first = np.zeros(M + 1, np.int64)
    first[1:] = np.cumsum(kept)
    tile_of = np.empty(first[M], np.int32)
    for i in prange(M):
        _bin_fill(i, args, first, tile_of)
    return _group_by_tile(order, first, tile_of, n_tiles)


@njit(cache=True, error_model="numpy")
def _bin_serial(args, order, n_tiles):
    M = order.shape[0]
    kept = np.empty(M, np.int64)
    for i in range(M):
        _bin_count(i, args, kept)
    first = np.zeros(M + 1, np.int64)
    first[1:] = np.cumsum(kept)
    tile_of = np.empty(first[M], np.int32)
    for i in range(M):
        _bin_fill(i, args, first, tile_of)
    return _group_by_tile(order, first, tile_of, n_tiles)


def bin_tiles(mux: np.ndarray, muy: np.ndarray, reach2: np.ndarray, tx0: np.ndarray, ty0: np.ndarray, nx: np.ndarray,
              ny: np.ndarray, view: np.ndarray, depth: np.ndarray, col_lo: np.ndarray, col_hi: np.ndarray,
              row_lo: np.ndarray, row_hi: np.ndarray, tiles_x: int, tiles_y: int, n_views: int,
              threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The depth-sorted tile lists of :func:`~vid2sim.splats.rasterize.bin_gaussians` in compiled passes: each entry's
    tiles counted and written (in entry order, which reads the arrays in order), the entries sorted by depth once (a
    stable radix sort of the depths' bits, which orders them as torch's sort does), then the intersections grouped by
    tile in that order (a counting sort, which keeps it).

    Args:
        mux, muy, reach2: (M,) the entries' pixel centres and squared reach (the circle test's bound).
        tx0, ty0, nx, ny: (M,) int32 their tile bounding boxes (first column and row, widths; empty when ≤ 0).
        view: (M,) int32 their views; depth: (M,) float32 or float64 their sort keys.
        col_lo, col_hi: (tiles_x,) the first and last pixel centres of each tile column (same dtype as mux);
            row_lo, row_hi: (tiles_y,) the same for the rows.
        threads: entries in parallel on this many threads; 1 runs serially (no numba thread pool).

    Returns:
        (entry (I,), tile_start (n_tiles,), tile_count (n_tiles,)), int64: per tile, its entries by depth, equal
        depths in entry order, NaN last.
    """
    wide = depth.dtype == np.float64
    order = _stable_argsort(_depth_keys64(depth) if wide else _depth_keys32(depth), 4 if wide else 2)
    args = (mux, muy, reach2, tx0, ty0, nx, ny, col_lo, col_hi, row_lo, row_hi, tiles_x, tiles_y, view)
    n_tiles = n_views * tiles_y * tiles_x
    if threads > 1:
        numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
        return _bin_parallel(args, order, n_tiles)
    return _bin_serial(args, order, n_tiles)
