"""The hull track (vid2sim.reconstruct.hull_track) and the joint fit's track term that uses it."""

import pytest
import torch
from test_joint_gauss_newton import _own_motion
from test_pipeline_joint import _ellipsoid_points, _masks_of

from vid2sim.asset.motion import GaussianRig, simulated_centre_of_mass
from vid2sim.reconstruct.clip import Observations
from vid2sim.reconstruct.config import JointConfig
from vid2sim.reconstruct.hull_track import HullTrack, hull_track
from vid2sim.reconstruct.stages.joint import ClipResiduals, joint_optimisation, set_floor_friction
from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.cameras import camera_ring


def test_the_hull_track_follows_a_moving_body_and_names_a_frame_without_a_hull():
    """An ellipsoid moved by known translations, seen by 6 views at 64²: each frame's hull centroid moves with it
    to within a quarter of a pixel (a pixel is 17 mm there; 4.1 mm measured) and its hull keeps its volume, which
    holds more than the ellipsoid's; a frame whose masks are empty is named."""
    points = _ellipsoid_points(40000)
    cams = camera_ring(6, 1.5, 25.0, 64, 64, fov_x_deg=40.0)
    moves = torch.tensor([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [0.04, 0.03, -0.02], [-0.03, 0.01, 0.02]])
    masks = torch.stack([_masks_of(points + d, cams, radius_px=1) for d in moves], dim=1)  # (V, T, H, W)
    track = hull_track(masks, cams, resolution=48)
    centroids = track.centroids
    assert centroids.shape == (4, 3) and centroids.dtype == torch.float64
    assert torch.allclose(centroids - centroids[0], (moves - moves[0]).double(), atol=5e-3)
    assert float(centroids[0].norm()) < 0.02  # the hull of a symmetric body is centred on it
    ellipsoid = 4 / 3 * torch.pi * 0.2 * 0.14 * 0.1
    assert bool((track.volumes > ellipsoid).all()) and float(track.volumes.max() / track.volumes.min()) < 1.05
    masks[:, 2] = 0.0
    with pytest.raises(ValueError, match="frame 2"):
        hull_track(masks, cams, resolution=48)
    with pytest.raises(ValueError, match="shape"):
        hull_track(masks[:, 0], cams)


def test_a_frame_whose_hull_changed_its_volume_gets_a_wider_standard_deviation():
    track = HullTrack(torch.zeros(4, 3, dtype=torch.float64), torch.tensor([1.0, 1.02, 0.85, 1.3], dtype=torch.float64))
    assert track.frame_sd(0.01, 0.05).tolist() == pytest.approx([0.01, 0.03, 0.06])  # within 5 %: kept; 15 %: ×3
    assert track.frame_sd(0.01, None).tolist() == [0.01] * 3


def test_the_track_residuals_vanish_on_the_models_own_centre_of_mass_and_ignore_a_constant_offset():
    """The model's own drop: its centre of mass as the track gives zero residuals at the true θ whatever constant
    offset the track carries (a hull centroid's bias), and residuals of (displacement error) / σ elsewhere."""
    sim, gaussians, cams, images = _own_motion(5, 4.6, 0.3, 0.05, [0.3, 0.0, -1.0], [0.0, 0.5, 0.0])
    names = ["log10_E", "nu"] + [f"linear_velocity_{a}" for a in "xyz"] + [f"angular_velocity_{a}" for a in "xyz"]
    theta = [4.6, 0.3, 0.3, 0.0, -1.0, 0.0, 0.5, 0.0]
    rig, obs = GaussianRig(sim, gaussians), Observations(images, cams)
    plain = ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], 4.0, names)
    truth = simulated_centre_of_mass(sim, plain.simulate(theta)).cpu()
    assert plain.track_residuals([plain.simulate(theta)]) is None
    clip = ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], 4.0, names, truth + torch.tensor([0.01, -0.02, 0.005]),
                         0.002)
    at_truth = clip.track_residuals([clip.simulate(theta)])
    assert at_truth.shape == (1, 12) and float(at_truth.abs().max()) < 1e-9
    faster = list(theta)
    faster[2] += 0.1  # 0.1 m/s more along x: the displacement at frame t is off by 0.1 t Δt along x
    off = clip.track_residuals([clip.simulate(faster)])[0].reshape(4, 3)
    dt = float(sim.config.dt)
    assert torch.allclose(off[:, 0], torch.tensor([0.1 * t * dt / 0.002 for t in range(1, 5)], dtype=torch.float64),
                          rtol=0.05)
    per_frame = ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], 4.0, names, truth,
                              torch.tensor([0.002, 0.004, 0.002, 0.001], dtype=torch.float64))
    widened = per_frame.track_residuals([per_frame.simulate(faster)])[0].reshape(4, 3)
    assert torch.allclose(widened[:, 0] * torch.tensor([2.0, 4.0, 2.0, 1.0], dtype=torch.float64), off[:, 0] * 2.0)
    with pytest.raises(ValueError, match="track"):
        ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], 4.0, names, truth[:3], 0.002)
    with pytest.raises(ValueError, match="track"):
        ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], 4.0, names, truth, torch.ones(3, dtype=torch.float64))
    with pytest.raises(ConfigError, match="track_sd"):
        JointConfig(track_sd=0.0)
    with pytest.raises(ConfigError, match="track_volume_tolerance"):
        JointConfig(track_volume_tolerance=-1.0)


@pytest.mark.slow
def test_a_track_with_an_offset_recovers_the_floors_friction_and_the_displacements():
    """The model's own sliding drop (μ = 0.6) with its centre of mass, offset by 1–2 cm, as the track (σ = 1 mm
    for a 0.5 m body): from the prior μ = 0.2 the fit recovers μ and ends within a millimetre of the track's
    displacements, and records the track."""
    sim, gaussians, cams, images = _own_motion(7, 4.8, 0.3, 0.05, [1.2, 0.0, -1.0], [0.0, 0.0, 0.0], friction=0.6)
    start = sim.rigid_velocity_state([1.2, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with torch.no_grad():
        truth = simulated_centre_of_mass(sim, [start] + sim.rollout(start, 6)).cpu()
    set_floor_friction(sim, 0.2)
    cfg = JointConfig(method="gauss_newton", fit_friction=True, coarse_log10_E=(), coarse_scale=1.0,
                      gauss_newton_iterations=5, track_sd=0.002)
    result = joint_optimisation(sim, gaussians, Observations(images, cams), [1.2, 0.0, -1.0], [0.0, 0.0, 0.0],
                                [0.0, 0.0, 0.0], cfg, progress=False,
                                track=HullTrack(truth + torch.tensor([0.01, -0.02, 0.015], dtype=torch.float64),
                                                torch.ones(7, dtype=torch.float64)))
    assert abs(result.floor_friction - 0.6) < 0.03
    assert result.track["sd"] == pytest.approx(0.002 * sim.length_scale)
    assert len(result.track["hull_centroids"]) == 7 and max(result.track["displacement_error"]) < 1e-3
    assert result.track["frame_sd"] == pytest.approx([0.002 * sim.length_scale] * 6)
    assert result.log[-1]["track_loss"] < result.log[0]["track_loss"]
    with pytest.raises(ValueError, match="track_sd"):
        joint_optimisation(sim, gaussians, Observations(images, cams), [1.2, 0.0, -1.0], [0.0, 0.0, 0.0],
                           [0.0, 0.0, 0.0], JointConfig(coarse_log10_E=()), progress=False,
                           track=HullTrack(truth, torch.ones(7, dtype=torch.float64)))
