"""The joint stage's Gauss–Newton fit of the physical parameters and its uncertainty.

Physics against physics: the finite-difference Jacobian of the whole clip's image residuals against the adjoint
gradient of the same loss; the fit on the model's own motion recovers E, ν and ζ from a start off in all three;
a clip that carries no information about the material (free flight) says so instead of returning the prior as
found; on a linear model with independent Gaussian noise the intervals hold the truth at their stated rate.
"""

import dataclasses
import math

import pytest
import torch
from test_pipeline_joint import _scene_setup

from vid2sim.asset.motion import GaussianRig
from vid2sim.physics.solver import SimulationError
from vid2sim.reconstruct.clip import Observations, frame_weights, render_states
from vid2sim.reconstruct.config import JointConfig
from vid2sim.reconstruct.gauss_newton import (
    Parameter,
    effective_images,
    levenberg_marquardt,
    linearise,
    marquardt_step,
    objective,
    track_loss,
    trajectory_loss,
)
from vid2sim.reconstruct.stages.joint import (
    ClipResiduals,
    _held_out_validation,
    floor_friction,
    joint_optimisation,
    physical_parameters,
    set_floor_friction,
)
from vid2sim.reconstruct.uncertainty import (
    NOT_IDENTIFIABLE,
    coarse_edge,
    information_by_frame,
    laplace_intervals,
    mark_coarse_edge,
    mark_unmoved,
)
from vid2sim.runtime.errors import ConfigError

# ---- the method on models whose answer is known ------------------------------------------------------------------


class LinearClip:
    """r_t(θ) = A_t θ − b_t: a clip model whose Jacobian is exact and whose posterior is Gaussian."""

    def __init__(self, A: torch.Tensor, b: torch.Tensor) -> None:
        self.A, self.b, self.frames = A, b, A.shape[0]  # (F, m, p), (F, m)

    def substeps(self, theta):
        return 1

    def simulate(self, theta, substeps=None):
        return torch.tensor(list(theta), dtype=torch.float64)

    def residuals(self, trajectories, frame):
        return torch.stack([self.A[frame] @ th - self.b[frame] for th in trajectories])

    def track_residuals(self, trajectories):
        return None


class DecayClip:
    """r_t(a, k) = a·exp(−k t) − y_t, one residual per frame: a nonlinear least-squares problem."""

    frames = 12

    def __init__(self, a: float, k: float) -> None:
        self.y = [a * math.exp(-k * t) for t in range(self.frames)]

    def substeps(self, theta):
        return 1

    def simulate(self, theta, substeps=None):
        return list(theta)

    def residuals(self, trajectories, frame):
        return torch.tensor([[th[0] * math.exp(-th[1] * frame) - self.y[frame]] for th in trajectories],
                            dtype=torch.float64)

    def track_residuals(self, trajectories):
        return None


def test_effective_images_count_images_by_their_weights():
    assert effective_images([0.25] * 4, 3) == pytest.approx(12.0)  # equal weights: every image counts
    assert effective_images([1.0, 0.0, 0.0], 4) == pytest.approx(4.0)  # one frame carries all the weight
    w = frame_weights(16, 4.0)  # the joint stage's decayed weights over 15 frames: about 7.7 frames' worth
    assert 7.0 < effective_images(w, 1) < 8.5


def test_levenberg_marquardt_solves_a_nonlinear_fit_and_holds_a_bound():
    """Noise-free exponential decay: the fit from far off lands on (a, k); with k's upper bound below the truth
    it ends on the bound, with a the best amplitude there."""
    clip = DecayClip(2.0, 0.3)
    params = [Parameter("a", 0.0, 10.0, 1e-6), Parameter("k", 0.0, 2.0, 1e-6)]
    fit = levenberg_marquardt(clip, params, [1.0, 0.8], n=12.0, iterations=40, tolerance=1e-12)
    assert fit.theta == pytest.approx([2.0, 0.3], abs=1e-5)
    assert fit.linearisation.loss < 1e-10 and fit.log[-1]["accepted"] in (True, False)
    bounded = [params[0], Parameter("k", 0.0, 0.2, 1e-6)]
    fit = levenberg_marquardt(clip, bounded, [1.0, 0.1], n=12.0, iterations=40, tolerance=1e-12)
    assert fit.theta[1] == pytest.approx(0.2, abs=1e-9)
    # the best a at k = 0.2 in closed form: Σ y e / Σ e² with e_t = exp(−0.2 t)
    e = [math.exp(-0.2 * t) for t in range(12)]
    assert fit.theta[0] == pytest.approx(sum(y * x for y, x in zip(clip.y, e)) / sum(x * x for x in e), rel=1e-4)


class CountingClip(DecayClip):
    """:class:`DecayClip` with measurements off by ±0.01 (so that the fit's loss stays finite), counting its
    rollouts."""

    def __init__(self, a: float, k: float) -> None:
        super().__init__(a, k)
        self.y = [y + 0.01 * (-1) ** t for t, y in enumerate(self.y)]
        self.rollouts = 0

    def simulate(self, theta, substeps=None):
        self.rollouts += 1
        return list(theta)


class SteppedClip(CountingClip):
    """:class:`CountingClip` whose automatic substep count jumps from 5 to 6 at a = ``jump``, and whose discrete
    solution then moves by ±0.01, alternating over the frames (as the reduced simulator's moves where √E crosses
    a count: a little, and nearly independently of the parameters' effect)."""

    def __init__(self, a: float, k: float, jump: float) -> None:
        super().__init__(a, k)
        self.jump = jump

    def substeps(self, theta):
        return 5 if theta[0] < self.jump else 6

    def simulate(self, theta, substeps=None):
        self.rollouts += 1
        return list(theta), self.substeps(theta) if substeps is None else substeps

    def residuals(self, trajectories, frame):
        return torch.tensor([[th[0] * math.exp(-th[1] * frame) - self.y[frame] - 0.01 * (n - 5) * (-1) ** frame]
                             for th, n in trajectories], dtype=torch.float64)


