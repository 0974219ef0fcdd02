"""Distance between two trajectories of the same points, as a fraction of the object's size.

This is the one measure behind every convergence and accuracy figure of the simulators: for each frame
the mean over points of the Euclidean distance, divided by the object's size (its rest bounding-box
diagonal); then the mean and the maximum over the frames compared (frame 0, the shared initial state, is
left out by default).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass
class TrajectoryDistance:
    """Distances in percent of the size.

    Attributes:
        mean: mean over the compared frames.
        max: largest per-frame value.
        per_frame: (T,) per-frame values for every frame (frame 0 included).
        frames: the frame indices averaged in ``mean`` / ``max``.
    """

    mean: float
    max: float
    per_frame: list[float]
    frames: list[int]

    def to_dict(self) -> dict:
        return {"mean_percent": self.mean, "max_percent": self.max, "frames": [self.frames[0], self.frames[-1]],
                "per_frame_percent": self.per_frame}


def trajectory_distance(a: Tensor | np.ndarray, b: Tensor | np.ndarray, size: float,
                        frames: slice | list[int] | None = None) -> TrajectoryDistance:
    """Distance between trajectories a and b: (T, N, 3) (same points, same frames) in % of ``size``.

    Args:
        a, b: (T, N, 3) positions.
        size: the object's size in the same units (its rest bounding-box diagonal), > 0.
        frames: the frames averaged (a slice or list of indices); default 1 … T−1.
    """
    A = torch.as_tensor(np.asarray(a) if not isinstance(a, Tensor) else a).detach().to(torch.float64)
    B = torch.as_tensor(np.asarray(b) if not isinstance(b, Tensor) else b).detach().to(torch.float64)
    if A.shape != B.shape or A.ndim != 3 or A.shape[-1] != 3:
        raise ValueError(f"trajectories must both have shape (T, N, 3), got {tuple(A.shape)} and {tuple(B.shape)}")
    if not size > 0:
        raise ValueError(f"size must be positive, got {size}")
    per = (A - B.to(A.device)).norm(dim=-1).mean(dim=-1).cpu().numpy() * (100.0 / size)
    T = len(per)
    idx = list(range(T))[frames] if isinstance(frames, slice) else (list(frames) if frames is not None
                                                                    else list(range(1, T)))
    if not idx:
        raise ValueError(f"no frames to compare among {T}")
    sel = per[idx]
    return TrajectoryDistance(float(sel.mean()), float(sel.max()), [float(v) for v in per], idx)
