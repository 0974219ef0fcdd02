"""The Gaussians' surface depth, and the depth carving of the simulation points that uses it."""

import pytest
import torch

from vid2sim.reconstruct.config import PointsConfig
from vid2sim.reconstruct.stages.points import object_points
from vid2sim.splats.cameras import Camera, camera_ring
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.render import render_gaussians
from vid2sim.splats.surface_depth import surface_depth


def _camera() -> Camera:
    """At the origin looking along +z (OpenCV axes), 32² pixels."""
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), K, 32, 32)


def _sheets(depths, opacities) -> Gaussians:
    """One wide flat Gaussian per depth on the optical axis (σ 0.3 m across, 5 mm deep): at the image centre
    each contributes exactly its opacity."""
    n = len(depths)
    means = torch.tensor([[0.0, 0.0, z] for z in depths])
    g = Gaussians.from_values(means, torch.full((n,), 0.3), torch.full((n, 3), 0.5), torch.tensor(opacities))
    return Gaussians(**{**g.__dict__, "log_scales": torch.log(torch.tensor([[0.3, 0.3, 0.005]] * n))})


def test_the_median_depth_is_the_first_surface_that_stops_half_the_light():
    cam = _camera()
    # a semi-opaque front surface (0.7) with an opaque layer 0.3 m behind it: the expected depth mixes them
    front = _sheets([1.0, 1.3], [0.7, 0.95])
    depth, alpha = surface_depth(front, [cam], planes=32)
    assert depth.shape == (1, 32, 32) and alpha.shape == (1, 32, 32)
    assert float(alpha[0, 16, 16]) == pytest.approx(1 - 0.3 * 0.05, abs=2e-3)
    assert float(depth[0, 16, 16]) == pytest.approx(1.0, abs=0.3 / 32)
    expected = float(render_gaussians(front, [cam]).depth[0, 16, 16, 0])
    assert expected == pytest.approx((0.7 * 1.0 + 0.3 * 0.95 * 1.3) / (1 - 0.3 * 0.05), abs=2e-3)  # 8.7 cm deeper
    # a faint floater (0.1) in front of an opaque surface does not count as the surface
    floater = _sheets([1.0, 1.3], [0.1, 0.95])
    depth, _ = surface_depth(floater, [cam], planes=32)
    assert 1.3 - 0.3 / 32 - 1e-6 <= float(depth[0, 16, 16]) <= 1.3 + 1e-6
    # where the Gaussians never stop half the light there is no surface
    faint = _sheets([1.0], [0.3])
    depth, alpha = surface_depth(faint, [cam], planes=8)
    assert torch.isinf(depth).all() and float(alpha.max()) == pytest.approx(0.3, abs=2e-3)
    with pytest.raises(ValueError, match="planes"):
        surface_depth(front, [cam], planes=1)
    with pytest.raises(ValueError, match="opacity"):
        surface_depth(front, [cam], opacity=1.0)
    # a lower level finds the first surface however faint: the floater at 1.0 stops 0.1 of the light
    depth, _ = surface_depth(floater, [cam], planes=32, opacity=0.05)
    assert float(depth[0, 16, 16]) == pytest.approx(1.0, abs=0.3 / 32)


def test_depth_carving_keeps_an_object_whose_surface_gaussians_are_faint():
    """An ellipsoid drawn by faint surface Gaussians (3 000 at opacity 0.03: a layer that stops less than half the
    light) over an opaque core, the way a fit can leave them. Carving the visual hull where the accumulated opacity
    reaches 0.2 (the default) keeps the object's inner 80 %; the median depth (½) passes the faint front layer and
    cuts deep into it, as the expected depth (the renderer's, pulled towards the core) does too."""
    radii = torch.tensor([0.2, 0.14, 0.1])
    g = torch.Generator().manual_seed(0)
    d = torch.randn(3000, 3, generator=g)
    surface = d / d.norm(dim=1, keepdim=True) * radii
    inner = torch.rand(3000, 3, generator=g) * 2 - 1
    inner = inner[(inner ** 2).sum(1) <= 1][:600] * radii * 0.5
    means = torch.cat([surface, inner])
    opacities = torch.cat([torch.full((3000,), 0.03), torch.full((len(inner),), 0.99)])
    gaussians = Gaussians.from_values(means, torch.full((len(means),), 0.012), torch.full((len(means), 3), 0.5),
                                      opacities)
    cams = camera_ring(6, 1.5, 25.0, 64, 64, fov_x_deg=40.0)
    masks = (render_gaussians(gaussians, cams).alpha[..., 0] > 0.5).float()
    probe = torch.rand(20000, 3, generator=g) * 2 - 1
    probe = probe[(probe ** 2).sum(1) <= 0.8 ** 2] * radii

    def kept_share(surface_opacity: float) -> float:
        obj = object_points(masks, cams, gaussians, PointsConfig(resolution=40, num_points=4000,
                                                                 surface_opacity=surface_opacity))
        cell = ((probe - obj.origin) / obj.voxel).floor().long()
        valid = ((cell >= 0) & (cell < torch.tensor(obj.occupancy.shape))).all(1)
        kept = torch.zeros(len(probe), dtype=torch.bool)
        kept[valid] = obj.occupancy[tuple(cell[valid].T)]
        return float(kept.float().mean())

    assert kept_share(0.2) == 1.0
    assert kept_share(0.5) < 0.8  # measured 0.71
    assert PointsConfig().surface_opacity == 0.2
    with pytest.raises(Exception, match="surface_opacity"):
        PointsConfig(surface_opacity=1.0)
