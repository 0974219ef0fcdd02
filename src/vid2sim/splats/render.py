"""One differentiable rendering function for 3D Gaussians, with two backends behind it.

:func:`render` takes Gaussians as plain tensors (so that a simulator can hand it deformed means and
covariances) and a batch of :class:`~vid2sim.splats.cameras.Camera` objects, and returns RGB, alpha
and expected depth for every view. Backends:

- ``"torch"`` — our own rasteriser (:mod:`vid2sim.splats.rasterize`), CPU or GPU, any float dtype: PyTorch for the
  projection and binning, and for compositing compiled kernels on the CPU (:mod:`vid2sim.splats.raster_kernels`,
  numba) and tensor operations elsewhere.
- ``"gsplat"`` — gsplat 1.5.3's CUDA rasteriser (:mod:`vid2sim.splats.gsplat_backend`); CUDA and
  float32 only; install with ``pip install "vid2sim[cuda]"``.

``backend="auto"`` takes gsplat when the tensors are float32 on a CUDA device and gsplat's kernels
load (they are built on first use), and the torch backend otherwise — with a warning saying why when
the tensors are on CUDA but gsplat cannot run. Both follow the same conventions (EWA projection with a 0.3 px²
low-pass, α = min(0.999, o·G), skip α < 1/255, stop at T ≤ 1e-4, 3DGS spherical harmonics with the
``+0.5`` offset, pixel centres at +0.5), so their images agree to float32 rounding.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.deform import DeformedGaussians
from vid2sim.splats.gaussians import Gaussians, covariances_from_scales_quats
from vid2sim.splats.gsplat_backend import render_gsplat
from vid2sim.splats.projection import project_gaussians
from vid2sim.splats.rasterize import (
    RasterOptions,
    bin_gaussians,
    composite,
    tile_size_for,
    untile,
    uses_compiled_kernels,
)
from vid2sim.splats.sh import eval_sh, num_sh_bases, sh_basis

if TYPE_CHECKING:  # pragma: no cover
    from vid2sim.splats.deform import DeformedGaussians

BACKENDS = ("auto", "torch", "gsplat")


@dataclass
class RenderOutput:
    """What :func:`render` returns for V views of N Gaussians at H × W pixels.

    Attributes:
        rgb: (V, H, W, D) composited colour over the background (D = 3 for RGB / SH colours).
        alpha: (V, H, W, 1) accumulated opacity 1 − T.
        depth: (V, H, W, 1) expected camera depth Σ wᵢ zᵢ / Σ wᵢ (0 where alpha is 0).
        means2d: (V, N, 2) projected centres in pixels. Part of the autograd graph: call
            ``means2d.retain_grad()`` before ``backward()`` to read the screen-space gradients that
            densification uses.
        radii: (V, N, 2) int32 screen bounding-box half sizes; 0 where a Gaussian is culled in a view.
        backend: the backend that rendered (``"torch"`` or ``"gsplat"``).
    """

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    backend: str


def _probe_gsplat() -> str | None:
    """None when gsplat's CUDA kernels load (building them on first use), else one line saying why not."""
    try:
        import gsplat  # noqa: F401
    except Exception as e:  # ImportError, or a broken install
        return f"gsplat is not importable ({type(e).__name__}: {e})"
    try:
        from gsplat.cuda._backend import _C
    except Exception as e:  # the JIT build of its kernels failed
        return f"gsplat's CUDA kernels failed to build or load ({type(e).__name__}: {e})"
    if _C is None:
        return "gsplat found no CUDA toolkit (nvcc) to build its kernels with"
    return None


