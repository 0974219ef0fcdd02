"""Deforming Gaussians by (x, F): covariance algebra, rigid-motion invariance of the images, gradients."""

import pytest
import torch

from vid2sim.splats.cameras import Camera, camera_ring
from vid2sim.splats.deform import deform_gaussians
from vid2sim.splats.gaussians import Gaussians, quat_to_rotmat
from vid2sim.splats.render import render, render_gaussians

F64 = torch.float64


def _gaussians(n=30, seed=0, degree=0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 0.8
    gs = Gaussians.from_values(
        means,
        torch.rand(n, 3, generator=g, dtype=F64) * 0.08 + 0.03,
        torch.rand(n, 3, generator=g, dtype=F64),
        torch.rand(n, generator=g, dtype=F64) * 0.8 + 0.1,
        quats=torch.randn(n, 4, generator=g, dtype=F64),
        sh_degree=degree,
    )
    return gs


def test_identity_deformation_changes_nothing():
    g = _gaussians()
    d = deform_gaussians(g, g.means, torch.eye(3, dtype=F64).expand(g.num, 3, 3))
    assert torch.allclose(d.covars, g.covariances(), atol=1e-15)
    cams = camera_ring(2, 2.5, 15.0, 24, 20)
    assert torch.allclose(render_gaussians(d, cams).rgb, render_gaussians(g, cams).rgb, atol=1e-12)


def test_stretch_of_isotropic_gaussian_is_analytic():
    g = Gaussians.from_values(torch.zeros(1, 3, dtype=F64), torch.full((1,), 0.1, dtype=F64),
                              torch.ones(1, 3, dtype=F64), torch.full((1,), 0.5, dtype=F64))
    F = torch.tensor([[[2.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.5]]], dtype=F64)
    d = deform_gaussians(g, torch.zeros(1, 3, dtype=F64), F)
    assert torch.allclose(d.covars[0], 0.01 * F[0] @ F[0].T, atol=1e-15)
    back = d.to_gaussians()
    assert torch.allclose(back.covariances(), d.covars, atol=1e-12)


def test_rigid_motion_moves_the_image_with_the_camera():
    # deforming by a rotation R0 and translation t and moving the camera the same way renders the same image
    g = _gaussians(40, seed=1)
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    q = torch.cat([torch.tensor([0.8], dtype=F64), 0.6 * axis / axis.norm()])
    R0 = quat_to_rotmat(q)
    t = torch.tensor([0.2, -0.1, 0.3], dtype=F64)
    x = g.means @ R0.T + t
    d = deform_gaussians(g, x, R0.expand(g.num, 3, 3))
    rigid = torch.eye(4, dtype=F64)
    rigid[:3, :3], rigid[:3, 3] = R0, t
    for cam in camera_ring(3, 2.5, 20.0, 30, 26):
        moved = Camera((cam.world_to_camera.to(F64) @ torch.linalg.inv(rigid)).float(), cam.K, cam.width, cam.height)
        a = render_gaussians(g, [cam]).rgb
        b = render_gaussians(d, [moved]).rgb
        assert float((a - b).abs().max()) < 2e-5  # the camera is stored in float32


def test_gradients_flow_to_positions_and_deformation_gradients():
    g = _gaussians(5, seed=2)
    cam = camera_ring(1, 2.0, 20.0, 12, 10, fov_x_deg=35.0)
    w = torch.randn(1, 10, 12, 3, generator=torch.Generator().manual_seed(0), dtype=F64)

    def f(x, F):
        d = deform_gaussians(g, x, F)
        return (render_gaussians(d, cam, background=0.3).rgb * w).sum()

    x = (g.means + 0.01).requires_grad_()
    F = (
        torch.eye(3, dtype=F64) + 0.1 * torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    ).requires_grad_()
    assert torch.autograd.gradcheck(f, (x, F), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)
    gx, gF = torch.autograd.grad(f(x, F), (x, F))
    assert float(gx.abs().max()) > 0 and float(gF.abs().max()) > 0


def test_deform_validates_shapes():
    g = _gaussians(4)
    with pytest.raises(ValueError, match=r"x must have shape \(4, 3\)"):
        deform_gaussians(g, torch.zeros(3, 3, dtype=F64), torch.eye(3, dtype=F64).expand(4, 3, 3))
    with pytest.raises(ValueError, match="F must have shape"):
        deform_gaussians(g, g.means, torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match="float32"):
        deform_gaussians(g, g.means.float(), torch.eye(3, dtype=F64).expand(4, 3, 3))
    d = deform_gaussians(g, g.means, torch.eye(3, dtype=F64).expand(4, 3, 3))
    out = render(d.means, d.opacities, d.sh, camera_ring(1, 2.0, 0.0, 8, 8), covars=d.covars, sh_degree=0)
    assert out.rgb.shape == (1, 8, 8, 3)
