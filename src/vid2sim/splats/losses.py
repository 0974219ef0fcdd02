"""Photometric losses of 3DGS fitting: L1, SSIM / D-SSIM and PSNR on (V, H, W, C) image batches.

SSIM follows Wang et al. (2004) as 3DGS uses it: an 11 × 11 Gaussian window with σ = 1.5,
C1 = (0.01 L)², C2 = (0.03 L)² with dynamic range L = 1, local statistics over the window's valid
positions only ("valid" convolution: no padding, so image borders add no artificial edges), mean
over positions and channels. The SSIM itself is `vid2sim.metrics.images.ssim_map` (one implementation
for training and evaluation; evaluation uses its "same" zero-padded variant, 3DGS's metric convention).
"""

from __future__ import annotations

import math

from torch import Tensor

from vid2sim.metrics.images import ssim_map as _ssim_map


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim != 4:
        raise ValueError(f"images must be batched (V, H, W, C), got shape {tuple(a.shape)}")


def ssim_map(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-position SSIM of two image batches ``(V, H, W, C)`` in [0, 1] → ``(V, H−w+1, W−w+1, C)``.

    The "valid" variant of the one SSIM implementation, :func:`vid2sim.metrics.images.ssim_map`.
    """
    _check_pair(a, b)
    return _ssim_map(a, b, window, sigma, padding="valid")


def ssim(a: Tensor, b: Tensor) -> Tensor:
    """Mean SSIM of two ``(V, H, W, C)`` batches (a 0-d tensor; 1 for identical images)."""
    return ssim_map(a, b).mean()


def l1(a: Tensor, b: Tensor) -> Tensor:
    """Mean absolute difference."""
    _check_pair(a, b)
    return (a - b).abs().mean()


def photometric_loss(render: Tensor, target: Tensor, lambda_dssim: float = 0.2) -> Tensor:
    """3DGS image loss (1 − λ) L1 + λ (1 − SSIM) on ``(V, H, W, C)`` batches (λ = 0.2)."""
    return (1.0 - lambda_dssim) * l1(render, target) + lambda_dssim * (1.0 - ssim(render, target))


def psnr(a: Tensor, b: Tensor) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (over the whole batch)."""
    _check_pair(a, b)
    mse = float(((a.detach() - b.detach()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
