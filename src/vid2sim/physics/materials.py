"""Hyperelastic energy densities Ψ(F) with analytic first Piola–Kirchhoff stress and tangent.

All functions are batched over points: ``F: (N, 3, 3)``; Lamé parameters are Python floats or 0-d
tensors (differentiable). Tangents are returned as ``(N, 9, 9)`` with
``C[n, 3*i + j, 3*k + l] = ∂P_ij / ∂F_kl`` (row-major flattening of F, as everywhere in vid2sim).

Models (paper, supplementary "Generalized to Different Materials"):

- Neo-Hookean:  Ψ = μ/2 (tr FᵀF − 3) − μ ln J + λ/2 (ln J)²
- StVK:         Ψ = μ tr(G²) + λ/2 tr(G)²,  G = ½ (FᵀF − I)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Union

import torch
from torch import Tensor

Scalar = Union[float, Tensor]


def lame_parameters(youngs_modulus: Scalar, poisson_ratio: Scalar) -> tuple[Scalar, Scalar]:
    """Lamé parameters (μ, λ) from Young's modulus E > 0 and Poisson's ratio −1 < ν < 0.5.

    μ = E / (2(1+ν)),  λ = E ν / ((1+ν)(1−2ν)). Differentiable when given tensors.
    """
    e = float(youngs_modulus.detach()) if isinstance(youngs_modulus, Tensor) else float(youngs_modulus)
    nu = float(poisson_ratio.detach()) if isinstance(poisson_ratio, Tensor) else float(poisson_ratio)
    if not e > 0 or e != e or e == float("inf"):
        raise ValueError(f"Young's modulus E must be a finite positive number, got {e}")
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"Poisson's ratio nu must satisfy -1 < nu < 0.5, got {nu}")
    mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))
    return mu, lam


def _check_F(F: Tensor) -> None:
    if F.ndim != 3 or F.shape[1:] != (3, 3):
        raise ValueError(f"deformation gradients F must have shape (N, 3, 3), got {tuple(F.shape)}")


def det3(F: Tensor) -> Tensor:
    """Determinants of 3×3 matrices F: (N, 3, 3) → (N,), by the triple product (differentiable, no LU)."""
    return (F[:, 0] * torch.linalg.cross(F[:, 1], F[:, 2])).sum(-1)


def inv3(F: Tensor) -> Tensor:
    """Inverses of 3×3 matrices F: (N, 3, 3) by the adjugate (differentiable; det F must be nonzero)."""
    cof = torch.stack([torch.linalg.cross(F[:, 1], F[:, 2]), torch.linalg.cross(F[:, 2], F[:, 0]),
                       torch.linalg.cross(F[:, 0], F[:, 1])], dim=1)  # rows: cofactor rows of F
    det = (F[:, 0] * cof[:, 0]).sum(-1)
    return cof.transpose(1, 2) / det[:, None, None]


# ---- Neo-Hookean -------------------------------------------------------------------------------

def neo_hookean_energy_density(F: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """Ψ(F) per point, (N,). Requires det F > 0 (returns NaN otherwise; the solver never goes there)."""
    _check_F(F)
    ic = (F * F).sum(dim=(1, 2))
    logj = torch.log(det3(F))
    return 0.5 * mu * (ic - 3.0) - mu * logj + 0.5 * lam * logj * logj


def neo_hookean_pk1(F: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """First Piola–Kirchhoff stress P = ∂Ψ/∂F = μ(F − F⁻ᵀ) + λ ln J F⁻ᵀ, (N, 3, 3)."""
    _check_F(F)
    finv_t = inv3(F).transpose(1, 2)
    logj = torch.log(det3(F))[:, None, None]
    return mu * (F - finv_t) + lam * logj * finv_t


def neo_hookean_energy_and_pk1(F: Tensor, mu: Scalar, lam: Scalar) -> tuple[Tensor, Tensor, Tensor]:
    """(Ψ (N,), P (N, 3, 3), J (N,)) in one pass (shared cofactors, det and log). Where J ≤ 0, Ψ and P are
    not finite; callers check J."""
    _check_F(F)
    cof = torch.stack([torch.linalg.cross(F[:, 1], F[:, 2]), torch.linalg.cross(F[:, 2], F[:, 0]),
                       torch.linalg.cross(F[:, 0], F[:, 1])], dim=1)  # rows of the cofactor matrix = J F⁻ᵀ
    J = (F[:, 0] * cof[:, 0]).sum(-1)
    logj = torch.log(J)
    finv_t = cof / J[:, None, None]
    psi = 0.5 * mu * ((F * F).sum(dim=(1, 2)) - 3.0) - mu * logj + 0.5 * lam * logj * logj
    P = mu * F + (lam * logj - mu)[:, None, None] * finv_t
    return psi, P, J


def stvk_energy_and_pk1(F: Tensor, mu: Scalar, lam: Scalar, C_ref: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(Ψ (N,), P (N, 3, 3)) of StVK measured from C_ref (identity when None) in one pass."""
    _check_F(F)
    G = green_strain(F, C_ref)
    tr = G.diagonal(dim1=1, dim2=2).sum(-1)
    psi = mu * (G * G).sum(dim=(1, 2)) + 0.5 * lam * tr * tr
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    P = F @ (2.0 * mu * G + (lam * tr)[:, None, None] * eye)
    return psi, P


