"""Speed of the reduced simulator and of the data-free network training (issue: simulator foundation).

Standard setting: 10 learned handles + 1 rigid, 500 cubature points, 20 000 object points sampled in a
box (half bounding-box diagonal 0.5, the canonical frame), Neo-Hookean E = 1e5 Pa, ν = 0.3, ρ = 1000,
Δt = 0.05 s, gravity −z, floor barrier at z = −0.7 (k = 1e5): the object falls 0.45 m, hits the floor
after 6 steps and bounces; 15 steps in all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import torch

from vid2sim.bench.timing import time_ms


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
    from vid2sim.physics.cubature import sample_cubature
    from vid2sim.physics.external import Floor, Gravity
    from vid2sim.physics.skinning import SkinningField
    from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
    from vid2sim.physics.solver import Material, SimConfig, Simulator

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
    """Figures: sim_step_ms (and sim_step_ms_always_projected, the same steps with Newton's Hessian projected
    at every iteration, as a same-run baseline), sim_window_ms, sim_window_points_ms, skinning/jacobian
    training ms per iteration."""
    from vid2sim.physics.neural_jacobian import NeuralJacobian, NeuralJacobianTrainingConfig, train_neural_jacobian
    from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning

    s = settings or PhysicsBenchSettings()
    if quick:
        s.skinning_pretrain_iters, s.train_timing_iters = 20, 2
    repeats = 1 if quick else 9  # medians over several runs: a shared 2-core machine is noisy
    sim, pts = build_standard_simulator(s, device)
    rest = sim.rest_state()

    # --- no-grad implicit steps ------------------------------------------------------------------
    with torch.no_grad():
        states = sim.rollout(rest, s.steps)
        rollout_ms = time_ms(lambda: sim.rollout(rest, s.steps), device, repeats)
        # same-run baseline: Newton with the PSD-projected Hessian at every iteration
        sim.config = replace(sim.config, hessian_projection="always")
        projected_ms = time_ms(lambda: sim.rollout(rest, s.steps), device, repeats)
        sim.config = replace(sim.config, hessian_projection="on_demand")
    iters = [st.newton_iterations for st in states]
    x_final = sim.positions(pts, states[-1].z).detach()
    penetration = max(0.0, s.floor_height - float(x_final[:, 2].min()))

    # --- a 4-step window with gradients to log10 E, ν and the skinning parameters --------------------
    start = states[s.window_start - 1]
    start = type(start)(start.z.detach(), start.zdot.detach(), start.t, None)
    sim.log10_E.requires_grad_(True)
    sim.nu.requires_grad_(True)
    params = [sim.log10_E, sim.nu, *sim.field.parameters()]
    cub_target = sim.X.detach()

    def window_cubature() -> None:
        seq = sim.rollout(start, s.window)
        loss = sum(((sim.positions(sim.X, st.z) - cub_target) ** 2).mean() for st in seq)
        torch.autograd.grad(loss, params, allow_unused=True)

    def window_points() -> None:
        seq = sim.rollout(start, s.window)
        w = sim.field(pts)
        from vid2sim.physics.skinning import deform

        loss = sum(((deform(pts, w, st.z) - pts) ** 2).mean() for st in seq)
        torch.autograd.grad(loss, params, allow_unused=True)

    window_ms = time_ms(window_cubature, device, repeats)
    window_points_ms = time_ms(window_points, device, repeats)
    sim.log10_E.requires_grad_(False)
    sim.nu.requires_grad_(False)

    # --- data-free training iterations --------------------------------------------------------------
    n = s.train_timing_iters
    skin_ms = time_ms(lambda: train_skinning(sim.field, pts, SkinningTrainingConfig(iterations=n, seed=s.seed),
                                             progress=False), device, repeats=1) / n
    nj = NeuralJacobian(num_handles_total=sim.field.num_handles_total, seed=s.seed).to(device)
    nj_ms = time_ms(lambda: train_neural_jacobian(nj, sim.field, pts, NeuralJacobianTrainingConfig(
        iterations=n, seed=s.seed), progress=False), device, repeats=1) / n

    return {
        "sim_step_ms": rollout_ms / s.steps,
        "sim_step_ms_always_projected": projected_ms / s.steps,
        "sim_newton_iterations": iters,
        "sim_floor_penetration_m": penetration,
        "sim_window_ms": window_ms,
        "sim_window_points_ms": window_points_ms,
        "skinning_train_ms_per_iter": skin_ms,
        "jacobian_train_ms_per_iter": nj_ms,
        "physics_settings": asdict(s),
    }
