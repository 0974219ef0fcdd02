"""Distance between two trajectories of the same points, as a fraction of the object's size.

This is the one measure behind every convergence and accuracy figure of the simulators: for each frame
the mean over points of the Euclidean distance, divided by the object's size (its rest bounding-box
diagonal); then the mean and the maximum over the frames compared (frame 0, the shared initial state, is
left out by default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass
class TrajectoryDistance:
    """Distances in percent of the size.

    Attributes:
        mean: mean over the compared frames.
        max: largest per-frame value.
        per_frame: (T,) per-frame values for every frame (frame 0 included).
        frames: the frame indices averaged in ``mean`` / ``max``.
    """

    mean: float
    max: float
    per_frame: list[float]
    frames: list[int]

    def to_dict(self) -> dict:
        return {"mean_percent": self.mean, "max_percent": self.max, "frames": [self.frames[0], self.frames[-1]],
                "per_frame_percent": self.per_frame}


def trajectory_distance(a: Tensor | np.ndarray, b: Tensor | np.ndarray, size: float,
                        frames: slice | list[int] | None = None) -> TrajectoryDistance:
    """Distance between trajectories a and b: (T, N, 3) (same points, same frames) in % of ``size``.

    Args:
        a, b: (T, N, 3) positions.
        size: the object's size in the same units (its rest bounding-box diagonal), > 0.
        frames: the frames averaged (a slice or list of indices); default 1 … T−1.
    """
    A = torch.as_tensor(np.asarray(a) if not isinstance(a, Tensor) else a).detach().to(torch.float64)
    B = torch.as_tensor(np.asarray(b) if not isinstance(b, Tensor) else b).detach().to(torch.float64)
    if A.shape != B.shape or A.ndim != 3 or A.shape[-1] != 3:
        raise ValueError(f"trajectories must both have shape (T, N, 3), got {tuple(A.shape)} and {tuple(B.shape)}")
    if not size > 0:
        raise ValueError(f"size must be positive, got {size}")
    per = (A - B.to(A.device)).norm(dim=-1).mean(dim=-1).cpu().numpy() * (100.0 / size)
    T = len(per)
    idx = list(range(T))[frames] if isinstance(frames, slice) else (list(frames) if frames is not None
                                                                    else list(range(1, T)))
    if not idx:
        raise ValueError(f"no frames to compare among {T}")
    sel = per[idx]
    return TrajectoryDistance(float(sel.mean()), float(sel.max()), [float(v) for v in per], idx)


def best_rotation(source: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    """The proper rotation R (…, 3, 3) minimising Σ_p w_p ‖R (a_p − ā) − (b_p − b̄)‖² (Kabsch, no reflection) for
    points ``source`` a and ``target`` b, both (…, N, 3), ā and b̄ their weighted means; ``weights`` (N,) ≥ 0 with
    a positive sum (default equal). Differentiable (through the SVD) where the fit is unique."""
    A, B = source.to(torch.float64), target.to(torch.float64)
    w = torch.ones(A.shape[-2], dtype=A.dtype, device=A.device) if weights is None else weights.to(A)
    w = (w / w.sum())[:, None]
    a, b = A - (w * A).sum(-2, keepdim=True), B - (w * B).sum(-2, keepdim=True)
    U, _, Vh = torch.linalg.svd(b.transpose(-1, -2) @ (w * a))  # Σ w b aᵀ = U S Vh
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.ones(*d.shape, 3, dtype=A.dtype, device=A.device)
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vh  # U diag(1, 1, d) Vh


def rigidly_aligned(source: Tensor, target: Tensor) -> Tensor:
    """``source`` moved per frame by the rigid motion (rotation + translation, no reflection) that best
    maps it onto ``target`` in the least-squares sense (:func:`best_rotation`), both (T, N, 3) or (N, 3)."""
    A, B = source.to(torch.float64), target.to(torch.float64)
    R = best_rotation(A, B)
    return (A - A.mean(-2, keepdim=True)) @ R.transpose(-1, -2) + B.mean(-2, keepdim=True)


def nonrigid_distance(a: Tensor | np.ndarray, b: Tensor | np.ndarray, size: float,
                      frames: slice | list[int] | None = None) -> TrajectoryDistance:
    """:func:`trajectory_distance` after aligning each frame of ``a`` rigidly onto ``b``: the part of the
    difference that no rigid motion explains — a shape (deformation) error, as opposed to a pose error."""
    A = torch.as_tensor(np.asarray(a) if not isinstance(a, Tensor) else a).detach().to(torch.float64)
    B = torch.as_tensor(np.asarray(b) if not isinstance(b, Tensor) else b).detach().to(torch.float64)
    if A.shape != B.shape or A.ndim != 3 or A.shape[-1] != 3:
        raise ValueError(f"trajectories must both have shape (T, N, 3), got {tuple(A.shape)} and {tuple(B.shape)}")
    return trajectory_distance(rigidly_aligned(A, B), B, size, frames)


def deformation(trajectory: Tensor | np.ndarray, rest: Tensor | np.ndarray, size: float) -> list[float]:
    """Per frame, how far the points of ``trajectory`` (T, N, 3) are from a rigid motion of their ``rest``
    positions (N, 3): the mean distance to the best rigidly moved rest shape, in percent of ``size``, (T,)."""
    X = torch.as_tensor(np.asarray(trajectory) if not isinstance(trajectory, Tensor) else trajectory).detach()
    R = torch.as_tensor(np.asarray(rest) if not isinstance(rest, Tensor) else rest).detach()
    if X.ndim != 3 or X.shape[1:] != R.shape or R.shape[-1] != 3:
        raise ValueError(f"trajectory must be (T, N, 3) and rest (N, 3) with the same N, got {tuple(X.shape)}, "
                         f"{tuple(R.shape)}")
    return trajectory_distance(rigidly_aligned(R.expand_as(X), X), X, size, frames=list(range(len(X)))).per_frame


def carry_by_tets(points: Tensor, vertices: Tensor, tets: Tensor, candidates: int = 24) -> tuple[Tensor, Tensor]:
    """Carry points with a tet mesh's motion: positions and deformation gradients at every frame.

    Each point is bound to one tet of frame 0: the tet that contains it, or, for a point outside the mesh, the
    one among the ``candidates`` tets with the nearest centroids whose smallest barycentric coordinate is the
    largest (the tet it is least outside of). It then follows that tet's affine map: x_t = Σ λ_k v_k(t) and
    F_t = D_t D_0⁻¹ with D the tet's edge matrix.

    Args:
        points: (N, 3) positions at frame 0.
        vertices: (T, Nv, 3) the mesh's vertex positions per frame (frame 0 is the binding frame).
        tets: (Nt, 4) vertex indices, non-degenerate at frame 0.
        candidates: nearest tets tried per point.

    Returns:
        x: (T, N, 3) positions; F: (T, N, 3, 3) deformation gradients (identity at frame 0), float64 on
        ``points``' device (the binding, a k-d tree search, runs on the CPU).
    """
    from scipy.spatial import cKDTree

    device = points.device if isinstance(points, Tensor) else torch.device("cpu")
    P = torch.as_tensor(points).detach().to(device="cpu", dtype=torch.float64)
    Vt = torch.as_tensor(vertices).detach().to(device="cpu", dtype=torch.float64)
    T = torch.as_tensor(tets).long().cpu()
    if P.ndim != 2 or P.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(P.shape)}")
    if Vt.ndim != 3 or Vt.shape[-1] != 3 or T.ndim != 2 or T.shape[-1] != 4 or len(T) == 0:
        raise ValueError(f"vertices must be (T, Nv, 3) and tets (Nt, 4) with Nt >= 1, got {tuple(Vt.shape)} and "
                         f"{tuple(T.shape)}")
    V0 = Vt[0]
    k = min(candidates, len(T))
    _, near = cKDTree(V0[T].mean(1).numpy()).query(P.numpy(), k=k)
    near = torch.as_tensor(near.reshape(len(P), k))
    best_score = torch.full((len(P),), -math.inf, dtype=torch.float64)
    best_tet = torch.zeros(len(P), dtype=torch.long)
    best_bary = torch.zeros(len(P), 4, dtype=torch.float64)
    for j in range(k):
        t = T[near[:, j]]
        a = V0[t[:, 0]]
        D = torch.stack([V0[t[:, 1]] - a, V0[t[:, 2]] - a, V0[t[:, 3]] - a], -1)
        lam = torch.linalg.solve(D, (P - a)[..., None])[..., 0]
        bary = torch.cat([1 - lam.sum(1, keepdim=True), lam], 1)
        score = bary.min(1).values
        better = score > best_score
        best_score = torch.where(better, score, best_score)
        best_tet = torch.where(better, near[:, j], best_tet)
        best_bary = torch.where(better[:, None], bary, best_bary)
    t = T[best_tet]
    x = (best_bary[None, :, :, None] * Vt[:, t]).sum(2)
    edges = torch.stack([Vt[:, t[:, q]] - Vt[:, t[:, 0]] for q in (1, 2, 3)], -1)  # (T, N, 3, 3)
    F = edges @ torch.linalg.inv(edges[0])[None]
    return x.to(device), F.to(device)


def tet_centre_of_mass(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray) -> Tensor:
    """Centre of mass per frame of a tet mesh of uniform density moving through ``vertices``.

    Each tet keeps its mass (its volume at frame 0, the rest shape placed in the world) and carries it at its
    centroid, which is exact for the affine motion of a linear tet; for quadratic tets (corner vertices in
    ``tets``, edge nodes listed after them in ``vertices``) it leaves out the bending of the edges.

    Args:
        vertices: (T, N, 3) node positions per frame (N ≥ the largest index in ``tets`` + 1).
        tets: (Nt, 4) corner indices.
    Returns:
        (T, 3) float64 centres of mass.
    Raises:
        ValueError: shapes that do not fit, or a mesh of zero volume at frame 0.
    """
    x = torch.as_tensor(vertices).double()
    t = torch.as_tensor(tets).long()
    if x.ndim != 3 or x.shape[-1] != 3 or t.ndim != 2 or t.shape[1] != 4 or t.numel() == 0:
        raise ValueError(f"tet_centre_of_mass: vertices must be (T, N, 3) and tets (Nt, 4), got {tuple(x.shape)} "
                         f"and {tuple(t.shape)}")
    if int(t.min()) < 0 or int(t.max()) >= x.shape[1]:
        raise ValueError(f"tet_centre_of_mass: tet indices must lie in [0, {x.shape[1] - 1}]")
    v0 = x[0, t]  # (Nt, 4, 3)
    mass = torch.linalg.det(v0[:, 1:] - v0[:, :1]).abs()  # 6 × volume: the common factor cancels
    if not float(mass.sum()) > 0:
        raise ValueError("tet_centre_of_mass: the tets have zero volume at frame 0")
    centroids = x[:, t].mean(dim=2)  # (T, Nt, 3)
    return (mass[None, :, None] * centroids).sum(1) / mass.sum()
