"""Levenberg–Marquardt over the few physical parameters of a simulated clip (the joint stage's default fit).

The joint optimisation's unknowns that decide the motion are few: log10 E, ν, the damping ratio ζ and the initial
linear and angular velocity (p = 8 or 9 numbers). Their residuals are many: every pixel of every observed view in
every observed frame. For such a problem Gauss–Newton is the natural method. The Jacobian J of the residuals
(p columns) comes from p + 1 rollouts of the whole observed clip (forward differences at a fixed substep count,
so that every column differentiates one discrete problem), which costs about as much as three adjoint gradients
and gives the curvature JᵀJ besides: the step, the uncertainty (:mod:`vid2sim.reconstruct.uncertainty`) and what
each frame says about each parameter all come from it.

The fit minimises a posterior, not the bare image loss:

    Φ(θ) = n/2 · log L(θ) + ½ ‖c(θ)‖² + ½ Σ_j ((θ_j − μ_j) / σ_j)²

where L is the weighted mean squared image error of the whole clip (``Σ_t ‖r_t‖²``, the residual blocks of
:class:`ClipModel`), n the number of independent measurements it holds (the effective number of images,
:func:`effective_images`) and (μ_j, σ_j) a Gaussian prior on the material (none on the velocities). The
logarithm profiles out the unknown image noise variance (σ̂² = L/n at the optimum). A direction the images do
not constrain stays at the prior instead of wandering along a flat valley, and
:func:`vid2sim.reconstruct.uncertainty.laplace_intervals` then says so. c are the model's *track* residuals, when it
has them (:meth:`ClipModel.track_residuals`): measurements of known standard deviation, already divided by it (the
joint stage's body position from the visual hulls), so their term needs no profiling.

Every step is accepted only if it lowers Φ on a fresh rollout, compared with θ at the same substep count: the
larger of θ's and the trial's automatic counts. The count jumps by one where √E crosses a step (at 7 substeps, every
0.11 decade of E), and the jump's change of the discrete solution can exceed what a damped step gains: compared
across counts, every step toward the minimum could be rejected and the fit stop where it started. Otherwise the
Marquardt damping grows and the step shrinks. Parameters stay inside their bounds (a step that
would leave the box along a coordinate at its bound holds that coordinate).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, Sequence

import torch
from torch import Tensor

from vid2sim.physics.solver import SimulationError


@dataclass(frozen=True)
class Parameter:
    """One fitted parameter.

    Attributes:
        name: its name (``log10_E``, ``nu``, ``damping_ratio``, ``linear_velocity_x`` …).
        lower, upper: its bounds.
        step: the forward-difference step of the Jacobian (in the parameter's units).
        prior_mean, prior_sd: the Gaussian prior's mean and standard deviation, or None (no prior).
    """

    name: str
    lower: float
    upper: float
    step: float
    prior_mean: float | None = None
    prior_sd: float | None = None

    def __post_init__(self) -> None:
        if not (self.lower < self.upper and self.step > 0):
            raise ValueError(f"parameter {self.name}: needs lower < upper and step > 0, got {self.lower}, "
                             f"{self.upper}, {self.step}")
        if (self.prior_mean is None) != (self.prior_sd is None) or (self.prior_sd is not None and self.prior_sd <= 0):
            raise ValueError(f"parameter {self.name}: a prior needs a mean and a standard deviation > 0")


class ClipModel(Protocol):
    """The observed clip as a function of the parameters θ (p numbers, in the order of the parameter list).

    ``frames`` residual blocks, one per observed frame 1 … T−1: block t is the frame's image error over every
    view, weighted so that Σ_t ‖r_t‖² is the clip's loss L. A model may also have ``simulate_many(thetas,
    substeps)``: the trajectories of several θ (None where one fails), which :func:`linearise` then uses for the
    Jacobian's independent rollouts (e.g. on worker processes, :mod:`vid2sim.reconstruct.rollouts`)."""

    frames: int

    def substeps(self, theta: Sequence[float]) -> int:
        """The automatic substep count at θ."""

    def simulate(self, theta: Sequence[float], substeps: int | None = None) -> Any:
        """The trajectory at θ (opaque to the fit; None substeps: the automatic count). Raises
        :class:`~vid2sim.physics.solver.SimulationError` where the simulation fails."""

    def residuals(self, trajectories: Sequence[Any], frame: int) -> Tensor:
        """(len(trajectories), n_t) weighted residuals of block ``frame`` (0 … frames−1) of each trajectory."""

    def track_residuals(self, trajectories: Sequence[Any]) -> Tensor | None:
        """(len(trajectories), m) track residuals c of each trajectory, each divided by its standard deviation
        (module docstring), or None: no track term."""


