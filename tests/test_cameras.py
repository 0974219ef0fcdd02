"""Camera conventions: OpenCV inside, NeRF/Blender on disk; known points land on known pixels."""

import math

import pytest
import torch

from vid2sim.splats.cameras import (
    Camera,
    camera_ring,
    camera_sphere,
    look_at,
    stack_cameras,
)


def _cam(eye, target=(0.0, 0.0, 0.0), f=100.0, w=128, h=96):
    return Camera(look_at(torch.tensor(eye), torch.tensor(target)), Camera.intrinsics(f, f, w / 2, h / 2), w, h)


def test_known_point_projects_to_known_pixel():
    # camera on +x looking at the origin, z up: image x (right) is world +y, image y (down) is world −z
    cam = _cam((2.0, 0.0, 0.0))
    pix, z = cam.project(torch.tensor([[0.0, 0.5, 0.25], [0.0, 0.0, 0.0]]))
    assert torch.allclose(z, torch.tensor([2.0, 2.0]), atol=1e-6)
    assert torch.allclose(pix[0], torch.tensor([64 + 100 * 0.5 / 2, 48 - 100 * 0.25 / 2]), atol=1e-4)
    assert torch.allclose(pix[1], torch.tensor([64.0, 48.0]), atol=1e-5)
    assert torch.allclose(cam.center, torch.tensor([2.0, 0.0, 0.0]), atol=1e-6)


def test_nerf_convention_blender_camera():
    # Blender/NeRF camera at z = 5 with identity rotation looks down −z with +y up in the image
    c2w = torch.eye(4)
    c2w[2, 3] = 5.0
    K = Camera.intrinsics(200.0, 200.0, 50.0, 40.0)
    cam = Camera.from_nerf(c2w, K, 100, 80)
    pix, z = cam.project(torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert torch.allclose(z, torch.full((3,), 5.0), atol=1e-6)
    assert torch.allclose(pix[0], torch.tensor([50.0, 40.0]), atol=1e-4)
    assert torch.allclose(pix[1], torch.tensor([50.0 + 200.0 / 5, 40.0]), atol=1e-4)  # world +x → image right
    assert torch.allclose(pix[2], torch.tensor([50.0, 40.0 - 200.0 / 5]), atol=1e-4)  # world +y → image up
    assert torch.allclose(cam.to_nerf().float(), c2w, atol=1e-6)


def test_nerf_round_trip_random_cameras():
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        eye = torch.randn(3, generator=g) * 3
        cam = _cam(tuple(eye.tolist()), target=tuple((0.1 * torch.randn(3, generator=g)).tolist()))
        back = Camera.from_nerf(cam.to_nerf(), cam.K, cam.width, cam.height)
        assert torch.allclose(back.world_to_camera, cam.world_to_camera, atol=1e-5)
        pts = torch.randn(10, 3, generator=g)
        assert torch.allclose(back.project(pts)[0], cam.project(pts)[0], atol=1e-3)
    assert math.isclose(cam.camera_angle_x, 2 * math.atan(64 / 100), rel_tol=1e-6)


def test_camera_ring_geometry():
    cams = camera_ring(6, 3.0, 30.0, 64, 48, fov_x_deg=50.0, target=(0.1, -0.2, 0.3))
    target = torch.tensor([[0.1, -0.2, 0.3]])
    for c in cams:
        pix, z = c.project(target)
        assert torch.allclose(pix[0], torch.tensor([32.0, 24.0]), atol=1e-4)
        assert math.isclose(float(z[0]), 3.0, rel_tol=1e-5)
        assert math.isclose(float(c.center[2] - 0.3), 3.0 * math.sin(math.radians(30.0)), rel_tol=1e-5)
        assert math.isclose(c.camera_angle_x, math.radians(50.0), rel_tol=1e-5)
        # world up (+z) points up in the image: a point above the target has a smaller row
        above = c.project(target + torch.tensor([[0.0, 0.0, 0.1]]))[0]
        assert above[0, 1] < 24.0
    azimuths = [math.atan2(float(c.center[1] + 0.2), float(c.center[0] - 0.1)) for c in cams]
    gaps = sorted((b - a) % (2 * math.pi) for a, b in zip(azimuths, azimuths[1:] + azimuths[:1]))
    assert all(math.isclose(gp, 2 * math.pi / 6, rel_tol=1e-4) for gp in gaps)


def test_camera_sphere_spread():
    cams = camera_sphere(20, 2.5, 32, 32, min_elevation_deg=-30, max_elevation_deg=60)
    centres = torch.stack([c.center for c in cams])
    assert torch.allclose(centres.norm(dim=1), torch.full((20,), 2.5), atol=1e-5)
    elev = torch.rad2deg(torch.asin(centres[:, 2] / 2.5))
    assert float(elev.min()) >= -30 - 1e-3 and float(elev.max()) <= 60 + 1e-3
    d = torch.cdist(centres, centres) + torch.eye(20) * 10
    assert float(d.min()) > 0.5  # no two cameras bunched together
    for c in cams:
        assert torch.allclose(c.project(torch.zeros(1, 3))[0], torch.tensor([[16.0, 16.0]]), atol=1e-4)


def test_resized_scales_pixel_coordinates():
    cam = _cam((1.5, -2.0, 0.7))
    small = cam.resized(64, 48)
    pts = torch.randn(7, 3) * 0.3
    assert torch.allclose(small.project(pts)[0], cam.project(pts)[0] * 0.5, atol=1e-4)


def test_stack_cameras_and_errors():
    cams = camera_ring(3, 2.0, 10.0, 40, 30)
    viewmats, Ks, w, h = stack_cameras(cams)
    assert viewmats.shape == (3, 4, 4) and Ks.shape == (3, 3, 3) and (w, h) == (40, 30)
    with pytest.raises(ValueError, match="share an image size"):
        stack_cameras([cams[0], cams[1].resized(20, 15)])
    with pytest.raises(ValueError, match="at least one"):
        stack_cameras([])
    with pytest.raises(ValueError, match="rigid"):
        Camera(torch.eye(4) * 2, Camera.intrinsics(1, 1, 1, 1), 4, 4)
    with pytest.raises(ValueError, match="focal"):
        Camera(torch.eye(4), Camera.intrinsics(-1, 1, 1, 1), 4, 4)
    with pytest.raises(ValueError, match="parallel"):
        look_at(torch.tensor([0.0, 0.0, 2.0]), torch.zeros(3))
    with pytest.raises(ValueError):
        camera_sphere(0, 1.0, 8, 8)
