"""The object's initial rigid velocity, from the ballistic (pre-contact) frames of the masks.

The reconstruction uses the object's frame-0 configuration as the simulator's rest shape and starts the
simulation with a rigid velocity field v_i = v + ω × (x_i − c) about the centroid c of the frame-0 points.
Until the object touches the floor it flies freely, so its first frames are a rigid motion under gravity
alone; :func:`estimate_initial_velocity` recovers (v, ω) from them in three steps.

1. **Per-frame rigid poses.** For t = 0, 1, …, a rigid pose x = R_t (X − c) + p_t of the object is
   fitted to the masks of all views by minimising a two-sided silhouette distance in pixels:

   * *inside*: every projected shape point must lie inside the mask — the mask's signed distance field
     (sub-pixel at anti-aliased edges: 0.5 − m on fractional pixels; the Euclidean distance transform
     ∓ 0.5 px elsewhere) is sampled bilinearly at each projected point, and its positive part penalised;
   * *coverage*: the mask must be covered — its boundary (the m = 0.5 iso-line, located to sub-pixel
     precision between neighbouring pixel centres) is sampled, and each sample's distance to the nearest
     projected point is penalised.

   The loss is the mean of both squared distances, averaged over views. It is a sum of squared residuals
   with analytic derivatives (pinhole projection, bilinear interpolation, a left-multiplied rotation
   increment), so Levenberg–Marquardt minimises it, pairing every boundary sample with its nearest
   projected point (k-d tree) anew at every step, as ICP does: a frame takes 5–20 evaluations where a
   first-order method through autograd needs hundreds.

   *What is projected* matters more than the optimiser. Points sampled inside the volume stop short of
   the surface by a random, direction-dependent gap, so their projections leave a sparse, ragged rim and
   the fitted rotation wanders by 1–3° from frame to frame (measured on the synthetic scenes) — with the
   3 pre-contact frames of a typical drop that alone is an error of several tenths of a rad/s in ω. The
   default ``shape_model="surface"`` therefore fits dense samples of a smooth surface reconstructed from
   the points (:func:`surface_samples`: binned, blurred, marching cubes at half the interior density),
   which lowers that scatter to a few tenths of a degree.

   Frame 0 is fitted as well (from the identity), so that a misfit of the shape to the frame-0 masks is
   shared by all frames and drops out of the velocities. Frame t starts from the ballistic model of
   frames 0 … t−1 (frame 1 from frame 0's pose, falling from rest).

2. **The ballistic model.** With known gravity g the centroid moves as p(t) = p₀ + v t + ½ g t² (linear
   least squares over the fitted centroids). The rotation is *torque-free rigid-body motion*: the angular
   momentum L = I(t) ω(t) is constant in the world frame while the inertia tensor I(t) = R(t) I_X R(t)ᵀ
   turns with the body (I_X: the inertia of the points about c, uniform density), so
   ω(t) = R(t) I_X⁻¹ R(t)ᵀ L is *not* constant unless the body spins about a principal axis; a tumbling
   object at 2 rad/s changes ω by several tenths of a rad/s within 0.35 s, and fitting a constant ω
   then returns roughly its mean over the frames instead of its value at frame 0 (on the synthetic
   tumbling test 0.1–0.3 rad/s off, against < 0.1 for the torque-free model). R(t) is integrated from
   (R₀, ω₀) by the explicit midpoint rule on SO(3) (:func:`propagate_rotations`; 4 substeps per frame) and
   (R₀, ω₀) is fitted by minimising Σ_t θ_t², θ_t the geodesic angle between R(t) and the fitted R_t
   (Levenberg–Marquardt on the rotation logs, started from the constant-ω least-squares solution).
   ``rotation_model="constant"`` fits R(t) = exp(t[ω]×) R₀ instead, for points whose inertia is not
   trustworthy (e.g. a hollow shell). Neither the centroid nor the angular momentum is affected by
   the elastic deformation a spinning soft body undergoes, but the rotation of its surface is, slightly.

3. **Which frames are ballistic.** Frames are added one at a time while the object is in free flight,
   up to ``max_frames``. Frame t is refused, and the search stops, when (a) the model of frames
   0 … t−1 predicts that the lowest point comes within ``floor_margin`` of the floor before t·dt,
   (b) the lowest point of the fitted pose of frame t is within ``floor_margin`` of the floor, or (c)
   the model refitted with frame t predicts such a contact before t·dt. Without a floor, all frames up to
   ``max_frames`` are used. Frames 0 and 1 must be usable.

Heights are measured along up = −g/|g|, and the floor is the plane up·x = ``floor_height`` (the scene
format's convention). "The lowest point" is the lowest of the *given* points — the points the simulator
will carry. Interior samples lie a few mm above the true surface, so a frame at or barely past the moment
of contact may be kept; it has not had time to deform or decelerate much.

Limitations: silhouettes alone constrain the pose, so an object whose silhouettes do not change under its
rotation (a sphere, a spin about an axis of symmetry) has an unobservable ω here; the stage therefore refines the
poses on the images (:mod:`vid2sim.reconstruct.photo_poses`) and refits the model to them
(:func:`refit_to_poses`). With only two usable frames
(contact between frames 1 and 2) the estimate is a finite difference, and a contact between frames 0 and
1 cannot be told from the data. Each frame's fit is independent (the model only initialises it), so a
poorly fitted frame is not rejected, only averaged by the least squares. The points must fill the object
uniformly for their centroid to be the centre of mass and their inertia the body's.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.reconstruct.photo_poses import refine_poses
from vid2sim.reconstruct.runner import Context, State
from vid2sim.reconstruct.silhouettes import (
    PoseFit,
    prepare_silhouette,
    so3_exp,
    so3_log,
    surface_samples,
)
from vid2sim.runtime.files import read_json, write_json_atomic
from vid2sim.splats.cameras import Camera, stack_cameras

_NAME = "estimate_initial_velocity"  # errors start with it
ROTATION_MODELS = ("torque_free", "constant")
SHAPE_MODELS = ("surface", "points")


class TooFewBallisticFrames(ValueError):
    """The object touches the floor before frame 1 (or at frame 0): no two frames of free flight."""


@dataclass
class InitialVelocity:
    """A rigid initial velocity, v_i = linear + angular × (x_i − centre), at frame 0.

    Attributes:
        linear: (3,) velocity of the centroid ``centre`` at frame 0 (m/s, world frame).
        angular: (3,) angular velocity at frame 0 (rad/s, world frame).
        centre: (3,) the centroid of the given frame-0 points (m), the point ``linear`` is about.
        frames_used: K, the number of frames 0 … K−1 the ballistic model was fitted to.
        residual_px: mean silhouette fit error of the K per-frame poses (px): per view, the mean of
            (a) the points' mean distance outside the mask and (b) the mask boundary's mean distance to
            the nearest projected point; averaged over views and frames.
        rotations: (K, 3, 3) fitted per-frame poses relative to frame 0's fit: frame t maps a frame-0 point X
            to ``rotations[t] @ X + translations[t]``; frame 0 is the identity.
        translations: (K, 3) see ``rotations``.
        frame_residuals_px: (K,) the per-frame silhouette errors behind ``residual_px``.
        model_residual_m: RMS distance (m) between the points posed by the per-frame fits and by the
            fitted ballistic model, over the K frames (how ballistic the fitted poses are).
        stop_reason: why no more frames were used (``"max_frames"``, ``"end of the masks"``, or the
            contact test that refused the next frame).
        seconds: wall time of the estimate.
    """

    linear: Tensor
    angular: Tensor
    centre: Tensor
    frames_used: int
    residual_px: float
    rotations: Tensor
    translations: Tensor
    frame_residuals_px: Tensor
    model_residual_m: float
    stop_reason: str
    seconds: float = 0.0

    def point_velocities(self, points: Tensor) -> Tensor:
        """The rigid velocity field (N, 3) at world points (N, 3) of frame 0."""
        lin = self.linear.to(points)
        ang = self.angular.to(points)
        return lin + torch.linalg.cross(ang.expand_as(points), points - self.centre.to(points), dim=-1)


# =============================================================================================
# rotations (numpy, float64)
# =============================================================================================


def propagate_rotations(R0: np.ndarray, omega0: np.ndarray, inertia: np.ndarray | None, times: Sequence[float],
                        max_step: float) -> np.ndarray:
    """Orientations (M, 3, 3) at ``times`` (M,) (non-decreasing, ≥ 0) of a free rigid body at R0 (3, 3) at t = 0.

    With ``inertia`` (3, 3) — the body's inertia tensor in the orientation R = I, about its centre of mass
    (any scale) — the motion is torque-free: the world angular momentum L = R₀ I R₀ᵀ ω₀ is conserved and
    ω(R) = R I⁻¹ Rᵀ L, integrated by the explicit midpoint rule on SO(3), R ← exp(h [ω(R_½)]×) R, with
    steps of at most ``max_step`` (s). Without it ω stays ω₀ (3,) and R(t) = exp(t [ω₀]×) R₀ exactly.
    """
    times = np.asarray(times, dtype=np.float64)
    if inertia is None:
        return so3_exp(times[:, None] * omega0[None]) @ R0
    inv = np.linalg.inv(inertia)
    L = R0 @ (inertia @ (R0.T @ omega0))
    out = np.empty((len(times), 3, 3))
    R, now = R0, 0.0
    for i, target in enumerate(times):
        if target - now > 1e-12:
            n = max(1, math.ceil((target - now) / max_step - 1e-9))
            h = (target - now) / n
            for _ in range(n):
                half = so3_exp(0.5 * h * (R @ (inv @ (R.T @ L)))) @ R
                R = so3_exp(h * (half @ (inv @ (half.T @ L)))) @ R
            now = float(target)
        out[i] = R
    return out


# =============================================================================================
# silhouettes
# =============================================================================================


# =============================================================================================
# the ballistic model
# =============================================================================================


@dataclass
class _Ballistic:
    """Free flight: centroid p(t) = p0 + v t + ½ g t², orientation R(t) from (R0, ω0) (all numpy float64)."""

    p0: np.ndarray
    v: np.ndarray
    g: np.ndarray
    R0: np.ndarray
    omega: np.ndarray
    inertia: np.ndarray | None
    max_step: float

    def rotations(self, times: Sequence[float]) -> np.ndarray:
        """(M, 3, 3) at ``times`` (M,)."""
        return propagate_rotations(self.R0, self.omega, self.inertia, times, self.max_step)

    def centroids(self, times: Sequence[float]) -> np.ndarray:
        """(M, 3) at ``times`` (M,)."""
        t = np.asarray(times, dtype=np.float64)[:, None]
        return self.p0 + self.v * t + 0.5 * self.g * t * t


def _fit_ballistic(times: np.ndarray, centroids: np.ndarray, rotations: np.ndarray, gravity: np.ndarray,
                   inertia: np.ndarray | None, max_step: float) -> _Ballistic:
    """Least-squares free flight through K ≥ 2 poses: times (K,), centroids (K, 3), rotations (K, 3, 3)."""
    from scipy.optimize import least_squares

    A = np.stack([np.ones_like(times), times], 1)
    sol = np.linalg.lstsq(A, centroids - 0.5 * gravity[None] * times[:, None] ** 2, rcond=None)[0]
    p0, v = sol[0], sol[1]
    # constant-ω start: log(R_t R_0ᵀ) ≈ t ω
    logs = so3_log(rotations @ rotations[0].T)
    omega = (times[:, None] * logs).sum(0) / max(float(times @ times), 1e-30)

    def residuals(x: np.ndarray) -> np.ndarray:
        R0 = so3_exp(x[:3]) @ rotations[0]
        pred = propagate_rotations(R0, x[3:], inertia, times, max_step)
        return so3_log(rotations.transpose(0, 2, 1) @ pred).reshape(-1)

    fit = least_squares(residuals, np.concatenate([np.zeros(3), omega]), method="lm", xtol=1e-12, ftol=1e-12)
    return _Ballistic(p0, v, gravity, so3_exp(fit.x[:3]) @ rotations[0], fit.x[3:], inertia, max_step)


# =============================================================================================
# the estimate
# =============================================================================================


def _check_inputs(points: Tensor, masks: Tensor, cameras: Sequence[Camera], dt: float, gravity: Tensor,
                  floor_height: float | None, max_frames: int) -> None:
    """Raise ValueError for arguments of the wrong shape, type or value."""
    name = "estimate_initial_velocity"
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3:
        got = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise ValueError(f"{name}: points must be a tensor of shape (N, 3), got {got}")
    if points.shape[0] < 4:
        raise ValueError(f"{name}: points must hold at least 4 points, got {points.shape[0]}")
    if not torch.isfinite(points).all():
        raise ValueError(f"{name}: points contain NaN or infinite values")
    if not isinstance(cameras, (list, tuple)) or not cameras:
        raise ValueError(f"{name}: cameras must be a non-empty list of Camera")
    _, _, width, height = stack_cameras(list(cameras))
    V = len(cameras)
    if not isinstance(masks, Tensor) or masks.ndim != 4:
        got = tuple(masks.shape) if isinstance(masks, Tensor) else type(masks).__name__
        raise ValueError(f"{name}: masks must be a tensor of shape (V, T, H, W), got {got}")
    if masks.shape[0] != V or tuple(masks.shape[2:]) != (height, width):
        raise ValueError(
            f"{name}: masks must have shape (V={V}, T, H={height}, W={width}) for {V} cameras of "
            f"{width}x{height}, got {tuple(masks.shape)}"
        )
    if masks.shape[1] < 2:
        raise ValueError(f"{name}: need at least 2 frames of masks, got T = {masks.shape[1]}")
    if not masks.is_floating_point() or not bool(torch.isfinite(masks).all()) or masks.min() < 0 or masks.max() > 1:
        raise ValueError(f"{name}: masks must be floats in [0, 1] (e.g. Scene.float_masks())")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise ValueError(f"{name}: dt must be a positive number of seconds, got {dt!r}")
    if gravity.shape != (3,) or not bool(torch.isfinite(gravity).all()):
        raise ValueError(f"{name}: gravity must be a finite (3,) vector, got shape {tuple(gravity.shape)}")
    if floor_height is not None:
        number = isinstance(floor_height, (int, float)) and not isinstance(floor_height, bool)
        if not number or not math.isfinite(floor_height):
            raise ValueError(f"{name}: floor_height must be a finite number or None, got {floor_height!r}")
        if float(gravity.norm()) == 0.0:
            raise ValueError(f"{name}: a floor needs a non-zero gravity (-gravity defines 'up')")
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 2:
        raise ValueError(f"{name}: max_frames must be an integer >= 2, got {max_frames!r}")


def estimate_initial_velocity(
    points: Tensor,
    masks: Tensor,
    cameras: Sequence[Camera],
    dt: float,
    gravity: Tensor,
    floor_height: float | None,
    max_frames: int = 8,
    progress: bool = False,
    *,
    rotation_model: str = "torque_free",
    floor_margin: float = 0.003,
    max_points: int = 20000,
    iterations: int = 30,
    shape_model: str = "surface",
    seed: int = 0,
) -> InitialVelocity:
    """Estimate the rigid velocity (v, ω) of the object at frame 0 from its ballistic frames.

    See the module docstring for the method.

    Args:
        points: (N, 3) world points filling the object at frame 0, uniformly (their centroid is taken as
            the centre of mass and, for ``rotation_model="torque_free"``, their inertia as the body's).
        masks: (V, T, H, W) object masks in [0, 1] of the observed views; frame t is at time t·dt (pass
            consecutive frames starting at frame 0).
        cameras: the V cameras of ``masks`` (one image size).
        dt: seconds between frames.
        gravity: (3,) gravity (m/s²).
        floor_height: the floor plane's height along −gravity/|gravity| (m), or None for no floor.
        max_frames: use at most this many frames (≥ 2).
        progress: print one line per fitted frame.
        rotation_model: ``"torque_free"`` (conserved angular momentum with the points' inertia) or
            ``"constant"`` (constant ω).
        floor_margin: clearance (m) above the floor at or below which the object counts as (possibly) in
            contact.
        max_points: the pose fits use at most this many shape points (a seeded random subset of the surface
            samples or of the points; the floor tests always use all given points).
        iterations: Levenberg–Marquardt iterations per fit, at most.
        shape_model: what is fitted to the silhouettes: ``"surface"`` (samples of a smooth surface
            reconstructed from the points, :func:`surface_samples`; falls back to the points when none is
            found) or ``"points"`` (a subset of the points themselves).
        seed: seeds the subsets.

    Returns:
        :class:`InitialVelocity` (tensors in the dtype and on the device of ``points``).

    Raises:
        ValueError: bad shapes or values; an empty mask (named by its view and frame index in ``masks``); a
            camera that does not see the points, or whose frame-0 mask does not match them; the object
            within ``floor_margin`` of the floor at frame 0; fewer than 2 usable frames.
    """
    start = time.perf_counter()
    gravity = torch.as_tensor(gravity).detach().to("cpu", torch.float64)
    _check_inputs(points, masks, cameras, dt, gravity, floor_height, max_frames)
    _check_options(rotation_model, floor_margin, shape_model, max_points, iterations)
    g = gravity.detach().to("cpu", torch.float64).numpy()
    P = points.detach().to("cpu", torch.float64).numpy()
    K_max = min(int(max_frames), masks.shape[1])
    masks_np = _used_masks(masks, K_max)
    viewmats_t, Ks_t, width, height = stack_cameras(list(cameras))
    viewmats, Ks = viewmats_t.detach().cpu().double().numpy(), Ks_t.detach().cpu().double().numpy()

    centre, inertia = _centre_and_inertia(P, rotation_model)
    r = P - centre
    rng = np.random.default_rng(seed)
    subset = r[rng.choice(len(r), max_points, replace=False)] if len(r) > max_points else r
    metres_per_px = _check_views(subset + centre, masks_np[:, 0], viewmats, Ks, width, height)
    surface = surface_samples(P, max_points, rng) if shape_model == "surface" else None
    Xc = subset if surface is None else surface - centre  # the points the silhouettes are fitted with
    flight = _Flight(shape=Xc, points=r, viewmats=viewmats, Ks=Ks, width=width, height=height, masks=masks_np,
                     metres_per_px=metres_per_px, radius=float(np.linalg.norm(r, axis=1).max()),
                     iterations=iterations, dt=dt, g=g, up=-g / np.linalg.norm(g) if floor_height is not None else None,
                     floor_height=floor_height, floor_margin=floor_margin, progress=progress)
    model_inertia = inertia if rotation_model == "torque_free" else None
    frames = _ballistic_frames(flight, centre, model_inertia, K_max, max_frames)
    out_dtype = points.dtype if points.is_floating_point() else torch.float32
    return _estimate(flight, frames, centre, out_dtype, points.device, start)


def _check_rotation_model(rotation_model: str) -> None:
    """Raise ValueError for an unknown rotation model (:data:`ROTATION_MODELS`)."""
    if rotation_model not in ROTATION_MODELS:
        raise ValueError(f"{_NAME}: rotation_model must be one of {ROTATION_MODELS}, got {rotation_model!r}")


def _check_options(rotation_model: str, floor_margin: float, shape_model: str, max_points: int,
                   iterations: int) -> None:
    """Raise ValueError for an unknown model or an out-of-range option of :func:`estimate_initial_velocity`."""
    _check_rotation_model(rotation_model)
    if not (math.isfinite(floor_margin) and floor_margin >= 0):
        raise ValueError(f"{_NAME}: floor_margin must be a finite number >= 0, got {floor_margin!r}")
    if shape_model not in SHAPE_MODELS:
        raise ValueError(f"{_NAME}: shape_model must be one of {SHAPE_MODELS}, got {shape_model!r}")
    if max_points < 4 or iterations < 1:
        raise ValueError(f"{_NAME}: max_points must be >= 4 and iterations >= 1, got {max_points}, {iterations}")


def _used_masks(masks: Tensor, K_max: int) -> np.ndarray:
    """The masks (V, K_max, H, W) float32 of the frames that may be used; refused when one is empty."""
    V = masks.shape[0]
    masks_np = masks.detach()[:, :K_max].to("cpu", torch.float32).numpy()
    for t in range(K_max):
        for v in range(V):
            if not (masks_np[v, t] >= 0.5).any():
                raise ValueError(f"{_NAME}: the mask of view {v} at frame {t} is empty (no pixel >= 0.5); the object "
                                 "must be visible in every view of the frames used")
    return masks_np


def _centre_and_inertia(P: np.ndarray, rotation_model: str) -> tuple[np.ndarray, np.ndarray]:
    """The centroid (3,) of the points ``P`` (N, 3) and their inertia (3, 3) about it (uniform density, unit
    mass); refused when singular and the rotation model needs it."""
    centre = P.mean(0)
    r = P - centre
    inertia = (r * r).sum(1).mean() * np.eye(3) - r.T @ r / len(r)
    evals = np.linalg.eigvalsh(inertia)
    if rotation_model == "torque_free" and evals[0] <= 1e-9 * evals[-1]:
        raise ValueError(f"{_NAME}: the points are degenerate (collinear): their inertia tensor is singular")
    return centre, inertia


def _check_views(X: np.ndarray, masks0: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int,
                 height: int) -> float:
    """Check that every camera sees the world points ``X`` (M, 3) and that they match its frame-0 mask
    (``masks0`` (V, H, W)); returns the mean size of a pixel at the points' depth (m)."""
    V = len(viewmats)
    cam = np.einsum("vij,nj->vni", viewmats[:, :3, :3], X) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    for v in range(V):
        if (z[v] <= 1e-6).any():
            raise ValueError(f"{_NAME}: camera {v} does not see the points: some lie behind it (check the camera "
                             "poses and that the points are in the same world frame)")
    zs = np.maximum(z, 1e-6)
    u = Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]
    w = Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]
    in_image = (u >= 0) & (u < width) & (w >= 0) & (w < height)
    col, row = np.clip(np.floor(u), 0, width - 1).astype(np.int64), np.clip(np.floor(w), 0, height - 1).astype(np.int64)
    for v in range(V):
        seen = float(in_image[v].mean())
        if seen < 0.5:
            raise ValueError(f"{_NAME}: camera {v} does not see the points: only {100 * seen:.0f} % of them project "
                             f"into its {width}x{height} image")
        matched = float(((masks0[v][row[v], col[v]] > 0.25) & in_image[v]).mean())
        if matched < 0.5:
            raise ValueError(
                f"{_NAME}: the points do not match the frame-0 mask of view {v}: only {100 * matched:.0f} % "
                "of them project inside it (are they the object at frame 0, in the cameras' world frame?)"
            )
    return float(z.mean()) / float(Ks[:, [0, 1], [0, 1]].mean())


