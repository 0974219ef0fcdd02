"""The input frame of the networks that take rest positions (skinning field, Neural Jacobian).

The reconstruction trains them on the object's canonical points (centred, half bounding-box diagonal 0.5)
while the simulator runs in the scene's metric frame; a network with an input frame evaluates itself at
X̂ = (X − centre) / scale. Both are buffers, so they are saved and loaded with the weights.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


class InputFrame(nn.Module):
    """Mixin for modules evaluated at X̂ = (X − ``input_centre``) / ``input_scale`` (identity by default)."""

    def _init_input_frame(self) -> None:
        self.register_buffer("input_centre", torch.zeros(3))
        self.register_buffer("input_scale", torch.ones(()))

    @torch.no_grad()
    def set_input_frame(self, centre: Tensor, scale: float) -> None:
        """Evaluate the network at the canonical point (X − centre) / scale instead of X.

        Args:
            centre: (3,) the object's centre in the world frame.
            scale: positive length (m) that maps to 1 (the bounding-box diagonal for the canonical frame).
        """
        centre = torch.as_tensor(centre, dtype=self.input_centre.dtype, device=self.input_centre.device)
        if centre.shape != (3,) or not bool(torch.isfinite(centre).all()):
            raise ValueError(f"input frame centre must be 3 finite numbers, got {centre.tolist()}")
        if not (math.isfinite(float(scale)) and float(scale) > 0):
            raise ValueError(f"input frame scale must be a positive finite length, got {scale}")
        self.input_centre.copy_(centre)
        self.input_scale.fill_(float(scale))

    def _canonical(self, X: Tensor) -> Tensor:
        return (X - self.input_centre) / self.input_scale
