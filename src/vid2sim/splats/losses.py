"""Photometric losses of 3DGS fitting: L1, SSIM / D-SSIM and PSNR on (V, H, W, C) image batches.

SSIM follows Wang et al. (2004) as 3DGS uses it: an 11 × 11 Gaussian window with σ = 1.5,
C1 = (0.01 L)², C2 = (0.03 L)² with dynamic range L = 1, local statistics over the window's valid
positions only ("valid" convolution: no padding, so image borders add no artificial edges), mean
over positions and channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim != 4:
        raise ValueError(f"images must be batched (V, H, W, C), got shape {tuple(a.shape)}")


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> Tensor:
    """Normalised 1-D Gaussian window (size,)."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    w = torch.exp(-(x**2) / (2 * sigma**2))
    return w / w.sum()


def ssim_map(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-position SSIM of two image batches ``(V, H, W, C)`` in [0, 1] → ``(V, H−w+1, W−w+1, C)``."""
    _check_pair(a, b)
    V, H, W, C = a.shape
    if H < window or W < window:
        raise ValueError(f"images of {H}x{W} are smaller than the {window}x{window} SSIM window")
    g = gaussian_window(window, sigma, a.dtype, a.device)
    kx = g.reshape(1, 1, 1, window).expand(C, 1, 1, window)
    ky = g.reshape(1, 1, window, 1).expand(C, 1, window, 1)

    def blur(x: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(x, kx, groups=C), ky, groups=C)

    x = a.permute(0, 3, 1, 2)
    y = b.permute(0, 3, 1, 2)
    stats = blur(torch.cat([x, y, x * x, y * y, x * y], dim=0))
    mu_x, mu_y, xx, yy, xy = stats.split(V, dim=0)
    var_x = xx - mu_x * mu_x
    var_y = yy - mu_y * mu_y
    cov = xy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    return s.permute(0, 2, 3, 1)


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