@dataclass
class _Flight:
    """What the frame-by-frame pose fits and floor tests need (float64 numpy unless stated).

    Attributes:
        shape: (M, 3) the shape points fitted to the silhouettes, about the centroid.
        points: (N, 3) all given points about the centroid (the floor tests use them all).
        viewmats, Ks: (V, 4, 4) world-to-camera matrices and (V, 3, 3) intrinsics; width, height: pixels.
        masks: (V, K_max, H, W) float32 masks of the frames that may be used.
        metres_per_px: a pixel's size at the points' depth; radius: the points' largest distance from the centroid.
        iterations: Levenberg–Marquardt iterations per fit, at most.
        dt: s per frame; g: (3,) gravity; up: (3,) −g/|g| with a floor, else None.
        floor_height, floor_margin: the floor along ``up`` (None: no floor) and the contact clearance (m).
        progress: print one line per fitted frame.
    """

    shape: np.ndarray
    points: np.ndarray
    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int
    masks: np.ndarray
    metres_per_px: float
    radius: float
    iterations: int
    dt: float
    g: np.ndarray
    up: np.ndarray | None
    floor_height: float | None
    floor_margin: float
    progress: bool

    def clearance(self, R: np.ndarray, p: np.ndarray) -> float:
        """Height (m) above the floor of the lowest given point posed by (R, p)."""
        assert self.up is not None and self.floor_height is not None
        return float(((self.points @ R.T + p) @ self.up).min()) - float(self.floor_height)

    def predicted_contact(self, model: _Ballistic, t0: float, t1: float) -> float | None:
        """The first of 9 times in [t0, t1] at which the model's lowest point is within the margin, if any."""
        if self.up is None:
            return None
        times = np.linspace(t0, t1, 9)
        for s, R, p in zip(times, model.rotations(times), model.centroids(times)):
            if self.clearance(R, p) <= self.floor_margin:
                return float(s)
        return None

    def fit_frame(self, t: int, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The pose (R (3, 3), p (3,)) of frame ``t`` fitted to its silhouettes from (R, p), and its residual (px)."""
        V = self.masks.shape[0]
        fitter = PoseFit(self.shape, self.viewmats, self.Ks, self.width, self.height,
                         [prepare_silhouette(self.masks[v, t]) for v in range(V)])
        return fitter.fit(R, p, self.metres_per_px, self.radius, self.iterations)

    def say(self, message: str) -> None:
        """Print one progress line (with ``progress``)."""
        if self.progress:
            print(f"[initial velocity] {message}", flush=True)


@dataclass
class _Frames:
    """The ballistic frames 0 … K−1: fitted rotations (K × (3, 3)), centroids (K × (3,)) and residuals (K, px),
    the ballistic model fitted through them, and why no more frames were used."""

    rotations: list[np.ndarray]
    centroids: list[np.ndarray]
    residuals: list[float]
    model: _Ballistic
    stop: str


def _ballistic_frames(f: _Flight, centre: np.ndarray, inertia: np.ndarray | None, K_max: int,
                      max_frames: int) -> _Frames:
    """Fit frame 0, then add frames one at a time while the object is in free flight (module docstring, step 3);
    ``inertia`` (3, 3) of the points at frame 0 (None: constant ω)."""
    max_step = f.dt / 4.0
    R_fit, p_fit, res = f.fit_frame(0, np.eye(3), centre.copy())
    rotations, centroids, residuals = [R_fit], [p_fit], [res]
    if inertia is not None:
        # the fitted poses place the points, not the object: frame 0's fit may be turned by degrees where the
        # silhouettes pin the shape loosely (up to 15° on a rounded benchmark object). The ballistic model
        # propagates those poses, so its inertia is the points' frame-0 inertia seen from frame 0's fitted
        # orientation (R₀ I_body R₀ᵀ = the frame-0 inertia).
        inertia = R_fit.T @ inertia @ R_fit
    f.say(f"frame 0: residual {res:.2f} px")
    if f.up is not None and f.clearance(R_fit, p_fit) <= f.floor_margin:
        raise TooFewBallisticFrames(
            f"{_NAME}: fewer than 2 usable frames: the object already touches the floor at frame 0 (its lowest "
            f"point is {1000 * f.clearance(R_fit, p_fit):.1f} mm above it, margin {1000 * f.floor_margin:.1f} mm)"
        )
    model: _Ballistic | None = None
    stop = "max_frames" if K_max == max_frames else "end of the masks"
    for t in range(1, K_max):
        if model is not None:
            hit = f.predicted_contact(model, (t - 1) * f.dt, t * f.dt)
            if hit is not None:
                stop = f"contact predicted at {hit:.3f} s, before frame {t}"
                break
            R_init, p_init = model.rotations([t * f.dt])[0], model.centroids([t * f.dt])[0]
        else:  # frame 1: frame 0's pose, falling from rest
            R_init, p_init = rotations[0], centroids[0] + 0.5 * f.g * f.dt * f.dt
        R_fit, p_fit, res = f.fit_frame(t, R_init, p_init)
        f.say(f"frame {t}: residual {res:.2f} px")
        if f.up is not None and f.clearance(R_fit, p_fit) <= f.floor_margin:
            stop = (f"frame {t} reaches the floor (fitted lowest point {1000 * f.clearance(R_fit, p_fit):.1f} mm "
                    "above it)")
            break
        times = np.arange(t + 1) * f.dt
        trial = _fit_ballistic(times, np.stack(centroids + [p_fit]), np.stack(rotations + [R_fit]), f.g,
                               inertia, max_step)
        hit = f.predicted_contact(trial, 0.0, t * f.dt)
        if hit is not None:
            stop = f"the fit with frame {t} predicts contact at {hit:.3f} s"
            break
        rotations.append(R_fit)
        centroids.append(p_fit)
        residuals.append(res)
        model = trial
    if model is None:
        raise TooFewBallisticFrames(
            f"{_NAME}: fewer than 2 usable frames ({stop}); the velocity needs frames 0 and 1 before "
            "any contact with the floor"
        )
    return _Frames(rotations, centroids, residuals, model, stop)


def _model_rms(model: _Ballistic, times: np.ndarray, rotations: np.ndarray, centroids: np.ndarray,
               offsets: np.ndarray) -> float:
    """RMS distance (m) between the points at ``offsets`` (N, 3) from the centroid posed by the K poses
    (``rotations`` (K, 3, 3), ``centroids`` (K, 3)) and by the ballistic ``model`` at ``times`` (K,)."""
    posed = np.einsum("kij,nj->kni", rotations, offsets) + centroids[:, None]
    posed_model = np.einsum("kij,nj->kni", model.rotations(times), offsets) + model.centroids(times)[:, None]
    return float(np.sqrt(((posed - posed_model) ** 2).sum(-1).mean()))


def _estimate(f: _Flight, frames: _Frames, centre: np.ndarray, dtype: torch.dtype, device: torch.device,
              start: float) -> InitialVelocity:
    """The :class:`InitialVelocity` of the ballistic ``frames`` (tensors of ``dtype`` on ``device``), with how far
    the model strays from the fitted poses; ``start``: when the estimate began (``time.perf_counter``)."""
    model, K = frames.model, len(frames.rotations)
    Rs, ps = np.stack(frames.rotations), np.stack(frames.centroids)
    times = np.arange(K) * f.dt
    model_rms = _model_rms(model, times, Rs, ps, f.shape)
    f.say(f"{K} frames: v = {np.round(model.v, 4).tolist()} m/s, ω = {np.round(model.omega, 4).tolist()} rad/s "
          f"({frames.stop})")

    def out(a: np.ndarray) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    # frame t's pose relative to frame 0's fit: a bias the fits share (the silhouettes pinning a rounded shape's
    # turn loosely) cancels, and frame 0 maps exactly to itself. On the small benchmark suite the absolute fits
    # are 0.1–17° off the true rotation of frames 1–4, the relative ones 0.2–2.2°.
    rel = Rs @ Rs[0].T
    return InitialVelocity(
        linear=out(model.v),
        angular=out(model.omega),
        centre=out(centre),
        frames_used=K,
        residual_px=float(np.mean(frames.residuals)),
        rotations=out(rel),
        translations=out(ps - rel @ ps[0]),
        frame_residuals_px=out(np.array(frames.residuals)),
        model_residual_m=model_rms,
        stop_reason=frames.stop,
        seconds=time.perf_counter() - start,
    )


def refit_to_poses(est: InitialVelocity, points: Tensor, rotations: np.ndarray, translations: np.ndarray, dt: float,
                   gravity: Tensor, rotation_model: str = "torque_free") -> InitialVelocity:
    """``est`` with its velocity refitted to other poses of its K frames (e.g. refined on the images,
    :func:`vid2sim.reconstruct.photo_poses.refine_poses`): the same ballistic model (module docstring, step 2).

    Args:
        est: the silhouette estimate (its frames, centre and residuals are kept).
        points: (N, 3) the frame-0 points ``est`` was estimated with (their inertia is the body's).
        rotations, translations: (K, 3, 3) and (K, 3) poses relative to frame 0, as ``est.rotations`` holds them.
        dt: seconds between frames; gravity: (3,) m/s².
        rotation_model: as :func:`estimate_initial_velocity`'s.
    """
    K = est.frames_used
    if rotations.shape != (K, 3, 3) or translations.shape != (K, 3):
        raise ValueError(f"refit_to_poses: the estimate has {K} frames; got rotations {rotations.shape} and "
                         f"translations {translations.shape}")
    _check_rotation_model(rotation_model)
    P = points.detach().to("cpu", torch.float64).numpy()
    centre, inertia = _centre_and_inertia(P, rotation_model)
    g = torch.as_tensor(gravity).detach().to("cpu", torch.float64).numpy()
    times = np.arange(K) * dt
    centroids = rotations @ centre + translations
    model = _fit_ballistic(times, centroids, rotations, g, inertia if rotation_model == "torque_free" else None,
                           dt / 4.0)
    like = est.linear
    return dataclasses.replace(
        est, linear=torch.as_tensor(model.v, dtype=like.dtype, device=like.device),
        angular=torch.as_tensor(model.omega, dtype=like.dtype, device=like.device),
        rotations=torch.as_tensor(rotations, dtype=like.dtype, device=like.device),
        translations=torch.as_tensor(translations, dtype=like.dtype, device=like.device),
        model_residual_m=_model_rms(model, times, rotations, centroids, P - centre))


# ---- the stage -------------------------------------------------------------------------------------------------


class VelocityStage:
    """Estimates the initial rigid velocity from the ballistic frames (``config.velocity``); writes
    ``velocity.json``. A drop that meets the floor by frame 1 is estimated from frames 0 and 1 regardless of the
    floor (to first order; the joint optimisation refines it), and the record says so. The frames' silhouette poses
    are then refined on the images with the frame-0 Gaussians (:mod:`vid2sim.reconstruct.photo_poses`;
    ``velocity.photometric_iterations`` 0 skips it) and the velocity refitted to them; the record keeps the
    silhouettes' estimate beside it."""

    name = "velocity"
    sections = ("velocity",)
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        return "estimating the initial velocity from the pre-contact frames"

    def run(self, ctx: Context, state: State) -> None:
        o, cfg = ctx.observed, ctx.config.velocity
        gravity = torch.tensor(o.gravity, dtype=torch.float32)
        points = state.obj_cpu.points
        contact_before_frame_1 = False
        try:
            est = estimate_initial_velocity(points, o.masks_cpu, o.cameras_cpu, o.dt, gravity, o.floor_height,
                                            max_frames=cfg.frames)
        except TooFewBallisticFrames as exc:
            ctx.say(f"      {exc}; estimating from frames 0 and 1 regardless of the floor")
            est = estimate_initial_velocity(points, o.masks_cpu, o.cameras_cpu, o.dt, gravity, None, max_frames=2)
            contact_before_frame_1 = True
        record = {"contact_before_frame_1": contact_before_frame_1}
        if cfg.photometric_iterations > 0:
            photo = refine_poses(state.gaussians, o.images[:, :est.frames_used], o.cameras, est.rotations,
                                 est.translations, o.gravity, o.dt, iterations=cfg.photometric_iterations,
                                 max_size=cfg.photometric_size, max_views=cfg.photometric_views,
                                 loss=cfg.photometric_loss, progress=ctx.progress)
            record["silhouettes"] = {"linear": est.linear.tolist(), "angular": est.angular.tolist(),
                                     "rotations": est.rotations.tolist(), "translations": est.translations.tolist()}
            record["photometric"] = {"loss_start": photo.loss_start.tolist(), "loss": photo.loss.tolist(),
                                     "start": photo.start, "steps": photo.steps}
            est = refit_to_poses(est, points, photo.rotations, photo.translations, o.dt, gravity)
        write_json_atomic(ctx.path("velocity.json"), {
            **record, "linear": est.linear.tolist(),
            "angular": est.angular.tolist(), "centre": est.centre.tolist(), "frames_used": est.frames_used,
            "residual_px": est.residual_px, "rotations": est.rotations.tolist(),
            "translations": est.translations.tolist()})

    def load(self, ctx: Context, state: State) -> None:
        state.velocity = read_json(ctx.path("velocity.json"), "the initial-velocity estimate")
