"""Material damping shared by the reduced simulator and the FEM ground truth: Kelvin–Voigt viscosity on
the Green-strain rate.

Model
-----
The viscous second Piola–Kirchhoff stress is that of St. Venant–Kirchhoff applied to the strain *rate*,

    S_v = 2 η_μ Ė + η_λ tr(Ė) I,          Ė = ½ d/dt (FᵀF),

with viscosities proportional to the elastic Lamé parameters, η_μ = τ μ and η_λ = τ λ. τ (seconds) is the
*retardation time*. Ė is unchanged by rigid motion, so a tumbling object is not slowed down; in the small-
strain limit S_v = τ σ(ε̇) and the model is stiffness-proportional Rayleigh damping C = τ K: an elastic
mode of angular frequency ω has the damping ratio ζ(ω) = τ ω / 2 (higher modes are damped more, as in
real rubber-like solids). It derives from the Rayleigh dissipation function
R = Σ_p v_p [η_μ ‖Ė_p‖² + η_λ/2 tr(Ė_p)²], whose velocity gradient is the damping force.

Parameter
---------
Users give a dimensionless **damping ratio** ζ at the reference angular frequency ω_ref = c / L, with the
bar-wave speed c = √(E/ρ) and the object's size L (by default the diagonal of its rest bounding box):

    τ = 2 ζ / ω_ref = 2 ζ L √(ρ / E).

So the same ζ gives every stiffness the same damping ratio on its own elastic time scale (η ∝ √(E ρ) L),
and a soft and a stiff object bounce alike in proportion. The lowest elastic mode of a compact object
has ω₁ ≈ 3–6 ω_ref, so its damping ratio is ≈ 3–6 ζ. ζ = 0 is the undamped model.

Time discretisation
-------------------
With a backward-differentiation step ẏ_{n+1} = (a₀ y_{n+1} − a₁ y_n − a₂ y_{n−1}) / h
(:mod:`vid2sim.physics.integrators`) the same formula discretises the strain rate,
Ė ≈ a₀ (C − C_ref) / (2h) with C = FᵀF and C_ref = (a₁ C_n + a₂ C_{n−1}) / a₀ (:func:`reference_metric`).
The damping force at the end of the step is then a gradient: h/a₀ · ∂R/∂y = τ a₀/h · ∂/∂y Σ_p v_p ψ(G_p) with

    ψ(G) = μ tr(G²) + λ/2 tr(G)²,    G = ½ (FᵀF − C_ref),

the StVK energy density measured from the metric C_ref instead of I
(:func:`vid2sim.physics.materials.stvk_energy_density` with ``C_ref``), so each implicit step stays the
minimisation of one incremental potential.
"""

from __future__ import annotations

import math
from typing import Union

import torch
from torch import Tensor

from vid2sim.physics.materials import stvk_energy_density, stvk_pk1, stvk_tangent

Scalar = Union[float, Tensor]

#: Default damping ratio ζ at ω_ref = √(E/ρ)/L (see the module docstring and docs/architecture.md).
DEFAULT_DAMPING_RATIO = 0.05


def check_damping_ratio(value: float, name: str = "damping_ratio") -> float:
    """Validate a damping ratio ζ (finite, ≥ 0) and return it as a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0 (0 = undamped), got {value!r}")
    return float(value)


def retardation_time(damping_ratio: Scalar, youngs_modulus: Scalar, density: Scalar, length: float) -> Scalar:
    """Kelvin–Voigt retardation time τ = 2 ζ L √(ρ / E) in seconds (differentiable in tensors).

    Args:
        damping_ratio: ζ ≥ 0 at ω_ref = √(E/ρ) / L.
        youngs_modulus: E in Pa.
        density: ρ in kg/m³.
        length: L in metres (the object's size), > 0.
    """
    if not (isinstance(length, (int, float)) and length > 0 and math.isfinite(length)):
        raise ValueError(f"the damping length scale must be a positive finite number of metres, got {length!r}")
    if isinstance(youngs_modulus, Tensor) or isinstance(density, Tensor) or isinstance(damping_ratio, Tensor):
        E = torch.as_tensor(youngs_modulus)
        rho = torch.as_tensor(density, dtype=E.dtype)
        return 2.0 * damping_ratio * length * torch.sqrt(rho / E)
    return 2.0 * float(damping_ratio) * length * math.sqrt(float(density) / float(youngs_modulus))


def viscous_energy_density(F: Tensor, C_ref: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """ψ(G) = μ tr(G²) + λ/2 tr(G)² with G = ½ (FᵀF − C_ref); F, C_ref: (N, 3, 3) → (N,)."""
    return stvk_energy_density(F, mu, lam, C_ref)


def viscous_pk1(F: Tensor, C_ref: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """∂ψ/∂F = F (2μ G + λ tr(G) I), (N, 3, 3)."""
    return stvk_pk1(F, mu, lam, C_ref)


def viscous_tangent(F: Tensor, C_ref: Tensor, mu: Scalar, lam: Scalar, psd: bool = False) -> Tensor:
    """∂²ψ/∂F², (N, 9, 9) (row-major vec F); ``psd`` gives a positive semi-definite surrogate
    (:func:`vid2sim.physics.materials.stvk_tangent`)."""
    return stvk_tangent(F, mu, lam, C_ref, psd=psd)


def reference_metric(coefficients: tuple[float, float, float], F_prev: Tensor, F_prev2: Tensor | None) -> Tensor:
    """C_ref = (a₁ F_nᵀF_n + a₂ F_{n−1}ᵀF_{n−1}) / a₀, (N, 3, 3), for BDF coefficients a = (a₀, a₁, a₂)."""
    a0, a1, a2 = coefficients
    C = (a1 / a0) * (F_prev.transpose(1, 2) @ F_prev)
    if a2 != 0.0:
        if F_prev2 is None:
            raise ValueError("this integrator needs the deformation two steps back (F_prev2)")
        C = C + (a2 / a0) * (F_prev2.transpose(1, 2) @ F_prev2)
    return C
