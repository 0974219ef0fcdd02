"""Image metrics: PSNR and SSIM of rendered against reference images, per image and averaged.

Images are floats in [0, 1] with the channels last: one image (H, W, C) or a batch (N, H, W, C); C = 3 for
RGB. Tensors or numpy arrays are accepted. The metric functions (:func:`psnr`, :func:`ssim`,
:func:`image_metrics`) evaluate in float64 and return Python floats; :func:`ssim_map` keeps the input's
dtype and is differentiable, so 3DGS fitting (`vid2sim.splats.losses`) uses the same implementation.

**PSNR** = −10 log10(MSE) for a peak value of 1, with the MSE clamped below at 1e-10: identical images
give 100 dB instead of infinity (a finite number that survives JSON).

**SSIM** (Wang et al. 2004) as the 3D Gaussian Splatting code computes it: an 11 × 11 Gaussian window with
σ = 1.5 (separable, normalised), C1 = (0.01 L)², C2 = (0.03 L)² with dynamic range L = 1, local
statistics per channel, biased (population) variances, and "same" convolution — zero padding of
window // 2 = 5 pixels so the SSIM map has the image's size (3DGS's ``F.conv2d(..., padding=window_size // 2)``)
— then the mean of the map over positions, channels and images. Zero padding makes the border
statistics differ from a reflecting or cropping implementation; ``padding="valid"`` (no padding, the
map shrinks by window − 1) is the convention of `vid2sim.splats.losses` for training and matches
scikit-image's interior (scikit-image ignores a border of (window − 1) // 2 pixels).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

ArrayLike = Tensor | np.ndarray

#: PSNR's floor on the mean squared error: identical images score −10 log10(1e-10) = 100 dB.
MSE_FLOOR = 1e-10
#: Images per chunk of the SSIM evaluation in :func:`image_metrics` (bounds the memory of the blur).
_SSIM_CHUNK = 8


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> Tensor:
    """Normalised 1-D Gaussian window (size,), centred at (size − 1) / 2."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"the SSIM window size must be odd and positive, got {size}")
    if not sigma > 0:
        raise ValueError(f"the SSIM window sigma must be positive, got {sigma}")
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    w = torch.exp(-(x**2) / (2 * sigma**2))
    return w / w.sum()


def _as_tensor(x: ArrayLike, name: str) -> Tensor:
    t = x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))
    if not t.is_floating_point():
        raise TypeError(f"{name} must hold floats in [0, 1], got dtype {t.dtype}")
    return t