def test_levenberg_marquardt_compares_a_trial_with_theta_at_the_same_substep_count():
    """Just below a jump of the substep count, every step toward the best fit crosses it, and the jump raises the
    loss by more than the step lowers it: compared with θ at θ's own count, every trial is rejected and the fit stops
    at its start. Compared at the trial's count, as the fit does, the steps are taken,
    each lowers the objective of one discrete problem, and the fit ends on the best fit at the new count."""
    clip = SteppedClip(2.0, 0.3, jump=1.9701)
    params = [Parameter("a", 0.0, 10.0, 1e-6), Parameter("k", 0.0, 2.0, 1e-6)]
    start = [1.97, 0.3]
    fit = levenberg_marquardt(clip, params, start, n=12.0, iterations=20, tolerance=1e-9)
    assert fit.log[1]["accepted"] and fit.theta[0] > clip.jump
    start_at_6 = trajectory_loss(clip, clip.simulate(start, 6))
    assert fit.linearisation.substeps == 6 and fit.linearisation.loss < 0.7 * start_at_6
    assert float(fit.linearisation.gradient.abs().max()) < 1e-5  # the best fit of the count-6 problem
    # the rule this replaces, Φ(trial at its own count) < Φ(θ at θ's own count), rejects the first step
    assert fit.log[1]["objective"] > fit.log[0]["objective"]


def test_levenberg_marquardt_stops_without_trials_when_the_model_predicts_too_little():
    """Near the decay's best fit, with a tolerance above what a step could still gain, the fit stops at the first
    Jacobian without simulating a trial step (the start and one perturbed rollout per parameter, no more), says so,
    and logs the predicted decrease, which matches the one a step makes when the tolerance lets it."""
    clip = CountingClip(2.0, 0.3)
    params = [Parameter("a", 0.0, 10.0, 1e-6), Parameter("k", 0.0, 2.0, 1e-6)]
    best = levenberg_marquardt(clip, params, [1.0, 0.8], n=12.0, iterations=40, tolerance=1e-12).theta
    start = [best[0] + 0.003, best[1]]
    clip.rollouts = 0
    loose = levenberg_marquardt(clip, params, start, n=12.0, iterations=10, tolerance=1.0)
    assert loose.stop.startswith("converged: the Gauss–Newton model predicts")
    assert clip.rollouts == 1 + 2 and loose.theta == start  # the start, then one per parameter
    entry = loose.log[-1]
    assert not entry["accepted"] and 0 < entry["predicted_decrease"] < 1.0
    tight = levenberg_marquardt(clip, params, start, n=12.0, iterations=1, tolerance=1e-12)
    made = tight.log[0]["objective"] - tight.log[1]["objective"]
    assert tight.log[1]["accepted"] and made == pytest.approx(tight.log[1]["predicted_decrease"], rel=0.05)


class WalledClip(CountingClip):
    """:class:`CountingClip` whose simulation fails farther than ``reach`` from ``centre`` (the Jacobian's tiny
    steps stay inside): every trial step the Gauss–Newton model proposes is rejected."""

    def __init__(self, a: float, k: float, centre: list[float], reach: float) -> None:
        super().__init__(a, k)
        self.centre, self.reach = centre, reach

    def simulate(self, theta, substeps=None):
        self.rollouts += 1
        if max(abs(x - c) for x, c in zip(theta, self.centre)) > self.reach:
            raise SimulationError("outside the wall")
        return list(theta)


def test_levenberg_marquardt_stops_simulating_trials_once_they_promise_less_than_the_tolerance():
    """Every trial step is rejected. After each, the Marquardt damping grows until the step is short enough that the
    model promises at most half of what the rejected one promised; a trial promised less than the tolerance would end
    the fit even if accepted, so it is not simulated: the fit stops after the trials that promised more, and says
    why. With no tolerance all six are simulated."""
    params = [Parameter("a", 0.0, 10.0, 1e-6), Parameter("k", 0.0, 2.0, 1e-6)]
    start = [1.0, 0.8]
    clip = WalledClip(2.0, 0.3, start, reach=1e-5)
    every = levenberg_marquardt(clip, params, start, n=12.0, iterations=1, tolerance=0.0)
    trials = every.log[1]["trials"]
    assert len(trials) == 6 and all(t["decrease"] is None for t in trials)
    promised = [t["predicted_decrease"] for t in trials]
    # after each rejection the damping grows until the model promises at most half of what the last trial failed to give
    assert all(0 < b <= 0.5 * a for a, b in zip(promised, promised[1:]))
    assert all(b["damping"] > a["damping"] for a, b in zip(trials, trials[1:]))
    tolerance = 0.5 * (promised[1] + promised[2])  # between the second trial's promise and the third's
    clip.rollouts = 0
    fit = levenberg_marquardt(clip, params, start, n=12.0, iterations=5, tolerance=tolerance)
    assert [t["predicted_decrease"] for t in fit.log[1]["trials"]] == pytest.approx(promised[:2])
    assert clip.rollouts == 1 + 2 + 2 and fit.log[1]["rollouts"] == 2 + 1 + 2  # start, Jacobian, two trials
    assert fit.theta == start and not fit.log[1]["accepted"]
    assert fit.stop.startswith("no step lowers the objective by the tolerance")


