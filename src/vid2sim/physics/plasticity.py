"""Plastic return maps on the Hencky strain: von Mises (plasticine) and Drucker–Prager (sand).

Paper, supplementary "Generalized to Different Materials" (plasticine and sand use the StVK energy plus
one of these maps). Both act on the singular values of the elastic deformation gradient
``F = U Σ Vᵀ`` through the Hencky strain ``ε = log Σ`` (a 3-vector) and its deviatoric part
``ε̂ = ε − mean(ε)``:

- **von Mises** (yield stress τ_Y):  δγ = ‖ε̂‖ − τ_Y / (2μ).
  δγ ≤ 0 → F unchanged; otherwise ``U exp(ε − δγ ε̂/‖ε̂‖) Vᵀ``, which puts ‖ε̂‖ exactly on τ_Y/(2μ)
  and keeps tr ε (the volume change).
- **Drucker–Prager** (friction angle θ_f):  α = √(2/3) · 2 sin θ_f / (3 − sin θ_f),
  δγ = ‖ε̂‖ + α (3λ + 2μ) tr ε / (2μ).
  tr ε > 0 (expansion: sand has no cohesion) → ``U Vᵀ`` (all elastic strain released);
  δγ ≤ 0 → F unchanged; otherwise ``U exp(ε − δγ ε̂/‖ε̂‖) Vᵀ`` (onto the cone
  ‖ε̂‖ = −α (3λ + 2μ) tr ε / (2μ), tr ε kept).

The maps are isotropic, so ``map(R F Q) = R map(F) Q`` for rotations R, Q, and the result does not depend
on which SVD was picked. The SVD is made a *rotation-variant* one here (U, V proper rotations, Σ > 0),
which for det F > 0 only needs a shared sign flip of one column of U and V.

The simulator keeps, per cubature point, the inverse plastic deformation gradient ``Fp⁻¹`` with
``F = F_e F_p`` (the elastic energy is evaluated on ``F_e = F Fp⁻¹``). After every converged implicit
step it calls :func:`update_plastic_state`. The maps update state between steps: they run without
autograd (no gradient flows through the plastic update) and never produce NaN for det F > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Union

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError

Scalar = Union[float, Tensor]

__all__ = [
    "VonMises",
    "DruckerPrager",
    "PlasticityModel",
    "return_map",
    "yield_function",
    "update_plastic_state",
    "rotation_svd",
    "plasticity_from_dict",
]


def _finite_float(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


@dataclass(frozen=True)
class VonMises:
    """Von Mises return map on the Hencky strain (the paper's plasticine).

    Attributes:
        yield_stress: τ_Y in Pa (> 0); the paper's plasticine example uses 500. The deviatoric Hencky
            strain is capped at ‖ε̂‖ = τ_Y / (2μ).
    """

    yield_stress: float = 500.0

    def __post_init__(self) -> None:
        v = _finite_float(self.yield_stress, "VonMises.yield_stress")
        if not v > 0:
            raise ConfigError(f"VonMises.yield_stress must be > 0 (Pa), got {v}")
        object.__setattr__(self, "yield_stress", v)

    def to_dict(self) -> dict:
        """{"type": "von_mises", "yield_stress": τ_Y}."""
        return {"type": "von_mises", "yield_stress": self.yield_stress}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "VonMises":
        """Inverse of :meth:`to_dict`."""
        return cls(**_fields_from_dict(d, "von_mises", ("yield_stress",)))


@dataclass(frozen=True)
class DruckerPrager:
    """Drucker–Prager return map on the Hencky strain (the paper's sand; no cohesion, no hardening).

    Attributes:
        friction_angle_deg: θ_f in degrees, 0 < θ_f < 90; the paper's sand example uses 10°.
    """

    friction_angle_deg: float = 10.0

    def __post_init__(self) -> None:
        v = _finite_float(self.friction_angle_deg, "DruckerPrager.friction_angle_deg")
        if not 0.0 < v < 90.0:
            raise ConfigError(f"DruckerPrager.friction_angle_deg must satisfy 0 < theta_f < 90 (degrees), got {v}")
        object.__setattr__(self, "friction_angle_deg", v)

    @property
    def alpha(self) -> float:
        """α = √(2/3) · 2 sin θ_f / (3 − sin θ_f)."""
        s = math.sin(math.radians(self.friction_angle_deg))
        return math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)

    def to_dict(self) -> dict:
        """{"type": "drucker_prager", "friction_angle_deg": θ_f}."""
        return {"type": "drucker_prager", "friction_angle_deg": self.friction_angle_deg}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "DruckerPrager":
        """Inverse of :meth:`to_dict`."""
        return cls(**_fields_from_dict(d, "drucker_prager", ("friction_angle_deg",)))


PlasticityModel = Union[VonMises, DruckerPrager]

_MODEL_TYPES = {"von_mises": VonMises, "drucker_prager": DruckerPrager}


def plasticity_from_dict(d: Mapping[str, Any]) -> PlasticityModel:
    """Build a :class:`VonMises` or :class:`DruckerPrager` from its ``to_dict()`` form (dispatch on "type")."""
    if not isinstance(d, Mapping):
        raise ValueError(f"plasticity config must be a mapping with a 'type' key, got {type(d).__name__}")
    kind = d.get("type")
    if kind not in _MODEL_TYPES:
        raise ValueError(f"unknown plasticity type {kind!r}; expected one of {sorted(_MODEL_TYPES)}")
    return _MODEL_TYPES[kind].from_dict(d)


def _fields_from_dict(d: Mapping[str, Any], kind: str, allowed: tuple[str, ...]) -> dict:
    if not isinstance(d, Mapping):
        raise ValueError(f"{kind} config must be a mapping, got {type(d).__name__}")
    if d.get("type", kind) != kind:
        raise ValueError(f"config type {d.get('type')!r} does not match {kind!r}")
    extra = sorted(set(d) - set(allowed) - {"type"})
    if extra:
        raise ValueError(f"unknown {kind} config field(s) {extra}; expected {list(allowed)}")
    return {k: d[k] for k in allowed if k in d}


# ---- SVD and Hencky strain ----------------------------------------------------------------------

def _check_F(F: Tensor, name: str) -> None:
    if not isinstance(F, Tensor) or F.ndim != 3 or F.shape[1:] != (3, 3):
        shape = tuple(F.shape) if isinstance(F, Tensor) else type(F).__name__
        raise ValueError(f"{name} must have shape (N, 3, 3), got {shape}")
    if not F.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {F.dtype}")
    if not bool(torch.isfinite(F).all()):
        raise ValueError(f"{name} contains non-finite values")


def rotation_svd(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rotation-variant SVD ``F = U diag(S) Vᵀ`` with U, V proper rotations and S > 0.

    Args:
        F: (N, 3, 3) with det F > 0.
    Returns:
        U: (N, 3, 3), S: (N, 3) (descending), V: (N, 3, 3)  — note V, not Vᵀ.
    Raises:
        ValueError: if any det F ≤ 0 (an inverted point has no real Hencky strain).
    """
    _check_F(F, "F")
    det = torch.linalg.det(F)
    if not bool((det > 0).all()):
        bad = int((det <= 0).nonzero()[0, 0])
        raise ValueError(
            f"plastic return map needs det F > 0 at every point; point {bad} has det F = {float(det[bad]):.6g}"
        )
    U, S, Vh = torch.linalg.svd(F)
    V = Vh.transpose(1, 2)
    # det F > 0 and S ≥ 0 ⇒ det U · det V = +1: either both rotations or both reflections. Flipping the
    # last column of both keeps U diag(S) Vᵀ unchanged and makes them rotations.
    flip = torch.linalg.det(U) < 0
    sign = torch.ones_like(S)
    sign[:, 2] = torch.where(flip, -1.0, 1.0).to(S.dtype)
    return U * sign[:, None, :], S, V * sign[:, None, :]


def _as_column(value: Scalar, n: int, like: Tensor, name: str) -> Tensor:
    """A scalar or (N,) parameter as a detached (N,) tensor."""
    v = torch.as_tensor(value.detach() if isinstance(value, Tensor) else value, dtype=like.dtype, device=like.device)
    if v.ndim == 0:
        v = v.expand(n)
    elif v.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} must be finite")
    return v


def _lame(mu: Scalar, lam: Scalar, n: int, like: Tensor) -> tuple[Tensor, Tensor]:
    mu_t = _as_column(mu, n, like, "mu")
    lam_t = _as_column(lam, n, like, "lam")
    if not bool((mu_t > 0).all()):
        raise ValueError(f"mu (shear modulus) must be > 0, got min {float(mu_t.min()):.6g}")
    return mu_t, lam_t


def _hencky(S: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """ε (N,3), ε̂ (N,3), ‖ε̂‖ (N,), tr ε (N,) from the singular values S (N,3)."""
    eps = torch.log(S)
    tr = eps.sum(dim=1)
    dev = eps - tr[:, None] / 3.0
    return eps, dev, dev.norm(dim=1), tr


def _yield(model: PlasticityModel, norm: Tensor, tr: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    if isinstance(model, VonMises):
        return norm - model.yield_stress / (2.0 * mu)
    if isinstance(model, DruckerPrager):
        return norm + model.alpha * (3.0 * lam + 2.0 * mu) * tr / (2.0 * mu)
    raise ValueError(f"plasticity model must be VonMises or DruckerPrager, got {type(model).__name__}")


# ---- public maps --------------------------------------------------------------------------------

def yield_function(model: PlasticityModel, F: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """The paper's δγ at each point, (N,): > 0 means outside the elastic region (the point yields).

    For Drucker–Prager, points with tr ε > 0 also yield (they are mapped to U Vᵀ) whatever δγ says.

    Args:
        model: :class:`VonMises` or :class:`DruckerPrager`.
        F: (N, 3, 3) elastic deformation gradients, det F > 0.
        mu, lam: Lamé parameters, scalars or (N,).
    """
    with torch.no_grad():
        _, S, _ = rotation_svd(F)
        mu_t, lam_t = _lame(mu, lam, F.shape[0], F)
        _, _, norm, tr = _hencky(S)
        return _yield(model, norm, tr, mu_t, lam_t)


def _map_strain(model: PlasticityModel, F: Tensor, mu: Scalar, lam: Scalar):
    """Shared core: (U, V, ε, ε', yielded) for F: (N, 3, 3) — ε' the mapped Hencky strain (N, 3)."""
    if not isinstance(model, (VonMises, DruckerPrager)):
        raise ValueError(f"plasticity model must be VonMises or DruckerPrager, got {type(model).__name__}")
    U, S, V = rotation_svd(F)
    mu_t, lam_t = _lame(mu, lam, F.shape[0], F)
    eps, dev, norm, tr = _hencky(S)
    dgamma = _yield(model, norm, tr, mu_t, lam_t)
    # ‖ε̂‖ = 0 with δγ > 0 cannot occur (VM: δγ = −τ_Y/2μ < 0; DP with tr ε ≤ 0: δγ ≤ 0), but guard
    # the division so masked-out lanes never produce inf/NaN.
    safe_norm = torch.where(norm > 0, norm, torch.ones_like(norm))
    eps_new = eps - (dgamma / safe_norm)[:, None] * dev
    yielded = dgamma > 0
    if isinstance(model, DruckerPrager):
        expand = tr > 0
        eps_new = torch.where(expand[:, None], torch.zeros_like(eps_new), eps_new)
        yielded = yielded | expand
    return U, V, eps, eps_new, yielded


def return_map(model: PlasticityModel, F_trial: Tensor, mu: Scalar, lam: Scalar) -> Tensor:
    """Project trial elastic deformation gradients back onto the elastic region (paper's Z(F)).

    Args:
        model: :class:`VonMises` (plasticine) or :class:`DruckerPrager` (sand).
        F_trial: (N, 3, 3) trial elastic deformation gradients, det > 0.
        mu, lam: Lamé parameters (floats, 0-d or (N,) tensors; detached — no gradient flows through).
    Returns:
        F_elastic: (N, 3, 3), same dtype/device. Points inside the elastic region are returned bit-for-bit
        unchanged; the others are rebuilt as ``U exp(ε') Vᵀ``.
    """
    with torch.no_grad():
        F = F_trial.detach()
        U, V, _, eps_new, yielded = _map_strain(model, F, mu, lam)
        if not bool(yielded.any()):
            return F.clone()
        F_new = (U * torch.exp(eps_new)[:, None, :]) @ V.transpose(1, 2)
        return torch.where(yielded[:, None, None], F_new, F)


def update_plastic_state(
    model: PlasticityModel, F_total: Tensor, Fp_inv: Tensor, mu: Scalar, lam: Scalar
) -> Tensor:
    """New inverse plastic deformation gradient after a converged step.

    With ``F = F_e F_p``: the trial elastic part is ``F_e,trial = F Fp⁻¹ = U Σ Vᵀ``; it is return-mapped
    to ``F_e = U exp(ε') Vᵀ`` and the plastic part becomes ``F_p = F_e⁻¹ F``, i.e. the stored inverse is
    ``Fp⁻¹ ← F⁻¹ F_e = Fp⁻¹ V diag(exp(ε' − ε)) Vᵀ`` (no matrix inverse needed), so that
    ``F · Fp⁻¹_new = F_e``. Points that did not yield keep their ``Fp⁻¹`` bit-for-bit (no round-off drift
    over many steps). The inverse is stored because the energy is evaluated on ``F_e = F Fp⁻¹`` (folded
    into the reduced basis by the solver).

    Args:
        model: :class:`VonMises` or :class:`DruckerPrager`.
        F_total: (N, 3, 3) total deformation gradients at the cubature points (det > 0).
        Fp_inv: (N, 3, 3) current inverse plastic deformation gradients (identity at rest).
        mu, lam: Lamé parameters, scalars or (N,).
    Returns:
        (N, 3, 3) new inverse plastic deformation gradients (no autograd graph).
    """
    _check_F(F_total, "F_total")
    _check_F(Fp_inv, "Fp_inv")
    if Fp_inv.shape != F_total.shape:
        raise ValueError(f"Fp_inv must have the shape of F_total {tuple(F_total.shape)}, got {tuple(Fp_inv.shape)}")
    with torch.no_grad():
        A = Fp_inv.detach()
        _, V, eps, eps_new, yielded = _map_strain(model, F_total.detach() @ A, mu, lam)
        if not bool(yielded.any()):
            return A.clone()
        A_new = A @ ((V * torch.exp(eps_new - eps)[:, None, :]) @ V.transpose(1, 2))
        return torch.where(yielded[:, None, None], A_new, A)
