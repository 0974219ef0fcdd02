"""The initial rigid velocity from the ballistic frames (vid2sim.reconstruct.stages.velocity).

Two kinds of data:

* an analytic drop without FEM: two overlapping ellipsoids (no symmetry, so every rotation shows in the
  silhouettes) tumbling torque-free under gravity — the reference motion is integrated by scipy from
  Euler's equations in the body frame, independently of the module's integrator — and rendered exactly
  (ray–ellipsoid tests, 4 × 4 supersampling) by a ring of 4 cameras at 64 × 64 px;
* a real synthetic scene (``make_scene``, small preset, seed 0, 6 frames) against the ground truth in its
  ``scene.json`` metadata.

Measured when written (2 cores): analytic drop |Δv| = 0.001–0.005 m/s and |Δω| = 0.01–0.09 rad/s over five
random motions at 64 and 96 px (8 frames); the small-preset scenes of seeds 0, 1, 2 (5, 3, 3 pre-contact
frames) |Δv| ≤ 0.008 m/s, |Δω| ≤ 0.11 rad/s. The tolerances below leave about a factor of 2–3.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from vid2sim.reconstruct.stages.velocity import (
    InitialVelocity,
    estimate_initial_velocity,
    propagate_rotations,
)
from vid2sim.splats.cameras import camera_ring

pytestmark = pytest.mark.slow  # fits Gaussians / generates synthetic scenes

DT = 0.05
GRAVITY = np.array([0.0, 0.0, -9.8])
# the analytic object in its rest frame: (centre, semi-axes) of two overlapping ellipsoids
ELLIPSOIDS = (((0.0, 0.0, 0.0), (0.35, 0.22, 0.15)), ((0.25, 0.1, 0.08), (0.15, 0.12, 0.10)))
V_TRUE = np.array([0.3, -0.2, 0.0])
W_TRUE = np.array([1.2, -0.8, 1.5])  # |ω| = 2.1 rad/s, not about a principal axis: ω(t) is not constant


def sample_object(n: int, rng: np.random.Generator) -> np.ndarray:
    """n points (n, 3) uniform in the union of the ellipsoids (rest frame)."""
    lo, hi = np.array([-0.36, -0.23, -0.16]), np.array([0.41, 0.23, 0.19])
    found = np.zeros((0, 3))
    while len(found) < n:
        p = rng.uniform(lo, hi, size=(4 * n, 3))
        inside = np.zeros(len(p), bool)
        for c, a in ELLIPSOIDS:
            inside |= (((p - c) / a) ** 2).sum(1) <= 1.0
        found = np.concatenate([found, p[inside]])
    return found[:n]


def inertia_of(points: np.ndarray) -> np.ndarray:
    """(3, 3) inertia tensor per unit mass of equal point masses about their centroid."""
    r = points - points.mean(0)
    return (r * r).sum(1).mean() * np.eye(3) - r.T @ r / len(r)


def torque_free_reference(R0: np.ndarray, omega0: np.ndarray, inertia: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Orientations (K, 3, 3): Euler's equations I_b ω̇_b = (I_b ω_b) × ω_b with Ṙ = R [ω_b]× (scipy DOP853).

    ``inertia`` is the world inertia at orientation R0 and ``omega0`` the world angular velocity at t = 0."""
    I_b = R0.T @ inertia @ R0
    I_inv = np.linalg.inv(I_b)

    def rhs(_: float, y: np.ndarray) -> np.ndarray:
        R, w = y[:9].reshape(3, 3), y[9:]
        skew = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        return np.concatenate([(R @ skew).ravel(), I_inv @ np.cross(I_b @ w, w)])

    sol = solve_ivp(rhs, (0.0, float(times[-1])), np.concatenate([R0.ravel(), R0.T @ omega0]), t_eval=times,
                    method="DOP853", rtol=1e-11, atol=1e-12)
    return sol.y[:9].T.reshape(-1, 3, 3)


def render_masks(cameras, rotations: np.ndarray, centroids: np.ndarray, rest_centroid: np.ndarray,
                 supersample: int = 4) -> torch.Tensor:
    """Anti-aliased masks (V, T, H, W) of the object posed at x = R_t (X − c_rest) + p_t, exactly (rays
    against the ellipsoids at supersample² points per pixel)."""
    res = cameras[0].width
    s = (np.arange(res * supersample) + 0.5) / supersample
    xs, ys = np.meshgrid(s, s)
    out = np.zeros((len(cameras), len(rotations), res, res), np.float32)
    for v, cam in enumerate(cameras):
        w2c, K = cam.world_to_camera.double().numpy(), cam.K.double().numpy()
        origin = -w2c[:3, :3].T @ w2c[:3, 3]
        dirs = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1) @ w2c[:3, :3]
        for t, (R, p) in enumerate(zip(rotations, centroids)):
            hit = np.zeros(xs.shape, bool)
            for c, a in ELLIPSOIDS:
                centre = R @ (np.asarray(c) - rest_centroid) + p
                M = R / np.asarray(a)[None, :]  # unit-sphere coordinates u = diag(1/a) Rᵀ (x − centre)
                o, d = (origin - centre) @ M, dirs @ M
                A, B, C = (d * d).sum(-1), (o * d).sum(-1), (o * o).sum() - 1.0
                hit |= B * B - A * C >= 0
            out[v, t] = hit.reshape(res, supersample, res, supersample).mean((1, 3))
    return torch.from_numpy(out)


