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
   the points (:func:`_surface_samples`: binned, blurred, marching cubes at half the interior density),
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
rotation (a sphere, a spin about an axis of symmetry) has an unobservable ω. With only two usable frames
(contact between frames 1 and 2) the estimate is a finite difference, and a contact between frames 0 and
1 cannot be told from the data. Each frame's fit is independent (the model only initialises it), so a
poorly fitted frame is not rejected, only averaged by the least squares. The points must fill the object
uniformly for their centroid to be the centre of mass and their inertia the body's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.splats.cameras import Camera, stack_cameras

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


def _hat(w: np.ndarray) -> np.ndarray:
    """Skew matrices (..., 3, 3) with [w]× y = w × y, of vectors (..., 3)."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues)."""
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, 2.0 * np.sin(0.5 * safe) ** 2 / safe**2)
    k = _hat(w)
    return np.eye(3) + a * k + b * (k @ k)


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (angles in [0, π]) of rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-1])


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
        return _exp(times[:, None] * omega0[None]) @ R0
    inv = np.linalg.inv(inertia)
    L = R0 @ (inertia @ (R0.T @ omega0))
    out = np.empty((len(times), 3, 3))
    R, now = R0, 0.0
    for i, target in enumerate(times):
        if target - now > 1e-12:
            n = max(1, math.ceil((target - now) / max_step - 1e-9))
            h = (target - now) / n
            for _ in range(n):
                half = _exp(0.5 * h * (R @ (inv @ (R.T @ L)))) @ R
                R = _exp(h * (half @ (inv @ (half.T @ L)))) @ R
            now = float(target)
        out[i] = R
    return out


# =============================================================================================
# silhouettes
# =============================================================================================


