"""The shared data-free optimisation loop (vid2sim.runtime.training) and the template training that uses it."""

from __future__ import annotations

import math

import pytest
import torch

from vid2sim.runtime.training import Progress, Schedule, optimise


def test_the_loop_minimises_and_touches_only_its_parameters():
    x = torch.tensor([3.0, -2.0], requires_grad=True)
    other = torch.tensor([1.0], requires_grad=True)  # used by the loss, not trained
    losses = optimise([x], lambda it: (((x - 1.0) ** 2).sum() * other.sum(), {}), Schedule(300, 0.05),
                      Progress("test", False), "test")
    assert len(losses) == 300 and losses[-1] < 1e-3 * losses[0]
    assert other.grad is None and x.grad is None and float(other.detach()) == 1.0


def test_the_closed_form_schedule_warms_up_then_decays_to_zero():
    s = Schedule(100, 1.0, warmup=10)
    assert s.factor(0) == pytest.approx(0.1 * 0.5 * (1 + math.cos(0.0)))
    assert s.factor(9) == pytest.approx(0.5 * (1 + math.cos(math.pi * 9 / 100)))
    assert s.factor(100) == pytest.approx(0.0, abs=1e-12)


def test_a_non_finite_loss_names_the_training_and_the_iteration():
    x = torch.zeros(1, requires_grad=True)
    with pytest.raises(FloatingPointError, match=r"toy: the loss became nan at iteration 2 \(part 1"):
        optimise([x], lambda it: (x.sum() * (float("nan") if it == 2 else 1.0), {"part": 1.0}), Schedule(5, 0.1),
                 Progress("toy", False), "toy")


def test_template_training_lowers_the_data_free_loss(one_torch_thread):
    from vid2sim.predictor.template import TemplateConfig, train_template

    cfg = TemplateConfig(shapes=2, points_per_shape=600, iterations=60, shapes_per_step=1, spectral_points=300,
                         warmup=5, width=16, hidden_layers=2, eval_shapes=0)
    trunk, info = train_template(cfg, progress=False)
    curve = info["loss_curve_per_50_steps"]
    assert len(curve) == 2 and all(math.isfinite(v) for v in curve) and curve[1] < curve[0]
    assert trunk.num_handles == 10
