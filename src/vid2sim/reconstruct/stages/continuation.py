"""The state at the end of the observed clip, fitted to its last frames: where the prediction goes on from.

The fitted simulation is one rollout from frame 0. After the bounces its errors have accumulated (the small suite's
scenes end the observed clip with the centre of mass 0.7–4 cm and the rotation 9–52° off the truth's), and a
prediction that goes on from there starts that far off. The observed frames say where the body is at their end:
this stage fits the state at frame a = T − ``window`` (T the observed frames) to frames a … T − 1 and stores it in
the asset (:attr:`~vid2sim.asset.folder.Asset.continuation`), and the captured drop goes on from it after the
observed frames (:func:`~vid2sim.asset.motion.simulate_states`). The observed frames themselves stay the rollout
from frame 0, so the dynamic reconstruction's score is still the physics' own.

The fitted unknowns are a rigid correction of the simulated state at frame a (:func:`~vid2sim.physics.rigid_motion.
rigidly_moved`): a rotation about the simulated centre of mass, a translation, and a change of the linear and angular
velocity (12 numbers); its shape and strain are the simulation's. Levenberg–Marquardt with forward-difference
Jacobians (:func:`~vid2sim.reconstruct.gauss_newton.levenberg_marquardt`) minimises the mean squared image error of
the window's frames in every observed view, from no correction; each iteration is 13 rollouts of ``window`` − 1
frames, the Jacobian's 12 shared with the reconstruction's rollout worker processes where it has them (``vid2sim
reconstruct --threads N`` starts N − 1). The material, the networks and the Gaussians are those of the stages
before. It runs on the CPU, where the asset is assembled (a few small rollouts).

Where the simulation already follows the video, a state fitted to two frames of 4 small views can predict worse
than the rollout it corrects (its velocity is the difference of two poses; a soft body's squash is read as a shift).
So the stage first checks (``check``, :func:`check_continuation`): it fits the same window ending ``window`` frames
earlier, simulates on through the last ``window`` frames, and uses a continuation only when that predicts them
better than the one rollout from frame 0; otherwise the asset has none and the drop stays that one rollout.
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import dataclass, replace
from typing import Any, Sequence

import torch
from torch import Tensor

from vid2sim.asset.folder import recorded_state
from vid2sim.asset.motion import GaussianRig, simulated_centre_of_mass
from vid2sim.physics.rigid_motion import rigidly_moved
from vid2sim.physics.solver import SimState, Simulator
from vid2sim.reconstruct.clip import Observations, frame_losses, render_states
from vid2sim.reconstruct.gauss_newton import Parameter, effective_images, levenberg_marquardt
from vid2sim.reconstruct.rollouts import Attempting, RolloutPool, rollout_from, simulate_many
from vid2sim.reconstruct.runner import Context, State
from vid2sim.runtime.files import read_json, write_json_atomic

RECORD = "continuation.json"
DIFFERENCE_STEP = 0.002
"""Forward-difference steps: this many radians, and this fraction of the object's size (per frame for the
velocities)."""
NAMES = ("rotation", "translation", "linear", "angular")


@dataclass
class WindowSimulation(Attempting):
    """The window's frames as a function of the 12 correction numbers θ (picklable, so that worker processes can
    simulate it: :func:`~vid2sim.reconstruct.rollouts.simulate_many`).

    Attributes:
        sim: the simulator (the fitted material).
        start: the simulated state of the window's first frame.
        centre: (3,) the point the correction's rotation turns about (m): the simulated centre of mass there.
        frames: the frames simulated after the first.
    """

    sim: Simulator
    start: SimState
    centre: list[float]
    frames: int

    def moved(self, theta: Sequence[float]) -> SimState:
        """The first frame's state corrected by θ = (rotation vector, translation, Δv, Δω), 3 numbers each."""
        return rigidly_moved(self.start, theta[0:3], theta[3:6], theta[6:9], theta[9:12], self.centre)

    def simulate(self, theta: Sequence[float], substeps: int | None = None, frames: int | None = None
                 ) -> list[SimState]:
        """The corrected state and the ``frames`` (default: the window's rest) frames after it."""
        return rollout_from(self.sim, self.moved(theta), self.frames if frames is None else frames, substeps)