def neo_hookean_viscous_energy_and_pk1(F: Tensor, mu: Scalar, lam: Scalar, k_elastic: Scalar, k_viscous: Scalar,
                                       C_ref: Tensor, energy: bool = True, lam_elastic: Scalar | None = None
                                       ) -> tuple[Tensor | None, Tensor, Tensor]:
    """k_e Ψ_NH + k_v ψ and k_e P_NH + k_v P_v in one pass: ((N,) or None, (N, 3, 3), J (N,)).

    ψ is the StVK energy measured from C_ref (the Kelvin–Voigt term of :mod:`vid2sim.physics.damping`). With
    C = FᵀF, G = ½ (C − C_ref) and c = λ ln J − μ the stress is F (k_e μ I + k_v (2μ G + λ tr G I)) + k_e c F⁻ᵀ,
    so the two models share F's cofactors, C and one product with F: the same values as
    :func:`neo_hookean_energy_and_pk1` and :func:`stvk_energy_and_pk1` in fewer (eager) operations. The energy
    is skipped (None) when ``energy`` is False. Where J ≤ 0 the values are not finite; callers check J.
    ``lam_elastic``: the λ of the Neo-Hookean part when it differs from the viscous part's (0 when the
    volumetric term is projected and added by the caller); None: ``lam``."""
    _check_F(F)
    lam_e = lam if lam_elastic is None else lam_elastic
    cof = torch.linalg.cross(F.roll(-1, dims=1), F.roll(-2, dims=1))  # rows: cross(F_{i+1}, F_{i+2}) = J F⁻ᵀ
    J = (F[:, 0] * cof[:, 0]).sum(-1)
    logj = torch.log(J)
    C = F.transpose(1, 2) @ F
    G = C.sub(C_ref).mul_(0.5)
    tr_g = G.diagonal(dim1=1, dim2=2).sum(-1)
    S = G * (2.0 * k_viscous * mu)
    S.diagonal(dim1=1, dim2=2).add_((k_viscous * lam * tr_g + k_elastic * mu)[:, None])
    P = torch.baddbmm((k_elastic * (lam_e * logj - mu) / J)[:, None, None] * cof, F, S)
    if not energy:
        return None, P, J
    tr_c = C.diagonal(dim1=1, dim2=2).sum(-1)
    psi = k_elastic * (0.5 * mu * (tr_c - 3.0) - mu * logj + 0.5 * lam_e * logj * logj) \
        + k_viscous * (mu * (G * G).sum(dim=(1, 2)) + 0.5 * lam * tr_g * tr_g)
    return psi, P, J


