"""The floor and sphere obstacles drawn as Gaussians by `vid2sim simulate`: on their surfaces, following a
moving floor, and visible in the frames (but not in the PLY files)."""

import math

import numpy as np
import pytest
import torch

from vid2sim.physics.external import Floor, Gravity, MovingFloor, SphereObstacle
from vid2sim.simulate.scenery import floor_patch, scenery_gaussians, sphere_shell
from vid2sim.splats.sh import C0


def test_floor_discs_lie_flat_on_the_plane_in_two_greys():
    d = floor_patch((0.0, 0.0, 1.0), (0.0, 0.0, -0.7), (0.3, -0.2), 0.5, cells=4, per_cell=3)
    assert d.num == 12 * 12
    assert torch.allclose(d.means[:, 2], torch.full((d.num,), -0.7))
    assert float(d.means[:, 0].mean()) == pytest.approx(0.3, abs=1e-6)
    evals = torch.linalg.eigvalsh(d.covars.double())
    assert torch.allclose(evals[:, 0] * 400, evals[:, 2], rtol=1e-4)  # thin along the normal (1/20 the radius)
    colours = (d.sh[:, 0] * C0 + 0.5).unique(dim=0)
    assert colours.shape[0] == 2


def test_a_tilted_moving_floor_is_drawn_where_the_physics_puts_it():
    floor = MovingFloor(height=-0.5, velocity=0.2, tilt_deg=10.0, tilt_rate_deg=20.0, tilt_axis=(1.0, 0.0, 0.0))
    t = 0.4
    d = scenery_gaussians([Gravity(), floor], t, (0.1, 0.0), 0.4)
    assert d is not None
    dist = floor.signed_distance(d.means.double(), t)
    assert float(dist.abs().max()) < 1e-5  # every disc on the plane at time t
    n = torch.tensor(floor.normal_at(t), dtype=torch.float64)
    smallest = torch.linalg.eigh(d.covars.double()).eigenvectors[:, :, 0]
    assert torch.allclose((smallest @ n).abs(), torch.ones(d.num, dtype=torch.float64), atol=1e-5)


def test_sphere_shell_sits_on_the_obstacle_and_nothing_is_drawn_without_contact_surfaces():
    d = sphere_shell((0.1, 0.2, -0.3), 0.25, count=200)
    r = (d.means.double() - torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)).norm(dim=1)
    assert torch.allclose(r, torch.full_like(r, 0.25), atol=1e-6)
    both = scenery_gaussians([Floor(-0.7), SphereObstacle((0.0, 0.0, -0.5), 0.2)], 0.0, (0.0, 0.0), 0.3, sh_bases=16)
    assert both.sh.shape[1:] == (16, 3) and bool((both.sh[:, 1:] == 0).all())
    assert scenery_gaussians([Gravity()], 0.0, (0.0, 0.0), 0.3) is None
    assert math.isclose(float(both.opacities.max()), 0.97, rel_tol=1e-6)


def test_simulate_draws_the_floor_in_the_frames_but_not_in_the_ply_files(tiny_asset, tmp_path):
    from PIL import Image

    from vid2sim.simulate.run import simulate
    from vid2sim.simulate.scenario import Scenario
    from vid2sim.splats.ply import load_ply

    def run(name, scenery):
        s = Scenario(frames=2)
        s.cameras.type, s.cameras.views, s.resolution = "ring", 1, 32
        return simulate(tiny_asset, s, tmp_path / name, progress=False, video=False, scenery=scenery)

    plain, drawn = run("plain", False), run("drawn", True)
    a = np.asarray(Image.open(plain / "frames" / "ring_00" / "0000.png")).astype(float)
    b = np.asarray(Image.open(drawn / "frames" / "ring_00" / "0000.png")).astype(float)
    assert (np.abs(a - b).max(-1) > 20).mean() > 0.1  # the floor covers a good part of the picture
    assert torch.equal(load_ply(plain / "ply" / "0000.ply").means, load_ply(drawn / "ply" / "0000.ply").means)