@dataclass
class Linearisation:
    """The clip's residuals and their Jacobian at θ, reduced to per-frame Gauss–Newton blocks.

    Attributes:
        theta: (p,) where it was taken.
        substeps: the substep count every rollout of it used.
        frame_loss: (F,) ‖r_t‖² per frame block (their sum is the loss L).
        frame_hessian: (F, p, p) J_tᵀ J_t per frame block, float64.
        frame_gradient: (F, p) J_tᵀ r_t per frame block, float64.
        steps: (p,) the difference steps used (negative where a step up would have left the bounds or failed).
        track_loss: ‖c‖², the track residuals' squared norm (0 without a track).
        track_hessian, track_gradient: (p, p) J_cᵀ J_c and (p,) J_cᵀ c, float64 (zeros without a track).
    """

    theta: list[float]
    substeps: int
    frame_loss: Tensor
    frame_hessian: Tensor
    frame_gradient: Tensor
    steps: list[float]
    track_loss: float = 0.0
    track_hessian: Tensor | None = None
    track_gradient: Tensor | None = None

    def __post_init__(self) -> None:
        p = len(self.theta)
        if self.track_hessian is None:
            self.track_hessian = torch.zeros(p, p, dtype=torch.float64)
        if self.track_gradient is None:
            self.track_gradient = torch.zeros(p, dtype=torch.float64)

    @property
    def loss(self) -> float:
        """L = Σ_t ‖r_t‖²."""
        return float(self.frame_loss.sum())

    @property
    def hessian(self) -> Tensor:
        """(p, p) JᵀJ."""
        return self.frame_hessian.sum(0)

    @property
    def gradient(self) -> Tensor:
        """(p,) Jᵀr (half the gradient of L)."""
        return self.frame_gradient.sum(0)


def _first_step(theta: list[float], j: int, parameter: Parameter) -> float:
    """The difference step of θ_j tried first: up, unless that would leave the bounds."""
    return parameter.step if theta[j] + parameter.step <= parameter.upper else -parameter.step


def _perturbed(model: ClipModel, theta: list[float], j: int, parameter: Parameter, substeps: int,
               tried: bool = False) -> tuple[Any, float]:
    """The trajectory with θ_j moved by ± its step (down when up would leave the bounds or fail), and the step;
    ``tried``: the first step (:func:`_first_step`) has failed already."""
    first = _first_step(theta, j, parameter)
    steps = (first, -first) if first > 0 else (first,)
    for h in steps[1:] if tried else steps:
        moved = list(theta)
        moved[j] += h
        try:
            return model.simulate(moved, substeps), h
        except SimulationError:
            continue
    raise SimulationError(f"the simulation fails on both sides of {parameter.name} = {theta[j]:.6g}")


