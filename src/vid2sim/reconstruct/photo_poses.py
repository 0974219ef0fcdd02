"""The ballistic frames' rigid poses refined on the images, not only on the silhouettes.

The ``velocity`` stage fits each pre-contact frame's rigid pose to the masks (:mod:`vid2sim.reconstruct.silhouettes`).
An outline pins a pose only as far as it changes with it: a rounded body, or a shape carved loosely from a
capture's masks, leaves its turn nearly free. On a capture twin of the small suite the silhouette fits turned the body
by 11, 26 and 38° over frames 1–3 where the truth turned 1.4, 2.9 and 4.3°, and fitting the same shape to the true
masks did not help (9–16°): the shape, not the masks, was off. The angular velocity, the appearance stage's virtual
views and the joint fit's start all inherit such a turn (docs/capture.md, "Measured", ninth entry).

The body's texture pins the turn. :func:`refine_poses` renders the frame-0 Gaussians moved rigidly by each frame's
pose into every observed view and minimises the mean absolute difference from that frame's images over a small
rotation and translation about the posed body's centre (Adam, from the silhouette pose or from the refined poses'
constant-velocity extrapolation, whichever matches better). On that twin the turns became 0.9, 2.0 and 3.3° (errors
0.6–1.2° against 11–38°); where the silhouettes were right already the two agree to a few tenths of a degree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.reconstruct.clip import downsample
from vid2sim.splats.cameras import Camera
from vid2sim.splats.deform import deform_gaussians
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.render import render_gaussians


@dataclass
class PhotoPoses:
    """Rigid poses of frames 0 … K−1 relative to frame 0 (float64 numpy): frame t maps a frame-0 point X to
    ``rotations[t] @ X + translations[t]``; frame 0 is the identity.

    Attributes:
        rotations: (K, 3, 3); translations: (K, 3).
        loss_start: (K,) each frame's loss at the pose it started from (frame 0: its own, at the identity);
            loss: (K,) the same at the refined pose.
        start: (K,) where each frame's refinement started: ``"silhouettes"`` or ``"extrapolated"`` (frame 0:
            ``"identity"``).
        steps: (K,) Adam steps taken per frame (frame 0: 0).
    """

    rotations: np.ndarray
    translations: np.ndarray
    loss_start: np.ndarray
    loss: np.ndarray
    start: list[str]
    steps: list[int]


_CHECK_EVERY = 10  # steps between the stopping rule's checks
_STOP_GAIN = 1e-3  # stop when the best loss fell by less than this fraction since the last check


def _hat(w: Tensor) -> Tensor:
    """(3, 3) skew matrix of a (3,) vector, differentiable."""
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


LOSSES = ("l1", "gradients")


def _gradients(images: Tensor) -> tuple[Tensor, Tensor]:
    """The differences of neighbouring pixels of (V, H, W, 3) images, down and across."""
    return images[:, 1:] - images[:, :-1], images[:, :, 1:] - images[:, :, :-1]


class _FrameMatch:
    """One frame's image loss as a function of a rigid pose of the frame-0 Gaussians: ``"l1"``, the mean absolute
    difference of the colours, or ``"gradients"``, that of their differences between neighbouring pixels (the
    texture's and the outline's edges; a smooth shading the Gaussians carry from frame 0 while the light stays put
    weighs less in it)."""

    def __init__(self, gaussians: Gaussians, images: Tensor, cameras: Sequence[Camera], kind: str = "l1") -> None:
        self.gaussians, self.images, self.cameras = gaussians, images, list(cameras)
        self.means = gaussians.means.detach()
        self.size = tuple(images.shape[1:3])
        self.edges = _gradients(images) if kind == "gradients" else None

    def loss(self, R: Tensor, T: Tensor) -> Tensor:
        """The loss with the Gaussians at ``R (3, 3) @ X + T (3,)``."""
        n = self.means.shape[0]
        moved = deform_gaussians(self.gaussians, self.means @ R.T + T, R.expand(n, 3, 3))
        rgb = downsample(render_gaussians(moved, self.cameras).rgb, self.size)
        if self.edges is None:
            return (rgb - self.images).abs().mean()
        down, across = _gradients(rgb)
        return (down - self.edges[0]).abs().mean() + (across - self.edges[1]).abs().mean()


def _refine_frame(match: _FrameMatch, R0: Tensor, T0: Tensor, radius: float, iterations: int, lr: float
                  ) -> tuple[Tensor, Tensor, float, int]:
    """Adam over a rotation vector w and a translation d (in units of ``radius``) about the posed centre c:
    X ↦ exp([w]×)(R0 X + T0 − c) + c + radius·d, stopped early once the loss settles (under 0.1 % lower than 10
    steps before). Returns the best pose seen (R, T), its loss and the steps taken."""
    c = (match.means @ R0.T + T0).mean(0)
    w = torch.zeros(3, dtype=R0.dtype, device=R0.device, requires_grad=True)
    d = torch.zeros(3, dtype=R0.dtype, device=R0.device, requires_grad=True)
    opt = torch.optim.Adam([w, d], lr=lr)
    decay = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.1 ** (1.0 / max(iterations, 1)))

    def pose(w: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        Rw = torch.linalg.matrix_exp(_hat(w))
        return Rw @ R0, Rw @ (T0 - c) + c + radius * d

    best, best_then, steps = math.inf, math.inf, 0
    kept = (w.detach().clone(), d.detach().clone())
    for i in range(iterations):
        opt.zero_grad()
        loss = match.loss(*pose(w, d))
        loss.backward()
        if float(loss.detach()) < best:
            best, kept = float(loss.detach()), (w.detach().clone(), d.detach().clone())
        if i % _CHECK_EVERY == 0:
            if best_then - best < _STOP_GAIN * best:  # settled: under 0.1 % better in the last steps
                break
            best_then = best
        opt.step()
        decay.step()
        steps += 1
    with torch.no_grad():
        R, T = pose(*kept)
        return R, T, float(match.loss(R, T)), steps


def _extrapolate(Rs: list[Tensor], Ts: list[Tensor], centre: Tensor, gravity_step: Tensor) -> tuple[Tensor, Tensor]:
    """Frame t's pose from frames t−2 and t−1 at constant spin and under gravity (``gravity_step`` = g dt²)."""
    turn = Rs[-1] @ Rs[-2].T
    c1, c2 = Rs[-1] @ centre + Ts[-1], Rs[-2] @ centre + Ts[-2]
    R = turn @ Rs[-1]
    return R, 2 * c1 - c2 + gravity_step - R @ centre


