"""Initial Gaussians from object masks: visual hull by space carving, coloured from the images.

A point belongs to the visual hull when it projects inside the object mask in every view (the
object is assumed fully inside every image). The hull is carved on a coarse voxel grid spanning the
region all cameras look at, then again on a finer grid fitted to the coarse hull. Gaussians are
placed on the hull's surface voxels (interior ones could never be seen), with isotropic scales of
about a voxel, and take the mean colour of the views in which the hull itself does not hide them
(each pixel's ray is marched through the voxel grid to its first occupied voxel). This replaces LGM's feed-forward
prediction in Stage I (its weights cannot
be downloaded here); any other initialiser with the same call signature can be used instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import torch
from torch import Tensor

from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.gaussians import Gaussians


class Initializer(Protocol):
    """Anything that turns the first multi-view frame into initial Gaussians."""

    def __call__(
        self,
        images: Tensor,
        masks: Tensor,
        cameras: Sequence[Camera],
        sh_degree: int,
        generator: torch.Generator,
    ) -> Gaussians:
        """images: (V, H, W, 3) in [0, 1]; masks: (V, H, W) in [0, 1]; one camera per view."""
        ...


def project_points(points: Tensor, viewmats: Tensor, Ks: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Integer pixel (V, N) columns and rows, and depths (V, N), of world points (N, 3)."""
    cam = torch.matmul(points, viewmats[:, :3, :3].transpose(1, 2)) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    u = Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]
    big = torch.full_like(u, -1.0)
    u = torch.where(z > 1e-6, u, big)
    v = torch.where(z > 1e-6, v, big)
    return torch.floor(u).long(), torch.floor(v).long(), z


def carve(points: Tensor, masks: Tensor, viewmats: Tensor, Ks: Tensor, threshold: float = 0.5) -> Tensor:
    """(N,) bool: which world points project inside the mask (> threshold) in every view.

    Args:
        points: (N, 3); masks: (V, H, W); viewmats: (V, 4, 4); Ks: (V, 3, 3).
    """
    V, H, W = masks.shape
    col, row, _ = project_points(points, viewmats, Ks)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    flat = (torch.arange(V, device=points.device)[:, None] * H + row.clamp(0, H - 1)) * W + col.clamp(0, W - 1)
    hit = masks.reshape(-1)[flat] > threshold
    return (inside & hit).all(dim=0)


def _axes_meeting_point(viewmats: Tensor) -> Tensor:
    """Least-squares point closest to all optical axes (3,)."""
    R = viewmats[:, :3, :3].double()
    centres = -(R.transpose(1, 2) @ viewmats[:, :3, 3:].double()).squeeze(-1)
    d = R[:, 2, :]  # viewing directions (camera z axes) in world coordinates
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]
    A = proj.sum(0)
    b = (proj @ centres[:, :, None]).sum(0).squeeze(-1)
    return torch.linalg.lstsq(A, b).solution.to(viewmats.dtype)


