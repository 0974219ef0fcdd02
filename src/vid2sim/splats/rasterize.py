"""Tile rasteriser: front-to-back alpha compositing of image-plane Gaussians.

Binning is PyTorch; compositing runs on the CPU in compiled kernels (:mod:`vid2sim.splats.raster_kernels`, the
same semantics, a render 1.5–1.9× faster) and elsewhere in the tensor operations described below
(``RasterOptions.kernels`` chooses).

Semantics (those of the reference 3DGS rasteriser and gsplat's "classic" mode): for each pixel
centre q, Gaussians are taken in increasing camera depth; each has

    α = min(0.999, o · exp(−½ (q − μ)ᵀ Σ2d⁻¹ (q − μ))),

Gaussians with α < 1/255 are skipped, and compositing stops *before* the first Gaussian whose
inclusion would bring the transmittance to 1e-4 or below. A pixel's features are
``Σ_k f_k w_k`` with weights ``w_k = α_k T_k``, ``T_k = Π_{j<k} (1 − α_j)`` over the included
Gaussians; its final transmittance is ``1 − Σ_k w_k``.

How the tensor path is made fast and memory-bounded:

- **Tile binning.** The image is cut into ``tile_size``² tiles; each visible (view, Gaussian) entry
  is listed in the tiles that its α ≥ 1/255 region can reach (bounding box, then a conservative
  circle test), and each tile's list is sorted by depth.
- **Quadratic-form trick.** Within a tile, ``σ' = −log(α)`` before clamping is a quadratic
  polynomial in tile-local pixel coordinates (u, v): ``c0 + c1 u + c2 v + c3 u² + c4 uv + c5 v²``.
  σ' for a whole batch of (tile, Gaussian) pairs at all P pixels of a tile is one matrix product of
  the (…, 6) coefficients with a fixed (6, P) basis; local coordinates keep it accurate in float32.
- **Depth chunks with early termination.** All tiles advance through their lists in chunks of K
  Gaussians; a tile drops out when its list ends or every pixel in it has terminated, so hidden
  Gaussians behind opaque surfaces cost nothing. At most ``max_elements`` (tile, Gaussian, pixel)
  triples are evaluated at once (memory bound, cache friendly).
- **Custom backward.** Nothing per (Gaussian, pixel) is stored: the backward pass replays the chunk
  schedule, recomputes α and uses ∂L/∂α_k = (g·f_k) T_k − (Σ_{j>k} (g·f_j) w_j)/(1 − α_k), the suffix
  sum being (total − running prefix). The gradients of the per-entry parameters (μ, conic, log o)
  follow from the coefficient formulas by hand.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.projection import ALPHA_THRESHOLD

try:  # numba is a dependency; a machine given vid2sim without it (a GPU check's PYTHONPATH) composites with tensors
    from vid2sim.splats import raster_kernels
    _NO_KERNELS = ""
except ImportError as _exc:  # pragma: no cover - numba is installed wherever the suite runs on a CPU
    raster_kernels = None
    _NO_KERNELS = str(_exc)

MAX_ALPHA = 0.999
T_EPS = 1e-4
_PAD_SIGMA = 1e4  # σ' of padding slots: exp(-1e4) == 0, so they are skipped
_LOG_255 = math.log(255.0)


@dataclass
class RasterOptions:
    """Tuning knobs of the rasteriser (the image does not depend on them, beyond float rounding).

    Attributes:
        tile_size: tile edge in pixels (power of two ≤ 32), or None (the default): :data:`COMPILED_TILE_SIZE` for
            the compiled kernels, and for the tensor path chosen per render from the Gaussians' footprint by
            :func:`auto_tile_size`.
        kernels: how a tile is composited: "auto" (the default) compiled kernels for float32 and float64 on the CPU
            (:mod:`vid2sim.splats.raster_kernels`) and tensor operations otherwise; "compiled" or "tensor" to
            choose (the compiled kernels take float32 and float64 CPU tensors only). ``chunk`` and ``max_elements``
            tune the tensor path.
        chunk: Gaussians per tile taken in one depth step.
        max_elements: cap on (tile × Gaussian × pixel) triples evaluated at once; peak extra memory
            is about 12 such float tensors (2^20: ≈ 50 MB in float32). 2^20 dispatches 38 % fewer operators
            than 2^18 in a joint iteration (7 241 → 4 505 for the 16 renders of ``bench speed``'s joint
            setting) at the same speed on a CPU (1 905 against 1 921 ms per iteration, median of 5 alternating
            runs, 1 thread, loaded 2-core machine).
    """

    tile_size: int | None = None
    kernels: str = "auto"
    chunk: int = 16
    max_elements: int = 1 << 20

    def __post_init__(self) -> None:
        if self.kernels not in KERNELS:
            raise ConfigError(f"RasterOptions.kernels must be one of {', '.join(KERNELS)}, got {self.kernels!r}")
        ts = self.tile_size
        if ts is not None and (not isinstance(ts, int) or ts <= 0 or ts & (ts - 1) or ts > 32):
            raise ConfigError(f"RasterOptions.tile_size must be a power of two in [1, 32] or None, got {ts!r}")
        if not isinstance(self.chunk, int) or self.chunk < 1:
            raise ConfigError(f"RasterOptions.chunk must be a positive integer, got {self.chunk!r}")
        ts = max(AUTO_TILE_SIZES) if ts is None else ts
        if self.max_elements < self.chunk * ts * ts:
            raise ConfigError(
                f"RasterOptions.max_elements={self.max_elements} is below one tile's chunk "
                f"(chunk * tile_size² = {self.chunk * ts * ts})"
            )


AUTO_TILE_SIZES = (4, 8)
KERNELS = ("auto", "compiled", "tensor")
#: the compiled kernels' tile edge: they evaluate only the pixels a Gaussian reaches, so larger tiles cost nothing
#: there and cut the intersections to bin and sort (the small preset's 4 frames × 4 views at 128², 6 000 Gaussians,
#: 1 thread, median of 5 interleaved, one run: forward + backward 364 / 309 / 306 / 294 ms at tiles 4 / 8 / 16 / 32, the
#: tensor path's automatic tile 562 ms; 16 keeps a few hundred tiles for the threads at that size)
COMPILED_TILE_SIZE = 16


def uses_compiled_kernels(opts: RasterOptions, like: Tensor) -> bool:
    """Whether :func:`composite` takes the compiled CPU kernels for ``opts`` and tensors of ``like``'s device and
    dtype (module docstring).

    Raises:
        ConfigError: ``opts.kernels`` "compiled" for tensors they do not take, or without numba. Without numba (a
            broken install: it is a dependency) "auto" warns and takes the tensor path.
    """
    # host memory: torch.device("cpu") itself (a CPU tensor's device never carries an index; the stand-in accelerator
    # of vid2sim.runtime.device_check, "cpu:0", takes the tensor path, which is what an accelerator runs)
    supported = like.device == torch.device("cpu") and like.dtype in (torch.float32, torch.float64)
    if opts.kernels == "compiled" and not supported:
        raise ConfigError(f"RasterOptions.kernels 'compiled' takes float32 or float64 CPU tensors, not {like.dtype} "
                          f"on {like.device}")
    if not supported or opts.kernels == "tensor":
        return False
    if raster_kernels is None:
        if opts.kernels == "compiled":
            raise ConfigError(f"RasterOptions.kernels 'compiled' needs numba, which does not import: {_NO_KERNELS}")
        warnings.warn(f"numba does not import ({_NO_KERNELS}); the CPU rasteriser composites with tensor operations, "
                      "about 2x slower: pip install numba", RuntimeWarning, stacklevel=3)
        return False
    return True


def tile_size_for(opts: RasterOptions, radii: Tensor, backward: bool, like: Tensor) -> int:
    """The tile edge of a render of tensors like ``like``: ``opts.tile_size`` if set, else :data:`COMPILED_TILE_SIZE`
    for the compiled kernels and :func:`auto_tile_size` for the tensor path."""
    if opts.tile_size is not None:
        return opts.tile_size
    return COMPILED_TILE_SIZE if uses_compiled_kernels(opts, like) else auto_tile_size(radii, backward)


def auto_tile_size(radii: Tensor, backward: bool) -> int:
    """The tensor path's faster tile edge for a render: 8 pixels for a forward-only render whose entries' median
    bounding-box half size reaches 4 pixels, else 4.

    Small tiles list a Gaussian in more tiles (binning, sorting, gathering per intersection); large ones evaluate
    more pixels it does not reach. Forward only (``benchmark_scene`` shells of 3 000–100 000 Gaussians, 4 views at
    128²–448², 1 thread, median of 3; ms with tile 4 against 8): median half size 4.5 px 253 against 235, 8 px 571
    against 393, 13.5 px 1 675 against 706, 33.5 px 1 214 against 597; a fitted asset at the full preset (8 261
    Gaussians, 12 views at 448², half size 8 px: the Gauss–Newton fit's renders) 2.6 s against 1.6 s; the small
    preset's (6 000 Gaussians, 128², 3 px) 0.48 s against 0.51 s. Tile 16 was slower than 8 in every case. With a
    backward pass the tile stays 4: the full preset's frame-0 Gaussian fit (half sizes 7–9 px) takes 158–162 s for
    200 steps with it against 169 s with 8, and ``bench speed``'s joint setting (4 px) 504 against 826 ms, although
    synthetic shells of half size 6.5–33.5 px are 1.1–1.6× faster with 8.

    Args:
        radii: (M, 2) the visible entries' bounding-box half sizes in pixels.
        backward: whether the render will be differentiated.
    """
    if backward or radii.shape[0] == 0:
        return AUTO_TILE_SIZES[0]
    half = float(radii.to(torch.float32).mean(1).median())
    return AUTO_TILE_SIZES[1] if half >= 4.0 else AUTO_TILE_SIZES[0]


@dataclass
class TileBins:
    """Depth-sorted (tile, entry) intersection lists.

    Attributes:
        isect_entry: (I,) int64 entry index of each intersection, grouped by tile, depth-sorted within.
        tile_start, tile_count: (n_tiles,) int64 offset and length of each tile's list.
        tiles_x, tiles_y, n_views, tile_size: the tiling; global tile id is
            ``view * tiles_y * tiles_x + ty * tiles_x + tx``.
    """

    isect_entry: Tensor
    tile_start: Tensor
    tile_count: Tensor
    tiles_x: int
    tiles_y: int
    n_views: int
    tile_size: int

    @property
    def n_tiles(self) -> int:
        return self.n_views * self.tiles_y * self.tiles_x

    @property
    def n_intersections(self) -> int:
        return int(self.isect_entry.shape[0])


@torch.no_grad()
def bin_gaussians(
    params: Tensor,
    radii: Tensor,
    depths: Tensor,
    view_ids: Tensor,
    n_views: int,
    width: int,
    height: int,
    tile_size: int,
    compiled: bool = False,
) -> TileBins:
    """List each visible entry in the tiles its α ≥ 1/255 region can touch, depth-sorted per tile.

    Args:
        params: (M, 6) entry parameters [μx, μy, a, b, c, log o] (see :func:`composite`).
        radii: (M, 2) bounding-box half sizes in pixels.
        depths: (M,) camera depths (sort key).
        view_ids: (M,) view of each entry.
        compiled: list them with the compiled CPU kernels (:func:`vid2sim.splats.raster_kernels.bin_tiles`: the
            same lists in a few passes instead of a global sort and tensors the size of every candidate tile; CPU
            tensors only, where :func:`uses_compiled_kernels` holds).
    """
    device = params.device
    ts = tile_size
    tx_n = math.ceil(width / ts)
    ty_n = math.ceil(height / ts)
    p = params.detach()
    mux, muy, a, b, c, lo = p.unbind(1)
    r = radii.to(p.dtype)
    tx0 = torch.floor((mux - r[:, 0]) / ts).clamp(0, tx_n).long()
    tx1 = torch.ceil((mux + r[:, 0]) / ts).clamp(0, tx_n).long()
    ty0 = torch.floor((muy - r[:, 1]) / ts).clamp(0, ty_n).long()
    ty1 = torch.ceil((muy + r[:, 1]) / ts).clamp(0, ty_n).long()
    nx = tx1 - tx0
    counts = nx * (ty1 - ty0)
    # conservative circle test: σ ≥ ½ λ_min |q − μ|², and α < 1/255 ⇔ σ > ln(255 o)
    lam_min = 0.5 * (a + c) - torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0))
    reach2 = (2.0 * (_LOG_255 + lo) / lam_min.clamp_min(1e-12)) * (1 + 1e-5) + 1e-6
    if compiled:
        return _compiled_bins(mux, muy, reach2, tx0, ty0, nx, ty1 - ty0, view_ids, depths, n_views, tx_n, ty_n, ts)

    # per-entry arrays in depth order, so that expanding them to candidates reads memory in order
    order = torch.argsort(depths.detach(), stable=True)
    per = torch.stack([tx0, ty0, nx, counts, view_ids.long()], dim=1).index_select(0, order).to(torch.int32)
    tx0_o, ty0_o, nx_o, counts_o, view_o = per.unbind(1)
    geo_o = torch.stack([mux, muy, reach2], dim=1).index_select(0, order)
    M = order.shape[0]
    cand = torch.repeat_interleave(torch.arange(M, device=device, dtype=torch.int32), counts_o)  # ascending
    first = torch.cumsum(counts_o, 0, dtype=torch.int32) - counts_o
    local = torch.arange(cand.shape[0], device=device, dtype=torch.int32) - first.index_select(0, cand)
    nx_e = nx_o.index_select(0, cand)
    ty_loc = torch.div(local, nx_e, rounding_mode="floor")
    tx = tx0_o.index_select(0, cand) + (local - ty_loc * nx_e)
    ty = ty0_o.index_select(0, cand) + ty_loc
    # conservative circle test against the tile's nearest pixel centre
    g = geo_o.index_select(0, cand)
    mx_e, my_e = g[:, 0], g[:, 1]
    x0 = tx.to(p.dtype) * ts
    y0 = ty.to(p.dtype) * ts
    dx = torch.minimum(torch.maximum(mx_e, x0 + 0.5), x0 + (ts - 0.5)) - mx_e
    dy = torch.minimum(torch.maximum(my_e, y0 + 0.5), y0 + (ts - 0.5)) - my_e
    kept = torch.nonzero(dx * dx + dy * dy <= g[:, 2]).squeeze(1)
    cand, tx, ty = cand.index_select(0, kept), tx.index_select(0, kept), ty.index_select(0, kept)
    tile = (view_o.index_select(0, cand) * ty_n + ty) * tx_n + tx
    n_tiles = n_views * ty_n * tx_n
    if n_tiles <= 2**15:
        key = tile.to(torch.int16)
    elif n_tiles < 2**31:
        key = tile
    else:  # pragma: no cover - beyond 2³¹ tiles
        key = tile.long()
    _, perm = torch.sort(key, stable=True)
    tile_count = torch.bincount(tile, minlength=n_tiles)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    entry = order.index_select(0, cand.index_select(0, perm))
    return TileBins(
        isect_entry=entry,
        tile_start=tile_start,
        tile_count=tile_count,
        tiles_x=tx_n,
        tiles_y=ty_n,
        n_views=n_views,
        tile_size=ts,
    )


def _compiled_bins(mux: Tensor, muy: Tensor, reach2: Tensor, tx0: Tensor, ty0: Tensor, nx: Tensor, ny: Tensor,
                   view_ids: Tensor, depths: Tensor, n_views: int, tx_n: int, ty_n: int, ts: int) -> TileBins:
    """:func:`bin_gaussians`' lists from its per-entry boxes by the compiled kernels. The tiles' nearest-pixel bounds
    are made here as the tensor path makes them (tile index × size, then ± the half pixel, in the entries' dtype), so
    the circle test compares the same numbers."""
    dtype = mux.dtype

    def bounds(n: int) -> tuple[np.ndarray, np.ndarray]:
        start = torch.arange(n).to(dtype) * ts
        return (start + 0.5).numpy(), (start + (ts - 0.5)).numpy()

    col_lo, col_hi = bounds(tx_n)
    row_lo, row_hi = bounds(ty_n)
    if n_views * ty_n * tx_n >= 2**31:  # pragma: no cover - beyond 2³¹ tiles
        raise ValueError(f"{n_views} views of {ty_n} × {tx_n} tiles: more tiles than 32-bit tile ids hold")
    small = [t.to(torch.int32).numpy() for t in (tx0, ty0, nx, ny, view_ids)]  # half the memory to read
    entry, tile_start, tile_count = raster_kernels.bin_tiles(
        mux.contiguous().numpy(), muy.contiguous().numpy(), reach2.contiguous().numpy(), *small,
        depths.detach().contiguous().numpy(), col_lo, col_hi, row_lo, row_hi, tx_n, ty_n, n_views,
        torch.get_num_threads())
    return TileBins(isect_entry=torch.from_numpy(entry), tile_start=torch.from_numpy(tile_start),
                    tile_count=torch.from_numpy(tile_count), tiles_x=tx_n, tiles_y=ty_n, n_views=n_views,
                    tile_size=ts)


def _pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(6, P) monomials [1, u, v, u², uv, v²] of the tile-local pixel-centre coordinates."""
    c = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - tile_size / 2
    v, u = torch.meshgrid(c, c, indexing="ij")  # pixels row-major inside a tile: v = row, u = column
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v])


