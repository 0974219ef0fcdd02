"""The projected volumetric term: the subspace's cure for volumetric locking (an F-bar method in the weights' span).

A skinning subspace with a few handles cannot bend without changing volume the way the continuum does: bending
one handle's region stretches one side and squeezes the other, and the pointwise volumetric energy
λ/2 Σ_p v_p (ln J_p)² charges that spurious volume change as if it were real. The subspace is then too stiff,
more and more as ν → ½ (measured on ``bench identify`` objects: the lowest frequency 1.02–1.15 × the
continuum's at ν = 0.3 and 1.22–1.46 × at 0.49), and a calibration has to take the stiffness out of λ, which
also takes out what ν does to the motion.

With ``Simulator(volumetric="projected")`` the volumetric strain ln J is replaced, in the λ term only, by its
v-weighted L² projection onto the span of the skinning weights (which contains the constants):

    ℓ̄ = P ℓ,   P = W (Wᵀ V W)⁻¹ Wᵀ V,   Ψ_vol = λ/2 Σ_p v_p ℓ̄_p²  (= λ/2 ℓᵀ V P ℓ),

with ℓ_p = ln J_p, W (K, H) the weights at the cubature points and V = diag(v). This is the mixed (u–p)
formulation whose pressure lives in the weights' span, the same idea as F-bar and B-bar in finite elements:
H volumetric constraints against 12H degrees of freedom, so the incompressible limit does not lock. A uniform
volume change (any affine deformation) is projected onto itself, so the bulk response is unchanged; the
per-handle volume change an impact's squash makes is kept; only the variation of ln J that the weights
cannot express (the bending's tension/compression pattern) no longer costs λ.

The stress at point p becomes λ ℓ̄_p F_p⁻ᵀ, and the Hessian gains the non-local, rank-H term
λ (Woᵀ V B)ᵀ (Woᵀ V B), with B_p = ∂ℓ_p/∂y and Wo the V-orthonormal basis of the span
(:func:`projection_basis`).

The Kelvin–Voigt damping (:mod:`vid2sim.physics.damping`) is τ times the same stiffness, so its λ term is projected
the same way: the trace of the rate strain G = ½ (FᵀF − C_ref) is replaced by its projection ḡ = P tr G, the
viscous stress gains τ-scaled λ ḡ_p F_p and the Hessian the rank-H λ (Woᵀ V B_g)ᵀ (Woᵀ V B_g), B_g,p = ∂ tr G_p / ∂y.
Left pointwise, the spurious volume change of a bending subspace is charged to the viscosity τλ: the impact
loses more energy than the continuum's and more the higher ν.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: the values ``Simulator(volumetric=...)`` takes
VOLUMETRIC_TERMS = ("pointwise", "projected")


def check_volumetric(value: object, model: str) -> str:
    """``value`` validated as a volumetric term for the elastic ``model`` (raises ValueError)."""
    if value not in VOLUMETRIC_TERMS:
        raise ValueError(f"volumetric must be one of {VOLUMETRIC_TERMS}, got {value!r}")
    if value == "projected" and model != "neo_hookean":
        raise ValueError(f"volumetric='projected' needs the neo_hookean model (its ln J term), got {model!r}")
    return str(value)


def projection_basis(w: Tensor, vol: Tensor) -> Tensor:
    """V-orthonormal basis Wo (K, H) of the span of the weights: Woᵀ V Wo = I. Differentiable in ``w``.

    Args:
        w: (K, H) skinning weights at the cubature points (the constant handle included).
        vol: (K,) their integration weights v.
    Raises:
        ValueError: when the weights are linearly dependent at these points (their Gram matrix is singular).
    """
    wd = w.double()  # the Gram matrix squares the weights' conditioning: float64 whatever the simulator's dtype
    gram = wd.T @ (wd * vol.double()[:, None])
    chol, info = torch.linalg.cholesky_ex(gram)
    # a column whose part outside the span of the ones before it is below 1e-5 of its norm counts as dependent
    # (a factorisation of a singular matrix may succeed in rounding)
    if int(info) != 0 or bool((chol.diagonal() ** 2 <= 1e-10 * gram.diagonal()).any()):
        raise ValueError(f"the skinning weights are linearly dependent at the {w.shape[0]} cubature points "
                         f"(their {w.shape[1]} x {w.shape[1]} Gram matrix is singular): the projected volumetric "
                         "term needs independent weights")
    return torch.linalg.solve_triangular(chol, wd.T, upper=False).T.to(w.dtype)  # W L⁻ᵀ


def project(basis: Tensor, vol: Tensor, values: Tensor) -> Tensor:
    """P values (K,): the v-weighted L² projection of per-point ``values`` (K,) onto the span of ``basis``."""
    return basis @ (basis.T @ (vol * values))


def swap_tangent(F: Tensor) -> Tensor:
    """∂(F⁻ᵀ)/∂F = −T with T[(i, j), (k, l)] = F⁻¹_jk F⁻¹_li: returns T, (N, 9, 9)."""
    n = F.shape[0]
    A = torch.linalg.inv(F).transpose(1, 2).reshape(n, 9)  # F⁻ᵀ row-major: A[(i, l)] = F⁻¹_li
    outer = A[:, :, None] * A[:, None, :]  # [(i, j), (k, l)] = A_ij A_kl
    return outer.reshape(n, 3, 3, 3, 3).permute(0, 1, 4, 3, 2).reshape(n, 9, 9)
