"""Barycentric embedding of points in a tet mesh: round trip, exactness for affine maps, outside points."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from vid2sim.synthetic.embedding import apply_embedding, embed_points, inside_tets


def grid_tets(n: int = 3, size: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """[0, size]³ split into n³ cubes of 6 tetrahedra each (Freudenthal/Kuhn split along the main diagonal)."""
    ax = np.linspace(0.0, size, n + 1)
    verts = np.array(list(itertools.product(ax, ax, ax)), dtype=np.float64)

    def vid(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            path = [np.array([i, j, k])]
            for axis in perm:
                step = path[-1].copy()
                step[axis] += 1
                path.append(step)
            tets.append([vid(*p) for p in path])
    return torch.from_numpy(verts), torch.tensor(tets)


def _tet_volume(v, t):
    e = v[t[:, 1:]] - v[t[:, :1]]
    return torch.linalg.det(e).abs() / 6


def test_grid_tets_fill_the_cube():
    v, t = grid_tets(3, 2.0)
    assert float(_tet_volume(v, t).sum()) == pytest.approx(8.0)


def test_inside_tets_is_the_cube():
    """Points of [-0.5, 1.5]³ are inside the unit cube's tets exactly where they are inside the cube; the tets'
    vertices (on the boundary) count as inside."""
    v, t = grid_tets(3)
    pts = torch.rand(4000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 2 - 0.5
    expected = ((pts >= 0) & (pts <= 1)).all(dim=1).numpy()
    assert 0.05 < expected.mean() < 0.25  # both kinds are tested
    np.testing.assert_array_equal(inside_tets(pts, v, t), expected)
    assert inside_tets(v, v, t).all() and inside_tets(pts.float().numpy(), v, t).shape == (4000,)
    flat = torch.cat([t, torch.tensor([[0, 1, 2, 3], [0, 0, 5, 9]])])  # a flat tet (0-3 lie on one line) and a repeat
    np.testing.assert_array_equal(inside_tets(pts, v, flat), expected)  # degenerate tets hold nothing, raise nothing
    assert not inside_tets(pts, v, torch.tensor([[0, 0, 5, 9]])).any()
    with pytest.raises(ValueError, match=r"inside_tets: points must be \(P, 3\)"):
        inside_tets(pts[:, :2], v, t)


def test_round_trip_inside_points():
    v, t = grid_tets(3)
    pts = torch.rand(400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    idx, bary = embed_points(pts, v, t)
    assert idx.shape == (400,) and bary.shape == (400, 4) and bary.dtype == torch.float64
    assert torch.allclose(bary.sum(1), torch.ones(400, dtype=torch.float64))
    assert float(bary.min()) >= -1e-12  # inside points get the tet that contains them
    assert torch.allclose(apply_embedding(v, idx, bary, t), pts, atol=1e-12)


def test_vertices_and_shared_faces():
    v, t = grid_tets(2)
    idx, bary = embed_points(v, v, t)  # every tet vertex: a one-hot weight
    assert torch.allclose(bary.max(1).values, torch.ones(len(v), dtype=torch.float64))
    assert torch.allclose(apply_embedding(v, idx, bary, t), v, atol=1e-12)


def test_affine_deformation_is_exact_inside_and_outside():
    v, t = grid_tets(3)
    g = torch.Generator().manual_seed(1)
    inside = torch.rand(200, 3, dtype=torch.float64, generator=g)
    # just outside the faces of the cube (the tetrahedralizer's envelope): up to 5e-3 away
    outside = torch.rand(50, 3, dtype=torch.float64, generator=g)
    outside[:25, 0] = -torch.rand(25, dtype=torch.float64, generator=g) * 5e-3
    outside[25:, 2] = 1.0 + torch.rand(25, dtype=torch.float64, generator=g) * 5e-3
    pts = torch.cat([inside, outside])
    idx, bary = embed_points(pts, v, t)
    assert float(bary[200:].min()) < 0  # extrapolated weights
    A = torch.tensor([[1.2, 0.3, -0.1], [0.05, 0.8, 0.2], [-0.3, 0.1, 1.1]], dtype=torch.float64)
    b = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    deformed = v @ A.T + b
    assert torch.allclose(apply_embedding(deformed, idx, bary, t), pts @ A.T + b, atol=1e-12)
    # the chosen tet of an outside point is the nearest one: its clamped point lies on the cube's face
    assert torch.allclose(apply_embedding(v, idx, bary, t), pts, atol=1e-12)


def test_time_batched_and_nonaffine_locality():
    v, t = grid_tets(2)
    pts = torch.tensor([[0.1, 0.2, 0.3], [0.7, 0.6, 0.9]], dtype=torch.float64)
    idx, bary = embed_points(pts, v, t)
    frames = torch.stack([v, v * 2.0, v + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)])
    out = apply_embedding(frames, idx, bary, t)
    assert out.shape == (3, 2, 3)
    assert torch.allclose(out[1], 2 * pts) and torch.allclose(out[2, :, 2], pts[:, 2] + 1)
    # moving one vertex far away only moves points whose tet uses it
    moved = v.clone()
    far_vertex = int(torch.argmax(v.sum(1)))  # corner (1, 1, 1)
    moved[far_vertex] += 10.0
    out = apply_embedding(moved, idx, bary, t)
    assert torch.allclose(out[0], pts[0])
    uses = (t[idx[1]] == far_vertex).any()
    assert bool(uses) == (not torch.allclose(out[1], pts[1]))


def test_float32_and_gradients():
    v, t = grid_tets(2)
    pts = torch.rand(10, 3)
    idx, bary = embed_points(pts, v.float(), t)
    assert bary.dtype == torch.float32
    x = v.clone().requires_grad_(True)
    apply_embedding(x, idx, bary, t).sum().backward()
    # every point distributes total weight 1 to each coordinate
    assert float(x.grad.sum()) == pytest.approx(3 * 10, rel=1e-6)


def test_errors():
    v, t = grid_tets(2)
    with pytest.raises(ValueError, match=r"1 of 1 points lie farther than max_distance"):
        embed_points(torch.tensor([[0.5, 0.5, 1.5]]), v, t)
    with pytest.raises(ValueError, match=r"farther than max_distance=0\.001"):
        embed_points(torch.tensor([[0.5, 0.5, 1.002]]), v, t, max_distance=1e-3)
    with pytest.raises(ValueError, match=r"tets must have shape \(Nt, 4\)"):
        embed_points(torch.zeros(1, 3), v, t[:, :3])
    flat = t.clone()
    flat[0] = torch.tensor([0, 1, 2, 2])
    with pytest.raises(ValueError, match="degenerate"):
        embed_points(torch.zeros(1, 3), v, flat)
    idx, bary = embed_points(torch.full((1, 3), 0.3), v, t)
    with pytest.raises(ValueError, match="tet_vertices_deformed must have shape"):
        apply_embedding(v[:, :2], idx, bary, t)