class WindowResiduals:
    """The last observed frames from ``anchor`` on as a function of θ (a
    :class:`~vid2sim.reconstruct.gauss_newton.ClipModel`): block k is frame ``anchor + k`` rendered in every view
    of ``obs``, minus the video, scaled so that the blocks' squared norms sum to the window's mean squared error.

    Args:
        sim: the simulator (the fitted material).
        rig: the Gaussians' rig on ``sim``.
        obs: the observed views, frames 0 … T−1.
        start: the simulated state of frame ``anchor``.
        anchor: the window's first frame (T − its length).
        pool: worker processes for the Jacobian's rollouts (:class:`~vid2sim.reconstruct.rollouts.RolloutPool`), or
            None.
    """

    def __init__(self, sim: Simulator, rig: GaussianRig, obs: Observations, start: SimState, anchor: int,
                 pool: RolloutPool | None = None) -> None:
        self.rig, self.obs, self.anchor, self.pool = rig, obs, anchor, pool
        V, T = obs.images.shape[:2]
        self.frames = T - anchor
        centre = [float(x) for x in simulated_centre_of_mass(sim, [start])[0]]
        self.simulation = WindowSimulation(sim, start, centre, self.frames - 1)
        self.scale = math.sqrt(1.0 / (self.frames * V * obs.images[0, 0].numel()))
        with torch.no_grad():
            self.basis = rig.basis()

    def substeps(self, theta: Sequence[float]) -> int:
        return self.simulation.sim.substeps()

    def simulate(self, theta: Sequence[float], substeps: int | None = None) -> list[SimState]:
        return self.simulation.simulate(theta, substeps)

    def simulate_many(self, thetas: Sequence[Sequence[float]], substeps: int | None = None
                      ) -> list[list[SimState] | None]:
        """Each θ's window (None where the simulation fails), on the ``pool``'s workers and here."""
        return simulate_many(self.simulation, thetas, substeps, self.pool)

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
                     iterations: int = 8, pool: RolloutPool | None = None) -> dict[str, Any]:
    """The state at frame ``anchor`` fitted to observed frames ``anchor`` … T−1 (module docstring), from the
    simulated ``start``; returns the asset's ``continuation`` record (:attr:`~vid2sim.asset.folder.Asset.
    continuation`, ``from_frame`` = T) with the fit's: the correction by name, the window's loss before and after,
    the iterations, why it stopped and its seconds. ``pool``: worker processes for the Jacobian's rollouts."""
    t0 = time.perf_counter()
    model = WindowResiduals(sim, rig, obs, start, anchor, pool)
    parameters = correction_parameters(sim.length_scale, sim.config.dt)
    n = effective_images([1.0 / model.frames] * model.frames, len(obs.cameras))
    fit = levenberg_marquardt(model, parameters, [0.0] * 12, n, iterations=iterations)
    state = model.simulation.moved(fit.theta)
    correction = {k: fit.theta[3 * i:3 * i + 3] for i, k in enumerate(NAMES)}
    return {"frame": anchor, "from_frame": int(obs.images.shape[1]), "z": state.z.detach().cpu().tolist(),
            "zdot": state.zdot.detach().cpu().tolist(), "t": float(state.t),
            "fit": {"correction": correction, "centre": model.simulation.centre, "loss_before": fit.log[0]["loss"],
                    "loss": fit.log[-1]["loss"],  # the last entry's θ is the kept one (no validation)
                    "iterations": len(fit.log) - 1, "stop": fit.stop, "seconds": time.perf_counter() - t0}}


def check_continuation(sim: Simulator, rig: GaussianRig, obs: Observations, states: Sequence[SimState], window: int,
                       iterations: int = 8, pool: RolloutPool | None = None) -> dict[str, Any]:
    """Whether a continuation would have predicted the clip's last ``window`` frames better than the one rollout:
    fitted (:func:`fit_continuation`) to the ``window`` frames before them, from the state of frame T − 2·window, it is
    simulated on through the held-out frames, and its image loss there (every view, summed over the frames) is set
    beside that of the rollout from frame 0 (``states``: its frames 0 … T−1).

    Returns:
        ``{"frame": the check's anchor, "predicted_frames": [first, last], "loss_continued", "loss_single",
        "fit": its fit's record}``.
    Raises:
        ValueError: fewer than 2·window + 1 frames, or ``states`` not one per frame.
    """
    T = obs.images.shape[1]
    if T < 2 * window + 1 or len(states) != T:
        raise ValueError(f"check_continuation: needs 2·window + 1 = {2 * window + 1} frames and one state each, "
                         f"got {T} frames and {len(states)} states")
    cut = T - window
    head = Observations(obs.images[:, :cut], obs.cameras, obs.background)
    record = fit_continuation(sim, rig, head, states[cut - window], cut - window, iterations, pool)
    with torch.no_grad():
        predicted = sim.rollout(recorded_state(record, sim), 2 * window - 1)[window - 1:]  # frames cut … T−1
        basis = rig.basis()
    frames = list(range(cut, T))
    continued = sum(frame_losses(rig, predicted, obs, frames, basis))
    single = sum(frame_losses(rig, list(states[cut:]), obs, frames, basis))
    return {"frame": cut - window, "predicted_frames": [cut, T - 1], "loss_continued": continued,
            "loss_single": single, "fit": record["fit"]}


class ContinuationStage:
    """The continuation (``config.continuation``, module docstring); writes ``continuation.json``: whether it is
    used, the check's record and the continuation. Loading it puts the state into ``state.asset.continuation``
    (None when the check kept the one rollout) and ``used`` and ``check`` into ``state.asset.extra["continuation"]``."""

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
        with torch.no_grad():
            start = asset.initial_state(sim)
            states = [start] + sim.rollout(start, o.frames - 1)
        rig = GaussianRig(sim, asset.gaussians, asset.shading)
        obs = Observations(o.images_cpu, o.cameras_cpu).at_scale(cfg.scale)  # the asset is on the CPU
        anchor = o.frames - cfg.window
        processes = ctx.rollout_processes
        with RolloutPool(processes) if processes > 0 else nullcontext() as pool:
            check = None
            if cfg.check and o.frames >= 2 * cfg.window + 1:
                check = check_continuation(sim, rig, obs, states, cfg.window, cfg.iterations, pool)
            used = check is None or check["loss_continued"] < check["loss_single"]
            record = fit_continuation(sim, rig, obs, states[anchor], anchor, cfg.iterations, pool) if used else None
        write_json_atomic(ctx.path(RECORD), {"used": used, "check": check, "continuation": record})

    def load(self, ctx: Context, state: State) -> None:
        if self.title(ctx, state) is None:
            return
        record = read_json(ctx.path(RECORD), "the continuation's record")
        state.asset = replace(state.asset, continuation=record["continuation"])
        state.asset.extra["continuation"] = {"used": record["used"], "check": record["check"]}
