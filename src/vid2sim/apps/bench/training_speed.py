"""Speed of the data-free network training (``vid2sim bench speed --only training``).

The standard setting of :mod:`vid2sim.apps.bench.physics_speed` (10 learned handles + 1 rigid, 20 000 points in
the box, the field pretrained for ``skinning_pretrain_iters`` iterations). Figures (medians of 3 timed runs of
``train_timing_iters`` iterations each, after one untimed run):

- ``skinning_train_ms_per_iter`` — one data-free training iteration of the skinning field (the default modal
  objective, 1 000 points per step), trained further in place; ``skinning_train_it_per_s`` the same as a rate;
- ``skinning_iter_ops`` — the top-level aten operators one such iteration dispatches
  (:mod:`vid2sim.apps.bench.op_count`: those of 11 iterations less those of 1, over 10, so without the
  optimiser's set-up): on a GPU each is a kernel launch, so this bounds the rate there;
- ``jacobian_train_ms_per_iter`` — one training iteration of a new Neural Jacobian on the same points.

Its own section since the physics section's 7-repeat medians of every simulator setting took more than two minutes
on an H200 (launch-bound), where these figures take seconds.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Any

import torch

from vid2sim.apps.bench.op_count import count_aten_ops
from vid2sim.apps.bench.physics_speed import PhysicsBenchSettings, build_standard_simulator
from vid2sim.apps.bench.timing import time_ms
from vid2sim.physics.neural_jacobian import NeuralJacobian, NeuralJacobianTrainingConfig, train_neural_jacobian
from vid2sim.physics.skinning import SkinningField
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning

REPEATS = 3
"""Timed runs of ``train_timing_iters`` iterations per figure (the median is reported)."""


def skinning_iteration_ops(field: SkinningField, points: torch.Tensor, seed: int = 0) -> float:
    """Top-level aten operators of one data-free skinning iteration (default objective) on a copy of ``field``
    with ``points`` (N, 3): those of an 11-iteration run less those of a 1-iteration run, over 10 (the set-up
    cancels)."""

    field = copy.deepcopy(field)

    def train(n: int):
        return lambda: train_skinning(field, points, SkinningTrainingConfig(iterations=n, seed=seed), progress=False)

    return (count_aten_ops(train(11)).top_level - count_aten_ops(train(1)).top_level) / 10


def run(device: torch.device, quick: bool = False, settings: PhysicsBenchSettings | None = None) -> dict[str, Any]:
    """The figures of the module docstring (``quick``: a 20-iteration pretraining, 2 iterations timed once)."""

    s = settings or PhysicsBenchSettings()
    if quick:
        s = replace(s, skinning_pretrain_iters=20, train_timing_iters=2)
    repeats, warmup = (1, 0) if quick else (REPEATS, 1)
    sim, pts = build_standard_simulator(s, device)
    iters = s.train_timing_iters
    skin_ms = time_ms(lambda: train_skinning(sim.field, pts, SkinningTrainingConfig(iterations=iters, seed=s.seed),
                                             progress=False), device, repeats, warmup) / iters
    nj = NeuralJacobian(num_handles_total=sim.field.num_handles_total, seed=s.seed).to(device)
    nj_ms = time_ms(lambda: train_neural_jacobian(nj, sim.field, pts, NeuralJacobianTrainingConfig(
        iterations=iters, seed=s.seed), progress=False), device, repeats, warmup) / iters
    return {
        "skinning_train_ms_per_iter": skin_ms,
        "skinning_train_it_per_s": 1e3 / skin_ms,
        "skinning_iter_ops": skinning_iteration_ops(sim.field, pts, s.seed),
        "jacobian_train_ms_per_iter": nj_ms,
        "training_settings": {"skinning_pretrain_iters": s.skinning_pretrain_iters, "timed_iters": iters,
                              "repeats": repeats, "num_points": s.num_points, "num_handles": s.num_handles},
    }
