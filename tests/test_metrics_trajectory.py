"""Trajectory distances: plain, after rigid alignment, and the deformation of a trajectory."""

import math

import pytest
import torch

from vid2sim.metrics import (
    deformation,
    nonrigid_distance,
    rigidly_aligned,
    trajectory_distance,
)

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


def test_carry_by_tets_follows_an_affine_motion_exactly_inside_and_outside():
    """Under an affine motion x -> A x + b of the whole mesh every tet has F = A, so points inside and points
    just outside the mesh (bound to the tet they are least outside of) move exactly with it."""
    from vid2sim.metrics import carry_by_tets

    g = torch.Generator().manual_seed(0)
    cube = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]],
                        dtype=torch.float64)
    tets = torch.tensor([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    frames = [cube]
    maps = []
    for _ in range(3):
        A = torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64)
        b = torch.randn(3, generator=g, dtype=torch.float64)
        maps.append((A, b))
        frames.append(cube @ A.T + b)
    inside = torch.rand(50, 3, generator=g, dtype=torch.float64)
    outside = torch.tensor([[1.05, 0.5, 0.5], [-0.02, 0.3, 0.9], [0.5, 0.5, 1.1]], dtype=torch.float64)
    points = torch.cat([inside, outside])
    x, F = carry_by_tets(points, torch.stack(frames), tets)
    assert x.shape == (4, 53, 3) and F.shape == (4, 53, 3, 3)
    torch.testing.assert_close(x[0], points)
    torch.testing.assert_close(F[0], torch.eye(3, dtype=torch.float64).expand(53, 3, 3))
    for t, (A, b) in enumerate(maps, start=1):
        torch.testing.assert_close(x[t], points @ A.T + b)
        torch.testing.assert_close(F[t], A.expand(53, 3, 3))
    with pytest.raises(ValueError, match="points"):
        carry_by_tets(torch.zeros(4, 2), torch.stack(frames), tets)


def test_tet_centre_of_mass_is_the_exact_moment_and_keeps_each_tets_mass():
    """Frame 0 gives the exact first moment of the solid (physics.mass.tet_moments); under an affine map the
    centre maps with it; when one tet alone is squeezed its mass stays its rest mass (the centre moves by
    exactly that tet's share of its centroid's motion)."""
    from vid2sim.metrics import tet_centre_of_mass
    from vid2sim.physics.mass import tet_moments

    g = torch.Generator().manual_seed(1)
    # a cube of 6 tets with uneven vertices, so the tets have different volumes
    cube = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]],
                        dtype=F64) + 0.1 * torch.rand(8, 3, generator=g, dtype=F64)
    tets = torch.tensor([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    m = tet_moments(cube, tets)
    A = _rotation((0.3, 1, 2), 0.7) @ torch.diag(torch.tensor([1.2, 0.8, 1.1], dtype=F64))
    b = torch.tensor([0.5, -0.2, 2.0], dtype=F64)
    frames = torch.stack([cube, cube @ A.T + b])
    c = tet_centre_of_mass(frames, tets)
    assert c.shape == (2, 3) and c.dtype == F64
    torch.testing.assert_close(c[0], m[1:4] / m[0])
    torch.testing.assert_close(c[1], A @ (m[1:4] / m[0]) + b)
    # only vertex 5 moves: tets 4 and 5 (the ones holding vertex 5) change shape and volume, not mass
    moved = cube.clone()
    moved[5] += torch.tensor([0.3, -0.2, 0.1], dtype=F64)
    c2 = tet_centre_of_mass(torch.stack([cube, moved]), tets)
    v = cube[tets]
    mass = torch.linalg.det(v[:, 1:] - v[:, :1]).abs()
    share = mass[4:].sum() / mass.sum() / 4  # each of those tets' centroids moves by a quarter of the vertex
    torch.testing.assert_close(c2[1] - c2[0], share * torch.tensor([0.3, -0.2, 0.1], dtype=F64))
    with pytest.raises(ValueError, match="vertices must be"):
        tet_centre_of_mass(cube, tets)
    with pytest.raises(ValueError, match="indices"):
        tet_centre_of_mass(frames, tets + 8)
