"""Where the object is in 3D, frame by frame, from its masks alone: triangulated silhouette centroids and a soft
visual hull (its centroid, its extent, its lowest point along a direction).

The soft hull of a point is the smallest mask value of its projections over the views (bilinear, 0 outside an
image); its centroid, weighted by how surely a voxel is inside, moves smoothly with the object instead of
jumping by voxels. A mask that misses part of the object (its colours close to the background's there) carves
that part out of the strict hull and pulls its centroid away; the *robust* hull takes the second-smallest value
instead (one view may disagree), so the centroid of the object's track does not jump with one view's mask. The
strict hull stays the object's outline for its extent and its lowest point. Everything here works in the
calibration's frame and units.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np
import torch

from vid2sim.scene.capture.cameras import CaptureCamera


def _stack(cameras: Sequence[CaptureCamera]) -> tuple[torch.Tensor, torch.Tensor]:
    w2c = torch.as_tensor(np.stack([c.world_to_camera for c in cameras]), dtype=torch.float64)
    K = torch.as_tensor(np.stack([c.K for c in cameras]), dtype=torch.float64)
    return w2c, K


def mask_centroids(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroids (…, 2) in pixels (x, y; pixel centres at +0.5) and areas (…,) of masks (…, H, W)."""
    H, W = masks.shape[-2:]
    area = masks.sum((-1, -2))
    xs = (np.arange(W) + 0.5)
    ys = (np.arange(H) + 0.5)
    cx = (masks.sum(-2) * xs).sum(-1) / np.maximum(area, 1e-9)
    cy = (masks.sum(-1) * ys).sum(-1) / np.maximum(area, 1e-9)
    return np.stack([cx, cy], -1), area