def test_marquardt_step_holds_a_coordinate_at_its_bound_and_solves_for_the_rest():
    H = torch.tensor([[2.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    g = torch.tensor([2.0, -1.0], dtype=torch.float64)  # the unconstrained step: Δ = (−5/3, 4/3)
    params = [Parameter("x", 0.0, 1.0, 1e-3), Parameter("y", -5.0, 5.0, 1e-3)]
    step = marquardt_step(H, g, [0.0, 0.0], params, damping=0.0)
    assert step[0] == 0.0  # x sits at its lower bound and the step points out: held
    assert step[1] == pytest.approx(0.5)  # y solved alone: 2 Δy = 1


def test_laplace_intervals_hold_the_truth_at_their_level_on_a_linear_gaussian_model():
    """40 measurements with independent Gaussian noise, 2 parameters, 400 noisy draws: the 68 % and 95 %
    intervals of the fit (the residual variance estimated from the fit's own residuals) hold the truth about as
    often as they say (the maximum-likelihood variance is biased low by (F − p)/F, so slightly less)."""
    g = torch.Generator().manual_seed(0)
    F, truth = 40, torch.tensor([1.5, -0.5], dtype=torch.float64)
    A = torch.randn(F, 1, 2, generator=g, dtype=torch.float64)
    params = [Parameter("a", -100.0, 100.0, 1e-3, 0.0, 1e4), Parameter("b", -100.0, 100.0, 1e-3, 0.0, 1e4)]
    hits = {0.68: 0, 0.95: 0}
    draws = 400
    n = effective_images([1.0 / F] * F, 1)
    for _ in range(draws):
        y = (A @ truth) + 0.3 * torch.randn(F, 1, generator=g, dtype=torch.float64)
        clip = LinearClip(A / math.sqrt(F), y / math.sqrt(F))  # weighted residuals: Σ_t ‖r_t‖² is the mean
        lin = linearise(clip, params, torch.linalg.lstsq(A[:, 0], y[:, 0]).solution.tolist())
        for level in hits:
            record = laplace_intervals(lin, params, n, level)
            lo, hi = record["a"]["interval"]
            hits[level] += lo <= 1.5 <= hi
    assert 0.60 <= hits[0.68] / draws <= 0.72
    assert 0.90 <= hits[0.95] / draws <= 0.97


def _seen_and_unseen():
    """(fit, parameters) of a linear model of 10 frames whose second parameter has no effect (y = 2 x + noise)."""
    g = torch.Generator().manual_seed(1)
    A = torch.zeros(10, 3, 2, dtype=torch.float64)
    A[:, :, 0] = torch.randn(10, 3, generator=g, dtype=torch.float64)
    b = A[:, :, 0] * 2.0 + 0.1 * torch.randn(10, 3, generator=g, dtype=torch.float64)
    params = [Parameter("seen", -10, 10, 1e-3, 0.0, 5.0), Parameter("unseen", 0.0, 0.49, 1e-3, 0.3, 0.1)]
    return levenberg_marquardt(LinearClip(A, b), params, [0.0, 0.3], n=10.0, iterations=20, tolerance=1e-10), params


def test_a_direction_the_clip_does_not_see_is_not_identifiable_and_keeps_the_prior():
    """A linear model whose second parameter has no effect: its interval is the prior's, it is flagged, and
    the first parameter's interval is the data's."""
    fit, params = _seen_and_unseen()
    record = laplace_intervals(fit.linearisation, params, 10.0, 0.68)
    assert record["unseen"]["identifiable"] is False and record["unseen"]["note"] == NOT_IDENTIFIABLE
    assert record["unseen"]["data_sd"] is None and record["unseen"]["sd"] == pytest.approx(0.1, rel=1e-6)
    assert record["unseen"]["value"] == pytest.approx(0.3) and record["unseen"]["interval"] == pytest.approx(
        [0.3 - 0.1 * 0.9944578832097535, 0.3 + 0.1 * 0.9944578832097535])
    assert record["seen"]["identifiable"] is True and record["seen"]["value"] == pytest.approx(2.0, abs=0.05)
    assert information_by_frame(fit.linearisation, params)["unseen"] == [0.0] * 10


class TrackedClip(LinearClip):
    """The linear clip with a track: c(θ) = (C θ − d) / σ, measurements of known standard deviation σ."""

    def __init__(self, A, b, C, d, sd):
        super().__init__(A, b)
        self.C, self.d, self.sd = C, d, sd

    def track_residuals(self, trajectories):
        return torch.stack([(self.C @ th - self.d) / self.sd for th in trajectories])


def test_a_track_term_pins_what_the_images_do_not_see_and_the_fit_minimises_the_whole_objective():
    """The images see only the first parameter; a track of 4 measurements (σ = 0.05) sees the second. The fit lands
    where Φ (images, track and prior) is stationary, the second parameter moves from its prior to the track's value,
    is identifiable, and its interval is the track's: σ / √4 (the prior's 0.1 barely narrows it)."""
    g = torch.Generator().manual_seed(1)
    A = torch.zeros(10, 3, 2, dtype=torch.float64)
    A[:, :, 0] = torch.randn(10, 3, generator=g, dtype=torch.float64)
    b = A[:, :, 0] * 2.0 + 0.1 * torch.randn(10, 3, generator=g, dtype=torch.float64)
    C = torch.tensor([[0.0, 1.0]] * 4, dtype=torch.float64)
    d = torch.full((4,), 0.42, dtype=torch.float64)
    params = [Parameter("seen", -10, 10, 1e-3, 0.0, 5.0), Parameter("unseen", 0.0, 0.49, 1e-3, 0.3, 0.1)]
    clip = TrackedClip(A, b, C, d, 0.05)
    fit = levenberg_marquardt(clip, params, [0.0, 0.3], n=10.0, iterations=20, tolerance=1e-10)
    assert fit.log[-1]["track_loss"] == pytest.approx(fit.linearisation.track_loss)
    # Φ is stationary at the fit: its forward differences vanish
    for j, h in enumerate((1e-6, 1e-6)):
        def phi(theta):
            trajectory = clip.simulate(theta)
            return objective(trajectory_loss(clip, trajectory), theta, params, 10.0, track_loss(clip, trajectory))
        moved = list(fit.theta)
        moved[j] += h
        assert abs(phi(moved) - phi(fit.theta)) / h < 1e-3
    prior_weight = 0.1 ** -2 / (0.1 ** -2 + 4 / 0.05 ** 2)  # the posterior mean of two Gaussians
    assert fit.theta[1] == pytest.approx(0.3 * prior_weight + 0.42 * (1 - prior_weight), abs=1e-6)
    record = laplace_intervals(fit.linearisation, params, 10.0, 0.68)
    assert record["unseen"]["identifiable"] is True and record["unseen"]["data_sd"] == pytest.approx(0.025, rel=1e-3)
    assert record["unseen"]["noise_sd"] == pytest.approx((0.1 ** -2 + 4 / 0.05 ** 2) ** -0.5, rel=1e-3)


def test_a_fit_at_an_end_of_the_coarse_grid_says_so():
    """Log10 E found at the grid's end where its lowest loss lies is flagged (the best friction's grid when
    the search tried several), and only when the fit stayed within half a step of that end; an interior minimum,
    a fit that moved away, and no search are not."""
    grid = (4.0, 4.25, 4.5, 4.75, 5.0)
    falling = [{"log10_E": e, "loss": 1.0 + e} for e in grid]  # lowest at 4.0
    rising = [{"log10_E": e, "loss": 10.0 - e} for e in grid]  # lowest at 5.0
    valley = [{"log10_E": e, "loss": (e - 4.5) ** 2} for e in grid]
    assert coarse_edge(falling, 3.999) == "lower" and coarse_edge(falling, 4.12) == "lower"
    assert coarse_edge(falling, 4.2) is None  # the fit left the edge
    assert coarse_edge(rising, 5.01) == "upper" and coarse_edge(valley, 4.5) is None and coarse_edge([], 4.0) is None
    # two frictions: the best loss is at μ = 0.5, whose grid has its minimum inside; μ = 0's at its lower end
    two = [{**r, "floor_friction": 0.0, "loss": r["loss"] + 1.0} for r in falling] + \
        [{**r, "floor_friction": 0.5} for r in valley]
    assert coarse_edge(two, 4.5) is None
    record = {"log10_E": {"value": 3.999, "note": "found"}, "nu": {"value": 0.3, "note": NOT_IDENTIFIABLE}}
    mark_coarse_edge(record, falling)
    entry = record["log10_E"]
    assert entry["at_coarse_edge"] == "lower" and entry["note"].startswith("found; at the lower end")
    assert "log10 E 4" in entry["note"] and "softer" in entry["note"] and "at_coarse_edge" not in record["nu"]
    record = {"log10_E": {"value": 4.5, "note": "found"}}
    mark_coarse_edge(record, valley)
    assert record["log10_E"] == {"value": 4.5, "note": "found", "at_coarse_edge": None}


def test_a_value_the_fit_did_not_move_is_not_reported_as_found():
    """A fit whose every step was refused keeps its start: ν at the prior, log10 E at the coarse search's grid
    value. Where the images constrain them, the note says they were left there, not found."""
    record = {"log10_E": {"value": 5.0, "note": "found", "prior_mean": 5.0, "data_sd": 0.01},
              "nu": {"value": 0.3, "note": "found", "prior_mean": 0.3, "data_sd": 0.061},
              "damping_ratio": {"value": 0.05, "note": NOT_IDENTIFIABLE, "prior_mean": 0.05, "data_sd": 0.2},
              "floor_friction": {"value": 0.31, "note": "found", "prior_mean": 0.0, "data_sd": 0.01}}
    kept = {"log10_E": 5.0, "nu": 0.3, "damping_ratio": 0.05, "floor_friction": 0.31}
    # a fit that moved log10 E: ν stayed put (not moved) but keeps its note, the fit did not stop at its start
    partly = {k: dict(v) for k, v in record.items()}
    mark_unmoved(partly, {**kept, "log10_E": 5.25}, kept_start=False)
    assert partly["log10_E"]["moved"] and not partly["nu"]["moved"]
    assert partly["log10_E"]["note"] == "found" and partly["nu"]["note"] == "found"
    # a fit that kept its start: every step refused
    mark_unmoved(record, kept, kept_start=True)
    assert not record["log10_E"]["moved"]
    assert record["log10_E"]["note"].startswith("left at the prior's value")
    assert not record["nu"]["moved"]
    assert record["nu"]["note"].startswith("left at the prior's value: the images constrain it (data sd 0.061)")
    assert record["damping_ratio"]["note"] == NOT_IDENTIFIABLE  # already says the images do not tell
    assert record["floor_friction"]["note"].startswith("left at the coarse search's value")
    # with the coarse search's edge note after it, both are said
    record = {"log10_E": {"value": 4.0, "note": "found", "prior_mean": 5.0, "data_sd": 0.01}}
    mark_unmoved(record, {"log10_E": 4.0}, kept_start=True)
    mark_coarse_edge(record, [{"log10_E": e, "loss": 1.0 + e} for e in (4.0, 4.25, 4.5, 4.75, 5.0)])
    note = record["log10_E"]["note"]
    assert note.startswith("left at the coarse search's value") and "; at the lower end" in note


def test_the_models_own_error_widens_what_the_images_determine_and_not_what_they_do_not():
    """A model error m adds in the share the images set the value: a parameter the clip determines (sd ≪ prior
    sd) gets √(σ_noise² + m²), an unseen one keeps the prior's width exactly; the noise-only figure stays in the
    record, and a negative or infinite m is refused."""
    fit, params = _seen_and_unseen()
    noise = laplace_intervals(fit.linearisation, params, 10.0, 0.68)
    both = laplace_intervals(fit.linearisation, params, 10.0, 0.68, {"seen": 0.2, "unseen": 0.09})
    seen, seen0 = both["seen"], noise["seen"]
    assert seen0["model_sd"] == 0.0 and seen0["sd"] == seen0["noise_sd"]
    assert seen["noise_sd"] == seen0["sd"] and seen["model_sd"] == 0.2 and seen["data_sd"] == seen0["data_sd"]
    # sd ≈ 0.02 against a prior of 5: the images set the value, the two add in quadrature
    assert seen["sd"] == pytest.approx(math.hypot(seen0["sd"], 0.2), rel=1e-4)
    z = 0.9944578832097535
    assert seen["interval"] == pytest.approx([seen["value"] - z * seen["sd"], seen["value"] + z * seen["sd"]])
    assert seen["identifiable"] and seen["note"] == "found"  # judged on the images, not on the model error
    assert both["unseen"]["sd"] == noise["unseen"]["sd"] and both["unseen"]["interval"] == noise["unseen"]["interval"]
    # a parameter the images tell as well as the prior (its posterior variance half the prior's): half gets through
    from vid2sim.reconstruct.uncertainty import _model_variance

    assert _model_variance(0.1 / math.sqrt(2), 0.1, 0.09) == pytest.approx(0.5 * 0.09 ** 2)
    assert _model_variance(math.inf, 0.1, 0.1) == 0.0 and _model_variance(0.05, 0.1, 0.0) == 0.0
    assert _model_variance(0.2, 0.1, 0.1) == 0.0  # never negative
    for bad in (-0.1, math.inf, math.nan):
        with pytest.raises(ValueError, match="model error of seen"):
            laplace_intervals(fit.linearisation, params, 10.0, 0.68, {"seen": bad})
    for name in ("model_error_log10_E", "model_error_nu"):
        with pytest.raises(ConfigError, match=name):
            JointConfig(**{name: -0.01})


# ---- the joint stage on the reduced model's own motion ------------------------------------------------------------


def _own_motion(frames: int, log10_E: float, nu: float, zeta: float, linear, angular, floor: bool = True,
                friction: float = 0.0, substeps: int | None = 6):
    """The test drop (tests/test_pipeline_joint.py) simulated at the given material (and floor friction) and
    rendered in its 2 views; returns the simulator (at that material, ``substeps`` steps per frame, None: the
    automatic count), its Gaussians, cameras and images (2, frames, 32, 32, 3).

    The fits below recover the model's own motion, which is the same motion at any fixed step count: 6 steps per
    frame at every trial (the automatic count takes 9 … 32 over the coarse grids) cut their time by a quarter
    to a third; the automatic count's use by the fit is tested on models whose answer is known (above)."""
    sim, gaussians, cams = _scene_setup()
    sim.config = dataclasses.replace(sim.config, substeps=substeps)
    if not floor:
        sim.externals = sim.externals[:1]  # gravity only: free flight
    set_floor_friction(sim, friction)
    with torch.no_grad():
        sim.log10_E.fill_(log10_E)
        sim.nu.fill_(nu)
        sim.damping_ratio.fill_(zeta)
    start = sim.rigid_velocity_state(linear, angular, [0.0, 0.0, 0.0])
    with torch.no_grad():
        states = [start] + sim.rollout(start, frames - 1)
        images = render_states(GaussianRig(sim, gaussians), states, Observations(torch.zeros(2, frames, 32, 32, 3),
                                                                                 cams), [0, 1]).transpose(0, 1).float()
    return sim, gaussians, cams, images


def test_the_clip_jacobian_agrees_with_the_adjoint_gradient():
    """2 Jᵀr of the forward-difference Jacobian (small steps, one substep count, Newton to round-off) equals the
    gradient of the whole clip's weighted image loss by the simulator's adjoint and the renderer, for log10 E, ν,
    ζ and the initial velocity."""
    sim, gaussians, cams, images = _own_motion(6, 4.6, 0.35, 0.08, [0.1, 0.0, -1.0], [0.0, 1.0, 0.0])
    sim.config = dataclasses.replace(sim.config, substeps=8, newton_tol=1e-13, newton_rtol=1e-12,
                                     newton_max_iters=50, reuse_hessian=False)
    gaussians = gaussians.to(dtype=torch.float64)
    rig = GaussianRig(sim, gaussians)
    target = (images.double() + 0.05 * torch.rand(images.shape, generator=torch.Generator().manual_seed(0),
                                                  dtype=torch.float64)).clamp(0, 1)
    obs = Observations(target, cams)
    cfg = JointConfig(method="gauss_newton", fit_damping=True, fit_friction=False, frame_decay=3.0)
    prior = {"log10_E": 5.0, "nu": 0.3, "damping_ratio": 0.05}
    params = [dataclasses.replace(q, step=1e-6) for q in physical_parameters(sim, cfg, prior, 0.05)]
    clip = ClipResiduals(sim, rig, obs, [0.0, 0.0, 0.0], cfg.frame_decay, [q.name for q in params])
    theta = [4.5, 0.3, 0.05, 0.12, 0.01, -0.95, 0.05, 0.9, -0.02]
    fd = 2 * linearise(clip, params, theta).gradient

    clip.apply(theta)
    leaves = [sim.log10_E, sim.nu, sim.damping_ratio]
    for p in leaves:
        p.requires_grad_(True)
    v = torch.tensor(theta[3:6], dtype=torch.float64, requires_grad=True)
    w = torch.tensor(theta[6:9], dtype=torch.float64, requires_grad=True)
    states = sim.rollout(sim.rigid_velocity_state(v, w, [0.0, 0.0, 0.0]), 5)
    weights = frame_weights(6, 3.0)
    loss = sum(wt * ((render_states(rig, [s], obs, [0, 1])[0] - target[:, t + 1]) ** 2).mean()
               for t, (wt, s) in enumerate(zip(weights, states)))
    grads = torch.autograd.grad(loss, leaves + [v, w])
    for p in leaves:
        p.requires_grad_(False)
    adjoint = torch.cat([g.reshape(-1) for g in grads])
    assert torch.allclose(fd, adjoint, rtol=2e-3, atol=1e-4 * float(adjoint.abs().max()))


def test_worker_processes_give_the_jacobian_and_the_coarse_search_of_one_process():
    """The Jacobian's perturbed rollouts on two worker processes (each a pickled copy of the simulator, one torch
    thread) and here give the Gauss–Newton blocks of one process, to rounding: the split of the θ is fixed, and only
    the thread count differs. So does the coarse search's grid over E and the floor's friction, shared the same way."""
    from vid2sim.reconstruct.rollouts import RolloutPool, simulate_many
    from vid2sim.reconstruct.stages.joint import coarse_search

    sim, gaussians, cams, images = _own_motion(6, 4.6, 0.35, 0.08, [0.1, 0.0, -1.0], [0.0, 1.0, 0.0])
    rig = GaussianRig(sim, gaussians)
    cfg = JointConfig(method="gauss_newton", fit_damping=True, frame_decay=3.0)
    prior = {"log10_E": 5.0, "nu": 0.3, "damping_ratio": 0.05, "floor_friction": 0.0}
    params = physical_parameters(sim, cfg, prior, 0.05)
    clip = ClipResiduals(sim, rig, Observations(images, cams), [0.0, 0.0, 0.0], cfg.frame_decay,
                         [q.name for q in params])
    theta = [4.5, 0.3, 0.05, 0.2, 0.12, 0.01, -0.95, 0.05, 0.9, -0.02]
    assert len(theta) == len(params)
    here = linearise(clip, params, theta)
    slider, slider_gaussians, slider_cams, slider_images = _own_motion(6, 4.8, 0.3, 0.05, [1.2, 0.0, -1.0],
                                                                      [0.0, 0.0, 0.0], friction=0.6)
    slider_rig = GaussianRig(slider, slider_gaussians)
    coarse_cfg = JointConfig(fit_friction=True, coarse_log10_E=(4.4, 4.8, 5.2), coarse_friction=(0.0, 0.5))

    def search(pool):
        set_floor_friction(slider, 0.0)
        velocity = ([1.2, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        return coarse_search(slider, slider_rig, lambda: slider.rigid_velocity_state(*velocity),
                             Observations(slider_images, slider_cams), coarse_cfg, pool=pool, velocity=velocity)

    alone = search(None)
    with RolloutPool(2) as pool:
        clip.pool = pool
        there = linearise(clip, params, theta)
        shared = search(pool)
        for process in list(pool._executor._processes.values()):  # workers that die (as the spawned children of
            process.kill()  # an unguarded script do) are named
        with pytest.raises(RuntimeError, match="rollout worker processes ended before they answered"):
            simulate_many(clip.simulation, [theta, theta, theta], None, pool)
    assert [(r["floor_friction"], r["log10_E"]) for r in shared] == [(r["floor_friction"], r["log10_E"]) for r in alone]
    assert len(alone) == 6  # the frictional pair's walk, started at its best, tried both neighbours
    assert [r["loss"] for r in shared] == pytest.approx([r["loss"] for r in alone], rel=1e-9)
    assert there.steps == here.steps and there.substeps == here.substeps
    assert torch.allclose(there.frame_loss, here.frame_loss, rtol=1e-9, atol=0)
    scale = float(here.hessian.abs().max())
    assert torch.allclose(there.frame_hessian, here.frame_hessian, rtol=1e-6, atol=1e-9 * scale)
    assert torch.allclose(there.frame_gradient, here.frame_gradient, rtol=1e-6,
                          atol=1e-9 * float(here.gradient.abs().max()))


class ManyClip(WalledClip):
    """:class:`WalledClip` that simulates several θ in one call (as on worker processes), None where one fails."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.calls = []

    def simulate_many(self, thetas, substeps=None):
        self.calls.append(len(thetas))
        out = []
        for theta in thetas:
            try:
                out.append(self.simulate(theta, substeps))
            except SimulationError:
                out.append(None)
        return out


def test_a_jacobian_simulated_at_once_falls_back_to_the_other_side_where_a_step_fails():
    """The first steps of every parameter go to ``simulate_many`` in one call; a step that fails there (here: up, out
    of the model's reach along a) is retried down, one by one, as the sequential Jacobian would."""
    params = [Parameter("a", 0.0, 10.0, 1e-3), Parameter("k", 0.0, 2.0, 1e-6)]
    start = [1.0, 0.8]
    walled = ManyClip(2.0, 0.3, [start[0] - 1.0, start[1]], 1.0 + 5e-4)  # a + 1e-3 fails, a − 1e-3 does not
    lin = linearise(walled, params, start)
    assert walled.calls == [2] and lin.steps == [-1e-3, 1e-6]
    sequential = WalledClip(2.0, 0.3, [start[0] - 1.0, start[1]], 1.0 + 5e-4)
    assert linearise(sequential, params, start).steps == lin.steps
    assert torch.equal(linearise(sequential, params, start).frame_hessian, lin.frame_hessian)


def _own_motion_off_the_prior():
    """The model's own 8-frame drop at log10 E = 4.5, ν = 0.42, ζ = 0.1 with the simulator set to the prior (5, 0.3,
    0.05), and the Gauss–Newton settings that fit it (ζ too; no model error: the model's own motion)."""
    sim, gaussians, cams, images = _own_motion(8, 4.5, 0.42, 0.1, [0.1, 0.0, -1.0], [0.0, 1.0, 0.0])
    with torch.no_grad():
        sim.log10_E.fill_(5.0)
        sim.nu.fill_(0.3)
        sim.damping_ratio.fill_(0.05)
    cfg = JointConfig(
        method="gauss_newton", fit_damping=True, coarse_log10_E=(4.0, 4.4, 4.8, 5.2, 5.6), coarse_scale=1.0,
        gauss_newton_iterations=6, model_error_log10_E=0.0, model_error_nu=0.0,
    )
    return sim, gaussians, cams, images, cfg


@pytest.mark.slow
def test_gauss_newton_recovers_E_nu_and_damping_of_the_models_own_motion():
    """Images of the model's own drop at log10 E = 4.5, ν = 0.42, ζ = 0.1 (off the prior 5, 0.3, 0.05 in all
    three, the initial velocity off by 5 %): the coarse search and the Gauss–Newton fit recover all three, with
    intervals that hold them, say they are identifiable, and a validation loss far below the start's."""
    sim, gaussians, cams, images, cfg = _own_motion_off_the_prior()
    result = joint_optimisation(sim, gaussians, Observations(images, cams), [0.12, 0.0, -0.95], [0.0, 0.9, 0.0],
                                [0.0, 0.0, 0.0], cfg, progress=False)
    assert result.method == "gauss_newton"
    assert abs(result.log10_E - 4.5) < 0.01 and abs(result.nu - 0.42) < 0.01
    assert abs(result.damping_ratio - 0.1) < 0.005
    assert result.validation_loss < 0.01 * result.start_validation_loss
    for name in ("log10_E", "nu", "damping_ratio"):
        entry = result.uncertainty[name]
        assert entry["identifiable"] and entry["note"] == "found"
        assert entry["sd"] < 0.2 * entry["prior_sd"]
    assert result.uncertainty["log10_E"]["at_coarse_edge"] is None  # 4.5 lies inside the grid 4.0 … 5.6
    assert float(sim.log10_E) == pytest.approx(result.log10_E) and float(sim.nu) == pytest.approx(result.nu)
    # before the first contact the images say nothing about the material: its information comes after it
    info = result.information_by_frame
    assert sum(info["log10_E"]) == pytest.approx(1.0) and info["log10_E"][0] < 1e-3


def test_held_out_frames_judge_the_fit_and_are_left_out_of_it():
    """With the last 2 of 8 frames held out, the fit sees frames 0 … 5 only (its information spans frames 1 … 5) and
    still recovers the model's own material; the validation that judges it is the held-out frames' mean image loss,
    the fitted frames' trajectory continued to them (equal to a fresh rollout of the whole clip's, off the truth)."""
    sim, gaussians, cams, images, cfg = _own_motion_off_the_prior()
    cfg = dataclasses.replace(cfg, held_out_frames=2)
    obs = Observations(images, cams)
    result = joint_optimisation(sim, gaussians, obs, [0.12, 0.0, -0.95], [0.0, 0.9, 0.0], [0.0, 0.0, 0.0], cfg,
                                progress=False)
    assert abs(result.log10_E - 4.5) < 0.02 and abs(result.nu - 0.42) < 0.02
    assert len(result.information_by_frame["log10_E"]) == 5
    assert result.validation_loss < 0.01 * result.start_validation_loss

    rig = GaussianRig(sim, gaussians)
    names = ["log10_E", "nu"] + [f"{k}_velocity_{a}" for k in ("linear", "angular") for a in "xyz"]
    clip = ClipResiduals(sim, rig, Observations(images[:, :6], cams), [0.0, 0.0, 0.0], None, names)
    theta = [4.8, 0.35, 0.1, 0.0, -1.0, 0.0, 1.0, 0.0]
    value = _held_out_validation(clip, rig, obs)(theta, clip.simulate(theta))
    with torch.no_grad():
        start = clip.apply(theta)
        states = [start] + sim.rollout(start, 7)
        renders = render_states(rig, states[6:], obs, [0, 1])  # (2 frames, 2 views, 32, 32, 3), float32
    assert value == pytest.approx(float(((renders - images[:, 6:].transpose(0, 1)) ** 2).mean()), rel=1e-5)
    with pytest.raises(ValueError, match="held_out_frames=7 leaves 1 of the 8"):
        joint_optimisation(sim, gaussians, obs, [0.12, 0.0, -0.95], [0.0, 0.9, 0.0], [0.0, 0.0, 0.0],
                           dataclasses.replace(cfg, held_out_frames=7), progress=False)


def test_held_out_frames_are_a_count_for_the_gauss_newton_fit():
    with pytest.raises(ConfigError, match="held_out_frames must be an integer >= 0"):
        JointConfig(held_out_frames=-1)
    with pytest.raises(ConfigError, match="needs the gauss_newton method"):
        JointConfig(method="windows", held_out_frames=2)


@pytest.mark.slow
def test_gauss_newton_recovers_the_floors_friction_of_the_models_own_motion():
    """Images of the model's own drop onto a floor with Coulomb friction μ = 0.6, thrown sideways so that it slides
    after landing: from the prior μ = 0.2 (E at the truth, no coarse search) the fit recovers μ, reports it
    identifiable, and leaves the simulator with it."""
    sim, gaussians, cams, images = _own_motion(7, 4.8, 0.3, 0.05, [1.2, 0.0, -1.0], [0.0, 0.0, 0.0], friction=0.6)
    set_floor_friction(sim, 0.2)
    cfg = JointConfig(method="gauss_newton", fit_friction=True, coarse_log10_E=(), coarse_scale=1.0,
                      gauss_newton_iterations=5)
    result = joint_optimisation(sim, gaussians, Observations(images, cams), [1.2, 0.0, -1.0], [0.0, 0.0, 0.0],
                                [0.0, 0.0, 0.0], cfg, progress=False)
    assert abs(result.floor_friction - 0.6) < 0.03 and abs(result.log10_E - 4.8) < 0.05
    assert floor_friction(sim) == pytest.approx(result.floor_friction)
    entry = result.uncertainty["floor_friction"]
    assert entry["identifiable"] and entry["prior_mean"] == pytest.approx(0.2)
    assert result.validation_loss < 0.1 * result.start_validation_loss


def test_the_coarse_search_picks_the_floors_friction_with_E():
    """On the model's own sliding drop with μ = 0.6 the coarse search over E × the friction grid (0, 0.5) picks 0.5
    and that row's E, and records the friction of every grid point; on the frictionless drop it picks 0."""
    from vid2sim.reconstruct.stages.joint import coarse_search

    for truth, expected in ((0.6, 0.5), (0.0, 0.0)):
        sim, gaussians, cams, images = _own_motion(6, 4.8, 0.3, 0.05, [1.2, 0.0, -1.0], [0.0, 0.0, 0.0],
                                                   friction=truth)
        set_floor_friction(sim, 0.0)
        cfg = JointConfig(fit_friction=True, coarse_log10_E=(4.4, 4.8, 5.2), coarse_friction=(0.0, 0.5))
        rig = GaussianRig(sim, gaussians)
        records = coarse_search(sim, rig, lambda: sim.rigid_velocity_state([1.2, 0.0, -1.0], [0.0, 0.0, 0.0],
                                                                           [0.0, 0.0, 0.0]),
                                Observations(images, cams), cfg)
        assert [(r["floor_friction"], r["log10_E"]) for r in records] == [(mu, e) for mu in (0.0, 0.5)
                                                                          for e in (4.4, 4.8, 5.2)]
        assert floor_friction(sim) == expected and abs(float(sim.log10_E) - 4.8) < 0.2


def test_the_coarse_search_picks_the_contact_surface_the_video_was_made_with():
    """The model's own drop, offered two contact surfaces: the "hull", with a keel (the true surface plus points 3 cm
    under its bottom, as a 4-view hull's), and the true one. The coarse search tries E on both, keeps the true
    surface and its E, and leaves the simulator with that surface."""
    from vid2sim.reconstruct.stages.joint import coarse_search

    sim, gaussians, cams, images = _own_motion(6, 4.8, 0.3, 0.05, [0.3, 0.0, -1.0], [0.0, 0.0, 0.0])
    true_points, true_areas = sim.contact_points, sim.contact_weights
    bottom = true_points[true_points[:, 2] < float(true_points[:, 2].min()) + 0.02]
    keel = torch.cat([true_points, bottom - torch.tensor([0.0, 0.0, 0.03], dtype=bottom.dtype)])
    keel_areas = torch.cat([true_areas, true_areas[: len(bottom)]])
    sim.set_contact(keel, keel_areas)
    cfg = JointConfig(fit_friction=False, coarse_log10_E=(4.4, 4.8, 5.2), contact_search=True)
    rig = GaussianRig(sim, gaussians)
    records = coarse_search(sim, rig, lambda: sim.rigid_velocity_state([0.3, 0.0, -1.0], [0.0, 0.0, 0.0],
                                                                       [0.0, 0.0, 0.0]),
                            Observations(images, cams), cfg, contacts={"hull": (keel, keel_areas),
                                                                       "floor-carved": (true_points, true_areas)})
    assert [(r["contact_surface"], r["log10_E"]) for r in records] == [
        (c, e) for c in ("hull", "floor-carved") for e in (4.4, 4.8, 5.2)]
    best = min(records, key=lambda r: r["loss"])
    assert best["contact_surface"] == "floor-carved" and best["log10_E"] == 4.8 and best["loss"] < 1e-8
    assert min(r["loss"] for r in records if r["contact_surface"] == "hull") > 1e-5  # the keel changes the bounce
    assert torch.equal(sim.contact_points, true_points) and abs(float(sim.log10_E) - 4.8) < 0.05


@pytest.mark.slow
def test_a_clip_without_contact_says_the_material_is_not_identifiable():
    """Free flight without spin (no floor): nothing deforms the body, so the images carry no information about E,
    ν or ζ. They stay at the prior, flagged "not identifiable from this video" with the prior's width, while the
    initial velocity is fitted."""
    sim, gaussians, cams, images = _own_motion(5, 4.5, 0.42, 0.1, [0.1, 0.0, -1.0], [0.0, 0.0, 0.0], floor=False)
    with torch.no_grad():
        sim.log10_E.fill_(5.0)
        sim.nu.fill_(0.3)
        sim.damping_ratio.fill_(0.05)
    cfg = JointConfig(
        method="gauss_newton", fit_damping=True, coarse_log10_E=(), coarse_scale=1.0, gauss_newton_iterations=3
    )
    result = joint_optimisation(sim, gaussians, Observations(images, cams), [0.12, 0.0, -0.95], [0.0, 0.0, 0.0],
                                [0.0, 0.0, 0.0], cfg, progress=False)
    for name, prior in (("log10_E", 5.0), ("nu", 0.3), ("damping_ratio", 0.05)):
        entry = result.uncertainty[name]
        assert not entry["identifiable"] and entry["note"] == NOT_IDENTIFIABLE
        assert entry["value"] == pytest.approx(prior, abs=5e-3)  # 0.005 decade: the prior's, to the clip's noise
        assert entry["sd"] == pytest.approx(entry["prior_sd"], rel=0.02)
    assert result.linear_velocity == pytest.approx([0.1, 0.0, -1.0], abs=2e-3)


# ---- what evaluate makes of the record ---------------------------------------------------------------------------


def test_evaluate_scores_the_intervals_against_the_truth_and_the_fit_against_its_start():
    """The interval of a reconstruction holds a truth inside it (1.0) and not one outside (0.0); a parameter
    without an interval is left out; the joint fit's record says whether the kept state beat the start."""
    from vid2sim.evaluate.scores import interval_coverage, joint_fit_record

    record = {"log10_E": {"interval": [5.1, 5.6]}, "nu": {"interval": [0.30, 0.36]}}
    assert interval_coverage(record, {"log10_E": 5.477, "nu": 0.42, "damping_ratio": 0.05}) == \
        {"log10_E": 1.0, "nu": 0.0}
    assert joint_fit_record({"start_validation_loss": 2e-3, "validation_loss": 1e-3, "joint_method": "gauss_newton"}) \
        == {"start_validation_loss": 2e-3, "validation_loss": 1e-3, "improved": 1.0, "method": "gauss_newton"}
    assert joint_fit_record({"start_validation_loss": 1e-3, "validation_loss": 1e-3})["improved"] == 0.0
    assert joint_fit_record({"validation_loss": 1e-3}) is None  # an asset made before the start was recorded


def test_the_scenes_true_floor_friction_is_read_from_its_metadata():
    """``floor_friction`` when the scene says it; scenes made before it: the independent engine's contact record, or
    0 for our FEM truth's frictionless floor; None for a scene that does not say (a capture)."""
    from vid2sim.evaluate.scores import true_floor_friction

    assert true_floor_friction({"floor_friction": 0.3, "truth": "fem"}) == 0.3
    assert true_floor_friction({"truth": "newton", "newton": {"contact": {"friction": 0.5}}}) == 0.5
    assert true_floor_friction({"truth": "fem"}) == 0.0
    assert true_floor_friction({}) is None and true_floor_friction({"floor_friction": "rough"}) is None


def test_grid_descent_walks_to_the_local_minimum_and_evaluates_each_point_once():
    """From any start the walk ends at the grid's minimum of a unimodal loss, evaluating a contiguous stretch once
    each; on a loss with two valleys it stops in the start's; at an end it stops there; a start off the grid is a
    named error."""
    from vid2sim.reconstruct.stages.joint import grid_descent

    def walk(losses, start):
        calls = []
        found = grid_descent(len(losses), start, lambda i: calls.append(i) or losses[i])
        return found, calls

    unimodal = [5.0, 4.0, 3.0, 2.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    for start in range(9):
        found, calls = walk(unimodal, start)
        assert found == 4 and len(calls) == len(set(calls))
        assert sorted(calls) == list(range(min(calls), max(calls) + 1))
        assert len(calls) <= abs(start - 4) + 3
    assert walk(unimodal, 4)[1] == [3, 4, 5]
    two_valleys = [3.0, 1.0, 3.0, 4.0, 2.0, 0.5, 2.0]
    assert walk(two_valleys, 2)[0] == 1 and walk(two_valleys, 3)[0] == 5
    assert walk([1.0, 2.0, 3.0], 2) == (0, [1, 2, 0])
    with pytest.raises(ValueError, match="outside the grid"):
        grid_descent(3, 3, lambda i: 0.0)


def test_the_coarse_search_walks_the_second_frictions_grid_from_the_first_ones_best():
    """With five grid values the first friction runs them all and the second only walks downhill from the first's
    best E, so it tries fewer; every row tried is recorded in ascending E per friction, and the picked pair is the
    lowest of all rows."""
    from vid2sim.reconstruct.stages.joint import coarse_search

    sim, gaussians, cams, images = _own_motion(6, 4.8, 0.3, 0.05, [1.2, 0.0, -1.0], [0.0, 0.0, 0.0], friction=0.0)
    cfg = JointConfig(fit_friction=True, coarse_log10_E=(5.6, 4.0, 4.4, 4.8, 5.2), coarse_friction=(0.0, 0.5))
    records = coarse_search(sim, GaussianRig(sim, gaussians),
                            lambda: sim.rigid_velocity_state([1.2, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
                            Observations(images, cams), cfg)
    first = [r["log10_E"] for r in records if r["floor_friction"] == 0.0]
    second = [r["log10_E"] for r in records if r["floor_friction"] == 0.5]
    assert first == [4.0, 4.4, 4.8, 5.2, 5.6]
    assert second == sorted(second) and 2 <= len(second) < 5
    best = min(records, key=lambda r: r["loss"])
    assert floor_friction(sim) == best["floor_friction"] == 0.0


def test_the_kept_states_jacobian_is_reused_when_a_later_step_made_it():
    """When the validation keeps an earlier θ than the last, its intervals come from the Jacobian made at it during
    the fit, not from a new one: no rollouts after the last iteration's, and the same blocks as a fresh one."""
    clip = CountingClip(2.0, 0.3)
    params = [Parameter("a", 0.0, 10.0, 1e-6), Parameter("k", 0.0, 2.0, 1e-6)]
    calls = []

    def validate(theta, trajectory):  # prefers the first step's θ over every later one
        calls.append(list(theta))
        return 0.0 if len(calls) == 2 else 1.0

    fit = levenberg_marquardt(clip, params, [1.0, 0.8], n=12.0, iterations=3, tolerance=1e-12, validate=validate,
                              patience=5)
    assert fit.theta == calls[1] and fit.log[-1]["accepted"] and fit.theta != calls[-1]
    # the start, then each iteration's (its logged count includes θ's own trajectory, already made); nothing after
    expected = 1 + sum(e["rollouts"] - 1 for e in fit.log[1:])
    assert clip.rollouts == expected
    fresh = linearise(clip, params, fit.theta)
    assert torch.equal(fit.linearisation.frame_hessian, fresh.frame_hessian)