def _perturbations(model: ClipModel, parameters: Sequence[Parameter], theta: list[float],
                   substeps: int) -> tuple[list[Any], list[float]]:
    """Each parameter's perturbed trajectory and step (:func:`_perturbed`). A model with ``simulate_many`` (θs,
    substeps → trajectories, None where one fails) simulates the first steps of all of them in one call (on worker
    processes, :class:`~vid2sim.reconstruct.stages.joint.ClipResiduals`); the rest are tried one by one."""
    if not hasattr(model, "simulate_many"):
        pairs = [_perturbed(model, theta, j, q, substeps) for j, q in enumerate(parameters)]
        return [t for t, _ in pairs], [h for _, h in pairs]
    steps = [_first_step(theta, j, q) for j, q in enumerate(parameters)]
    moved = [[x + (h if k == j else 0.0) for k, x in enumerate(theta)] for j, h in enumerate(steps)]
    variants = list(model.simulate_many(moved, substeps))
    for j, q in enumerate(parameters):
        if variants[j] is None:
            variants[j], steps[j] = _perturbed(model, theta, j, q, substeps, tried=True)
    return variants, steps


def linearise(model: ClipModel, parameters: Sequence[Parameter], theta: Sequence[float],
              base: Any | None = None) -> Linearisation:
    """The per-frame Gauss–Newton blocks at θ by forward differences (p + 1 rollouts of the clip, all at the
    automatic substep count of θ; ``base``: θ's own trajectory at that count, when already simulated).

    The p perturbed trajectories are simulated first, then each frame's p + 1 renders are compared at once, so
    the Jacobian is never held whole: memory is one frame's (p + 1) × n_t residuals."""
    theta = [float(x) for x in theta]
    n = model.substeps(theta)
    base = model.simulate(theta, n) if base is None else base
    variants, steps = _perturbations(model, parameters, theta, n)
    p, F = len(parameters), model.frames
    step_t = torch.tensor(steps, dtype=torch.float64)
    frame_loss = torch.zeros(F, dtype=torch.float64)
    frame_hessian = torch.zeros(F, p, p, dtype=torch.float64)
    frame_gradient = torch.zeros(F, p, dtype=torch.float64)
    for t in range(F):
        with torch.no_grad():
            R = model.residuals([base] + variants, t)  # (p + 1, n_t)
            r = R[0]
            J = (R[1:] - r) / step_t.to(R)[:, None]  # (p, n_t)
            frame_loss[t] = float(r.double() @ r.double())
            frame_hessian[t] = (J @ J.T).double()
            frame_gradient[t] = (J @ r).double()
    lin = Linearisation(theta, n, frame_loss, frame_hessian, frame_gradient, steps)
    with torch.no_grad():
        R = model.track_residuals([base] + variants)
    if R is not None:
        R = R.double()
        J = (R[1:] - R[0]) / step_t[:, None]  # (p, m)
        lin.track_loss, lin.track_hessian, lin.track_gradient = float(R[0] @ R[0]), J @ J.T, J @ R[0]
    return lin


def effective_images(frame_weights: Sequence[float], views: int) -> float:
    """n: the number of independent measurements a whole-clip loss holds, counting each (view, frame) image as
    one (the image errors of a model that is off are correlated over a whole image, not pixel by pixel): the
    Kish effective sample size of the images' weights, views × (Σ w)² / Σ w²."""
    total = sum(frame_weights)
    squares = sum(w * w for w in frame_weights)
    return views * total * total / squares if squares > 0 else 0.0


def prior_precision(parameters: Sequence[Parameter]) -> tuple[Tensor, Tensor]:
    """(p,) the prior's precisions 1/σ² (0 where a parameter has no prior) and (p,) its means (0 there)."""
    precision = torch.tensor([0.0 if q.prior_sd is None else q.prior_sd ** -2 for q in parameters],
                             dtype=torch.float64)
    mean = torch.tensor([0.0 if q.prior_mean is None else q.prior_mean for q in parameters], dtype=torch.float64)
    return precision, mean


def objective(loss: float, theta: Sequence[float], parameters: Sequence[Parameter], n: float,
              track: float = 0.0) -> float:
    """Φ(θ) = n/2 · log L + ½ ‖c‖² + ½ Σ_j ((θ_j − μ_j)/σ_j)² (module docstring; ``track`` = ‖c‖²); +inf for a
    non-finite loss."""
    if not (math.isfinite(loss) and math.isfinite(track)):
        return math.inf
    precision, mean = prior_precision(parameters)
    d = torch.tensor(list(theta), dtype=torch.float64) - mean
    return 0.5 * n * math.log(max(loss, 1e-300)) + 0.5 * track + 0.5 * float((precision * d * d).sum())


