"""Rotations of a scenario's initial pose (``initial.euler_deg``, ``initial.axis_angle``) as (3, 3) float64 matrices."""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

__all__ = ["euler_to_matrix", "axis_angle_to_matrix"]


def euler_to_matrix(euler_deg: Sequence[float]) -> Tensor:
    """R = Rz Ry Rx (3, 3) float64 for rotations (rx, ry, rz) in degrees about the fixed world axes."""
    rx, ry, rz = (math.radians(float(a)) for a in euler_deg)

    def rot(axis: int, a: float) -> torch.Tensor:
        c, s = math.cos(a), math.sin(a)
        i, j = [(1, 2), (0, 2), (0, 1)][axis]
        m = torch.eye(3, dtype=torch.float64)
        m[i, i], m[j, j] = c, c
        m[i, j], m[j, i] = (-s, s) if axis != 1 else (s, -s)
        return m

    return rot(2, rz) @ rot(1, ry) @ rot(0, rx)


def axis_angle_to_matrix(axis_angle: Sequence[float]) -> Tensor:
    """Rodrigues' rotation (3, 3) float64 about the axis (ax, ay, az) by the angle (degrees), right-handed."""
    axis = torch.tensor([float(a) for a in axis_angle[:3]], dtype=torch.float64)
    axis = axis / axis.norm()
    a = math.radians(float(axis_angle[3]))
    K = torch.zeros(3, 3, dtype=torch.float64)
    K[0, 1], K[0, 2], K[1, 2] = -axis[2], axis[1], -axis[0]
    K = K - K.T
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * K + (1 - math.cos(a)) * (K @ K)
