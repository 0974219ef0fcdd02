"""Farthest-point sampling and cubature weights."""

import pytest
import torch

from vid2sim.physics.cubature import (
    farthest_point_sampling,
    sample_cubature,
    voronoi_weights,
)


def _cloud(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)


def _covering_radius(points: torch.Tensor, chosen: torch.Tensor) -> float:
    return float(torch.cdist(points, points[chosen]).min(dim=1).values.max())


def test_known_tiny_example_on_a_line():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]])
    # start 0 → farthest 10 → 3 (distance 3) → tie 1 vs 2 (distance 1) broken by the lower index → 2
    assert farthest_point_sampling(pts, 5, seed=None).tolist() == [0, 4, 3, 1, 2]


def test_each_pick_is_the_farthest_from_the_previous_picks():
    pts = _cloud(400)
    idx = farthest_point_sampling(pts, 40, seed=5)
    for i in range(1, 40):
        d_pick = float(torch.cdist(pts[idx[i]][None], pts[idx[:i]]).min())
        assert d_pick == pytest.approx(_covering_radius(pts, idx[:i]), abs=1e-12)


def test_distinct_and_covering_radius_decreases():
    pts = _cloud(600, seed=1)
    idx = farthest_point_sampling(pts, 120, seed=0)
    assert idx.dtype == torch.long and idx.shape == (120,)
    assert len(set(idx.tolist())) == 120
    radii = [_covering_radius(pts, idx[:k]) for k in (5, 10, 20, 40, 80, 120)]
    assert all(a > b for a, b in zip(radii[:-1], radii[1:]))
    # greedy FPS is a 2-approximation of the optimal k-centre radius, far better than a random subset
    g = torch.Generator().manual_seed(3)
    rand = torch.randperm(600, generator=g)[:40]
    assert _covering_radius(pts, idx[:40]) < 0.75 * _covering_radius(pts, rand)


def test_duplicates_still_give_distinct_indices():
    base = _cloud(10, seed=2)
    pts = torch.cat([base, base, base])  # every position three times
    idx = farthest_point_sampling(pts, 30, seed=1)
    assert sorted(idx.tolist()) == list(range(30))
    # the first 10 picks hit all 10 distinct positions before any duplicate
    assert sorted((idx[:10] % 10).tolist()) == list(range(10))


def test_determinism_and_seed_controls_the_start():
    pts = _cloud(300, seed=4)
    a = farthest_point_sampling(pts, 25, seed=11)
    b = farthest_point_sampling(pts, 25, seed=11)
    assert torch.equal(a, b)
    starts = {int(farthest_point_sampling(pts, 1, seed=s)[0]) for s in range(6)}
    assert len(starts) > 1
    assert int(farthest_point_sampling(pts, 3, seed=None)[0]) == 0
    # the second pick does not depend on randomness beyond the start: farthest from the start
    far = int(torch.cdist(pts[a[0]][None], pts).argmax())
    assert int(a[1]) == far


def test_sample_cubature_weights():
    pts = _cloud(200, seed=6).float()
    idx, w = sample_cubature(pts, 50, volume=0.8, seed=0)
    assert idx.shape == (50,) and w.shape == (50,) and w.dtype == torch.float32
    assert torch.allclose(w, torch.full((50,), 0.8 / 50))
    assert float(w.sum()) == pytest.approx(0.8, rel=1e-6)
    assert torch.equal(idx, farthest_point_sampling(pts, 50, seed=0))
    # integration of a polynomial over the box [0,2]×[0,1]×[0,0.5] (volume 1): ∫ x dV = 1·1 (mean of x = 1)
    big = _cloud(4000, seed=7)
    idx, w = sample_cubature(big, 500, volume=1.0)
    assert float((w * big[idx, 0]).sum()) == pytest.approx(1.0, abs=0.03)


def test_voronoi_weights_are_cell_volumes_and_integrate_better_than_equal_weights():
    pts = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [1.1, 0, 0]], dtype=torch.float64)
    # cells of points 0 and 3: {0, 0.1, 0.2} and {1.0, 1.1}
    assert torch.equal(voronoi_weights(pts, torch.tensor([0, 3]), 5.0), torch.tensor([3.0, 2.0], dtype=torch.float64))
    big = _cloud(20000, seed=8)
    idx, w = sample_cubature(big, 200, volume=1.0, seed=0, weights="voronoi")
    assert bool((w > 0).all()) and float(w.sum()) == pytest.approx(1.0, rel=1e-12)
    assert torch.equal(idx, farthest_point_sampling(big, 200, seed=0))
    assert torch.equal(voronoi_weights(big, idx, 1.0, chunk=777), w)
    # ∫ x² dV over [0,2]×[0,1]×[0,0.5] = 4/3 and ∫ x² y² z² dV = 8/3 · 1/3 · 1/24: FPS puts proportionally more
    # points on the boundary, which equal weights over-count
    for f, exact in ((lambda p: p[:, 0] ** 2, 4 / 3), (lambda p: (p[:, 0] * p[:, 1] * p[:, 2]) ** 2, 8 / 3 / 3 / 24)):
        _, we = sample_cubature(big, 200, volume=1.0, seed=0)
        err_equal = abs(float((we * f(big[idx])).sum()) - exact)
        err_voronoi = abs(float((w * f(big[idx])).sum()) - exact)
        assert err_voronoi < 0.5 * err_equal, (err_voronoi, err_equal)


def test_bad_inputs():
    pts = _cloud(10)
    with pytest.raises(ValueError, match="k must be"):
        farthest_point_sampling(pts, 11)
    with pytest.raises(ValueError, match="k must be"):
        farthest_point_sampling(pts, 0)
    with pytest.raises(ValueError, match="empty"):
        farthest_point_sampling(torch.zeros(0, 3), 1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        farthest_point_sampling(torch.zeros(10, 2), 1)
    bad = pts.clone()
    bad[3, 0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        farthest_point_sampling(bad, 2)
    with pytest.raises(ValueError, match="volume"):
        sample_cubature(pts, 5, volume=0.0)
    with pytest.raises(ValueError, match="weights must be one of"):
        sample_cubature(pts, 5, weights="gauss")