class AnalyticDrop:
    """The tumbling two-ellipsoid drop of the module docstring, 8 frames."""

    def __init__(self, frames: int = 8, resolution: int = 64, num_points: int = 20000) -> None:
        rng = np.random.default_rng(0)
        rest = sample_object(num_points, rng)
        rest_centroid = rest.mean(0)
        R0 = Rotation.from_rotvec([0.3, -0.5, 0.7]).as_matrix()
        p0 = np.array([0.05, -0.03, 0.0])
        points = (rest - rest_centroid) @ R0.T + p0
        self.times = np.arange(frames) * DT
        self.rotations = torque_free_reference(R0, W_TRUE, inertia_of(points), self.times)
        self.centroids = p0 + V_TRUE * self.times[:, None] + 0.5 * GRAVITY * self.times[:, None] ** 2
        self.cameras = camera_ring(4, 2.4, 20.0, resolution, resolution, target=(0.0, 0.0, -0.4))
        self.masks = render_masks(self.cameras, self.rotations, self.centroids, rest_centroid)
        self.points = torch.tensor(points)
        self.rest_offsets = rest - rest_centroid

    def lowest(self, t: float) -> float:
        """Lowest z of the given points under the true motion at time t (s)."""
        R = torque_free_reference(self.rotations[0], W_TRUE, inertia_of(self.points.numpy()), np.array([0.0, t]))[-1]
        p = self.centroids[0] + V_TRUE * t + 0.5 * GRAVITY * t * t
        return float((self.rest_offsets @ R.T + p)[:, 2].min())


@pytest.fixture(scope="module")
def drop() -> AnalyticDrop:
    return AnalyticDrop()


def estimate(drop: AnalyticDrop, floor_height: float | None = None, **kwargs) -> InitialVelocity:
    return estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, torch.tensor(GRAVITY), floor_height,
                                     **kwargs)


# ---- the rotation model -------------------------------------------------------------------------------------


def test_torque_free_propagation_matches_euler_equations() -> None:
    """The module's SO(3) midpoint integrator against scipy on Euler's equations: within 2e-4 rad over 0.35 s
    at |ω| = 2.1 rad/s; the constant-ω model is exact; ω really does change (by > 0.2 rad/s) here."""
    points = sample_object(5000, np.random.default_rng(1))
    inertia = inertia_of(points)
    R0 = Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix()
    inertia_world = R0 @ inertia @ R0.T
    times = np.arange(8) * DT
    ref = torque_free_reference(R0, W_TRUE, inertia_world, times)
    # propagate_rotations takes the inertia at orientation R = I, i.e. of the points as given (here: rest frame)
    ours = propagate_rotations(R0, W_TRUE, inertia, times, DT / 4)
    angle = np.linalg.norm(Rotation.from_matrix(np.transpose(ref, (0, 2, 1)) @ ours).as_rotvec(), axis=1)
    assert angle.max() < 2e-4, angle
    # the angular velocity at the end differs from the start: a constant-ω model cannot follow this body
    late = torque_free_reference(R0, W_TRUE, inertia_world, np.array([0.0, 0.35, 0.35 + 1e-4]))
    w_late = Rotation.from_matrix(late[2] @ late[1].T).as_rotvec() / 1e-4
    assert np.linalg.norm(w_late - W_TRUE) > 0.2
    const = propagate_rotations(R0, W_TRUE, None, times, DT / 4)
    expected = Rotation.from_rotvec(times[:, None] * W_TRUE[None]).as_matrix() @ R0
    assert np.abs(const - expected).max() < 1e-12


# ---- the analytic drop -----------------------------------------------------------------------------------------


