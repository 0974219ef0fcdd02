"""The CUDA backend of :func:`vid2sim.splats.render.render`: gsplat 1.5.3's ``rasterization``.

gsplat is an optional dependency (``pip install "vid2sim[cuda]"`` → ``gsplat==1.5.3`` and
``packaging``); it is imported only when this backend is used. Its 1.5.3 wheel compiles its CUDA
kernels on first use, which takes minutes once per machine.

The call uses ``render_mode="RGB+ED"`` (colour channels plus expected depth Σwz / Σw as the last
channel), ``packed=False`` (so that ``means2d`` and ``radii`` come back as (V, N, ·) tensors),
``rasterize_mode="classic"`` and the same ``eps2d``, near/far planes and backgrounds as the torch
backend; with ``covars`` given, quats and scales are not passed. gsplat evaluates SH colours as
``max(0, SH(d) + 0.5)`` with d from the camera centre to the Gaussian, exactly like
:func:`vid2sim.splats.sh.eval_sh`.

Covariances are symmetrised, ``(Σ + Σᵀ)/2``, before gsplat reads them: gsplat keeps only the upper
triangle, so the gradient it returns for a 3×3 Σ sits on the upper triangle with doubled off-diagonal
entries. Through the symmetrisation it becomes the symmetric gradient the torch backend returns (the
same chain rule for anything Σ was computed from, e.g. the simulator's F).

``tests/test_splats_gsplat_cpu.py`` runs this wrapper through gsplat's real Python front end on a CPU
(its kernels replaced by gsplat's PyTorch reference code); ``tests/test_splats_gsplat.py`` runs it on the
real CUDA kernels.
"""

from __future__ import annotations

from torch import Tensor


def render_gsplat(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    covars: Tensor | None,
    opacities: Tensor,
    colors: Tensor,
    sh_degree: int | None,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Render with gsplat; same arguments as :func:`vid2sim.splats.render.render` after batching.

    Args:
        means: (N, 3); quats: (N, 4) and scales: (N, 3), or covars: (N, 3, 3); opacities: (N,);
        colors: (N, D) or SH (N, K, 3); viewmats: (V, 4, 4); Ks: (V, 3, 3); backgrounds: (V, D).
        Per-view Gaussians: means (V, N, 3) and covars (V, N, 3, 3), rendered as gsplat's batch of V
        one-camera scenes (opacities and colours shared).

    Returns:
        rgb (V, H, W, D), alpha (V, H, W, 1), depth (V, H, W, 1), means2d (V, N, 2), radii (V, N, 2).
    """
    try:
        from gsplat import rasterization
    except ImportError as e:  # pragma: no cover - exercised only without gsplat
        raise ImportError(
            "the gsplat backend needs gsplat 1.5.3: pip install 'gsplat==1.5.3' packaging"
        ) from e
    if covars is not None:
        quats_arg, scales_arg = None, None
        covars = 0.5 * (covars + covars.transpose(-1, -2))
    else:
        quats_arg, scales_arg = quats, scales
    per_view = means.ndim == 3
    if per_view:  # gsplat's leading batch dimension: V scenes of one camera each
        V = means.shape[0]
        viewmats, Ks, backgrounds = viewmats[:, None], Ks[:, None], backgrounds[:, None]
        opacities = opacities.expand(V, *opacities.shape)
        colors = colors.expand(V, *colors.shape)
    rendered, alphas, meta = rasterization(
        means=means,
        quats=quats_arg,
        scales=scales_arg,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        packed=False,
        backgrounds=backgrounds,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        covars=covars,
    )
    means2d, radii = meta["means2d"], meta["radii"]
    if per_view:
        rendered, alphas, means2d, radii = rendered[:, 0], alphas[:, 0], means2d[:, 0], radii[:, 0]
    rgb = rendered[..., :-1]
    depth = rendered[..., -1:]
    if radii.ndim == 2:  # older layouts return one radius per Gaussian
        radii = radii[..., None].expand(*radii.shape, 2)
    return rgb, alphas, depth, means2d, radii