@functools.lru_cache(maxsize=None)
def gsplat_unavailable_reason() -> str | None:
    """Why the gsplat backend cannot run here (None when it can). Probed once per process."""
    return _probe_gsplat()


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype) -> str:
    """The backend ``render`` will use for tensors on ``device`` of ``dtype`` (see module docstring)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        if device.type != "cuda" or dtype != torch.float32:
            return "torch"
        reason = gsplat_unavailable_reason()
        if reason is None:
            return "gsplat"
        warnings.warn(f"rendering with the torch backend on {device}: {reason} (the gsplat backend is much faster "
                      "on CUDA: pip install 'vid2sim[cuda]' where the CUDA toolkit is installed)",
                      RuntimeWarning, stacklevel=3)
        return "torch"
    if backend == "gsplat":
        if device.type != "cuda":
            raise ValueError(
                f"backend 'gsplat' needs the Gaussians on a CUDA device, got tensors on {device}; "
                "use backend='torch' (or 'auto') on CPU"
            )
        if dtype != torch.float32:
            raise ValueError(f"backend 'gsplat' renders float32 only, got {dtype}; use backend='torch' for {dtype}")
        reason = gsplat_unavailable_reason()
        if reason is not None:
            raise RuntimeError(
                f"backend 'gsplat' requested but {reason}; install it with "
                "pip install 'gsplat==1.5.3' packaging  (or pip install 'vid2sim[cuda]') on a machine with "
                "the CUDA toolkit, or use backend='torch'"
            )
    return backend


def _check_inputs(
    means: Tensor,
    opacities: Tensor,
    colors: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    covars: Tensor | None,
    sh_degree: int | None,
    n_views: int,
) -> None:
    if not isinstance(means, Tensor) or means.ndim not in (2, 3) or means.shape[-1] != 3:
        raise ValueError(f"means must be a tensor of shape (N, 3) or (V, N, 3), got "
                         f"{getattr(means, 'shape', type(means))}")
    if not means.is_floating_point():
        raise ValueError(f"means must be a floating tensor, got {means.dtype}")
    if means.ndim == 3 and means.shape[0] != n_views:
        raise ValueError(f"per-view means (V, N, 3) need one set per camera: got V={means.shape[0]} for "
                         f"{n_views} cameras")
    n = means.shape[-2]
    if opacities.shape != (n,):
        raise ValueError(f"opacities must have shape (N={n},), got {tuple(opacities.shape)}")
    if covars is not None:
        if quats is not None or scales is not None:
            raise ValueError("pass either covars or (quats and scales), not both")
        if covars.shape != means.shape[:-1] + (3, 3):
            raise ValueError(f"covars must have shape {tuple(means.shape[:-1]) + (3, 3)} (like means), "
                             f"got {tuple(covars.shape)}")
    else:
        if means.ndim == 3:
            raise ValueError("per-view means (V, N, 3) need per-view covars (V, N, 3, 3), not quats and scales")
        if quats is None or scales is None:
            raise ValueError("pass covars (N, 3, 3), or both quats (N, 4) and scales (N, 3)")
        if quats.shape != (n, 4):
            raise ValueError(f"quats must have shape (N={n}, 4), got {tuple(quats.shape)}")
        if scales.shape != (n, 3):
            raise ValueError(f"scales must have shape (N={n}, 3), got {tuple(scales.shape)}")
    if sh_degree is None:
        if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] < 1:
            raise ValueError(f"colors must have shape (N={n}, D) when sh_degree is None, got {tuple(colors.shape)}")
    else:
        k = num_sh_bases(sh_degree)
        if colors.ndim != 3 or colors.shape[0] != n or colors.shape[2] != 3 or colors.shape[1] < k:
            raise ValueError(
                f"colors must be SH coefficients of shape (N={n}, K>={k}, 3) for sh_degree={sh_degree}, "
                f"got {tuple(colors.shape)}"
            )
    optional = {"opacities": opacities, "colors": colors, "quats": quats, "scales": scales, "covars": covars}
    for name, t in optional.items():
        if t is not None and (t.device != means.device or t.dtype != means.dtype):
            raise ValueError(f"{name} is {t.dtype} on {t.device}; expected means' {means.dtype} on {means.device}")


def _backgrounds(background, n_views: int, channels: int, like: Tensor) -> Tensor:
    bg = torch.as_tensor(background if background is not None else 0.0, dtype=like.dtype, device=like.device)
    if bg.ndim == 0:
        bg = bg.expand(channels)
    if bg.shape == (channels,):
        bg = bg[None].expand(n_views, channels)
    if bg.shape != (n_views, channels):
        raise ValueError(
            f"background must be a scalar, ({channels},) or (V={n_views}, {channels}); got {tuple(bg.shape)}"
        )
    return bg


def render(
    means: Tensor,
    opacities: Tensor,
    colors: Tensor,
    cameras: Camera | Sequence[Camera],
    *,
    quats: Tensor | None = None,
    scales: Tensor | None = None,
    covars: Tensor | None = None,
    sh_degree: int | None = None,
    background: float | Sequence[float] | Tensor | None = 1.0,
    backend: str = "auto",
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    raster_options: RasterOptions | None = None,
) -> RenderOutput:
    """Render N Gaussians into V cameras (all of one image size), differentiably.

    Args:
        means: (N, 3) world centres, or (V, N, 3) one set per camera (e.g. the frames of a simulation, each
            seen by its own cameras: one call composites them all, which costs less than one call per frame).
        opacities: (N,) opacities in [0, 1] (activated, not logits).
        colors: (N, D) colours/features when ``sh_degree`` is None, else (N, K, 3) SH coefficients
            with K ≥ (sh_degree + 1)² (evaluated per view, 3DGS convention).
        cameras: one :class:`Camera` or a sequence of V cameras sharing width and height.
        quats: (N, 4) rotations (w, x, y, z), need not be normalised; with ``scales``.
        scales: (N, 3) standard deviations (activated, not log); with ``quats``.
        covars: (N, 3, 3) world covariances, instead of quats/scales (e.g. the deformed F Σ Fᵀ); (V, N, 3, 3)
            with per-camera means.
        sh_degree: SH degree to evaluate, or None for plain colours.
        background: scalar, (D,) or (V, D) background colour; white (1.0) by default; None = black.
        backend: "auto", "torch" or "gsplat" (see module docstring).
        eps2d: low-pass variance added to each projected covariance (px²).
        near_plane, far_plane: camera-depth range rendered.
        raster_options: tuning of the torch backend (tile size, chunking, memory cap).

    Returns:
        :class:`RenderOutput` with ``rgb (V, H, W, D)``, ``alpha (V, H, W, 1)``, ``depth (V, H, W, 1)``.
        Gradients flow to means, opacities, colors and quats/scales or covars (and to a tensor
        background).
    """
    viewmats, Ks, width, height = stack_cameras(cameras)
    _check_inputs(means, opacities, colors, quats, scales, covars, sh_degree, viewmats.shape[0])
    viewmats = viewmats.to(device=means.device, dtype=means.dtype)
    Ks = Ks.to(device=means.device, dtype=means.dtype)
    n_views = viewmats.shape[0]
    channels = 3 if sh_degree is not None else colors.shape[1]
    bg = _backgrounds(background, n_views, channels, means)
    chosen = resolve_backend(backend, means.device, means.dtype)
    if chosen == "gsplat":

        rgb, alpha, depth, means2d, radii = render_gsplat(
            means, quats, scales, covars, opacities, colors, sh_degree, viewmats, Ks, width, height, bg,
            eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
        )
        return RenderOutput(rgb, alpha, depth, means2d, radii, "gsplat")

    opts = raster_options if raster_options is not None else RasterOptions()
    if covars is None:
        covars = covariances_from_scales_quats(scales, quats)  # type: ignore[arg-type]
    proj = project_gaussians(means, covars, opacities, viewmats, Ks, width, height, eps2d, near_plane, far_plane)
    flat = torch.nonzero(proj.visible.reshape(-1)).squeeze(1)  # visible (view, Gaussian) entries
    n = means.shape[-2]
    v_idx = torch.div(flat, n, rounding_mode="floor")
    g_idx = flat - v_idx * n
    if sh_degree is None:
        col = colors.index_select(0, g_idx)
    else:
        col = _sh_colors(colors, sh_degree, means, viewmats).reshape(-1, 3).index_select(0, flat)
    log_op = torch.log(opacities.clamp_min(1e-30))
    per_view = torch.cat([proj.means2d, proj.conics, proj.depths[..., None]], dim=-1)  # (V, N, 6)
    ent = per_view.reshape(-1, 6).index_select(0, flat)
    params = torch.cat([ent[:, :5], log_op.index_select(0, g_idx)[:, None]], dim=1)  # (M, 6) [μx, μy, a, b, c, log o]
    depths = ent[:, 5]
    feat = torch.cat([col, depths[:, None]], dim=1)  # (M, D + 1)
    radii = proj.radii.reshape(-1, 2).index_select(0, flat)
    tile = tile_size_for(opts, radii, torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (means, opacities, colors, quats, scales, covars)), means)
    bins = bin_gaussians(params, radii, depths, v_idx, n_views, width, height, tile,
                         compiled=uses_compiled_kernels(opts, params))
    acc = composite(params, feat, bins, opts)  # (n_tiles, D + 2, P)
    img = untile(acc, bins, width, height)  # (V, H, W, D + 2)
    alpha = img[..., channels + 1 :]
    rgb = img[..., :channels] + (1.0 - alpha) * bg[:, None, None, :]
    depth = img[..., channels : channels + 1] / alpha.clamp_min(1e-10)
    return RenderOutput(rgb, alpha, depth, proj.means2d, proj.radii, "torch")


def _sh_colors(sh: Tensor, degree: int, means: Tensor, viewmats: Tensor) -> Tensor:
    """(V, N, 3) colours of SH coefficients ``sh: (N, K, 3)`` at ``means`` (N, 3) or (V, N, 3) seen from
    each camera centre."""
    if degree == 0:
        return eval_sh(0, sh, means.reshape(-1, means.shape[-2], 3)[0]).expand(viewmats.shape[0], -1, -1)
    campos = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:]).squeeze(-1)  # (V, 3)
    dirs = (means if means.ndim == 3 else means[None]) - campos[:, None]  # (V, N, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = num_sh_bases(degree)
    basis = sh_basis(degree, dirs)  # (V, N, k)
    rgb = torch.bmm(basis.transpose(0, 1), sh[:, :k])  # (N, V, 3)
    return torch.clamp_min(rgb.transpose(0, 1) + 0.5, 0.0)


def render_gaussians(
    gaussians: "Gaussians | DeformedGaussians",
    cameras: Camera | Sequence[Camera],
    *,
    sh_degree: int | None = None,
    **kwargs,
) -> RenderOutput:
    """Render a :class:`Gaussians` or :class:`~vid2sim.splats.deform.DeformedGaussians` set.

    Uses the set's full SH degree unless ``sh_degree`` is given. Keyword arguments go to
    :func:`render` (background, backend, …).
    """

    deg = gaussians.sh_degree if sh_degree is None else sh_degree
    if isinstance(gaussians, DeformedGaussians):
        return render(gaussians.means, gaussians.opacities, gaussians.sh, cameras,
                      covars=gaussians.covars, sh_degree=deg, **kwargs)
    if not isinstance(gaussians, Gaussians):
        raise ValueError(f"render_gaussians takes Gaussians or DeformedGaussians, got {type(gaussians).__name__}")
    return render(
        gaussians.means,
        gaussians.opacities,
        gaussians.sh,
        cameras,
        quats=gaussians.quats,
        scales=gaussians.scales,
        sh_degree=deg,
        **kwargs,
    )
