"""Trajectory distances: plain, after rigid alignment, and the deformation of a trajectory."""

import math

import pytest
import torch

from vid2sim.metrics import deformation, nonrigid_distance, rigidly_aligned, trajectory_distance

F64 = torch.float64


def _rotation(axis, angle):
    axis = torch.tensor(axis, dtype=F64) / torch.tensor(axis, dtype=F64).norm()
    K = torch.zeros(3, 3, dtype=F64)
    K[0, 1], K[0, 2], K[1, 2] = -axis[2], axis[1], -axis[0]
    K = K - K.T
    return torch.eye(3, dtype=F64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _cloud(n=200, seed=0):
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64) - 0.5


def test_rigid_motions_have_no_nonrigid_distance_and_no_deformation():
    X = _cloud()
    frames = torch.stack([X @ _rotation((1, 2, 0.5), 0.4 * t).T + torch.tensor([0.1 * t, 0.0, -0.2 * t], dtype=F64)
                          for t in range(4)])
    still = X.expand(4, -1, -1)
    assert trajectory_distance(frames, still, 1.0).mean > 5  # the pose differs...
    assert nonrigid_distance(frames, still, 1.0).max < 1e-10  # ...the shape does not
    assert max(deformation(frames, X, 1.0)) < 1e-10
    assert torch.allclose(rigidly_aligned(frames[2], frames[3]), frames[3], atol=1e-12)


def test_a_reflection_is_not_a_rigid_motion():
    X = _cloud(seed=1)
    mirrored = X * torch.tensor([-1.0, 1.0, 1.0], dtype=F64)
    # the best proper rotation cannot undo a mirror image of an asymmetric cloud
    assert nonrigid_distance(mirrored[None], X[None], 1.0, frames=[0]).mean > 1.0


def test_a_uniform_stretch_is_measured_as_deformation_analytically():
    """x = diag(1 + s, 1, 1) X on a centred cube grid: the best rigid fit is the identity, so the
    deformation is s·mean|X_1|; the pose part of a rotated, stretched copy is removed exactly."""
    g = torch.linspace(-0.5, 0.5, 11, dtype=F64)
    X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    s = 0.1
    stretched = X * torch.tensor([1 + s, 1.0, 1.0], dtype=F64)
    expected = 100 * s * float(X[:, 0].abs().mean())
    assert deformation(stretched[None], X, 1.0)[0] == pytest.approx(expected, rel=1e-9)
    R = _rotation((0.3, -1, 2), 1.1)
    moved = stretched @ R.T + torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    assert nonrigid_distance(moved[None], X[None], 1.0, frames=[0]).mean == pytest.approx(expected, rel=1e-6)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="shape"):
        nonrigid_distance(torch.zeros(2, 5, 3), torch.zeros(2, 4, 3), 1.0)
    with pytest.raises(ValueError, match="rest"):
        deformation(torch.zeros(2, 5, 3), torch.zeros(4, 3), 1.0)
