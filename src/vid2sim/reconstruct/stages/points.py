"""The simulation points of a reconstruction: the object's interior at frame 0, from masks and Gaussians.

1. Carve the visual hull of the frame-0 masks of all observed views on a voxel grid
   (:func:`vid2sim.splats.visual_hull.visual_hull`).
2. Refine it with the fitted Gaussians: render their depth from every observed view and drop the hull
   voxels that lie in front of the rendered surface (by more than ``depth_tolerance`` voxels) where the view
   sees the object — the concavities and bulges a few silhouettes cannot carve.
3. Sample points uniformly in the kept voxels; the volume is their count × voxel³; the surface voxels, with
   their exposed face area (× 2/3, the mean overestimate of a voxel staircase), are the contact points (a
   contact pressure, like the FEM ground truth's floor).

The object's canonical frame (centred on its bounding box, scaled so that half the box diagonal is 0.5) is
recorded for the skinning network's input; physics stays in the scene's metric frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.gaussians import Gaussians


@dataclass
class PointsConfig:
    """Settings of :func:`object_points`.

    Attributes:
        resolution: voxels along the longest side of the hull's box (fine carving pass).
        num_points: interior samples drawn (skinning training and cubature choose among them).
        depth_tolerance: how far (in voxels) a hull voxel may lie in front of the Gaussians' rendered
            surface before it is carved.
        alpha_threshold: the rendered opacity above which a pixel's depth is trusted.
        mask_threshold: mask values above it count as object.
        max_contact_points: the surface voxels are reduced to at most this many contact points (farthest-point
            sampling; each keeps the area of the voxels nearest to it) — the contact's cost grows with them.
        seed: seeds the sampling.
        frame_rounds: rounds of carving with the later frames' masks (:mod:`vid2sim.reconstruct.stages.carving`; 0: the
            frame-0 hull only).
        frame_residual_ratio: a frame carves only if its rigid pose fits its silhouettes with a residual at most
            this many times frame 0's.
        free_flight_tolerance: a frame carves only if the tracked centroid's acceleration is within this
            fraction of |g| of gravity (no contact).
        coverage_tolerance: a frame carves only if that uncovers at most this fraction of every mask of frame 0
            and of the frames chosen before it.
        track_points: surface samples the tracking fits to the silhouettes.
        carve_margin_px: a later frame carves a voxel only if its centre projects more than this many pixels
            outside a mask, on the mask's sub-pixel signed distance (0: at the mask's 0.5 iso-line; on the small
            suite 0.25 gave the same images and a worse E, README).
    """

    resolution: int = 64
    num_points: int = 20000
    depth_tolerance: float = 1.5
    alpha_threshold: float = 0.5
    mask_threshold: float = 0.5
    max_contact_points: int = 1000
    seed: int = 0
    frame_rounds: int = 2
    frame_residual_ratio: float = 4.0
    free_flight_tolerance: float = 0.5
    coverage_tolerance: float = 0.01
    track_points: int = 5000
    carve_margin_px: float = 0.0

    def __post_init__(self) -> None:
        if self.frame_rounds < 0 or self.track_points < 4:
            raise ConfigError(f"PointsConfig.frame_rounds must be >= 0 and track_points >= 4, got {self.frame_rounds}, "
                             f"{self.track_points}")
        if not (isinstance(self.carve_margin_px, (int, float)) and 0 <= self.carve_margin_px < math.inf):
            raise ConfigError(f"PointsConfig.carve_margin_px must be a finite number >= 0, got {self.carve_margin_px!r}")
        for name in ("frame_residual_ratio", "free_flight_tolerance", "coverage_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"PointsConfig.{name} must be a finite number > 0, got {value!r}")
        if self.resolution < 8:
            raise ConfigError(f"PointsConfig.resolution must be >= 8, got {self.resolution}")
        if self.num_points < 100:
            raise ConfigError(f"PointsConfig.num_points must be >= 100, got {self.num_points}")
        if self.max_contact_points < 1:
            raise ConfigError(f"PointsConfig.max_contact_points must be >= 1, got {self.max_contact_points}")
        if self.depth_tolerance < 0:
            raise ConfigError(f"PointsConfig.depth_tolerance must be >= 0, got {self.depth_tolerance}")


@dataclass
class ObjectPoints:
    """The object at frame 0, ready for the simulator.

    Attributes:
        points: (N, 3) interior samples (world frame, m).
        volume: the object's volume (m³).
        contact_points: (S, 3) surface-voxel centres; contact_areas: (S,) their exposed area (m²).
        centre: (3,) bounding-box centre; scale: bounding-box diagonal (m) — the canonical frame maps
            X to (X − centre) / scale.
        voxel: voxel edge (m); hull_voxels, kept_voxels: voxel counts before and after the depth carving.
        occupancy: (A, B, C) bool, the kept voxels; origin: (3,) the grid's corner (voxel (i, j, k) spans
            origin + [i, i + 1] · voxel, …).
    """

    points: Tensor
    volume: float
    contact_points: Tensor
    contact_areas: Tensor
    centre: Tensor
    scale: float
    voxel: float
    hull_voxels: int
    kept_voxels: int
    occupancy: Tensor
    origin: Tensor

    def canonical(self, X: Tensor) -> Tensor:
        """(N, 3) world points → canonical frame."""
        return (X - self.centre.to(X)) / self.scale


def _carve_by_depth(centres: Tensor, depth: Tensor, alpha: Tensor, viewmats: Tensor, Ks: Tensor,
                    tolerance: float, alpha_threshold: float) -> Tensor:
    """(M,) bool: voxel centres not in front of the rendered surface in any view that sees the object there."""
    V, H, W = depth.shape
    cam = torch.matmul(centres, viewmats[:, :3, :3].transpose(1, 2)) + viewmats[:, None, :3, 3]  # (V, M, 3)
    z = cam[..., 2]
    zs = z.clamp_min(1e-6)
    u = torch.floor(Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]).long()
    v = torch.floor(Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]).long()
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H) & (z > 1e-6)
    flat = (torch.arange(V, device=centres.device)[:, None] * H + v.clamp(0, H - 1)) * W + u.clamp(0, W - 1)
    d = depth.reshape(-1)[flat]
    seen = inside & (alpha.reshape(-1)[flat] > alpha_threshold)
    in_front = seen & (z < d - tolerance)
    return ~in_front.any(dim=0)


def sample_in_voxels(occupancy: Tensor, origin: Tensor, voxel: float, n: int, generator: torch.Generator) -> Tensor:
    """(n, 3) points uniform in the occupied voxels of ``occupancy`` (A, B, C) (a voxel drawn uniformly, then a
    uniform point in it), in the dtype of ``origin`` (3,)."""
    idx = torch.nonzero(occupancy).to(origin.dtype)
    pick = torch.randint(0, idx.shape[0], (n,), generator=generator)
    return origin + (idx[pick] + torch.rand(n, 3, generator=generator, dtype=origin.dtype)) * voxel


def object_points(masks: Tensor, cameras: Sequence[Camera], gaussians: Gaussians | None = None,
                  config: PointsConfig | None = None) -> ObjectPoints:
    """Fill the object seen in ``masks: (V, H, W)`` (frame 0 of the observed views) with points.

    Args:
        masks: (V, H, W) object masks in [0, 1] of the V ``cameras``.
        gaussians: the Gaussians fitted to frame 0; when given, their rendered depth carves the hull (step 2
            of the module docstring).
        config: :class:`PointsConfig`.
    Raises:
        ValueError: empty hull (names the likely cause) or too few kept voxels.
    """
    from vid2sim.splats.render import render_gaussians
    from vid2sim.splats.visual_hull import visual_hull

    cfg = config or PointsConfig()
    dtype = torch.float32
    occ, lo, voxel = visual_hull(masks.to(dtype), cameras, cfg.resolution, max(8, cfg.resolution // 2),
                                 cfg.mask_threshold)
    hull = int(occ.sum())
    if gaussians is not None:
        with torch.no_grad():
            out = render_gaussians(gaussians, list(cameras), background=1.0)
        viewmats, Ks, _, _ = stack_cameras(cameras)
        idx = torch.nonzero(occ)
        centres = lo + (idx.to(dtype) + 0.5) * voxel
        keep = _carve_by_depth(centres, out.depth[..., 0], out.alpha[..., 0], viewmats.to(dtype), Ks.to(dtype),
                               cfg.depth_tolerance * voxel, cfg.alpha_threshold)
        occ = torch.zeros_like(occ)
        occ[tuple(idx[keep].T)] = True
    return points_from_occupancy(occ, lo, voxel, cfg, hull_voxels=hull)


def points_from_occupancy(occ: Tensor, origin: Tensor, voxel: float, config: PointsConfig | None = None,
                          hull_voxels: int | None = None) -> ObjectPoints:
    """The :class:`ObjectPoints` of a carved voxel grid: interior samples, volume, contact points (step 3 of
    the module docstring) and the canonical frame.

    Args:
        occ: (A, B, C) bool, the object's voxels; origin: (3,) the grid's corner; voxel: the voxel edge (m).
        config: :class:`PointsConfig` (``num_points``, ``max_contact_points``, ``seed``).
        hull_voxels: the voxel count before the last carving (recorded); None: ``occ``'s own.
    Raises:
        ValueError: fewer than 8 voxels.
    """
    from vid2sim.splats.visual_hull import _surface

    cfg = config or PointsConfig()
    dtype = torch.float32
    lo = origin.to(dtype)
    hull = int(occ.sum()) if hull_voxels is None else int(hull_voxels)
    kept = int(occ.sum())
    if kept < 8:
        raise ValueError(f"only {kept} voxels of the object survive carving at resolution {cfg.resolution} "
                         "(hull {hull}); check the masks and cameras, or raise PointsConfig.resolution")
    gen = torch.Generator().manual_seed(cfg.seed)
    points = sample_in_voxels(occ, lo, voxel, cfg.num_points, gen)
    surface = _surface(occ)
    s_idx = torch.nonzero(surface)
    p = torch.nn.functional.pad(occ.float()[None, None], (1, 1, 1, 1, 1, 1))[0, 0]
    i, j, k = (s_idx + 1).T
    exposed = sum(1.0 - p[i + di, j + dj, k + dk] for di, dj, dk in
                  ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)))
    contact = lo + (s_idx.to(dtype) + 0.5) * voxel
    areas = exposed.to(dtype) * voxel ** 2 / 1.5  # a staircase overestimates a surface's area by 3/2 on average
    if contact.shape[0] > cfg.max_contact_points:
        from vid2sim.physics.cubature import farthest_point_sampling

        keep = farthest_point_sampling(contact, cfg.max_contact_points, seed=cfg.seed)
        nearest = torch.cdist(contact, contact[keep]).argmin(dim=1)
        areas = torch.zeros(len(keep), dtype=dtype).index_add_(0, nearest, areas)
        contact = contact[keep]
    box_lo, box_hi = points.min(0).values, points.max(0).values
    return ObjectPoints(points=points, volume=kept * voxel ** 3, contact_points=contact, contact_areas=areas,
                        centre=0.5 * (box_lo + box_hi), scale=float((box_hi - box_lo).norm()), voxel=voxel,
                        hull_voxels=hull, kept_voxels=kept, occupancy=occ.cpu(), origin=lo.cpu())