def posterior_curvature(lin: Linearisation, parameters: Sequence[Parameter], n: float) -> tuple[Tensor, Tensor]:
    """The Gauss–Newton Hessian (p, p) and gradient (p,) of Φ at ``lin.theta``: n JᵀJ / L + J_cᵀJ_c + P and
    n Jᵀr / L + J_cᵀc + P (θ − μ)."""
    precision, mean = prior_precision(parameters)
    scale = n / max(lin.loss, 1e-300)
    theta = torch.tensor(lin.theta, dtype=torch.float64)
    hessian = scale * lin.hessian + lin.track_hessian + torch.diag(precision)
    gradient = scale * lin.gradient + lin.track_gradient + precision * (theta - mean)
    return hessian, gradient


def marquardt_step(hessian: Tensor, gradient: Tensor, theta: Sequence[float], parameters: Sequence[Parameter],
                   damping: float) -> list[float]:
    """θ + Δ with (H + damping · diag H) Δ = −g, kept in the bounds: a coordinate at a bound whose step points out
    of the box is held there and the step solved again without it; the rest is clipped to the bounds."""
    p = len(parameters)
    free = list(range(p))
    lower = [q.lower for q in parameters]
    upper = [q.upper for q in parameters]
    delta = torch.zeros(p, dtype=torch.float64)
    for _ in range(p):
        idx = torch.tensor(free, dtype=torch.long)
        H = hessian[idx][:, idx]
        A = H + damping * torch.diag(torch.diagonal(H).clamp_min(1e-12))
        d = torch.linalg.solve(A, -gradient[idx])
        delta.zero_()
        delta[idx] = d
        blocked = [j for j in free
                   if (theta[j] <= lower[j] and delta[j] < 0) or (theta[j] >= upper[j] and delta[j] > 0)]
        if not blocked:
            break
        free = [j for j in free if j not in blocked]
        if not free:
            delta.zero_()
            break
    return [min(max(float(theta[j] + delta[j]), lower[j]), upper[j]) for j in range(p)]


def shortened_step(hessian: Tensor, gradient: Tensor, theta: Sequence[float], parameters: Sequence[Parameter],
                   damping: float, ceiling: float = math.inf, growth: float = 4.0,
                   max_damping: float = 1e12) -> tuple[list[float], float, float]:
    """The Marquardt step (:func:`marquardt_step`) at the smallest damping of damping · growth^k, k ≥ 0, whose
    predicted decrease (:func:`predicted_decrease`) is at most ``ceiling`` (the damping stops growing at
    ``max_damping``). Returns (the trial θ, its predicted decrease, the damping used)."""
    while True:
        trial = marquardt_step(hessian, gradient, theta, parameters, damping)
        promised = predicted_decrease(hessian, gradient, theta, trial)
        if promised <= ceiling or damping * growth > max_damping:
            return trial, promised, damping
        damping *= growth


def predicted_decrease(hessian: Tensor, gradient: Tensor, theta: Sequence[float], trial: Sequence[float]) -> float:
    """The decrease of Φ the Gauss–Newton model (Φ's ``hessian`` (p, p) and ``gradient`` (p,) at θ) predicts for the
    move from θ to ``trial``: −(gᵀΔ + ½ ΔᵀHΔ)."""
    delta = torch.tensor(list(trial), dtype=torch.float64) - torch.tensor(list(theta), dtype=torch.float64)
    return float(-(gradient @ delta + 0.5 * delta @ (hessian @ delta)))


