"""The simulation points of a reconstruction: the object's interior at frame 0, from masks and Gaussians.

1. Carve the visual hull of the frame-0 masks of all observed views on a voxel grid
   (:func:`vid2sim.splats.visual_hull.visual_hull`).
2. Refine it with the fitted Gaussians: find the surface they show in every observed view (the depth where the
   accumulated opacity reaches ``surface_opacity``, :func:`vid2sim.splats.surface_depth.surface_depth`) and drop
   the hull voxels that lie in front of it (by more than ``depth_tolerance`` voxels) where the view sees the object —
   the concavities and bulges a few silhouettes cannot carve.
3. Sample points uniformly in the kept voxels; the volume is their count × voxel³; the surface voxels, with
   their exposed face area (× 2/3, the mean overestimate of a voxel staircase), are the contact points (a
   contact pressure, like the FEM ground truth's floor).

The object's canonical frame (centred on its bounding box, scaled so that half the box diagonal is 0.5) is
recorded for the skinning network's input; physics stays in the scene's metric frame.

**Carving with the later frames** (:func:`carve_with_frames`). The object's hull carved again with the silhouettes of
its later frames

Four views of frame 0 leave the visual hull far too large wherever no camera sees the object in profile. The
worst of it is where the simulator's contact happens. On the small suite's scene 4 the frame-0 hull (after
the Gaussians' depth carving) sticks out 4–7 cm below the object along the directions that face the floor
while it rolls after its first bounce. The simulated bounce then gives the wrong spin: 130° off by frame 15,
even with the true initial velocity and material. With the true surface as contact points it is 20° off.

The object turns in the later frames, though, and shows those sides in profile. So, in ``rounds``:

1. **Track** the hull's rigid pose in every observed frame from the masks (:func:`track_poses`: the
   silhouette fit of :mod:`vid2sim.reconstruct.stages.velocity`, each frame started from the previous pose
   advanced by the last frame-to-frame motion). Poses are relative to frame 0's fit: frame t maps a frame-0
   point X to R_t X + T_t.
2. **Choose frames** that a rigid pose explains:
   * in free flight: the tracked centroid's acceleration (central difference) is within
     ``free_flight_tolerance`` · |g| of gravity. In contact the object is squashed, and those silhouettes would
     carve away what the squash hides.
   * fitted about as well as frame 0: silhouette residual at most ``frame_residual_ratio`` × frame 0's. A
     soft object vibrating after its bounce, or a lost track, fits worse.
   * harmless to the frames already chosen: carving with the frame must not uncover more than
     ``coverage_tolerance`` of any mask of frame 0 or of an earlier chosen frame, each seen through its own
     pose (a correct hull projects onto its own masks; a wrong pose cuts into the object). Frames are taken in
     time order, so the early frames, whose track has not drifted, judge the late ones. Silhouettes alone can
     let the track drift on a rounded object: on scene 1 of the small suite the tracked pose is 13° off by
     frame 6 and 40–70° from frame 9 on, with residuals still a fraction of a pixel.
3. **Carve** the frame-0 voxels (hull and depth carving, :func:`~vid2sim.reconstruct.stages.points.object_points`):
   keep the voxels whose centres, posed by each chosen frame, project inside that frame's masks in every view
   (:func:`within_silhouettes`, on the masks' sub-pixel signed distance, with ``carve_margin_px``).

The next round tracks with the carved hull, which fits the silhouettes better, and carves the frame-0 voxels
again (not the previous round's), so a pose that was wrong in one round leaves no trace. Measurements:
docs/architecture.md, "The hull from the later frames".
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.cubature import farthest_point_sampling, sample_cubature
from vid2sim.physics.mass import moment_matched_volumes, voxel_moments
from vid2sim.reconstruct.config import PointsConfig
from vid2sim.reconstruct.runner import Context, State
from vid2sim.reconstruct.silhouettes import PoseFit, prepare_silhouette, surface_samples
from vid2sim.runtime.files import read_json, save_torch_atomic, write_json_atomic
from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.surface_depth import surface_depth
from vid2sim.splats.visual_hull import project_points, surface_voxels, visual_hull


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


def _at_most(camera: Camera, side: int) -> Camera:
    """``camera`` with its image's longer side at most ``side`` pixels (the same view, K scaled)."""
    scale = side / max(camera.width, camera.height)
    if scale >= 1:
        return camera
    return camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))


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
    seen = inside & (alpha.reshape(-1)[flat] > alpha_threshold) & torch.isfinite(d)
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

    cfg = config or PointsConfig()
    dtype = torch.float32
    occ, lo, voxel = visual_hull(masks.to(dtype), cameras, cfg.resolution, max(8, cfg.resolution // 2),
                                 cfg.mask_threshold)
    hull = int(occ.sum())
    if gaussians is not None:
        # a voxel spans a few pixels of a full-size view: depth maps of twice the grid's resolution resolve it, at a
        # fraction of the cost (each depth plane is a render)
        small = [_at_most(c, 2 * cfg.resolution) for c in cameras]
        depth, alpha = surface_depth(gaussians, small, cfg.depth_planes, cfg.surface_opacity)
        viewmats, Ks, _, _ = stack_cameras(small)
        idx = torch.nonzero(occ)
        centres = lo + (idx.to(dtype) + 0.5) * voxel
        keep = _carve_by_depth(centres, depth.to(dtype), alpha.to(dtype), viewmats.to(dtype), Ks.to(dtype),
                               cfg.depth_tolerance * voxel, cfg.alpha_threshold)
        occ = torch.zeros_like(occ)
        occ[tuple(idx[keep].T)] = True
    return points_from_occupancy(occ, lo, voxel, cfg, hull_voxels=hull)


def contact_surface(occ: Tensor, origin: Tensor, voxel: float, max_points: int, seed: int) -> tuple[Tensor, Tensor]:
    """The contact points of a voxel solid: its surface voxels' centres (S, 3) and their exposed face area (S,) m²
    (× 2/3, a staircase's mean overestimate), reduced to at most ``max_points`` by farthest-point sampling, each
    kept point carrying the area of the surface voxels nearest to it. ``occ`` (A, B, C) bool; ``origin`` (3,)."""
    dtype = torch.float32
    lo = origin.to(dtype)
    s_idx = torch.nonzero(surface_voxels(occ))
    p = torch.nn.functional.pad(occ.float()[None, None], (1, 1, 1, 1, 1, 1))[0, 0]
    i, j, k = (s_idx + 1).T
    exposed = sum(1.0 - p[i + di, j + dj, k + dk] for di, dj, dk in
                  ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)))
    contact = lo + (s_idx.to(dtype) + 0.5) * voxel
    areas = exposed.to(dtype) * voxel ** 2 / 1.5  # a staircase overestimates a surface's area by 3/2 on average
    if contact.shape[0] > max_points:
        keep = farthest_point_sampling(contact, max_points, seed=seed)
        nearest = torch.cdist(contact, contact[keep]).argmin(dim=1)
        areas = torch.zeros(len(keep), dtype=dtype).index_add_(0, nearest, areas)
        contact = contact[keep]
    return contact, areas


