"""The object's position in every observed frame from its silhouettes: the centroid of each frame's visual hull.

The joint fit compares rendered images with the video, and the images say little about where the whole body is
once the simulated motion has parted from the truth: a fit may then trade the body's position for a better match
of its texture (a fitted floor friction on a frictionless drop walked the centre of mass 3–5 cm sideways,
docs/results.md). The visual hull of each observed frame, carved from the masks of all the observed views, locates
the body directly. Its centroid is not the centre of mass (a hull fills concavities; the carve is coarser on sides no
view sees in profile), but while the body keeps its shape that error is nearly the same from frame to frame, so the
centroid's *displacement* from frame 0 follows the centre of mass's: within 4–5 mm RMS over the 16 observed frames
of four 12-view full-size scenes, 7–18 mm with the small preset's 4 views. A body that deforms changes both: on a soft
full-size scene that squashes flat (its hull 15 % smaller from the contact on) the centroid was 12–30 mm off. The
hull's volume says when: :meth:`HullTrack.frame_sd` widens a frame's standard deviation by how much its hull's
volume differs from frame 0's (``vid2sim.reconstruct.stages.joint``'s track term uses it; docs/architecture.md,
"The hull track").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.mass import voxel_moments
from vid2sim.splats.cameras import Camera
from vid2sim.splats.visual_hull import visual_hull


@dataclass
class HullTrack:
    """Each observed frame's visual hull, reduced to its centroid and volume.

    Attributes:
        centroids: (T, 3) float64, world metres.
        volumes: (T,) float64, m³.
    """

    centroids: Tensor
    volumes: Tensor

    def frame_sd(self, sd: float, volume_tolerance: float | None) -> Tensor:
        """(T−1,) the standard deviation of frames 1 … T−1's displacements from frame 0: ``sd``, times
        |V_t / V_0 − 1| / ``volume_tolerance`` where the hull's volume changed by more than that fraction (the body
        deformed, and its hull's centroid no longer follows its centre of mass); ``sd`` everywhere with None."""
        out = torch.full((self.centroids.shape[0] - 1,), float(sd), dtype=torch.float64)
        if volume_tolerance is None:
            return out
        change = (self.volumes[1:] / self.volumes[0] - 1.0).abs()
        return out * (change / volume_tolerance).clamp_min(1.0)


def hull_track(masks: Tensor, cameras: Sequence[Camera], resolution: int = 64, threshold: float = 0.5,
               progress: bool = False) -> HullTrack:
    """The centroid and volume of each frame's visual hull.

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
    centroids, volumes = [], []
    for t in tqdm(range(masks.shape[1]), desc="visual hull per frame", disable=not progress, leave=False):
        try:
            occupancy, lo, voxel = visual_hull(masks[:, t].float().cpu(), list(cameras), resolution=resolution,
                                               threshold=threshold)
        except ValueError as exc:
            raise ValueError(f"frame {t}: {exc}") from None
        moments = voxel_moments(occupancy.cpu(), lo.cpu(), float(voxel))  # (volume, first moments, …)
        centroids.append(moments[1:4] / moments[0])
        volumes.append(float(moments[0]))
    return HullTrack(torch.stack(centroids), torch.tensor(volumes, dtype=torch.float64))