@dataclass
class FitResult:
    """What :func:`levenberg_marquardt` found.

    Attributes:
        theta: (p,) the kept parameters (the best by ``validate``, or by Φ without it).
        linearisation: the Gauss–Newton blocks at ``theta`` (for the uncertainty and the information by frame).
        objective: Φ at ``theta``.
        validation_loss: ``validate(theta)`` (None without ``validate``); with a track term the kept θ is the best
            by n/2 · log(validation loss) + ½ ‖c‖², the validated Φ without its prior.
        start_validation_loss: ``validate`` of the start (None without it).
        log: one dict per iteration: ``iteration``, ``loss`` (L), ``objective`` (Φ, both at the state's own automatic
            substep count: a step accepted on the comparison at a common count may show a higher Φ than the entry
            before), ``damping`` (Marquardt's λ),
            ``accepted``, ``rollouts``, ``ms``, ``predicted_decrease`` (of the first trial step) and ``trials`` (each
            simulated trial's ``damping``, ``predicted_decrease`` and ``decrease``, None where rejected), the
            parameters by name, ``validation_loss`` when validated and
            ``track_loss`` (‖c‖²) with a track term.
        stop: why it stopped.
    """

    theta: list[float]
    linearisation: Linearisation
    objective: float
    validation_loss: float | None
    start_validation_loss: float | None
    log: list[dict[str, Any]] = field(default_factory=list)
    stop: str = ""