def test_recovers_velocity_of_tumbling_drop(drop: AnalyticDrop) -> None:
    est = estimate(drop)
    assert est.frames_used == 8 and est.stop_reason == "max_frames"
    assert (
        est.rotations.shape == (8, 3, 3) and est.translations.shape == (8, 3) and est.frame_residuals_px.shape == (8,)
    )
    torch.testing.assert_close(est.centre, drop.points.mean(0))
    dv = float(np.linalg.norm(est.linear.numpy() - V_TRUE))
    dw = float(np.linalg.norm(est.angular.numpy() - W_TRUE))
    assert dv < 0.02, (est.linear, dv)
    assert dw < 0.15, (est.angular, dw)
    assert est.residual_px < 0.2 and est.model_residual_m < 0.005
    # the per-frame poses follow the true motion (frame t maps frame-0 points to frame t; frame 0 is the identity)
    torch.testing.assert_close(est.rotations[0], torch.eye(3, dtype=est.rotations.dtype))
    torch.testing.assert_close(est.translations[0], torch.zeros(3, dtype=est.translations.dtype))
    for t in range(8):
        rel = drop.rotations[t] @ drop.rotations[0].T
        angle = np.linalg.norm(Rotation.from_matrix(est.rotations[t].numpy().T @ rel).as_rotvec())
        assert np.degrees(angle) < 2.5, (t, np.degrees(angle))
        c = drop.points.mean(0).numpy()
        moved = est.rotations[t].numpy() @ c + est.translations[t].numpy()
        assert np.linalg.norm(moved - drop.centroids[t]) < 0.005
    # the velocity field: v at the centre, rigid elsewhere
    x = drop.points[:5]
    vel = est.point_velocities(x)
    expected = est.linear + torch.linalg.cross(est.angular.expand_as(x), x - est.centre, dim=-1)
    torch.testing.assert_close(vel, expected)


def test_poses_are_relative_to_frame_0s_fit(drop: AnalyticDrop) -> None:
    """Points that the frame-0 silhouettes place turned (here: the object's own points turned by 8° about their
    centroid, as a loose hull can be) still give the true frame-to-frame motion: each pose is relative to frame
    0's fit, so the fit's common turn cancels and frame 0 maps to itself."""
    c = drop.points.mean(0)
    turn = torch.tensor(Rotation.from_rotvec(np.radians(8.0) * np.array([0.6, 0.0, 0.8])).as_matrix())
    turned = (drop.points - c) @ turn.T + c
    est = estimate_initial_velocity(turned, drop.masks, drop.cameras, DT, torch.tensor(GRAVITY), None)
    torch.testing.assert_close(est.rotations[0], torch.eye(3, dtype=est.rotations.dtype))
    torch.testing.assert_close(est.translations[0], torch.zeros(3, dtype=est.translations.dtype))
    for t in range(1, est.frames_used):
        rel = drop.rotations[t] @ drop.rotations[0].T
        angle = np.degrees(np.linalg.norm(Rotation.from_matrix(est.rotations[t].numpy().T @ rel).as_rotvec()))
        assert angle < 2.5, (t, angle)
        moved = est.rotations[t].numpy() @ c.numpy() + est.translations[t].numpy()
        assert np.linalg.norm(moved - drop.centroids[t]) < 0.005, t
    assert float(np.linalg.norm(est.angular.numpy() - W_TRUE)) < 0.15


def test_constant_omega_model_misses_the_tumble(drop: AnalyticDrop) -> None:
    """Fitting a constant ω to a tumbling body returns about its mean over the frames, not ω at frame 0."""
    est = estimate(drop, rotation_model="constant")
    dv = float(np.linalg.norm(est.linear.numpy() - V_TRUE))
    dw = float(np.linalg.norm(est.angular.numpy() - W_TRUE))
    assert dv < 0.02
    assert dw > 0.15, dw


def test_stops_before_predicted_floor_contact(drop: AnalyticDrop) -> None:
    """With a floor that the (unbouncing) analytic drop reaches between frames 4 and 5, frames 0 … 4 are used."""
    floor = drop.lowest(4.5 * DT)
    assert drop.lowest(4 * DT) - floor > 0.02
    est = estimate(drop, floor_height=floor, max_frames=8)
    assert est.frames_used == 5, est.stop_reason
    assert "contact" in est.stop_reason
    assert float(np.linalg.norm(est.linear.numpy() - V_TRUE)) < 0.03
    assert float(np.linalg.norm(est.angular.numpy() - W_TRUE)) < 0.25


# ---- a make_scene scene ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory: pytest.TempPathFactory):
    from vid2sim.scene.folder import load_scene
    from vid2sim.synthetic.fem import FEMResult
    from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene

    config = SyntheticSceneConfig.preset("small", seed=0, frames=6, observed_frames=6)
    folder = make_scene(config, tmp_path_factory.mktemp("initial_state") / "seed0", progress=False)
    return load_scene(folder), FEMResult.load(folder / "fem_result.npz")


