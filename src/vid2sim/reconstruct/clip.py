"""The observed clip as the joint optimisation sees it: the observed images, renders of simulated states, losses.

:class:`Observations` holds the observed views' frames (at full size, or area-averaged to a coarser scale);
:func:`render_states` renders simulated states through a :class:`~vid2sim.asset.motion.GaussianRig` at the
observations' size; :func:`image_loss` is the paper's mean squared image error and :func:`clip_loss` its weighted
mean over a whole simulated clip (:func:`frame_weights`). Both joint methods (:mod:`vid2sim.reconstruct.gauss_newton`,
:mod:`vid2sim.reconstruct.windows`) and the stage (:mod:`vid2sim.reconstruct.stages.joint`) build on these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.asset.motion import GaussianRig
from vid2sim.physics.solver import SimState, Simulator
from vid2sim.splats.cameras import Camera
from vid2sim.splats.render import render


@dataclass
class Observations:
    """The observed video as the optimisation sees it.

    Attributes:
        images: (V, T, H, W, 3) observed frames 0 … T−1 of the observed views, composited on white, float.
        cameras: the V cameras.
        background: RGB background (white for vid2sim scenes).
    """

    images: Tensor
    cameras: list[Camera]
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def at_scale(self, scale: float) -> "Observations":
        """The same observations at ``scale`` × the resolution: area-averaged images, the same cameras.

        The renders of a scaled loss are made at the cameras' full resolution and area-averaged to the images' size
        (:func:`render_states`), so that both sides of the loss pass through the same filter. Gaussians rendered
        directly by half-size cameras are not the average of their full-size render (a splat's footprint does not
        shrink with the pixel grid below a pixel): on the small suite that left a floor of 3.6e-3 in the frame-0 loss
        at half resolution against 4e-5 at full, 70 % of the coarse search's loss at its minimum (docs/architecture.md,
        "The coarse losses' resolution"). At the small preset rendering at full size costs about the same on the CPU
        (the per-Gaussian work dominates); at 448² the pixels count."""
        if scale == 1.0:
            return self
        V, T, H, W, _ = self.images.shape
        h, w = max(8, round(H * scale)), max(8, round(W * scale))
        return Observations(downsample(self.images.reshape(V * T, H, W, 3), (h, w)).reshape(V, T, h, w, 3),
                            self.cameras, self.background)


def downsample(images: Tensor, size: tuple[int, int]) -> Tensor:
    """(..., H, W, 3) images area-averaged to (..., h, w, 3) (the input itself when the size is already (h, w))."""
    if tuple(images.shape[-3:-1]) == tuple(size):
        return images
    lead = images.shape[:-3]
    x = images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x, size=size, mode="area")
    return x.permute(0, 2, 3, 1).reshape(*lead, *size, 3)


def detached_state(state: SimState) -> SimState:
    """``state`` with every tensor detached from its graph (the same step and time)."""
    d = (lambda t: None if t is None else t.detach())
    return SimState(d(state.z), d(state.zdot), state.t, d(state.Fp_inv), z_prev=d(state.z_prev),
                    zdot_prev=d(state.zdot_prev), h_prev=state.h_prev)


def render_states(rig: GaussianRig, states: Sequence[SimState], obs: Observations, views: Sequence[int],
                  basis: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """(len(states), len(views), H, W, 3) renders of the states in the given views of ``obs``, at the size of
    ``obs.images`` (rendered by the cameras at their own size and area-averaged to it, :meth:`Observations.at_scale`).

    All frames go to the renderer in one call (per-view Gaussians: frame t's Gaussians for frame t's
    cameras), which composites them together; with gsplat that is one batched launch. On the CPU it saves
    6 % at the small preset's 4 frames × 4 views (forward + backward 390 → 368 ms, 1 thread)."""

    basis = rig.basis() if basis is None else basis
    cams = [obs.cameras[v] for v in views]
    nv = len(cams)
    size = tuple(obs.images.shape[2:4])
    if rig.shading is not None:  # colours differ per frame: one call per frame
        frames = [rig.deformed(s.z, basis) for s in states]
        out = torch.stack([render(d.means, d.opacities, d.sh, cams, covars=d.covars, sh_degree=d.sh_degree,
                                  background=list(obs.background)).rgb for d in frames])
        return downsample(out, size)
    means, covars = rig.deformed_frames(torch.stack([s.z for s in states]), basis)  # all frames in one batch
    g = rig.gaussians
    out = render(means.repeat_interleave(nv, dim=0), g.opacities, g.sh, cams * len(states),  # (T·V, N, 3)
                 covars=covars.repeat_interleave(nv, dim=0), sh_degree=g.sh_degree, background=list(obs.background)).rgb
    return downsample(out.reshape(len(states), nv, *out.shape[1:]), size)


def image_loss(renders: Tensor, targets: Tensor) -> Tensor:
    """The mean squared image error (the paper's loss), a scalar."""
    return ((renders - targets) ** 2).mean()


def frame_weights(frames: int, decay: float | None) -> list[float]:
    """Weights of frames 1 … frames−1 in a whole-clip loss, summing to 1: exp(−(t − 1)/decay), or equal
    when ``decay`` is None."""
    raw = [1.0 if decay is None else math.exp(-(t - 1) / decay) for t in range(1, frames)]
    total = sum(raw)
    return [w / total for w in raw]  # empty for a one-frame clip


def clip_loss(sim: Simulator, rig: GaussianRig, start: SimState, obs: Observations,
              decay: float | None = None) -> tuple[float, list[SimState]]:
    """Weighted mean squared image error of the whole observed clip (frames 1 … T−1, all views; weights
    :func:`frame_weights`), without gradients, and the simulated states of frames 0 … T−1 (frame 0 =
    ``start``).

    Equal weights (``decay`` None) judge the clip as a whole, and its late frames weigh as much as the first
    bounce. After that bounce a stiff object rocks on the frictionless floor, and where it rocks to drifts
    chaotically with small errors of the model; a whole-clip loss then favours the material whose rocking
    happens to match, often a softer one. Decaying weights favour the first contact, where E acts most
    directly."""
    with torch.no_grad():
        states = [start] + sim.rollout(start, obs.images.shape[1] - 1)
    return trajectory_clip_loss(rig, states, obs, decay), states


def trajectory_clip_loss(rig: GaussianRig, states: Sequence[SimState], obs: Observations,
                         decay: float | None = None) -> float:
    """:func:`clip_loss` of simulated states: ``states[t]`` is frame t's, t = 0 … T−1 (T = the frames of ``obs``)."""
    T = obs.images.shape[1]
    if len(states) != T:
        raise ValueError(f"trajectory_clip_loss: {len(states)} states for a clip of {T} frames")
    losses = frame_losses(rig, states[1:], obs, range(1, T), rig.basis())
    return sum(w * v for w, v in zip(frame_weights(T, decay), losses))


def frame_losses(rig: GaussianRig, states: Sequence[SimState], obs: Observations, frames: Sequence[int],
                 basis: tuple[Tensor, Tensor] | None = None) -> list[float]:
    """The image loss (:func:`image_loss`, every view of ``obs``) of each observed frame in ``frames`` (indices into
    ``obs.images``' frame axis), ``states[i]`` the simulated state of ``frames[i]``; one frame rendered at a time,
    without gradients."""
    with torch.no_grad():
        out = []
        for state, t in zip(states, frames):
            r = render_states(rig, [state], obs, range(len(obs.cameras)), basis)[0]
            out.append(float(image_loss(r, obs.images[:, t].to(r))))
    return out
