"""Geometry shared by the stages: a closed surface of a solid from its interior samples, and rigid poses fitted
to silhouettes (used by the initial velocity, :mod:`~vid2sim.reconstruct.stages.velocity`, and by the carving with
the later frames, :mod:`~vid2sim.reconstruct.stages.points`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt, gaussian_filter, map_coordinates
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes


def hat(w: np.ndarray) -> np.ndarray:
    """Skew matrices (..., 3, 3) with [w]× y = w × y, of vectors (..., 3)."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, 2.0 * np.sin(0.5 * safe) ** 2 / safe**2)
    k = hat(w)
    return np.eye(3) + a * k + b * (k @ k)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (angles in [0, π]) of rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-1])


def solid_surface(points: np.ndarray, cells: int = 64, rng: np.random.Generator | None = None,
                  max_points: int = 50000) -> tuple[np.ndarray, np.ndarray] | None:
    """A closed, outward-oriented triangle surface of the solid that ``points`` (N, 3) fill uniformly.

    ``rng`` draws the ``max_points`` used when there are more (default: seed 0).

    Returns:
        vertices (Nv, 3) float64 and faces (Nf, 3) int64, or None when no surface is found (too few points).
    """

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


def prepare_silhouette(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mask (H, W) in [0, 1] prepared for fitting.

    Returns ``(field (H, W), boundary (M, 2))``. ``field`` is the signed distance (px) of each pixel centre
    from the mask's 0.5 iso-line, positive outside: on anti-aliased pixels 0.5 − m (a straight edge through
    a pixel that covers the fraction m lies 0.5 − m px from its centre), elsewhere the Euclidean distance
    transform to the nearest pixel on the other side minus 0.5 px. ``boundary`` holds the iso-line's
    crossings of the segments between 4-neighbouring pixel centres (x, y in pixels, centres at +0.5),
    linearly interpolated.
    """

    m = mask.astype(np.float64)
    inside = m >= 0.5
    field = np.where(inside, 0.5 - distance_transform_edt(inside), distance_transform_edt(~inside) - 0.5)
    frac = (m > 1e-3) & (m < 1.0 - 1e-3)
    field = np.where(frac, 0.5 - m, field)
    samples = []
    for axis in (0, 1):
        a = m[:-1, :] if axis == 0 else m[:, :-1]
        b = m[1:, :] if axis == 0 else m[:, 1:]
        r, c = np.nonzero((a - 0.5) * (b - 0.5) < 0)
        f = (a[r, c] - 0.5) / (a[r, c] - b[r, c])
        x = c + 0.5 + (f if axis == 1 else 0.0)
        y = r + 0.5 + (f if axis == 0 else 0.0)
        samples.append(np.stack([x, y], -1))
    return field, np.concatenate(samples, 0)


def surface_samples(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray | None:
    """At most ``n`` points (M, 3) on a smooth estimate of the surface of the solid that ``points`` (N, 3) fill.

    The silhouette of a solid is the projection of its surface, but interior samples stop short of the
    surface by a random, direction-dependent gap (a sparse rim): fitted to silhouettes they leave the pose,
    above all the rotation, uncertain by a degree or two. So the surface is taken from
    :func:`solid_surface` (binned on a grid of their mean nearest-neighbour spacing,
    at most 160 cells a side, blurred, marching cubes at half the density). Returns None when none is found.
    """
    surface = solid_surface(points, cells=160, rng=rng)
    if surface is None:
        return None
    verts = surface[0]
    return verts if len(verts) <= n else verts[rng.choice(len(verts), n, replace=False)]


class PoseFit:
    """The silhouette objective of one frame (V views) as a function of a rigid pose.

    A pose (R (3, 3), p (3,)) places the centred shape points Xc (N, 3) at x = R Xc + p. Residuals, in
    pixels: per view, every point's distance outside the mask (weight 1/(V N)), and every boundary sample's
    distance to its nearest projected point (weight 1/(V M_v)). Only points projecting within
    ``candidate_px`` of the boundary or outside it are searched for the nearest one (the nearest point of a
    boundary sample at distance d lies within d of the boundary, so this is exact whenever d is smaller).
    """

    candidate_px = 4.0

    def __init__(self, Xc: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
                 silhouettes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.Xc, self.Rv, self.tv, self.Ks = Xc, viewmats[:, :3, :3], viewmats[:, :3, 3], Ks
        self.width, self.height = width, height
        self.fields = [s[0] for s in silhouettes]
        self.boundary = [s[1] for s in silhouettes]

    def _project(self, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels (V, N, 2) of the points posed by (R, p), their rotated offsets y = R Xc (N, 3) and camera
        coordinates (V, N, 3)."""
        y = self.Xc @ R.T
        cam = np.matmul((y + p)[None], self.Rv.transpose(0, 2, 1)) + self.tv[:, None, :]
        z = np.maximum(cam[..., 2], 1e-6)
        pix = np.stack([self.Ks[:, None, 0, 0] * cam[..., 0] / z + self.Ks[:, None, 0, 2],
                        self.Ks[:, None, 1, 1] * cam[..., 1] / z + self.Ks[:, None, 1, 2]], -1)
        return pix, y, cam

    def _jacobian(self, v: int, y: np.ndarray, cam: np.ndarray) -> np.ndarray:
        """Derivatives (n, 2, 6) of the pixels of n points in view v (rotated offsets y (n, 3), camera
        coordinates cam (n, 3)) with respect to a left rotation increment ρ (R ← exp(ρ) R) and a
        translation increment τ (p ← p + τ)."""
        z = np.maximum(cam[:, 2], 1e-6)
        fx, fy = self.Ks[v, 0, 0], self.Ks[v, 1, 1]
        d = np.zeros((len(z), 2, 3))
        d[:, 0, 0], d[:, 0, 2] = fx / z, -fx * cam[:, 0] / z**2
        d[:, 1, 1], d[:, 1, 2] = fy / z, -fy * cam[:, 1] / z**2
        dpix_dx = d @ self.Rv[v]  # (n, 2, 3)
        return np.concatenate([-dpix_dx @ hat(y), dpix_dx], -1)  # d(ρ × y)/dρ = −[y]×

    def _sample(self, v: int, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) of pixels (N, 2) from the mask boundary of view v (bilinear, border-clamped,
        plus the distance beyond the image; positive outside) and its gradient (N, 2)."""
        field = self.fields[v]
        H, W = field.shape
        xs, ys = pix[:, 0] - 0.5, pix[:, 1] - 0.5
        cx, cy = np.clip(xs, 0.0, W - 1.0), np.clip(ys, 0.0, H - 1.0)
        i0 = np.minimum(np.floor(cx).astype(np.int64), W - 2)
        j0 = np.minimum(np.floor(cy).astype(np.int64), H - 2)
        fx, fy = cx - i0, cy - j0
        f00, f01 = field[j0, i0], field[j0, i0 + 1]
        f10, f11 = field[j0 + 1, i0], field[j0 + 1, i0 + 1]
        value = (1 - fy) * ((1 - fx) * f00 + fx * f01) + fy * ((1 - fx) * f10 + fx * f11)
        gx = np.where(cx == xs, (1 - fy) * (f01 - f00) + fy * (f11 - f10), 0.0)
        gy = np.where(cy == ys, (1 - fx) * (f10 - f00) + fx * (f11 - f01), 0.0)
        u, w = pix[:, 0], pix[:, 1]
        value = value + np.maximum(-u, 0) + np.maximum(u - W, 0) + np.maximum(-w, 0) + np.maximum(w - H, 0)
        gx = gx - (u < 0) + (u > W)
        gy = gy - (w < 0) + (w > H)
        return value, np.stack([gx, gy], -1)

    def evaluate(self, R: np.ndarray, p: np.ndarray, jacobian: bool = True
                 ) -> tuple[float, np.ndarray, np.ndarray, list[tuple[float, float]]]:
        """The loss at (R, p); the Gauss–Newton system JᵀWJ (6, 6) and JᵀWr (6,) (zeros unless ``jacobian``);
        and per view the mean outside distance and the mean coverage distance (px)."""

        pix, y, cam = self._project(R, p)
        V, N = pix.shape[:2]
        loss, A, g, means = 0.0, np.zeros((6, 6)), np.zeros(6), []
        for v in range(V):
            signed, grad = self._sample(v, pix[v])
            active = np.nonzero(signed > 0)[0]
            o = signed[active]
            w_out = 1.0 / (V * N)
            b = self.boundary[v]
            w_cov = 1.0 / (V * max(len(b), 1))
            near = np.nonzero(signed > -self.candidate_px)[0]
            if len(near) == 0:
                near = np.arange(N)
            dist, j = cKDTree(pix[v, near]).query(b) if len(b) else (np.zeros(0), np.zeros(0, np.int64))
            idx = near[j]
            loss += w_out * float(o @ o) + w_cov * float(dist @ dist)
            means.append((float(o.sum()) / N, float(dist.mean()) if len(b) else 0.0))
            if not jacobian:
                continue
            Jo = (grad[active, None, :] @ self._jacobian(v, y[active], cam[v, active]))[:, 0]
            A += w_out * Jo.T @ Jo
            g += w_out * Jo.T @ o
            keep = dist > 0
            off = pix[v, idx[keep]] - b[keep]
            unit = off / dist[keep, None]
            Jc = (unit[:, None, :] @ self._jacobian(v, y[idx[keep]], cam[v, idx[keep]]))[:, 0]
            A += w_cov * Jc.T @ Jc
            g += w_cov * Jc.T @ dist[keep]
        return loss, A, g, means

    def fit(self, R: np.ndarray, p: np.ndarray, metres_per_px: float, radius: float, iterations: int
            ) -> tuple[np.ndarray, np.ndarray, float]:
        """Levenberg–Marquardt from (R, p); returns the fitted (R (3, 3), p (3,)) and the residual (px)."""
        loss, A, g, means = self.evaluate(R, p)
        lam = 1e-3
        for _ in range(iterations):
            diag = np.maximum(np.diag(A), 1e-12 * max(float(np.diag(A).max()), 1e-30))
            step = np.linalg.solve(A + lam * np.diag(diag), -g)
            R_new, p_new = so3_exp(step[:3]) @ R, p + step[3:]
            new, A_new, g_new, means_new = self.evaluate(R_new, p_new)
            moved_px = (np.linalg.norm(step[:3]) * radius + np.linalg.norm(step[3:])) / metres_per_px
            if new <= loss:
                done = loss - new <= 1e-6 * loss or moved_px < 5e-3
                R, p, loss, A, g, means = R_new, p_new, new, A_new, g_new, means_new
                lam = max(lam / 3.0, 1e-7)
                if done:
                    break
            else:
                lam *= 4.0
                if lam > 1e6 or moved_px < 1e-4:
                    break
        return R, p, float(np.mean([0.5 * (a + b) for a, b in means]))