def rigid_frames(residuals_px: Sequence[float], ratio: float, reference_frames: int = 3) -> np.ndarray:
    """(T,) bool: the tracked frames whose rigid fit is about as good as in flight: silhouette residual at most
    ``ratio`` × the median residual of the first ``reference_frames`` frames (a drop's video starts in flight, where
    a rigid pose fits well). A soft object squashes at the contact: its rigid fit degrades there and its pose sinks
    below the floor, so those frames' poses would carve the squash as keel (:func:`floor_carved_contact`).

    Args:
        residuals_px: (T,) :attr:`TrackedPoses.residuals_px`.
    Raises:
        ValueError: no residuals, or a ratio below 1.
    """
    r = np.asarray(residuals_px, dtype=np.float64)
    if r.ndim != 1 or r.size == 0:
        raise ValueError(f"rigid_frames: residuals must be a non-empty (T,) sequence, got shape {r.shape}")
    if not ratio >= 1.0:
        raise ValueError(f"rigid_frames: ratio must be >= 1, got {ratio!r}")
    return r <= ratio * float(np.median(r[:reference_frames]))


def floor_carved_contact(obj: ObjectPoints, rotations: np.ndarray, translations: np.ndarray, floor_height: float,
                         margin_voxels: float = 1.0, config: PointsConfig | None = None
                         ) -> tuple[Tensor, Tensor, int]:
    """The contact surface of ``obj``'s voxels without those that a tracked rigid pose puts below the floor.

    A 4-view hull reaches below the object where no camera sees it from below, and that keel is what meets the floor
    first. Posed by the rigid poses tracked from the masks (:func:`track_poses`: frame t maps X to R_t X + T_t), a
    voxel centre lower than ``margin_voxels`` voxels under the floor (the plane z = ``floor_height``) in any frame
    cannot be the object's if the pose is right — but a soft object squashes at the contact and a track drifts, so
    this surface is a candidate for the joint stage's coarse search (``JointConfig.contact_search``) to judge by the
    video, never taken unseen. The mass and the interior points stay the hull's.

    Args:
        rotations: (T, 3, 3); translations: (T, 3).
    Returns:
        (S, 3) contact points and (S,) areas as :func:`contact_surface`, and the number of voxels removed.
    Raises:
        ValueError: poses of mismatched shapes, or a carve that leaves fewer than 8 voxels.
    """
    cfg = config or PointsConfig()
    R, T = np.asarray(rotations, dtype=np.float64), np.asarray(translations, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or T.shape != (R.shape[0], 3):
        raise ValueError(f"floor_carved_contact: rotations must be (T, 3, 3) and translations (T, 3), got {R.shape} "
                         f"and {T.shape}")
    occ = obj.occupancy.cpu()
    idx = torch.nonzero(occ)
    centres = (obj.origin.cpu().double() + (idx.double() + 0.5) * obj.voxel).numpy()
    lowest = np.min(np.einsum("tj,nj->tn", R[:, 2, :], centres) + T[:, None, 2], axis=0)  # (N,) over the frames
    keep = lowest >= floor_height - margin_voxels * obj.voxel
    if keep.sum() < 8:
        raise ValueError(f"floor_carved_contact: only {int(keep.sum())} of {len(keep)} voxels stay above the floor")
    carved = torch.zeros_like(occ)
    carved[tuple(idx[torch.from_numpy(keep)].T)] = True
    contact, areas = contact_surface(carved, obj.origin.cpu(), obj.voxel, cfg.max_contact_points, cfg.seed)
    return contact.to(obj.contact_points), areas.to(obj.contact_areas), int((~keep).sum())


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
    contact, areas = contact_surface(occ, lo, voxel, cfg.max_contact_points, cfg.seed)
    box_lo, box_hi = points.min(0).values, points.max(0).values
    return ObjectPoints(points=points, volume=kept * voxel ** 3, contact_points=contact, contact_areas=areas,
                        centre=0.5 * (box_lo + box_hi), scale=float((box_hi - box_lo).norm()), voxel=voxel,
                        hull_voxels=hull, kept_voxels=kept, occupancy=occ.cpu(), origin=lo.cpu())


@dataclass
class TrackedPoses:
    """Rigid poses of the object in consecutive frames, relative to frame 0.

    Attributes:
        rotations: (T, 3, 3) and translations: (T, 3): frame t maps a frame-0 point X to R_t X + T_t.
        residuals_px: (T,) the silhouette fits' mean residuals (pixels).
        centroids: (T, 3) the tracked points' centroid in each frame (m).
    """

    rotations: np.ndarray
    translations: np.ndarray
    residuals_px: np.ndarray
    centroids: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])


