"""A picture of a fit: target, render and error side by side, one row per view.

``vid2sim fit-gaussians`` writes it as ``comparison.png`` so that a user sees at a glance what the PSNR
figures in ``fit_report.json`` mean, and which views (held out ones especially) are weak.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw
from torch import Tensor

LABEL_HEIGHT = 12
"""Pixels of the black strip above each row that holds its label."""


def comparison_image(
    targets: Tensor,
    renders: Tensor,
    labels: Sequence[str] | None = None,
    max_size: int = 256,
    error_gain: float = 4.0,
    headings: bool = True,
) -> np.ndarray:
    """One row per view: target | render | error (|render − target| averaged over RGB, × ``error_gain``).

    Args:
        targets: (V, H, W, 3) images in [0, 1].
        renders: (V, H, W, 3) rendered images in [0, 1], same shape.
        labels: V strings, each written in a black strip of ``LABEL_HEIGHT`` pixels above its row, or None.
        max_size: panels larger than this (in either side) are downscaled by an integer factor (area
            averaging) so that the picture of a 12-view 448² scene stays a few megabytes.
        error_gain: brightness gain of the error panel (an error of 1/gain shows white).
        headings: a black strip of ``LABEL_HEIGHT`` pixels on top naming the columns ("target", "render",
            "|error| x gain").

    Returns:
        uint8 array of shape (c + V · (h + l), 3 · w, 3), h × w the (possibly downscaled) panel size, l the
        label strip (``LABEL_HEIGHT`` with labels, else 0), c the headings strip (``LABEL_HEIGHT`` or 0).
    """
    if targets.ndim != 4 or targets.shape[-1] != 3:
        raise ValueError(f"targets must have shape (V, H, W, 3), got {tuple(targets.shape)}")
    if renders.shape != targets.shape:
        raise ValueError(f"renders have shape {tuple(renders.shape)}, targets {tuple(targets.shape)}; they must match")
    if labels is not None and len(labels) != targets.shape[0]:
        raise ValueError(f"{len(labels)} labels for {targets.shape[0]} views")
    if max_size < 1:
        raise ValueError(f"max_size must be ≥ 1, got {max_size}")
    with torch.no_grad():
        t = targets.detach().float().cpu().clamp(0, 1)
        r = renders.detach().float().cpu().clamp(0, 1)
        err = ((r - t).abs().mean(-1, keepdim=True) * error_gain).clamp(0, 1).expand_as(t)
        panels = [t, r, err]
        factor = -(-max(t.shape[1], t.shape[2]) // max_size)  # ceil
        if factor > 1:
            h, w = t.shape[1] - t.shape[1] % factor, t.shape[2] - t.shape[2] % factor  # whole blocks only
            panels = [torch.nn.functional.avg_pool2d(p[:, :h, :w].permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1)
                      for p in panels]
        row = torch.cat(panels, dim=2)  # (V, h, 3w, 3)
        if labels:
            row = torch.cat([torch.zeros(row.shape[0], LABEL_HEIGHT, *row.shape[2:]), row], dim=1)
        grid = (row.reshape(-1, row.shape[2], 3) * 255.0 + 0.5).to(torch.uint8).numpy()
    if labels:
        picture = Image.fromarray(grid)
        draw = ImageDraw.Draw(picture)
        for i, label in enumerate(labels):
            draw.text((2, i * row.shape[1] + 1), label, fill=(255, 255, 255))
        grid = np.asarray(picture).copy()
    if headings:
        top = Image.new("RGB", (grid.shape[1], LABEL_HEIGHT))
        draw = ImageDraw.Draw(top)
        w = grid.shape[1] // 3
        for i, name in enumerate(("target", "render", f"|error| x{error_gain:g}")):
            draw.text((i * w + 2, 1), name, fill=(255, 255, 255))
        grid = np.concatenate([np.asarray(top), grid], axis=0)
    return grid