def refine_poses(gaussians: Gaussians, images: Tensor, cameras: Sequence[Camera], rotations: Tensor,
                 translations: Tensor, gravity: Sequence[float], dt: float, *, iterations: int = 150,
                 lr: float = 3e-3, max_size: int = 128, max_views: int = 0, loss: str = "l1",
                 progress: bool = False) -> PhotoPoses:
    """Refine the rigid poses of frames 1 … K−1 on the images (module docstring).

    Args:
        gaussians: the frame-0 Gaussians (world frame, on the device the renders run on).
        images: (V, K, H, W, 3) the observed views' frames 0 … K−1, in [0, 1], composited on white.
        cameras: the V cameras.
        rotations, translations: (K, 3, 3) and (K, 3): the silhouette poses relative to frame 0 (frame 0 the
            identity), as :class:`~vid2sim.reconstruct.stages.velocity.InitialVelocity` holds them.
        gravity: (3,) m/s²; dt: seconds between frames (for the extrapolated starts).
        iterations: Adam steps per frame (the learning rate decays tenfold over them).
        lr: Adam's step, radians for the turn and the body's radius for the shift.
        max_size: the loss's images' longer side at most: the renders (made at the cameras' size) and the images
            area-averaged to it, so both pass through one filter (0: the images' own size). Rendering with
            cameras scaled down instead is not the same filter (a splat does not shrink below a pixel) and turned
            the poses 0.4–0.8° on the test ball.
        max_views: the loss reads at most this many of the views, spread over their order (0: all).
        loss: ``"l1"`` (colours) or ``"gradients"`` (their differences between neighbouring pixels), see
            ``_FrameMatch``.
        progress: print one line per frame.

    Returns:
        :class:`PhotoPoses`.
    """
    V, K, H, W, _ = images.shape
    if rotations.shape != (K, 3, 3) or translations.shape != (K, 3) or len(cameras) != V:
        raise ValueError(f"refine_poses: {K} frames of {V} views need rotations (K, 3, 3), translations (K, 3) and "
                         f"{V} cameras, got {tuple(rotations.shape)}, {tuple(translations.shape)}, {len(cameras)}")
    if loss not in LOSSES:
        raise ValueError(f"refine_poses: loss must be one of {LOSSES}, got {loss!r}")
    if max_views > 0 and V > max_views:
        keep = np.unique(np.linspace(0, V - 1, max_views).round().astype(int)).tolist()
        images, cameras, V = images[keep], [cameras[v] for v in keep], len(keep)
    dev, dtype = gaussians.means.device, gaussians.means.dtype
    scale = 1.0 if max_size <= 0 or max(H, W) <= max_size else max_size / max(H, W)
    h, w = max(8, round(H * scale)), max(8, round(W * scale))
    cams = [c.to(dev) for c in cameras]
    frames = images.to(dev, dtype)
    if (h, w) != (H, W):
        frames = downsample(frames.reshape(V * K, H, W, 3), (h, w)).reshape(V, K, h, w, 3)
    means = gaussians.means.detach()
    centre = means.mean(0)
    radius = float((means - centre).norm(dim=1).max())
    g_step = torch.as_tensor(gravity, dtype=dtype, device=dev) * dt * dt
    Rs = [torch.eye(3, dtype=dtype, device=dev)]
    Ts = [torch.zeros(3, dtype=dtype, device=dev)]
    with torch.no_grad():
        first = float(_FrameMatch(gaussians, frames[:, 0], cams, loss).loss(Rs[0], Ts[0]))
    at_start, at_end, start, steps = [first], [first], ["identity"], [0]
    for t in range(1, K):
        match = _FrameMatch(gaussians, frames[:, t], cams, loss)
        starts = {"silhouettes": (rotations[t].to(dev, dtype), translations[t].to(dev, dtype))}
        if t >= 2:
            starts["extrapolated"] = _extrapolate(Rs, Ts, centre, g_step)
        with torch.no_grad():
            scored = {k: float(match.loss(*pose)) for k, pose in starts.items()}
        best = min(scored, key=scored.get)
        R, T, final, taken = _refine_frame(match, *starts[best], radius, iterations, lr)
        Rs.append(R)
        Ts.append(T)
        at_start.append(scored[best])
        at_end.append(final)
        start.append(best)
        steps.append(taken)
        if progress:
            turn = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(R)) - 1) / 2))))
            print(f"[photometric poses] frame {t}: loss {scored[best]:.5f} -> {final:.5f} from the {best} pose, "
                  f"turned {turn:.2f} deg from frame 0, {taken} steps", flush=True)
    return PhotoPoses(torch.stack(Rs).double().cpu().numpy(), torch.stack(Ts).double().cpu().numpy(),
                      np.array(at_start), np.array(at_end), start, steps)
