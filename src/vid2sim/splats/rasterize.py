"""Pure-PyTorch tile rasteriser: front-to-back alpha compositing of image-plane Gaussians.

Semantics (those of the reference 3DGS rasteriser and gsplat's "classic" mode): for each pixel
centre q, Gaussians are taken in increasing camera depth; each has

    α = min(0.999, o · exp(−½ (q − μ)ᵀ Σ2d⁻¹ (q − μ))),

Gaussians with α < 1/255 are skipped, and compositing stops *before* the first Gaussian whose
inclusion would bring the transmittance to 1e-4 or below. A pixel's features are
``Σ_k f_k w_k`` with weights ``w_k = α_k T_k``, ``T_k = Π_{j<k} (1 − α_j)`` over the included
Gaussians; its final transmittance is ``1 − Σ_k w_k``.

How it is made fast and memory-bounded on a CPU:

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
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from vid2sim.splats.projection import ALPHA_THRESHOLD

MAX_ALPHA = 0.999
T_EPS = 1e-4
_PAD_SIGMA = 1e4  # σ' of padding slots: exp(-1e4) == 0, so they are skipped
_LOG_255 = math.log(255.0)


@dataclass
class RasterOptions:
    """Tuning knobs of the pure-PyTorch rasteriser (the image does not depend on them).

    Attributes:
        tile_size: tile edge in pixels (power of two ≤ 32).
        chunk: Gaussians per tile taken in one depth step.
        max_elements: cap on (tile × Gaussian × pixel) triples evaluated at once; peak extra memory
            is about 12 such float tensors.
    """

    tile_size: int = 4
    chunk: int = 16
    max_elements: int = 1 << 18

    def __post_init__(self) -> None:
        ts = self.tile_size
        if not isinstance(ts, int) or ts <= 0 or ts & (ts - 1) or ts > 32:
            raise ValueError(f"RasterOptions.tile_size must be a power of two in [1, 32], got {ts!r}")
        if not isinstance(self.chunk, int) or self.chunk < 1:
            raise ValueError(f"RasterOptions.chunk must be a positive integer, got {self.chunk!r}")
        if self.max_elements < self.chunk * ts * ts:
            raise ValueError(
                f"RasterOptions.max_elements={self.max_elements} is below one tile's chunk "
                f"(chunk * tile_size² = {self.chunk * ts * ts})"
            )


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
) -> TileBins:
    """List each visible entry in the tiles its α ≥ 1/255 region can touch, depth-sorted per tile.

    Args:
        params: (M, 6) entry parameters [μx, μy, a, b, c, log o] (see :func:`composite`).
        radii: (M, 2) bounding-box half sizes in pixels.
        depths: (M,) camera depths (sort key).
        view_ids: (M,) view of each entry.
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

    order = torch.argsort(depths.detach(), stable=True)
    counts_o = counts.index_select(0, order)
    entry = torch.repeat_interleave(order, counts_o)
    first = torch.cumsum(counts_o, 0) - counts_o
    local = torch.arange(entry.shape[0], device=device) - torch.repeat_interleave(first, counts_o)
    nx_e = nx.index_select(0, entry).clamp_min(1)
    ty_loc = torch.div(local, nx_e, rounding_mode="floor")
    tx = tx0.index_select(0, entry) + (local - ty_loc * nx_e)
    ty = ty0.index_select(0, entry) + ty_loc
    # nearest pixel centre of the tile to μ
    mx_e = mux.index_select(0, entry)
    my_e = muy.index_select(0, entry)
    dx = torch.minimum(torch.maximum(mx_e, tx * ts + 0.5), tx * ts + (ts - 0.5)) - mx_e
    dy = torch.minimum(torch.maximum(my_e, ty * ts + 0.5), ty * ts + (ts - 0.5)) - my_e
    kept = torch.nonzero(dx * dx + dy * dy <= reach2.index_select(0, entry)).squeeze(1)
    entry, tx, ty = entry.index_select(0, kept), tx.index_select(0, kept), ty.index_select(0, kept)
    tile = (view_ids.long().index_select(0, entry) * ty_n + ty) * tx_n + tx
    n_tiles = n_views * ty_n * tx_n
    key = tile.to(torch.int32) if n_tiles < 2**31 else tile
    _, perm = torch.sort(key, stable=True)
    tile_count = torch.bincount(tile, minlength=n_tiles)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    return TileBins(
        isect_entry=entry.index_select(0, perm),
        tile_start=tile_start,
        tile_count=tile_count,
        tiles_x=tx_n,
        tiles_y=ty_n,
        n_views=n_views,
        tile_size=ts,
    )


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