def _grid(lo: Tensor, hi: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Voxel centres (n³, 3) of the box [lo, hi] and the voxel edge lengths (3,)."""
    step = (hi - lo) / n
    axes = [lo[i] + (torch.arange(n, dtype=lo.dtype, device=lo.device) + 0.5) * step[i] for i in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return pts, step


def visual_hull(
    masks: Tensor,
    cameras: Sequence[Camera],
    resolution: int = 64,
    coarse_resolution: int = 32,
    threshold: float = 0.5,
) -> tuple[Tensor, Tensor, float]:
    """Carve the visual hull of the masked object.

    Returns ``(occupancy (r, r, r) bool, box_min (3,), voxel_size)`` with r = ``resolution``; the
    voxel (i, j, k) is centred at ``box_min + ((i, j, k) + 0.5) · voxel_size`` with cubic voxels.
    Raises ValueError when no point projects inside all masks.
    """
    viewmats, Ks, width, height = stack_cameras(cameras)
    dev = masks.device
    viewmats, Ks = viewmats.to(dev), Ks.to(dev)
    if masks.shape != (len(cameras), height, width):
        raise ValueError(f"masks must have shape (V={len(cameras)}, H={height}, W={width}), got {tuple(masks.shape)}")
    masks = masks.float()
    centre = _axes_meeting_point(viewmats.cpu()).to(dev)
    cam_centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:]).squeeze(-1)
    fov = torch.maximum(width / Ks[:, 0, 0], height / Ks[:, 1, 1])  # 2 tan(half-angle), widest axis
    half = float(((cam_centres - centre).norm(dim=1) * fov * 0.5).max())
    lo, hi = centre - half, centre + half
    for n in (coarse_resolution, resolution):
        pts, step = _grid(lo, hi, n)
        keep = carve(pts, masks, viewmats, Ks, threshold)
        if not bool(keep.any()):
            raise ValueError(
                "visual hull is empty: no point projects inside the masks of all views "
                "(check the masks, that the object is inside every image, and the camera poses)"
            )
        if n == resolution:
            break
        kept = pts[keep]
        pad = step * 1.5
        size = float(((kept.amax(0) + pad) - (kept.amin(0) - pad)).max())
        mid = 0.5 * (kept.amax(0) + kept.amin(0))
        lo, hi = mid - size / 2, mid + size / 2
    occ = keep.reshape(n, n, n)
    return occ, lo, float(step[0])


def surface_voxels(occ: Tensor) -> Tensor:
    """Occupied voxels with at least one empty 6-neighbour (the grid border counts as empty)."""
    p = torch.nn.functional.pad(occ.float()[None, None], (1, 1, 1, 1, 1, 1))[0, 0]
    inner = p[:-2, 1:-1, 1:-1] * p[2:, 1:-1, 1:-1] * p[1:-1, :-2, 1:-1] * p[1:-1, 2:, 1:-1]
    inner = inner * p[1:-1, 1:-1, :-2] * p[1:-1, 1:-1, 2:]
    return occ & (inner == 0)


def hull_depth(occ: Tensor, box_min: Tensor, voxel: float, viewmats: Tensor, Ks: Tensor, width: int, height: int,
               max_samples: int = 1 << 22) -> Tensor:
    """Camera depth (V, H, W) of the first occupied voxel along each pixel-centre ray (inf: none).

    Rays are marched in steps of 0.4 voxel of camera depth through the box of the grid ``occ``
    (r, r, r) whose voxel (i, j, k) is centred at ``box_min + ((i, j, k) + 0.5) · voxel``; at most
    ``max_samples`` ray samples are held at once.
    """
    dev, dt = occ.device, viewmats.dtype
    r = occ.shape[0]
    corners = box_min + voxel * r * torch.tensor(
        [[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=dt, device=dev
    )
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dt, device=dev) + 0.5,
                            torch.arange(width, dtype=dt, device=dev) + 0.5, indexing="ij")
    out = torch.full((viewmats.shape[0], height * width), float("inf"), dtype=dt, device=dev)
    for v in range(viewmats.shape[0]):
        R, t, K = viewmats[v, :3, :3], viewmats[v, :3, 3], Ks[v]
        z_corners = (corners @ R.T + t)[:, 2]
        z0, z1 = max(float(z_corners.min()), 1e-6), float(z_corners.max())
        if z1 <= z0:
            continue
        zs = torch.arange(z0, z1 + 0.4 * voxel, 0.4 * voxel, dtype=dt, device=dev)  # (S,)
        rays = torch.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], torch.ones_like(xs)], -1)
        rays = rays.reshape(-1, 3) @ R  # world offset per unit camera depth (rows of R: camera axes)
        centre = -R.T @ t
        per = max(1, max_samples // zs.numel())
        for a in range(0, rays.shape[0], per):
            pts = centre + rays[a : a + per, None, :] * zs[None, :, None]  # (n, S, 3)
            idx = torch.floor((pts - box_min) / voxel).long()
            inside = ((idx >= 0) & (idx < r)).all(-1)
            idx = idx.clamp(0, r - 1)
            hit = occ[idx[..., 0], idx[..., 1], idx[..., 2]] & inside  # (n, S)
            first = torch.argmax(hit.to(torch.uint8), dim=1)
            depth = zs[first]
            out[v, a : a + per] = torch.where(hit.any(dim=1), depth, torch.full_like(depth, float("inf")))
    return out.reshape(-1, height, width)


def visible_colours(points: Tensor, images: Tensor, viewmats: Tensor, Ks: Tensor, depth: Tensor,
                    tolerance: float) -> Tensor:
    """Mean colour (N, 3) of each point over the views in which it is not hidden.

    A point is visible in a view when its camera depth is at most ``depth`` (V, H, W) at its pixel
    (the first surface along the pixel's ray, :func:`hull_depth`) plus ``tolerance``; points visible
    nowhere get the mean over all views that contain them.
    """
    V, H, W, _ = images.shape
    col, row, z = project_points(points, viewmats, Ks)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    pix = (torch.arange(V, device=points.device)[:, None] * H + row.clamp(0, H - 1)) * W + col.clamp(0, W - 1)
    vis = inside & (z <= depth.reshape(-1)[pix] + tolerance)
    rgb = images.reshape(-1, images.shape[-1])[pix]  # (V, N, 3)
    w = vis.to(images.dtype)
    none = w.sum(0) == 0
    w[:, none] = inside[:, none].to(images.dtype)
    return (rgb * w[..., None]).sum(0) / w.sum(0).clamp_min(1.0)[:, None]


@dataclass
class VisualHullInitializer:
    """Initial Gaussians on the visual hull's surface (see module docstring).

    Attributes:
        num_points: at most this many Gaussians (surface voxels are subsampled when more).
        resolution, coarse_resolution: voxel grids of the two carving passes.
        mask_threshold: mask values above it count as object.
        init_opacity: initial opacity (3DGS starts SfM points at 0.1; hull points already lie on the
            object, so a higher start converges faster).
        scale_factor: initial isotropic scale in voxels.
    """

    num_points: int = 5000
    resolution: int = 64
    coarse_resolution: int = 32
    mask_threshold: float = 0.5
    init_opacity: float = 0.5
    scale_factor: float = 0.75

    def __call__(
        self,
        images: Tensor,
        masks: Tensor,
        cameras: Sequence[Camera],
        sh_degree: int,
        generator: torch.Generator,
    ) -> Gaussians:
        occ, lo, voxel = visual_hull(masks, cameras, self.resolution, self.coarse_resolution, self.mask_threshold)
        surf = surface_voxels(occ)
        idx = torch.nonzero(surf).to(images.dtype)  # (S, 3) voxel indices
        if idx.shape[0] > self.num_points:
            pick = torch.randperm(idx.shape[0], generator=generator)[: self.num_points].to(idx.device)
            idx = idx[pick]
        jitter = (torch.rand(idx.shape, generator=generator, dtype=idx.dtype) - 0.5).to(idx.device) * 0.5
        points = lo.to(images.dtype) + (idx + 0.5 + jitter) * voxel
        viewmats, Ks, width, height = stack_cameras(cameras)
        viewmats, Ks = viewmats.to(images), Ks.to(images)
        depth = hull_depth(occ, lo.to(images), voxel, viewmats, Ks, width, height)
        colours = visible_colours(points, images, viewmats, Ks, depth, tolerance=2.0 * voxel)
        n = points.shape[0]
        return Gaussians.from_values(
            points,
            torch.full((n,), self.scale_factor * voxel, dtype=images.dtype, device=images.device),
            colours.clamp(0.0, 1.0),
            torch.full((n,), self.init_opacity, dtype=images.dtype, device=images.device),
            sh_degree=sh_degree,
        )