def _as_batch(render: ArrayLike, target: ArrayLike) -> tuple[Tensor, Tensor, bool]:
    """Both images as (N, H, W, C) tensors on the render's device; whether the input was one image."""
    a = _as_tensor(render, "render")
    b = _as_tensor(target, "target").to(a.device)
    if a.shape != b.shape:
        raise ValueError(f"render and target must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim not in (3, 4):
        raise ValueError(f"images must have shape (H, W, C) or (N, H, W, C), got {tuple(a.shape)}")
    single = a.ndim == 3
    if single:
        a, b = a.unsqueeze(0), b.unsqueeze(0)
    if a.shape[0] == 0 or a.shape[-1] == 0:
        raise ValueError(f"no images to compare (shape {tuple(a.shape)})")
    return a, b, single


def ssim_map(render: ArrayLike, target: ArrayLike, window: int = 11, sigma: float = 1.5,
             padding: Literal["same", "valid"] = "same") -> Tensor:
    """Per-pixel, per-channel SSIM of two images (the shared implementation; differentiable).

    Args:
        render, target: (H, W, C) or (N, H, W, C) floats in [0, 1], same shape.
        window, sigma: the Gaussian window (odd size; 11 and 1.5 as in 3DGS).
        padding: ``"same"`` — zero padding of window // 2, map of the image's size (3DGS's convention,
            the evaluation default); ``"valid"`` — no padding, only windows inside the image.

    Returns:
        (N, H', W', C), or (H', W', C) for one image, in the input's dtype: H' = H for ``"same"``,
        H − window + 1 for ``"valid"`` (likewise W').
    """
    a, b, single = _as_batch(render, target)
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    N, H, W, C = a.shape
    if padding == "valid" and (H < window or W < window):
        raise ValueError(f"images of {H}x{W} are smaller than the {window}x{window} SSIM window")
    g = gaussian_window(window, sigma, a.dtype, a.device)
    pad = window // 2 if padding == "same" else 0
    x = a.permute(0, 3, 1, 2)
    y = b.permute(0, 3, 1, 2)
    mu_x, mu_y, xx, yy, xy = _separable_blur(torch.cat([x, y, x * x, y * y, x * y], dim=0), g, pad).split(N, dim=0)
    var_x = xx - mu_x * mu_x
    var_y = yy - mu_y * mu_y
    cov = xy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    s = s.permute(0, 2, 3, 1)
    return s[0] if single else s


def _separable_blur(x: Tensor, g: Tensor, pad: int) -> Tensor:
    """(N, C, H, W) x correlated with the window g ⊗ g (k taps) after zero padding by ``pad`` on each side:
    (N, C, H + 2·pad − k + 1, W + 2·pad − k + 1), differentiable.

    Two equal computations, the faster for the dtype: float64 (the evaluation's precision) as k shifted, weighted
    sums per direction, for which PyTorch's CPU convolution has no fast kernel; other dtypes as two depthwise
    convolutions (oneDNN on a CPU for the channels-last images SSIM passes, cuDNN on a GPU). Twelve 448² images in
    float64, "same" (1 thread, median of 3): 1.9 s with the sums against 8.5 s with the convolutions; the Gaussian
    fit's float32 loss on two 448² views, forward and backward: 0.09 s with the convolutions against 0.32 s with the
    sums. The two agree to 1e-14 (tests/test_metrics_images.py)."""
    k = g.numel()
    if x.dtype != torch.float64:
        C = x.shape[1]
        kx = g.reshape(1, 1, 1, k).expand(C, 1, 1, k)
        ky = g.reshape(1, 1, k, 1).expand(C, 1, k, 1)
        # separable: zero padding per direction equals the 2-D convolution's zero padding
        return F.conv2d(F.conv2d(x, kx, padding=(0, pad), groups=C), ky, padding=(pad, 0), groups=C)
    weights = g.tolist()
    for dim in (-1, -2):
        if pad:
            x = F.pad(x, (pad, pad) if dim == -1 else (0, 0, pad, pad))
        size = x.shape[dim] - k + 1
        out = x.narrow(dim, 0, size) * weights[0]
        for j in range(1, k):
            out.add_(x.narrow(dim, j, size), alpha=weights[j])
        x = out
    return x


def _per_image_mse(a: Tensor, b: Tensor) -> Tensor:
    """(N,) mean squared error of each image pair of (N, H, W, C) stacks, in float64."""
    return ((a.detach().double() - b.detach().double()) ** 2).mean(dim=(1, 2, 3))


def _psnr_from_mse(mse: Tensor) -> Tensor:
    return -10.0 * torch.log10(mse.clamp_min(MSE_FLOOR))


def psnr(render: ArrayLike, target: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1] (peak 1).

    The MSE is the mean over every pixel and channel of the whole input — for a batch, one pooled MSE
    (not the mean of per-image PSNRs; :func:`image_metrics` gives those) — or, with a mask, the
    mask-weighted mean over the masked pixels' channels. The MSE is clamped at 1e-10, so identical
    images give 100 dB rather than infinity.

    Args:
        render, target: (H, W, C) or (N, H, W, C), same shape.
        mask: optional (H, W) / (N, H, W) (or with a trailing 1): bool, or float weights ≥ 0; must not be
            all zero.

    Returns:
        PSNR in dB.
    """
    a, b, single = _as_batch(render, target)
    sq = (a.detach().double() - b.detach().double()) ** 2
    if mask is None:
        mse = sq.mean()
    else:
        m = (mask if isinstance(mask, Tensor) else torch.as_tensor(np.asarray(mask))).detach().to(a.device)
        expected = tuple(a.shape[1:3]) if single else tuple(a.shape[:3])
        if tuple(m.shape) == expected + (1,):
            m = m[..., 0]
        if tuple(m.shape) != expected:
            raise ValueError(f"mask must have shape {expected} (optionally with a trailing 1), got {tuple(m.shape)}")
        m = m.double().reshape(a.shape[:3])
        if bool((m < 0).any()):
            raise ValueError("mask weights must be non-negative")
        total = float(m.sum())
        if not total > 0:
            raise ValueError("mask selects no pixels")
        mse = (sq.sum(dim=-1) * m).sum() / (total * a.shape[-1])
    return float(_psnr_from_mse(mse))


def ssim(render: ArrayLike, target: ArrayLike) -> float:
    """Mean SSIM (3DGS convention: 11×11 Gaussian window, σ = 1.5, "same" zero padding) in float64.

    Args:
        render, target: (H, W, C) or (N, H, W, C) in [0, 1], same shape.

    Returns:
        The mean of the SSIM map over positions, channels and images (1 for identical images).
    """
    a, b, _ = _as_batch(render, target)
    total = 0.0
    for i in range(0, a.shape[0], _SSIM_CHUNK):
        total += float(ssim_map(a[i : i + _SSIM_CHUNK].detach().double(), b[i : i + _SSIM_CHUNK].detach().double())
                       .sum())
    return total / a.numel()


def image_metrics(renders: ArrayLike, targets: ArrayLike, layout: Literal["TV", "VT"] | None = None) -> dict:
    """PSNR and SSIM of every image of a stack, and their means.

    Every image is scored on its own (:func:`psnr` of the pair, :func:`ssim` of the pair); the means are
    means of those per-image values (the usual novel-view-synthesis convention).

    Args:
        renders, targets: (N, H, W, 3) stacks, or (T, V, H, W, 3) / (V, T, H, W, 3) multi-view videos,
            floats in [0, 1], same shape.
        layout: for 5-D input, required: ``"TV"`` for (T, V, H, W, 3) or ``"VT"`` for (V, T, H, W, 3) (the
            scene folder's order, ``Scene.images``). Must be None for 4-D input.

    Returns:
        A JSON-ready dict. Always: ``psnr``, ``ssim`` (floats, means over all images), ``num_images``.
        For (N, H, W, 3): ``psnr_per_frame``, ``ssim_per_frame`` — lists of N, one per image.
        For 5-D input: ``psnr_per_frame`` / ``ssim_per_frame`` — (T,) means over the views of each time
        step; ``psnr_per_view`` / ``ssim_per_view`` — (V,) means over time of each view;
        ``psnr_per_image`` / ``ssim_per_image`` — T lists of V values, indexed [t][v] whatever the
        input layout; and ``layout``.
    """
    a = _as_tensor(renders, "renders")
    b = _as_tensor(targets, "targets").to(a.device)
    if a.shape != b.shape:
        raise ValueError(f"renders and targets must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim == 5:
        if layout not in ("TV", "VT"):
            raise ValueError("5-D image stacks need layout='TV' for (T, V, H, W, 3) or layout='VT' for "
                             f"(V, T, H, W, 3) (the scene folder's order), got layout={layout!r}")
        if layout == "VT":
            a, b = a.transpose(0, 1), b.transpose(0, 1)
        T, V = a.shape[:2]
        a, b = a.reshape(T * V, *a.shape[2:]), b.reshape(T * V, *b.shape[2:])
    elif a.ndim == 4:
        if layout is not None:
            raise ValueError(f"layout is only for 5-D stacks; got it with a 4-D stack {tuple(a.shape)}")
        T, V = a.shape[0], 1
    else:
        raise ValueError(f"image stacks must have shape (N, H, W, 3), (T, V, H, W, 3) or (V, T, H, W, 3), "
                         f"got {tuple(a.shape)}")
    if a.shape[0] == 0:
        raise ValueError("no images to compare")
    p = _psnr_from_mse(_per_image_mse(a, b))
    s = torch.cat([ssim_map(a[i : i + _SSIM_CHUNK].detach().double(), b[i : i + _SSIM_CHUNK].detach().double())
                   .mean(dim=(1, 2, 3)) for i in range(0, a.shape[0], _SSIM_CHUNK)])
    out: dict = {"psnr": float(p.mean()), "ssim": float(s.mean()), "num_images": int(a.shape[0])}
    if V == 1 and layout is None:
        out["psnr_per_frame"] = [float(v) for v in p]
        out["ssim_per_frame"] = [float(v) for v in s]
        return out
    p, s = p.reshape(T, V), s.reshape(T, V)
    out.update({
        "layout": layout,
        "psnr_per_frame": [float(v) for v in p.mean(dim=1)],
        "ssim_per_frame": [float(v) for v in s.mean(dim=1)],
        "psnr_per_view": [float(v) for v in p.mean(dim=0)],
        "ssim_per_view": [float(v) for v in s.mean(dim=0)],
        "psnr_per_image": [[float(v) for v in row] for row in p],
        "ssim_per_image": [[float(v) for v in row] for row in s],
    })
    return out


__all__ = ["MSE_FLOOR", "gaussian_window", "image_metrics", "psnr", "ssim", "ssim_map"]
