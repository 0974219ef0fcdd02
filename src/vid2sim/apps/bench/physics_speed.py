"""Speed of the reduced simulator and of the data-free network training.

Standard setting: 10 learned handles + 1 rigid, 500 cubature points, 20 000 object points sampled in a
box (half bounding-box diagonal 0.5, the canonical frame), Neo-Hookean E = 1e5 Pa, ν = 0.3, ρ = 1000,
the default damping (ζ = 0.05), video frames of Δt = 0.05 s, gravity −z, the paper's floor barrier at
z = −0.7 (k = 1e5 per cubature point): the object falls 0.45 m, hits the floor in frame 6 and bounces;
15 frames in all.

Figures (medians; every baseline is measured in the same run):

- ``sim_frame_ms`` — one video frame at the default accuracy (BDF2, automatic substeps
  ``sim_frame_substeps``, chord Newton), no gradients; ``sim_frame_time_convergence_percent`` says how far
  that trajectory is from the same simulation with 4× the substeps (mean over frames, % of the size);
- ``sim_frame_ms_plain_newton`` — the same with a fresh Hessian every Newton iteration;
- ``sim_step_ms`` — one implicit-Euler step per frame (the paper's and this project's former setting),
  and ``sim_step_ms_always_projected`` with the Hessian projected every iteration;
  ``sim_step_time_convergence_percent`` is its distance from the 4× refined default;
- ``sim_window_ms`` — 4 frames at the default accuracy with gradients to log10 E, ν and the skinning
  parameters (forward + backward), ``sim_window_ms_one_step_per_frame`` the same with one implicit-Euler
  step per frame; ``sim_window_points_ms`` with the loss on all 20 000 points;
- ``sim_frame_ms_projected`` and ``sim_window_ms_projected`` — the same frame and window with the projected
  volumetric term (``Simulator(volumetric="projected")``, :mod:`vid2sim.physics.volumetric`);
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import torch

from vid2sim.apps.bench.timing import time_ms
from vid2sim.metrics import trajectory_distance
from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.external import Floor, Gravity
from vid2sim.physics.skinning import SkinningField, deform
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.physics.solver import Material, SimConfig, SimState, Simulator


@dataclass
class PhysicsBenchSettings:
    num_handles: int = 10
    num_cubature: int = 500
    num_points: int = 20_000
    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    dt: float = 0.05
    floor_height: float = -0.7
    steps: int = 15
    window: int = 4
    window_start: int = 5  # the window covers the impact (steps 6-9)
    skinning_pretrain_iters: int = 200
    train_timing_iters: int = 10
    seed: int = 0


def box_points(n: int, seed: int, device: torch.device, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(n, 3) points uniform in a 0.6 × 0.4 × 0.6 box scaled to half-diagonal 0.5, centred at 0."""
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([0.6, 0.4, 0.6], dtype=torch.float64)
    size = size * (0.5 / float(size.norm() / 2))
    pts = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * size
    return pts.to(device=device, dtype=dtype)


def build_standard_simulator(settings: PhysicsBenchSettings, device: torch.device, pretrain: bool = True):
    """(simulator, object points (N, 3)) of the standard setting; the field is briefly data-free trained."""

    pts = box_points(settings.num_points, settings.seed, device)
    field = SkinningField(num_handles=settings.num_handles, seed=settings.seed).to(device)
    if pretrain and settings.skinning_pretrain_iters > 0:
        train_skinning(field, pts, SkinningTrainingConfig(iterations=settings.skinning_pretrain_iters,
                                                          seed=settings.seed), progress=False)
    idx, weights = sample_cubature(pts, settings.num_cubature, volume=1.0, seed=settings.seed)
    material = Material(settings.youngs_modulus, settings.poisson_ratio)
    externals = [Gravity(), Floor(height=settings.floor_height)]
    # the box is normalised to a bounding-box diagonal of exactly 1: the damping's and the automatic
    # substeps' length scale (the cubature points' own box is slightly smaller)
    sim = Simulator(field, pts[idx], weights.to(pts), material, externals, SimConfig(dt=settings.dt), length_scale=1.0)
    return sim, pts


def run(device: torch.device, quick: bool = False, settings: PhysicsBenchSettings | None = None) -> dict[str, Any]:
    """The figures of the module docstring (the networks' training: :mod:`vid2sim.apps.bench.training_speed`)."""

    s = settings or PhysicsBenchSettings()
    if quick:
        s.skinning_pretrain_iters, s.train_timing_iters = 20, 2
    repeats = 1 if quick else 7  # medians over several runs: a shared 2-core machine is noisy
    sim, pts = build_standard_simulator(s, device)
    timer = _Timer(sim, sim.rest_state(), s, device, repeats, warmup=0 if quick else 1)
    default = sim.config
    one_step = replace(default, substeps=1, integrator="implicit_euler")
    frames, states, ie_states = _frame_figures(timer, pts, default, one_step, quick)
    windows = _window_figures(timer, pts, default, one_step, states, ie_states)
    return {**frames, **windows, "physics_settings": asdict(s)}


