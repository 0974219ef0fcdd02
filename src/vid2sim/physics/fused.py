"""Fused kernels of the reduced implicit step: the common case in few, large tensor operations.

The reduced simulator is small (D = 12H ≈ 132 unknowns, K ≈ 500 cubature points), so on a GPU every torch
operation costs a launch (≈ 5–10 µs) whatever its size, and the per-term code of
:class:`~vid2sim.physics.reduced.StepProblem` issues hundreds per Newton iteration. This module evaluates the
same incremental potential, its gradient, its exact Hessian and the adjoint's products for the **common
case** — an elastic Neo-Hookean material with Kelvin–Voigt damping (or none), the exact closed-form
F-basis, the pointwise volumetric term, gravity and contact barriers without a contact layer or dashpot (friction
on static floors only) —
with every per-point quantity computed for all points at once and the material's constants folded into
per-point coefficient vectors made once per step length (:class:`PointCoefficients`). Whatever else a step
needs goes through the per-term code, which stays the reference (``SimConfig.fused_kernels=False``).

Layouts (as in :mod:`vid2sim.physics.reduced`; K points, L = 4H, D = 3L):

- ``y`` (D,) row-major, ``Y = y.view(3, L)``;
- Newton's evaluations (few points, many calls) keep deformation gradients **transposed and point-major**,
  ``Ft: (K, 3, 3)`` with ``Ft[p, c, a] = F_p[a, c]``: one ``addmm`` of the basis rows ``G_rows[(p, c), l] =
  G[p, c, l]`` gives them, ``Ft = I + G_rows Yᵀ``, and a stress kept the same way, ``Pt[p, c, a] = P_p[a, c]``,
  gives the force as one product ``Pt_rowsᵀ G_rows``;
- the Hessians and the adjoint (many points: a batch of steps) keep per-point quantities **point-last**,
  ``F: (3, 3, n)`` with ``F[a, c, p] = F_p[a, c]``, from the basis columns ``G_soa_cols[l, (c, p)]``, so that every
  elementwise product runs along the points (small batched matrix products and inner dimensions of 3 are slow on
  a CPU); tangents are ``T: (3, 3, 3, 3, n)`` with ``T[i, k, j, l, p] = ∂P_ij/∂F_kl``.

Damped Neo-Hookean terms (materials.neo_hookean_viscous_*; v the cubature weights, k_e = h²/a₀², k_d = hτ/a₀):

    v [k_e Ψ_NH(F; μ, λ) + k_d ψ(G; μ, λ)],   G = ½ (FᵀF − C_ref),
    Pᵀ = v [(k_e μ I + k_d S) Fᵀ + k_e (λ ln J − μ) F⁻¹],   S = 2μ G + λ tr G I.

The adjoint. A converged step's gradients to its inputs are −λᵀ ∂∇Φ/∂θ with λ = H⁻¹ ∂L/∂y*, and every one of
them is a fixed linear map of λ: through ŷ a multiple of Mλ; to μ, λ and τ three rows E (3, D); to the previous
states, through the viscous reference metric C_ref, a per-point 9 × 9 map of dF = ∂F/∂y λ (``metric_adjoint_map``).
:class:`AdjointBatch` makes these maps and the Hessians of a rollout's steps in batches when the backward pass
first needs them, so that each step's own backward is a solve and a few products.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.external import Floor, Gravity, energy_and_gradient
from vid2sim.physics.integrators import BDFStep
from vid2sim.physics.reduced import reduced_point_hessian, smoothed_friction

#: Temporary memory (bytes) one batch of adjoint data may take; longer rollouts are done in several batches.
ADJOINT_BATCH_BYTES = 1 << 27
#: On a CPU the Hessians' per-point products are made for as many steps at once as fit in this many bytes (a
#: cache's worth: larger blocks are slower there); on a GPU for the whole batch.
CPU_BLOCK_BYTES = 1 << 22


# ---- per-point coefficients --------------------------------------------------------------------

@dataclass
class PointCoefficients:
    """Per-point, volume-weighted factors of one step's damped Neo-Hookean terms (v the cubature weights,
    k_e and k_d the step's weights, h / a₀ its length over its first BDF coefficient):
    α = v k_d μ, β₀ = v k_e μ, β₁ = ½ v k_d λ, γ = v k_e λ.

    Attributes:
        flat: the (K,) vectors 'alpha', 'beta0', 'beta1', 'gamma', 'vk_e' (v k_e), 'vk_d' (v k_d), 'tau_mu'
            (−(h/a₀) v μ) and 'tau_lam' (−½ (h/a₀) v λ): the point-last kernels' factors.
        alpha, gamma, neg_beta0: (K, 1, 1) α, γ, −β₀ (the point-major stress kernel's).
        beta0, beta1: (K, 1) β₀, β₁.
        lin, quad: (K, 11) the energy Σ_p f·(lin + quad ∘ f) of the per-point features f = [tr(C − C_ref), ln J,
            vec(C − C_ref)]: lin = [½β₀, −β₀, 0 …], quad = [¼β₁, ½γ, ¼α …] (:func:`energy_offset` adds the rest).
        beta0_eye: (9K,) vec(β₀ I) per point (Σ β₀ tr C_ref as one product); offset: 0-d −3/2 Σ β₀.
        k_e, k_d: the step's weights of the potential energy and of the viscous potential (k_d a float or 0-d).
    """

    flat: dict[str, Tensor]
    alpha: Tensor
    beta0: Tensor
    beta1: Tensor
    gamma: Tensor
    neg_beta0: Tensor
    lin: Tensor
    quad: Tensor
    beta0_eye: Tensor
    offset: Tensor
    k_e: float
    k_d: float | Tensor

    @classmethod
    def make(cls, vol: Tensor, mu: Tensor, lam: Tensor, k_e: float, k_d: float | Tensor,
             h_over_a0: float) -> "PointCoefficients":
        """From the cubature weights ``vol: (K,)``, 0-d μ and λ, and the step's k_e, k_d and h / a₀."""
        K = vol.shape[0]
        flat = {"alpha": vol * (k_d * mu), "beta0": vol * (k_e * mu), "beta1": vol * (0.5 * k_d * lam),
                "gamma": vol * (k_e * lam), "vk_e": vol * k_e, "vk_d": vol * k_d, "tau_mu": vol * (-h_over_a0 * mu),
                "tau_lam": vol * (-0.5 * h_over_a0 * lam)}
        alpha, beta0, beta1, gamma = (flat[k].view(K, 1) for k in ("alpha", "beta0", "beta1", "gamma"))
        lin = torch.cat([0.5 * beta0, -beta0, torch.zeros_like(beta0).expand(K, 9)], dim=1)
        quad = torch.cat([0.25 * beta1, 0.5 * gamma, (0.25 * alpha).expand(K, 9)], dim=1)
        eye = torch.eye(3, dtype=vol.dtype, device=vol.device).view(1, 9)
        return cls(flat, alpha.view(K, 1, 1), beta0, beta1, gamma.view(K, 1, 1), (-beta0).view(K, 1, 1), lin, quad,
                   (beta0 * eye).view(-1), -1.5 * beta0.sum(), k_e, k_d)


def _flat_coefficients(parts: Sequence[PointCoefficients]) -> dict[str, Tensor]:
    """The point-last factors of several point sets one after the other (n = Σ K,)."""
    if len(parts) == 1:
        return parts[0].flat
    return {k: torch.cat([p.flat[k] for p in parts]) for k in parts[0].flat}


# ---- Newton's kernels (point-major, transposed F) ---------------------------------------------------

def point_state(Ft: Tensor, C_ref: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(cof, J, C − C_ref, tr(C − C_ref)) of transposed deformation gradients ``Ft: (K, 3, 3)`` and reference
    metrics ``C_ref: (K, 3, 3)``: cof = cof(Fᵀ) = J F⁻¹ (K, 3, 3) (rows: cross(row i+1, row i+2)), J = det F
    (K, 1, 1), C = FᵀF, the trace (K, 1)."""
    cof = torch.linalg.cross(Ft.roll(-1, 1), Ft.roll(-2, 1))
    J = (Ft * cof).sum((1, 2), keepdim=True).div_(3.0)  # each row's triple product is J
    diff = torch.baddbmm(C_ref, Ft, Ft.transpose(1, 2), beta=-1.0)
    return cof, J, diff, diff.diagonal(dim1=1, dim2=2).sum(-1, keepdim=True)


def _stress_factor(diff: Tensor, tr: Tensor, coef: PointCoefficients) -> Tensor:
    """Dm = v (k_e μ I + k_d S) (K, 3, 3) with S = μ (C − C_ref) + ½ λ tr(C − C_ref) I the viscous second
    Piola–Kirchhoff stress (= 2μ G + λ tr G I)."""
    Dm = diff * coef.alpha
    Dm.diagonal(dim1=1, dim2=2).add_(torch.addcmul(coef.beta0, coef.beta1, tr))
    return Dm


def damped_neo_hookean_stress(Ft: Tensor, C_ref: Tensor, coef: PointCoefficients, energy: bool = True
                              ) -> tuple[Tensor, Tensor | None, Tensor]:
    """The volume-weighted, step-weighted stress and energy of every point in one pass.

    Args:
        Ft: (K, 3, 3) transposed deformation gradients (``Ft[p, c, a] = F_p[a, c]``).
        C_ref: (K, 3, 3) the viscous reference metric (the identity when undamped).
        coef: the step's :class:`PointCoefficients`.
        energy: also return the energy.
    Returns:
        (Pt (K, 3, 3): the transposed stresses v (k_e P_NH + k_d P_v); the energy Σ_p v (k_e Ψ_NH + k_d ψ) (0-d)
        without its constant (:func:`energy_offset`), or None; J (K, 1, 1)). Where J ≤ 0 the values are not
        finite; callers check J.
    """
    cof, J, diff, tr = point_state(Ft, C_ref)
    logj = J.log()
    Pt = torch.baddbmm(torch.addcmul(coef.neg_beta0, coef.gamma, logj).div_(J) * cof,
                       _stress_factor(diff, tr, coef), Ft)
    if not energy:
        return Pt, None, J
    f = torch.cat([tr, logj.view(-1, 1), diff.view(-1, 9)], dim=1)
    return Pt, (f * torch.addcmul(coef.lin, coef.quad, f)).sum(), J


def energy_offset(C_ref: Tensor, coef: PointCoefficients) -> Tensor:
    """0-d Σ_p ½β₀ (tr C_ref − 3): the constant the energy of :func:`damped_neo_hookean_stress` leaves out
    (C_ref: (K, 3, 3))."""
    return torch.dot(coef.beta0_eye, C_ref.reshape(-1)).mul(0.5).add_(coef.offset)


# ---- the Hessians' and the adjoint's kernels (point-last F) --------------------------------------------

def soa_point_state(F: Tensor, C_ref: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(cof(F) = J F⁻ᵀ (3, 3, n), J (n,), C − C_ref (3, 3, n), tr(C − C_ref) (n,)) of point-last deformation gradients
    F: (3, 3, n) (contiguous) and metrics C_ref: (3, 3, n), C = FᵀF."""
    n = F.shape[2]
    cof = torch.linalg.cross(F.roll(-1, 0), F.roll(-2, 0), dim=1)
    J = (F * cof).sum((0, 1)).div_(3.0)
    diff = (F.view(3, 3, 1, n) * F.view(3, 1, 3, n)).sum(0).sub_(C_ref)
    return cof, J, diff, diff.diagonal(dim1=0, dim2=1).sum(-1)


def _soa_stress_factor(diff: Tensor, tr: Tensor, c: dict[str, Tensor]) -> Tensor:
    """Dm = α (C − C_ref) + (β₀ + β₁ tr(C − C_ref)) I, point-last (3, 3, n) (:func:`_stress_factor`)."""
    Dm = diff * c["alpha"]
    Dm.diagonal(dim1=0, dim2=1).add_(torch.addcmul(c["beta0"], c["beta1"], tr).unsqueeze(-1))
    return Dm


def damped_neo_hookean_tangent(F: Tensor, C_ref: Tensor, c: dict[str, Tensor],
                               state: tuple[Tensor, Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """The exact volume-weighted, step-weighted tangent v (k_e ∂P_NH/∂F + k_d ∂P_v/∂F) of every point.

    With A = F⁻ᵀ and c = μ − λ ln J it is v k_e [μ δ_ik δ_jl + c A_il A_kj + λ A_ij A_kl] + v k_d [δ_ik S_lj +
    μ F_il F_kj + μ (FFᵀ)_ik δ_lj + λ F_ij F_kl] (:func:`~vid2sim.physics.materials.neo_hookean_viscous_tangent`):
    six outer products, each one broadcast product along the points.

    Args:
        F: (3, 3, n) point-last deformation gradients (contiguous); C_ref: (3, 3, n) the viscous reference
            metrics (the identity when undamped); c: the (n,) factors (:attr:`PointCoefficients.flat`);
            state: their :func:`soa_point_state`, if made.
    Returns:
        T: (3, 3, 3, 3, n) with ``T[i, k, j, l, p] = ∂P_ij/∂F_kl`` (contiguous).
    """
    n = F.shape[2]
    cof, J, diff, tr = state if state is not None else soa_point_state(F, C_ref)
    A = cof / J  # F⁻ᵀ
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    FFt = (F.view(3, 1, 3, n) * F.view(1, 3, 3, n)).sum(2)
    swap = torch.addcmul(c["beta0"], c["gamma"], J.log(), value=-1.0)  # v k_e (μ − λ ln J)
    out = torch.mul((A * c["gamma"]).view(3, 1, 3, 1, n), A.view(1, 3, 1, 3, n), out=F.new_empty(3, 3, 3, 3, n))
    out.addcmul_((F * (2.0 * c["beta1"])).view(3, 1, 3, 1, n), F.view(1, 3, 1, 3, n))  # λ-terms: V_ij V_kl
    out.addcmul_((A * swap).view(3, 1, 1, 3, n), A.view(1, 3, 3, 1, n))  # V_il V_kj
    out.addcmul_((F * c["alpha"]).view(3, 1, 1, 3, n), F.view(1, 3, 3, 1, n))
    out.addcmul_(eye.view(3, 3, 1, 1, 1), _soa_stress_factor(diff, tr, c).view(1, 1, 3, 3, n))  # δ_ik Dm_jl
    out.addcmul_((FFt * c["alpha"]).view(3, 3, 1, 1, n), eye.view(1, 1, 3, 3, 1))  # α (FFᵀ)_ik δ_jl
    return out


def material_adjoint_rows(F: Tensor, state: tuple[Tensor, Tensor, Tensor, Tensor], c: dict[str, Tensor]) -> Tensor:
    """Per point the matrices B_θ (3, 3, 3, n) (θ = μ, λ, τ; point-last) with −λᵀ ∂∇Φ/∂θ = Σ_p ⟨B_θ,p, dF_p⟩,
    dF = ∂F/∂y λ. From ∂P/∂μ = k_e (F − F⁻ᵀ) + k_d F (C − C_ref), ∂P/∂λ = k_e ln J F⁻ᵀ + ½ k_d tr(C − C_ref) F
    and ∂P/∂τ = (h/a₀) F S: B_μ = v k_e (F⁻ᵀ − F) − v k_d F (C − C_ref), B_λ = −½ v k_d tr(C − C_ref) F −
    v k_e ln J F⁻ᵀ, B_τ = −(h/a₀) v F (μ (C − C_ref) + ½ λ tr(C − C_ref) I)."""
    cof, J, diff, tr = state
    n = F.shape[2]
    A = cof / J
    Fd = (F.view(3, 3, 1, n) * diff.view(1, 3, 3, n)).sum(1)  # F (C − C_ref)
    trF = F * tr
    b_mu = torch.addcmul((A - F) * c["vk_e"], Fd, c["vk_d"], value=-1.0)
    b_lam = torch.addcmul(trF * (-0.5 * c["vk_d"]), A * J.log(), c["vk_e"], value=-1.0)
    b_tau = torch.addcmul(Fd * c["tau_mu"], trF, c["tau_lam"])
    return torch.stack([b_mu, b_lam, b_tau])


def metric_adjoint_map(F: Tensor, F_prev: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """The map dF ↦ R = 2c F_prev Q per point, where Q = ½α (W + Wᵀ) + β₁ tr W I, W = FᵀdF: the viscous term's
    dependence on C_ref passes λ on to a previous state F_prev through C_ref = Σ c F_prevᵀF_prev, whose gradient
    to F_prev is 2c F_prev Q (a = cα, b = 2cβ₁, (n,)).

    R[e, c] = Σ_xy (a δ_yc (F_prev Fᵀ)[e, x] + a F_prev[e, y] F[x, c] + b F_prev[e, c] F[x, y]) dF[x, y].

    Args:
        F, F_prev: (3, 3, n) point-last, contiguous.
    Returns:
        (3, 3, 3, 3, n) with ``[e, c, x, y, p]`` the coefficient of dF[x, y] in R[e, c].
    """
    n = F.shape[2]
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    N = (F_prev.view(3, 1, 3, n) * F.view(1, 3, 3, n)).sum(2)  # F_prev Fᵀ
    out = torch.mul((F_prev * b).view(3, 3, 1, 1, n), F.view(1, 1, 3, 3, n), out=F.new_empty(3, 3, 3, 3, n))
    out.addcmul_((F_prev * a).view(3, 1, 1, 3, n), F.transpose(0, 1).reshape(1, 3, 3, 1, n))
    out.addcmul_((N * a).view(3, 1, 3, 1, n), eye.view(1, 3, 1, 3, 1))
    return out


# ---- one frame's constants ---------------------------------------------------------------------

def fused_supported(model: str, structured: bool, plastic: bool, volumetric: Tensor | None, dashpot: Tensor | None,
                    layer_k: Tensor | None, externals: Sequence) -> bool:
    """Whether a step can use the fused kernels: elastic Neo-Hookean, the structured F-basis, the pointwise
    volumetric term, no contact dashpot or layer, friction on static floors only, and no body force but gravity."""
    body_ok = all(isinstance(e, Gravity) for e in externals if getattr(e, "kind", "body") == "body")
    frictionless = all(getattr(e, "friction", 0.0) == 0.0 for e in externals if type(e) is not Floor)
    return (model == "neo_hookean" and structured and not plastic and volumetric is None and dashpot is None
            and layer_k is None and body_ok and frictionless)


@dataclass
class FusedFrame:
    """The constants of a frame's substeps (one basis, material and set of points), detached.

    Attributes:
        G_rows: (3K, L) the F-basis point-major, ``G_rows[(p, c), l] = G[p, c, l]``; eye_rows: (3K, 3) the identity's
            rows per point (Ft = I + G_rows Yᵀ).
        G_soa_cols: (L, 3K) point-last, ``[l, (c, p)]``; G_soa_rows: (3K, L) its transpose; G_soa: (3, L, K)
            ``[c, l, p]``; eye_soa: (3, 3K) the identity's columns (F = I + Y G_soa_cols).
        vol: (K,) cubature weights; mu, lam: 0-d Lamé parameters; tau: 0-d retardation time or None.
        mass_block: (L, L) Σ_p m_p b_p b_pᵀ; mass_matrix: (D, D) I₃ ⊗ mass_block.
        tracked_cols: (L, K + Nc) LBS rows of the cubature and contact points, transposed (the points
            Newton's convergence test watches).
        gravity: (e₀ (), f (3, L)) with the gravity energy e₀ − f·y (zeros without gravity).
        contact_X, contact_b, contact_w: (Nc, 3), (Nc, L), (Nc,) the contact points' rest positions, LBS rows and
            weights; contact_cols: (L, Nc) the rows transposed.
        floors: [(z_c − h (Nc,), 2k)] of the :class:`~vid2sim.physics.external.Floor` barriers (only the
            height of a point matters to them); barriers: the other contact energies.
        frictions: [(z_c − h (Nc,), 2k μ, ε_v)] of the floors with friction μ > 0.
    """

    G_rows: Tensor
    eye_rows: Tensor
    G_soa_cols: Tensor
    G_soa_rows: Tensor
    G_soa: Tensor
    eye_soa: Tensor
    vol: Tensor
    mu: Tensor
    lam: Tensor
    tau: Tensor | None
    mass_block: Tensor
    mass_matrix: Tensor
    tracked_cols: Tensor
    gravity: tuple[Tensor, Tensor]
    contact_X: Tensor
    contact_b: Tensor
    contact_w: Tensor
    contact_cols: Tensor
    floors: list[tuple[Tensor, float]]
    barriers: list
    frictions: list[tuple[Tensor, float, float]] = field(default_factory=list)
    _coefficients: dict = field(default_factory=dict)
    _metrics: list = field(default_factory=list)

    @classmethod
    def build(cls, X: Tensor, vol: Tensor, mass: Tensor, b: Tensor, G: Tensor, mu: Tensor, lam: Tensor,
              tau: Tensor | None, externals: Sequence, contact_X: Tensor | None, contact_b: Tensor | None,
              contact_w: Tensor | None) -> "FusedFrame":
        """From the step's inputs (shapes of :class:`~vid2sim.physics.reduced.StepProblem`; G: (K, 3, L))."""
        K, _, L = G.shape
        X, vol, mass, b, G = (t.detach() for t in (X, vol, mass, b, G))
        eye = torch.eye(3, dtype=X.dtype, device=X.device)
        G_soa = G.permute(1, 2, 0).contiguous()  # [c, l, p]
        G_soa_cols = G_soa.transpose(0, 1).reshape(L, 3 * K)
        mass_block = (b * mass[:, None]).T @ b
        if contact_b is None:
            contact_X, contact_b, contact_w = X, b, torch.ones_like(mass)
        contact_X, contact_b, contact_w = contact_X.detach(), contact_b.detach(), contact_w.detach()
        tracked = b if contact_b is b else torch.cat([b, contact_b])
        acc = torch.tensor([0.0, 0.0, 0.0] + [a for e in externals if isinstance(e, Gravity) for a in e.acceleration],
                           dtype=X.dtype, device=X.device).view(-1, 3).sum(0)
        gravity = (-(mass * (X @ acc)).sum(), acc[:, None] * (mass @ b)[None, :])
        contact = [e for e in externals if getattr(e, "kind", "body") == "contact"]
        floors = [(contact_X[:, 2] - e.height, 2.0 * e.stiffness) for e in contact if type(e) is Floor]
        return cls(
            G.reshape(3 * K, L),
            eye.repeat(K, 1),
            G_soa_cols,
            G_soa_cols.T.contiguous(),
            G_soa,
            eye.repeat_interleave(K, dim=1),
            vol,
            mu.detach(),
            lam.detach(),
            None if tau is None else tau.detach(),
            mass_block,
            torch.block_diag(mass_block, mass_block, mass_block),
            tracked.T.contiguous(),
            gravity,
            contact_X,
            contact_b,
            contact_w,
            contact_b.T.contiguous(),
            floors,
            [e for e in contact if type(e) is not Floor],
            [(contact_X[:, 2] - e.height, 2.0 * e.stiffness * e.friction, e.friction_velocity)
             for e in contact if type(e) is Floor and e.friction > 0],
        )

    @property
    def num_points(self) -> int:
        return self.vol.shape[0]

    def coefficients(self, step: BDFStep) -> tuple[PointCoefficients, Tensor, Tensor]:
        """(the :class:`PointCoefficients`, the constant part of the gradient −k_e f_gravity (3, L), the gravity
        energy's constant k_e e₀ (0-d)) of a step, made once per step length and BDF coefficients."""
        key = (step.h, step.a0)
        if key not in self._coefficients:
            k_e = step.energy_scale
            k_d = 0.0 if self.tau is None else step.damping_scale(self.tau)
            coef = PointCoefficients.make(self.vol, self.mu, self.lam, k_e, k_d, step.h / step.a0)
            self._coefficients[key] = (coef, self.gravity[1] * -k_e, k_e * self.gravity[0])
        return self._coefficients[key]

    def deformation(self, y: Tensor) -> Tensor:
        """Ft: (K, 3, 3) transposed deformation gradients at the row-major state y: (D,)."""
        return torch.addmm(self.eye_rows, self.G_rows, y.view(3, -1).t()).view(-1, 3, 3)

    def soa_deformations(self, Y: Tensor) -> Tensor:
        """F: (3, 3, S K) point-last deformation gradients of S states Y: (S, 3, L) (contiguous, state-major points)."""
        S, _, L = Y.shape
        K = self.num_points
        F = torch.addmm(self.eye_soa, Y.view(3 * S, L), self.G_soa_cols) if S == 1 else \
            torch.mm(Y.view(3 * S, L), self.G_soa_cols).view(S, 9, K).add_(self.eye_soa.view(1, 9, K))
        return F.view(S, 3, 3, K).permute(1, 2, 0, 3).reshape(3, 3, S * K)

    def metric(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """(Ft, C = FᵀF) (K, 3, 3) at y; the last three states asked for are remembered (a step's C_ref is made of
        its two previous states, and its converged state is checked before the next step starts: the next step
        then finds all it needs)."""
        for known, Ft, C in self._metrics:
            if known is y:
                return Ft, C
        Ft = self.deformation(y)
        C = torch.bmm(Ft, Ft.transpose(1, 2))
        self._metrics = [*self._metrics[-2:], (y, Ft, C)]
        return Ft, C


# ---- one step ------------------------------------------------------------------------------------

@dataclass
class _FloorFriction:
    """A static floor's friction in one step (the potential of :class:`~vid2sim.physics.reduced.StepProblem`): the
    floor's normal is e_z, so the slip of the A points in contact at the start of the step is the horizontal part
    of their BDF velocity, u = (a₀/h)(x_xy − x_ref) (A, 2).

    Attributes:
        b: (A, L) the points' LBS rows; x0: (A, 2) their rest x, y; x_ref: (A, 2) the BDF reference position;
        c: (A,) k_e μ λ with the normal force λ = 2k w (h − z_λ) at the state y_λ the step takes it at (the start
        of the step, or the simulator's fixed point); eps: ε_v; rate: a₀/h.
    """

    b: Tensor
    x0: Tensor
    x_ref: Tensor
    c: Tensor
    eps: float
    rate: float

    @classmethod
    def make(cls, frame: "FusedFrame", step: BDFStep, offset: Tensor, k2_mu: float, eps: float, y_prev: Tensor,
             y_prev2: Tensor | None, y_lag: Tensor) -> "_FloorFriction | None":
        """From the frame's floor (offset z_c − h (Nc,), 2kμ, ε_v), the states before the step and the state
        y_λ: (D,) of the normal force; None when no contact point is below the floor at y_λ."""
        a0, a1, a2 = step.coefficients
        Yp = y_prev.view(3, -1)
        s_lag = torch.addmv(offset, frame.contact_b, y_lag.view(3, -1)[2])
        index = (s_lag < 0).nonzero()[:, 0]
        if index.numel() == 0:
            return None
        b = frame.contact_b[index]
        x0 = frame.contact_X[index, :2]
        x_ref = (a1 / a0) * torch.addmm(x0, b, Yp[:2].t())
        if step.needs_history:
            x_ref = x_ref + (a2 / a0) * torch.addmm(x0, b, y_prev2.view(3, -1)[:2].t())
        c = (step.energy_scale * k2_mu) * frame.contact_w[index] * (-s_lag[index])
        return cls(b, x0, x_ref, c, float(eps), a0 / step.h)

    def _slip(self, Y: Tensor) -> tuple[Tensor, Tensor]:
        """(u (A, 2), σ (A,)) at the state Y: (3, L)."""
        u = (torch.addmm(self.x0, self.b, Y[:2].t()) - self.x_ref).mul_(self.rate)
        return u, torch.sqrt((u * u).sum(1) + torch.finfo(u.dtype).tiny)

    def add_gradient(self, Y: Tensor, grad: Tensor, energy: bool) -> tuple[Tensor, float] | None:
        """Add ∂D_f/∂Y to grad: (3, L) in place; returns D_f as a part (0-d, factor), or None without ``energy``."""
        u, sigma = self._slip(Y)
        f0, phi, _ = smoothed_friction(sigma, self.eps)
        grad[:2].addmm_((self.c * phi).unsqueeze(1).mul(u).t(), self.b)
        return (torch.dot(self.c, f0), 1.0 / self.rate) if energy else None

    def add_hessian(self, Y: Tensor, H: Tensor) -> None:
        """Add ∂²D_f/∂y² to H: (D, D) in place: per point (a₀/h) c [φ I₂ + σ φ'(σ) ûûᵀ] in the x, y rows."""
        u, sigma = self._slip(Y)
        _, phi, sigma_dphi = smoothed_friction(sigma, self.eps)
        u_hat = u / sigma.unsqueeze(1)
        block = u.new_zeros(u.shape[0], 3, 3)  # the z row and column stay zero: the slip is horizontal
        xy = block[:, :2, :2]
        xy.copy_((sigma_dphi.view(-1, 1, 1) * u_hat.unsqueeze(2)) * u_hat.unsqueeze(1))
        xy.diagonal(dim1=1, dim2=2).add_(phi.unsqueeze(1))
        xy.mul_((self.rate * self.c).view(-1, 1, 1))
        H += reduced_point_hessian(block, self.b)


@dataclass
class StepAdjoint:
    """What a step's backward pass needs (made by :class:`AdjointBatch`).

    Attributes:
        hessian: (D, D) the exact Hessian at the converged state where it is indefinite (then the adjoint solves
            with LU), else None; factor: its Cholesky factor where it is positive definite, else None.
        rows: (3, D) E: the gradients to (μ, λ, τ) are E λ.
        metric_map: (2, 3, 3, 3, 3, K) the maps of :func:`metric_adjoint_map` to the previous state and the one
            before (2c folded in), or None when undamped.
        history: (4, 1, 1) the factors of Mλ in the gradients to (y_prev, ẏ_prev, y_prev2, ẏ_prev2):
            (a₁/a₀, h a₁/a₀², a₂/a₀, h a₂/a₀²) (ŷ's coefficients).
    """

    hessian: Tensor | None
    factor: Tensor | None
    rows: Tensor
    metric_map: Tensor | None
    history: Tensor


class FusedStep:
    """One implicit step's incremental potential (that of :class:`~vid2sim.physics.reduced.StepProblem`) on the
    fused kernels: Φ and ∇Φ, the exact Hessian, and the adjoint.

    Args:
        frame: the frame's constants.
        step: the BDF step; t: the time at its end.
        y_prev, y_prev2: (D,) the states at the start of the step and one step earlier (None without history).
        y_pred: (D,) the inertial target ŷ.
        friction_state: (D,) the state y_λ friction's normal force is taken at (None: y_prev).
    """

    def __init__(self, frame: FusedFrame, step: BDFStep, t: float, y_prev: Tensor, y_prev2: Tensor | None,
                 y_pred: Tensor, friction_state: Tensor | None = None) -> None:
        self.frame, self.step, self.t = frame, step, t
        self.Y_pred = y_pred.view(3, -1)
        self.coef, self.force_constant, constant = frame.coefficients(step)
        self.k_e = step.energy_scale
        self.batch: AdjointBatch | None = None
        self.solution: Tensor | None = None
        self.adjoint_data: StepAdjoint | None = None
        a0, a1, a2 = step.coefficients
        self.previous: list[Tensor] = []  # Ft (K, 3, 3) of the states C_ref is made of
        if frame.tau is None:
            self.C_ref = frame.eye_rows.view(-1, 3, 3)
        else:
            Ft1, C1 = frame.metric(y_prev)
            self.previous.append(Ft1)
            self.C_ref = (a1 / a0) * C1
            if step.needs_history:
                Ft2, C2 = frame.metric(y_prev2)
                self.previous.append(Ft2)
                self.C_ref.add_(C2, alpha=a2 / a0)
        y_lag = y_prev if friction_state is None else friction_state
        frictions = (_FloorFriction.make(frame, step, *f, y_prev, y_prev2, y_lag) for f in frame.frictions)
        self.frictions = [f for f in frictions if f is not None]
        # Φ's constant parts: Σ ½β₀ (tr C_ref − 3) + k_e e₀ + f·ŷ (the gravity term f·y is written f·(y − ŷ) + f·ŷ)
        self.constants = [
            energy_offset(self.C_ref, self.coef),
            torch.dot(self.force_constant.view(-1), y_pred),
            constant,
        ]

    # ---- Φ and ∇Φ --------------------------------------------------------------------------------
    def _barriers(self, Y: Tensor, grad: Tensor, energy: bool) -> list[tuple[Tensor, float]]:
        """Add k_e ∂E_contact/∂Y to grad: (3, L) in place at the state Y: (3, L); returns k_e E_contact as parts
        (0-d tensor, factor) (none without ``energy``)."""
        fr, k_e = self.frame, self.k_e
        parts = []
        for offset, k2 in fr.floors:  # E = k Σ w min(0, s)², s = z − h
            q = torch.addmv(offset, fr.contact_b, Y[2]).clamp_max_(0.0)
            wq = fr.contact_w * q
            grad[2].addmv_(fr.contact_cols, wq, alpha=k2 * k_e)
            if energy:
                parts.append((torch.dot(wq, q), 0.5 * k2 * k_e))
        if fr.barriers:
            x = torch.addmm(fr.contact_X, fr.contact_b, Y.t())
            for ext in fr.barriers:
                e_i, g_i = energy_and_gradient(ext, x, fr.contact_w, self.t)
                grad.addmm_(g_i.t(), fr.contact_b, alpha=k_e)
                if energy:
                    parts.append((e_i, k_e))
        for friction in self.frictions:
            part = friction.add_gradient(Y, grad, energy)
            if part is not None:
                parts.append(part)
        return parts

    def evaluate(self, y: Tensor, energy: bool = True) -> tuple[list[tuple[Tensor, float]], Tensor, Tensor]:
        """(Φ as parts (0-d tensor, factor): Φ = Σ factor · part (none without ``energy``), ∇Φ (D,), J (K, 1, 1))
        at y: (D,); Φ and ∇Φ are not finite where J ≤ 0."""
        fr = self.frame
        Y = y.view(3, -1)
        Ft = torch.addmm(fr.eye_rows, fr.G_rows, Y.t()).view(-1, 3, 3)
        Pt, e_el, J = damped_neo_hookean_stress(Ft, self.C_ref, self.coef, energy)
        dY = Y - self.Y_pred
        base = torch.addmm(self.force_constant, dY, fr.mass_block)  # M dy + f
        grad = torch.addmm(base, Pt.view(-1, 3).t(), fr.G_rows)
        contact = self._barriers(Y, grad, energy)
        if not energy:
            return [], grad.view(-1), J
        inertia = (dY * base.add_(self.force_constant)).sum()  # dy·(M dy + 2f) = 2 (½ dyᵀM dy + f·dy)
        return [(inertia, 0.5), (e_el, 1.0), *contact, *((c, 1.0) for c in self.constants)], grad.view(-1), J

    def potential(self, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(Φ (0-d), ∇Φ (D,), J (K, 1, 1)) at y (:meth:`evaluate` with Φ summed)."""
        parts, g, J = self.evaluate(y)
        return sum(f * p for p, f in parts), g, J

    def energy_and_gradient(self, y: Tensor) -> tuple[float, Tensor | None]:
        """(Φ(y), ∇Φ(y)) with one synchronisation (Φ's parts are summed in double precision); (inf, None) where a
        cubature point is inverted (det F ≤ 0)."""
        parts, g, J = self.evaluate(y)
        *values, lowest = torch.stack([p for p, _ in parts] + [J.amin()]).tolist()
        return (sum(f * v for (_, f), v in zip(parts, values)), g) if lowest > 0 else (float("inf"), None)

    def valid(self, y: Tensor) -> bool:
        """No cubature point is inverted at y (det F > 0 everywhere)."""
        Ft, _ = self.frame.metric(y)
        return bool(torch.linalg.det(Ft).amin() > 0)

    # ---- the exact Hessian and the adjoint -------------------------------------------------------
    def soa_metric(self) -> Tensor:
        """C_ref point-last (3, 3, K) (a view)."""
        return self.C_ref.permute(1, 2, 0)

    def hessian(self, y: Tensor) -> Tensor:
        """∇²Φ(y): (D, D), exact (unprojected)."""
        Y = y.view(1, 3, -1)
        T = damped_neo_hookean_tangent(self.frame.soa_deformations(Y), self.soa_metric(), self.coef.flat)
        return _assemble_hessians([self], Y, T)[0]

    def adjoint_solve(self, grad_y: Tensor) -> Tensor:
        """λ = H⁻¹ ∂L/∂y* (D,) with the exact Hessian H at the converged state (LU where it is indefinite, e.g. under
        compression); the step must have been registered with an :class:`AdjointBatch`."""
        if self.adjoint_data is None:
            if self.batch is None:
                raise RuntimeError("the step's converged state was never registered for its adjoint")
            self.batch.make(self)
        data = self.adjoint_data
        if data.factor is None:
            return torch.linalg.solve(data.hessian, grad_y)
        return torch.cholesky_solve(grad_y.view(-1, 1), data.factor).view(-1)

    def adjoint(self, grad_y: Tensor) -> tuple[Tensor, Tensor]:
        """The step's backward pass: for ∂L/∂y* (D,) the gradients to (y_prev, ẏ_prev, y_prev2, ẏ_prev2) (4, D) and to
        (μ, λ, τ) (3,), i.e. −λᵀ ∂∇Φ/∂θ with λ = H⁻¹ ∂L/∂y* (H exact at y*; the step must have been registered
        with an :class:`AdjointBatch`)."""
        lam = self.adjoint_solve(grad_y)
        data, fr = self.adjoint_data, self.frame
        Lam = lam.view(3, -1)
        history = data.history * torch.mm(Lam, fr.mass_block)  # (4, 3, L): through ŷ
        if data.metric_map is not None:  # through C_ref to the previous states
            dF = torch.mm(Lam, fr.G_soa_cols).view(1, 1, 1, 3, 3, -1)  # dF[x, y, p]
            R = (data.metric_map * dF).sum((3, 4))  # (2, 3, 3, K): [state, e, c, p]
            history[0::2].add_(torch.mm(R.view(6, -1), fr.G_soa_rows).view(2, 3, -1))
        return history.view(4, -1), torch.mv(data.rows, lam)


class AdjointBatch:
    """Makes the :class:`StepAdjoint` of registered steps in batches when a backward pass first needs one: the
    steps sharing a frame's constants that were registered up to the one asked for (the backward pass goes back
    in time), as many as :data:`ADJOINT_BATCH_BYTES` of temporaries allow."""

    def __init__(self) -> None:
        self._pending: list[FusedStep] = []

    def add(self, step: FusedStep, y: Tensor) -> None:
        """Register a step and its converged state y: (D,) for the adjoint."""
        step.solution, step.batch = y.detach(), self
        self._pending.append(step)

    def make(self, step: FusedStep) -> None:
        """Make the adjoint data of ``step`` and of the pending steps before it in one batch."""
        fr = step.frame
        K, L = fr.num_points, fr.G_rows.shape[1]
        per_step = fr.G_rows.element_size() * (K * 800 + 8 * (3 * L) ** 2)
        most = max(1, ADJOINT_BATCH_BYTES // per_step)
        end = self._pending.index(step)
        start = end
        while start > 0 and end - start + 1 < most and self._pending[start - 1].frame is fr:
            start -= 1
        chunk = self._pending[start:end + 1]
        del self._pending[start:end + 1]
        for s, data in zip(chunk, _adjoint_data(chunk)):
            s.adjoint_data = data


def _soa_stack(mats: Sequence[Tensor], transpose: bool = False) -> Tensor:
    """Point-major (K, 3, 3) matrices of S steps as one point-last (3, 3, S K) tensor (``transpose``: of their
    transposes)."""
    M = torch.stack(list(mats))  # (S, K, 3, 3)
    return M.permute(3, 2, 0, 1).reshape(3, 3, -1) if transpose else M.permute(2, 3, 0, 1).reshape(3, 3, -1)


def _adjoint_data(steps: Sequence[FusedStep]) -> list[StepAdjoint]:
    """The :class:`StepAdjoint` of S steps sharing one frame's constants, in one batch."""
    fr = steps[0].frame
    S, K = len(steps), fr.num_points
    L = fr.G_rows.shape[1]
    Y = torch.stack([s.solution for s in steps]).view(S, 3, L)
    F = fr.soa_deformations(Y)
    c = _flat_coefficients([s.coef for s in steps])
    C_ref = _soa_stack([s.C_ref for s in steps])  # symmetric: the order of its two indices does not matter
    state = soa_point_state(F, C_ref)
    H = _assemble_hessians(steps, Y, damped_neo_hookean_tangent(F, C_ref, c, state))
    factor, info = torch.linalg.cholesky_ex(H)
    B = material_adjoint_rows(F, state, c).view(3, 3, 3, S, K).permute(3, 0, 1, 2, 4).reshape(S * 9, 3 * K)
    rows = torch.mm(B, fr.G_soa_rows).view(S, 3, 3 * L)  # Σ_p ⟨B_p, dF_p⟩ = E λ
    a0, a1, a2, h = torch.tensor([[*s.step.coefficients, s.step.h] for s in steps], dtype=H.dtype,
                                 device=H.device).unbind(1)
    history = torch.stack([a1 / a0, h * a1 / a0**2, a2 / a0, h * a2 / a0**2], dim=1).view(S, 4, 1, 1)
    maps = None
    if fr.tau is not None:
        maps = []
        for i, ratio in ((0, a1 / a0), (1, a2 / a0)):  # the state one step back and two (C_ref's terms)
            prev = _soa_stack([s.previous[i] if i < len(s.previous) else s.previous[0] for s in steps], transpose=True)
            scale = ratio.repeat_interleave(K)
            maps.append(metric_adjoint_map(F, prev, c["alpha"] * scale, (2.0 * scale) * c["beta1"]))
        maps = torch.stack(maps).view(2, 3, 3, 3, 3, S, K)
    return [StepAdjoint(H[s] if bad else None, None if bad else factor[s], rows[s],
                        None if maps is None else maps[..., s, :], history[s]) for s, bad in enumerate(info.tolist())]


#: The row blocks (i, k), i ≤ k, of the Hessian that are assembled; the others are transposes: those of the pairs
#: _BELOW, and _ORDER puts the nine (the six made, then the three transposed) in row-major order.
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_BELOW = (1, 2, 4)
_ORDER = (0, 1, 2, 6, 3, 4, 7, 8, 5)


@functools.lru_cache(maxsize=None)
def _index(values: tuple[int, ...], device: torch.device) -> Tensor:
    """A constant index tensor, made once per device."""
    return torch.tensor(values, device=device)


def _assemble_hessians(steps: Sequence[FusedStep], Y: Tensor, T: Tensor) -> Tensor:
    """The exact Hessians (S, D, D) of S steps sharing one frame's constants at their states Y: (S, 3, L), from the
    points' tangents T (3, 3, 3, 3, S K) (:func:`damped_neo_hookean_tangent`):
    H[(i, l'), (k, m)] = Σ_p Σ_jl G[p, j, l'] T[i, k, j, l, p] G[p, l, m] + the mass and contact terms. For the six
    row-block pairs i ≤ k, TG[q, m, j, p] = Σ_l T[q, j, l, p] G[p, l, m] is a product along the points and the sum
    over (j, p) one matrix product, for as many steps at once as :data:`CPU_BLOCK_BYTES` allow on a CPU."""
    fr = steps[0].frame
    S, K = len(steps), fr.num_points
    L = fr.G_rows.shape[1]
    T6 = T.view(9, 3, 3, S, K).index_select(0, _index(tuple(3 * i + k for i, k in _PAIRS), T.device))
    T6 = T6.permute(2, 3, 0, 1, 4).contiguous()  # [l, s, q, j, p]
    per_step = 18 * L * K * T.element_size()
    block = S if T.device.type != "cpu" else max(1, min(S, CPU_BLOCK_BYTES // per_step))
    G = fr.G_soa.view(3, 1, 1, L, 1, K)
    parts = []
    for s0 in range(0, S, block):
        Tb = T6[:, s0:s0 + block].unsqueeze(3)  # (l, s, q, 1, j, p)
        TG = torch.mul(Tb[0], G[0]).addcmul_(Tb[1], G[1]).addcmul_(Tb[2], G[2])  # (s, q, m, j, p)
        parts.append(torch.mm(TG.view(-1, 3 * K), fr.G_soa_rows))  # [(s, q, m), l']
    Hq = (parts[0] if len(parts) == 1 else torch.cat(parts)).view(S, 6, L, L)  # [s, q, m, l'] = H[(i, l'), (k, m)]
    blocks = torch.cat([Hq.transpose(2, 3), Hq.index_select(1, _index(_BELOW, T.device))], 1)  # [(i, k), l', m]
    H = blocks.index_select(1, _index(_ORDER, T.device)).view(S, 3, 3, L, L)
    H = H.permute(0, 1, 3, 2, 4).reshape(S, 3 * L, 3 * L) + fr.mass_matrix
    _add_barrier_hessians(steps, Y, H)
    return 0.5 * (H + H.transpose(1, 2))


def _add_barrier_hessians(steps: Sequence[FusedStep], Y: Tensor, H: Tensor) -> None:
    """Add k_e ∇²E_contact of each step at its state (Y: (S, 3, L)) to H: (S, D, D) in place."""

    fr = steps[0].frame
    S, _, L = Y.shape
    if fr.floors:
        k_e = torch.tensor([s.k_e for s in steps], dtype=H.dtype, device=H.device).view(S, 1)
        heights = torch.mm(Y[:, 2], fr.contact_cols)  # (S, Nc): z − z_rest
        for offset, k2 in fr.floors:  # k2 w e_z e_zᵀ where a point is below the floor: the zz block only
            h = (heights + offset < 0).to(H.dtype) * (k2 * fr.contact_w) * k_e
            weighted = (fr.contact_cols.unsqueeze(0) * h.unsqueeze(1)).view(S * L, -1)  # (S L, Nc)
            H[:, 2 * L:, 2 * L:] += torch.mm(weighted, fr.contact_b).view(S, L, L)
    for s, step in enumerate(steps):
        for friction in step.frictions:
            friction.add_hessian(Y[s], H[s])
    for ext in fr.barriers:
        for s, step in enumerate(steps):
            x = torch.addmm(fr.contact_X, fr.contact_b, Y[s].t())
            H[s] += step.k_e * reduced_point_hessian(ext.hessian(x, fr.contact_w, step.t, project=False), fr.contact_b)