def test_matches_ground_truth_of_synthetic_scene(small_scene) -> None:
    """Seed 0 of the small preset: the object reaches the floor between frames 4 and 5."""
    from vid2sim.meshing.tetra import sample_points_in_tets

    scene, fem = small_scene
    cfg = scene.config
    points, _, _ = sample_points_in_tets(fem.trajectory[0], fem.tets, 20000, seed=0)
    masks = scene.float_masks()[cfg.observed_views][:, cfg.observed_frames]
    cameras = [scene.cameras[v] for v in cfg.observed_views]
    est = estimate_initial_velocity(points, masks, cameras, cfg.dt, torch.tensor(cfg.gravity), cfg.floor_height)

    # ground truth: metadata velocities are about the tet mesh's centre of mass; move them to our centre
    pose = cfg.metadata["initial_pose"]
    v_com = torch.tensor(pose["linear_velocity"], dtype=torch.float64)
    w = torch.tensor(pose["angular_velocity"], dtype=torch.float64)
    x0, tets = fem.trajectory[0].double(), fem.tets.long()
    corners = x0[tets]
    vol = torch.linalg.det(corners[:, 1:] - corners[:, :1]).abs() / 6
    com = (vol[:, None] * corners.mean(1)).sum(0) / vol.sum()
    v_true = v_com + torch.linalg.cross(w, est.centre.double() - com)
    assert (
        float(
            (fem.velocities[0].double() - (v_com + torch.linalg.cross(w.expand_as(x0), x0 - com, dim=-1))).abs().max()
        )
        < 1e-6
    )

    dv = float((est.linear.double() - v_true).norm())
    dw = float((est.angular.double() - w).norm())
    assert dv < 0.03, (est.linear, v_true)
    assert dw < 0.25, (est.angular, w)
    # only frames before the contact are used, and most of them
    K = est.frames_used
    assert 3 <= K <= 5, est.stop_reason
    assert float(fem.trajectory[:K, :, 2].min()) > cfg.floor_height


# ---- argument checks -------------------------------------------------------------------------------------------


def test_rejects_bad_shapes_and_values(drop: AnalyticDrop) -> None:
    g = torch.tensor(GRAVITY)
    with pytest.raises(ValueError, match=r"points must be a tensor of shape \(N, 3\)"):
        estimate_initial_velocity(drop.points[:, :2], drop.masks, drop.cameras, DT, g, None)
    with pytest.raises(ValueError, match=r"masks must have shape \(V=4, T, H=64, W=64\)"):
        estimate_initial_velocity(drop.points, drop.masks[:3], drop.cameras, DT, g, None)
    with pytest.raises(ValueError, match="at least 2 frames"):
        estimate_initial_velocity(drop.points, drop.masks[:, :1], drop.cameras, DT, g, None)
    with pytest.raises(ValueError, match=r"masks must be floats in \[0, 1\]"):
        estimate_initial_velocity(drop.points, drop.masks * 2, drop.cameras, DT, g, None)
    with pytest.raises(ValueError, match="dt must be a positive"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, 0.0, g, None)
    with pytest.raises(ValueError, match="gravity must be a finite"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, torch.zeros(2), None)
    with pytest.raises(ValueError, match="max_frames must be an integer >= 2"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, g, None, max_frames=1)
    with pytest.raises(ValueError, match="rotation_model must be one of"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, g, None, rotation_model="spin")


def test_names_an_empty_mask(drop: AnalyticDrop) -> None:
    masks = drop.masks.clone()
    masks[2, 3] = 0.0
    with pytest.raises(ValueError, match="mask of view 2 at frame 3 is empty"):
        estimate_initial_velocity(drop.points, masks, drop.cameras, DT, torch.tensor(GRAVITY), None)


def test_rejects_points_the_cameras_do_not_see(drop: AnalyticDrop) -> None:
    g = torch.tensor(GRAVITY)
    far = drop.points + torch.tensor([0.0, 0.0, 3.0], dtype=drop.points.dtype)
    with pytest.raises(ValueError, match="camera 0 does not see the points"):
        estimate_initial_velocity(far, drop.masks, drop.cameras, DT, g, None)
    shifted = drop.points + torch.tensor([0.0, 0.0, 0.35], dtype=drop.points.dtype)
    with pytest.raises(ValueError, match="do not match the frame-0 mask of view 0"):
        estimate_initial_velocity(shifted, drop.masks, drop.cameras, DT, g, None)


def test_needs_two_frames_before_contact(drop: AnalyticDrop) -> None:
    g = torch.tensor(GRAVITY)
    floor = float(drop.points[:, 2].min()) - 0.001  # the object rests on the floor at frame 0
    with pytest.raises(ValueError, match="fewer than 2 usable frames"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, g, floor)
    floor = drop.lowest(0.9 * DT)  # contact between frames 0 and 1
    with pytest.raises(ValueError, match="fewer than 2 usable frames"):
        estimate_initial_velocity(drop.points, drop.masks, drop.cameras, DT, g, floor)
