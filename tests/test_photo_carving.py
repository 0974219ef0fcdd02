"""Photo-consistency carving (:mod:`vid2sim.reconstruct.photo_carving`) on a ray-traced textured sphere: the
visual hull of six cameras around it is larger than the sphere where no silhouette is tangent to it; the colours
carve part of that excess without eating into the sphere, and a solid that is already right is left alone."""

from __future__ import annotations

import math

import pytest
import torch

from vid2sim.reconstruct.photo_carving import photo_carve
from vid2sim.splats.cameras import camera_sphere, stack_cameras
from vid2sim.splats.visual_hull import visual_hull

RADIUS, CENTRE = 0.3, torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)


def _texture(p: torch.Tensor) -> torch.Tensor:
    """A view-independent colour (N, 3) in [0.05, 0.95] of surface points p (N, 3): stripes of a few cm in three
    directions, one per channel."""
    k = 2 * math.pi / 0.4
    dirs = torch.tensor([[1.0, 0.3, 0.2], [-0.2, 1.0, 0.5], [0.4, -0.3, 1.0]], dtype=p.dtype)
    return 0.5 + 0.45 * torch.sin(k * p @ dirs.T)


def _render(cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray-traced images (V, H, W, 3) on white and masks (V, H, W) of the textured sphere."""
    viewmats, Ks, W, H = stack_cameras(cameras)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                          indexing="ij")
    images, masks = [], []
    for vm, K in zip(viewmats.double(), Ks.double()):
        R, t = vm[:3, :3], vm[:3, 3]
        origin = -R.T @ t
        d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
        d = d_cam.reshape(-1, 3) @ R
        d = d / d.norm(dim=1, keepdim=True)
        oc = origin - CENTRE
        b = d @ oc
        disc = b * b - (oc @ oc - RADIUS ** 2)
        hit = disc > 0
        s = -b - disc.clamp_min(0).sqrt()
        colour = torch.ones(len(d), 3, dtype=torch.float64)
        colour[hit] = _texture(origin + s[hit, None] * d[hit])
        images.append(colour.reshape(H, W, 3))
        masks.append(hit.reshape(H, W).double())
    return torch.stack(images).float(), torch.stack(masks).float()


def _sphere_voxels(shape, origin: torch.Tensor, voxel: float) -> torch.Tensor:
    idx = torch.nonzero(torch.ones(shape, dtype=torch.bool)).double()
    centres = origin.double() + (idx + 0.5) * voxel
    return ((centres - CENTRE).norm(dim=1) <= RADIUS).reshape(shape)


def _centre(occ: torch.Tensor, origin: torch.Tensor, voxel: float) -> torch.Tensor:
    return origin.double() + (torch.nonzero(occ).double().mean(0) + 0.5) * voxel


@pytest.fixture(scope="module")
def sphere_scene():
    cameras = camera_sphere(6, 1.5, 128, 128, fov_x_deg=40.0)
    images, masks = _render(cameras)
    occ, origin, voxel = visual_hull(masks, cameras, 48, 24)
    return cameras, images, masks, occ, origin, voxel, _sphere_voxels(occ.shape, origin, voxel)


def test_the_colours_carve_the_hulls_cap_and_spare_the_sphere(sphere_scene):
    cameras, images, masks, hull, origin, voxel, truth = sphere_scene
    excess = int((hull & ~truth).sum())
    assert excess > 0.04 * int(truth.sum())  # six silhouettes leave the hull about 5 % too large
    result = photo_carve(hull, origin, voxel, images, masks, cameras, threshold=0.05, rounds=30)
    carved = result.occupancy
    assert result.start_voxels == int(hull.sum()) and result.end_voxels == int(carved.sum())
    assert not bool((carved & ~hull).any())  # carving only removes
    # part of the excess goes (the rest is seen by fewer than two views, or too thin for the colours to differ) ...
    assert int((carved & ~truth).sum()) < 0.9 * excess
    # ... and the sphere stays: at most 1 % of its voxels lost
    assert int((truth & ~carved).sum()) <= 0.01 * int(truth.sum())
    # the centre of mass moves toward the sphere's
    before = (_centre(hull, origin, voxel) - CENTRE).norm()
    after = (_centre(carved, origin, voxel) - CENTRE).norm()
    assert after < before
    assert result.rounds[-1]["carved"] == 0 and all(r["compared"] > 0 for r in result.rounds)


def test_a_solid_that_is_right_is_left_alone_and_the_guard_stops_a_runaway(sphere_scene):
    cameras, images, masks, hull, origin, voxel, truth = sphere_scene
    kept = photo_carve(truth, origin, voxel, images, masks, cameras, threshold=0.05)
    assert int(truth.sum()) - kept.end_voxels <= 0.01 * int(truth.sum())
    # a threshold below any colour noise would carve on and on: the guard refuses the round that crosses the limit
    runaway = photo_carve(hull, origin, voxel, images, masks, cameras, threshold=1e-4, rounds=50, max_fraction=0.1)
    assert runaway.start_voxels - runaway.end_voxels <= 0.1 * runaway.start_voxels
    assert runaway.rounds[-1].get("refused") is True


def test_bad_settings_and_shapes_are_errors(sphere_scene):
    cameras, images, masks, hull, origin, voxel, _ = sphere_scene
    with pytest.raises(ValueError, match="images must be"):
        photo_carve(hull, origin, voxel, images[:3], masks, cameras, threshold=0.1)
    with pytest.raises(ValueError, match="threshold must be > 0"):
        photo_carve(hull, origin, voxel, images, masks, cameras, threshold=0.0)
    with pytest.raises(ValueError, match="min_views >= 2"):
        photo_carve(hull, origin, voxel, images, masks, cameras, threshold=0.1, min_views=1)