def energy_and_pk1(model: str, F: Tensor, mu: Scalar, lam: Scalar) -> tuple[Tensor, Tensor, Tensor]:
    """(Ψ (N,), P (N, 3, 3), J (N,)) of the named elastic model in one pass."""
    if model == "neo_hookean":
        return neo_hookean_energy_and_pk1(F, mu, lam)
    if model == "stvk":
        psi, P = stvk_energy_and_pk1(F, mu, lam)
        return psi, P, det3(F)
    raise ValueError(f"unknown elastic model {model!r}; expected one of {sorted(ELASTIC_MODELS)}")


def neo_hookean_tangent(F: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """∂P/∂F, (N, 9, 9): μ δ_ik δ_jl + (μ − λ ln J) F⁻¹_jk F⁻¹_li + λ F⁻¹_ji F⁻¹_lk."""
    _check_F(F)
    n = F.shape[0]
    finv = inv3(F)
    finv_t = finv.transpose(1, 2)
    coef = (mu - lam * torch.log(det3(F)))[:, None, None]
    # (μ − λ ln J) F⁻¹_jk F⁻¹_li at [i, j, k, l], the coefficient folded into the small factor
    swap = ((coef * finv_t)[:, :, None, None, :] * finv[:, None, :, :, None]).reshape(n, 9, 9)
    # λ F⁻¹_ji F⁻¹_lk = λ vec(F⁻ᵀ) vec(F⁻ᵀ)ᵀ
    v = finv_t.reshape(n, 9)
    outer = (lam * v)[:, :, None] * v[:, None, :]
    return swap + outer + mu * torch.eye(9, dtype=F.dtype, device=F.device)


# ---- St. Venant–Kirchhoff ----------------------------------------------------------------------

def green_strain(F: Tensor, C_ref: Tensor | None = None) -> Tensor:
    """G = ½ (FᵀF − C_ref), (N, 3, 3); C_ref: (N, 3, 3) or None for the identity (the Green strain)."""
    C = F.transpose(1, 2) @ F
    if C_ref is None:
        return 0.5 * (C - torch.eye(3, dtype=F.dtype, device=F.device))
    return 0.5 * (C - C_ref)


def _stvk_stress(G: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """Second Piola–Kirchhoff stress S = 2μ G + λ tr(G) I of the strain G: (N, 3, 3)."""
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    return 2.0 * mu * G + lam * G.diagonal(dim1=1, dim2=2).sum(-1)[:, None, None] * eye


def stvk_energy_density(F: Tensor, mu: Scalar, lam: Scalar, C_ref: Tensor | None = None) -> Tensor:
    """Ψ(F) = μ tr(G²) + λ/2 tr(G)², G = ½ (FᵀF − C_ref) (C_ref = I: StVK), (N,)."""
    _check_F(F)
    G = green_strain(F, C_ref)
    tr = G.diagonal(dim1=1, dim2=2).sum(-1)
    return mu * (G * G).sum(dim=(1, 2)) + 0.5 * lam * tr * tr


def stvk_pk1(F: Tensor, mu: Scalar, lam: Scalar, C_ref: Tensor | None = None) -> Tensor:
    """P = F S with S = 2μ G + λ tr(G) I, G = ½ (FᵀF − C_ref), (N, 3, 3)."""
    _check_F(F)
    return F @ _stvk_stress(green_strain(F, C_ref), mu, lam)


def stvk_tangent(F: Tensor, mu: Scalar, lam: Scalar, C_ref: Tensor | None = None, psd: bool = False) -> Tensor:
    """∂P/∂F, (N, 9, 9): δ_ik S_lj + μ (F_il F_kj + (F Fᵀ)_ik δ_lj) + λ F_ij F_kl.

    The last three terms are the Gauss–Newton part (∂G/∂F)ᵀ ∂²Ψ/∂G² (∂G/∂F), positive semi-definite for
    μ ≥ 0, 3λ + 2μ ≥ 0; only δ_ik S_lj can be indefinite. With ``psd`` S is replaced by its positive part
    (eigenvalues clamped at 0), which makes the whole tangent positive semi-definite — a cheap PSD
    surrogate, exact wherever S ⪰ 0.
    """
    _check_F(F)
    n = F.shape[0]
    S = _stvk_stress(green_strain(F, C_ref), mu, lam)
    if psd:
        evals, evecs = torch.linalg.eigh(0.5 * (S + S.transpose(1, 2)))
        S = (evecs * evals.clamp_min(0.0)[:, None, :]) @ evecs.transpose(1, 2)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    t1 = torch.einsum("ik,nlj->nijkl", eye, S)
    t2 = torch.einsum("nil,nkj->nijkl", F, F)
    t3 = torch.einsum("nik,lj->nijkl", F @ F.transpose(1, 2), eye)
    fv = F.reshape(n, 9)
    outer = fv[:, :, None] * fv[:, None, :]
    return (t1 + mu * (t2 + t3)).reshape(n, 9, 9) + lam * outer


def neo_hookean_viscous_tangent(F: Tensor, mu: Scalar, lam: Scalar, k_elastic: Scalar, k_viscous: Scalar,
                                C_ref: Tensor | None, lam_elastic: Scalar | None = None) -> Tensor:
    """k_e ∂P_NH/∂F + k_v ∂P_v/∂F, (N, 9, 9): the exact tangent of a damped Neo-Hookean step in one pass.

    P_v is the StVK stress measured from C_ref (the Kelvin–Voigt term of :mod:`vid2sim.physics.damping`;
    None: no viscous term). With A = F⁻ᵀ and c = μ − λ ln J every term is an outer product or a Kronecker
    product with δ:
      k_e [μ δ_ik δ_jl + c A_il A_kj + λ A_ij A_kl] + k_v [δ_ik S_lj + μ F_il F_kj + μ (FFᵀ)_ik δ_lj + λ F_ij F_kl],
    so it is assembled from two batched outer products instead of the separate 9 × 9 tangents
    (:func:`neo_hookean_tangent` + :func:`stvk_tangent`, which it equals). ``lam_elastic``: as in
    :func:`neo_hookean_viscous_energy_and_pk1`.
    """
    _check_F(F)
    lam_e = lam if lam_elastic is None else lam_elastic
    n = F.shape[0]
    cof = torch.stack([torch.linalg.cross(F[:, 1], F[:, 2]), torch.linalg.cross(F[:, 2], F[:, 0]),
                       torch.linalg.cross(F[:, 0], F[:, 1])], dim=1)
    J = (F[:, 0] * cof[:, 0]).sum(-1)
    A = (cof / J[:, None, None]).reshape(n, 9)  # F⁻ᵀ, row-major
    c = mu - lam_e * torch.log(J)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    if C_ref is None:
        plain = (k_elastic * lam_e) * A[:, :, None] * A[:, None, :]
        swap = (k_elastic * c)[:, None, None] * A[:, :, None] * A[:, None, :]
        delta_jl = (k_elastic * mu) * eye.expand(n, 3, 3)
        out = plain.reshape(n, 3, 3, 3, 3) + swap.reshape(n, 3, 3, 3, 3).permute(0, 1, 4, 3, 2)
    else:
        f = F.reshape(n, 9)
        V = torch.stack([A, f], dim=2)  # (n, 9, 2)
        coef = torch.stack([torch.as_tensor(k_elastic * lam_e, dtype=F.dtype, device=F.device).expand(n),
                            torch.as_tensor(k_viscous * lam, dtype=F.dtype, device=F.device).expand(n)], dim=1)
        plain = (V * coef[:, None, :]) @ V.transpose(1, 2)
        coef_s = torch.stack([k_elastic * c, torch.as_tensor(k_viscous * mu, dtype=F.dtype,
                                                              device=F.device).expand(n)], dim=1)
        swap = (V * coef_s[:, None, :]) @ V.transpose(1, 2)
        S = _stvk_stress(green_strain(F, C_ref), mu, lam)
        delta_jl = (k_elastic * mu) * eye + k_viscous * S  # S symmetric: S_lj = S_jl
        out = plain.reshape(n, 3, 3, 3, 3) + swap.reshape(n, 3, 3, 3, 3).permute(0, 1, 4, 3, 2)
        ffT = (k_viscous * mu) * (F @ F.transpose(1, 2))
        for j in range(3):  # μ (FFᵀ)_ik δ_lj
            out[:, :, j, :, j] += ffT
    for i in range(3):  # δ_ik (k_e μ δ_jl + k_v S_lj)
        out[:, i, :, i, :] += delta_jl
    return out.reshape(n, 9, 9)


# ---- model table and PSD projection -------------------------------------------------------------

ELASTIC_MODELS = {
    "neo_hookean": (neo_hookean_energy_density, neo_hookean_pk1, neo_hookean_tangent),
    "stvk": (stvk_energy_density, stvk_pk1, stvk_tangent),
}


def elastic_model(name: str):
    """(energy_density, pk1, tangent) functions of the named model ('neo_hookean' or 'stvk')."""
    try:
        return ELASTIC_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown elastic model {name!r}; expected one of {sorted(ELASTIC_MODELS)}") from None


def project_psd(H: Tensor, floor: float = 0.0, tolerance: float = 1e-6) -> Tensor:
    """Project symmetric matrices (N, d, d) to positive semi-definite by clamping eigenvalues at ``floor``.

    Fast path: a matrix whose Cholesky factorisation succeeds after adding ``tolerance · max|diag|`` to
    its diagonal has no eigenvalue below ``−tolerance · max|diag|`` and is returned unchanged (elastic
    tangents are exactly singular in rotation directions at rest, so an exact test would send nearly
    every point to the slow path for a change below round-off). Only the others are eigendecomposed.
    """
    if H.ndim != 3 or H.shape[1] != H.shape[2]:
        raise ValueError(f"project_psd expects (N, d, d) matrices, got {tuple(H.shape)}")
    H = 0.5 * (H + H.transpose(1, 2))
    bad = ~_nearly_pd(H, tolerance)
    if not bool(bad.any()):
        return H
    evals, evecs = torch.linalg.eigh(H[bad])
    fixed = (evecs * evals.clamp_min(floor)[:, None, :]) @ evecs.transpose(1, 2)
    out = H.clone()
    out[bad] = fixed
    return out


def _unit(v: Tensor) -> Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)


def symmetric_eigen_3x3(A: Tensor, eigenvalues: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Eigen-decomposition of symmetric 3×3 matrices in closed form, fully vectorised.

    Returns (eigenvalues (N, 3) ascending, eigenvectors (N, 3, 3) as columns). The eigenvector of the
    best-separated extreme eigenvalue comes from the largest cross product of two rows of A − eI; the other
    two from an exact 2×2 rotation in the plane orthogonal to it, so repeated eigenvalues are handled.
    ``eigenvalues`` (N, 3) ascending, when already known (from :func:`symmetric_eigenvalues_3x3`), are reused.
    """
    e = symmetric_eigenvalues_3x3(A) if eigenvalues is None else eigenvalues
    n = A.shape[0]
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    low_isolated = (e[:, 1] - e[:, 0]) > (e[:, 2] - e[:, 1])
    e_iso = torch.where(low_isolated, e[:, 0], e[:, 2])
    M = A - e_iso[:, None, None] * eye
    crosses = torch.stack([torch.linalg.cross(M[:, 0], M[:, 1]), torch.linalg.cross(M[:, 0], M[:, 2]),
                           torch.linalg.cross(M[:, 1], M[:, 2])], dim=1)
    norms = crosses.norm(dim=-1)
    best = norms.argmax(dim=1)
    v = crosses[torch.arange(n, device=A.device), best]
    fallback = norms.max(dim=1).values <= torch.finfo(A.dtype).tiny
    v = torch.where(fallback[:, None], eye[0].expand(n, 3), v)
    v = _unit(v)
    # an orthonormal basis (p, q) of the plane orthogonal to v
    axis = eye[v.abs().argmin(dim=1)]
    p = _unit(torch.linalg.cross(v, axis))
    q = torch.linalg.cross(v, p)
    Ap, Aq = (A @ p[:, :, None])[:, :, 0], (A @ q[:, :, None])[:, :, 0]
    a, b, c = (p * Ap).sum(-1), (p * Aq).sum(-1), (q * Aq).sum(-1)
    theta = 0.5 * torch.atan2(2.0 * b, a - c)
    ct, st = torch.cos(theta), torch.sin(theta)
    w1 = ct[:, None] * p + st[:, None] * q  # Rayleigh quotient: the larger in-plane eigenvalue
    w2 = -st[:, None] * p + ct[:, None] * q
    # order the columns as the ascending eigenvalues
    lo = low_isolated[:, None]
    col0 = torch.where(lo, v, w2)
    col1 = torch.where(lo, w2, w1)  # low isolated: (v, w2, w1); high isolated: (w2, w1, v)
    col2 = torch.where(lo, w1, v)
    return e, torch.stack([col0, col1, col2], dim=-1)


@dataclass
class NeoHookeanIndefinite:
    """Where a Neo-Hookean tangent is indefinite and the closed-form modes that fix it.

    Attributes:
        twist_index: (M,) points whose twist modes need clamping.
        twist_modes: (M, 3, 3, 3) unit twist modes D_k (k = 0, 1, 2) as 3×3 matrices.
        twist_amount: (M, 3) max(0, −eigenvalue) of each mode; adding Σ_k amount_k vec(D_k) vec(D_k)ᵀ
            to the tangent clamps those eigenvalues at 0 and leaves every other mode unchanged.
        general: (N,) bool, points with μ − λ ln J < 0 (extreme expansion) whose scaling block may be
            indefinite too; they need a general eigendecomposition.
    """

    twist_index: Tensor
    twist_modes: Tensor
    twist_amount: Tensor
    general: Tensor

    @property
    def empty(self) -> bool:
        return self.twist_index.numel() == 0 and not bool(self.general.any())


def neo_hookean_indefinite(F: Tensor, mu: Scalar, lam: Scalar, tolerance: float = 1e-6) -> NeoHookeanIndefinite:
    """Closed-form analysis of the Neo-Hookean tangent's negative eigenvalues at F: (N, 3, 3).

    With F = U Σ Vᵀ and c = μ − λ ln J, the tangent's eigenvectors include the three twist modes
    D_k = (u_i v_jᵀ − u_j v_iᵀ) / √2 ({i, j, k} = {0, 1, 2}) with eigenvalues μ − c σ_k / J; these turn
    negative under compression. The remaining six eigenvalues (flip modes μ + c σ_k / J and a 3×3
    scaling block) are positive whenever c ≥ 0. Twist eigenvalues below −``tolerance`` · (λ + 2μ) are
    reported (smaller ones are round-off at rotations). Singular values and V come from the closed-form
    eigen-decomposition of FᵀF, U = F V Σ⁻¹; eigenvectors are only computed where needed.
    """
    J = det3(F)
    c = mu - lam * torch.log(J)
    FtF = F.transpose(1, 2) @ F
    e = symmetric_eigenvalues_3x3(FtF)
    twist = mu - (c / J)[:, None] * e.clamp_min(0.0).sqrt()
    general = c < 0
    bad = (twist < -tolerance * (lam + 2.0 * mu)).any(dim=1) & ~general
    index = bad.nonzero()[:, 0]
    if index.numel() == 0:
        return NeoHookeanIndefinite(index, F.new_zeros(0, 3, 3, 3), F.new_zeros(0, 3), general)
    if index.numel() < F.shape[0]:
        F, FtF, e, twist = F[index], FtF[index], e[index], twist[index]
    _, V = symmetric_eigen_3x3(FtF, e)
    S = e.clamp_min(torch.finfo(F.dtype).tiny).sqrt()
    Ut = ((F @ V) / S[:, None, :]).transpose(1, 2)  # rows u_i
    Vt = V.transpose(1, 2)  # rows v_i
    i, j = [1, 0, 0], [2, 2, 1]  # mode k = 0, 1, 2 ↔ pair (i, j)
    D = (Ut[:, i, :, None] * Vt[:, j, None, :] - Ut[:, j, :, None] * Vt[:, i, None, :]) / math.sqrt(2.0)
    return NeoHookeanIndefinite(index, D, (-twist).clamp_min(0.0), general)


def symmetric_eigenvalues_3x3(A: Tensor) -> Tensor:
    """Eigenvalues of symmetric 3×3 matrices A: (N, 3, 3) in closed form (trigonometric method), (N, 3) ascending."""
    q = A.diagonal(dim1=1, dim2=2).sum(-1) / 3.0
    p1 = A[:, 0, 1] ** 2 + A[:, 0, 2] ** 2 + A[:, 1, 2] ** 2
    d = A.diagonal(dim1=1, dim2=2) - q[:, None]
    p = torch.sqrt(((d * d).sum(-1) + 2.0 * p1) / 6.0)
    safe_p = torch.where(p > 0, p, torch.ones_like(p))
    B = (A - q[:, None, None] * torch.eye(3, dtype=A.dtype, device=A.device)) / safe_p[:, None, None]
    r = (det3(B) / 2.0).clamp(-1.0, 1.0)
    phi = torch.acos(r) / 3.0
    e_max = q + 2.0 * p * torch.cos(phi)
    e_min = q + 2.0 * p * torch.cos(phi + 2.0 * math.pi / 3.0)
    e_mid = 3.0 * q - e_max - e_min
    return torch.stack([e_min, e_mid, e_max], dim=-1)


def project_tangent_psd(model: str, F: Tensor, C: Tensor, mu: Scalar, lam: Scalar, tolerance: float = 1e-6) -> Tensor:
    """PSD projection of the tangent C = ∂P/∂F (N, 9, 9) of ``model`` at F (N, 3, 3).

    Neo-Hookean: the tangent's eigenvalues are known in closed form — twist modes μ − c σ_k / J with
    c = μ − λ ln J, and a scaling block that is positive definite whenever c ≥ 0 — so the singular values
    alone (closed-form eigenvalues of FᵀF) tell which points need projecting. Twist modes more negative
    than ``tolerance`` · (λ + 2μ) are clamped in closed form (:func:`neo_hookean_indefinite`); points with
    c < 0 (extreme expansion) go through the general eigendecomposition. Other models: like
    :func:`project_psd`.
    """
    C = 0.5 * (C + C.transpose(1, 2))
    if model != "neo_hookean":
        return project_psd(C, tolerance=tolerance)
    fix = neo_hookean_indefinite(F, mu, lam, tolerance)
    if fix.empty:
        return C
    out = C.clone()
    if fix.twist_index.numel():
        d = fix.twist_modes.reshape(-1, 3, 9)
        out[fix.twist_index] += (d * fix.twist_amount[:, :, None]).transpose(1, 2) @ d
    if bool(fix.general.any()):
        out[fix.general] = project_psd(C[fix.general], tolerance=tolerance)
    return out


def _nearly_pd(H: Tensor, tolerance: float) -> Tensor:
    shift = tolerance * H.diagonal(dim1=1, dim2=2).abs().amax(dim=1)
    eye = torch.eye(H.shape[1], dtype=H.dtype, device=H.device)
    _, info = torch.linalg.cholesky_ex(H + shift[:, None, None] * eye)
    return info == 0
