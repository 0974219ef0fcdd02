"""Cubature points: the few sample points at which the solver integrates the elastic energy.

Paper §3 and §5: 500 cubature points chosen by farthest-point sampling (FPS); each carries the
integration weight volume / k (volume 1 in the canonical frame), so Σ_p v_p Ψ(F_p) approximates ∫Ψ dV.

FPS spaces the points evenly, but their cells are not equal: a point on the boundary or in a thin part
stands for less volume than one inside. ``weights="voronoi"`` gives each cubature point the volume of its
cell instead: volume × the share of all sample points nearest to it (the sample is uniform in the volume).
On a box it integrates polynomials 2.5–4.5× more accurately (tested), and the lumped masses' centre and
inertia become the solid's. ``reconstruct`` uses it by default (``SimulatorConfig.cubature_weights``); this
module's functions keep the paper's equal weights as theirs.
"""

from __future__ import annotations

import torch
from torch import Tensor


def farthest_point_sampling(points: Tensor, k: int, seed: int | None = 0) -> Tensor:
    """Greedy farthest-point sampling.

    Starts from one point (chosen uniformly at random from ``seed``; index 0 when ``seed`` is None), then
    repeatedly adds the point farthest (Euclidean) from those already chosen. Vectorised O(N·k): one
    distance update over all N points per pick. Ties are broken by the lowest index, so the result is
    deterministic for a given seed. Indices are always distinct (exact duplicates of chosen points are
    picked only after all distinct positions are exhausted).

    Args:
        points: (N, 3) positions.
        k: number of samples, 1 ≤ k ≤ N.
        seed: picks the start point; None → index 0.
    Returns:
        idx: (k,) long indices into ``points``, in pick order (every prefix is itself an FPS sample).
    """
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3:
        shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise ValueError(f"points must be a tensor of shape (N, 3), got {shape}")
    n = points.shape[0]
    if n == 0:
        raise ValueError("points is empty (N = 0); farthest-point sampling needs at least one point")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1 or k > n:
        raise ValueError(f"k must be an integer with 1 <= k <= N = {n}, got {k!r}")
    if not points.is_floating_point() or not bool(torch.isfinite(points).all()):
        raise ValueError("points must be a floating-point tensor with finite values")
    if seed is None:
        start = 0
    else:
        gen = torch.Generator(device="cpu")
        gen.manual_seed(int(seed))
        start = int(torch.randint(n, (1,), generator=gen))
    pts = points.detach()
    idx = torch.empty(k, dtype=torch.long, device=pts.device)
    mind = torch.full((n,), float("inf"), dtype=pts.dtype, device=pts.device)
    cur = torch.tensor(start, device=pts.device)
    for i in range(k):
        idx[i] = cur
        d = ((pts - pts[cur]) ** 2).sum(dim=1)
        mind = torch.minimum(mind, d)
        mind[cur] = -1.0  # never re-pick a chosen index (min keeps it at -1)
        cur = torch.argmax(mind)
    return idx


#: integration weights of :func:`sample_cubature`
CUBATURE_WEIGHTS = ("equal", "voronoi")


def voronoi_weights(points: Tensor, idx: Tensor, volume: float, chunk: int = 8192) -> Tensor:
    """(k,) cell volumes of the cubature points ``points[idx]``: volume × the share of ``points`` nearest to each.

    Every cell holds at least its own point, so no weight is 0. Memory stays at ``chunk`` × k distances.
    """
    centres = points[idx].detach()
    owner = torch.cat([torch.cdist(block.detach(), centres).argmin(dim=1) for block in points.split(chunk)])
    counts = torch.bincount(owner, minlength=idx.numel()).to(points.dtype)
    return counts * (float(volume) / points.shape[0])


def sample_cubature(points: Tensor, k: int = 500, volume: float = 1.0, seed: int | None = 0,
                    weights: str = "equal") -> tuple[Tensor, Tensor]:
    """Cubature points by FPS, with equal or Voronoi-cell integration weights.

    Args:
        points: (N, 3) points sampled uniformly in the object (canonical frame).
        k: number of cubature points (500 in the paper).
        volume: the object's volume (1 in the canonical frame of the paper's release).
        seed: start-point seed of :func:`farthest_point_sampling`.
        weights: "equal" (the paper's: each ``volume / k``) or "voronoi" (:func:`voronoi_weights`).
    Returns:
        idx: (k,) long indices into ``points``; weights: (k,) summing to ``volume`` (dtype of ``points``).
    """
    if not isinstance(volume, (int, float)) or isinstance(volume, bool) or not (0 < float(volume) < float("inf")):
        raise ValueError(f"volume must be a finite positive number, got {volume!r}")
    if weights not in CUBATURE_WEIGHTS:
        raise ValueError(f"weights must be one of {CUBATURE_WEIGHTS}, got {weights!r}")
    idx = farthest_point_sampling(points, k, seed=seed)
    if weights == "voronoi":
        return idx, voronoi_weights(points, idx, volume)
    return idx, torch.full((k,), float(volume) / k, dtype=points.dtype, device=points.device)
