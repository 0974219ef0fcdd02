"""The state at the end of the observed clip, fitted to its last frames: where the prediction goes on from.

The fitted simulation is one rollout from frame 0. After the bounces its errors have accumulated (small-suite
scenes end the observed clip 1–3 cm and several degrees off the truth), and a prediction that goes on from there
starts that far off. The observed frames say where the body is at their end: this stage fits the state at frame
a = T − ``window`` (T the observed frames) to frames a … T − 1 and stores it in the asset
(:attr:`~vid2sim.asset.folder.Asset.continuation`), and the captured drop goes on from it after the observed
frames (:func:`~vid2sim.asset.motion.simulate_states`). The observed frames themselves stay the rollout from frame
0, so the dynamic reconstruction's score is still the physics' own.

The fitted unknowns are a rigid correction of the simulated state at frame a (:func:`~vid2sim.physics.rigid_motion.
rigidly_moved`): a rotation about the simulated centre of mass, a translation, and a change of the linear and angular
velocity (12 numbers); its shape and strain are the simulation's. Levenberg–Marquardt with forward-difference
Jacobians (:func:`~vid2sim.reconstruct.gauss_newton.levenberg_marquardt`) minimises the mean squared image error of
the window's frames in every observed view, from no correction; each iteration is 13 rollouts of ``window`` − 1
frames. The material, the networks and the Gaussians are those of the stages before. It runs on the CPU, where
the asset is assembled (a few small rollouts).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any, Sequence

import torch
from torch import Tensor

from vid2sim.asset.motion import GaussianRig, simulated_centre_of_mass
from vid2sim.physics.rigid_motion import rigidly_moved
from vid2sim.physics.solver import SimState, Simulator
from vid2sim.reconstruct.clip import Observations, render_states
from vid2sim.reconstruct.gauss_newton import Parameter, effective_images, levenberg_marquardt
from vid2sim.reconstruct.runner import Context, State
from vid2sim.runtime.files import read_json, write_json_atomic

RECORD = "continuation.json"
DIFFERENCE_STEP = 0.002
"""Forward-difference steps: this many radians, and this fraction of the object's size (per frame for the
velocities)."""
NAMES = ("rotation", "translation", "linear", "angular")


class WindowResiduals:
    """The last ``frames`` observed frames as a function of the 12 correction numbers θ (a
    :class:`~vid2sim.reconstruct.gauss_newton.ClipModel`): block k is frame ``anchor + k`` rendered in every view
    of ``obs``, minus the video, scaled so that the blocks' squared norms sum to the window's mean squared error.

    Args:
        sim: the simulator (the fitted material).
        rig: the Gaussians' rig on ``sim``.
        obs: the observed views, frames 0 … T−1.
        start: the simulated state of frame ``anchor``.
        anchor: the window's first frame (T − frames).
    """

    def __init__(self, sim: Simulator, rig: GaussianRig, obs: Observations, start: SimState, anchor: int) -> None:
        self.sim, self.rig, self.obs, self.start, self.anchor = sim, rig, obs, start, anchor
        V, T = obs.images.shape[:2]
        self.frames = T - anchor
        self.centre = [float(x) for x in simulated_centre_of_mass(sim, [start])[0]]
        self.scale = math.sqrt(1.0 / (self.frames * V * obs.images[0, 0].numel()))
        with torch.no_grad():
            self.basis = rig.basis()

    def moved(self, theta: Sequence[float]) -> SimState:
        """The frame-``anchor`` state corrected by θ = (rotation vector, translation, Δv, Δω), 3 numbers each."""
        return rigidly_moved(self.start, theta[0:3], theta[3:6], theta[6:9], theta[9:12], self.centre)

    def substeps(self, theta: Sequence[float]) -> int:
        return self.sim.substeps()

    def simulate(self, theta: Sequence[float], substeps: int | None = None, frames: int | None = None
                 ) -> list[SimState]:
        """The corrected state and the ``frames`` (default: the window's rest) frames after it."""
        start = self.moved(theta)
        config = self.sim.config
        if substeps is not None:
            self.sim.config = replace(config, substeps=substeps)
        try:
            with torch.no_grad():
                return [start] + self.sim.rollout(start, self.frames - 1 if frames is None else frames)
        finally:
            self.sim.config = config

    def residuals(self, trajectories: Sequence[list[SimState]], frame: int) -> Tensor:
        with torch.no_grad():
            renders = render_states(self.rig, [s[frame] for s in trajectories], self.obs,
                                    range(len(self.obs.cameras)), self.basis)
            target = self.obs.images[:, self.anchor + frame].to(renders)
            return ((renders - target) * self.scale).reshape(len(trajectories), -1)

    def track_residuals(self, trajectories: Sequence[list[SimState]]) -> None:
        return None


def correction_parameters(length: float, dt: float) -> list[Parameter]:
    """The 12 corrections (rotation vector in rad, translation in m, Δv in m/s, Δω in rad/s), no prior, bounded by
    a quarter turn, the object's size ``length`` and that size (a turn) per frame."""
    h, v, w = DIFFERENCE_STEP, DIFFERENCE_STEP * length / dt, DIFFERENCE_STEP / dt
    return ([Parameter(f"rotation_{a}", -math.pi / 2, math.pi / 2, h) for a in "xyz"]
            + [Parameter(f"translation_{a}", -length, length, h * length) for a in "xyz"]
            + [Parameter(f"linear_{a}", -length / dt, length / dt, v) for a in "xyz"]
            + [Parameter(f"angular_{a}", -1.0 / dt, 1.0 / dt, w) for a in "xyz"])


def fit_continuation(sim: Simulator, rig: GaussianRig, obs: Observations, start: SimState, anchor: int,
                     iterations: int = 8) -> dict[str, Any]:
    """The state at frame ``anchor`` fitted to observed frames ``anchor`` … T−1 (module docstring), from the
    simulated ``start``; returns the asset's ``continuation`` record (:attr:`~vid2sim.asset.folder.Asset.
    continuation`, ``from_frame`` = T) with the fit's: the correction by name, the window's loss before and after,
    the iterations, why it stopped and its seconds."""
    t0 = time.perf_counter()
    model = WindowResiduals(sim, rig, obs, start, anchor)
    parameters = correction_parameters(sim.length_scale, sim.config.dt)
    n = effective_images([1.0 / model.frames] * model.frames, len(obs.cameras))
    fit = levenberg_marquardt(model, parameters, [0.0] * 12, n, iterations=iterations)
    state = model.moved(fit.theta)
    correction = {k: fit.theta[3 * i:3 * i + 3] for i, k in enumerate(NAMES)}
    return {"frame": anchor, "from_frame": int(obs.images.shape[1]), "z": state.z.detach().cpu().tolist(),
            "zdot": state.zdot.detach().cpu().tolist(), "t": float(state.t),
            "fit": {"correction": correction, "centre": model.centre, "loss_before": fit.log[0]["loss"],
                    "loss": fit.log[-1]["loss"] if fit.log[-1]["accepted"] else _last_accepted(fit.log),
                    "iterations": len(fit.log) - 1, "stop": fit.stop, "seconds": time.perf_counter() - t0}}


def _last_accepted(log: list[dict[str, Any]]) -> float:
    return [e for e in log if e["accepted"]][-1]["loss"]


class ContinuationStage:
    """The continuation (``config.continuation``, module docstring); writes ``continuation.json``. Loading it
    puts the state into ``state.asset.continuation``."""

    name = "continuation"
    sections = ("continuation",)
    revision = 0

    def title(self, ctx: Context, state: State) -> str | None:
        window = ctx.config.continuation.window
        if window == 0 or ctx.observed.frames < window + 1:
            return None
        return f"fitting the state at the end of the clip to its last {window} frames"

    def run(self, ctx: Context, state: State) -> None:
        cfg, o, asset = ctx.config.continuation, ctx.observed, state.asset
        sim = asset.simulator()
        anchor = o.frames - cfg.window
        with torch.no_grad():
            start = asset.initial_state(sim)
            at_anchor = ([start] + sim.rollout(start, anchor))[anchor]
        rig = GaussianRig(sim, asset.gaussians, asset.shading)
        obs = Observations(o.images_cpu, o.cameras_cpu).at_scale(cfg.scale)  # the asset is on the CPU
        record = fit_continuation(sim, rig, obs, at_anchor, anchor, cfg.iterations)
        write_json_atomic(ctx.path(RECORD), record)

    def load(self, ctx: Context, state: State) -> None:
        if self.title(ctx, state) is None:
            return
        record = read_json(ctx.path(RECORD), "the continuation's record")
        state.asset = replace(state.asset, continuation=record)