def track_poses(points: Tensor, masks: Tensor, cameras: Sequence[Camera], iterations: int = 30,
                max_points: int = 5000, seed: int = 0) -> TrackedPoses:
    """Track the rigid pose of the solid that ``points`` fill through the frames of ``masks``.

    Args:
        points: (N, 3) samples filling the object at frame 0 (world frame, m).
        masks: (V, T, H, W) object masks in [0, 1] of consecutive frames (frame 0 first).
        cameras: the V cameras (one image size).
        iterations: Levenberg–Marquardt iterations per frame, at most.
        max_points: surface samples fitted to the silhouettes.
        seed: seeds the surface samples.

    Returns:
        :class:`TrackedPoses` of frames 0 … K−1, K ≤ T: tracking stops before the first frame whose mask is
        empty in some view (the object left it).
    """

    if masks.ndim != 4 or masks.shape[0] != len(cameras):
        raise ValueError(f"track_poses: masks must be (V={len(cameras)}, T, H, W), got {tuple(masks.shape)}")
    P = points.detach().to("cpu", torch.float64).numpy()
    centre = P.mean(0)
    rng = np.random.default_rng(seed)
    surface = surface_samples(P, max_points, rng)
    if surface is None:
        surface = P[rng.choice(len(P), min(max_points, len(P)), replace=False)]
    Xc = surface - centre
    radius = float(np.linalg.norm(P - centre, axis=1).max())
    viewmats_t, Ks_t, width, height = stack_cameras(list(cameras))
    viewmats, Ks = viewmats_t.detach().cpu().double().numpy(), Ks_t.detach().cpu().double().numpy()
    depth = np.einsum("vj,nj->vn", viewmats[:, 2, :3], P[:: max(1, len(P) // 1000)]) + viewmats[:, 2:3, 3]
    metres_per_px = float(depth.mean()) / float(Ks[:, [0, 1], [0, 1]].mean())
    m = masks.detach().to("cpu", torch.float32).numpy()
    R, p = np.eye(3), centre.copy()
    step_R, step_p = np.eye(3), np.zeros(3)
    Rs, ps, res = [], [], []
    for t in range(m.shape[1]):
        if not all((m[v, t] >= 0.5).any() for v in range(len(cameras))):
            break
        fitter = PoseFit(Xc, viewmats, Ks, width, height, [prepare_silhouette(m[v, t]) for v in range(len(cameras))])
        R_new, p_new, r = fitter.fit(step_R @ R, p + step_p, metres_per_px, radius, iterations)
        if t > 0:
            step_R, step_p = R_new @ R.T, p_new - p
        R, p = R_new, p_new
        Rs.append(R)
        ps.append(p)
        res.append(r)
    if not Rs:
        raise ValueError("track_poses: the masks of frame 0 are empty in some view")
    Rs_a, ps_a = np.stack(Rs), np.stack(ps)
    rel = Rs_a @ Rs_a[0].T  # frame 0's fit → frame t's
    return TrackedPoses(rotations=rel, translations=ps_a - rel @ ps_a[0], residuals_px=np.array(res),
                        centroids=ps_a)


def gravity_deviation(centroids: np.ndarray, dt: float, gravity: Sequence[float]) -> list[float | None]:
    """Per frame, |a − g| / |g| for the centroid's acceleration a (central difference of the (T, 3)
    ``centroids``, ``dt`` s apart): 0 in free flight, several in contact. None for the first and last frame."""
    g = np.asarray(gravity, dtype=np.float64)
    if g.shape != (3,) or not np.isfinite(g).all() or not np.linalg.norm(g) > 0:
        raise ValueError(f"gravity_deviation: gravity must be a finite non-zero (3,) vector to tell free flight from "
                         f"contact, got {list(np.ravel(g))}")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"gravity_deviation: dt must be a positive number of seconds, got {dt!r}")
    out: list[float | None] = [None] * len(centroids)
    for t in range(1, len(centroids) - 1):
        acc = (centroids[t + 1] - 2 * centroids[t] + centroids[t - 1]) / (dt * dt)
        out[t] = float(np.linalg.norm(acc - g) / np.linalg.norm(g))
    return out


def within_silhouettes(points: Tensor, masks: Tensor, viewmats: Tensor, Ks: Tensor, margin_px: float) -> Tensor:
    """(N,) bool: which world points (N, 3) project, in every view, at most ``margin_px`` pixels outside the
    mask's 0.5 iso-line (the signed distance of :func:`~vid2sim.reconstruct.stages.velocity.prepare_silhouette`,
    interpolated bilinearly). ``masks``: (V, H, W) in [0, 1]; ``viewmats``: (V, 4, 4); ``Ks``: (V, 3, 3)."""

    V, H, W = masks.shape
    cam = torch.matmul(points, viewmats[:, :3, :3].transpose(1, 2)) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    u = Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]
    keep = torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    for i in range(V):
        field = torch.from_numpy(prepare_silhouette(masks[i].detach().cpu().numpy())[0]).float()
        grid = torch.stack([u[i] / W * 2 - 1, v[i] / H * 2 - 1], -1)[None, None]  # pixel centres at +0.5
        d = torch.nn.functional.grid_sample(field[None, None], grid, mode="bilinear", padding_mode="border",
                                            align_corners=False)[0, 0, 0]
        outside_image = (u[i] < 0) | (u[i] > W) | (v[i] < 0) | (v[i] > H)
        keep &= (z[i] > 1e-6) & (d <= margin_px) & ~outside_image
    return keep


_COVER_OFFSETS = torch.tensor([[0.0, 0.0, 0.0]] + [[a, b, c] for a in (-0.45, 0.45) for b in (-0.45, 0.45)
                                                     for c in (-0.45, 0.45)])


def voxel_pixel_hits(voxels: Tensor, origin: Tensor, voxel: float, cameras: Sequence[Camera], size: tuple[int, int],
                     pose: tuple[np.ndarray, np.ndarray] | None = None) -> Tensor:
    """Per view and pixel, how many sample points of the voxels land on it: (V, H·W) int64.

    Each voxel is projected as its centre and 8 points at ±0.45 voxel (voxels are about a pixel wide at the
    default resolution), so the pixels hit form a solid silhouette. The counts of a set are the sum of its
    parts', so a subset's hits are the whole set's counts less those of the voxels it leaves out.

    Args:
        voxels: (N, 3) integer grid indices of the voxels; origin: (3,) the grid's corner; voxel: its edge (m).
        cameras: the V cameras; size: (H, W) of their images.
        pose: (R (3, 3), T (3,)) moving the voxels (X ↦ R X + T); None: as they are.
    """

    H, W = size
    offsets = _COVER_OFFSETS.to(voxels.device)
    pts = (origin.float() + (voxels.to(torch.float32)[:, None, :] + 0.5 + offsets[None]) * voxel).reshape(-1, 3)
    if pose is not None:
        pts = pts @ torch.as_tensor(pose[0], dtype=torch.float32).T + torch.as_tensor(pose[1], dtype=torch.float32)
    viewmats, Ks, _, _ = stack_cameras(list(cameras))
    col, row, _ = project_points(pts, viewmats.float(), Ks.float())
    hits = torch.zeros(len(cameras), H * W, dtype=torch.int64, device=col.device)
    for v in range(len(cameras)):
        ok = (col[v] >= 0) & (col[v] < W) & (row[v] >= 0) & (row[v] < H)
        hits[v] = torch.bincount(row[v][ok] * W + col[v][ok], minlength=H * W)
    return hits


def hits_coverage(hits: Tensor, masks: Tensor, threshold: float = 0.5) -> list[float]:
    """Per view, the fraction of the mask's pixels (> ``threshold``) with a hit: ``hits`` (V, H·W) from
    :func:`voxel_pixel_hits`, ``masks`` (V, H, W) in [0, 1]."""
    inside = masks.reshape(masks.shape[0], -1) > threshold
    covered = ((hits > 0) & inside).sum(1)
    return [float(c) / max(1, int(n)) for c, n in zip(covered, inside.sum(1))]


def silhouette_coverage(occupancy: Tensor, origin: Tensor, voxel: float, masks: Tensor,
                        cameras: Sequence[Camera], threshold: float = 0.5,
                        pose: tuple[np.ndarray, np.ndarray] | None = None) -> list[float]:
    """Per view, the fraction of the mask's pixels (> ``threshold``) that the occupied voxels cover (each voxel
    projected as in :func:`voxel_pixel_hits`).

    Args:
        occupancy: (A, B, C) bool; origin: (3,) the grid's corner; voxel: its edge (m).
        masks: (V, H, W) in [0, 1]; cameras: the V cameras.
        pose: (R (3, 3), T (3,)) moving the voxels (X ↦ R X + T) into the frame of ``masks``; None: as they are.
    """

    hits = voxel_pixel_hits(torch.nonzero(occupancy), origin, voxel, cameras, tuple(masks.shape[1:]), pose)
    return hits_coverage(hits, masks, threshold)


def carve_with_frames(masks: Tensor, cameras: Sequence[Camera], dt: float, gravity: Sequence[float],
                      gaussians: Any | None = None, config: Any | None = None,
                      progress: bool = False) -> tuple[Any, dict[str, Any]]:
    """The object's points from the masks of all observed frames (the module docstring).

    Args:
        masks: (V, T, H, W) object masks in [0, 1] of the observed views, consecutive frames from frame 0.
        cameras: the V cameras.
        dt: seconds between frames; gravity: (3,) m/s².
        gaussians: the Gaussians fitted to frame 0 (their depth carves the frame-0 hull), or None.
        config: :class:`~vid2sim.reconstruct.stages.points.PointsConfig` (its ``frame_*`` fields; ``frame_rounds`` 0
            gives the frame-0 points).

    Returns:
        (:class:`~vid2sim.reconstruct.stages.points.ObjectPoints`, a JSON-ready record: per round the tracked residuals,
        which frames were in free flight, chosen, or refused and why, and the voxel counts).
    """

    cfg = config or PointsConfig()
    V, T = masks.shape[:2]
    obj0 = object_points(masks[:, 0], cameras, gaussians, cfg)
    record: dict[str, Any] = {"frame0_voxels": obj0.kept_voxels, "rounds": []}
    if cfg.frame_rounds == 0 or T < 3:
        record["skipped"] = "frame_rounds is 0" if cfg.frame_rounds == 0 else f"{T} frames (3 or more needed)"
        return obj0, record
    occ0, origin, voxel = obj0.occupancy, obj0.origin, obj0.voxel
    idx = torch.nonzero(occ0)
    centres = (origin.double() + (idx.double() + 0.5) * voxel)
    viewmats, Ks, _, _ = stack_cameras(list(cameras))
    viewmats, Ks = viewmats.float(), Ks.float()
    size = (int(masks.shape[2]), int(masks.shape[3]))
    obj = obj0
    for r in range(cfg.frame_rounds):
        poses = track_poses(obj.points, masks, cameras, max_points=cfg.track_points, seed=cfg.seed)
        deviation = gravity_deviation(poses.centroids, dt, gravity)
        limit = cfg.frame_residual_ratio * float(poses.residuals_px[0])
        keep = torch.ones(len(idx), dtype=torch.bool)
        chosen, refused = [], {}

        # per frame that carves, the frame-0 voxels' pixel hits posed there; a trial's hits are those less the
        # hits of the voxels it removes (a few per cent of them), the same pixels as projecting what it keeps
        hits: dict[int, Tensor] = {}

        def voxel_hits(voxels: Tensor, s: int) -> Tensor:
            return voxel_pixel_hits(voxels, origin, voxel, cameras, size, (poses.rotations[s], poses.translations[s]))

        def cover(s: int, removed: Tensor | None = None) -> list[float]:
            kept = hits[s] if removed is None else hits[s] - voxel_hits(removed, s)
            return hits_coverage(kept, masks[:, s].float(), cfg.mask_threshold)

        hits[0] = voxel_hits(idx, 0)
        base_cover = {0: cover(0)}  # the frames that carve, and what the frame-0 voxels cover of them
        for t in range(1, poses.num_frames):
            if deviation[t] is None or deviation[t] > cfg.free_flight_tolerance:
                refused[t] = "not in free flight" if deviation[t] is not None else "last frame"
                continue
            if poses.residuals_px[t] > limit:
                refused[t] = f"residual {poses.residuals_px[t]:.2f} px > {limit:.2f}"
                continue
            posed = centres @ torch.from_numpy(poses.rotations[t]).T + torch.from_numpy(poses.translations[t])
            inside = within_silhouettes(posed.float(), masks[:, t], viewmats, Ks, cfg.carve_margin_px)
            removed = idx[~(keep & inside)]
            losses = {s: max(b - c for b, c in zip(base, cover(s, removed))) for s, base in base_cover.items()}
            worst = max(losses, key=losses.get)
            if losses[worst] > cfg.coverage_tolerance:
                refused[t] = f"uncovers {100 * losses[worst]:.1f} % of a mask of frame {worst}"
                continue
            keep &= inside
            chosen.append(t)
            hits[t] = voxel_hits(idx, t)
            base_cover[t] = cover(t)
        occ = torch.zeros_like(occ0)
        occ[tuple(idx[keep].T)] = True
        obj = points_from_occupancy(occ, origin, voxel, cfg, hull_voxels=obj0.hull_voxels)
        record["rounds"].append({"tracked_frames": poses.num_frames,
                                 "residuals_px": [round(float(x), 4) for x in poses.residuals_px],
                                 "gravity_deviation": [None if d is None else round(d, 3) for d in deviation],
                                 "chosen": chosen, "refused": {str(k): v for k, v in refused.items()},
                                 "voxels": int(keep.sum())})
        if progress:
            print(f"      round {r + 1}: carved with frames {chosen}: {int(keep.sum())} of {len(idx)} voxels kept",
                  flush=True)
    return obj, record


# ---- the stage -------------------------------------------------------------------------------------------------


@dataclass
class Cubature:
    """The simulator's integration points among the object's points.

    Attributes:
        index: (K,) indices into the object's points (farthest-point sampled).
        weights: (K,) their integration volumes in m³ (the object's volume / K each, or their Voronoi cells).
        mass_volumes: (K,) the volumes their lumped masses are made of when the masses are corrected to the
            kept voxels' moments (``simulator.mass`` "moments"), else None (the masses are ``weights``).
    """

    index: Tensor
    weights: Tensor
    mass_volumes: Tensor | None


def simulation_cubature(obj: ObjectPoints, count: int, mass: str, seed: int, volumes: str = "equal") -> Cubature:
    """The :class:`Cubature` of ``count`` points of ``obj`` (on its device), with integration volumes by
    ``volumes`` ("equal" or "voronoi", :func:`~vid2sim.physics.cubature.sample_cubature`) and masses by ``mass``."""
    index, weights = sample_cubature(obj.points, count, volume=obj.volume, seed=seed, weights=volumes)
    mass_volumes = None
    if mass == "moments":  # the kept voxels' mass, centre of mass and inertia, exactly
        mass_volumes = moment_matched_volumes(obj.points[index], weights,
                                              voxel_moments(obj.occupancy, obj.origin, obj.voxel).to(weights))
    return Cubature(index, weights, mass_volumes)


class PointsStage:
    """Fills the object with points (:func:`object_points`) and carves the hull with the later frames
    (:func:`carve_with_frames`, ``config.points``); writes ``points.pt`` and ``carving.json``."""

    name = "points"
    sections = ("points",)
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        rounds = ctx.config.points.frame_rounds
        return "filling the object with simulation points" + (
            f" (the hull carved with the later frames, {rounds} rounds)" if rounds else "")

    def run(self, ctx: Context, state: State) -> None:
        o = ctx.observed
        carved, carving = carve_with_frames(o.masks_cpu, o.cameras_cpu, o.dt, o.gravity, state.gaussians.to("cpu"),
                                            ctx.config.points, progress=ctx.progress)
        save_torch_atomic({k: v for k, v in asdict(carved).items()}, ctx.path("points.pt"))
        write_json_atomic(ctx.path("carving.json"), carving)

    def load(self, ctx: Context, state: State) -> None:
        state.obj_cpu = ObjectPoints(**torch.load(ctx.path("points.pt"), weights_only=True))
        state.carving = read_json(ctx.path("carving.json"), "the carving record")
        state.log["carving"] = state.carving
        state.obj = replace(state.obj_cpu, **{k: getattr(state.obj_cpu, k).to(ctx.device) for k in
                                              ("points", "contact_points", "contact_areas", "centre")})
        sim = ctx.config.simulator
        state.cubature = simulation_cubature(state.obj, sim.cubature, sim.mass, ctx.config.seed, sim.cubature_weights)