def levenberg_marquardt(model: ClipModel, parameters: Sequence[Parameter], theta0: Sequence[float], n: float,
                        iterations: int = 8, tolerance: float = 1e-3, patience: int = 2,
                        validate: Callable[[list[float], Any], float] | None = None,
                        on_iteration: Callable[[dict[str, Any]], None] | None = None,
                        validation_with_track: bool = True) -> FitResult:
    """Minimise Φ (module docstring) from θ0 by Levenberg–Marquardt with forward-difference Jacobians.

    Args:
        model: the clip (:class:`ClipModel`).
        parameters: the p parameters (bounds, difference steps, priors); θ0 must lie in the bounds.
        n: the effective number of measurements (:func:`effective_images`).
        iterations: at most this many Jacobians (each p + 1 rollouts, plus the trial steps).
        tolerance: stop when an accepted step lowers Φ by less than this, or when the Gauss–Newton model predicts
            less for a trial step (:func:`predicted_decrease`; that trial is not simulated: the first one, or one
            whose damping grew after rejected trials). Φ is in units of log-likelihood: 0.05 is a change of the loss
            of 0.1 / n of itself.
        patience: stop when ``validate`` has not improved on its best for this many accepted steps.
        validate: θ, its trajectory → the validation loss (e.g. the clip at full resolution); the kept θ is
            the best by it (with a track term, by n/2 · log of it + ½ ‖c‖²), the start included. None: the last
            accepted θ is kept.
        validation_with_track: whether the keep-best criterion adds the model's track term (False where ``validate``
            judges frames the model's residuals and track leave out: the criterion is then the validation loss alone).
    Returns:
        :class:`FitResult`; the model's simulator is left at an arbitrary θ (set it from ``theta``).
    """
    p = len(parameters)
    theta = [float(x) for x in theta0]
    for q, x in zip(parameters, theta):
        if not q.lower <= x <= q.upper:
            raise ValueError(f"the start of {q.name} ({x}) lies outside its bounds [{q.lower}, {q.upper}]")
    trajectory = model.simulate(theta)
    loss, track = trajectory_loss(model, trajectory), track_loss(model, trajectory)
    phi = objective(loss, theta, parameters, n, track or 0.0)
    keep = _KeepBest(validate, n, validation_with_track)
    start_val = keep.offer(theta, trajectory, phi, track)
    log: list[dict[str, Any]] = [{"iteration": 0, "accepted": True, "rollouts": 1,
                                  **_values(parameters, theta, loss, phi, track),
                                  **({"validation_loss": start_val} if start_val is not None else {})}]
    damping, stop, lin = 1e-2, f"{iterations} iterations", None
    made: dict[tuple[float, ...], Linearisation] = {}  # every θ's Jacobian, for the kept θ's intervals
    for it in range(1, iterations + 1):
        t0 = time.perf_counter()
        lin = linearise(model, parameters, theta, trajectory)  # the trajectory used θ's automatic substeps
        made[tuple(theta)] = lin
        hessian, gradient = posterior_curvature(lin, parameters, n)
        rollouts, accepted, predicted, settled = p + 1, False, None, False
        trials: list[dict[str, float]] = []
        reference = {lin.substeps: phi}  # Φ at θ by substep count (the trial comparison's common discretisation)
        for _ in range(6):
            # after a rejected trial the step shortens until the model promises at most half of what that trial
            # failed to deliver (near the first damping a fourfold one barely moves the step)
            ceiling = 0.5 * trials[-1]["predicted_decrease"] if trials else math.inf
            trial, promised, damping = shortened_step(hessian, gradient, theta, parameters, damping, ceiling)
            if trial == theta:
                break
            # a trial the model predicts to gain less than the tolerance would end the fit even if accepted, and
            # a larger damping only shortens the step: such a trial is not simulated, and the fit stops here
            predicted = promised if predicted is None else predicted
            settled = promised < tolerance
            if settled:
                break
            found, used = _compared(model, parameters, theta, trial, n, lin.substeps, reference)
            rollouts += used
            trials.append({"damping": damping, "predicted_decrease": promised,
                           "decrease": found[4] if found is not None else None})
            if found is not None:
                trial_trajectory, trial_loss, trial_track, trial_phi, decrease = found
                accepted = True
                break
            damping *= 4.0
        entry: dict[str, Any] = {"iteration": it, "damping": damping, "accepted": accepted, "rollouts": rollouts,
                                 "predicted_decrease": predicted, "trials": trials}
        if not accepted:
            entry.update(**_values(parameters, theta, loss, phi, track), ms=1000 * (time.perf_counter() - t0))
            log.append(entry)
            if on_iteration is not None:
                on_iteration(entry)
            stop = _unaccepted(settled, bool(trials))
            break
        theta, trajectory, loss, track, phi = trial, trial_trajectory, trial_loss, trial_track, trial_phi
        damping = max(damping / 3.0, 1e-6)
        entry.update(_values(parameters, theta, loss, phi, track))
        value = keep.offer(theta, trajectory, phi, track)
        if value is not None:
            entry["validation_loss"] = value
        entry["ms"] = 1000 * (time.perf_counter() - t0)
        log.append(entry)
        if on_iteration is not None:
            on_iteration(entry)
        if decrease < tolerance:
            stop = "converged: the last step lowered the objective by less than the tolerance"
            break
        if validate is not None and keep.since >= patience:
            stop = f"the validation loss has not improved for {patience} steps"
            break
    kept = tuple(keep.theta)
    final = made[kept] if kept in made else \
        linearise(model, parameters, keep.theta, trajectory if theta == keep.theta else None)
    return FitResult(keep.theta, final, keep.phi, keep.value, start_val, log, stop)


def _unaccepted(settled: bool, simulated: bool) -> str:
    """Why :func:`levenberg_marquardt` stopped at an iteration without an accepted step: ``settled``, the model
    promised less than the tolerance (for the first trial, or after ``simulated`` trials were rejected)."""
    if settled and not simulated:
        return "converged: the Gauss–Newton model predicts a decrease below the tolerance"
    if settled:
        return "no step lowers the objective by the tolerance, as a shorter one would be predicted to"
    return "no step lowers the objective"


