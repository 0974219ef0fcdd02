"""Fused kernels of the reduced implicit step: the common case in few, large tensor operations.

The reduced simulator is small (D = 12H ≈ 132 unknowns, K ≈ 500 cubature points), so on a GPU every torch
operation costs a launch (≈ 5–10 µs) whatever its size, and the per-term code of
:class:`~vid2sim.physics.reduced.StepProblem` issues hundreds per Newton iteration. This module evaluates the
same incremental potential, its gradient, its exact Hessian and the adjoint's products for the **common
case** — an elastic Neo-Hookean material with Kelvin–Voigt damping (or none), the exact closed-form
F-basis, the pointwise volumetric term, gravity and contact barriers without a contact layer or dashpot —
with every per-point quantity computed for all points at once and the material's constants folded into
per-point coefficient vectors made once per step length (:class:`PointCoefficients`). Whatever else a step
needs goes through the per-term code, which stays the reference (``SimConfig.fused_kernels=False``).

Layouts (as in :mod:`vid2sim.physics.reduced`; K points, L = 4H, D = 3L):

- ``y`` (D,) row-major, ``Y = y.view(3, L)``;
- the F-basis ``G: (K, 3, L)`` is kept as ``G_rows = G.view(3K, L)`` (row (p, c)) and its transpose;
- deformation gradients are kept **transposed**, ``Ft: (K, 3, 3)`` with ``Ft[p, c, a] = F_p[a, c]``: one
  ``addmm`` gives them, ``Ft = I + G_rows Yᵀ``, and a stress kept transposed the same way, ``Pt[p, c, a] =
  P_p[a, c]``, gives the force as one product ``Σ_p ∂vec F_p/∂yᵀ vec P_p = (Pt_rowsᵀ G_rows)``;
- tangents are returned as ``T: (K, 3, 3, 3, 3)`` with ``T[p, j, i, k, l] = ∂P_ij/∂F_kl`` (the row index of P
  second), which makes the Hessian's assembly two matrix products with no reordering of the points.

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

#: Temporary memory (bytes) one batch of adjoint Hessians may take; longer rollouts are done in several batches.
ADJOINT_BATCH_BYTES = 1 << 27


# ---- per-point kernels -------------------------------------------------------------------------

@dataclass
class PointCoefficients:
    """Per-point, volume-weighted factors of one step's damped Neo-Hookean terms (v the cubature weights,
    k_e and k_d the step's weights, h / a₀ its length over its first BDF coefficient):
    α = v k_d μ, β₀ = v k_e μ, β₁ = ½ v k_d λ, γ = v k_e λ.

    Attributes:
        alpha, gamma, neg_beta0: (K, 1, 1) α, γ, −β₀.
        beta0, beta1: (K, 1) β₀, β₁.
        lin, quad: (K, 11) the energy Σ_p f·(lin + quad ∘ f) of the per-point features f = [tr(C − C_ref), ln J,
            vec(C − C_ref)]: lin = [½β₀, −β₀, 0 …], quad = [¼β₁, ½γ, ¼α …] (:func:`energy_offset` adds the rest).
        plain: (K, 2, 1) [γ, 2β₁]: the factors of the tangent's outer products vec F⁻ᵀ vec F⁻ᵀᵀ and vec F vec Fᵀ.
        vk_e, vk_d: (K, 1, 1) v k_e, v k_d; tau_mu, tau_lam: (K, 1, 1) −(h/a₀) v μ, −½ (h/a₀) v λ (the adjoint's
            rows to μ, λ and τ).
        beta0_eye: (9K,) vec(β₀ I) per point (Σ β₀ tr C_ref as one product); offset: 0-d −3/2 Σ β₀.
        k_e, k_d: the step's weights of the potential energy and of the viscous potential (k_d a float or 0-d).
    """

    alpha: Tensor
    beta0: Tensor
    beta1: Tensor
    gamma: Tensor
    neg_beta0: Tensor
    lin: Tensor
    quad: Tensor
    plain: Tensor
    vk_e: Tensor
    vk_d: Tensor
    tau_mu: Tensor
    tau_lam: Tensor
    beta0_eye: Tensor
    offset: Tensor
    k_e: float
    k_d: float | Tensor

    _POINTWISE = ("alpha", "beta0", "beta1", "gamma", "neg_beta0", "lin", "quad", "plain", "vk_e", "vk_d", "tau_mu",
                  "tau_lam", "beta0_eye")

    @classmethod
    def make(cls, vol: Tensor, mu: Tensor, lam: Tensor, k_e: float, k_d: float | Tensor,
             h_over_a0: float) -> "PointCoefficients":
        """From the cubature weights ``vol: (K,)``, 0-d μ and λ, and the step's k_e, k_d and h / a₀."""
        K = vol.shape[0]
        v = vol.view(K, 1)
        alpha, beta0, beta1, gamma = v * (k_d * mu), v * (k_e * mu), v * (0.5 * k_d * lam), v * (k_e * lam)
        lin = torch.cat([0.5 * beta0, -beta0, torch.zeros_like(vol).view(K, 1).expand(K, 9)], dim=1)
        quad = torch.cat([0.25 * beta1, 0.5 * gamma, (0.25 * alpha).expand(K, 9)], dim=1)
        eye = torch.eye(3, dtype=vol.dtype, device=vol.device).view(1, 9)
        pointwise = [t.view(K, 1, 1) for t in (v * k_e, v * k_d, v * (-h_over_a0 * mu), v * (-0.5 * h_over_a0 * lam))]
        return cls(alpha.view(K, 1, 1), beta0, beta1, gamma.view(K, 1, 1), (-beta0).view(K, 1, 1), lin, quad,
                   torch.stack([gamma, 2.0 * beta1], dim=1), *pointwise, (beta0 * eye).view(-1), -1.5 * beta0.sum(),
                   k_e, k_d)

    @staticmethod
    def cat(parts: Sequence["PointCoefficients"]) -> "PointCoefficients":
        """The coefficients of several point sets (e.g. several steps' points) one after the other."""
        tensors = {name: torch.cat([getattr(p, name) for p in parts]) for name in PointCoefficients._POINTWISE}
        return PointCoefficients(**tensors, offset=sum(p.offset for p in parts), k_e=parts[0].k_e, k_d=parts[0].k_d)


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
    """0-d Σ_p ½β₀ (tr C_ref − 3): the constant the energy of :func:`damped_neo_hookean_stress` leaves out."""
    return torch.dot(coef.beta0_eye, C_ref.reshape(-1)).mul(0.5).add_(coef.offset)