@dataclass
class _Timer:
    """Times ``sim`` from its ``rest`` state on ``device``: medians over ``repeats`` runs after ``warmup`` runs
    (``quick``: none, a check that the figures come out)."""

    sim: Simulator
    rest: SimState
    settings: PhysicsBenchSettings
    device: torch.device
    repeats: int
    warmup: int = 1

    def rollout(self, config: SimConfig) -> tuple[float, list[SimState]]:
        """ms per frame of the ``settings.steps`` frames from rest with ``config``, without gradients, and those
        frames' states (the simulator keeps ``config``)."""
        sim, s = self.sim, self.settings
        sim.config = config
        with torch.no_grad():
            states = sim.rollout(self.rest, s.steps)
            ms = time_ms(lambda: sim.rollout(self.rest, s.steps), self.device, self.repeats, self.warmup)
        return ms / s.steps, states


def _frame_figures(timer: _Timer, pts: torch.Tensor, default: SimConfig, one_step: SimConfig, quick: bool
                   ) -> tuple[dict[str, Any], list[SimState], list[SimState]]:
    """The ``sim_frame_*``, ``sim_step_*`` and ``sim_floor_penetration_m`` figures of the drop of the object points
    ``pts`` (N, 3), and the states of the default and the one-step-per-frame drops."""
    sim, s = timer.sim, timer.settings
    n = sim.substeps()
    size = float((pts.max(0).values - pts.min(0).values).norm())
    frame_ms, states = timer.rollout(default)
    plain_ms, _ = timer.rollout(replace(default, reuse_hessian=False))
    step_ms, ie_states = timer.rollout(one_step)
    projected_ms, _ = timer.rollout(replace(one_step, hessian_projection="always"))
    _, refined = timer.rollout(replace(default, substeps=4 * n)) if not quick else (0.0, states)
    sim.config = default

    probe = pts[::20]

    def traj(seq) -> torch.Tensor:
        return torch.stack([sim.positions(probe, st.z).detach() for st in seq])

    convergence = trajectory_distance(traj(states), traj(refined), size, frames=list(range(s.steps))).mean
    ie_distance = trajectory_distance(traj(ie_states), traj(refined), size, frames=list(range(s.steps))).mean
    with torch.no_grad():  # the deepest any object point goes below the floor over the drop
        lowest = min(float(sim.positions(pts, st.z)[:, 2].min()) for st in states)
    penetration = max(0.0, s.floor_height - lowest)
    figures = {
        "sim_frame_ms": frame_ms,
        "sim_frame_substeps": n,
        "sim_frame_time_convergence_percent": convergence,
        "sim_frame_ms_plain_newton": plain_ms,
        "sim_step_ms": step_ms,
        "sim_step_ms_always_projected": projected_ms,
        "sim_step_time_convergence_percent": ie_distance,
        "sim_floor_penetration_m": penetration,
    }
    return figures, states, ie_states


def _window_figures(timer: _Timer, pts: torch.Tensor, default: SimConfig, one_step: SimConfig,
                    states: list[SimState], ie_states: list[SimState]) -> dict[str, Any]:
    """The ``sim_window_*`` figures (a 4-frame window with gradients to log10 E, ν and the skinning parameters,
    from the drops' ``states`` and ``ie_states``) and ``sim_frame_ms_projected``; the simulator is left as it
    was (default configuration, pointwise volumetric term, no gradients to the material)."""
    sim, s = timer.sim, timer.settings
    sim.log10_E.requires_grad_(True)
    sim.nu.requires_grad_(True)
    params = [sim.log10_E, sim.nu, *sim.field.parameters()]
    cub_target = sim.X.detach()

    def window(config: SimConfig, seq: list[SimState], points: bool = False) -> float:
        return _window_ms(timer, config, seq[s.window_start - 1], params, cub_target, pts if points else None)

    window_ms = window(default, states)
    window_one_step_ms = window(one_step, ie_states)
    window_points_ms = window(default, states, points=True)
    sim.config = default
    sim.volumetric = "projected"
    frame_projected_ms, projected_states = timer.rollout(default)
    window_projected_ms = window(default, projected_states)
    sim.volumetric = "pointwise"
    sim.config = default
    sim.log10_E.requires_grad_(False)
    sim.nu.requires_grad_(False)
    return {
        "sim_window_ms": window_ms,
        "sim_window_ms_one_step_per_frame": window_one_step_ms,
        "sim_window_points_ms": window_points_ms,
        "sim_frame_ms_projected": frame_projected_ms,
        "sim_window_ms_projected": window_projected_ms,
    }


def _window_ms(timer: _Timer, config: SimConfig, start: SimState, params: list[torch.Tensor],
               cub_target: torch.Tensor, pts: torch.Tensor | None) -> float:
    """ms of one window of ``settings.window`` frames from ``start`` (detached) with ``config``, forward and
    backward to ``params``: the loss on the cubature points' displacement from ``cub_target`` (K, 3), or with
    ``pts`` (N, 3) on those points' displacement."""
    sim, s = timer.sim, timer.settings
    sim.config = config
    start = type(start)(start.z.detach(), start.zdot.detach(), start.t, None,
                        z_prev=None if start.z_prev is None else start.z_prev.detach(),
                        zdot_prev=None if start.zdot_prev is None else start.zdot_prev.detach(),
                        h_prev=start.h_prev)

    def run_window() -> None:
        out = sim.rollout(start, s.window)
        if pts is not None:
            w = sim.field(pts)
            loss = sum(((deform(pts, w, st.z) - pts) ** 2).mean() for st in out)
        else:
            loss = sum(((sim.positions(sim.X, st.z) - cub_target) ** 2).mean() for st in out)
        torch.autograd.grad(loss, params, allow_unused=True)

    return time_ms(run_window, timer.device, timer.repeats, timer.warmup)
