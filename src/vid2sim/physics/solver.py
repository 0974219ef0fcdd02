"""Implicit-Euler time integration of the reduced model, with the adjoint of each converged step.

One step minimises the incremental potential (paper Eq. 2, DESIGN.md)

    z_{t+1} = argmin_z ½ ‖z − z_t − Δt ż_t‖²_M + Δt² E_pot(z),      ż_{t+1} = (z_{t+1} − z_t) / Δt

by Newton's method with PSD-projected Hessians and a backtracking line search that starts from the full
Newton step and never accepts a state with an inverted cubature point (det F ≤ 0).

Gradients: the converged step satisfies ∇Φ(z*; θ) = 0, so dz*/dθ = −H⁻¹ ∂∇Φ/∂θ. The backward pass of
:class:`_ImplicitStep` solves H λ = ∂L/∂z* once (H the exact, unprojected Hessian at z*) and returns
−λᵀ ∂∇Φ/∂θ for every input θ (previous state, Lamé parameters, masses, the skinning field's LBS rows and
F-basis) — no backpropagation through Newton iterations or the line search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.materials import ELASTIC_MODELS, lame_parameters
from vid2sim.physics.reduced import (
    ElasticBasis,
    StepProblem,
    apply_plastic_state,
    lbs_rows,
    y_to_z_index,
    z_to_y_index,
)


class SimulationError(RuntimeError):
    """The simulation reached a state it cannot continue from (inverted elements, NaN, failed line search)."""


@dataclass
class SimConfig:
    """Time-integration settings (defaults: the paper / its public release).

    Attributes:
        dt: time step in seconds (one implicit step per video frame).
        newton_max_iters: Newton iterations per step at most.
        newton_rtol: converged when ‖∇Φ‖ ≤ rtol · max(‖∇Φ(z₀)‖, Δt² Σm · reference_acceleration).
        reference_acceleration: sets the absolute force scale of the tolerance (m/s²).
        line_search_max_halvings: backtracking halvings before the step is declared failed.
        armijo: sufficient-decrease constant of the line search.
        hessian_projection: "always" — Newton uses the Hessian with every per-point block projected to
            positive semi-definite; "on_demand" — Newton uses the exact Hessian whenever it is positive
            definite (its Cholesky factorisation succeeds, which the inertia term makes the common case)
            and the projected one otherwise. Both give a descent direction for the line search; the
            exact one converges at least as fast and costs less than half (no per-point eigen-analysis).
    """

    dt: float = 0.05
    newton_max_iters: int = 10
    newton_rtol: float = 1e-4
    reference_acceleration: float = 9.8
    line_search_max_halvings: int = 30
    armijo: float = 1e-4
    hessian_projection: str = "on_demand"

    def __post_init__(self) -> None:
        if self.hessian_projection not in ("always", "on_demand"):
            raise ValueError(
                f"SimConfig.hessian_projection must be 'always' or 'on_demand', got {self.hessian_projection!r}")
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"SimConfig.dt must be a positive finite number, got {self.dt}")
        if self.newton_max_iters < 1:
            raise ValueError(f"SimConfig.newton_max_iters must be >= 1, got {self.newton_max_iters}")
        if not self.newton_rtol > 0:
            raise ValueError(f"SimConfig.newton_rtol must be > 0, got {self.newton_rtol}")


@dataclass
class Material:
    """A homogeneous material. ``model`` is 'neo_hookean' (the paper's elastic model) or 'stvk';
    ``plasticity`` is None, a :class:`~vid2sim.physics.plasticity.VonMises` (plasticine) or a
    :class:`~vid2sim.physics.plasticity.DruckerPrager` (sand) return map (both used with 'stvk' in the paper).
    """

    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    model: str = "neo_hookean"
    plasticity: object | None = None

    def __post_init__(self) -> None:
        lame_parameters(self.youngs_modulus, self.poisson_ratio)  # validates E and ν
        if not (self.density > 0 and math.isfinite(self.density)):
            raise ValueError(f"Material.density must be a positive finite number (kg/m³), got {self.density}")
        if self.model not in ELASTIC_MODELS:
            raise ValueError(f"Material.model must be one of {sorted(ELASTIC_MODELS)}, got {self.model!r}")


@dataclass
class SimState:
    """State of the reduced model at time ``t``.

    Attributes:
        z: (12H,) handle transforms (handle-major layout of :mod:`vid2sim.physics.skinning`).
        zdot: (12H,) their velocities.
        t: time in seconds.
        Fp_inv: (K, 3, 3) inverse plastic deformation gradient per cubature point, or None (elastic).
        newton_iterations: Newton iterations the step into this state took (0 for an initial state).
        converged: whether that step met the gradient tolerance.
    """

    z: Tensor
    zdot: Tensor
    t: float = 0.0
    Fp_inv: Tensor | None = None
    newton_iterations: int = 0
    converged: bool = True


@dataclass
class StepStats:
    iterations: int = 0
    converged: bool = False
    line_search_halvings: list[int] = field(default_factory=list)


def _cholesky_solve(H: Tensor, rhs: Tensor) -> Tensor:
    """Solve H x = rhs for symmetric positive (semi-)definite H, regularising if needed."""
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) == 0:
        return torch.cholesky_solve(rhs[:, None], L)[:, 0]
    scale = float(H.diagonal().abs().mean())
    for k in range(1, 12):
        L, info = torch.linalg.cholesky_ex(H + (scale * 10.0 ** (k - 10)) * torch.eye(H.shape[0], dtype=H.dtype, device=H.device))
        if int(info) == 0:
            return torch.cholesky_solve(rhs[:, None], L)[:, 0]
    raise SimulationError("Newton system is not positive definite even after regularisation")


def _newton_direction(problem: StepProblem, y: Tensor, g: Tensor, config: SimConfig) -> Tensor:
    """−H⁻¹ g with H the exact Hessian when ``on_demand`` and it is positive definite, else the projected one."""
    if config.hessian_projection == "on_demand":
        L, info = torch.linalg.cholesky_ex(problem.hessian(y, project=False))
        if int(info) == 0:
            return -torch.cholesky_solve(g[:, None], L)[:, 0]
    return -_cholesky_solve(problem.hessian(y, project=True), g)


def newton_solve(problem: StepProblem, config: SimConfig) -> tuple[Tensor, StepStats]:
    """Minimise the step's incremental potential; returns (y*, stats). Inputs are treated as constants."""
    stats = StepStats()
    eps = torch.finfo(problem.y_prev.dtype).eps
    y = problem.y_pred
    phi, ok = problem.potential(y)
    if not ok:  # the inertial prediction inverts something: start from the previous (valid) state
        y = problem.y_prev
        phi, ok = problem.potential(y)
        if not ok:
            raise SimulationError(f"state at t = {problem.t - problem.dt:.4g} s has inverted cubature points (det F <= 0)")
    force_scale = problem.dt**2 * float(problem.mass.sum()) * config.reference_acceleration
    g = problem.gradient(y)
    ref = max(float(g.norm()), force_scale)
    for it in range(config.newton_max_iters):
        if float(g.norm()) <= config.newton_rtol * ref:
            stats.converged = True
            break
        d = _newton_direction(problem, y, g, config)
        slope = float(g @ d)
        alpha = 1.0
        inverted = False
        for halving in range(config.line_search_max_halvings + 1):
            y_new = y + alpha * d
            phi_new, ok = problem.potential(y_new)
            inverted = not ok
            tol = 16 * eps * max(abs(float(phi)), abs(float(phi_new)) if ok else 0.0, 1.0)
            if ok and float(phi_new) <= float(phi) + config.armijo * alpha * slope + tol:
                break
            alpha *= 0.5
        else:
            if abs(slope) <= 1e4 * eps * max(abs(float(phi)), 1.0):
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
        y, phi = y_new, phi_new
        stats.iterations = it + 1
        g = problem.gradient(y)
    else:
        stats.converged = float(g.norm()) <= config.newton_rtol * ref
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
    config: SimConfig
    stats: StepStats | None = None

    def problem(self, y_prev, ydot_prev, mu, lam, mass, b, basis_t) -> StepProblem:
        basis = ElasticBasis(self.A, basis_t, None) if self.structured else ElasticBasis(self.A, None, basis_t)
        return StepProblem(self.X, self.vol, mass, b, basis, mu, lam, self.model, self.externals,
                           self.t, self.config.dt, y_prev, ydot_prev)


class _ImplicitStep(torch.autograd.Function):
    """y_next = argmin Φ(y; inputs); backward by the adjoint of the converged step."""

    @staticmethod
    def forward(ctx, spec: _StepSpec, y_prev, ydot_prev, mu, lam, mass, b, basis_t):  # type: ignore[override]
        problem = spec.problem(y_prev, ydot_prev, mu, lam, mass, b, basis_t)
        y, stats = newton_solve(problem, spec.config)
        spec.stats = stats
        ctx.spec = spec
        ctx.save_for_backward(y, y_prev, ydot_prev, mu, lam, mass, b, basis_t)
        return y

    @staticmethod
    def backward(ctx, grad_y):  # type: ignore[override]
        spec: _StepSpec = ctx.spec
        y, *inputs = ctx.saved_tensors
        H = spec.problem(*inputs).hessian(y, project=False)
        adj = _cholesky_solve(H, grad_y) if torch.linalg.cholesky_ex(H)[1] == 0 else torch.linalg.solve(H, grad_y)
        needs = ctx.needs_input_grad[1:]
        with torch.enable_grad():
            req = [t.detach().requires_grad_(n) for t, n in zip(inputs, needs)]
            g = spec.problem(*req).gradient(y.detach())
            wanted = [r for r, n in zip(req, needs) if n]
            grads = torch.autograd.grad(g, wanted, grad_outputs=-adj, allow_unused=True) if wanted else ()
        it = iter(grads)
        out = [next(it) if n else None for n in needs]
        return (None, *out)


class Simulator:
    """Mesh-free reduced-order simulator of one object (paper §3, §4.2).

    Args:
        field: the skinning field (:class:`~vid2sim.physics.skinning.SkinningField`); H = field.num_handles_total.
        cubature_points: (K, 3) rest positions of the cubature points (canonical frame).
        cubature_weights: (K,) integration weights (volume / K in the paper).
        material: a :class:`Material`. Its E, ν and density become the differentiable tensors
            ``log10_E``, ``nu`` and ``density`` of this simulator (set ``requires_grad`` on them to optimise).
        externals: external energies (gravity, floor, moving floor, spheres; :mod:`vid2sim.physics.external`).
        config: :class:`SimConfig`.
        jacobian: optional Neural Jacobian (:class:`~vid2sim.physics.neural_jacobian.NeuralJacobian`); when
            given and ``use_neural_jacobian`` is True, dF/dz comes from it instead of the exact closed form.
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
    ) -> None:
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
        self.field = field
        self.X = cubature_points
        self.vol = cubature_weights
        self.material = material
        self.externals = list(externals)
        self.config = config or SimConfig()
        self.jacobian = jacobian
        self.use_neural_jacobian = use_neural_jacobian
        dtype, device = cubature_points.dtype, cubature_points.device
        self.log10_E = torch.tensor(math.log10(material.youngs_modulus), dtype=dtype, device=device)
        self.nu = torch.tensor(material.poisson_ratio, dtype=dtype, device=device)
        self.density = torch.tensor(material.density, dtype=dtype, device=device)
        H = field.num_handles_total
        self.num_dofs = 12 * H
        self._perm = z_to_y_index(H, device)
        self._inv = y_to_z_index(H, device)

    # ---- differentiable quantities -------------------------------------------------------------
    def lame(self) -> tuple[Tensor, Tensor]:
        """(μ, λ) from the current ``log10_E`` and ``nu`` (validated)."""
        if not bool(torch.isfinite(self.log10_E)) or not bool(torch.isfinite(self.nu)):
            raise ValueError(
                f"material parameters must be finite, got log10_E={float(self.log10_E.detach())}, nu={float(self.nu.detach())}"
            )
        return lame_parameters(10.0**self.log10_E, self.nu)  # type: ignore[return-value]

    def masses(self) -> Tensor:
        """(K,) lumped masses ρ·v_p."""
        if not float(self.density.detach()) > 0:
            raise ValueError(f"density must be positive, got {float(self.density.detach())}")
        return self.density * self.vol

    def reduced_basis(self) -> tuple[Tensor, Tensor, bool]:
        """(b (K, L), basis (K, 3, L) structured or (K, 9, D) dense in y layout, structured?) from the field."""
        from vid2sim.physics.skinning import gradient_basis

        w, dw = self.field.weights_and_gradients(self.X)
        b = lbs_rows(self.X, w)
        if self.use_neural_jacobian:
            J = self.jacobian(self.X)  # (K, 9, 12H) in z layout
            return b, J[:, :, self._perm], False
        return b, gradient_basis(self.X, w, dw), True

    # ---- states --------------------------------------------------------------------------------
    def rest_state(self, zdot: Tensor | None = None) -> SimState:
        """The rest state z = 0 (optionally with initial velocities zdot: (12H,)) at t = 0."""
        z = torch.zeros(self.num_dofs, dtype=self.X.dtype, device=self.X.device)
        plastic = self.material.plasticity is not None
        Fp = torch.eye(3, dtype=self.X.dtype, device=self.X.device).expand(self.X.shape[0], 3, 3).clone() if plastic else None
        return SimState(z, torch.zeros_like(z) if zdot is None else zdot, 0.0, Fp)

    def rigid_velocity_state(self, linear: Sequence[float], angular: Sequence[float] = (0, 0, 0), about: Sequence[float] = (0, 0, 0)) -> SimState:
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
    def step(self, state: SimState, basis: tuple[Tensor, Tensor, bool] | None = None,
             lame: tuple[Tensor, Tensor] | None = None) -> SimState:
        """One implicit-Euler step. Differentiable (adjoint) w.r.t. the state, E, ν, density and the field."""
        if state.z.shape != (self.num_dofs,) or state.zdot.shape != (self.num_dofs,):
            raise ValueError(f"state z and zdot must have shape ({self.num_dofs},), got {tuple(state.z.shape)}, {tuple(state.zdot.shape)}")
        if not bool(torch.isfinite(state.z).all() & torch.isfinite(state.zdot).all()):
            raise SimulationError(f"state at t = {state.t:.4g} s contains NaN or infinite values")
        b, basis_t, structured = basis if basis is not None else self.reduced_basis()
        mu, lam = lame if lame is not None else self.lame()
        A = torch.eye(3, dtype=self.X.dtype, device=self.X.device).expand(self.X.shape[0], 3, 3)
        if state.Fp_inv is not None:
            folded = apply_plastic_state(basis_t, structured, state.Fp_inv)
            A, basis_t = folded.A, folded.tensor
        t_next = state.t + self.config.dt
        spec = _StepSpec(self.X, self.vol, A, structured, self.material.model, self.externals, t_next, self.config)
        y_prev, ydot_prev = state.z[self._perm], state.zdot[self._perm]
        y = _ImplicitStep.apply(spec, y_prev, ydot_prev, torch.as_tensor(mu), torch.as_tensor(lam),
                                self.masses(), b, basis_t)
        z = y[self._inv]
        zdot = (z - state.z) / self.config.dt
        Fp_inv = state.Fp_inv
        if self.material.plasticity is not None:
            Fp_inv = self._update_plastic(state, z.detach(), structured, b, mu, lam)
        return SimState(z, zdot, t_next, Fp_inv, spec.stats.iterations, spec.stats.converged)

    def _update_plastic(self, state: SimState, z: Tensor, structured: bool, b: Tensor, mu, lam) -> Tensor:
        from vid2sim.physics.plasticity import update_plastic_state

        F_total = self.deformation_gradients_at_cubature(z)
        return update_plastic_state(self.material.plasticity, F_total, state.Fp_inv,
                                    torch.as_tensor(mu).detach(), torch.as_tensor(lam).detach())

    def rollout(self, state: SimState, steps: int, progress: bool = False) -> list[SimState]:
        """``steps`` implicit steps from ``state``; returns the states after each step (length ``steps``)."""
        if steps < 0:
            raise ValueError(f"steps must be >= 0, got {steps}")
        basis = self.reduced_basis()
        lame = self.lame()
        out = []
        iterator = range(steps)
        if progress:
            from tqdm.auto import tqdm

            iterator = tqdm(iterator, desc="simulate", unit="step")
        for _ in iterator:
            state = self.step(state, basis, lame)
            out.append(state)
        return out

    # ---- outputs -------------------------------------------------------------------------------
    def positions(self, points: Tensor, z: Tensor) -> Tensor:
        """World positions x: (N, 3) of rest points ``points: (N, 3)`` for the state z: (12H,)."""
        from vid2sim.physics.skinning import deform

        return deform(points, self.field(points), z)

    def deformation_gradients(self, points: Tensor, z: Tensor) -> Tensor:
        """Deformation gradients F: (N, 3, 3) at rest points ``points: (N, 3)`` (exact, from the field)."""
        from vid2sim.physics.skinning import deformation_gradient, gradient_basis

        w, dw = self.field.weights_and_gradients(points)
        return deformation_gradient(gradient_basis(points, w, dw), z)

    def deformation_gradients_at_cubature(self, z: Tensor) -> Tensor:
        """F: (K, 3, 3) at the cubature points for z: (12H,) (total F, plastic part included)."""
        return self.deformation_gradients(self.X, z)