def damped_neo_hookean_tangent(Ft: Tensor, C_ref: Tensor, coef: PointCoefficients,
                               state: tuple[Tensor, Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """The exact volume-weighted, step-weighted tangent v (k_e ∂P_NH/∂F + k_d ∂P_v/∂F) of every point.

    With A = F⁻ᵀ and c = μ − λ ln J it is v k_e [μ δ_ik δ_jl + c A_il A_kj + λ A_ij A_kl] + v k_d [δ_ik S_lj +
    μ F_il F_kj + μ (FFᵀ)_ik δ_lj + λ F_ij F_kl] (:func:`~vid2sim.physics.materials.neo_hookean_viscous_tangent`),
    made of two batched products over the pair (A, F) and two diagonal updates.

    Args:
        Ft, C_ref, coef: as in :func:`damped_neo_hookean_stress`; state: their :func:`point_state`, if made.
    Returns:
        T: (K, 3, 3, 3, 3) with ``T[p, j, i, k, l] = ∂P_ij/∂F_kl`` (contiguous).
    """
    K = Ft.shape[0]
    cof, J, diff, tr = state if state is not None else point_state(Ft, C_ref)
    pair = torch.stack([cof / J, Ft], dim=1)  # (K, 2, 3, 3): F⁻¹ = Aᵀ and Fᵀ, i.e. [s, j, i] = V_s[i, j]
    U = pair.view(K, 2, 9).transpose(1, 2)  # (K, 9 (j, i), 2)
    V = pair.transpose(2, 3).reshape(K, 2, 9)  # (K, 2, 9 (k, l)) = V_s[k, l]
    swap_coef = torch.cat([torch.addcmul(coef.beta0.view(K, 1, 1), coef.gamma, J.log(), value=-1.0),
                           coef.alpha], dim=1)  # (K, 2, 1): [v k_e c, v k_d μ]
    out = torch.bmm(U, coef.plain * V).view(K, 3, 3, 3, 3)  # Σ_s ρ_s V_s[i, j] V_s[k, l]
    # Σ_s σ_s V_s[k, j] V_s[i, l], made at [j, k, i, l]
    out += torch.bmm(U, swap_coef * V).view(K, 3, 3, 3, 3).permute(0, 1, 3, 2, 4)
    out.diagonal(dim1=2, dim2=3).add_(_stress_factor(diff, tr, coef).unsqueeze(-1))  # δ_ik Dm_jl
    out.diagonal(dim1=1, dim2=4).add_((torch.bmm(Ft.transpose(1, 2), Ft) * coef.alpha).unsqueeze(-1))  # δ_jl α(FFᵀ)_ik
    return out


def material_adjoint_rows(Ft: Tensor, state: tuple[Tensor, Tensor, Tensor, Tensor], coef: PointCoefficients) -> Tensor:
    """Per point the matrices B_θ (K, 3, 3, 3) (θ = μ, λ, τ; transposed layout) with −λᵀ ∂∇Φ/∂θ = Σ_p ⟨B_θ,p, dFt_p⟩,
    dF = ∂F/∂y λ. From ∂P/∂μ = k_e (F − F⁻ᵀ) + k_d F (C − C_ref), ∂P/∂λ = k_e ln J F⁻ᵀ + ½ k_d tr(C − C_ref) F
    and ∂P/∂τ = (h/a₀) F S: B_μ = v k_e (F⁻¹ − Fᵀ) − v k_d (C − C_ref) Fᵀ, B_λ = −½ v k_d tr(C − C_ref) Fᵀ −
    v k_e ln J F⁻¹, B_τ = −(h/a₀) v (μ (C − C_ref) + ½ λ tr(C − C_ref)) Fᵀ."""
    cof, J, diff, tr = state
    K = Ft.shape[0]
    Ainv = cof / J
    DF = torch.bmm(diff, Ft)
    trF = tr.view(K, 1, 1) * Ft
    b_mu = torch.addcmul((Ainv - Ft) * coef.vk_e, coef.vk_d, DF, value=-1.0)
    b_lam = torch.addcmul(trF * (-0.5 * coef.vk_d), Ainv * J.log(), coef.vk_e, value=-1.0)
    b_tau = torch.addcmul(DF * coef.tau_mu, coef.tau_lam, trF)
    return torch.stack([b_mu, b_lam, b_tau], dim=1)


def metric_adjoint_map(Ft: Tensor, Ft_prev: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """The map dFt ↦ R = Q Fᵀ_prev per point (n, 9, 9), ``R.view(9) = map @ dFt.view(9)``, where Q = a (W + Wᵀ) +
    b tr W I, W = FᵀdF (the viscous term's dependence on C_ref passes λ on to a previous state F_prev through
    C_ref = Σ c F_prevᵀF_prev: the gradient to F_prev is 2c F_prev Q with a = ½α, b = β₁; here a and b (n, 1, 1)
    carry the 2c). Entries: R[c, e] = Σ_xy (a Ft[c, y] Ft_prev[x, e] + a δ_cx (FtᵀFt_prev)[y, e] + b Ft_prev[c, e]
    Ft[x, y]) dFt[x, y]."""
    n = Ft.shape[0]
    out = torch.bmm(Ft_prev.view(n, 9, 1) * b, Ft.view(n, 1, 9))  # b Ft_prev[c, e] Ft[x, y]
    o5 = out.view(n, 3, 3, 3, 3)  # [c, e, x, y]
    o5 += torch.bmm(Ft.view(n, 9, 1) * a, Ft_prev.view(n, 1, 9)).view(n, 3, 3, 3, 3).permute(0, 1, 4, 3, 2)
    o5.diagonal(dim1=1, dim2=3).add_((torch.bmm(Ft.transpose(1, 2), Ft_prev) * a).transpose(1, 2).unsqueeze(-1))
    return out


# ---- one frame's constants ---------------------------------------------------------------------

def fused_supported(model: str, structured: bool, plastic: bool, volumetric: Tensor | None, dashpot: Tensor | None,
                    layer_k: Tensor | None, externals: Sequence) -> bool:
    """Whether a step can use the fused kernels: elastic Neo-Hookean, the structured F-basis, the pointwise
    volumetric term, no contact dashpot or layer, and no body force but gravity."""
    body_ok = all(isinstance(e, Gravity) for e in externals if getattr(e, "kind", "body") == "body")
    return (model == "neo_hookean" and structured and not plastic and volumetric is None and dashpot is None
            and layer_k is None and body_ok)


@dataclass
class FusedFrame:
    """The constants of a frame's substeps (one basis, material and set of points), detached.

    Attributes:
        G_rows: (3K, L) the F-basis, row (p, c); G_cols: (L, 3K) its transpose (contiguous).
        eye_rows: (3K, 3) the identity's rows per point (F = I + Y G).
        vol: (K,) cubature weights; mu, lam: 0-d Lamé parameters; tau: 0-d retardation time or None.
        mass_block: (L, L) Σ_p m_p b_p b_pᵀ; mass_matrix: (D, D) I₃ ⊗ mass_block.
        tracked_cols: (L, K + Nc) LBS rows of the cubature and contact points, transposed (the points
            Newton's convergence test watches).
        gravity: (e₀ (), f (3, L)) with the gravity energy e₀ − f·y (zeros without gravity).
        contact_X, contact_b, contact_w: (Nc, 3), (Nc, L), (Nc,) the contact points' rest positions, LBS rows and
            weights; contact_cols: (L, Nc) the rows transposed.
        floors: [(z_c − h (Nc,), 2k)] of the :class:`~vid2sim.physics.external.Floor` barriers (only the
            height of a point matters to them); barriers: the other contact energies.
    """

    G_rows: Tensor
    G_cols: Tensor
    eye_rows: Tensor
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
    _coefficients: dict = field(default_factory=dict)
    _metrics: list = field(default_factory=list)

    @classmethod
    def build(cls, X: Tensor, vol: Tensor, mass: Tensor, b: Tensor, G: Tensor, mu: Tensor, lam: Tensor,
              tau: Tensor | None, externals: Sequence, contact_X: Tensor | None, contact_b: Tensor | None,
              contact_w: Tensor | None) -> "FusedFrame":
        """From the step's inputs (shapes of :class:`~vid2sim.physics.reduced.StepProblem`; G: (K, 3, L))."""
        K, _, L = G.shape
        X, vol, mass, b, G = (t.detach() for t in (X, vol, mass, b, G))
        G_rows = G.reshape(3 * K, L)
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
        return cls(G_rows, G_rows.T.contiguous(), torch.eye(3, dtype=X.dtype, device=X.device).repeat(K, 1), vol,
                   mu.detach(), lam.detach(), None if tau is None else tau.detach(), mass_block,
                   torch.block_diag(mass_block, mass_block, mass_block), tracked.T.contiguous(), gravity,
                   contact_X, contact_b, contact_w, contact_b.T.contiguous(), floors,
                   [e for e in contact if type(e) is not Floor])

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

    def metric(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """(Ft, C = FᵀF) (K, 3, 3) at y; the last two states asked for are remembered (a step's previous state
        is the next step's state two back, and its converged state is checked before the next step starts)."""
        for known, Ft, C in self._metrics:
            if known is y:
                return Ft, C
        Ft = self.deformation(y)
        C = torch.bmm(Ft, Ft.transpose(1, 2))
        self._metrics = [*self._metrics[-1:], (y, Ft, C)]
        return Ft, C


# ---- one step ------------------------------------------------------------------------------------

@dataclass
class StepAdjoint:
    """What a step's backward pass needs (made by :class:`AdjointBatch`).

    Attributes:
        hessian: (D, D) the exact Hessian at the converged state; factor: its Cholesky factor, or None where it is
            indefinite (then LU).
        rows: (3, D) E: the gradients to (μ, λ, τ) are E λ.
        metric_map: (2, K, 9, 9) the maps of :func:`metric_adjoint_map` to the previous state and the one before
            (2c folded in), or None when undamped.
        history: (4, 1, 1) the factors of Mλ in the gradients to (y_prev, ẏ_prev, y_prev2, ẏ_prev2):
            (a₁/a₀, h a₁/a₀², a₂/a₀, h a₂/a₀²) (ŷ's coefficients).
    """

    hessian: Tensor
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
    """

    def __init__(self, frame: FusedFrame, step: BDFStep, t: float, y_prev: Tensor, y_prev2: Tensor | None,
                 y_pred: Tensor) -> None:
        self.frame, self.step, self.t = frame, step, t
        self.Y_pred = y_pred.view(3, -1)
        self.coef, self.force_constant, constant = frame.coefficients(step)
        self.k_e = step.energy_scale
        self.batch: AdjointBatch | None = None
        self.solution: Tensor | None = None
        self.adjoint_data: StepAdjoint | None = None
        a0, a1, a2 = step.coefficients
        self.previous: list[tuple[float, Tensor]] = []
        if frame.tau is None:
            self.C_ref = frame.eye_rows.view(-1, 3, 3)
        else:
            Ft1, C1 = frame.metric(y_prev)
            self.previous.append((a1 / a0, Ft1))
            self.C_ref = (a1 / a0) * C1
            if step.needs_history:
                Ft2, C2 = frame.metric(y_prev2)
                self.previous.append((a2 / a0, Ft2))
                self.C_ref.add_(C2, alpha=a2 / a0)
        # Φ's constant parts: Σ ½β₀ (tr C_ref − 3) + k_e e₀ + f·ŷ (the gravity term f·y is written f·(y − ŷ) + f·ŷ)
        self.constants = [energy_offset(self.C_ref, self.coef), torch.dot(self.force_constant.view(-1), y_pred), constant]

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
    def hessian(self, y: Tensor) -> Tensor:
        """∇²Φ(y): (D, D), exact (unprojected)."""
        Ft = torch.addmm(self.frame.eye_rows, self.frame.G_rows, y.view(3, -1).t()).view(-1, 3, 3)
        return _assemble_hessians([self], y.view(1, 3, -1), Ft,
                                  damped_neo_hookean_tangent(Ft, self.C_ref, self.coef))[0]

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
            R = torch.matmul(data.metric_map, torch.mm(fr.G_rows, Lam.t()).view(-1, 9, 1)).view(2, -1, 3)
            history[0::2] += torch.matmul(R.transpose(1, 2), fr.G_rows)
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
        per_step = fr.G_rows.element_size() * (K * (27 * L + 400) + 8 * (3 * L) ** 2)
        most = max(1, ADJOINT_BATCH_BYTES // per_step)
        end = self._pending.index(step)
        start = end
        while start > 0 and end - start + 1 < most and self._pending[start - 1].frame is fr:
            start -= 1
        chunk = self._pending[start:end + 1]
        del self._pending[start:end + 1]
        for s, data in zip(chunk, _adjoint_data(chunk)):
            s.adjoint_data = data


def _adjoint_data(steps: Sequence[FusedStep]) -> list[StepAdjoint]:
    """The :class:`StepAdjoint` of S steps sharing one frame's constants, in one batch."""
    fr = steps[0].frame
    S, K = len(steps), fr.num_points
    L = fr.G_rows.shape[1]
    Y = torch.stack([s.solution for s in steps]).view(S, 3, L)
    Ft = torch.matmul(fr.G_rows, Y.transpose(1, 2)).add_(fr.eye_rows).view(S * K, 3, 3)
    coef = PointCoefficients.cat([s.coef for s in steps]) if S > 1 else steps[0].coef
    C_ref = torch.cat([s.C_ref for s in steps]) if S > 1 else steps[0].C_ref
    state = point_state(Ft, C_ref)
    H = _assemble_hessians(steps, Y, Ft, damped_neo_hookean_tangent(Ft, C_ref, coef, state))
    factor, info = torch.linalg.cholesky_ex(H)
    B = material_adjoint_rows(Ft, state, coef).view(S, K, 3, 3, 3).transpose(1, 2).reshape(S, 3, 3 * K, 3)
    rows = torch.matmul(B.transpose(2, 3), fr.G_rows).view(S, 3, 3 * L)  # Σ_p ⟨B_p, G_p Λᵀ⟩ = E λ
    a0, a1, a2 = (torch.tensor([s.step.coefficients[i] for s in steps], dtype=H.dtype, device=H.device)
                  for i in range(3))
    h = torch.tensor([s.step.h for s in steps], dtype=H.dtype, device=H.device)
    history = torch.stack([a1 / a0, h * a1 / a0**2, a2 / a0, h * a2 / a0**2], dim=1).view(S, 4, 1, 1)
    maps = None
    if fr.tau is not None:
        maps = []
        for i, c in ((0, a1 / a0), (1, a2 / a0)):  # the state one step back and two (C_ref's terms)
            prev = torch.cat([(s.previous[i] if i < len(s.previous) else s.previous[0])[1] for s in steps])
            scale = (2.0 * c).repeat_interleave(K).view(S * K, 1, 1)
            maps.append(metric_adjoint_map(Ft, prev, coef.alpha * (0.5 * scale), coef.beta1.view(-1, 1, 1) * scale))
        maps = torch.stack(maps).view(2, S, K, 9, 9)
    return [StepAdjoint(H[s], factor[s] if bad == 0 else None, rows[s], None if maps is None else maps[:, s],
                        history[s]) for s, bad in enumerate(info.tolist())]


#: The row blocks (a, b), a ≤ b, of the Hessian that are assembled; the others are their transposes: those of
#: the pairs _BELOW, and _ORDER puts the nine (made six, then the three transposed) in row-major order.
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_BELOW = (1, 2, 4)
_ORDER = (0, 1, 2, 6, 3, 4, 7, 8, 5)


@functools.lru_cache(maxsize=None)
def _index(values: tuple[int, ...], device: torch.device) -> Tensor:
    """A constant index tensor, made once per device."""
    return torch.tensor(values, device=device)


def _assemble_hessians(steps: Sequence[FusedStep], Y: Tensor, Ft: Tensor, T: Tensor) -> Tensor:
    """The exact Hessians (S, D, D) of S steps sharing one frame's constants at their states Y: (S, 3, L), from the
    points' transposed F (S K, 3, 3) and tangents T (S K, 3, 3, 3, 3) ([p, j, i, k, l] = ∂P_ij/∂F_kl):
    H[(i, l'), (k, m)] = Σ_p Σ_jl G[p, j, l'] T[p, j, i, k, l] G[p, l, m] + the mass and contact terms."""
    fr = steps[0].frame
    S, K = len(steps), fr.num_points
    L = fr.G_rows.shape[1]
    T6 = T.view(S, K, 3, 9, 3).index_select(3, _index(tuple(3 * i + k for i, k in _PAIRS), Ft.device))  # (S, K, j, 6, l)
    TG = torch.matmul(T6.view(S, K, 18, 3), fr.G_rows.view(K, 3, L))  # (S, K, 18, L): [p, (j, q), m]
    Hq = torch.matmul(fr.G_cols, TG.view(S, 3 * K, 6 * L)).view(S, L, 6, L)  # [l', q, m]
    # the nine blocks (i, k) in order: the six made and the transposes of the three below the diagonal
    blocks = torch.cat([Hq, Hq.index_select(2, _index(_BELOW, Ft.device)).permute(0, 3, 2, 1)], 2)
    H = blocks.index_select(2, _index(_ORDER, Ft.device)).view(S, L, 3, 3, L)
    H = H.permute(0, 2, 1, 3, 4).reshape(S, 3 * L, 3 * L) + fr.mass_matrix
    _add_barrier_hessians(steps, Y, H)
    return 0.5 * (H + H.transpose(1, 2))


def _add_barrier_hessians(steps: Sequence[FusedStep], Y: Tensor, H: Tensor) -> None:
    """Add k_e ∇²E_contact of each step at its state (Y: (S, 3, L)) to H: (S, D, D) in place."""
    from vid2sim.physics.reduced import _reduced_point_hessian

    fr = steps[0].frame
    L = Y.shape[2]
    if fr.floors:
        k_e = torch.tensor([s.k_e for s in steps], dtype=H.dtype, device=H.device)
        heights = torch.matmul(fr.contact_b, Y[:, 2].t())  # (Nc, S): z − z_rest
        for offset, k2 in fr.floors:  # k2 w e_z e_zᵀ where a point is below the floor: the zz block only
            h = (heights + offset[:, None] < 0).to(H.dtype) * (k2 * fr.contact_w[:, None]) * k_e
            H[:, 2 * L:, 2 * L:] += torch.matmul(fr.contact_cols * h.t()[:, None, :], fr.contact_b)
    for ext in fr.barriers:
        for s, step in enumerate(steps):
            x = torch.addmm(fr.contact_X, fr.contact_b, Y[s].t())
            H[s] += step.k_e * _reduced_point_hessian(ext.hessian(x, fr.contact_w, step.t, project=False), fr.contact_b)
