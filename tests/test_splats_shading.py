"""Shading of Gaussians under a world-fixed light (vid2sim.splats.shading)."""

import math

import pytest
import torch

from vid2sim.splats.deform import deform_gaussians
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.sh import eval_sh
from vid2sim.splats.shading import Shading, cofactor, outward_normals, scale_sh_colour


def _rotation(axis, angle):
    a = torch.as_tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    K = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def test_cofactor_is_det_times_inverse_transpose_and_carries_face_normals():
    g = torch.Generator().manual_seed(0)
    F = torch.eye(3, dtype=torch.float64) + 0.4 * torch.randn(20, 3, 3, generator=g, dtype=torch.float64)
    want = torch.linalg.det(F)[:, None, None] * torch.linalg.inv(F).transpose(1, 2)
    assert torch.allclose(cofactor(F), want, atol=1e-12)
    # Nanson: a face spanned by t1, t2 (normal N = t1 x t2) is spanned by F t1, F t2 after the deformation
    t1 = torch.randn(20, 3, generator=g, dtype=torch.float64)
    t2 = torch.randn(20, 3, generator=g, dtype=torch.float64)
    N = torch.linalg.cross(t1, t2)
    deformed = torch.linalg.cross((F @ t1[..., None])[..., 0], (F @ t2[..., None])[..., 0])
    assert torch.allclose((cofactor(F) @ N[..., None])[..., 0], deformed, atol=1e-12)


def test_scaled_sh_coefficients_scale_the_3dgs_colour_in_every_direction():
    g = torch.Generator().manual_seed(1)
    sh = 0.3 * torch.randn(50, 9, 3, generator=g, dtype=torch.float64)
    sh[:, 0] += 1.0  # colours well above 0, where the renderer's clamp does not act
    factor = 0.2 + torch.rand(50, generator=g, dtype=torch.float64)
    dirs = torch.randn(50, 3, generator=g, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    before, after = eval_sh(2, sh, dirs), eval_sh(2, scale_sh_colour(sh, factor), dirs)
    assert bool((before > 0).all())
    assert torch.allclose(after, factor[:, None] * before, atol=1e-12)


def test_lambert_factor_turns_with_the_body_and_unshade_inverts_shade():
    normals = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]], dtype=torch.float64)
    light = [0.0, 0.0, 3.0]
    s = Shading.create(normals, light, 0.25)
    assert float(s.ambient) == pytest.approx(0.25)
    assert s.factor().tolist() == pytest.approx([1.0, 0.25, 0.25])  # lit, grazing, facing away
    R = _rotation([0.0, 1.0, 0.0], -math.pi / 3)  # the body turns 60 degrees about y
    turned = s.factor(R.expand(3, 3, 3))
    assert turned.tolist() == pytest.approx([0.25 + 0.75 * 0.5, 0.25 + 0.75 * math.cos(math.pi / 6), 0.25])
    # a uniform stretch does not change normals
    assert torch.allclose(s.factor(2.0 * torch.eye(3, dtype=torch.float64).expand(3, 3, 3)), s.factor())
    sh = torch.rand(3, 4, 3, dtype=torch.float64)
    assert torch.allclose(s.unshade(s.shade(sh)), sh, atol=1e-12)
    with pytest.raises(ValueError, match="ambient"):
        Shading.create(normals, light, 1.0)
    with pytest.raises(ValueError, match="light"):
        Shading.create(normals, [0.0, 0.0, 0.0], 0.5)
    with pytest.raises(ValueError, match="normals"):
        s.shade(torch.rand(4, 1, 3, dtype=torch.float64))


def test_outward_normals_of_a_ball_point_radially_out():
    g = torch.Generator().manual_seed(2)
    pts = 2 * torch.rand(20000, 3, generator=g, dtype=torch.float64) - 1
    interior = pts[pts.norm(dim=1) < 0.5]
    dirs = torch.randn(200, 3, generator=g, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    spacing = (4 / 3 * math.pi * 0.5 ** 3 / interior.shape[0]) ** (1 / 3)
    n = outward_normals(0.48 * dirs, interior, 2 * spacing)
    cos = (n * dirs).sum(1)
    assert torch.allclose(n.norm(dim=1), torch.ones(200, dtype=torch.float64))
    assert float(cos.min()) > math.cos(math.radians(20)) and float(cos.mean()) > math.cos(math.radians(6))
    with pytest.raises(ValueError, match="bandwidth"):
        outward_normals(dirs, interior, 0.0)


def test_the_light_and_ambient_share_are_recovered_from_a_turning_body():
    """Colours of a turning ball under an unknown light pin the light down: gradient descent from a light straight
    above and ambient 0.5 finds the true direction and share (the albedos are known here)."""
    g = torch.Generator().manual_seed(3)
    normals = torch.randn(300, 3, generator=g, dtype=torch.float64)
    truth = Shading.create(normals, [0.35, 0.25, 1.0], 0.3)
    turns = [_rotation([1.0, 0.3, 0.0], a).expand(300, 3, 3) for a in (0.0, 0.7, 1.5, 2.4)]
    seen = [truth.factor(R) for R in turns]
    start = Shading.create(normals, [0.0, 0.0, 1.0], 0.5)
    light = start.light.clone().requires_grad_(True)
    logit = start.ambient_logit.clone().requires_grad_(True)
    opt = torch.optim.Adam([light, logit], lr=0.02)
    for _ in range(600):
        s = Shading(normals, light, logit)
        loss = sum(((s.factor(R) - c) ** 2).mean() for R, c in zip(turns, seen))
        opt.zero_grad()
        loss.backward()
        opt.step()
    fitted = Shading(normals, light.detach(), logit.detach())
    want = torch.tensor([0.35, 0.25, 1.0], dtype=torch.float64)
    assert float(fitted.ambient) == pytest.approx(0.3, abs=1e-3)
    assert float((fitted.light / fitted.light.norm()) @ (want / want.norm())) > math.cos(math.radians(0.5))


def test_deform_gaussians_lights_albedos_by_the_deformed_normals():
    n = 4
    g = Gaussians.from_values(torch.zeros(n, 3, dtype=torch.float64), 0.1 * torch.ones(n, dtype=torch.float64),
                              torch.full((n, 3), 0.6, dtype=torch.float64), torch.full((n,), 0.9, dtype=torch.float64))
    normals = torch.tensor([[0.0, 0.0, 1.0]] * n, dtype=torch.float64)
    s = Shading.create(normals, [0.0, 0.0, 1.0], 0.2)
    R = _rotation([1.0, 0.0, 0.0], math.pi / 2).expand(n, 3, 3).contiguous()
    rest = deform_gaussians(g, g.means, torch.eye(3, dtype=torch.float64).expand(n, 3, 3).contiguous(), s)
    side = deform_gaussians(g, g.means, R, s)
    rgb = lambda d: eval_sh(0, d.sh, torch.ones(n, 3, dtype=torch.float64))
    assert torch.allclose(rgb(rest), torch.full((n, 3), 0.6, dtype=torch.float64))
    assert torch.allclose(rgb(side), torch.full((n, 3), 0.6 * 0.2, dtype=torch.float64))
    assert torch.equal(deform_gaussians(g, g.means, R).sh, g.sh)  # no shading: colours as stored
