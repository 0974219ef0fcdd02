"""Implicit time integration of the reduced model, with the adjoint of each converged step.

One video frame of length Δt is ``SimConfig.substeps`` implicit steps of h = Δt / substeps with the
integrator ``SimConfig.integrator`` (BDF2 by default, or implicit Euler; :mod:`vid2sim.physics.integrators`).
Each step minimises the incremental potential

    y_{n+1} = argmin_y ½ ‖y − ŷ‖²_M + k_E E_pot(y) + k_D Σ_p v_p ψ(F_p(y))

(inertia, elastic + external potential, Kelvin–Voigt damping of :mod:`vid2sim.physics.damping`) by
Newton's method with a backtracking line search that starts from the full Newton step and never accepts a
state with an inverted cubature point (det F ≤ 0).

Gradients: the converged step satisfies ∇Φ(y*; θ) = 0, so dy*/dθ = −H⁻¹ ∂∇Φ/∂θ. The backward pass of
:class:`_ImplicitStep` solves H λ = ∂L/∂y* once (H the exact, unprojected Hessian at y*) and returns
−λᵀ ∂∇Φ/∂θ for every input θ (the previous states and velocities, Lamé parameters, retardation time,
masses, the skinning field's LBS rows and F-basis) — no backpropagation through Newton iterations or the
line search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.damping import (
    DEFAULT_DAMPING_RATIO,
    check_damping_ratio,
    retardation_time,
)
from vid2sim.physics.fused import AdjointBatch, FusedFrame, FusedStep, fused_supported
from vid2sim.physics.integrators import INTEGRATORS, BDFStep, auto_substeps, bdf_step
from vid2sim.physics.materials import ELASTIC_MODELS, lame_parameters
from vid2sim.physics.plasticity import DruckerPrager, VonMises, plasticity_from_dict, update_plastic_state
from vid2sim.physics.reduced import (
    ElasticBasis,
    StepProblem,
    apply_plastic_state,
    friction_barriers,
    lbs_rows,
    y_to_z_index,
    z_to_y_index,
)
from vid2sim.physics.skinning import deform, deformation_gradient, gradient_basis
from vid2sim.physics.stiffness_curve import StiffnessCurve
from vid2sim.physics.volumetric import check_volumetric, projection_basis
from vid2sim.runtime.errors import ConfigError


class SimulationError(RuntimeError):
    """The simulation reached a state it cannot continue from (inverted elements, NaN, failed line search)."""


@dataclass
class SimConfig:
    """Time-integration settings.

    Attributes:
        dt: time between video frames in seconds; one :meth:`Simulator.step` advances one frame.
        substeps: implicit steps per frame (step h = dt / substeps), or None (default) for
            :func:`~vid2sim.physics.integrators.auto_substeps` of the current material: ⌈16 Δt √(E/ρ)/L⌉ in
            [4, 64] (4 at E = 1e4, 8 at 1e5, 26 at 1e6 for ρ = 1000, L = 1), which keeps a tumbling drop
            within 1 % of the object's size of the same simulation refined 4× in time.
        integrator: 'bdf2' (second order, the default) or 'implicit_euler' (first order; with
            ``substeps=1`` the paper's one implicit-Euler step per frame, which damps the object's
            elastic modes numerically and makes E hard to identify — see docs/architecture.md).
        newton_max_iters: Newton iterations per step at most.
        newton_tol: a step is converged when the Newton step moves no cubature or contact point by more
            than newton_tol × the simulator's length scale, nor by more than ``newton_rtol`` × the largest
            move of a point over the step (so that the leftovers of many short steps do not add up); never
            below 30 ε of the dtype × the length scale.
        newton_rtol: that relative part of the tolerance.
        reuse_hessian: keep the factorised Hessian across Newton iterations and substeps (a chord
            iteration: every iteration then costs one gradient and one product with the kept inverse), turned with the
            object by a fitted rotation (:class:`NewtonCache`), and refactorise it when a line search needs
            halvings or an iteration shrinks the step by less than ``reuse_rate``. The converged state is
            the same minimiser; the adjoint always uses the exact Hessian at it. False: a fresh Hessian at
            every iteration (plain Newton).
        reuse_rate: the contraction per iteration below which a kept Hessian is reused.
        fused_kernels: evaluate the step on the fused kernels of :mod:`vid2sim.physics.fused` where it allows them
            (elastic Neo-Hookean, the closed-form F-basis, the pointwise volumetric term, no contact layer or
            dashpot): the same potential, gradient, Hessian and adjoint in far fewer tensor operations. False: the
            per-term reference code everywhere.
        line_search_max_halvings: backtracking halvings before the step is declared failed.
        armijo: sufficient-decrease constant of the line search.
        hessian_projection: "always" — Newton uses the Hessian with every per-point block projected to
            positive semi-definite; "on_demand" — Newton uses the exact Hessian whenever it is positive
            definite (its Cholesky factorisation succeeds, which the inertia term makes the common case)
            and the projected one otherwise. Both give a descent direction for the line search; the
            exact one converges at least as fast and costs less than half (no per-point eigen-analysis).
        friction_iterations: with Coulomb friction on a barrier, the normal force (and the contact set) that friction
            scales is made implicit by a fixed point over the step: the step is solved again with them taken at its
            last solution, until no contact point moves by more than ``friction_tol`` × the length scale between two
            solutions, at most this many times (each solve differentiated exactly, so the gradient is that of the
            computed step). 0: the normal force of the start of the step (lagged: an O(h) error that, measured on a
            tumbling drop, dominates the time-step error).
        friction_tol: that fixed point's tolerance. Each solve shrinks the change about 50× (measured), so the
            error left is about 2 % of it: 1e-4 needs half the solves of 1e-6 and moves a friction drop's centre of
            mass by 0.001 cm.
        dtype: the floating type the simulation computes in, "float64" (the default) or "float32". The
            simulator's inputs (cubature and contact points, weights) are cast to it and the networks it reads
            (skinning field, Neural Jacobian) are evaluated in their own type and cast. float32's round-off,
            about 1e-7 of the object's size per step, divided by the step into velocity, is amplified by
            friction's stick–slip into centimetres over a drop: a reconstructed asset thrown onto a floor with
            μ 0.42 ends 1.5 cm from its float64 rollout at 8 substeps per frame (frictionless: 0.08 cm), and
            refining the step in float32 stops converging. float32 for devices without float64 (e.g. Apple's).
    """

    dt: float = 0.05
    substeps: int | None = None
    integrator: str = "bdf2"
    newton_max_iters: int = 20
    newton_tol: float = 1e-6
    newton_rtol: float = 1e-4
    reuse_hessian: bool = True
    reuse_rate: float = 0.25
    fused_kernels: bool = True
    line_search_max_halvings: int = 30
    armijo: float = 1e-4
    hessian_projection: str = "on_demand"
    friction_iterations: int = 4
    friction_tol: float = 1e-4
    dtype: str = "float64"

    def __post_init__(self) -> None:
        if self.hessian_projection not in ("always", "on_demand"):
            raise ConfigError(
                f"SimConfig.hessian_projection must be 'always' or 'on_demand', got {self.hessian_projection!r}")
        if self.integrator not in INTEGRATORS:
            raise ConfigError(f"SimConfig.integrator must be one of {list(INTEGRATORS)}, got {self.integrator!r}")
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ConfigError(f"SimConfig.dt must be a positive finite number, got {self.dt}")
        if self.substeps is not None and (isinstance(self.substeps, bool) or not isinstance(self.substeps, int)
                                          or self.substeps < 1):
            raise ConfigError(f"SimConfig.substeps must be an integer >= 1 or None (automatic), got {self.substeps!r}")
        if self.newton_max_iters < 1:
            raise ConfigError(f"SimConfig.newton_max_iters must be >= 1, got {self.newton_max_iters}")
        if not self.newton_tol > 0:
            raise ConfigError(f"SimConfig.newton_tol must be > 0, got {self.newton_tol}")
        if not self.newton_rtol > 0:
            raise ConfigError(f"SimConfig.newton_rtol must be > 0, got {self.newton_rtol}")
        if isinstance(self.friction_iterations, bool) or not isinstance(self.friction_iterations, int) \
                or self.friction_iterations < 0:
            raise ConfigError(
                f"SimConfig.friction_iterations must be an integer >= 0, got {self.friction_iterations!r}")
        if not self.friction_tol > 0:
            raise ConfigError(f"SimConfig.friction_tol must be > 0, got {self.friction_tol}")
        if self.dtype not in SIM_DTYPES:
            raise ConfigError(f"SimConfig.dtype must be one of {list(SIM_DTYPES)}, got {self.dtype!r}")
        if not 0 < self.reuse_rate < 1:
            raise ConfigError(f"SimConfig.reuse_rate must be in (0, 1), got {self.reuse_rate}")

    @property
    def torch_dtype(self) -> torch.dtype:
        """The torch dtype of :attr:`dtype`."""
        return SIM_DTYPES[self.dtype]


#: The floating types a simulation may compute in (:attr:`SimConfig.dtype`).
SIM_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass
class Material:
    """A homogeneous material.

    Attributes:
        youngs_modulus: E in Pa.
        poisson_ratio: ν in (−1, 0.5).
        density: ρ in kg/m³.
        model: 'neo_hookean' (the paper's elastic model) or 'stvk'.
        plasticity: None, a :class:`~vid2sim.physics.plasticity.VonMises` (plasticine) or a
            :class:`~vid2sim.physics.plasticity.DruckerPrager` (sand) return map (both used with 'stvk' in
            the paper).
        damping_ratio: ζ of the Kelvin–Voigt material damping at ω_ref = √(E/ρ)/L
            (:mod:`vid2sim.physics.damping`; retardation time τ = 2 ζ L √(ρ/E)); 0 is undamped.
    """

    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    model: str = "neo_hookean"
    plasticity: object | None = None
    damping_ratio: float = DEFAULT_DAMPING_RATIO

    def __post_init__(self) -> None:
        lame_parameters(self.youngs_modulus, self.poisson_ratio)  # validates E and ν
        self.damping_ratio = check_damping_ratio(self.damping_ratio, "Material.damping_ratio")
        if not (self.density > 0 and math.isfinite(self.density)):
            raise ConfigError(f"Material.density must be a positive finite number (kg/m³), got {self.density}")
        if self.model not in ELASTIC_MODELS:
            raise ConfigError(f"Material.model must be one of {sorted(ELASTIC_MODELS)}, got {self.model!r}")
        self.plasticity = _check_plasticity(self.plasticity)


def _check_plasticity(value: object) -> object:
    """None, a return-map model, or its ``to_dict()`` form (converted); anything else is a named error."""
    from collections.abc import Mapping


    if value is None or isinstance(value, (VonMises, DruckerPrager)):
        return value
    if isinstance(value, Mapping):
        return plasticity_from_dict(value)
    raise ValueError("Material.plasticity must be None, VonMises(yield_stress=...) (plasticine), "
                     f"DruckerPrager(friction_angle_deg=...) (sand) or their dict form, got {value!r}")


@dataclass
class SimState:
    """State of the reduced model at time ``t``.

    Attributes:
        z: (12H,) handle transforms (handle-major layout of :mod:`vid2sim.physics.skinning`).
        zdot: (12H,) their velocities.
        t: time in seconds.
        Fp_inv: (K, 3, 3) inverse plastic deformation gradient per cubature point, or None (elastic).
        newton_iterations: Newton iterations of all substeps of the frame into this state (0 initially).
        converged: whether every one of those substeps met the gradient tolerance.
        z_prev, zdot_prev: (12H,) the state one substep earlier, which BDF2 needs; None for an initial
            state (the first substep is then an implicit-Euler step).
        h_prev: the length (s) of that last substep, or None.
    """

    z: Tensor
    zdot: Tensor
    t: float = 0.0
    Fp_inv: Tensor | None = None
    newton_iterations: int = 0
    converged: bool = True
    z_prev: Tensor | None = None
    zdot_prev: Tensor | None = None
    h_prev: float | None = None


@dataclass
class ReducedBasis:
    """Skinning quantities of a simulator's points (from :meth:`Simulator.reduced_basis`).

    Attributes:
        b: (K, L) LBS rows of the cubature points (x_p = X_p + Y b_p, L = 4H).
        basis: (K, 3, L) structured F-basis, or (K, 9, 12H) dense (Neural Jacobian) in y layout.
        structured: which of the two ``basis`` is.
        contact_b: (Nc, L) LBS rows of the contact points, or None when they are the cubature points.
        volumetric: (K, H) V-orthonormal basis of the weights' span when the volumetric term is projected
            (:func:`vid2sim.physics.volumetric.projection_basis`), else None.
    """

    b: Tensor
    basis: Tensor
    structured: bool
    contact_b: Tensor | None = None
    volumetric: Tensor | None = None


@dataclass
class StepStats:
    """Outcome of one implicit step: Newton iterations (direction solves), Hessian factorisations, whether
    it converged, and the line-search halvings per iteration."""

    iterations: int = 0
    hessians: int = 0
    converged: bool = False
    line_search_halvings: list[int] = field(default_factory=list)


@dataclass
class NewtonCache:
    """The factorised Newton matrix kept between iterations and substeps (``SimConfig.reuse_hessian``).

    The Hessian of a rotation-invariant energy (inertia, elasticity, damping) at a configuration turned by
    a rotation R is (R ⊗ I) H (R ⊗ I)ᵀ in the row-major layout (y = vec of the 3 × L matrix Y), so the
    kept factor stays useful while the object tumbles: each solve turns the gradient back by the rotation
    fitted (weighted Kabsch) between the cubature points now and when the factor was made.

    The fit needs Σ_p m_p x_p(y) a_pᵀ for the cubature points x_p = X_p + Y b_p and their centred positions
    a_p when the factor was made. As Σ m_p a_p = 0, that is Xa + Y Ba with the constants Xa = Σ m X aᵀ (3, 3)
    and Ba = Σ m b aᵀ (L, 3), kept with the factor: a (3 × L)(L × 3) product per fit instead of moving the
    K points.

    Attributes:
        factor: Cholesky factor (D, D) of the last Hessian, or None.
        moments: (Xa (3, 3), Ba (L, 3)) of the cubature positions where it was made, for the rotation fit.
        stale: refactorise at the next iteration.
        rotation: the last fitted rotation (3, 3).
        adjoint: the converged states of the fused steps that will need an adjoint (their Hessians are made in one
            batch, :class:`~vid2sim.physics.fused.AdjointBatch`).
        frame: (the inputs it was made of, the :class:`~vid2sim.physics.fused.FusedFrame`) of the frames sharing
            this cache.
    """

    factor: Tensor | None = None
    moments: tuple[Tensor, Tensor] | None = None
    stale: bool = True
    rotation: Tensor | None = None
    adjoint: AdjointBatch = field(default_factory=AdjointBatch)
    frame: tuple[tuple, FusedFrame] | None = None
    neg_inverse: Tensor | None = None
    step_matrix: Tensor | None = None

    def keep(self, factor: Tensor, problem: StepProblem, y: Tensor, chord: bool = True) -> None:
        """Store a fresh factor made at the state y: (D,) of ``problem`` (with ``chord``, also its inverse for the
        chord steps)."""
        x = problem.positions(y)
        m = problem.mass
        a = m[:, None] * (x - (m[:, None] * x).sum(0) / m.sum())  # m_p a_p, (K, 3)
        self.factor, self.moments = factor, (problem.X.T @ a, problem.b.T @ a)
        self.stale = False
        self.rotation = torch.eye(3, dtype=y.dtype, device=y.device)
        self.neg_inverse = torch.cholesky_inverse(factor).contiguous().neg_() if chord else None  # −H₀⁻¹
        self.step_matrix = self.neg_inverse

    def _turn(self, rotation: Tensor) -> None:
        """Fit the chord step's matrix −(R ⊗ I) H₀⁻¹ (R ⊗ I)ᵀ (D, D) to the rotation R (3, 3): every chord step of the
        substep is then one product. [a, l, b, m] = −Σ_cd R[a, c] H₀⁻¹[(c, l), (d, m)] R[b, d]."""
        self.rotation = rotation
        D = self.neg_inverse.shape[0]
        left = torch.mm(rotation, self.neg_inverse.view(3, -1)).view(D, 3, D // 3)  # [(a, l), d, m]
        self.step_matrix = torch.einsum("bd,xdm->xbm", rotation, left).reshape(D, D)

    def direction(self, problem: StepProblem, y: Tensor, g: Tensor, refit: bool = True) -> Tensor:
        """The chord step −(R ⊗ I) H₀⁻¹ (R ⊗ I)ᵀ g (D,) with the kept H₀ and the rotation R fitted now (``refit``)
        or at the last fit (within one short step the object turns by a negligible angle)."""
        if refit or self.rotation is None:
            Xa, Ba = self.moments
            self._turn(_rotation_of(torch.addmm(Xa, y.view(3, -1), Ba)))
        return torch.mv(self.step_matrix, g)


def _rotation_of(cov: Tensor) -> Tensor:
    """The rotation R (3, 3) minimising Σ m_p ‖R a_p − b_p‖² given cov = Σ m_p b_p a_pᵀ (3, 3) of centred
    reference points a and points b (Kabsch, with the reflection removed)."""
    U, _, Vh = torch.linalg.svd(cov)
    Vh.select(0, 2).mul_(torch.linalg.det(U @ Vh))  # det(U Vh) = ±1: U diag(1, 1, ±1) Vh has det +1
    return U @ Vh


def _factorize(H: Tensor) -> Tensor | None:
    L, info = torch.linalg.cholesky_ex(H)
    return L if int(info) == 0 else None


def _cholesky_solve(H: Tensor, rhs: Tensor) -> Tensor:
    """Solve H x = rhs for symmetric positive (semi-)definite H, regularising if needed."""
    L = _factorize(H)
    if L is not None:
        return torch.cholesky_solve(rhs[:, None], L)[:, 0]
    return torch.cholesky_solve(rhs[:, None], _regularized_factor(H))[:, 0]


def _regularized_factor(H: Tensor) -> Tensor:
    scale = float(H.diagonal().abs().mean())
    eye = torch.eye(H.shape[0], dtype=H.dtype, device=H.device)
    for k in range(1, 12):
        L = _factorize(H + (scale * 10.0 ** (k - 10)) * eye)
        if L is not None:
            return L
    raise SimulationError("Newton system is not positive definite even after regularisation")


def _newton_factor(problem: StepProblem, y: Tensor, config: SimConfig) -> Tensor:
    """Cholesky factor of the exact Hessian when ``on_demand`` and it is positive definite, else of the
    projected one (regularised if even that is singular)."""
    if config.hessian_projection == "on_demand":
        L = _factorize(problem.hessian(y, project=False))
        if L is not None:
            return L
    H = problem.hessian(y, project=True)
    L = _factorize(H)
    return L if L is not None else _regularized_factor(H)


def newton_solve(problem: StepProblem, config: SimConfig, length_scale: float,
                 cache: NewtonCache | None = None) -> tuple[Tensor, StepStats]:
    """Minimise the step's incremental potential; returns (y*, stats). Inputs are treated as constants.

    Converged when the (chord or Newton) step moves no point by more than ``config.newton_tol`` ×
    ``length_scale``. With ``config.reuse_hessian`` the factorised Hessian in ``cache`` is reused while the
    steps shrink by at least ``config.reuse_rate`` per iteration (see :class:`SimConfig`).
    """
    cache = cache if cache is not None else NewtonCache()
    stats = StepStats()
    eps = torch.finfo(problem.y_prev.dtype).eps
    floor = 30.0 * eps * length_scale
    absolute = max(config.newton_tol * length_scale, floor)
    y = problem.y_start
    phi, g = problem.energy_and_gradient(y)
    if g is None:  # the prediction inverts something: start from the previous (valid) state
        y = problem.y_prev
        phi, g = problem.energy_and_gradient(y)
        if g is None:
            raise SimulationError(
                f"state at t = {problem.t - problem.dt:.4g} s has inverted cubature points (det F <= 0)"
            )
    previous = math.inf
    for it in range(config.newton_max_iters):
        fresh = cache.factor is None or cache.stale or not config.reuse_hessian
        if fresh:
            cache.keep(_newton_factor(problem, y, config), problem, y, config.reuse_hessian)
            stats.hessians += 1
            d = torch.mv(cache.step_matrix, g) if config.reuse_hessian \
                else torch.cholesky_solve(g.view(-1, 1), cache.factor).view(-1).neg_()
        else:
            d = cache.direction(problem, y, g, refit=it == 0)
        stats.iterations = it + 1
        y_full = y + d
        size, move, slope = problem.newton_measures(g, d, y_full)
        tol = max(floor, min(absolute, config.newton_rtol * move))
        if size <= tol:
            if problem.valid(y_full):
                y = y_full
            stats.converged = True
            break
        alpha = 1.0
        inverted = False
        for halving in range(config.line_search_max_halvings + 1):
            y_new = y_full if halving == 0 else y + alpha * d
            phi_new, g_new = problem.energy_and_gradient(y_new)
            inverted = g_new is None
            slack = 16 * eps * max(abs(phi), abs(phi_new) if not inverted else 0.0, 1.0)
            if not inverted and phi_new <= phi + config.armijo * alpha * slope + slack:
                break
            alpha *= 0.5
        else:
            if not fresh:  # the reused Hessian led nowhere: retry from here with a fresh one
                cache.stale = True
                stats.line_search_halvings.append(config.line_search_max_halvings + 1)
                continue
            if abs(slope) <= 1e4 * eps * max(abs(phi), 1.0):
                # the remaining decrease is below round-off: this is as converged as the precision allows
                stats.converged = True
                break
            cause = (
                "even the shortest step inverts a cubature point (det F <= 0): the object is being crushed; "
                "the material may be too soft for this impact (StVK offers no resistance to inversion) — "
                "use a stiffer material, Neo-Hookean, or a smaller dt"
                if inverted
                else "no step along the Newton direction decreases the energy"
            )
            raise SimulationError(f"line search failed at t = {problem.t:.4g} s (Newton iteration {it + 1}): {cause}")
        stats.line_search_halvings.append(halving)
        if halving > 0 or (not fresh and size > config.reuse_rate * previous):
            cache.stale = True  # far from converged or slow contraction: refactorise at the next iteration
        previous = size
        y, phi, g = y_new, phi_new, g_new
    if not bool(torch.isfinite(y).all()):
        raise SimulationError(f"Newton produced a non-finite state at t = {problem.t:.4g} s")
    return y, stats


@dataclass
class _StepSpec:
    """Non-tensor data of one step (what the autograd Function needs besides its tensor inputs)."""

    X: Tensor
    vol: Tensor
    A: Tensor
    structured: bool
    model: str
    externals: Sequence
    t: float
    step: BDFStep
    config: SimConfig
    contact_X: Tensor | None = None
    contact_w: Tensor | None = None
    length_scale: float = 1.0
    cache: NewtonCache | None = None
    stats: StepStats | None = None
    frame: FusedFrame | None = None  # the frame's constants when the step runs on the fused kernels
    fused: FusedStep | None = None  # the step on them, once made

    def problem(self, y_prev, ydot_prev, y_prev2, ydot_prev2, mu, lam, tau, mass, b, basis_t, contact_b,
                layer_k=None, dashpot=None, volumetric=None, friction_state=None, fused: bool = False) -> StepProblem:
        """The step's problem of these inputs; with ``fused`` (and a ``frame``) on the fused kernels."""
        basis = ElasticBasis(self.A, basis_t, None) if self.structured else ElasticBasis(self.A, None, basis_t)
        problem = StepProblem(self.X, self.vol, mass, b, basis, mu, lam, self.model, self.externals,
                              self.t, self.step, y_prev, ydot_prev, y_prev2, ydot_prev2, tau,
                              self.contact_X, contact_b, self.contact_w, layer_k, dashpot, volumetric, friction_state)
        if fused and self.frame is not None:
            problem.fused = self.fused = FusedStep(self.frame, self.step, self.t, y_prev, y_prev2, problem.y_pred,
                                                   friction_state)
        return problem


#: The inputs of :class:`_ImplicitStep` after ``spec``, in order; the fused adjoint serves the first seven.
_STEP_INPUTS = ("y_prev", "ydot_prev", "y_prev2", "ydot_prev2", "mu", "lam", "tau", "mass", "b", "basis",
                "contact_b", "layer_k", "dashpot", "volumetric", "friction_state")


class _ImplicitStep(torch.autograd.Function):
    """y_next = argmin Φ(y; inputs); backward by the adjoint of the converged step.

    Inputs after ``spec``: y_prev, ydot_prev, y_prev2, ydot_prev2 (None unless BDF2 has history), μ, λ,
    τ (None when undamped), masses, LBS rows b, F-basis, contact points' LBS rows (None: the cubature points),
    the contact layer's stiffness (None: no layer), the contact dashpot's coefficient (None: none), the
    projected volumetric term's basis (None: pointwise), the state friction's normal force is taken at (None: the
    start of the step).
    """

    @staticmethod
    def forward(ctx, spec: _StepSpec, *inputs):  # type: ignore[override]
        problem = spec.problem(*inputs, fused=True)
        y, stats = newton_solve(problem, spec.config, spec.length_scale, spec.cache)
        if spec.fused is not None and any(ctx.needs_input_grad[1:]):
            spec.cache.adjoint.add(spec.fused, y)
        spec.stats = stats
        ctx.spec = spec
        ctx.present = [t is not None for t in inputs]
        ctx.save_for_backward(y, *[t for t in inputs if t is not None])
        return y

    @staticmethod
    def backward(ctx, grad_y):  # type: ignore[override]
        spec: _StepSpec = ctx.spec
        y, *saved = ctx.saved_tensors
        it_saved = iter(saved)
        inputs = [next(it_saved) if p else None for p in ctx.present]
        needs = [n and t is not None for n, t in zip(ctx.needs_input_grad[1:], inputs)]
        if spec.fused is not None and not spec.fused.frictions and not any(needs[len(_FUSED_ADJOINT):]):
            return (None, *_fused_adjoint(spec.fused, grad_y, needs))
        # otherwise −λᵀ ∂∇Φ/∂θ by autograd of the reference gradient (friction's normal force and reference
        # position also depend on the previous states or the fixed point's last solution)
        # one problem for the gradient's graph and the Hessian: the Hessian reuses what the gradient cached
        # (the inertial target, C_ref, the mass block) without recording it
        with torch.enable_grad():
            req = [t.detach().requires_grad_(n) if t is not None else None for t, n in zip(inputs, needs)]
            problem = spec.problem(*req)
            g = problem.gradient(y.detach())
        if spec.fused is not None:  # the same exact Hessian, made with the rollout's others
            adj = spec.fused.adjoint_solve(grad_y)
        else:
            with torch.no_grad():
                H = problem.hessian(y.detach(), project=False)
            factor = _factorize(H)  # the exact Hessian may be indefinite (e.g. under compression): then LU
            adj = (
                torch.cholesky_solve(grad_y[:, None], factor)[:, 0]
                if factor is not None
                else torch.linalg.solve(H, grad_y)
            )
        wanted = [r for r, n in zip(req, needs) if n]
        grads = torch.autograd.grad(g, wanted, grad_outputs=-adj, allow_unused=True) if wanted else ()
        it = iter(grads)
        out = [next(it) if n else None for n in needs]
        return (None, *out)


_FUSED_ADJOINT = _STEP_INPUTS[:7]


def _touches(barriers: Sequence, x: Tensor, t: float) -> bool:
    """Whether a point x: (N, 3) is inside one of ``barriers`` at time t (signed distance < 0)."""
    return any(bool((e.signed_distance(x, t) < 0).any()) for e in barriers)


def _fused_adjoint(fused: FusedStep, grad_y: Tensor, needs: list[bool]) -> list[Tensor | None]:
    """The adjoint of a step on the fused kernels: the gradients of the inputs ``needs`` marks, in the order of
    :data:`_STEP_INPUTS` (those beyond the first seven are never needed here)."""
    history, params = fused.adjoint(grad_y)
    values = [*history.unbind(0), *params.unbind(0)]
    return [v if need else None for v, need in zip(values, needs)] + [None] * (len(needs) - len(values))


class Simulator:
    """Mesh-free reduced-order simulator of one object (paper §3, §4.2).

    Args:
        field: the skinning field (:class:`~vid2sim.physics.skinning.SkinningField`); H = field.num_handles_total.
        cubature_points: (K, 3) rest positions of the cubature points (canonical frame).
        cubature_weights: (K,) integration weights (volume / K in the paper).
        material: a :class:`Material`. Its E, ν, density and damping ratio become the differentiable
            tensors ``log10_E``, ``nu``, ``density`` and ``damping_ratio`` of this simulator (set
            ``requires_grad`` on them to optimise).
        externals: external energies (gravity, floor, moving floor, spheres; :mod:`vid2sim.physics.external`).
        config: :class:`SimConfig`.
        jacobian: optional Neural Jacobian (:class:`~vid2sim.physics.neural_jacobian.NeuralJacobian`); when
            given and ``use_neural_jacobian`` is True, dF/dz comes from it instead of the exact closed form.
        length_scale: L (m) of the damping's reference frequency √(E/ρ)/L; default the diagonal of the
            cubature points' bounding box (the object's size). Give the same L to compare with an FEM.
        contact_points: (Nc, 3) rest positions where the barrier energies (floor, spheres) act, e.g.
            samples of the object's surface; default the cubature points (the paper).
        contact_weights: (Nc,) their barrier weights (default 1 each: the paper's per-point penalty; area
            weights in m² make the barrier stiffness a contact pressure per metre of penetration).
        stiffness_scale: s > 0; the elastic energy (and the damping and substep count, which follow the
            frequencies) use E·s instead of E. A Rayleigh–Ritz subspace is stiffer than the continuum; with
            s = (ω_continuum / ω_subspace)² of the lowest mode (:func:`vid2sim.physics.modes.stiffness_calibration`)
            the subspace vibrates at the material's frequency and ``log10_E`` stays the material's. A
            :class:`~vid2sim.physics.stiffness_curve.StiffnessCurve` gives s as a function of the current ν
            (:func:`vid2sim.physics.modes.stiffness_calibration_curve`), differentiable in ν: the subspace's
            volumetric locking grows with ν, so one factor is right at one ν only. A curve with ``lam_scale``
            scales λ by its own factor s_λ(ν) (μ by s(ν)), which also corrects the impact's squash.
        contact_layer: h ≥ 0 (m). The skinning subspace cannot represent the local indentation where the object
            touches something, so its contact is too stiff. With h > 0 every barrier (floor, spheres) acts
            through a layer of the body in series, of stiffness k_b = E·s / ((1 − ν²) h) per unit area (the
            elastic half-space's indentation modulus over a depth h): a barrier of stiffness k acts as
            k / (1 + k / k_b). Differentiable in E and ν. 0 (the default): no layer.
        contact_damping: β ≥ 0, a normal dashpot in every barrier contact of coefficient c = β √(E·s ρ) per unit
            contact weight (:meth:`contact_dashpot`, :class:`~vid2sim.physics.reduced.StepProblem`): the
            subspace lacks the fast, damped modes into which the continuum loses an impact's energy, so it
            rebounds too high; the dashpot takes that energy at the contact. Becomes the differentiable tensor
            ``contact_damping``. 0 (the default): none.
        volumetric: "pointwise" (the default): the Neo-Hookean λ/2 (ln J)² at every cubature point;
            "projected": ln J projected onto the skinning weights' span in that term
            (:mod:`vid2sim.physics.volumetric`), which removes the subspace's volumetric locking (neo_hookean only).
        mass_volumes: (K,) > 0, the volumes that carry the cubature points' mass (inertia and body forces such
            as gravity); default ``cubature_weights``. :func:`vid2sim.physics.mass.moment_matched_volumes` gives
            ones whose centre of mass and inertia tensor are the body's (the elastic energy keeps the cubature
            weights).
    """

    def __init__(
        self,
        field: torch.nn.Module,
        cubature_points: Tensor,
        cubature_weights: Tensor,
        material: Material,
        externals: Sequence = (),
        config: SimConfig | None = None,
        jacobian: torch.nn.Module | None = None,
        use_neural_jacobian: bool = False,
        length_scale: float | None = None,
        contact_points: Tensor | None = None,
        contact_weights: Tensor | None = None,
        stiffness_scale: "float | StiffnessCurve" = 1.0,
        contact_layer: float = 0.0,
        contact_damping: float = 0.0,
        volumetric: str = "pointwise",
        mass_volumes: Tensor | None = None,
    ) -> None:
        if not isinstance(stiffness_scale, StiffnessCurve):
            if isinstance(stiffness_scale, bool) or not isinstance(stiffness_scale, (int, float)) \
                    or not (0 < float(stiffness_scale) < math.inf):
                raise ValueError("stiffness_scale must be a finite positive number or a StiffnessCurve, "
                                 f"got {stiffness_scale!r}")
            stiffness_scale = float(stiffness_scale)
        self.stiffness_scale: float | StiffnessCurve = stiffness_scale
        if isinstance(contact_layer, bool) or not isinstance(contact_layer, (int, float)) \
                or not (0 <= float(contact_layer) < math.inf):
            raise ValueError(f"contact_layer must be a finite number of metres >= 0, got {contact_layer!r}")
        self.contact_layer = float(contact_layer)
        if isinstance(contact_damping, bool) or not isinstance(contact_damping, (int, float)) \
                or not (0 <= float(contact_damping) < math.inf):
            raise ValueError(
                f"contact_damping must be a finite number >= 0 (0 = no contact dashpot), got {contact_damping!r}"
            )
        if cubature_points.ndim != 2 or cubature_points.shape[1] != 3 or cubature_points.shape[0] == 0:
            raise ValueError(f"cubature_points must have shape (K, 3) with K >= 1, got {tuple(cubature_points.shape)}")
        if cubature_weights.shape != cubature_points.shape[:1]:
            raise ValueError(
                f"cubature_weights must have shape ({cubature_points.shape[0]},), got {tuple(cubature_weights.shape)}"
            )
        if not bool(torch.isfinite(cubature_points).all()) or not bool((cubature_weights > 0).all()):
            raise ValueError("cubature_points must be finite and cubature_weights positive")
        if use_neural_jacobian and jacobian is None:
            raise ValueError("use_neural_jacobian=True needs a Neural Jacobian network (jacobian=...)")
        if mass_volumes is not None and (mass_volumes.shape != cubature_weights.shape
                                         or not bool(torch.isfinite(mass_volumes).all())
                                         or not bool((mass_volumes > 0).all())):
            raise ValueError(f"mass_volumes must be finite and positive with shape ({cubature_points.shape[0]},), "
                             f"got shape {tuple(mass_volumes.shape)}")
        self.config = config or SimConfig()
        dtype = self.config.torch_dtype  # every input in the simulation's floating type
        cubature_points, cubature_weights = cubature_points.to(dtype), cubature_weights.to(dtype)
        mass_volumes = None if mass_volumes is None else mass_volumes.to(dtype)
        contact_points = None if contact_points is None else contact_points.to(dtype)
        contact_weights = None if contact_weights is None else contact_weights.to(dtype)
        self.field = field
        self.X = cubature_points
        self.vol = cubature_weights
        self.mass_volumes = cubature_weights if mass_volumes is None else mass_volumes
        self.material = material
        self.volumetric = check_volumetric(volumetric, material.model)
        self.externals = list(externals)
        self.jacobian = jacobian
        self.use_neural_jacobian = use_neural_jacobian
        device = cubature_points.device  # (dtype: the simulation's, which the inputs were cast to above)
        self.log10_E = torch.tensor(math.log10(material.youngs_modulus), dtype=dtype, device=device)
        self.nu = torch.tensor(material.poisson_ratio, dtype=dtype, device=device)
        self.density = torch.tensor(material.density, dtype=dtype, device=device)
        self.damping_ratio = torch.tensor(material.damping_ratio, dtype=dtype, device=device)
        self.contact_damping = torch.tensor(float(contact_damping), dtype=dtype, device=device)
        if length_scale is None:
            extent = cubature_points.detach().amax(0) - cubature_points.detach().amin(0)
            length_scale = float(extent.norm())
        if not (isinstance(length_scale, (int, float)) and math.isfinite(length_scale) and length_scale > 0):
            raise ValueError(f"length_scale must be a positive finite number of metres, got {length_scale!r}")
        self.length_scale = float(length_scale)
        self.contact_points: Tensor | None = None
        self.contact_weights: Tensor | None = None
        if contact_points is None:
            if contact_weights is not None:
                raise ValueError("contact_weights were given without contact_points")
        else:
            self.set_contact(contact_points, contact_weights)
        H = field.num_handles_total
        self.num_dofs = 12 * H
        self._perm = z_to_y_index(H, device)
        self._inv = y_to_z_index(H, device)

    # ---- differentiable quantities -------------------------------------------------------------
    def lame(self) -> tuple[Tensor, Tensor]:
        """(μ, λ) from the current ``log10_E`` and ``nu`` (validated)."""
        if not bool(torch.isfinite(self.log10_E)) or not bool(torch.isfinite(self.nu)):
            raise ValueError(
                f"material parameters must be finite, got log10_E={float(self.log10_E.detach())}, "
                f"nu={float(self.nu.detach())}"
            )
        mu, lam = lame_parameters(self.effective_youngs_modulus(), self.nu)
        if isinstance(self.stiffness_scale, StiffnessCurve) and self.stiffness_scale.lam_scale is not None:
            lam = lam * self.stiffness_scale.lam_factor(self.nu)  # a two-factor curve: λ by s_λ(ν) alone
        return mu, lam  # type: ignore[return-value]

    def effective_youngs_modulus(self) -> Tensor:
        """0-d E·s: the modulus the elastic energy uses (``stiffness_scale`` s, or s(ν) of a
        :class:`~vid2sim.physics.stiffness_curve.StiffnessCurve` at the current ``nu``; E itself when s = 1)."""
        scale = self.stiffness_scale
        return 10.0**self.log10_E * (scale(self.nu) if isinstance(scale, StiffnessCurve) else scale)

    def contact_layer_stiffness(self) -> Tensor | None:
        """0-d k_b = E·s / ((1 − ν²) h) (Pa/m) of the contact layer (``contact_layer`` h), None when h = 0."""
        if self.contact_layer == 0.0:
            return None
        return self.effective_youngs_modulus() / ((1.0 - self.nu * self.nu) * self.contact_layer)

    def contact_dashpot(self) -> Tensor | None:
        """0-d c = β √(E·s ρ) (N·s/m per unit contact weight; with area weights Pa·s/m) of the contact dashpot
        from the current ``contact_damping`` β; None when β = 0 and it is not being optimised.

        √(Eρ) is the material's impedance to a compression wave (a boundary with c = √(Eρ) absorbs a bar wave
        that reaches it), so β is dimensionless and means the same for every stiffness."""
        beta = self.contact_damping
        if not bool(torch.isfinite(beta)) or float(beta.detach()) < 0:
            raise ValueError(f"contact_damping must be a finite number >= 0, got {float(beta.detach())}")
        if float(beta.detach()) == 0.0 and not beta.requires_grad:
            return None
        return beta * torch.sqrt(self.effective_youngs_modulus() * self.density)

    def retardation_time(self) -> Tensor | None:
        """Kelvin–Voigt τ = 2 ζ L √(ρ/E) (s) from the current ``damping_ratio``, ``log10_E`` and ``density``;
        None for an undamped material (ζ = 0 and not being optimised)."""
        zeta = self.damping_ratio
        if not bool(torch.isfinite(zeta)) or float(zeta.detach()) < 0:
            raise ValueError(f"damping_ratio must be a finite number >= 0, got {float(zeta.detach())}")
        if float(zeta.detach()) == 0.0 and not zeta.requires_grad:
            return None
        return retardation_time(zeta, self.effective_youngs_modulus(), self.density, self.length_scale)

    def set_contact(self, points: Tensor, weights: Tensor | None = None) -> None:
        """Make ``points`` (Nc, 3), rest positions, where the barrier energies act, with ``weights`` (Nc,) > 0 (None:
        ones); converted to the simulator's dtype and device."""
        dtype, device = self.X.dtype, self.X.device
        points = points.to(device=device, dtype=dtype)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"contact_points must have shape (Nc, 3) with Nc >= 1, got {tuple(points.shape)}")
        weights = torch.ones(points.shape[0], dtype=dtype, device=device) if weights is None \
            else weights.to(device=device, dtype=dtype)
        if weights.shape != points.shape[:1] or not bool((weights > 0).all()):
            raise ValueError(f"contact_weights must be positive with shape ({points.shape[0]},), "
                             f"got {tuple(weights.shape)}")
        if not bool(torch.isfinite(points).all()):
            raise ValueError("contact_points must be finite")
        self.contact_points, self.contact_weights = points, weights

    def substeps(self) -> int:
        """Implicit steps per frame: ``config.substeps``, or the automatic count for the current E, density
        and length scale (:func:`~vid2sim.physics.integrators.auto_substeps`)."""
        if self.config.substeps is not None:
            return self.config.substeps
        return auto_substeps(self.config.dt, float(self.effective_youngs_modulus().detach()),
                             float(self.density.detach()), self.length_scale)

    def masses(self) -> Tensor:
        """(K,) lumped masses ρ·v_p (v_p: ``mass_volumes``)."""
        if not float(self.density.detach()) > 0:
            raise ValueError(f"density must be positive, got {float(self.density.detach())}")
        return self.density * self.mass_volumes

    def reduced_basis(self) -> "ReducedBasis":
        """The skinning quantities of the cubature (and contact) points from the field (differentiable)."""

        w, dw = self.field.weights_and_gradients(self.X)
        b = lbs_rows(self.X, w)
        contact_b = (
            None if self.contact_points is None else lbs_rows(self.contact_points, self.field(self.contact_points))
        )
        volumetric = projection_basis(w, self.vol) if self.volumetric == "projected" else None
        if self.use_neural_jacobian:
            J = self.jacobian(self.X)  # (K, 9, 12H) in z layout
            return ReducedBasis(b, J[:, :, self._perm], False, contact_b, volumetric)
        return ReducedBasis(b, gradient_basis(self.X, w, dw), True, contact_b, volumetric)

    # ---- states --------------------------------------------------------------------------------
    def rest_state(self, zdot: Tensor | None = None) -> SimState:
        """The rest state z = 0 (optionally with initial velocities zdot: (12H,)) at t = 0."""
        z = torch.zeros(self.num_dofs, dtype=self.X.dtype, device=self.X.device)
        plastic = self.material.plasticity is not None
        Fp = (
            torch.eye(3, dtype=self.X.dtype, device=self.X.device).expand(self.X.shape[0], 3, 3).clone()
            if plastic
            else None
        )
        return SimState(z, torch.zeros_like(z) if zdot is None else zdot, 0.0, Fp)

    def rigid_velocity_state(
        self, linear: Sequence[float], angular: Sequence[float] = (0, 0, 0), about: Sequence[float] = (0, 0, 0)
    ) -> SimState:
        """Rest state moving rigidly: velocity v + ω × (X − c), put on the constant (rigid) handle."""
        state = self.rest_state()
        H = self.num_dofs // 12
        w = torch.as_tensor(angular, dtype=self.X.dtype, device=self.X.device)
        v = torch.as_tensor(linear, dtype=self.X.dtype, device=self.X.device)
        c = torch.as_tensor(about, dtype=self.X.dtype, device=self.X.device)
        skew = torch.zeros(3, 3, dtype=self.X.dtype, device=self.X.device)
        skew[0, 1], skew[0, 2], skew[1, 2] = -w[2], w[1], -w[0]
        skew = skew - skew.T
        zd = state.zdot.clone().reshape(H, 3, 4)
        zd[H - 1, :, :3] = skew
        zd[H - 1, :, 3] = v - skew @ c
        state.zdot = zd.reshape(-1)
        return state

    # ---- stepping ------------------------------------------------------------------------------
    def step(self, state: SimState, basis: "ReducedBasis | None" = None,
             lame: tuple[Tensor, Tensor] | None = None, tau: Tensor | None | str = "auto",
             cache: NewtonCache | None = None, substeps: int | None = None, masses: Tensor | None = None) -> SimState:
        """Advance one video frame (``config.substeps`` implicit steps). Differentiable (adjoint of every
        step) w.r.t. the state, E, ν, density, the damping ratio and the field.

        ``basis``, ``lame``, ``tau``, ``substeps`` and ``masses`` may be passed precomputed and ``cache`` shared
        between frames (as :meth:`rollout` does); the cache must only be shared by steps with the same inputs."""
        if state.z.shape != (self.num_dofs,) or state.zdot.shape != (self.num_dofs,):
            raise ValueError(
                f"state z and zdot must have shape ({self.num_dofs},), got {tuple(state.z.shape)}, "
                f"{tuple(state.zdot.shape)}"
            )
        if (state.z_prev is None) != (state.zdot_prev is None):
            raise ValueError("state.z_prev and state.zdot_prev must be given together (or both None)")
        history = [state.z, state.zdot] + ([state.z_prev, state.zdot_prev] if state.z_prev is not None else [])
        if not bool(torch.isfinite(torch.cat(history)).all()):
            raise SimulationError(f"state at t = {state.t:.4g} s contains NaN or infinite values")
        basis = basis if basis is not None else self.reduced_basis()
        b, basis_t, structured = basis.b, basis.basis, basis.structured
        mu, lam = lame if lame is not None else self.lame()
        tau = self.retardation_time() if isinstance(tau, str) else tau
        mu, lam = torch.as_tensor(mu), torch.as_tensor(lam)
        layer_k = self.contact_layer_stiffness()
        dashpot = self.contact_dashpot()
        masses = self.masses() if masses is None else masses
        cfg = self.config
        cache = cache if cache is not None else NewtonCache()
        n = substeps if substeps is not None else self.substeps()
        h = cfg.dt / n
        h_prev = state.h_prev if state.z_prev is not None else None
        y, ydot = state.z[self._perm], state.zdot[self._perm]
        y2 = state.z_prev[self._perm] if state.z_prev is not None else None
        ydot2 = state.zdot_prev[self._perm] if state.zdot_prev is not None else None
        Fp_inv = state.Fp_inv
        frame = None
        if cfg.fused_kernels and fused_supported(self.material.model, structured, Fp_inv is not None,
                                                 basis.volumetric, dashpot, layer_k, self.externals):
            inputs = (self.X, self.vol, masses, b, basis_t, mu, lam, tau, basis.contact_b, self.contact_points,
                      self.contact_weights, *self.externals)
            if cache.frame is not None and len(cache.frame[0]) == len(inputs) \
                    and all(a is c for a, c in zip(cache.frame[0], inputs)):
                frame = cache.frame[1]  # the same inputs as the frame before (a rollout's): the same constants
            else:
                frame = FusedFrame.build(self.X, self.vol, masses, b, basis_t, mu, lam, tau, self.externals,
                                         self.contact_points, basis.contact_b, self.contact_weights)
                cache.frame = (inputs, frame)
        identity = torch.eye(3, dtype=self.X.dtype, device=self.X.device).expand(self.X.shape[0], 3, 3)
        frictions = friction_barriers(self.externals) if cfg.friction_iterations > 0 else []
        iterations, converged = 0, True
        for s in range(n):
            A, step_basis = identity, basis_t
            if Fp_inv is not None:
                folded = apply_plastic_state(basis_t, structured, Fp_inv)
                A, step_basis = folded.A, folded.tensor
            bdf = bdf_step(cfg.integrator, h, h_prev if y2 is not None else None)
            t_next = state.t + (s + 1) * h
            if Fp_inv is not None:
                cache.stale = True  # the plastic state changed the basis
            spec = _StepSpec(self.X, self.vol, A, structured, self.material.model, self.externals, t_next, bdf, cfg,
                             self.contact_points, self.contact_weights, self.length_scale, cache, frame=frame)
            inputs = (y, ydot, y2 if bdf.needs_history else None, ydot2 if bdf.needs_history else None, mu, lam, tau,
                      masses, b, step_basis, basis.contact_b, layer_k, dashpot, basis.volumetric)
            y_new = _ImplicitStep.apply(spec, *inputs, None)
            iterations += spec.stats.iterations
            converged = converged and spec.stats.converged
            if frictions:
                lagged = _touches(frictions, self._contact_positions(basis, y), state.t + s * h)
                y_new, its, ok = self._implicit_normal_force(spec, inputs, y_new, frictions, basis, lagged)
                iterations, converged = iterations + its, converged and ok
            ydot_new = bdf.velocity(y_new, y, y2 if bdf.needs_history else None)
            y2, ydot2, y, ydot = y, ydot, y_new, ydot_new
            h_prev = h
            if self.material.plasticity is not None:
                Fp_inv = self._update_plastic(Fp_inv, y.detach()[self._inv], mu, lam, t_next)
        return SimState(y[self._inv], ydot[self._inv], state.t + cfg.dt, Fp_inv, iterations, converged,
                        y2[self._inv], ydot2[self._inv], h)

    @torch.no_grad()
    def _contact_positions(self, basis: "ReducedBasis", y: Tensor) -> Tensor:
        """(Nc, 3) the contact points' positions at the permuted state y: (D,), without gradients."""
        if basis.contact_b is None:
            return self.X + basis.b @ y.view(3, -1).T
        return self.contact_points + basis.contact_b @ y.view(3, -1).T

    def _implicit_normal_force(self, spec: _StepSpec, inputs: tuple, y_new: Tensor, barriers: Sequence,
                               basis: "ReducedBasis", lagged_contact: bool) -> tuple[Tensor, int, bool]:
        """The fixed point of :attr:`SimConfig.friction_iterations`: the step solved again with friction's normal
        force taken at its last solution y_new: (D,) until the contact points stop moving; ``lagged_contact``: whether
        the first solve (normal force of the start of the step) had friction. Returns (y (D,), Newton iterations,
        all converged). Each solve is an :class:`_ImplicitStep` with the last solution as an input, so the gradient
        is that of the computed fixed-point iterate."""
        cfg = self.config
        tol = cfg.friction_tol * self.length_scale
        iterations, converged = 0, True
        x_new = self._contact_positions(basis, y_new)
        for _ in range(cfg.friction_iterations):
            contact = _touches(barriers, x_new, spec.t)
            if not contact and not lagged_contact:
                break  # no friction at either state: the solve already is the implicit one
            spec = replace(spec, stats=None, fused=None)
            y_next = _ImplicitStep.apply(spec, *inputs, y_new)
            iterations += spec.stats.iterations
            converged = converged and spec.stats.converged
            x_next = self._contact_positions(basis, y_next)
            moved = float((x_next - x_new).norm(dim=1).max())
            y_new, x_new, lagged_contact = y_next, x_next, contact
            if moved <= tol:
                break
        return y_new, iterations, converged

    def _update_plastic(self, Fp_inv: Tensor, z: Tensor, mu, lam, t: float) -> Tensor:
        """The plastic state after the step to time ``t``: (C, 3, 3) inverse plastic deformation gradients.

        The step's line search accepts only states whose elastic F = F_total Fp⁻¹ has det > 0, but a point crushed
        flat (det ≈ 0, which StVK does not resist) can come out of the return map's own arithmetic at det ≤ 0 by
        round-off; that is the simulation failing, reported as a :class:`SimulationError`, not a bad argument."""
        F_total = self.deformation_gradients_at_cubature(z)
        det = torch.linalg.det(F_total.detach() @ Fp_inv.detach())
        if not bool((det > 0).all()):
            bad = int((det <= 0).nonzero()[0, 0])
            raise SimulationError(
                f"cubature point {bad} is crushed flat at t = {t:.4g} s (elastic det F = {float(det[bad]):.3g}): "
                "the material may be too soft for this impact (StVK offers no resistance to inversion) — use a "
                "stiffer material or a smaller dt")
        return update_plastic_state(self.material.plasticity, F_total, Fp_inv,
                                    torch.as_tensor(mu).detach(), torch.as_tensor(lam).detach())

    def rollout(self, state: SimState, steps: int, progress: bool = False) -> list[SimState]:
        """``steps`` video frames from ``state``; returns the states at the end of each (length ``steps``)."""
        if steps < 0:
            raise ValueError(f"steps must be >= 0, got {steps}")
        basis = self.reduced_basis()
        lame = self.lame()
        tau = self.retardation_time()
        masses = self.masses()
        cache = NewtonCache()
        n = self.substeps()
        out = []
        iterator = range(steps)
        if progress:
            from tqdm.auto import tqdm

            iterator = tqdm(iterator, desc="simulate", unit="frame")
        for _ in iterator:
            state = self.step(state, basis, lame, tau, cache, n, masses)
            out.append(state)
        return out

    # ---- outputs -------------------------------------------------------------------------------
    def positions(self, points: Tensor, z: Tensor) -> Tensor:
        """World positions x: (N, 3) of rest points ``points: (N, 3)`` for the state z: (12H,), in the points'
        dtype."""

        return deform(points, self.field(points), z)

    def deformation_gradients(self, points: Tensor, z: Tensor) -> Tensor:
        """Deformation gradients F: (N, 3, 3) at rest points ``points: (N, 3)`` (exact, from the field), in the
        points' dtype."""

        w, dw = self.field.weights_and_gradients(points)
        return deformation_gradient(gradient_basis(points, w, dw), z)

    def deformation_gradients_at_cubature(self, z: Tensor) -> Tensor:
        """F: (K, 3, 3) at the cubature points for z: (12H,) (total F, plastic part included)."""
        return self.deformation_gradients(self.X, z)