class _Step:
    """Per-step lookups for the active tiles: list offsets, lengths and tile centres."""

    def __init__(self, active: Tensor, bins: TileBins, dtype: torch.dtype):
        self.active = active
        self.start = bins.tile_start.index_select(0, active)
        self.count = bins.tile_count.index_select(0, active)
        self.cx, self.cy = _tile_centres(active, bins, dtype)


class _Chunk:
    """Depth chunk [c0, c0 + K) of tiles [s, e) of a step: gathered entries and α at every tile pixel."""

    def __init__(self, params: Tensor, feat1: Tensor, bins: TileBins, step: _Step, s: int, e: int,
                 c0: int, K: int, basis: Tensor, alpha_th: float):
        A = e - s
        pos = c0 + torch.arange(K, device=params.device)
        valid = pos[None, :] < step.count[s:e, None]  # (A, K)
        idx = (step.start[s:e, None] + pos[None, :]) * valid
        ent = bins.isect_entry.index_select(0, idx.reshape(-1)).reshape(A, K)
        self.ent = ent
        prm = params.index_select(0, ent.reshape(-1)).reshape(A, K, 6)
        self.mx = prm[..., 0] - step.cx[s:e]
        self.my = prm[..., 1] - step.cy[s:e]
        a, b, c = prm[..., 2], prm[..., 3], prm[..., 4]
        self.a, self.b, self.c = a, b, c
        self.bx = a * self.mx + b * self.my
        self.by = b * self.mx + c * self.my
        const = 0.5 * (self.mx * self.bx + self.my * self.by) - prm[..., 5]
        const = const * valid + _PAD_SIGMA * (~valid)
        coef = torch.stack([const, -self.bx, -self.by, 0.5 * a, b, 0.5 * c], dim=-1)  # (A, K, 6)
        self.f = feat1.index_select(0, ent.reshape(-1)).reshape(A, K, -1)  # (A, K, C1)
        vis = torch.exp((coef @ basis).neg_())  # (A, K, P) = o·exp(−σ)
        self.vis = vis
        alpha = vis.clamp(max=MAX_ALPHA)
        self.alpha = F.threshold_(alpha, alpha_th, 0.0)

    def transmittance(self, p_in: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(T before each Gaussian, included mask as 0/1 floats, weights w), all (A, K, P)."""
        om = torch.rsub(self.alpha, 1.0)
        self.om = om
        cp = torch.cumprod(torch.cat([p_in[:, None, :], om], dim=1), dim=1)
        t_before = cp[:, :-1]
        self.p_last = cp[:, -1]
        incl = torch.empty_like(om)
        torch.gt(cp[:, 1:], T_EPS, out=incl)
        w = self.alpha * t_before
        w.mul_(incl)
        return t_before, incl, w


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
        acc = torch.zeros(bins.n_tiles, C1, P, dtype=dtype, device=device)
        active = torch.nonzero(bins.tile_count > 0).squeeze(1)
        acc_act = torch.zeros(active.numel(), C1, P, dtype=dtype, device=device)
        p_act = torch.ones(active.numel(), P, dtype=dtype, device=device)
        steps: list[tuple[_Step, int, Tensor, Tensor]] = []
        c0 = 0
        while active.numel():
            step = _Step(active, bins, dtype)
            p_next = torch.empty_like(p_act)
            for s, e in _groups(active.numel(), K, P, opts.max_elements):
                ch = _Chunk(params, feat1, bins, step, s, e, c0, K, basis, th)
                _, _, w = ch.transmittance(p_act[s:e])
                acc_act[s:e] += ch.f.transpose(1, 2) @ w
                p_next[s:e] = ch.p_last
            c0 += K
            keep = (step.count > c0) & (p_next > T_EPS).any(dim=1)
            kept = torch.nonzero(keep).squeeze(1)
            done = torch.nonzero(~keep).squeeze(1)
            acc.index_copy_(0, active.index_select(0, done), acc_act.index_select(0, done))
            steps.append((step, c0 - K, p_act, kept))
            active = active.index_select(0, kept)
            acc_act = acc_act.index_select(0, kept)
            p_act = p_next.index_select(0, kept)
        ctx.save_for_backward(params, feat1, acc)
        ctx.bins, ctx.opts, ctx.steps = bins, opts, steps
        return acc

    @staticmethod
    def backward(ctx, grad_acc: Tensor):  # type: ignore[override]
        params, feat1, acc = ctx.saved_tensors
        bins: TileBins = ctx.bins
        K = ctx.opts.chunk
        ts = bins.tile_size
        P = ts * ts
        C1 = feat1.shape[1]
        basis = _pixel_basis(ts, params.dtype, params.device)
        basis_t = basis.T.contiguous()
        th = _alpha_threshold(params.dtype)
        n_grad = 6 + C1
        grad_all = torch.zeros(params.shape[0] * n_grad, dtype=params.dtype, device=params.device)
        col = torch.arange(n_grad, device=params.device)
        grad_acc = grad_acc.contiguous()
        if not ctx.steps:
            return grad_all.reshape(-1, n_grad)[:, :6], grad_all.reshape(-1, n_grad)[:, 6:-1], None, None
        first = ctx.steps[0][0].active
        g_act = grad_acc.index_select(0, first)  # (A, C1, P)
        rem = (g_act * acc.index_select(0, first)).sum(1)  # Σ_all (g·f_j) w_j, (A, P)
        for step, c0, p_in, kept in ctx.steps:
            rem_next = torch.empty_like(rem)
            for s, e in _groups(step.active.numel(), K, P, ctx.opts.max_elements):
                ch = _Chunk(params, feat1, bins, step, s, e, c0, K, basis, th)
                t_before, incl, w = ch.transmittance(p_in[s:e])
                g = g_act[s:e]
                gf = ch.f @ g  # (A, K, P): g·f_k
                rest = torch.cumsum(gf * w, dim=1).neg_().add_(rem[s:e, None, :])  # Σ_{j>k} (g·f_j) w_j
                rem_next[s:e] = rest[:, -1]
                d_alpha = gf.mul_(t_before).sub_(rest.div_(ch.om))  # ∂L/∂α
                unclamped = torch.empty_like(ch.vis)
                torch.le(ch.vis, MAX_ALPHA, out=unclamped)
                d_alpha.mul_(ch.alpha).mul_(incl).mul_(unclamped)  # = −∂L/∂σ'
                g0, g1, g2, g3, g4, g5 = (d_alpha @ basis_t).neg_().unbind(-1)  # ∂L/∂coef, (A, K) each
                # coef = [½ mᵀ Q m − lo, −(a mx + b my), −(b mx + c my), ½a, b, ½c], m = μ − tile centre
                mx, my = ch.mx, ch.my
                d_f = w @ g.transpose(1, 2)  # (A, K, C1)
                d_all = torch.cat(
                    [
                        torch.stack(
                            [
                                g0 * ch.bx - g1 * ch.a - g2 * ch.b,
                                g0 * ch.by - g1 * ch.b - g2 * ch.c,
                                0.5 * g0 * mx * mx - g1 * mx + 0.5 * g3,
                                g0 * mx * my - g1 * my - g2 * mx + g4,
                                0.5 * g0 * my * my - g2 * my + 0.5 * g5,
                                -g0,
                            ],
                            dim=-1,
                        ),
                        d_f,
                    ],
                    dim=-1,
                )  # (A, K, 6 + C1); padding slots are exactly zero
                flat = (ch.ent.reshape(-1, 1) * n_grad + col).reshape(-1)
                grad_all.index_add_(0, flat, d_all.reshape(-1))
            g_act = g_act.index_select(0, kept)
            rem = rem_next.index_select(0, kept)
        grad_all = grad_all.reshape(-1, n_grad)
        return grad_all[:, :6], grad_all[:, 6 : 6 + C1 - 1], None, None


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
    """
    return _Composite.apply(params, feat, bins, opts)


def untile(x: Tensor, bins: TileBins, width: int, height: int) -> Tensor:
    """(n_tiles, C, P) tile layout → (V, H, W, C) images (cropped to the image size)."""
    ts = bins.tile_size
    C = x.shape[1]
    img = x.reshape(bins.n_views, bins.tiles_y, bins.tiles_x, C, ts, ts).permute(0, 1, 4, 2, 5, 3)
    img = img.reshape(bins.n_views, bins.tiles_y * ts, bins.tiles_x * ts, C)
    return img[:, :height, :width]