def _tile_centres(tiles: Tensor, bins: TileBins, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(A, 1) pixel coordinates of the centres of the given global tile ids."""
    local = tiles % (bins.tiles_x * bins.tiles_y)
    ts = bins.tile_size
    cx = (local % bins.tiles_x).to(dtype) * ts + ts / 2
    cy = torch.div(local, bins.tiles_x, rounding_mode="floor").to(dtype) * ts + ts / 2
    return cx[:, None], cy[:, None]


class _Slots:
    """Each tile's depth-sorted list cut into blocks of K slots (the last one padded).

    Block ``bstart[t] + c`` holds entries ``[cK, (c+1)K)`` of tile t's list, so one depth chunk of
    a group of tiles is one gather of whole blocks. Per slot it holds the negated quadratic
    coefficients ``ncoef = −coef`` (so that ``ncoef @ basis = −σ'``), the features and the centre
    offset (μ − tile centre) needed by the backward pass. Padding slots get σ' = 10⁴ (α = 0, so
    they add nothing) and point at entry 0.
    """

    def __init__(self, params: Tensor, feat1: Tensor, bins: TileBins, K: int):
        dev, dtype = params.device, params.dtype
        cnt = bins.tile_count
        nb = torch.div(cnt + (K - 1), K, rounding_mode="floor")
        self.bstart = torch.cumsum(nb, 0) - nb
        B = int(nb.sum())
        blk_tile = torch.repeat_interleave(torch.arange(bins.n_tiles, device=dev), nb)
        rank = (torch.arange(B, device=dev) - self.bstart.index_select(0, blk_tile)) * K
        rank = rank[:, None] + torch.arange(K, device=dev)  # (B, K) position in the tile's list
        valid = rank < cnt.index_select(0, blk_tile)[:, None]
        src = (bins.tile_start.index_select(0, blk_tile)[:, None] + rank) * valid
        # padding slots point at entry 0: their α is forced to 0, so they contribute nothing either way
        self.entry = bins.isect_entry.index_select(0, src.reshape(-1)) if B else src.reshape(-1)
        # the slots' parameters point-last (6, B, K): each term below is one contiguous element-wise pass
        mux, muy, a, b, c, lo = params.t().index_select(1, self.entry).view(6, B, K).unbind(0)
        cx, cy = _tile_centres(blk_tile, bins, dtype)
        mx, my = mux - cx, muy - cy
        qmx = torch.addcmul(a * mx, b, my)  # (Qm)ₓ
        qmy = torch.addcmul(b * mx, c, my)  # (Qm)_y
        neg_const = lo - 0.5 * (mx * qmx + my * qmy)  # −(½ mᵀQm − log o)
        neg_const = torch.where(valid, neg_const, neg_const.new_full((), -_PAD_SIGMA))
        self.ncoef = torch.stack([neg_const, qmx, qmy, -0.5 * a, -b, -0.5 * c], dim=-1)  # (B, K, 6)
        self.mxy = torch.stack([mx, my], dim=-1)  # (B, K, 2)
        self.feat = feat1.index_select(0, self.entry).view(B, K, feat1.shape[1])  # (B, K, C1); B may be 0
        self.n_blocks = B


def _param_grads(d_ncoef: Tensor, ncoef: Tensor, mxy: Tensor, out: Tensor) -> Tensor:
    """Per-slot ∂L/∂[μx, μy, a, b, c, log o] (…, 6), written into ``out`` and returned, from n = ∂L/∂(−coef) (…, 6).

    coef = [½ mᵀQm − log o, −(Qm)ₓ, −(Qm)_y, ½a, b, ½c] with Q = [[a, b], [b, c]] and m = μ − tile centre. With
    the slots' ``ncoef`` = [·, (Qm)ₓ, (Qm)_y, q₀, q₁, q₂] (q = −[½a, b, ½c]) and v = (n₁, n₂) − ½ n₀ m:
    ∂μ = −n₀ Qm + Q (n₁, n₂), ∂a = mₓvₓ − ½n₃, ∂b = mₓv_y + m_yvₓ − n₄, ∂c = m_yv_y − ½n₅, ∂log o = n₀ —
    written column by column into the result (a few fused element-wise operations each).
    """
    n0, n1, n2, n3, n4, n5 = d_ncoef.unbind(-1)
    qmx, qmy, q0, q1, q2 = ncoef[..., 1:].unbind(-1)
    mx, my = mxy.unbind(-1)
    vx = torch.addcmul(n1, n0, mx, value=-0.5)
    vy = torch.addcmul(n2, n0, my, value=-0.5)
    d_mx, d_my, d_a, d_b, d_c, d_log_o = out.unbind(-1)
    torch.mul(n0, qmx, out=d_mx).addcmul_(n1, q0, value=2.0).addcmul_(n2, q1).neg_()  # −n₀(Qm)ₓ + a n₁ + b n₂
    torch.mul(n0, qmy, out=d_my).addcmul_(n1, q1).addcmul_(n2, q2, value=2.0).neg_()  # −n₀(Qm)_y + b n₁ + c n₂
    torch.mul(mx, vx, out=d_a).add_(n3, alpha=-0.5)
    torch.mul(mx, vy, out=d_b).addcmul_(my, vx).sub_(n4)
    torch.mul(my, vy, out=d_c).add_(n5, alpha=-0.5)
    d_log_o.copy_(n0)
    return out


def _alpha(ncoef: Tensor, basis: Tensor, alpha_th: float) -> tuple[Tensor, Tensor]:
    """o·exp(−σ') and α = min(0.999, ·) zeroed below 1/255, both (A, K, P)."""
    vis = torch.exp(ncoef @ basis)
    alpha = F.threshold_(vis.clamp(max=MAX_ALPHA), alpha_th, 0.0)
    return vis, alpha


def _transmittance(alpha: Tensor, p_in: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """T before each Gaussian, the inclusion mask (0/1), weights w (all (A, K, P)) and the running
    transmittance after the chunk (A, P)."""
    A, K, P = alpha.shape
    cp = torch.empty(A, K + 1, P, dtype=alpha.dtype, device=alpha.device)
    cp[:, 0] = p_in
    torch.sub(1.0, alpha, out=cp[:, 1:])
    cp.cumprod_(dim=1)
    t_before = cp[:, :-1]
    incl = torch.empty_like(alpha)
    torch.gt(cp[:, 1:], T_EPS, out=incl)
    w = alpha * t_before
    w.mul_(incl)
    return t_before, incl, w, cp[:, -1]


def _groups(n: int, K: int, P: int, max_elements: int) -> list[tuple[int, int]]:
    per = max(1, max_elements // (K * P))
    return [(s, min(n, s + per)) for s in range(0, n, per)]


def _alpha_threshold(dtype: torch.dtype) -> float:
    """Largest value below 1/255 in ``dtype``: ``F.threshold`` keeps x > th, i.e. α ≥ 1/255."""
    t = torch.tensor(ALPHA_THRESHOLD, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros((), dtype=dtype)))


class _Composite(torch.autograd.Function):
    """(params (M, 6), feat (M, C)) → acc (n_tiles, C + 1, P), the last channel being Σ w."""

    @staticmethod
    def forward(ctx, params: Tensor, feat: Tensor, bins: TileBins, opts: RasterOptions):  # type: ignore[override]
        ts = bins.tile_size
        P = ts * ts
        dtype, device = params.dtype, params.device
        feat1 = torch.cat([feat, torch.ones_like(feat[:, :1])], dim=1)
        C1 = feat1.shape[1]
        basis = _pixel_basis(ts, dtype, device)
        th = _alpha_threshold(dtype)
        K = opts.chunk
        slots = _Slots(params, feat1, bins, K)
        acc = torch.zeros(bins.n_tiles, C1, P, dtype=dtype, device=device)
        active = torch.nonzero(bins.tile_count > 0).squeeze(1)
        acc_act = torch.zeros(active.numel(), C1, P, dtype=dtype, device=device)
        p_act = torch.ones(active.numel(), P, dtype=dtype, device=device)
        steps: list[tuple[Tensor, Tensor, Tensor, Tensor]] = []
        c = 0
        while active.numel():
            bids = slots.bstart.index_select(0, active) + c
            count = bins.tile_count.index_select(0, active)
            p_next = torch.empty_like(p_act)
            for s, e in _groups(active.numel(), K, P, opts.max_elements):
                ncoef = slots.ncoef.index_select(0, bids[s:e])
                f = slots.feat.index_select(0, bids[s:e])
                _, alpha = _alpha(ncoef, basis, th)
                _, _, w, p_last = _transmittance(alpha, p_act[s:e])
                acc_act[s:e].baddbmm_(f.transpose(1, 2), w)
                p_next[s:e] = p_last
            c += 1
            keep = (count > c * K) & (p_next > T_EPS).any(dim=1)
            kept = torch.nonzero(keep).squeeze(1)
            done = torch.nonzero(~keep).squeeze(1)
            acc.index_copy_(0, active.index_select(0, done), acc_act.index_select(0, done))
            steps.append((active, bids, p_act, kept))
            active = active.index_select(0, kept)
            acc_act = acc_act.index_select(0, kept)
            p_act = p_next.index_select(0, kept)
        ctx.save_for_backward(params, acc)
        ctx.slots, ctx.opts, ctx.steps, ctx.C1 = slots, opts, steps, C1
        return acc

    @staticmethod
    def backward(ctx, grad_acc: Tensor):  # type: ignore[override]
        params, acc = ctx.saved_tensors
        slots: _Slots = ctx.slots
        K = ctx.opts.chunk
        C = ctx.C1 - 1
        ts = int(math.isqrt(acc.shape[2]))
        P = ts * ts
        basis = _pixel_basis(ts, params.dtype, params.device)
        basis_t = basis.T.contiguous()
        th = _alpha_threshold(params.dtype)
        # per-slot gradients [∂μx, ∂μy, ∂a, ∂b, ∂c, ∂log o, ∂f_0 … ∂f_{C-1}]
        d_slots = torch.zeros(slots.n_blocks, K, 6 + C, dtype=params.dtype, device=params.device)
        grad_acc = grad_acc.contiguous()
        if ctx.steps:
            first = ctx.steps[0][0]
            g_act = grad_acc.index_select(0, first)  # (A, C1, P)
            rem = (g_act * acc.index_select(0, first)).sum(1)  # Σ_all (g·f_j) w_j, (A, P)
        for active, bids, p_in, kept in ctx.steps:
            rem_next = torch.empty_like(rem)
            for s, e in _groups(active.numel(), K, P, ctx.opts.max_elements):
                b = bids[s:e]
                ncoef = slots.ncoef.index_select(0, b)
                f = slots.feat.index_select(0, b)
                vis, alpha = _alpha(ncoef, basis, th)
                t_before, incl, w, _ = _transmittance(alpha, p_in[s:e])
                g = g_act[s:e]
                gf = f @ g  # (A, K, P): g·f_k
                rest = torch.cumsum(gf * w, dim=1).neg_().add_(rem[s:e, None, :])  # Σ_{j>k} (g·f_j) w_j
                rem_next[s:e] = rest[:, -1]
                d_alpha = gf.mul_(t_before).sub_(rest.div_(torch.rsub(alpha, 1.0)))  # ∂L/∂α
                unclamped = torch.empty_like(vis)
                torch.le(vis, MAX_ALPHA, out=unclamped)
                d_alpha.mul_(alpha).mul_(incl).mul_(unclamped)  # ∂L/∂(−σ') = α ∂L/∂α
                d_ncoef = d_alpha @ basis_t  # (A, K, 6)
                d = torch.empty(e - s, K, 6 + C, dtype=params.dtype, device=params.device)
                _param_grads(d_ncoef, ncoef, slots.mxy.index_select(0, b), d[..., :6])
                d[..., 6:] = w @ g[:, :C].transpose(1, 2)
                d_slots.index_copy_(0, b, d)
            g_act = g_act.index_select(0, kept)
            rem = rem_next.index_select(0, kept)
        out = torch.zeros(params.shape[0], 6 + C, dtype=params.dtype, device=params.device)
        out.index_add_(0, slots.entry, d_slots.reshape(-1, 6 + C))
        return out[:, :6], out[:, 6:], None, None


class _CompiledComposite(torch.autograd.Function):
    """:class:`_Composite` by the compiled CPU kernels of :mod:`vid2sim.splats.raster_kernels` (same contract)."""

    @staticmethod
    def forward(ctx, params: Tensor, feat: Tensor, bins: TileBins):  # type: ignore[override]
        params = params.detach().contiguous()
        feat1 = torch.cat([feat.detach(), torch.ones_like(feat[:, :1])], dim=1).contiguous()
        acc = params.new_zeros(bins.n_tiles, feat1.shape[1], bins.tile_size ** 2)
        raster_kernels.composite_forward(params.numpy(), feat1.numpy(), *_bins_arrays(bins),
                                         _alpha_threshold(params.dtype), acc.numpy(), torch.get_num_threads())
        ctx.save_for_backward(params, feat1, acc)
        ctx.bins = bins
        return acc

    @staticmethod
    def backward(ctx, grad_acc: Tensor):  # type: ignore[override]
        params, feat1, acc = ctx.saved_tensors
        bins: TileBins = ctx.bins
        C = feat1.shape[1] - 1
        d_isect = params.new_zeros(bins.n_intersections, 6 + C)
        raster_kernels.composite_backward(params.numpy(), feat1.numpy(), *_bins_arrays(bins),
                                          _alpha_threshold(params.dtype), grad_acc.contiguous().numpy(), acc.numpy(),
                                          d_isect.numpy(), torch.get_num_threads())
        out = params.new_zeros(params.shape[0], 6 + C)
        raster_kernels.sum_rows(bins.isect_entry.numpy(), d_isect.numpy(), out.numpy())
        return out[:, :6], out[:, 6:], None


def _bins_arrays(bins: TileBins) -> tuple:
    """The tile lists as the compiled kernels take them: entry, tile_start, tile_count, tiles_x, tiles_y, tile_size."""
    return (bins.isect_entry.numpy(), bins.tile_start.numpy(), bins.tile_count.numpy(), bins.tiles_x, bins.tiles_y,
            bins.tile_size)


def composite(params: Tensor, feat: Tensor, bins: TileBins, opts: RasterOptions) -> Tensor:
    """Differentiable front-to-back compositing, in tile layout.

    Args:
        params: (M, 6) per-entry [μx, μy, a, b, c, log o]: pixel centre, conic, log opacity.
        feat: (M, C) per-entry features (colour channels, depth, …).
        bins: tile lists from :func:`bin_gaussians` (built from the same ``params``).
        opts: chunking options.

    Returns:
        ``acc: (n_tiles, C + 1, P)`` with channels Σ_k f_k w_k and, last, Σ_k w_k = 1 − T
        (P = tile_size² pixels, row-major inside each tile).

    Raises:
        ConfigError: ``opts.kernels`` "compiled" for tensors the kernels do not take (:func:`uses_compiled_kernels`).
    """
    if uses_compiled_kernels(opts, params):
        return _CompiledComposite.apply(params, feat, bins)
    return _Composite.apply(params, feat, bins, opts)


def untile(x: Tensor, bins: TileBins, width: int, height: int) -> Tensor:
    """(n_tiles, C, P) tile layout → (V, H, W, C) images (cropped to the image size)."""
    ts = bins.tile_size
    C = x.shape[1]
    img = x.reshape(bins.n_views, bins.tiles_y, bins.tiles_x, C, ts, ts).permute(0, 1, 4, 2, 5, 3)
    img = img.reshape(bins.n_views, bins.tiles_y * ts, bins.tiles_x * ts, C)
    return img[:, :height, :width]