@dataclass
class _KeepBest:
    """The θ :func:`levenberg_marquardt` keeps: the best by the score of ``validate``'s loss (n/2 · log of it, plus
    ½ ‖c‖² of the model's track where ``with_track``), the start included; without ``validate``, the last accepted θ.

    Attributes:
        theta, phi, value: the kept θ, its Φ and its validation loss (None without ``validate``).
        since: accepted steps offered since the kept one (the patience's count).
    """

    validate: Callable[[list[float], Any], float] | None
    n: float
    with_track: bool
    theta: list[float] = field(default_factory=list)
    phi: float = math.inf
    value: float | None = None
    score: float = math.inf
    since: int = 0

    def offer(self, theta: Sequence[float], trajectory: Any, phi: float, track: float | None) -> float | None:
        """Judge an accepted θ (the start first, which is kept whatever its score); returns its validation loss."""
        if self.validate is None:
            self.theta, self.phi = list(theta), phi
            return None
        value = self.validate(list(theta), trajectory)
        score = 0.5 * self.n * math.log(max(value, 1e-300)) + (0.5 * (track or 0.0) if self.with_track else 0.0)
        if not self.theta or score < self.score:
            self.theta, self.phi, self.value, self.score, self.since = list(theta), phi, value, score, 0
        else:
            self.since += 1
        return value


def _compared(model: ClipModel, parameters: Sequence[Parameter], theta: list[float], trial: list[float], n: float,
              own: int, reference: dict[int, float]) -> tuple[tuple | None, int]:
    """Simulate ``trial`` and compare it with θ at one substep count (module docstring): the larger of θ's (``own``)
    and the trial's automatic counts; ``reference`` holds Φ(θ) by count and gains the counts simulated here.

    Returns ((the trial's trajectory, L, ‖c‖² and Φ at its own automatic count, the decrease of Φ at the common
    count) where the trial lowers Φ, else None; the number of rollouts simulated)."""
    trial_count = model.substeps(trial)
    count, rollouts = max(own, trial_count), 0
    if count not in reference:  # the trial needs more substeps than θ: θ again at the trial's count
        reference[count] = _evaluated(model, parameters, theta, n, count)[3]
        rollouts += 1
    if not math.isfinite(reference[count]):  # θ fails at the trial's count: nothing to compare with
        return None, rollouts
    evaluated = _evaluated(model, parameters, trial, n, count)
    rollouts += 1
    decrease = reference[count] - evaluated[3]
    if not decrease > 0:
        return None, rollouts
    if count != trial_count:  # better at θ's higher count; the next Jacobian needs the trial's own count
        evaluated = _evaluated(model, parameters, trial, n)
        rollouts += 1
        if not math.isfinite(evaluated[3]):
            return None, rollouts
    return (*evaluated, decrease), rollouts


def _evaluated(model: ClipModel, parameters: Sequence[Parameter], theta: list[float],
               n: float, substeps: int | None = None) -> tuple[Any, float, float | None, float]:
    """θ's trajectory (``substeps`` per frame; None: θ's automatic count), loss L, track loss ‖c‖² (None without a
    track) and Φ; L and Φ are +inf (and the trajectory None) where the simulation fails."""
    try:
        trajectory = model.simulate(theta, substeps)
        loss, track = trajectory_loss(model, trajectory), track_loss(model, trajectory)
    except SimulationError:
        return None, math.inf, None, math.inf
    return trajectory, loss, track, objective(loss, theta, parameters, n, track or 0.0)


def _values(parameters: Sequence[Parameter], theta: Sequence[float], loss: float, phi: float,
            track: float | None) -> dict[str, Any]:
    """A log entry's state: ``loss``, ``objective``, the parameters by name, and ``track_loss`` with a track."""
    return {"loss": loss, "objective": phi, **dict(zip((q.name for q in parameters), theta)),
            **({"track_loss": track} if track is not None else {})}


def trajectory_loss(model: ClipModel, trajectory: Any) -> float:
    """L = Σ_t ‖r_t‖² of one trajectory."""
    with torch.no_grad():
        return float(sum(float((model.residuals([trajectory], t)[0].double() ** 2).sum()) for t in range(model.frames)))


def track_loss(model: ClipModel, trajectory: Any) -> float | None:
    """‖c‖² of one trajectory's track residuals (None when the model has no track term)."""
    with torch.no_grad():
        c = model.track_residuals([trajectory])
    return None if c is None else float((c[0].double() ** 2).sum())
