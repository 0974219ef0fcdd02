"""Accuracy of the data-free Neural Jacobian against the exact dF/dz (``vid2sim bench jacobian``).

On the standard simulator setting of :mod:`vid2sim.apps.bench.physics_speed` (10 + 1 handles, 20 000 box points,
500 cubature points, the drop on the floor), train the paper's Neural Jacobian data-free for a number of
iterations and report

- ``jacobian_mse`` — the paper's metric (1/N) Σ_i ‖J_θ(X_i) − J(X_i)‖²_F over all object points,
  ``jacobian_relative_frobenius`` — ‖J_θ − J‖_F / ‖J‖_F, and ``jacobian_max_abs``;
- ``jacobian_rollout_max_deviation`` — the largest distance between object points simulated with the
  exact dF/dz and with the network over the 15-step drop, relative to the object's bounding-box
  diagonal (1.0 here).

The paper trains 10 000 iterations (about an hour on a 2-core CPU); fewer iterations give an upper
bound of the error it reaches.
"""

from __future__ import annotations

from typing import Any

import torch

from vid2sim.apps.bench.physics_speed import (
    PhysicsBenchSettings,
    build_standard_simulator,
)
from vid2sim.apps.bench.timing import time_ms
from vid2sim.physics.neural_jacobian import (
    NeuralJacobian,
    NeuralJacobianTrainingConfig,
    jacobian_error,
    train_neural_jacobian,
)
from vid2sim.physics.solver import Simulator
from vid2sim.runtime.errors import ConfigError


def run(device: torch.device, iterations: int = 1000, progress: bool = True, quick: bool = False) -> dict[str, Any]:
    """Train for ``iterations`` and return the figures above (plus the training time per iteration). ``quick``: a
    smaller object (2 000 points, 100 cubature points) and a 3-frame rollout, for the test suite."""

    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ConfigError(f"iterations must be a positive integer, got {iterations!r}")
    settings = PhysicsBenchSettings(num_points=2000, num_cubature=100, steps=3) if quick else PhysicsBenchSettings()
    sim, pts = build_standard_simulator(settings, device)
    for p in sim.field.parameters():
        p.requires_grad_(False)
    net = NeuralJacobian(num_handles_total=sim.field.num_handles_total, seed=settings.seed).to(device)
    config = NeuralJacobianTrainingConfig(iterations=iterations, seed=settings.seed)
    train_ms = time_ms(lambda: train_neural_jacobian(net, sim.field, pts, config, progress=progress), device,
                       repeats=1, warmup=0) / iterations
    net.eval()
    with torch.no_grad():
        errors = jacobian_error(net, sim.field, pts)
        exact = sim.rollout(sim.rest_state(), settings.steps)
        neural_sim = Simulator(sim.field, sim.X, sim.vol, sim.material, sim.externals, sim.config,
                               jacobian=net, use_neural_jacobian=True)
        neural = neural_sim.rollout(neural_sim.rest_state(), settings.steps)
        deviation = max(float((sim.positions(pts, a.z) - sim.positions(pts, b.z)).norm(dim=1).max())
                        for a, b in zip(exact, neural))
    size = float((pts.max(0).values - pts.min(0).values).norm())
    return {
        "device": str(device),
        "jacobian_train_iterations": iterations,
        "quick": quick,
        "jacobian_train_ms_per_iter": train_ms,
        "jacobian_mse": errors["mse"],
        "jacobian_relative_frobenius": errors["relative_frobenius"],
        "jacobian_max_abs": errors["max_abs"],
        "jacobian_rollout_max_deviation": deviation / size,
        "jacobian_rollout_newton_iterations": [s.newton_iterations for s in neural],
    }