def _prepare_silhouette(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mask (H, W) in [0, 1] prepared for fitting.

    Returns ``(field (H, W), boundary (M, 2))``. ``field`` is the signed distance (px) of each pixel centre
    from the mask's 0.5 iso-line, positive outside: on anti-aliased pixels 0.5 − m (a straight edge through
    a pixel that covers the fraction m lies 0.5 − m px from its centre), elsewhere the Euclidean distance
    transform to the nearest pixel on the other side minus 0.5 px. ``boundary`` holds the iso-line's
    crossings of the segments between 4-neighbouring pixel centres (x, y in pixels, centres at +0.5),
    linearly interpolated.
    """
    from scipy.ndimage import distance_transform_edt

    m = mask.astype(np.float64)
    inside = m >= 0.5
    field = np.where(inside, 0.5 - distance_transform_edt(inside), distance_transform_edt(~inside) - 0.5)
    frac = (m > 1e-3) & (m < 1.0 - 1e-3)
    field = np.where(frac, 0.5 - m, field)
    samples = []
    for axis in (0, 1):
        a = m[:-1, :] if axis == 0 else m[:, :-1]
        b = m[1:, :] if axis == 0 else m[:, 1:]
        r, c = np.nonzero((a - 0.5) * (b - 0.5) < 0)
        f = (a[r, c] - 0.5) / (a[r, c] - b[r, c])
        x = c + 0.5 + (f if axis == 1 else 0.0)
        y = r + 0.5 + (f if axis == 0 else 0.0)
        samples.append(np.stack([x, y], -1))
    return field, np.concatenate(samples, 0)


def _surface_samples(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray | None:
    """At most ``n`` points (M, 3) on a smooth estimate of the surface of the solid that ``points`` (N, 3) fill.

    The silhouette of a solid is the projection of its surface, but interior samples stop short of the
    surface by a random, direction-dependent gap (a sparse rim): fitted to silhouettes they leave the pose,
    above all the rotation, uncertain by a degree or two. So the surface is taken from
    :func:`vid2sim.reconstruct.stages.calibration.solid_surface` (binned on a grid of their mean nearest-neighbour spacing,
    at most 160 cells a side, blurred, marching cubes at half the density). Returns None when none is found.
    """
    from vid2sim.reconstruct.stages.calibration import solid_surface

    surface = solid_surface(points, cells=160, rng=rng)
    if surface is None:
        return None
    verts = surface[0]
    return verts if len(verts) <= n else verts[rng.choice(len(verts), n, replace=False)]


class _PoseFit:
    """The silhouette objective of one frame (V views) as a function of a rigid pose.

    A pose (R (3, 3), p (3,)) places the centred shape points Xc (N, 3) at x = R Xc + p. Residuals, in
    pixels: per view, every point's distance outside the mask (weight 1/(V N)), and every boundary sample's
    distance to its nearest projected point (weight 1/(V M_v)). Only points projecting within
    ``candidate_px`` of the boundary or outside it are searched for the nearest one (the nearest point of a
    boundary sample at distance d lies within d of the boundary, so this is exact whenever d is smaller).
    """

    candidate_px = 4.0

    def __init__(self, Xc: np.ndarray, viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
                 silhouettes: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.Xc, self.Rv, self.tv, self.Ks = Xc, viewmats[:, :3, :3], viewmats[:, :3, 3], Ks
        self.width, self.height = width, height
        self.fields = [s[0] for s in silhouettes]
        self.boundary = [s[1] for s in silhouettes]

    def _project(self, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels (V, N, 2) of the points posed by (R, p), their rotated offsets y = R Xc (N, 3) and camera
        coordinates (V, N, 3)."""
        y = self.Xc @ R.T
        cam = np.matmul((y + p)[None], self.Rv.transpose(0, 2, 1)) + self.tv[:, None, :]
        z = np.maximum(cam[..., 2], 1e-6)
        pix = np.stack([self.Ks[:, None, 0, 0] * cam[..., 0] / z + self.Ks[:, None, 0, 2],
                        self.Ks[:, None, 1, 1] * cam[..., 1] / z + self.Ks[:, None, 1, 2]], -1)
        return pix, y, cam

    def _jacobian(self, v: int, y: np.ndarray, cam: np.ndarray) -> np.ndarray:
        """Derivatives (n, 2, 6) of the pixels of n points in view v (rotated offsets y (n, 3), camera
        coordinates cam (n, 3)) with respect to a left rotation increment ρ (R ← exp(ρ) R) and a
        translation increment τ (p ← p + τ)."""
        z = np.maximum(cam[:, 2], 1e-6)
        fx, fy = self.Ks[v, 0, 0], self.Ks[v, 1, 1]
        d = np.zeros((len(z), 2, 3))
        d[:, 0, 0], d[:, 0, 2] = fx / z, -fx * cam[:, 0] / z**2
        d[:, 1, 1], d[:, 1, 2] = fy / z, -fy * cam[:, 1] / z**2
        dpix_dx = d @ self.Rv[v]  # (n, 2, 3)
        return np.concatenate([-dpix_dx @ _hat(y), dpix_dx], -1)  # d(ρ × y)/dρ = −[y]×

    def _sample(self, v: int, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) of pixels (N, 2) from the mask boundary of view v (bilinear, border-clamped,
        plus the distance beyond the image; positive outside) and its gradient (N, 2)."""
        field = self.fields[v]
        H, W = field.shape
        xs, ys = pix[:, 0] - 0.5, pix[:, 1] - 0.5
        cx, cy = np.clip(xs, 0.0, W - 1.0), np.clip(ys, 0.0, H - 1.0)
        i0 = np.minimum(np.floor(cx).astype(np.int64), W - 2)
        j0 = np.minimum(np.floor(cy).astype(np.int64), H - 2)
        fx, fy = cx - i0, cy - j0
        f00, f01 = field[j0, i0], field[j0, i0 + 1]
        f10, f11 = field[j0 + 1, i0], field[j0 + 1, i0 + 1]
        value = (1 - fy) * ((1 - fx) * f00 + fx * f01) + fy * ((1 - fx) * f10 + fx * f11)
        gx = np.where(cx == xs, (1 - fy) * (f01 - f00) + fy * (f11 - f10), 0.0)
        gy = np.where(cy == ys, (1 - fx) * (f10 - f00) + fx * (f11 - f01), 0.0)
        u, w = pix[:, 0], pix[:, 1]
        value = value + np.maximum(-u, 0) + np.maximum(u - W, 0) + np.maximum(-w, 0) + np.maximum(w - H, 0)
        gx = gx - (u < 0) + (u > W)
        gy = gy - (w < 0) + (w > H)
        return value, np.stack([gx, gy], -1)

    def evaluate(self, R: np.ndarray, p: np.ndarray, jacobian: bool = True
                 ) -> tuple[float, np.ndarray, np.ndarray, list[tuple[float, float]]]:
        """The loss at (R, p); the Gauss–Newton system JᵀWJ (6, 6) and JᵀWr (6,) (zeros unless ``jacobian``);
        and per view the mean outside distance and the mean coverage distance (px)."""
        from scipy.spatial import cKDTree

        pix, y, cam = self._project(R, p)
        V, N = pix.shape[:2]
        loss, A, g, means = 0.0, np.zeros((6, 6)), np.zeros(6), []
        for v in range(V):
            signed, grad = self._sample(v, pix[v])
            active = np.nonzero(signed > 0)[0]
            o = signed[active]
            w_out = 1.0 / (V * N)
            b = self.boundary[v]
            w_cov = 1.0 / (V * max(len(b), 1))
            near = np.nonzero(signed > -self.candidate_px)[0]
            if len(near) == 0:
                near = np.arange(N)
            dist, j = cKDTree(pix[v, near]).query(b) if len(b) else (np.zeros(0), np.zeros(0, np.int64))
            idx = near[j]
            loss += w_out * float(o @ o) + w_cov * float(dist @ dist)
            means.append((float(o.sum()) / N, float(dist.mean()) if len(b) else 0.0))
            if not jacobian:
                continue
            Jo = (grad[active, None, :] @ self._jacobian(v, y[active], cam[v, active]))[:, 0]
            A += w_out * Jo.T @ Jo
            g += w_out * Jo.T @ o
            keep = dist > 0
            off = pix[v, idx[keep]] - b[keep]
            unit = off / dist[keep, None]
            Jc = (unit[:, None, :] @ self._jacobian(v, y[idx[keep]], cam[v, idx[keep]]))[:, 0]
            A += w_cov * Jc.T @ Jc
            g += w_cov * Jc.T @ dist[keep]
        return loss, A, g, means

    def fit(self, R: np.ndarray, p: np.ndarray, metres_per_px: float, radius: float, iterations: int
            ) -> tuple[np.ndarray, np.ndarray, float]:
        """Levenberg–Marquardt from (R, p); returns the fitted (R (3, 3), p (3,)) and the residual (px)."""
        loss, A, g, means = self.evaluate(R, p)
        lam = 1e-3
        for _ in range(iterations):
            diag = np.maximum(np.diag(A), 1e-12 * max(float(np.diag(A).max()), 1e-30))
            step = np.linalg.solve(A + lam * np.diag(diag), -g)
            R_new, p_new = _exp(step[:3]) @ R, p + step[3:]
            new, A_new, g_new, means_new = self.evaluate(R_new, p_new)
            moved_px = (np.linalg.norm(step[:3]) * radius + np.linalg.norm(step[3:])) / metres_per_px
            if new <= loss:
                done = loss - new <= 1e-6 * loss or moved_px < 5e-3
                R, p, loss, A, g, means = R_new, p_new, new, A_new, g_new, means_new
                lam = max(lam / 3.0, 1e-7)
                if done:
                    break
            else:
                lam *= 4.0
                if lam > 1e6 or moved_px < 1e-4:
                    break
        return R, p, float(np.mean([0.5 * (a + b) for a, b in means]))


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
    logs = _log(rotations @ rotations[0].T)
    omega = (times[:, None] * logs).sum(0) / max(float(times @ times), 1e-30)

    def residuals(x: np.ndarray) -> np.ndarray:
        R0 = _exp(x[:3]) @ rotations[0]
        pred = propagate_rotations(R0, x[3:], inertia, times, max_step)
        return _log(rotations.transpose(0, 2, 1) @ pred).reshape(-1)

    fit = least_squares(residuals, np.concatenate([np.zeros(3), omega]), method="lm", xtol=1e-12, ftol=1e-12)
    return _Ballistic(p0, v, gravity, _exp(fit.x[:3]) @ rotations[0], fit.x[3:], inertia, max_step)


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
        if isinstance(floor_height, bool) or not isinstance(floor_height, (int, float)) or not math.isfinite(floor_height):
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
            reconstructed from the points, :func:`_surface_samples`; falls back to the points when none is
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
    name = "estimate_initial_velocity"
    gravity = torch.as_tensor(gravity).detach().to("cpu", torch.float64)
    _check_inputs(points, masks, cameras, dt, gravity, floor_height, max_frames)
    if rotation_model not in ROTATION_MODELS:
        raise ValueError(f"{name}: rotation_model must be one of {ROTATION_MODELS}, got {rotation_model!r}")
    if not (math.isfinite(floor_margin) and floor_margin >= 0):
        raise ValueError(f"{name}: floor_margin must be a finite number >= 0, got {floor_margin!r}")
    if shape_model not in SHAPE_MODELS:
        raise ValueError(f"{name}: shape_model must be one of {SHAPE_MODELS}, got {shape_model!r}")
    if max_points < 4 or iterations < 1:
        raise ValueError(f"{name}: max_points must be >= 4 and iterations >= 1, got {max_points}, {iterations}")
    device = points.device
    out_dtype = points.dtype if points.is_floating_point() else torch.float32
    g = gravity.detach().to("cpu", torch.float64).numpy()
    P = points.detach().to("cpu", torch.float64).numpy()
    V, T, H, W = masks.shape
    K_max = min(int(max_frames), T)
    masks_np = masks.detach()[:, :K_max].to("cpu", torch.float32).numpy()
    for t in range(K_max):
        for v in range(V):
            if not (masks_np[v, t] >= 0.5).any():
                raise ValueError(f"{name}: the mask of view {v} at frame {t} is empty (no pixel >= 0.5); the object "
                                 "must be visible in every view of the frames used")
    viewmats_t, Ks_t, width, height = stack_cameras(list(cameras))
    viewmats, Ks = viewmats_t.detach().cpu().double().numpy(), Ks_t.detach().cpu().double().numpy()

    centre = P.mean(0)
    r = P - centre
    inertia = (r * r).sum(1).mean() * np.eye(3) - r.T @ r / len(r)
    evals = np.linalg.eigvalsh(inertia)
    if rotation_model == "torque_free" and evals[0] <= 1e-9 * evals[-1]:
        raise ValueError(f"{name}: the points are degenerate (collinear): their inertia tensor is singular")
    radius = float(np.linalg.norm(r, axis=1).max())
    rng = np.random.default_rng(seed)
    subset = r[rng.choice(len(r), max_points, replace=False)] if len(r) > max_points else r

    # the cameras must see the points, and the frame-0 masks must match them
    cam = np.einsum("vij,nj->vni", viewmats[:, :3, :3], subset + centre) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    for v in range(V):
        if (z[v] <= 1e-6).any():
            raise ValueError(f"{name}: camera {v} does not see the points: some lie behind it (check the camera "
                             "poses and that the points are in the same world frame)")
    zs = np.maximum(z, 1e-6)
    u = Ks[:, None, 0, 0] * cam[..., 0] / zs + Ks[:, None, 0, 2]
    w = Ks[:, None, 1, 1] * cam[..., 1] / zs + Ks[:, None, 1, 2]
    in_image = (u >= 0) & (u < width) & (w >= 0) & (w < height)
    col, row = np.clip(np.floor(u), 0, width - 1).astype(np.int64), np.clip(np.floor(w), 0, height - 1).astype(np.int64)
    for v in range(V):
        seen = float(in_image[v].mean())
        if seen < 0.5:
            raise ValueError(f"{name}: camera {v} does not see the points: only {100 * seen:.0f} % of them project "
                             f"into its {width}x{height} image")
        matched = float(((masks_np[v, 0][row[v], col[v]] > 0.25) & in_image[v]).mean())
        if matched < 0.5:
            raise ValueError(f"{name}: the points do not match the frame-0 mask of view {v}: only {100 * matched:.0f} % "
                             "of them project inside it (are they the object at frame 0, in the cameras' world frame?)")
    metres_per_px = float(z.mean()) / float(Ks[:, [0, 1], [0, 1]].mean())
    surface = _surface_samples(P, max_points, rng) if shape_model == "surface" else None
    Xc = subset if surface is None else surface - centre  # the points the silhouettes are fitted with

    up = -g / np.linalg.norm(g) if floor_height is not None else None
    max_step = dt / 4.0
    model_inertia = inertia if rotation_model == "torque_free" else None

    def clearance(R: np.ndarray, p: np.ndarray) -> float:
        """Height (m) above the floor of the lowest given point posed by (R, p)."""
        assert up is not None and floor_height is not None
        return float(((r @ R.T + p) @ up).min()) - float(floor_height)

    def predicted_contact(model: _Ballistic, t0: float, t1: float) -> float | None:
        """The first of 9 times in [t0, t1] at which the model's lowest point is within the margin, if any."""
        if up is None:
            return None
        times = np.linspace(t0, t1, 9)
        for s, R, p in zip(times, model.rotations(times), model.centroids(times)):
            if clearance(R, p) <= floor_margin:
                return float(s)
        return None

    def fit_frame(t: int, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        fitter = _PoseFit(Xc, viewmats, Ks, width, height, [_prepare_silhouette(masks_np[v, t]) for v in range(V)])
        return fitter.fit(R, p, metres_per_px, radius, iterations)

    def say(message: str) -> None:
        if progress:
            print(f"[initial velocity] {message}", flush=True)

    R_fit, p_fit, res = fit_frame(0, np.eye(3), centre.copy())
    rotations, centroids, residuals = [R_fit], [p_fit], [res]
    if model_inertia is not None:
        # the fitted poses place the points, not the object: frame 0's fit may be turned by degrees where the
        # silhouettes pin the shape loosely (up to 15° on a rounded benchmark object). The ballistic model
        # propagates those poses, so its inertia is the points' frame-0 inertia seen from frame 0's fitted
        # orientation (R₀ I_body R₀ᵀ = the frame-0 inertia).
        model_inertia = R_fit.T @ model_inertia @ R_fit
    say(f"frame 0: residual {res:.2f} px")
    if up is not None and clearance(R_fit, p_fit) <= floor_margin:
        raise TooFewBallisticFrames(
            f"{name}: fewer than 2 usable frames: the object already touches the floor at frame 0 (its lowest point "
            f"is {1000 * clearance(R_fit, p_fit):.1f} mm above it, margin {1000 * floor_margin:.1f} mm)"
        )
    model: _Ballistic | None = None
    stop = "max_frames" if K_max == max_frames else "end of the masks"
    for t in range(1, K_max):
        if model is not None:
            hit = predicted_contact(model, (t - 1) * dt, t * dt)
            if hit is not None:
                stop = f"contact predicted at {hit:.3f} s, before frame {t}"
                break
            R_init, p_init = model.rotations([t * dt])[0], model.centroids([t * dt])[0]
        else:  # frame 1: frame 0's pose, falling from rest
            R_init, p_init = rotations[0], centroids[0] + 0.5 * g * dt * dt
        R_fit, p_fit, res = fit_frame(t, R_init, p_init)
        say(f"frame {t}: residual {res:.2f} px")
        if up is not None and clearance(R_fit, p_fit) <= floor_margin:
            stop = f"frame {t} reaches the floor (fitted lowest point {1000 * clearance(R_fit, p_fit):.1f} mm above it)"
            break
        times = np.arange(t + 1) * dt
        trial = _fit_ballistic(times, np.stack(centroids + [p_fit]), np.stack(rotations + [R_fit]), g,
                               model_inertia, max_step)
        hit = predicted_contact(trial, 0.0, t * dt)
        if hit is not None:
            stop = f"the fit with frame {t} predicts contact at {hit:.3f} s"
            break
        rotations.append(R_fit)
        centroids.append(p_fit)
        residuals.append(res)
        model = trial
    K = len(rotations)
    if model is None:
        raise TooFewBallisticFrames(f"{name}: fewer than 2 usable frames ({stop}); the velocity needs frames 0 and 1 before "
                         "any contact with the floor")

    Rs, ps = np.stack(rotations), np.stack(centroids)
    times = np.arange(K) * dt
    posed_fit = np.einsum("kij,nj->kni", Rs, Xc) + ps[:, None]
    posed_model = np.einsum("kij,nj->kni", model.rotations(times), Xc) + model.centroids(times)[:, None]
    model_rms = float(np.sqrt(((posed_fit - posed_model) ** 2).sum(-1).mean()))
    say(f"{K} frames: v = {np.round(model.v, 4).tolist()} m/s, ω = {np.round(model.omega, 4).tolist()} rad/s ({stop})")

    def out(a: np.ndarray) -> Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=out_dtype, device=device)

    # frame t's pose relative to frame 0's fit: a bias the fits share (the silhouettes pinning a rounded shape's
    # turn loosely) cancels, and frame 0 maps exactly to itself. On the small benchmark suite the absolute fits
    # are 0.1–17° off the true rotation of frames 1–4, the relative ones 0.2–2.2°.
    rel = Rs @ Rs[0].T
    return InitialVelocity(
        linear=out(model.v),
        angular=out(model.omega),
        centre=out(centre),
        frames_used=K,
        residual_px=float(np.mean(residuals)),
        rotations=out(rel),
        translations=out(ps - rel @ ps[0]),
        frame_residuals_px=out(np.array(residuals)),
        model_residual_m=model_rms,
        stop_reason=stop,
        seconds=time.perf_counter() - start,
    )
