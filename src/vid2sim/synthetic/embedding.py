"""Barycentric embedding of points (render-mesh vertices, say) in a tetrahedral mesh.

The FEM ground truth deforms a tet mesh; the textured render surface follows it by carrying each
of its vertices along with the tetrahedron it lies in: ``x = Σ_k w_k · X_{tet[k]}`` with fixed
barycentric weights ``w`` computed in the rest configuration. This keeps the FEM and the
renderer independent of each other's meshes.

Points outside the tet mesh (a tetrahedralizer may move the boundary by a hair) are assigned to
the nearest tetrahedron (exact point–tetrahedron distance) and keep that tetrahedron's
*extrapolated* barycentric weights (some negative, all summing to one). That makes the map exact
for every affine deformation and returns every point exactly in the rest configuration; points
farther than ``max_distance`` from the tet mesh are an error, as they mean the two meshes do not
describe the same object.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from vid2sim.physics.tet_modes import TET_EDGES


def _barycentric(points: np.ndarray, tet_points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (M, 4) of points (M, 3) w.r.t. tetrahedra (M, 4, 3)."""
    a = tet_points[:, 0]
    m = np.stack([tet_points[:, 1] - a, tet_points[:, 2] - a, tet_points[:, 3] - a], axis=2)  # (M, 3, 3)
    w123 = np.linalg.solve(m, (points - a)[..., None])[..., 0]
    return np.concatenate([1.0 - w123.sum(axis=1, keepdims=True), w123], axis=1)


