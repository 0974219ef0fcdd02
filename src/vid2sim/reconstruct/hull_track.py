"""The object's position in every observed frame from its silhouettes: the centroid of each frame's visual hull.

The joint fit compares rendered images with the video, and the images say little about where the whole body is
once the simulated motion has parted from the truth: a fit may then trade the body's position for a better match
of its texture (a fitted floor friction on a frictionless drop walked the centre of mass 3–5 cm sideways,
docs/results.md). The visual hull of each observed frame, carved from the masks of all the observed views, locates
the body directly. Its centroid is not the centre of mass (a hull fills concavities; the carve is coarser on sides no
view sees in profile), but that error is nearly the same from frame to frame, so the centroid's *displacement* from
frame 0 follows the centre of mass's: within 4–5 mm RMS over the 16 observed frames of four 12-view full-size
scenes, 15 mm on a soft one that squashes flat; 7–18 mm with the small preset's 4 views
(``vid2sim.reconstruct.stages.joint``'s track term uses it; docs/architecture.md, "The hull track").
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from vid2sim.splats.cameras import Camera
from vid2sim.splats.visual_hull import visual_hull


def hull_centroids(masks: Tensor, cameras: Sequence[Camera], resolution: int = 64, threshold: float = 0.5,
                   progress: bool = False) -> Tensor:
    """(T, 3) float64: the centroid of each frame's visual hull (world metres).

    Args:
        masks: (V, T, H, W) object masks in [0, 1] of the V observed views over T frames.
        cameras: the V cameras.
        resolution: voxels per side of each frame's hull (:func:`~vid2sim.splats.visual_hull.visual_hull`; 64 puts
            the centroid within 0.1–0.2 mm of a 96³ carve's on the full-size scenes, at 3 s for 16 frames).
        threshold: the mask level inside which a pixel is the object.
    Raises:
        ValueError: masks of the wrong shape, or a frame whose masks leave no hull (naming the frame).
    """
    from tqdm.auto import tqdm

    if masks.dim() != 4 or masks.shape[0] != len(cameras):
        raise ValueError(f"masks must have shape (V={len(cameras)}, T, H, W), got {tuple(masks.shape)}")
    out = []
    for t in tqdm(range(masks.shape[1]), desc="visual hull per frame", disable=not progress, leave=False):
        try:
            occupancy, lo, voxel = visual_hull(masks[:, t].float().cpu(), list(cameras), resolution=resolution,
                                               threshold=threshold)
        except ValueError as exc:
            raise ValueError(f"frame {t}: {exc}") from None
        index = torch.nonzero(occupancy).double()
        out.append(lo.double().cpu() + (index.mean(0) + 0.5) * voxel)
    return torch.stack(out)
