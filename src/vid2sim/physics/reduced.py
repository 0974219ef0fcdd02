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
from typing import Callable, Sequence

import torch
from torch import Tensor

from vid2sim.physics.materials import det3, elastic_model


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
            Y = y.reshape(3, -1)
            return self.A + torch.einsum("al,pcl->pac", Y, self.G)
        K = self.A.shape[0]
        return self.A + (self.J @ y).reshape(K, 3, 3)

    def force(self, P: Tensor) -> Tensor:
        """Σ_p ∂vec(F_p)/∂y ᵀ vec(P_p) for P: (K, 3, 3) (already volume-weighted) → (D,)."""
        if self.G is not None:
            return torch.einsum("pac,pcl->al", P, self.G).reshape(-1)
        K = P.shape[0]
        return torch.einsum("pi,pid->d", P.reshape(K, 9), self.J)

    def hessian(self, C: Tensor) -> Tensor:
        """Σ_p ∂vec(F_p)/∂yᵀ C_p ∂vec(F_p)/∂y for C: (K, 9, 9) (volume-weighted) → (D, D)."""
        if self.G is not None:
            G = self.G
            K, _, L = G.shape
            # T[p, (c, a, b), m] = Σ_d C[p, (a, c), (b, d)] G[p, d, m]
            Cr = C.reshape(K, 3, 3, 3, 3).permute(0, 2, 1, 3, 4).reshape(K, 27, 3)
            T = torch.bmm(Cr, G)  # (K, 27, L)
            Hm = G.permute(2, 0, 1).reshape(L, K * 3) @ T.reshape(K * 3, 9 * L)  # (L, 3·3·L)
            return Hm.reshape(L, 3, 3, L).permute(1, 0, 2, 3).reshape(3 * L, 3 * L)
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


ExternalTotal = Callable[[Tensor, Tensor, float], tuple[Tensor, Tensor, Tensor]]


@dataclass
class StepProblem:
    """One implicit-Euler step's incremental potential, at fixed inputs.

    Φ(y) = ½ (y − ỹ)ᵀ M (y − ỹ) + Δt² (Σ_p v_p Ψ(F_p(y)) + E_ext(x(y), t)),   ỹ = y_prev + Δt ẏ_prev.
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
    dt: float
    y_prev: Tensor  # (D,)
    ydot_prev: Tensor  # (D,)

    # ---- pieces ------------------------------------------------------------------------------
    @property
    def y_pred(self) -> Tensor:
        return self.y_prev + self.dt * self.ydot_prev

    def positions(self, y: Tensor) -> Tensor:
        """x: (K, 3) cubature positions."""
        return self.X + self.b @ y.reshape(3, -1).T

    def mass_times(self, dy: Tensor) -> Tensor:
        """M dy for dy: (D,), with M = I₃ ⊗ Σ_p m_p b_p b_pᵀ (never formed here; differentiable)."""
        u = self.b @ dy.reshape(3, -1).T  # (K, 3)
        return ((self.mass[:, None] * u).T @ self.b).reshape(-1)

    @functools.cached_property
    def mass_matrix(self) -> Tensor:
        """(D, D) reduced mass matrix (constant during a step; computed once)."""
        Mb = (self.b * self.mass[:, None]).T @ self.b
        return torch.block_diag(Mb, Mb, Mb)

    def _external_energy(self, x: Tensor) -> Tensor:
        e = x.new_zeros(())
        for ext in self.externals:
            e = e + ext.energy(x, self.mass, self.t)
        return e

    def _external_gradient(self, x: Tensor) -> Tensor:
        g = torch.zeros_like(x)
        for ext in self.externals:
            g = g + ext.gradient(x, self.mass, self.t)
        return g

    def potential(self, y: Tensor) -> tuple[Tensor, bool]:
        """(Φ(y), valid) where valid is False if any cubature point is inverted (det F ≤ 0)."""
        F = self.basis.deformation_gradient(y)
        if not bool((det3(F) > 0).all()):
            return y.new_full((), float("inf")), False
        psi = elastic_model(self.model)[0](F, self.mu, self.lam)
        e_ext = self._external_energy(self.positions(y))
        dy = y - self.y_pred
        phi = 0.5 * dy @ self.mass_times(dy) + self.dt**2 * ((self.vol * psi).sum() + e_ext)
        return phi, True

    def gradient(self, y: Tensor) -> Tensor:
        """∇Φ(y): (D,). A differentiable expression of every input (used by the adjoint)."""
        F = self.basis.deformation_gradient(y)
        P = elastic_model(self.model)[1](F, self.mu, self.lam)
        gx = self._external_gradient(self.positions(y))
        f_ext = (gx.T @ self.b).reshape(-1)
        f_el = self.basis.force(self.vol[:, None, None] * P)
        return self.mass_times(y - self.y_pred) + self.dt**2 * (f_el + f_ext)

    def hessian(self, y: Tensor, project: bool = True) -> Tensor:
        """∇²Φ(y): (D, D); per-point elastic and external blocks projected to PSD when ``project``
        (Newton), exact when not (the adjoint)."""
        from vid2sim.physics.materials import project_tangent_psd

        F = self.basis.deformation_gradient(y)
        C = elastic_model(self.model)[2](F, self.mu, self.lam)
        if project:
            C = project_tangent_psd(self.model, F, C, self.mu, self.lam)
        x = self.positions(y)
        hx = x.new_zeros(x.shape[0], 3, 3)
        for ext in self.externals:
            hx = hx + ext.hessian(x, self.mass, self.t, project=project)
        H = self.mass_matrix + self.dt**2 * (
            self.basis.hessian(self.vol[:, None, None] * C) + self._reduced_point_hessian(hx)
        )
        return 0.5 * (H + H.T)

    def _reduced_point_hessian(self, hx: Tensor) -> Tensor:
        """Σ_p (I₃ ⊗ b_p) H_p (I₃ ⊗ b_p)ᵀ for per-point blocks hx: (K, 3, 3), over active points only."""
        L = self.b.shape[1]
        active = hx.abs().amax(dim=(1, 2)) > 0
        if not bool(active.any()):
            return hx.new_zeros(3 * L, 3 * L)
        ba, ha = self.b[active], hx[active]
        Hr = torch.einsum("pab,pl,pm->albm", ha, ba, ba)
        return Hr.reshape(3 * L, 3 * L)