def triangulate(cameras: Sequence[CaptureCamera], pixels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Least-squares meeting point (T, 3) of the rays through pixels (V, T, 2) of valid (V, T) views (NaN where fewer
    than two views are valid)."""
    V, T = valid.shape
    out = np.full((T, 3), np.nan)
    centres = np.stack([c.center for c in cameras])
    for t in range(T):
        A = np.zeros((3, 3))
        b = np.zeros(3)
        n = 0
        for v in range(V):
            if not valid[v, t]:
                continue
            cam = cameras[v]
            d_cam = np.linalg.solve(cam.K, np.array([pixels[v, t, 0], pixels[v, t, 1], 1.0]))
            d = cam.rotation.T @ d_cam
            d /= np.linalg.norm(d)
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ centres[v]
            n += 1
        if n >= 2:
            out[t] = np.linalg.solve(A, b)
    return out


@dataclass
class HullFrame:
    """The soft visual hull of one frame on a voxel grid.

    Attributes:
        origin: (3,) centre of the grid's first voxel (calibration frame); voxel: the voxel edge length;
        resolution: voxels per side n; occupancy: (n³,) soft hull value in [0, 1], index (i·n + j)·n + k for the
            voxel at origin + voxel·(i, j, k).
        robust: (n³,) the robust hull's value (one view may disagree), or None (as strict: too few views).
    """

    origin: np.ndarray
    voxel: float
    resolution: int
    occupancy: np.ndarray
    robust: np.ndarray | None = None

    @cached_property
    def points(self) -> np.ndarray:
        """(n³, 3) voxel centres (computed once: the free-flight search asks for the lowest point often)."""
        return self.origin + self.voxel * _unit_grid(self.resolution).numpy().astype(np.float64)

    def centroid(self, robust: bool = False) -> np.ndarray:
        """(3,) centroid weighted by clip((occ − 0.3) / 0.4, 0, 1) (NaN for an empty hull), of the robust hull's
        values with ``robust`` (where there are)."""
        occ = self.robust if robust and self.robust is not None else self.occupancy
        n = self.resolution
        w = np.clip((occ - 0.3) / 0.4, 0.0, 1.0).reshape(n, n, n)
        total = w.sum()
        if total <= 0:
            return np.full(3, np.nan)
        ax = np.arange(n, dtype=np.float64)
        ijk = np.array([w.sum((1, 2)) @ ax, w.sum((0, 2)) @ ax, w.sum((0, 1)) @ ax]) / total
        return self.origin + self.voxel * ijk

    def extent(self) -> float:
        """Diameter of the hull's voxels with occupancy > 0.5 (largest distance from the centroid, doubled)."""
        inside = self.occupancy > 0.5
        if not inside.any():
            return 0.0
        p = self.points[inside]
        c = p.mean(0)
        return 2.0 * float(np.linalg.norm(p - c, axis=1).max()) + self.voxel


_GRIDS: dict[int, torch.Tensor] = {}


def _unit_grid(n: int) -> torch.Tensor:
    """(n³, 3) float32 integer voxel coordinates (i, j, k), cached."""
    if n not in _GRIDS:
        ax = torch.arange(n, dtype=torch.float32)
        _GRIDS[n] = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    return _GRIDS[n]


def soft_hull(cameras: Sequence[CaptureCamera], masks: np.ndarray, centre: np.ndarray, half_size: float,
              resolution: int, robust_views: int = 4) -> HullFrame:
    """The soft visual hull of one frame: masks (V, H, W) float in [0, 1] of the views to use, a cube of
    ``half_size`` around ``centre`` (3,) split into ``resolution``³ voxels; with at least ``robust_views`` views
    also the robust hull (the second-smallest value over the views)."""
    w2c, K = _stack(cameras)
    V, H, W = masks.shape
    n = int(resolution)
    voxel = 2.0 * half_size / n
    origin = np.asarray(centre, dtype=np.float64) - half_size + 0.5 * voxel
    # camera coordinates of every voxel, relative to the grid origin (float32 is plenty at this scale)
    R = w2c[:, :3, :3]
    t0 = (R @ torch.as_tensor(origin, dtype=torch.float64) + w2c[:, :3, 3]).to(torch.float32)
    Rv = (R * voxel).to(torch.float32)
    cam = torch.einsum("vij,nj->vni", Rv, _unit_grid(n)) + t0[:, None, :]
    z = cam[..., 2]
    zs = z.clamp_min(1e-9)
    Kf = K.to(torch.float32)
    u = Kf[:, None, 0, 0] * cam[..., 0] / zs + Kf[:, None, 0, 2]
    v = Kf[:, None, 1, 1] * cam[..., 1] / zs + Kf[:, None, 1, 2]
    # grid_sample's align_corners=False convention: −1 and 1 are the outer edges of the image
    grid = torch.stack([2 * u / W - 1, 2 * v / H - 1], -1)[:, None]
    vals = torch.nn.functional.grid_sample(torch.as_tensor(masks, dtype=torch.float32)[:, None], grid,
                                           mode="bilinear", padding_mode="zeros", align_corners=False)[:, 0, 0]
    vals = torch.where(z > 1e-9, vals, torch.zeros_like(vals))
    if V >= max(robust_views, 2):
        two = torch.topk(vals, 2, dim=0, largest=False, sorted=True).values.numpy().astype(np.float64)
        return HullFrame(origin, voxel, n, two[0], two[1])
    return HullFrame(origin, voxel, n, vals.min(0).values.numpy().astype(np.float64))


def lowest_point(hull: HullFrame, up: np.ndarray) -> float:
    """The lowest height along ``up`` (3,) where the soft hull crosses 0.5, interpolated within the voxel."""
    inside = hull.occupancy > 0.5
    if not inside.any():
        return float("nan")
    h = hull.points @ up
    k = int(np.argmin(np.where(inside, h, np.inf)))
    occ = hull.occupancy[k]
    # the voxel centre at height h[k] has occupancy occ > 0.5; assume the value falls to 0 over one voxel below
    return float(h[k] - hull.voxel * min(occ - 0.5, 0.5))
