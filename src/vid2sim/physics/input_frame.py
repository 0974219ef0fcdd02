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

    def _in_parameters_dtype(self, X: Tensor, parameter: Tensor) -> Tensor:
        """Check rest positions X: (N, 3) (finite, floating, on ``parameter``'s device) and return them in
        ``parameter``'s dtype: the networks evaluate in their own dtype and their callers cast the result back to
        X's (a float64 simulator reads a float32 network)."""
        check_points(X)
        if X.device != parameter.device:
            raise ValueError(f"X is on {X.device} but the {type(self).__name__}'s parameters are on {parameter.device}")
        return X.to(parameter.dtype)


def check_points(X: Tensor, name: str = "X") -> None:
    """Raise a TypeError / ValueError naming ``name`` unless X is a finite floating-point tensor of shape (N, 3)."""
    if not isinstance(X, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (N, 3), got {type(X).__name__}")
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(X.shape)}")
    if not X.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {X.dtype}")
    if not bool(torch.isfinite(X).all()):
        bad = int((~torch.isfinite(X)).any(dim=1).sum())
        raise ValueError(f"{name} contains NaN or infinite values ({bad} of {X.shape[0]} points)")


def uniform_(p: Tensor, bound: float, gen: torch.Generator | None) -> None:
    """Fill ``p`` in place with U(−bound, bound), drawn in float64 on the CPU from ``gen`` (the same values for a
    seed whatever ``p``'s dtype and device)."""
    vals = torch.rand(p.shape, generator=gen, dtype=torch.float64) * (2 * bound) - bound
    with torch.no_grad():
        p.copy_(vals.to(dtype=p.dtype, device=p.device))
