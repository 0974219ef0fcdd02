"""The stiffness calibration of a reconstruction: a tet mesh of the reconstructed solid, and the factor that
brings the skinning subspace's lowest vibration mode to the continuum's.

The skinning subspace is a Rayleigh–Ritz approximation, stiffer than the continuum, so a material fitted with
it comes out soft (docs/architecture.md, "Calibrating the subspace's stiffness"). The reference is quadratic
tets on a mesh of the same solid. A reconstruction has no such mesh; it has interior samples. So:

1. :func:`solid_surface` — the samples are binned on a grid (at most ``cells`` a side), blurred (Gaussian,
   σ = 1.5 cells) and the surface is the level set at half the median density at the points (marching cubes;
   a blurred step is at half its height at the step). The grid is padded, so the surface is closed.
2. fTetWild tetrahedralizes it (:func:`vid2sim.meshing.tetra.tetrahedralize`).
3. :func:`vid2sim.physics.modes.stiffness_calibration_curve` compares the two lowest frequencies at a grid
   of ν (or :func:`~vid2sim.physics.modes.stiffness_calibration` at one ν): the subspace's volumetric locking
   grows with ν, so the factor is a curve s(ν) (:mod:`vid2sim.physics.stiffness_curve`).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import Tensor


def solid_surface(points: np.ndarray, cells: int = 64, rng: np.random.Generator | None = None,
                  max_points: int = 50000) -> tuple[np.ndarray, np.ndarray] | None:
    """A closed, outward-oriented triangle surface of the solid that ``points`` (N, 3) fill uniformly.

    ``rng`` draws the ``max_points`` used when there are more (default: seed 0).

    Returns:
        vertices (Nv, 3) float64 and faces (Nf, 3) int64, or None when no surface is found (too few points).
    """
    from scipy.ndimage import gaussian_filter, map_coordinates
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    rng = rng if rng is not None else np.random.default_rng(0)
    Q = points if len(points) <= max_points else points[rng.choice(len(points), max_points, replace=False)]
    if len(Q) < 8:
        return None
    spacing = float(cKDTree(Q).query(Q, k=2)[0][:, 1].mean())
    lo, hi = Q.min(0), Q.max(0)
    h = max(spacing, float((hi - lo).max()) / cells, 1e-9)
    sigma = 1.5
    pad = math.ceil(4 * sigma) + 2
    lo = lo - pad * h
    shape = np.ceil((hi + pad * h - lo) / h).astype(np.int64)
    counts = np.histogramdd(Q, bins=tuple(shape), range=[(lo[i], lo[i] + shape[i] * h) for i in range(3)])[0]
    density = gaussian_filter(counts, sigma)
    level = 0.5 * float(np.median(map_coordinates(density, ((Q - lo) / h - 0.5).T, order=1)))
    if not 0 < level < float(density.max()):
        return None
    try:
        verts, faces = marching_cubes(density, level=level)[:2]
    except (ValueError, RuntimeError):
        return None
    if len(verts) < 4:
        return None
    verts, faces = lo + (verts + 0.5) * h, faces.astype(np.int64)
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    if np.einsum("ij,ij->", a, np.cross(b, c)) < 0:  # 6 × the signed volume: orient the normals outward
        faces = faces[:, ::-1].copy()
    return verts, faces


def calibrate_stiffness(field, cubature: Tensor, weights: Tensor, points: Tensor, poisson_ratio: float,
                        edge_length: float = 0.08, cells: int = 64, seed: int = 0,
                        nus: tuple[float, ...] | None = None, factors: int = 1) -> dict:
    """The stiffness factor s of a reconstruction (``Simulator(stiffness_scale=s)``).

    Args:
        field: the trained skinning field (its input frame set: it takes world points).
        cubature: (K, 3) the simulator's cubature points; weights: (K,) their volumes.
        points: (N, 3) the interior samples the subspace was trained on (world frame, m).
        poisson_ratio: ν at which both frequencies are compared (the prior's).
        nus: a grid of ν: also measure the curve s(ν) there (None: only at ``poisson_ratio``).
        factors: with ``nus``, 1 (one factor on E) or 2 (a factor on μ and one on λ, matched to the six lowest
            modes; :func:`vid2sim.physics.modes.stiffness_calibration_curve`).
        edge_length: fTetWild's target edge length relative to the bounding-box diagonal (the small preset's
            FEM uses 0.08).
        cells: the surface grid's cells along the longest side.
    Returns:
        {"stiffness_scale": s at ``poisson_ratio``, "stiffness_curve": the curve's ``to_dict()`` or None,
        "tets": mesh size, "mesh_volume_m3", "points_volume_ratio" (the mesh's volume over the weights' sum),
        "seconds"}.
    Raises:
        ValueError: no closed surface could be made from the points.
    """
    from vid2sim.meshing.tetra import tet_volumes, tetrahedralize
    from vid2sim.physics.modes import stiffness_calibration, stiffness_calibration_curve

    t0 = time.perf_counter()
    P = points.detach().double().cpu().numpy()
    surface = solid_surface(P, cells=cells, rng=np.random.default_rng(seed))
    if surface is None:
        raise ValueError(f"no closed surface could be made from the {len(P)} interior points for the stiffness "
                         "calibration; set ReconstructConfig.calibrate_stiffness=False")
    mesh = tetrahedralize(surface[0], surface[1], edge_length_fac=edge_length, epsilon=5e-3, name="reconstructed solid")
    X, T = mesh.vertices.double(), mesh.tets
    curve = stiffness_calibration_curve(field, cubature, weights, X, T, nus, factors=factors) if nus is not None else None
    s = curve.at(poisson_ratio) if curve is not None else stiffness_calibration(field, cubature, weights, X, T,
                                                                                 poisson_ratio)
    volume = float(tet_volumes(X, T).abs().sum())
    return {"stiffness_scale": s, "stiffness_curve": curve.to_dict() if curve is not None else None,
            "tets": int(len(T)), "mesh_volume_m3": volume,
            "points_volume_ratio": volume / float(weights.sum()), "seconds": time.perf_counter() - t0}
