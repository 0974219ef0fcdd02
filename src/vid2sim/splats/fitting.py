"""Fit 3D Gaussians to one time instant seen by several calibrated cameras (Stage I geometry).

The paper initialises appearance and geometry with LGM, a feed-forward model whose weights cannot
be downloaded here; its own ablation "Stage I + fit GS" shows that fitting Gaussians to the first
frames is nearly as good. :func:`fit_gaussians` does that: initial Gaussians from an
:class:`~vid2sim.splats.visual_hull.Initializer` (the visual hull of the masks by default; a
feed-forward predictor can be passed instead), then 3DGS optimisation with

    loss = (1 − λ) L1 + λ (1 − SSIM)  (λ = 0.2)  +  w_mask · |alpha − mask|,

Adam with the 3DGS learning rates (positions scaled by the scene extent and decayed exponentially),
one SH band switched on at a time, and adaptive density control (:mod:`vid2sim.splats.densify`) on
a schedule scaled to the iteration count (3DGS's 30 000-iteration schedule: densify from 500 to
15 000 every 100 steps, opacity reset every 3 000, one more SH band every 1 000).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.densify import Densifier, DensifyConfig
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.losses import photometric_loss, psnr
from vid2sim.splats.rasterize import RasterOptions
from vid2sim.splats.render import BACKENDS, RenderOutput, render
from vid2sim.splats.visual_hull import Initializer, VisualHullInitializer


@dataclass
class FitConfig:
    """Settings of :func:`fit_gaussians` (3DGS defaults, schedule as fractions of ``iterations``).

    Attributes:
        iterations: optimisation steps (each renders ``views_per_step`` views).
        sh_degree: final SH degree; bands are switched on one by one every ``sh_band_every`` of the run.
        lambda_dssim: weight λ of the D-SSIM term.
        mask_weight: weight of the L1 alpha-vs-mask term.
        background: RGB background of the images (white for vid2sim scenes).
        lr_means, lr_means_final: position learning rate at the start and end (× scene extent).
        lr_sh_dc, lr_sh_rest, lr_opacity, lr_scales, lr_quats: 3DGS learning rates.
        densify_from, densify_until: densification window as fractions of the run.
        densify_every: steps between densifications (None: ``max(5, iterations // 45)``).
        opacity_reset_every: fraction of the run between opacity resets (inside the window), but
            never fewer than ``min_reset_interval`` steps apart: after a reset, opacities need on the
            order of a hundred Adam steps to recover, so short runs reset rarely or never.
        min_reset_interval: see ``opacity_reset_every``.
        sh_band_every: fraction of the run between SH band increases.
        views_per_step: views rendered per step (None: all; otherwise a random subset).
        densify: density-control thresholds.
        seed: seeds initialisation sampling, view subsets and splits.
        raster_options: torch-backend tuning.
        backend: rendering backend ("auto", "torch", "gsplat").
    """

    iterations: int = 1000
    sh_degree: int = 3
    lambda_dssim: float = 0.2
    mask_weight: float = 0.1
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify_from: float = 500 / 30000
    densify_until: float = 0.5
    densify_every: int | None = None
    opacity_reset_every: float = 0.1
    min_reset_interval: int = 300
    sh_band_every: float = 1 / 30
    views_per_step: int | None = None
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    seed: int = 0
    raster_options: RasterOptions | None = None
    backend: str = "auto"

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ConfigError(f"FitConfig.iterations must be >= 1, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise ConfigError(f"FitConfig.sh_degree must be 0, 1, 2 or 3, got {self.sh_degree}")
        if not 0 <= self.densify_from <= self.densify_until <= 1:
            raise ConfigError(
                f"FitConfig needs 0 <= densify_from <= densify_until <= 1, got {self.densify_from}, "
                f"{self.densify_until}"
            )
        if not 0 <= self.lambda_dssim <= 1:
            raise ConfigError(f"FitConfig.lambda_dssim must be in [0, 1], got {self.lambda_dssim}")
        if self.mask_weight < 0:
            raise ConfigError(f"FitConfig.mask_weight must be >= 0, got {self.mask_weight}")
        if self.densify_every is not None and self.densify_every < 1:
            raise ConfigError(f"FitConfig.densify_every must be >= 1 or None, got {self.densify_every}")
        if self.min_reset_interval < 1:
            raise ConfigError(f"FitConfig.min_reset_interval must be >= 1, got {self.min_reset_interval}")
        if self.views_per_step is not None and self.views_per_step < 1:
            raise ConfigError(f"FitConfig.views_per_step must be >= 1 or None, got {self.views_per_step}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"FitConfig.backend must be one of {BACKENDS}, got {self.backend!r}")


def scene_extent(cameras: Sequence[Camera]) -> float:
    """3DGS's scene scale: 1.1 × the largest distance of a camera centre from their mean."""
    centres = torch.stack([c.center.double() for c in cameras])
    return 1.1 * max(float((centres - centres.mean(0)).norm(dim=1).max()), 1e-6)


def _check_inputs(images: Tensor, masks: Tensor, cameras: Sequence[Camera]) -> None:
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must have shape (V, H, W, 3), got {tuple(images.shape)}")
    V, H, W, _ = images.shape
    if masks.shape != (V, H, W):
        raise ValueError(f"masks must have shape (V={V}, H={H}, W={W}), got {tuple(masks.shape)}")
    if len(cameras) != V:
        raise ValueError(f"need one camera per image: {V} images, {len(cameras)} cameras")
    _, _, w, h = stack_cameras(cameras)
    if (w, h) != (W, H):
        raise ValueError(f"cameras are {w}x{h} but the images are {W}x{H}")
    if not images.is_floating_point() or float(images.min()) < 0 or float(images.max()) > 1:
        lo, hi = (float(images.min()), float(images.max())) if images.is_floating_point() else (None, None)
        raise ValueError(f"images must be floating point in [0, 1], got {images.dtype} with range [{lo}, {hi}]")
    if masks.dtype != torch.bool:
        if not masks.is_floating_point():
            raise ValueError(f"masks must be bool or floating point in [0, 1], got {masks.dtype}")
        lo, hi = float(masks.min()), float(masks.max())
        if lo < 0 or hi > 1:
            raise ValueError(f"masks must lie in [0, 1], got values in [{lo}, {hi}]")


def _schedule(cfg: FitConfig) -> tuple[int, int, int, int, int]:
    n = cfg.iterations
    every = cfg.densify_every if cfg.densify_every is not None else max(5, n // 45)
    start = int(round(cfg.densify_from * n))
    stop = int(round(cfg.densify_until * n))
    reset = max(cfg.min_reset_interval, int(round(cfg.opacity_reset_every * n)), 1)
    band = max(1, int(round(cfg.sh_band_every * n)))
    return every, start, stop, reset, band


def fit_gaussians(
    images: Tensor,
    masks: Tensor,
    cameras: Sequence[Camera],
    config: FitConfig | None = None,
    initializer: Initializer | None = None,
    progress: bool = True,
    history: list[dict[str, float]] | None = None,
) -> Gaussians:
    """Fit Gaussians to ``images: (V, H, W, 3)`` in [0, 1] with object ``masks: (V, H, W)``.

    Args:
        cameras: V calibrated cameras (OpenCV convention), one per image, of the images' size.
        config: optimisation settings (:class:`FitConfig`).
        initializer: produces the initial Gaussians (default :class:`VisualHullInitializer`).
        progress: show a tqdm progress bar.
        history: if given, one dict per step is appended: ``step``, ``loss``, ``psnr`` (of the
            views rendered in that step), ``gaussians`` (count after the step), ``densified`` and
            ``opacity_reset`` (1.0 on the steps where density control / the opacity reset ran).

    Returns:
        The fitted :class:`Gaussians` (detached), on the images' device and dtype.
    """
    cfg = config if config is not None else FitConfig()
    _check_inputs(images, masks, cameras)
    dev, dt = images.device, images.dtype
    cams = [c.to(dev) for c in cameras]
    masks = masks.to(dt)
    gen = torch.Generator().manual_seed(cfg.seed)
    g0 = _initial_gaussians(images, masks, cams, cfg, initializer, gen)
    extent = scene_extent(cams)
    params, optimizer = _adam(g0, cfg, extent)
    means_group = next(gr for gr in optimizer.param_groups if gr["name"] == "means")
    densifier = Densifier(cfg.densify, extent)
    every, start, stop, reset, band = _schedule(cfg)
    bg = torch.tensor(cfg.background, dtype=dt, device=dev)
    V = images.shape[0]
    decay = math.log(cfg.lr_means_final / cfg.lr_means)
    reset_done = False

    bar = tqdm(range(1, cfg.iterations + 1), disable=not progress, desc="fit Gaussians", leave=False)
    for step in bar:
        frac = (step - 1) / max(1, cfg.iterations - 1)
        means_group["lr"] = cfg.lr_means * extent * math.exp(decay * frac)
        degree = min(cfg.sh_degree, (step - 1) // band)
        views = _step_views(V, cfg, gen)
        densifying = start <= step < stop
        out, loss = _render_loss(params, [cams[i] for i in views], images[views], masks[views], degree, bg, cfg,
                                 densifying)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if densifying:
            densifier.accumulate(out.means2d.grad, out.radii, images.shape[2], images.shape[1])
        optimizer.step()
        densified = densifying and step > start and step % every == 0
        if densified:
            densifier.densify_and_prune(params, optimizer, gen, prune_large=reset_done)
        opacity_reset = densifying and step % reset == 0
        if opacity_reset:
            densifier.reset_opacity(params, optimizer)
            reset_done = True
        if history is not None or (progress and step % 10 == 0):
            stats = _step_stats(step, loss, psnr(out.rgb, images[views]), params, densified, opacity_reset)
            if history is not None:
                history.append(stats)
            if progress and step % 10 == 0:
                bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.1f}", n=int(stats["gaussians"]))
    bar.close()
    return _detached_gaussians(params)


def _step_views(V: int, cfg: FitConfig, gen: torch.Generator) -> list[int]:
    """The views rendered in a step: all V, or ``cfg.views_per_step`` of them drawn with ``gen``."""
    if cfg.views_per_step is None or cfg.views_per_step >= V:
        return list(range(V))
    return torch.randperm(V, generator=gen)[: cfg.views_per_step].tolist()


def _step_stats(step: int, loss: Tensor, step_psnr: float, params: dict[str, Tensor], densified: bool,
                opacity_reset: bool) -> dict[str, float]:
    """One entry of ``fit_gaussians``' history (see its docstring)."""
    return {"step": float(step), "loss": float(loss.detach()), "psnr": step_psnr,
            "gaussians": float(params["means"].shape[0]), "densified": float(densified),
            "opacity_reset": float(opacity_reset)}


def _initial_gaussians(images: Tensor, masks: Tensor, cams: list[Camera], cfg: FitConfig,
                       initializer: Initializer | None, gen: torch.Generator) -> Gaussians:
    """The initializer's Gaussians (default :class:`VisualHullInitializer`) for ``images`` (V, H, W, 3) and
    ``masks`` (V, H, W), in their device and dtype with ``cfg.sh_degree``; refused when there are none."""
    init = initializer if initializer is not None else VisualHullInitializer()
    g0 = init(images, masks, cams, cfg.sh_degree, gen)
    if not isinstance(g0, Gaussians) or g0.num == 0:
        raise ValueError("the initializer returned no Gaussians")
    return g0.to(device=images.device, dtype=images.dtype).with_sh_degree(cfg.sh_degree)


def _adam(g0: Gaussians, cfg: FitConfig, extent: float) -> tuple[dict[str, Tensor], torch.optim.Adam]:
    """The optimised tensors of ``g0`` (means (N, 3), log_scales (N, 3), quats (N, 4), opacity_logits (N,),
    sh_dc (N, 1, 3), sh_rest (N, B − 1, 3)) and their Adam, one named group each at ``cfg``'s learning rate (the
    means' scaled by the scene ``extent``)."""
    params = {
        "means": g0.means.detach().clone(),
        "log_scales": g0.log_scales.detach().clone(),
        "quats": g0.quats.detach().clone(),
        "opacity_logits": g0.opacity_logits.detach().clone(),
        "sh_dc": g0.sh[:, :1].detach().clone(),
        "sh_rest": g0.sh[:, 1:].detach().clone(),
    }
    lrs = {
        "means": cfg.lr_means * extent,
        "log_scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacity_logits": cfg.lr_opacity,
        "sh_dc": cfg.lr_sh_dc,
        "sh_rest": cfg.lr_sh_rest,
    }
    for t in params.values():
        t.requires_grad_(True)
    optimizer = torch.optim.Adam(
        [{"params": [params[k]], "lr": lrs[k], "name": k} for k in params], lr=0.0, eps=1e-15
    )
    return params, optimizer


def _render_loss(params: dict[str, Tensor], cams: list[Camera], target: Tensor, masks: Tensor, degree: int,
                 bg: Tensor, cfg: FitConfig, densifying: bool) -> tuple[RenderOutput, Tensor]:
    """The Gaussians of ``params`` rendered in ``cams`` with SH degree ``degree`` over ``bg`` (3,), and the loss
    against ``target`` (V', H, W, 3) and ``masks`` (V', H, W): photometric, plus the mask term when weighted.
    While ``densifying`` the screen-space means keep their gradient for the density control."""
    sh = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
    out = render(
        params["means"],
        torch.sigmoid(params["opacity_logits"]),
        sh,
        cams,
        quats=params["quats"],
        scales=torch.exp(params["log_scales"]),
        sh_degree=degree,
        background=bg,
        backend=cfg.backend,
        raster_options=cfg.raster_options,
    )
    if densifying:
        out.means2d.retain_grad()
    loss = photometric_loss(out.rgb, target, cfg.lambda_dssim)
    if cfg.mask_weight > 0:
        loss = loss + cfg.mask_weight * (out.alpha[..., 0] - masks).abs().mean()
    return out, loss


def _detached_gaussians(params: dict[str, Tensor]) -> Gaussians:
    """The fitted :class:`Gaussians` of the optimised tensors, detached."""
    sh = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
    return Gaussians(
        means=params["means"].detach(),
        log_scales=params["log_scales"].detach(),
        quats=params["quats"].detach(),
        opacity_logits=params["opacity_logits"].detach(),
        sh=sh.detach(),
    )
