"""The subspace's stiffness correction as a smooth function of Poisson's ratio: s(ν).

A skinning subspace with a few handles cannot bend without changing volume the way the continuum does, so
its volumetric term stiffens it more and more as ν → ½ (volumetric locking). Measured on a ``bench identify``
shape with 10 handles, its lowest frequency is 1.04 × that of quadratic tets at ν = 0.3 and 1.19 × at
ν = 0.49, while the continuum's own frequency at a fixed E *falls* by 5 % over ν ∈ [0.2, 0.49]. A single factor
measured at the prior ν corrects E at that ν only; a fit that moves ν then meets a stiffness the continuum
does not have and is pushed towards small ν.

:class:`StiffnessCurve` holds s at a grid of ν (:func:`vid2sim.physics.modes.stiffness_calibration_curve`
measures it) and interpolates log s with a monotone cubic (Fritsch–Carlson), so that s(ν) and ds/dν are
continuous and the simulator's adjoint carries the gradient to ν through it
(``Simulator(stiffness_scale=curve)``). Outside the grid s is held at the end values.

The locking is volumetric, so one factor on the whole energy corrects the lowest mode only: it leaves the
squash of an impact too stiff (measured: a soft ``bench identify`` object squashed 6.8 % of its size where the
continuum squashes 8.6 %) and the next modes off by up to 8 %. A curve with ``lam_scale`` scales the two Lamé
parameters separately, μ by s(ν) and λ by s_λ(ν) (:func:`~vid2sim.physics.modes.stiffness_calibration_curve`
with ``factors=2`` fits both to the six lowest modes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError


def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch–Carlson slopes of the monotone piecewise-cubic Hermite interpolant through (x, y)."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    if len(x) == 2:
        return np.full_like(y, delta[0])
    for k in range(1, len(x) - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            d[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
    for end, (k0, k1) in ((0, (0, 1)), (-1, (-1, -2))):  # three-point end slopes, kept shape-preserving
        hk0, hk1 = h[k0], h[k1]
        dk0, dk1 = delta[k0], delta[k1]
        slope = ((2 * hk0 + hk1) * dk0 - hk0 * dk1) / (hk0 + hk1)
        if np.sign(slope) != np.sign(dk0):
            slope = 0.0
        elif np.sign(dk0) != np.sign(dk1) and abs(slope) > abs(3 * dk0):
            slope = 3 * dk0
        d[end] = slope
    return d


@dataclass(frozen=True)
class StiffnessCurve:
    """s(ν) > 0 at increasing grid values of ν, interpolated smoothly in log s.

    Attributes:
        nu: (n,) strictly increasing grid of Poisson's ratios in [0, 0.5), n ≥ 2.
        scale: (n,) s at those ν, finite and positive: the factor on E (on μ, and on λ too unless
            ``lam_scale`` is given).
        lam_scale: None, or (n,) the factor s_λ on λ alone at those ν, finite and positive.
    """

    nu: tuple[float, ...]
    scale: tuple[float, ...]
    lam_scale: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        nu = tuple(float(v) for v in self.nu)
        scale = tuple(float(v) for v in self.scale)
        if len(nu) < 2 or len(nu) != len(scale):
            raise ConfigError(
                f"StiffnessCurve needs n >= 2 values of nu and as many scales, got {len(nu)} and {len(scale)}"
            )
        if not all(0.0 <= v < 0.5 for v in nu) or any(b <= a for a, b in zip(nu, nu[1:])):
            raise ConfigError(f"StiffnessCurve.nu must increase strictly within [0, 0.5), got {nu}")
        if not all(math.isfinite(s) and s > 0 for s in scale):
            raise ConfigError(f"StiffnessCurve.scale must be finite and positive, got {scale}")
        object.__setattr__(self, "nu", nu)
        object.__setattr__(self, "scale", scale)
        if self.lam_scale is not None:
            lam_scale = tuple(float(v) for v in self.lam_scale)
            if len(lam_scale) != len(nu) or not all(math.isfinite(s) and s > 0 for s in lam_scale):
                raise ConfigError(
                    f"StiffnessCurve.lam_scale must hold {len(nu)} finite positive values, got {lam_scale}"
                )
            object.__setattr__(self, "lam_scale", lam_scale)

    def _tables(self, values: tuple[float, ...] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.asarray(self.nu)
        y = np.log(np.asarray(self.scale if values is None else values))
        return x, y, _pchip_slopes(x, y)

    def __call__(self, nu: Tensor) -> Tensor:
        """s at ``nu`` (0-d tensor), differentiable in ``nu``; the end values outside the grid."""
        return self._interpolate(nu, self.scale)

    def lam_factor(self, nu: Tensor) -> Tensor:
        """The factor on λ alone at ``nu`` relative to :meth:`__call__`'s factor on E: s_λ(ν)/s(ν) (1 without
        ``lam_scale``), differentiable in ``nu``; so λ = s_λ λ(E, ν) = λ(E s, ν) · lam_factor."""
        if self.lam_scale is None:
            return torch.ones_like(nu)
        return self._interpolate(nu, self.lam_scale) / self._interpolate(nu, self.scale)

    def _interpolate(self, nu: Tensor, values: tuple[float, ...]) -> Tensor:
        x, y, d = (torch.as_tensor(a, dtype=nu.dtype, device=nu.device) for a in self._tables(values))
        inside = nu.clamp(x[0], x[-1])
        k = torch.searchsorted(x, inside.detach().reshape(1), right=True).clamp(1, len(x) - 1)[0] - 1
        h = x[k + 1] - x[k]
        t = (inside - x[k]) / h
        t2, t3 = t * t, t * t * t
        log_s = ((2 * t3 - 3 * t2 + 1) * y[k] + (t3 - 2 * t2 + t) * h * d[k]
                 + (-2 * t3 + 3 * t2) * y[k + 1] + (t3 - t2) * h * d[k + 1])
        return torch.exp(log_s)

    def at(self, nu: float) -> float:
        """s at the number ``nu``."""
        return float(self(torch.tensor(float(nu), dtype=torch.float64)))

    def lam_at(self, nu: float) -> float:
        """s_λ at the number ``nu`` (the factor on λ; equals :meth:`at` without ``lam_scale``)."""
        return self.at(nu) * float(self.lam_factor(torch.tensor(float(nu), dtype=torch.float64)))

    def to_dict(self) -> dict[str, Any]:
        """{"nu": [...], "scale": [...]} and, with two factors, "lam_scale": [...] (JSON-ready)."""
        out: dict[str, Any] = {"nu": list(self.nu), "scale": list(self.scale)}
        if self.lam_scale is not None:
            out["lam_scale"] = list(self.lam_scale)
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "StiffnessCurve":
        """The inverse of :meth:`to_dict`; a clear ``ValueError`` for anything else."""
        if not isinstance(values, dict) or not {"nu", "scale"} <= set(values) <= {"nu", "scale", "lam_scale"}:
            raise ConfigError("a stiffness curve must be {'nu': [...], 'scale': [...]} with an optional "
                             f"'lam_scale': [...], got {values!r}")
        lam = values.get("lam_scale")
        return cls(tuple(values["nu"]), tuple(values["scale"]), None if lam is None else tuple(lam))