def _point_tet_distance(points: np.ndarray, tet_points: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Distance (M,) of points (M, 3) to tetrahedra (M, 4, 3); 0 inside."""
    from trimesh.triangles import closest_point

    m = len(points)
    inside = bary.min(axis=1) >= 0
    dist = np.zeros(m)
    out = np.flatnonzero(~inside)
    if len(out) == 0:
        return dist
    faces = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    tris = tet_points[out][:, faces]  # (K, 4, 3, 3)
    pts = np.repeat(points[out], 4, axis=0)
    cp = closest_point(tris.reshape(-1, 3, 3), pts)
    dist[out] = np.linalg.norm(cp - pts, axis=1).reshape(-1, 4).min(axis=1)
    return dist


def _candidate_pairs(points: np.ndarray, corners: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Every (point, tetrahedron) pair that may lie within ``distance`` of each other, as index arrays (P', ),
    (P', ) sorted by point: a tetrahedron within d of a point has its centroid within (the largest
    centroid-to-corner distance + d) of it. ``points`` (M, 3), ``corners`` (Nt, 4, 3)."""
    centroids = corners.mean(axis=1)
    radius = float(np.linalg.norm(corners - centroids[:, None], axis=2).max())
    reach = radius * (1.0 + 1e-9) + distance  # a tet's own corners are found despite rounding
    cand = cKDTree(centroids).query_ball_point(points, r=reach, workers=1)
    lens = np.fromiter((len(c) for c in cand), dtype=np.int64, count=len(points))
    pidx = np.repeat(np.arange(len(points)), lens)
    tidx = np.concatenate([np.asarray(c, dtype=np.int64) for c in cand]) if len(pidx) else np.zeros(0, np.int64)
    return pidx, tidx


def inside_tets(points: Tensor | np.ndarray, tet_vertices: Tensor | np.ndarray,
                tets: Tensor | np.ndarray) -> np.ndarray:
    """Which points lie inside a tet mesh (in a tetrahedron, its boundary included up to 1e-9 barycentric).
    Degenerate (zero-volume) tetrahedra hold no point.

    Args:
        points: (P, 3). tet_vertices: (Nv, 3). tets: (Nt, 4) corner indices into ``tet_vertices``.
    Returns:
        (P,) bool.
    """
    pts = np.asarray(torch.as_tensor(points).detach().cpu(), dtype=np.float64)
    verts = np.asarray(torch.as_tensor(tet_vertices).detach().cpu(), dtype=np.float64)
    tt = np.asarray(torch.as_tensor(tets).detach().cpu(), dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or verts.ndim != 2 or verts.shape[1] != 3 or tt.ndim != 2 \
            or tt.shape[1] != 4 or len(tt) == 0:
        raise ValueError(f"inside_tets: points must be (P, 3), tet_vertices (Nv, 3) and tets (Nt, 4), got "
                         f"{pts.shape}, {verts.shape} and {tt.shape}")
    corners = verts[tt]
    diag = float(np.linalg.norm(verts.max(0) - verts.min(0)))
    corners = corners[np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) > 1e-14 * diag ** 3]
    inside = np.zeros(len(pts), dtype=bool)
    if len(corners) == 0:
        return inside
    pidx, tidx = _candidate_pairs(pts, corners, 0.0)
    chunk = 1 << 20
    for s in range(0, len(pidx), chunk):
        pi, ti = pidx[s: s + chunk], tidx[s: s + chunk]
        hit = _barycentric(pts[pi], corners[ti]).min(axis=1) >= -1e-9
        inside[pi[hit]] = True
    return inside


def embed_points(
    points: Tensor,
    tet_vertices: Tensor,
    tets: Tensor,
    max_distance: float | None = None,
) -> tuple[Tensor, Tensor]:
    """Find the tetrahedron and barycentric weights of every point.

    Args:
        points: (P, 3) positions in the rest configuration of the tet mesh.
        tet_vertices: (Nv, 3) rest positions of the tet-mesh vertices.
        tets: (Nt, 4) vertex indices of the tetrahedra (either orientation).
        max_distance: largest allowed distance of a point from the tet mesh; default 1 % of the
            tet mesh's bounding-box diagonal.

    Returns:
        tet_index: (P,) long, the containing tetrahedron (or the nearest one for points outside;
            for a point on a shared face or edge, the tetrahedron in which it is most interior).
        bary: (P, 4) weights in the dtype of ``points``, summing to one; all ≥ 0 (up to rounding)
            inside the mesh, extrapolated outside it.

    Raises:
        ValueError: bad shapes, degenerate tetrahedra, or points farther than ``max_distance``.
    """
    pts_t = torch.as_tensor(points)
    dtype = pts_t.dtype if pts_t.is_floating_point() else torch.float32
    pts = pts_t.detach().cpu().to(torch.float64).numpy()
    verts = torch.as_tensor(tet_vertices).detach().cpu().to(torch.float64).numpy()
    tt = torch.as_tensor(tets).detach().cpu().numpy().astype(np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (P, 3), got {pts.shape}")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"tet_vertices must have shape (Nv, 3), got {verts.shape}")
    if tt.ndim != 2 or tt.shape[1] != 4 or len(tt) == 0:
        raise ValueError(f"tets must have shape (Nt, 4) with Nt >= 1, got {tt.shape}")
    if tt.min() < 0 or tt.max() >= len(verts):
        raise ValueError(f"tets index vertices in [{tt.min()}, {tt.max()}] but there are {len(verts)} tet vertices")
    corners = verts[tt]  # (Nt, 4, 3)
    edges = corners[:, 1:] - corners[:, :1]
    vol6 = np.abs(np.linalg.det(edges))
    diag = float(np.linalg.norm(verts.max(0) - verts.min(0)))
    if (vol6 <= 1e-14 * diag**3).any():
        raise ValueError(f"tets contains {int((vol6 <= 1e-14 * diag**3).sum())} degenerate (zero-volume) tetrahedra")
    if max_distance is None:
        max_distance = 0.01 * diag
    if len(pts) == 0:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, 4, dtype=dtype)

    pidx, tidx = _candidate_pairs(pts, corners, max_distance)
    far = np.setdiff1d(np.arange(len(pts)), pidx)
    if len(far):
        raise ValueError(
            f"{len(far)} of {len(pts)} points lie farther than max_distance={max_distance:.4g} from the tet mesh "
            f"(first: point {int(far[0])} at {pts[far[0]].tolist()})"
        )
    tet_index = np.empty(len(pts), dtype=np.int64)
    bary = np.empty((len(pts), 4))
    best_score = np.full(len(pts), -np.inf)
    chunk = 1 << 20
    for s in range(0, len(pidx), chunk):
        pi, ti = pidx[s : s + chunk], tidx[s : s + chunk]
        b = _barycentric(pts[pi], corners[ti])
        score = b.min(axis=1)  # ≥ 0 inside; the larger, the more interior
        order = np.lexsort((-score, pi))  # per point, best score first
        first = order[np.r_[True, pi[order][1:] != pi[order][:-1]]]
        better = score[first] > best_score[pi[first]]
        upd = first[better]
        best_score[pi[upd]] = score[upd]
        tet_index[pi[upd]] = ti[upd]
        bary[pi[upd]] = b[upd]

    tol = 1e-9
    outside = np.flatnonzero(best_score < -tol)
    if len(outside):
        # exact nearest tetrahedron among the candidates of each outside point
        sel = np.isin(pidx, outside)
        pi, ti = pidx[sel], tidx[sel]
        b = _barycentric(pts[pi], corners[ti])
        d = _point_tet_distance(pts[pi], corners[ti], b)
        order = np.lexsort((d, pi))
        first = order[np.r_[True, pi[order][1:] != pi[order][:-1]]]
        worst = d[first].max()
        if worst > max_distance:
            n_bad = int((d[first] > max_distance).sum())
            raise ValueError(
                f"{n_bad} of {len(pts)} points lie farther than max_distance={max_distance:.4g} from the tet mesh "
                f"(largest distance {worst:.4g})"
            )
        tet_index[pi[first]] = ti[first]
        bary[pi[first]] = b[first]
    return torch.from_numpy(tet_index), torch.from_numpy(bary).to(dtype)


def apply_embedding(tet_vertices_deformed: Tensor, tet_index: Tensor, bary: Tensor, tets: Tensor) -> Tensor:
    """Carry embedded points along with deformed tet vertices (or the nodes of quadratic tets).

    Args:
        tet_vertices_deformed: (N, 3) or (T, N, 3) deformed node positions.
        tet_index: (P,) long, from :func:`embed_points`.
        bary: (P, 4) weights, from :func:`embed_points`.
        tets: (Nt, 4) the tet mesh's vertex indices (the same array given to ``embed_points``), or (Nt, 10)
            quadratic tets whose first four columns are those (:attr:`FEMResult.embedding_elements`).

    Returns:
        (P, 3) or (T, P, 3) positions ``Σ_k N_k(bary) · X[tets[tet_index, k]]`` in the dtype and on the
        device of ``tet_vertices_deformed`` (differentiable with respect to it). N_k are the barycentric
        weights themselves for linear tets; for quadratic tets L_a(2L_a − 1) at the vertices and 4 L_a L_b at
        the edge midpoints.
    """
    x = torch.as_tensor(tet_vertices_deformed)
    if x.ndim not in (2, 3) or x.shape[-1] != 3:
        raise ValueError(f"tet_vertices_deformed must have shape (Nv, 3) or (T, Nv, 3), got {tuple(x.shape)}")
    tets = torch.as_tensor(tets, device=x.device).long()
    tet_index = torch.as_tensor(tet_index, device=x.device).long()
    bary = torch.as_tensor(bary, device=x.device).to(x.dtype)
    if tets.ndim != 2 or tets.shape[1] not in (4, 10):
        raise ValueError(f"tets must have shape (Nt, 4) or (Nt, 10), got {tuple(tets.shape)}")
    if tet_index.ndim != 1 or bary.shape != (tet_index.shape[0], 4):
        raise ValueError(
            f"tet_index (P,) and bary (P, 4) must agree, got {tuple(tet_index.shape)} and {tuple(bary.shape)}"
        )
    if len(tet_index) and (int(tet_index.min()) < 0 or int(tet_index.max()) >= tets.shape[0]):
        raise ValueError(
            f"tet_index must lie in [0, {tets.shape[0]}), got [{int(tet_index.min())}, {int(tet_index.max())}]"
        )
    if len(tets) and int(tets.max()) >= x.shape[-2]:
        raise ValueError(f"tets index vertex {int(tets.max())} but tet_vertices_deformed has {x.shape[-2]} vertices")
    idx = tets[tet_index]  # (P, 4) or (P, 10)
    if tets.shape[1] == 10:

        bary = torch.cat(
            [bary * (2 * bary - 1)] + [4 * bary[:, a : a + 1] * bary[:, b : b + 1] for a, b in TET_EDGES], dim=1
        )
    return (x[..., idx, :] * bary[..., None]).sum(dim=-2)
