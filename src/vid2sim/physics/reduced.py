"""The reduced-order model: everything the implicit solver needs at the cubature points.

The reduced state of H handles is z ∈ R^{12H}, laid out handle-major (``z[12j + 4a + k] = Z_j[a, k]``,
see :mod:`vid2sim.physics.skinning`). Inside the solver we use the *row-major* layout
``y[a·L + 4j + k] = Z_j[a, k]`` with L = 4H, i.e. ``Y = y.reshape(3, L)`` holds row a of every handle's
transform. In that layout LBS and the deformation gradient are block structured:

    x_p = X_p + Y b_p               with b_p[4j + k] = w_j(X_p) [X_p, 1]_k              (L,)
    F_p = A_p + Y G_p               with G_p[c, 4j + k] = w_j δ_kc + [X_p, 1]_k ∂_c w_j  (3, L)

so the reduced mass matrix is I₃ ⊗ Σ_p m_p b_p b_pᵀ and every per-point 3×3 Hessian block couples only
rows of Y. ``A_p`` is the inverse plastic deformation gradient (identity for elastic materials), folded
into the basis (``F_e = F F_p⁻¹``). A dense basis ``J_p: (9, D)`` (the Neural Jacobian's prediction, D = 3L)
replaces ``G_p`` when requested.

All functions here are plain differentiable torch expressions of their tensor inputs: the solver's
adjoint differentiates :func:`incremental_gradient` with respect to the material parameters, the masses,
the skinning quantities (b, G) and the previous state.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from vid2sim.physics.damping import reference_metric, viscous_tangent
from vid2sim.physics.external import Gravity, energy_and_gradient
from vid2sim.physics.integrators import BDFStep
from vid2sim.physics.materials import (
    det3,
    elastic_model,
    energy_and_pk1,
    neo_hookean_tangent,
    neo_hookean_viscous_energy_and_pk1,
    neo_hookean_viscous_tangent,
    project_psd,
    project_tangent_psd,
    stvk_energy_and_pk1,
)
from vid2sim.physics.volumetric import project as project_volumetric
from vid2sim.physics.volumetric import swap_tangent

if TYPE_CHECKING:  # pragma: no cover
    from vid2sim.physics.fused import FusedStep


def z_to_y_index(num_handles_total: int, device: torch.device | None = None) -> Tensor:
    """Index ``perm`` with ``y = z[perm]`` (handle-major z → row-major y), (12H,) long."""
    h = num_handles_total
    a, j, k = torch.meshgrid(torch.arange(3), torch.arange(h), torch.arange(4), indexing="ij")
    return (12 * j + 4 * a + k).reshape(-1).to(device)


def y_to_z_index(num_handles_total: int, device: torch.device | None = None) -> Tensor:
    """Inverse of :func:`z_to_y_index`: ``z = y[inv]``, (12H,) long."""
    perm = z_to_y_index(num_handles_total)
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(perm.numel())
    return inv.to(device)


def lbs_rows(X: Tensor, w: Tensor) -> Tensor:
    """b: (N, L) with ``b[p, 4j + k] = w_j(X_p) [X_p, 1]_k``; ``x_p = X_p + Y b_p``."""
    xh = torch.cat([X, torch.ones_like(X[:, :1])], dim=1)
    return (w[:, :, None] * xh[:, None, :]).reshape(X.shape[0], -1)


@dataclass
class ElasticBasis:
    """Deformation-gradient basis at the cubature points: ``F_p = A_p + Y G_p`` or ``vec F_p = vec A_p + J_p y``.

    Attributes:
        A: (K, 3, 3) base (inverse plastic deformation gradient; identity when elastic).
        G: (K, 3, L) structured basis, or None when ``J`` is given.
        J: (K, 9, D) dense basis in y layout (Neural Jacobian), or None.
    """

    A: Tensor
    G: Tensor | None = None
    J: Tensor | None = None

    @property
    def tensor(self) -> Tensor:
        return self.G if self.G is not None else self.J  # type: ignore[return-value]

    def with_tensor(self, t: Tensor) -> "ElasticBasis":
        return ElasticBasis(self.A, t, None) if self.G is not None else ElasticBasis(self.A, None, t)

    def deformation_gradient(self, y: Tensor) -> Tensor:
        """F: (K, 3, 3) for the row-major state y: (D,)."""
        if self.G is not None:
            # (G_p Yᵀ)[c, a] = Σ_l G_p[c, l] Y[a, l] = (Y G_p)[a, c]
            return self.A + (self.G @ y.reshape(3, -1).T).transpose(1, 2)
        K = self.A.shape[0]
        return self.A + (self.J @ y).reshape(K, 3, 3)

    def force(self, P: Tensor) -> Tensor:
        """Σ_p ∂vec(F_p)/∂y ᵀ vec(P_p) for P: (K, 3, 3) (already volume-weighted) → (D,)."""
        if self.G is not None:
            K, _, L = self.G.shape
            return (P.transpose(0, 1).reshape(3, 3 * K) @ self.G.reshape(3 * K, L)).reshape(-1)
        K = P.shape[0]
        return torch.einsum("pi,pid->d", P.reshape(K, 9), self.J)

    def point_rows(self, M: Tensor) -> Tensor:
        """Per point ∂vec(F_p)/∂y ᵀ vec(M_p) for M: (K, 3, 3) → (K, D) (:meth:`force` is their sum)."""
        K = M.shape[0]
        if self.G is not None:
            return (M @ self.G).reshape(K, -1)  # [p, (a, l)] = Σ_c M_p[a, c] G_p[c, l]
        return torch.einsum("pi,pid->pd", M.reshape(K, 9), self.J)

    def hessian(self, C: Tensor) -> Tensor:
        """Σ_p ∂vec(F_p)/∂yᵀ C_p ∂vec(F_p)/∂y for C: (K, 9, 9) (volume-weighted) → (D, D)."""
        if self.G is not None:
            G = self.G
            K, _, L = G.shape
            # H[(a, l), (b, m)] = Σ_p Σ_cd G[p, c, l] C[p, (a, c), (b, d)] G[p, d, m]; C is symmetric
            # ((a, c) ↔ (b, d)), so only the row blocks a ≤ b are computed and the others are their transposes
            C5 = C.reshape(K, 3, 3, 3, 3)  # [p, a, c, b, d]
            pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
            Cr = torch.stack([C5[:, a, :, b, :] for a, b in pairs], dim=1)  # (K, 6, c, d)
            T = (Cr.reshape(K, 18, 3) @ G).reshape(K, 6, 3, L)  # [p, pair, c, m]
            Hm = G.permute(2, 0, 1).reshape(L, K * 3) @ T.permute(0, 2, 1, 3).reshape(K * 3, 6 * L)
            Hm = Hm.reshape(L, 6, L)
            H = C.new_empty(3, L, 3, L)
            for q, (a, b) in enumerate(pairs):
                H[a, :, b, :] = Hm[:, q, :]
                if a != b:
                    H[b, :, a, :] = Hm[:, q, :].T
            return H.reshape(3 * L, 3 * L)
        K, _, D = self.J.shape
        CJ = C @ self.J
        return self.J.reshape(K * 9, D).T @ CJ.reshape(K * 9, D)


def apply_plastic_state(basis_tensor: Tensor, structured: bool, Fp_inv: Tensor) -> ElasticBasis:
    """Fold the inverse plastic deformation gradient into the basis: F_e = F Fp⁻¹ (rows of F times Fp⁻¹)."""
    if structured:
        G = torch.einsum("pcd,pcl->pdl", Fp_inv, basis_tensor)  # G'[d,l] = Σ_c Finv[c,d] G[c,l]
        return ElasticBasis(Fp_inv, G, None)
    K, _, D = basis_tensor.shape
    J = torch.einsum("pacy,pcd->pady", basis_tensor.reshape(K, 3, 3, D), Fp_inv).reshape(K, 9, D)
    return ElasticBasis(Fp_inv, None, J)


@dataclass
class StepProblem:
    """One implicit step's incremental potential, at fixed inputs (see :mod:`vid2sim.physics.integrators`).

    Φ(y) = ½ (y − ŷ)ᵀ M (y − ŷ) + k_E (Σ_p v_p Ψ(F_p(y)) + E_ext(x(y), t)) + k_D Σ_p v_p ψ(F_p(y); C_ref,p)

    with ŷ, k_E = h²/a₀² and k_D = h τ/a₀ from the BDF step, Ψ the elastic energy density and ψ the
    Kelvin–Voigt viscous potential (:mod:`vid2sim.physics.damping`) measured from the metric
    C_ref = (a₁ C(y_prev) + a₂ C(y_prev2)) / a₀. ``tau`` None means undamped.

    External energies of kind "body" (gravity) act on the cubature points with their masses; those of
    kind "contact" (barriers) on the contact points (``contact_X``, LBS rows ``contact_b``) with the
    weights ``contact_w`` — by default the cubature points with weight 1 (the paper's floor formula).
    With ``contact_layer_stiffness`` k_b, a barrier of stiffness k acts through a layer of the body in series:
    its weights are scaled by 1 / (1 + k / k_b) (:meth:`vid2sim.physics.solver.Simulator.contact_layer_stiffness`).

    With ``contact_damping`` c (a normal dashpot in every barrier's contact, N·s/m per unit contact weight:
    with area weights a pressure per normal velocity) the step adds the dissipation potential

        D(y) = (h / a₀) c Σ_i w_i φ_i ½ (s_i(y) − s_ref,i)²,    s_ref = (a₁ s_i(x_n, t_n) + a₂ s_i(x_{n−1}, t_{n−1})) /
        a₀,

    whose gradient is k_E times the dashpot force −c w_i φ_i ṡ_i ∇s_i with the BDF rate ṡ of the signed
    distance s to the barrier (the barrier's own motion included). φ_i = 1 for the points that were in contact
    (s < 0) at the start of the step, else 0: the activation lags by one step (an O(h) error that the step
    count controls, like the rest of the step) and keeps D quadratic, so Newton and the adjoint stay exact.

    A barrier with Coulomb friction μ > 0 (its ``friction``) adds the smoothed, lagged friction potential of
    incremental-potential contact (Li et al. 2020, "IPC", §5):

        D_f(y) = k_E (h / a₀) μ Σ_i λ_i f₀(‖u_i(y)‖),    u_i = T_i ((a₀ / h)(x_i(y) − x_ref,i) − v_b,i),

    with x_ref = (a₁ x_n + a₂ x_{n−1}) / a₀ (so (a₀/h)(x − x_ref) is the BDF velocity of the point), v_b the
    barrier's surface velocity there, T_i = I − n_i n_iᵀ the tangent projector and λ_i = 2 k w_i max(0, −s_i) the
    penalty's normal force, and f₀ the integral of IPC's smoothed sliding law f₁(σ) = 2σ/ε_v − σ²/ε_v² below the
    slip speed ε_v, 1 above. Its gradient is k_E times the friction force −μ λ_i f₁(‖u_i‖) u_i/‖u_i‖; it is convex
    in y, so Newton's Hessian needs no projection and the adjoint stays exact. λ_i, n_i, v_b and the set of points
    in contact are evaluated at ``friction_state`` y_λ at the end of the step — the simulator's fixed point
    y_λ = y* makes the normal force implicit (:attr:`vid2sim.physics.solver.SimConfig.friction_iterations`) — or,
    when it is None, at the start of the step (lagged, as the dashpot's activation).
    """

    X: Tensor  # (K, 3) cubature rest positions
    vol: Tensor  # (K,) integration weights
    mass: Tensor  # (K,) lumped masses
    b: Tensor  # (K, L) LBS rows
    basis: ElasticBasis
    mu: Tensor
    lam: Tensor
    model: str
    externals: Sequence  # ExternalEnergy objects (vid2sim.physics.external)
    t: float  # time at the end of the step
    step: BDFStep
    y_prev: Tensor  # (D,) state at the start of the step
    ydot_prev: Tensor  # (D,)
    y_prev2: Tensor | None = None  # (D,) state one step earlier (BDF2)
    ydot_prev2: Tensor | None = None
    tau: Tensor | None = None  # Kelvin–Voigt retardation time (s), None = undamped
    contact_X: Tensor | None = None  # (Nc, 3) contact points' rest positions (None: the cubature points)
    contact_b: Tensor | None = None  # (Nc, L) their LBS rows
    contact_w: Tensor | None = None  # (Nc,) their barrier weights
    contact_layer_stiffness: Tensor | None = None  # k_b (0-d, Pa/m): the body's contact layer in series
    contact_damping: Tensor | None = None  # c (0-d, N·s/m per unit contact weight): the contact dashpot
    volumetric: Tensor | None = None  # (K, H) V-orthonormal weights: the λ term projected (physics.volumetric)
    friction_state: Tensor | None = None  # (D,) y_λ: the state friction's normal force is taken at (None: y_prev)
    fused: "FusedStep | None" = None  # the same step on the fused kernels (physics.fused), used where it applies

    # ---- pieces ------------------------------------------------------------------------------
    @property
    def dt(self) -> float:
        """The step length h."""
        return self.step.h

    @functools.cached_property
    def y_pred(self) -> Tensor:
        """ŷ, the inertial target of the step (D,)."""
        return self.step.target(self.y_prev, self.ydot_prev, self.y_prev2, self.ydot_prev2)

    @functools.cached_property
    def c_ref(self) -> Tensor | None:
        """C_ref (K, 3, 3) of the viscous potential, or None when undamped."""
        if self.tau is None:
            return None
        F_prev = self.basis.deformation_gradient(self.y_prev)
        F_prev2 = self.basis.deformation_gradient(self.y_prev2) if self.step.needs_history else None
        return reference_metric(self.step.coefficients, F_prev, F_prev2)

    def positions(self, y: Tensor) -> Tensor:
        """x: (K, 3) cubature positions."""
        return self.X + self.b @ y.reshape(3, -1).T

    @functools.cached_property
    def mass_block(self) -> Tensor:
        """(L, L) block Σ_p m_p b_p b_pᵀ of the reduced mass matrix M = I₃ ⊗ block (differentiable)."""
        return (self.b * self.mass[:, None]).T @ self.b

    def mass_times(self, dy: Tensor) -> Tensor:
        """M dy for dy: (D,), with M = I₃ ⊗ Σ_p m_p b_p b_pᵀ (differentiable)."""
        return (dy.reshape(3, -1) @ self.mass_block).reshape(-1)

    @functools.cached_property
    def mass_matrix(self) -> Tensor:
        """(D, D) reduced mass matrix (constant during a step; computed once)."""
        Mb = self.mass_block
        return torch.block_diag(Mb, Mb, Mb)

    @functools.cached_property
    def _contact(self) -> tuple[Tensor, Tensor, Tensor]:
        """(rest positions (Nc, 3), LBS rows (Nc, L), weights (Nc,)) of the contact points."""
        if self.contact_b is None:
            return self.X, self.b, torch.ones_like(self.mass)
        return self.contact_X, self.contact_b, self.contact_w

    @functools.cached_property
    def _externals_by_kind(self) -> tuple[list, list]:
        body = [e for e in self.externals if getattr(e, "kind", "body") == "body"]
        contact = [e for e in self.externals if getattr(e, "kind", "body") == "contact"]
        return body, contact

    def _barrier_weights(self, ext, weights: Tensor) -> Tensor:
        """The contact weights a barrier ``ext`` acts with: through the contact layer in series, if any."""
        k_b = self.contact_layer_stiffness
        return weights if k_b is None else weights / (1.0 + ext.stiffness / k_b)

    def _contact_positions(self, y: Tensor) -> Tensor:
        X, b, _ = self._contact
        return X + b @ y.reshape(3, -1).T

    @functools.cached_property
    def _dashpot_reference(self) -> list[tuple[object, Tensor, Tensor]]:
        """[(barrier, s_ref (Nc,), k (Nc,))] of the contact dashpot: the reference distance of the BDF rate and
        the coefficient (h / a₀) c w φ per contact point (φ: in contact at the start of the step); empty
        without ``contact_damping``."""
        if self.contact_damping is None:
            return []
        a0, a1, a2 = self.step.coefficients
        _, _, w = self._contact
        t_prev = self.t - self.step.h
        x_prev = self._contact_positions(self.y_prev)
        out = []
        for ext in self._externals_by_kind[1]:
            s_prev = ext.signed_distance(x_prev, t_prev)
            s_ref = (a1 / a0) * s_prev
            if self.step.needs_history:
                s_ref = s_ref + (a2 / a0) * ext.signed_distance(self._contact_positions(self.y_prev2),
                                                                t_prev - self.step.h_prev)
            active = (s_prev.detach() < 0).to(s_prev.dtype)
            out.append((ext, s_ref, (self.step.h / a0) * self.contact_damping * w * active))
        return out

    @functools.cached_property
    def _friction_reference(self) -> list[tuple[Tensor, Tensor, Tensor, Tensor, Tensor, float]]:
        """[(index (A,), x_ref (A, 3), v_b (A, 3), n (A, 3), c (A,), ε_v)] of every barrier with friction, over the
        A contact points in contact with it at y_λ (``friction_state``, else the start of the step): the BDF
        reference position, the barrier's surface velocity, its normal and the coefficient k_E μ λ there; empty
        without friction."""
        barriers = friction_barriers(self.externals)
        if not barriers:
            return []
        a0, a1, a2 = self.step.coefficients
        _, _, w = self._contact
        x_prev = self._contact_positions(self.y_prev)
        x_ref = (a1 / a0) * x_prev
        if self.step.needs_history:
            x_ref = x_ref + (a2 / a0) * self._contact_positions(self.y_prev2)
        if self.friction_state is None:
            x_lag, t_lag = x_prev, self.t - self.step.h
        else:
            x_lag, t_lag = self._contact_positions(self.friction_state), self.t
        out = []
        for ext in barriers:
            s_lag, n, _ = ext.distance_derivatives(x_lag, t_lag)
            index = (s_lag.detach() < 0).nonzero()[:, 0]
            if index.numel() == 0:
                continue
            normal_force = 2.0 * ext.stiffness * self._barrier_weights(ext, w)[index] * (-s_lag[index])
            coefficient = self.step.energy_scale * ext.friction * normal_force
            v_b = ext.surface_velocity(x_lag[index], self.t)
            out.append((index, x_ref[index], v_b, n[index], coefficient, float(ext.friction_velocity)))
        return out

    def _slip(self, x: Tensor, x_ref: Tensor, v_b: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
        """(u (A, 3), σ (A,)): the tangential slip velocity (a₀/h)(x − x_ref) − v_b projected off the normal n,
        and its length (kept off zero by the dtype's smallest normal number, so that it differentiates)."""
        v = (self.step.a0 / self.step.h) * (x - x_ref) - v_b
        u = v - (v * n).sum(1, keepdim=True) * n
        return u, torch.sqrt((u * u).sum(1) + torch.finfo(u.dtype).tiny)

    def _friction_energy_and_force(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """(D_f(y) (), ∂D_f/∂y (D,)) of the barriers' friction (zeros without any)."""
        e, f = y.new_zeros(()), y.new_zeros(y.shape)
        x = self._contact_positions(y)
        b = self._contact[1]
        for index, x_ref, v_b, n, c, eps in self._friction_reference:
            u, sigma = self._slip(x[index], x_ref, v_b, n)
            f0, phi, _ = smoothed_friction(sigma, eps)
            e = e + (self.step.h / self.step.a0) * (c * f0).sum()
            f = f + (((c * phi)[:, None] * u).T @ b[index]).reshape(-1)
        return e, f

    def _friction_hessian(self, y: Tensor) -> Tensor | None:
        """∂²D_f/∂y² (D, D) of the barriers' friction, or None without any: per point
        c (a₀/h) [φ T + σ φ'(σ) ûûᵀ] with φ = f₁(σ)/σ and T = I − nnᵀ, positive semi-definite."""
        if not self._friction_reference:
            return None
        x = self._contact_positions(y)
        b = self._contact[1]
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        H = None
        for index, x_ref, v_b, n, c, eps in self._friction_reference:
            u, sigma = self._slip(x[index], x_ref, v_b, n)
            _, phi, sigma_dphi = smoothed_friction(sigma, eps)
            u_hat = u / sigma[:, None]
            tangent = eye - n[:, :, None] * n[:, None, :]
            block = phi[:, None, None] * tangent + sigma_dphi[:, None, None] * (u_hat[:, :, None] * u_hat[:, None, :])
            H_b = reduced_point_hessian(((self.step.a0 / self.step.h) * c)[:, None, None] * block, b[index])
            H = H_b if H is None else H + H_b
        return H

    def _dashpot_energy_and_force(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """(D(y) (), ∂D/∂y (D,)) of the contact dashpot (zeros without one)."""
        e, f = y.new_zeros(()), y.new_zeros(y.shape)
        if not self._dashpot_reference:
            return e, f
        x = self._contact_positions(y)
        g = torch.zeros_like(x)
        for ext, s_ref, k in self._dashpot_reference:
            s, ds, _ = ext.distance_derivatives(x, self.t)
            r = s - s_ref
            e = e + 0.5 * (k * r * r).sum()
            g = g + (k * r)[:, None] * ds
        return e, f + (g.T @ self._contact[1]).reshape(-1)

    def _dashpot_hessian(self, y: Tensor, project: bool) -> Tensor | None:
        """∂²D/∂y² (D, D) of the contact dashpot, or None without one. Per point k (∇s∇sᵀ + r ∇²s); ``project``
        keeps the curvature term only where it is positive semi-definite (r ≥ 0 for a convex barrier)."""
        if not self._dashpot_reference:
            return None
        x = self._contact_positions(y)
        hx = x.new_zeros(x.shape[0], 3, 3)
        for ext, s_ref, k in self._dashpot_reference:
            s, ds, curvature = ext.distance_derivatives(x, self.t)
            hx = hx + k[:, None, None] * (ds[:, :, None] * ds[:, None, :])
            if curvature is not None:
                r = s - s_ref
                if project:
                    r = r.clamp_min(0.0)
                hx = hx + (k * r)[:, None, None] * curvature
        return reduced_point_hessian(hx, self._contact[1])

    @functools.cached_property
    def _gravity(self) -> tuple[Tensor, Tensor] | None:
        """Uniform gravity is linear in y: E = −Σ_p m_p g·(X_p + Y b_p) = e₀ − f·y with the constant force
        f = vec(g (Σ_p m_p b_p)ᵀ) (D,); returns (e₀, f) for the sum of the Gravity terms, or None."""
        g = [ext for ext in self._externals_by_kind[0] if isinstance(ext, Gravity)]
        if not g:
            return None
        acc = sum(torch.tensor(ext.acceleration, dtype=self.X.dtype, device=self.X.device) for ext in g)
        e0 = -(self.mass * (self.X @ acc)).sum()
        return e0, (acc[:, None] * (self.mass @ self.b)[None, :]).reshape(-1)

    def _external_energy_and_force(self, y: Tensor, energy: bool = True) -> tuple[Tensor, Tensor]:
        """(E_ext (), ∂E_ext/∂y (D,)); ``energy`` is unused (the energy comes with the gradient)."""
        body, contact = self._externals_by_kind
        e = y.new_zeros(())
        f = y.new_zeros(y.shape)
        if self._gravity is not None:
            e0, fg = self._gravity
            e, f = e0 - fg @ y, -fg
            body = [ext for ext in body if not isinstance(ext, Gravity)]
        for points, b, weights, energies in ((None, self.b, self.mass, body), (True, None, None, contact)):
            if not energies:
                continue
            if points is None:
                x = self.positions(y)
            else:
                _, b, weights = self._contact
                x = self._contact_positions(y)
            g = torch.zeros_like(x)
            for ext in energies:
                w_ext = weights if points is None else self._barrier_weights(ext, weights)
                e_i, g_i = energy_and_gradient(ext, x, w_ext, self.t)
                e = e + e_i
                g = g + g_i
            f = f + (g.T @ b).reshape(-1)
        return e, f

    def _external_hessian(self, y: Tensor, project: bool) -> Tensor:
        body, contact = self._externals_by_kind
        L = self.b.shape[1]
        H = y.new_zeros(3 * L, 3 * L)
        if body:
            x = self.positions(y)
            hx = x.new_zeros(x.shape[0], 3, 3)
            for ext in body:
                hx = hx + ext.hessian(x, self.mass, self.t, project=project)
            H = H + reduced_point_hessian(hx, self.b)
        if contact:
            xc, w = self._contact_positions(y), self._contact[2]
            hx = xc.new_zeros(xc.shape[0], 3, 3)
            for ext in contact:
                hx = hx + ext.hessian(xc, self._barrier_weights(ext, w), self.t, project=project)
            H = H + reduced_point_hessian(hx, self._contact[1])
        return H

    def evaluate(self, y: Tensor, energy: bool = True) -> tuple[Tensor, Tensor | None, bool]:
        """(Φ(y) (), ∇Φ(y) (D,), valid) in one pass over the points. ``valid`` is False (Φ = inf, ∇Φ None)
        when a cubature point is inverted (det F ≤ 0). With ``energy=False`` Φ is not computed (0).
        A differentiable expression of every input (the adjoint differentiates ∇Φ) unless the step is ``fused``
        (:mod:`vid2sim.physics.fused`: inputs detached, the same values)."""
        if self.fused is not None:
            if energy:
                phi, g, J = self.fused.potential(y)
            else:
                phi, (_, g, J) = y.new_zeros(()), self.fused.evaluate(y, energy=False)
            if not bool((J > 0).all()):
                return y.new_full((), float("inf")), None, False
            return phi, g, True
        F = self.basis.deformation_gradient(y)
        k_e = self.step.energy_scale
        projected = self.volumetric is not None
        lam_e = self.lam * 0.0 if projected else self.lam  # the projected λ term is added below
        if self.tau is not None and self.model == "neo_hookean":  # the common case, fused
            # projected: both λ terms (elastic and viscous) are added below, in the weights' span
            psi, stress, J = neo_hookean_viscous_energy_and_pk1(F, self.mu, lam_e, k_e,
                                                                self.step.damping_scale(self.tau), self.c_ref, energy,
                                                                lam_elastic=lam_e)
        else:
            psi, P, J = energy_and_pk1(self.model, F, self.mu, lam_e)
            stress, psi = k_e * P, k_e * psi
            if self.tau is not None:
                k_d = self.step.damping_scale(self.tau)
                psi_d, P_d = stvk_energy_and_pk1(F, self.mu, self.lam, self.c_ref)
                stress, psi = stress + k_d * P_d, psi + k_d * psi_d
        if not bool((J > 0).all()):
            return y.new_full((), float("inf")), None, False
        if projected:
            l_bar = project_volumetric(self.volumetric, self.vol, torch.log(J))
            stress = stress + (k_e * self.lam * l_bar)[:, None, None] * torch.linalg.inv(F).transpose(1, 2)
            if energy:
                psi = psi + k_e * 0.5 * self.lam * l_bar * l_bar
            if self.tau is not None:  # the Kelvin–Voigt λ term on the projected strain rate tr G (F-bar alike)
                k_d = self.step.damping_scale(self.tau)
                g_bar = project_volumetric(self.volumetric, self.vol, _half_trace_strain(F, self.c_ref))
                stress = stress + (k_d * self.lam * g_bar)[:, None, None] * F
                if energy:
                    psi = psi + k_d * 0.5 * self.lam * g_bar * g_bar
        dy = y - self.y_pred
        m_dy = self.mass_times(dy)
        e_ext, f_ext = self._external_energy_and_force(y, energy)
        phi = y.new_zeros(())
        if energy:
            phi = 0.5 * (dy @ m_dy) + self.vol @ psi + k_e * e_ext
        g = m_dy + self.basis.force(self.vol[:, None, None] * stress) + k_e * f_ext
        if self.contact_damping is not None:
            e_d, f_d = self._dashpot_energy_and_force(y)
            phi, g = phi + e_d if energy else phi, g + f_d
        if self._friction_reference:
            e_f, f_f = self._friction_energy_and_force(y)
            phi, g = phi + e_f if energy else phi, g + f_f
        return phi, g, True

    @property
    def y_start(self) -> Tensor:
        """Newton's starting point: the extrapolation of :meth:`BDFStep.start` when the step has history,
        else the inertial target ŷ; a step of friction's fixed point (``friction_state`` given) starts from that
        state, the solution of the same step with the normal force one iteration older, which lies close."""
        if self.friction_state is not None:
            return self.friction_state.detach()
        if self.ydot_prev2 is None:
            return self.y_pred
        return self.step.start(self.y_prev, self.ydot_prev, self.ydot_prev2)

    def energy_and_gradient(self, y: Tensor) -> tuple[float, Tensor | None]:
        """(Φ(y) as a float, ∇Φ(y) (D,)) as Newton needs them, with one synchronisation on the fused kernels;
        (inf, None) where a cubature point is inverted (det F ≤ 0)."""
        if self.fused is not None:
            return self.fused.energy_and_gradient(y)
        phi, g, ok = self.evaluate(y)
        return (float(phi), g) if ok else (float("inf"), None)

    def valid(self, y: Tensor) -> bool:
        """No cubature point is inverted at y (det F > 0 everywhere)."""
        if self.fused is not None:
            return self.fused.valid(y)
        return bool((det3(self.basis.deformation_gradient(y)) > 0).all())

    def potential(self, y: Tensor) -> tuple[Tensor, bool]:
        """(Φ(y), valid) where valid is False if any cubature point is inverted (det F ≤ 0)."""
        phi, _, ok = self.evaluate(y)
        return phi, ok

    def gradient(self, y: Tensor) -> Tensor:
        """∇Φ(y): (D,). A differentiable expression of every input (used by the adjoint)."""
        _, g, ok = self.evaluate(y, energy=False)
        if not ok:
            raise ValueError("the gradient is undefined where a cubature point is inverted (det F <= 0)")
        return g

    def newton_measures(self, g: Tensor, d: Tensor, y_new: Tensor) -> tuple[float, float, float]:
        """(the largest coordinate change max |Δx| over the cubature and contact points for the Newton step d, the
        same for the whole step so far y_new − y_prev, the slope g·d) for g, d, y_new: (D,), with one
        synchronisation."""
        both = torch.stack([d, y_new - self.y_prev]).view(6, -1)
        moves = torch.mm(both, self._tracked_cols).abs_().amax(1)
        values = torch.cat([moves, torch.dot(g, d).view(1)]).tolist()
        return max(values[:3]), max(values[3:6]), values[6]

    @functools.cached_property
    def _tracked_cols(self) -> Tensor:
        """The LBS rows of the points :meth:`newton_measures` watches, the cubature and contact points, transposed:
        (L, K [+ Nc])."""
        if self.fused is not None:
            return self.fused.frame.tracked_cols
        rows = self.b if self.contact_b is None else torch.cat([self.b, self.contact_b])
        return rows.detach().T.contiguous()

    def hessian(self, y: Tensor, project: bool = True) -> Tensor:
        """∇²Φ(y): (D, D); per-point elastic, viscous and external blocks projected to PSD when ``project``
        (Newton), exact when not (the adjoint)."""

        if self.fused is not None and not project:
            return self.fused.hessian(y)

        F = self.basis.deformation_gradient(y)
        k_d = self.step.damping_scale(self.tau) if self.tau is not None else 0.0
        k_e = self.step.energy_scale
        if self.volumetric is not None:
            return self._projected_hessian(y, F, k_e, k_d, project)
        if not project and self.model == "neo_hookean":
            C = neo_hookean_viscous_tangent(F, self.mu, self.lam, k_e, k_d, self.c_ref)
        else:
            C = elastic_model(self.model)[2](F, self.mu, self.lam)
            if project:
                C = project_tangent_psd(self.model, F, C, self.mu, self.lam)
            C = k_e * C
            if self.tau is not None:
                C = C + k_d * viscous_tangent(F, self.c_ref, self.mu, self.lam, psd=project)
        return self._assemble_hessian(y, C, project)

    def _projected_hessian(self, y: Tensor, F: Tensor, k_e, k_d, project: bool) -> Tensor:
        """:meth:`hessian` with the projected volumetric term (:mod:`vid2sim.physics.volumetric`): per point
        the Neo-Hookean tangent without its λ term plus −λ ℓ̄_p ∂F⁻ᵀ/∂F (PSD-projected per point for Newton),
        and the non-local λ (Woᵀ V B)ᵀ (Woᵀ V B) with B_p = ∂ ln J_p / ∂y."""

        J = torch.linalg.det(F)
        l_bar = project_volumetric(self.volumetric, self.vol, torch.log(J))
        local = neo_hookean_tangent(F, self.mu, self.lam * 0.0) \
            - (self.lam * l_bar)[:, None, None] * swap_tangent(F)
        if project:
            local = project_psd(0.5 * (local + local.transpose(1, 2)))
        C = k_e * local
        B = self.basis.point_rows(torch.linalg.inv(F).transpose(1, 2))  # (K, D): ∂ ln J_p / ∂y
        WB = self.volumetric.T @ (self.vol[:, None] * B)  # (H, D)
        extra = (k_e * self.lam) * (WB.T @ WB)
        if self.tau is not None:
            # viscous: StVK on the rate without its λ term, + λ ḡ_p I (∂F/∂F) locally and the rank-H λ (Woᵀ V B_g)ᵀ(…)
            g_bar = project_volumetric(self.volumetric, self.vol, _half_trace_strain(F, self.c_ref))
            eye = torch.eye(9, dtype=F.dtype, device=F.device)
            visc = viscous_tangent(F, self.c_ref, self.mu, self.lam * 0.0, psd=project) \
                + (self.lam * g_bar)[:, None, None] * eye
            if project:
                visc = visc + (self.lam * g_bar).clamp(max=0.0).neg()[:, None, None] * eye
            C = C + k_d * visc
            Bg = self.basis.point_rows(F)  # (K, D): ∂ tr G_p / ∂y
            WBg = self.volumetric.T @ (self.vol[:, None] * Bg)
            extra = extra + (k_d * self.lam) * (WBg.T @ WBg)
        return self._assemble_hessian(y, C, project, extra=extra)

    def _assemble_hessian(self, y: Tensor, C: Tensor, project: bool, extra: Tensor | None = None) -> Tensor:
        H = self.mass_matrix + self.basis.hessian(self.vol[:, None, None] * C) \
            + self.step.energy_scale * self._external_hessian(y, project)
        if extra is not None:
            H = H + extra
        for H_c in (self._dashpot_hessian(y, project), self._friction_hessian(y)):
            if H_c is not None:
                H = H + H_c
        return 0.5 * (H + H.T)


def _half_trace_strain(F: Tensor, C_ref: Tensor) -> Tensor:
    """tr G = ½ (‖F‖² − tr C_ref), (K,): the trace of the Kelvin–Voigt strain measured from C_ref."""
    return 0.5 * ((F * F).sum(dim=(1, 2)) - C_ref.diagonal(dim1=1, dim2=2).sum(-1))


def friction_barriers(externals: Sequence) -> list:
    """The contact barriers among ``externals`` with Coulomb friction μ > 0."""
    return [e for e in externals if getattr(e, "kind", "body") == "contact" and getattr(e, "friction", 0.0) > 0]


def smoothed_friction(sigma: Tensor, eps: float) -> tuple[Tensor, Tensor, Tensor]:
    """The smoothed Coulomb law of incremental-potential contact at slip speeds σ (A,) > 0 with slip speed ε_v:
    (f₀(σ), φ = f₁(σ)/σ, σ φ'(σ)), each (A,), where f₁(σ) = 2σ/ε_v − σ²/ε_v² below ε_v and 1 above, f₀ its integral
    (f₀(0) = ε_v/3). The friction potential is c f₀(σ) per point, its force c φ u, its Hessian c (φ T + σφ' ûûᵀ)."""
    slow = sigma < eps
    f0 = torch.where(slow, sigma * sigma / eps - sigma**3 / (3.0 * eps * eps) + eps / 3.0, sigma)
    phi = torch.where(slow, 2.0 / eps - sigma / (eps * eps), 1.0 / sigma)
    sigma_dphi = torch.where(slow, -sigma / (eps * eps), -1.0 / sigma)
    return f0, phi, sigma_dphi


def reduced_point_hessian(hx: Tensor, b: Tensor) -> Tensor:
    """Σ_p (I₃ ⊗ b_p) H_p (I₃ ⊗ b_p)ᵀ (3L, 3L) for per-point blocks hx: (N, 3, 3) and LBS rows b: (N, L),
    over the points with a nonzero block only."""
    L = b.shape[1]
    active = hx.abs().amax(dim=(1, 2)) > 0
    if not bool(active.any()):
        return hx.new_zeros(3 * L, 3 * L)
    ba, ha = b[active], hx[active]
    P = ba.shape[0]
    # Hr[(a, b), (l, m)] = Σ_p h_p[a, b] b_p[l] b_p[m]: one matmul (9 × P)(P × L²)
    Hr = ha.reshape(P, 9).T @ (ba[:, :, None] * ba[:, None, :]).reshape(P, L * L)
    return Hr.reshape(3, 3, L, L).permute(0, 2, 1, 3).reshape(3 * L, 3 * L)
