"""Photo-consistency carving of the simulation solid at frame 0 (space carving, Kutulakos and Seitz 2000).

A visual hull is the largest solid that its silhouettes allow: wherever no camera sees the object in profile it
bulges out, and a bulge carries mass in the wrong place (the centre of mass off, the contact point wrong). The
colours tell the bulge from the object: a voxel on the true surface shows the same surface point, so nearly the same
colour, to every camera that sees it, while a voxel of the bulge floats in front of the object and each camera sees
whatever of the object lies behind it along its own ray, in other colours. So, round by round:

1. Take the solid's **surface voxels** (occupied, with a free 6-neighbour).
2. **Visibility**: a surface voxel is seen by a view when the segment from its centre to the camera, marched in
   steps of half a voxel from 1.5 voxels out, meets no occupied voxel, and its centre projects inside the image, on
   a pixel whose 3 × 3 neighbourhood is all inside the view's mask (away from the silhouette's edge, where colours
   mix with the background).
3. **Colour**: each view's image is box-blurred over a voxel's footprint (its side in pixels at the object's
   distance) and sampled bilinearly at the voxel's centre.
4. **Carve** the surface voxels seen by at least ``min_views`` views whose colours spread by more than
   ``threshold``: the root mean square over R, G, B of the colours' standard deviation across those views.

The next round looks at the new surface, which the carved voxels uncovered. It stops when a round carves nothing,
after ``rounds`` rounds, or before a round that would take the solid below ``1 − max_fraction`` of its starting
voxels (that round is not applied): a threshold too low for the scene's shading would otherwise eat into the object.

It needs views around the object: with the small preset's four views (two antipodal pairs) almost no hull voxel is
seen by two of them, so nothing can be compared (docs/results.md, "Photo-consistency does not carve the hull's
excess either"); with the full preset's twelve it can.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor
from torch.nn import functional as Fn

from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.visual_hull import surface_voxels

#: the march along a voxel's ray to its camera: its first sample (voxels out) and its step (voxels)
MARCH_START, MARCH_STEP = 1.5, 0.5


@dataclass
class PhotoCarving:
    """What :func:`photo_carve` did.

    Attributes:
        occupancy: (A, B, C) bool, the carved solid.
        rounds: per round {"surface": surface voxels, "compared": those seen by ``min_views`` views or more,
            "carved": those carved}; a round refused by ``max_fraction`` has "refused": true and carved nothing.
        start_voxels, end_voxels: the solid's voxel counts before and after.
    """

    occupancy: Tensor
    rounds: list[dict[str, Any]]
    start_voxels: int
    end_voxels: int

    def record(self) -> dict[str, Any]:
        """A JSON-ready summary (``carving.json``'s ``photo``)."""
        return {"start_voxels": self.start_voxels, "end_voxels": self.end_voxels, "rounds": self.rounds}


def _visible(occ: Tensor, idx: Tensor, centres: Tensor, camera_centre: Tensor, origin: Tensor,
             voxel: float) -> Tensor:
    """(S,) bool: which surface voxels (indices ``idx`` (S, 3), centres (S, 3)) see ``camera_centre`` (3,) past
    every occupied voxel of ``occ`` (A, B, C)."""
    shape = torch.tensor(occ.shape, device=idx.device)
    to_camera = camera_centre - centres
    distance = to_camera.norm(dim=1, keepdim=True)
    direction = to_camera / distance
    longest = float(math.sqrt(sum(n * n for n in occ.shape))) + 2.0  # no ray needs to go further inside the grid
    steps = torch.arange(MARCH_START, longest, MARCH_STEP, dtype=centres.dtype, device=centres.device) * voxel
    free = torch.ones(len(idx), dtype=torch.bool, device=idx.device)
    flat = occ.reshape(-1)
    strides = torch.tensor([occ.shape[1] * occ.shape[2], occ.shape[2], 1], device=idx.device)
    for chunk in torch.split(steps, 32):
        samples = centres[:, None, :] + chunk[None, :, None] * direction[:, None, :]  # (S, n, 3)
        cell = torch.floor((samples - origin) / voxel).long()
        inside = ((cell >= 0) & (cell < shape)).all(-1) & (chunk[None, :] < distance)
        hit = flat[(cell.clamp_min(0).minimum(shape - 1) * strides).sum(-1)] & inside
        free &= ~hit.any(1)
    return free


def _colours(image: Tensor, mask: Tensor, camera: Camera, centres: Tensor, footprint_px: float,
             mask_threshold: float) -> tuple[Tensor, Tensor]:
    """(S, 3) colours of ``image`` (H, W, 3), box-blurred over ``footprint_px`` pixels, at the projections of
    ``centres`` (S, 3), and (S,) bool: which project inside the image, on a pixel whose 3 × 3 neighbourhood lies in
    ``mask`` (H, W)."""
    H, W = mask.shape
    viewmats, Ks, _, _ = stack_cameras([camera])
    R, t, K = viewmats[0, :3, :3].to(centres), viewmats[0, :3, 3].to(centres), Ks[0].to(centres)
    cam = centres @ R.T + t
    z = cam[:, 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    inside_image = (z > 1e-6) & (u >= 0.5) & (u < W - 0.5) & (v >= 0.5) & (v < H - 0.5)
    solid = -Fn.max_pool2d(-(mask > mask_threshold).float()[None, None], 3, stride=1, padding=1)[0, 0] > 0.5
    ok = inside_image & solid[v.long().clamp(0, H - 1), u.long().clamp(0, W - 1)]
    k = max(1, int(round(footprint_px)))
    k += 1 - k % 2  # odd: centred
    chw = image.permute(2, 0, 1)[None].to(centres.dtype)
    blurred = Fn.avg_pool2d(chw, k, stride=1, padding=k // 2, count_include_pad=False) if k > 1 else chw
    grid = torch.stack([u / W * 2 - 1, v / H * 2 - 1], -1)[None, None]  # pixel centres at +0.5
    colours = Fn.grid_sample(blurred, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return colours[0, :, 0].T, ok


def photo_carve(occupancy: Tensor, origin: Tensor, voxel: float, images: Tensor, masks: Tensor,
                cameras: Sequence[Camera], threshold: float, rounds: int = 12, min_views: int = 2,
                max_fraction: float = 0.25, mask_threshold: float = 0.5) -> PhotoCarving:
    """Carve the surface voxels whose colours the views disagree on (the module docstring).

    Args:
        occupancy: (A, B, C) bool, the solid at the time of ``images``; origin: (3,) the grid's corner (voxel
            (i, j, k) spans origin + [i, i + 1] · voxel, …); voxel: its edge (m).
        images: (V, H, W, 3) colours in [0, 1] of the V ``cameras``; masks: (V, H, W) in [0, 1].
        threshold: the colour spread (RMS over RGB of the standard deviation across views) above which a voxel
            is carved.
        rounds: rounds at most; min_views: views a voxel must be seen by to be judged (>= 2).
        max_fraction: the carving stops before it would remove more than this fraction of the starting voxels.
        mask_threshold: mask values above it count as object.
    Returns:
        :class:`PhotoCarving`.
    Raises:
        ValueError: mismatched shapes or settings out of range.
    """
    V = len(cameras)
    if images.ndim != 4 or images.shape[0] != V or images.shape[-1] != 3 or masks.shape != images.shape[:3]:
        raise ValueError(f"photo_carve: images must be (V={V}, H, W, 3) and masks (V, H, W), got "
                         f"{tuple(images.shape)} and {tuple(masks.shape)}")
    if not (math.isfinite(threshold) and threshold > 0) or rounds < 1 or min_views < 2 or not 0 < max_fraction < 1:
        raise ValueError(f"photo_carve: threshold must be > 0, rounds >= 1, min_views >= 2 and max_fraction in "
                         f"(0, 1), got {threshold}, {rounds}, {min_views}, {max_fraction}")
    dtype = torch.float32
    occ = occupancy.clone().bool().cpu()
    lo = origin.to(dtype).cpu()
    viewmats, Ks, _, _ = stack_cameras(list(cameras))
    viewmats, Ks = viewmats.to(dtype).cpu(), Ks.to(dtype).cpu()
    camera_centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:4])[..., 0]  # (V, 3)
    solid_centre = lo + (torch.nonzero(occ).to(dtype).mean(0) + 0.5) * voxel
    footprints = [float(Ks[i, 0, 0]) * voxel / float((camera_centres[i] - solid_centre).norm()) for i in range(V)]
    start = int(occ.sum())
    record: list[dict[str, Any]] = []
    for _ in range(rounds):
        idx = torch.nonzero(surface_voxels(occ))
        centres = lo + (idx.to(dtype) + 0.5) * voxel
        seen = torch.zeros(V, len(idx), dtype=torch.bool)
        colours = torch.zeros(V, len(idx), 3, dtype=dtype)
        for i in range(V):
            colours[i], in_mask = _colours(images[i].cpu(), masks[i].cpu(), cameras[i], centres, footprints[i],
                                           mask_threshold)
            candidates = torch.nonzero(in_mask)[:, 0]
            seen[i, candidates] = _visible(occ, idx[candidates], centres[candidates], camera_centres[i], lo, voxel)
        count = seen.sum(0)
        judged = count >= min_views
        weight = seen.to(dtype)[..., None]
        mean = (colours * weight).sum(0) / count.clamp_min(1)[:, None]
        variance = (((colours - mean) ** 2) * weight).sum(0) / count.clamp_min(1)[:, None]
        spread = variance.mean(1).sqrt()
        carve = judged & (spread > threshold)
        entry = {"surface": len(idx), "compared": int(judged.sum()), "carved": int(carve.sum())}
        if start - (int(occ.sum()) - int(carve.sum())) > max_fraction * start:
            record.append({**entry, "carved": 0, "refused": True})
            break
        record.append(entry)
        if not bool(carve.any()):
            break
        occ[tuple(idx[carve].T)] = False
    return PhotoCarving(occ, record, start, int(occ.sum()))
