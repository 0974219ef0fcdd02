"""Speed of the data-free network training (``vid2sim bench speed --only training``).

The standard setting of :mod:`vid2sim.apps.bench.physics_speed` (10 learned handles + 1 rigid, 20 000 points in
the box, the field pretrained for ``skinning_pretrain_iters`` iterations). Figures (medians of 3 timed runs of
``train_timing_iters`` iterations each, after one untimed run):

- ``skinning_train_ms_per_iter`` — one data-free training iteration of the skinning field (the modal objective,
  the pipeline's, 1 000 points per step), trained further in place, as ``reconstruct`` runs it (on CUDA: replayed
  as a CUDA graph, :mod:`vid2sim.runtime.training`); ``skinning_train_it_per_s`` the same as a rate;
  ``skinning_train_ms_per_iter_eager`` the same iterations without the graph (the baseline of the same run; on a
  CPU the two are the same path);
- ``skinning_iter_ops`` — the top-level aten operators one eager iteration dispatches
  (:mod:`vid2sim.apps.bench.op_count`: those of 11 iterations less those of 1, over 10, so without the
  optimiser's set-up): on a GPU each is a kernel launch, which is what the graph saves;
- ``jacobian_train_ms_per_iter`` (and ``..._eager``) — one training iteration of a new Neural Jacobian on the same
  points.

The timed runs are of ``train_timing_iters`` iterations each on a CPU, of :data:`CUDA_TIMING_ITERS` on CUDA: with a
CUDA graph the first :data:`~vid2sim.runtime.training.GRAPH_WARMUP` iterations are eager and one is the capture,
so a run of a few hundred is what ``reconstruct``'s thousands see, and a short one understates the graph's rate.

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


CUDA_TIMING_ITERS = 300
"""Iterations per timed run on CUDA (the module docstring)."""

OBJECTIVE = "modal"
"""The skinning objective timed (``reconstruct``'s default, :class:`~vid2sim.reconstruct.config.NetworksConfig`)."""


def skinning_iteration_ops(field: SkinningField, points: torch.Tensor, seed: int = 0) -> float:
    """Top-level aten operators of one eager data-free skinning iteration (:data:`OBJECTIVE`) on a copy of
    ``field`` with ``points`` (N, 3): those of an 11-iteration run less those of a 1-iteration run, over 10 (the
    set-up cancels)."""

    field = copy.deepcopy(field)

    def train(n: int):
        config = SkinningTrainingConfig(iterations=n, seed=seed, objective=OBJECTIVE)
        return lambda: train_skinning(field, points, config, progress=False, cuda_graph=False)

    return (count_aten_ops(train(11)).top_level - count_aten_ops(train(1)).top_level) / 10


def run(device: torch.device, quick: bool = False, settings: PhysicsBenchSettings | None = None) -> dict[str, Any]:
    """The figures of the module docstring (``quick``: a 20-iteration pretraining, 2 iterations timed once)."""

    s = settings or PhysicsBenchSettings()
    if quick:
        s = replace(s, skinning_pretrain_iters=20, train_timing_iters=2)
    repeats, warmup = (1, 0) if quick else (REPEATS, 1)
    sim, pts = build_standard_simulator(s, device)
    iters = s.train_timing_iters if quick or device.type != "cuda" else CUDA_TIMING_ITERS
    skin = SkinningTrainingConfig(iterations=iters, seed=s.seed, objective=OBJECTIVE)
    nj = NeuralJacobian(num_handles_total=sim.field.num_handles_total, seed=s.seed).to(device)
    jac = NeuralJacobianTrainingConfig(iterations=iters, seed=s.seed)
    figures: dict[str, Any] = {}
    for suffix, graph in (("", True), ("_eager", False)):
        figures[f"skinning_train_ms_per_iter{suffix}"] = time_ms(lambda: train_skinning(
            sim.field, pts, skin, progress=False, cuda_graph=graph), device, repeats, warmup) / iters
        figures[f"jacobian_train_ms_per_iter{suffix}"] = time_ms(lambda: train_neural_jacobian(
            nj, sim.field, pts, jac, progress=False, cuda_graph=graph), device, repeats, warmup) / iters
    return {
        **figures,
        "skinning_train_it_per_s": 1e3 / figures["skinning_train_ms_per_iter"],
        "skinning_iter_ops": skinning_iteration_ops(sim.field, pts, s.seed),
        "training_settings": {"objective": OBJECTIVE, "skinning_pretrain_iters": s.skinning_pretrain_iters,
                              "timed_iters": iters,
                              "repeats": repeats, "num_points": s.num_points, "num_handles": s.num_handles},
    }
