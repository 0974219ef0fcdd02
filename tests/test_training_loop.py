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


@pytest.mark.parametrize("warmup", [None, 4])
def test_the_schedules_rates_are_those_the_eager_loop_steps_with(warmup):
    schedule = Schedule(12, 0.3, warmup=warmup)
    x = torch.zeros(1, requires_grad=True)
    seen = []

    def step(it):
        return (x - 1.0).pow(2).sum(), {}

    # the rates of the scheduler the eager loop makes, on the optimiser it makes
    opt = torch.optim.Adam([x], lr=0.3)
    sched = schedule._scheduler(opt)
    for _ in range(12):
        seen.append(float(opt.param_groups[0]["lr"]))
        sched.step()
    assert schedule.learning_rates() == seen
    assert optimise([x], step, schedule, Progress("toy", False), "toy")  # and the loop runs with it


def test_a_step_split_into_inputs_trains_exactly_as_the_plain_one():
    g = torch.Generator().manual_seed(0)
    targets = torch.randn(20, 3, generator=g)

    def train(split: bool) -> tuple[list[float], torch.Tensor]:
        x = torch.zeros(3, requires_grad=True)
        if split:
            return optimise([x], lambda t: (((x - t) ** 2).sum(), {"t0": t[0]}), Schedule(20, 0.1),
                            Progress("toy", False), "toy", inputs=lambda it: (targets[it],)), x.detach()
        return optimise([x], lambda it: (((x - targets[it]) ** 2).sum(), {"t0": targets[it][0]}), Schedule(20, 0.1),
                        Progress("toy", False), "toy"), x.detach()

    (a, xa), (b, xb) = train(True), train(False)
    assert a == b and torch.equal(xa, xb)


def test_the_no_device_waits_guard_catches_reading_a_value(no_device_waits):
    t = torch.ones(3)
    with pytest.raises(AssertionError, match="waits for the device"):
        with no_device_waits:
            bool((t > 0).all())
    with pytest.raises(AssertionError, match="waits for the device"):
        with no_device_waits:
            t[t > 0]
    with no_device_waits:
        torch.where(t > 0, t, -t).sum() * 2  # stays on the device


@pytest.mark.cuda
def test_a_graphed_training_matches_the_eager_one_and_reports_a_nan_at_its_iteration():
    import warnings

    from vid2sim.runtime.training import GRAPH_CHECK_EVERY

    g = torch.Generator().manual_seed(0)
    targets = torch.randn(150, 3, generator=g).cuda()
    scale = torch.ones(150).cuda()

    def train(graph: bool, scale: torch.Tensor) -> tuple[list[float], torch.Tensor]:
        x = torch.zeros(3, device="cuda", requires_grad=True)
        losses = optimise([x], lambda t, s: ((((x - t) ** 2).sum() * s), {"s": s}),
                          Schedule(150, 0.05, cuda_graph=graph), Progress("toy", False), "toy",
                          inputs=lambda it: (targets[it], scale[it]))
        return losses, x.detach()

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a capture that failed would warn
        (a, xa), (b, xb) = train(True, scale), train(False, scale)
    assert a == pytest.approx(b, rel=1e-5, abs=1e-7) and torch.allclose(xa, xb, rtol=1e-5, atol=1e-6)
    bad = scale.clone()
    bad[GRAPH_CHECK_EVERY + 7] = float("nan")  # inside the first replayed block but its first iteration
    with pytest.raises(FloatingPointError, match=rf"toy: the loss became nan at iteration {GRAPH_CHECK_EVERY + 7} "
                                                  r"\(s nan\)"):
        train(True, bad)
