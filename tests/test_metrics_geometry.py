"""Geometry metrics: Chamfer distance (by hand, self, concentric spheres), surface sampling (uniform
density, points on the faces, determinism), surface Chamfer and material errors."""

import math

import numpy as np
import pytest
import torch
import trimesh

from vid2sim.metrics import (
    ChamferDistance,
    chamfer,
    chamfer_distance,
    material_errors,
    sample_surface,
    surface_chamfer,
)


def sphere_points(n: int, radius: float, seed: int) -> torch.Tensor:
    """(n, 3) uniform points on a sphere (normalised Gaussians)."""
    x = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return radius * x / x.norm(dim=1, keepdim=True)


def test_chamfer_by_hand_and_against_itself():
    a = torch.tensor([[0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    c = chamfer(a, b)
    assert isinstance(c, ChamferDistance)
    assert (c.a_to_b, c.b_to_a, c.symmetric) == pytest.approx((1.0, 1.5, 1.25))  # L2, not squared
    assert c.to_dict() == {"chamfer": c.symmetric, "a_to_b": c.a_to_b, "b_to_a": c.b_to_a}
    pts = torch.rand(3000, 3, generator=torch.Generator().manual_seed(0)) * 100.0 + 1e4
    assert chamfer_distance(pts, pts) == 0.0
    assert chamfer_distance(pts, pts[torch.randperm(3000)]) == 0.0
    sub = chamfer(pts[:100], pts)
    assert sub.a_to_b == 0.0 and sub.b_to_a > 0.0
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        chamfer_distance(pts[:, :2], pts)


def test_chamfer_of_concentric_spheres_is_the_radius_gap():
    """Analytically 0.1 both ways; 20 000 samples a side add ≈ 1e-3 of sampling bias."""
    c = chamfer(sphere_points(20000, 1.0, 0), sphere_points(20000, 1.1, 1))
    assert c.a_to_b == pytest.approx(0.1, abs=3e-3) and c.b_to_a == pytest.approx(0.1, abs=3e-3)
    assert c.symmetric == pytest.approx(0.1, abs=3e-3)


def test_surface_chamfer_to_a_sphere_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.1)
    d = surface_chamfer(sphere_points(20000, 1.0, 2), mesh.vertices, mesh.faces, n_surface=20000, seed=0)
    assert d == pytest.approx(0.1, abs=3e-3)
    assert d == surface_chamfer(sphere_points(20000, 1.0, 2), mesh.vertices, mesh.faces, n_surface=20000, seed=0)


def test_sample_surface_is_area_uniform_on_a_unit_square():
    # Unit square fanned around an off-centre vertex P = (0.3, 0.6): triangle areas 0.3, 0.35, 0.2, 0.15.
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.3, 0.6, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    n = 40000
    p = sample_surface(verts, faces, n, seed=3)
    assert p.shape == (n, 3) and p.dtype == torch.float64
    assert (p[:, 2] == 0).all() and (p[:, :2] >= 0).all() and (p[:, :2] <= 1).all()
    # Uniform density: a 4 × 4 grid of cells, each within 5 binomial standard deviations of n / 16.
    cells = (p[:, 0] * 4).long().clamp_max(3) * 4 + (p[:, 1] * 4).long().clamp_max(3)
    counts = torch.bincount(cells, minlength=16).double()
    sd = math.sqrt(n * (1 / 16) * (15 / 16))
    assert (counts - n / 16).abs().max() < 5 * sd
    # Each triangle receives its share of the area (point-in-triangle by the sign of the cross products).
    q = p[:, :2]
    for (i, j, k), area in zip(faces.tolist(), (0.3, 0.35, 0.2, 0.15)):
        tri = verts[[i, j, k], :2]

        def side(u, v):
            e, r = tri[v] - tri[u], q - tri[u]
            return e[0] * r[:, 1] - e[1] * r[:, 0]

        inside = ((side(0, 1) >= 0) & (side(1, 2) >= 0) & (side(2, 0) >= 0)).double().sum()
        assert abs(float(inside) - area * n) < 5 * math.sqrt(n * area * (1 - area))
    # Deterministic from the seed, and the seed matters; float32 vertices give float32 points.
    assert torch.equal(p, sample_surface(verts, faces, n, seed=3))
    assert not torch.equal(p, sample_surface(verts, faces, n, seed=4))
    assert sample_surface(verts.float(), faces, 10, seed=0).dtype == torch.float32


def test_sample_surface_points_lie_on_the_faces():
    mesh = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(0).random(3)))
    V, F = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    p = sample_surface(V, F, 2000, seed=1)
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = torch.linalg.cross(v1 - v0, v2 - v0)
    n = n / n.norm(dim=1, keepdim=True)
    plane = ((p[:, None, :] - v0[None]) * n[None]).sum(-1).abs()  # (P, F) distance to each face's plane
    # Barycentric coordinates in every face.
    e1, e2, r = v1 - v0, v2 - v0, p[:, None, :] - v0[None]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    r1, r2 = (r * e1).sum(-1), (r * e2).sum(-1)
    det = d11 * d22 - d12 * d12
    u, v = (d22 * r1 - d12 * r2) / det, (d11 * r2 - d12 * r1) / det
    on_face = (plane < 1e-9) & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
    assert on_face.any(dim=1).all()
    with pytest.raises(ValueError, match="outside"):
        sample_surface(V, F + 100, 5)


def test_material_errors():
    err = material_errors({"E": 2e5, "nu": 0.3}, {"log10_E": 5.0, "nu": 0.25, "density": 1000.0})
    assert err["abs_error_log10_E"] == pytest.approx(math.log10(2.0))
    assert err["abs_error_nu"] == pytest.approx(0.05)
    assert set(err) == {"abs_error_log10_E", "abs_error_nu"}
    assert material_errors({"E": 1e5, "log10_E": 5.0, "nu": 0.3}, {"E": 1e5, "nu": 0.3}) == {
        "abs_error_log10_E": 0.0, "abs_error_nu": 0.0}
    with pytest.raises(ValueError, match=r"truth.*'nu'"):
        material_errors({"E": 1e5, "nu": 0.3}, {"E": 1e5})
    with pytest.raises(ValueError, match=r"fitted.*'E'"):
        material_errors({"nu": 0.3}, {"E": 1e5, "nu": 0.3})
    with pytest.raises(ValueError, match=r"fitted.*'E'.*positive"):
        material_errors({"E": -1.0, "nu": 0.3}, {"E": 1e5, "nu": 0.3})
    with pytest.raises(ValueError, match=r"truth.*'nu'.*\(-1, 0.5\)"):
        material_errors({"E": 1e5, "nu": 0.3}, {"E": 1e5, "nu": 0.5})
    with pytest.raises(ValueError, match="disagree"):
        material_errors({"E": 1e5, "log10_E": 4.0, "nu": 0.3}, {"E": 1e5, "nu": 0.3})
    with pytest.raises(ValueError, match=r"'nu' must be a number"):
        material_errors({"E": 1e5, "nu": "soft"}, {"E": 1e5, "nu": 0.3})
