"""External potential energies on the world positions of simulation points: gravity and barrier contacts.

Paper, supplementary "Boundary Condition Implementation": contacts are penalty barriers that add potential
energy, e.g. the floor ``E_f = 1e5 · Σ_i max(0, h_f − z_i)²``; other barriers (a moving floor, spheres —
supplementary "Generalized to Complex Boundary Conditions") follow the same pattern
``E = k Σ_i w_i max(0, −signed_distance(x_i, t))²``. Gravity is ``E_g = −Σ_i m_i g·x_i``.

Every energy is a sum over points with a per-point weight ``w_i``, so its Hessian w.r.t. all positions is
block diagonal. The weights mean: for the body force (:class:`Gravity`, ``kind = "body"``) the point masses
in kg, evaluated at the simulator's cubature points; for the barriers (``kind = "contact"``) a factor on each
point's penalty, evaluated at the simulator's *contact points* — weight 1 on the cubature points is the
paper's per-point formula, surface samples weighted by their area make the penalty a contact pressure
k · depth (Pa) integrated over the surface, independent of how finely the surface is sampled. ``hessian``
returns the per-point 3×3 blocks (N, 3, 3), projected to positive semi-definite (exactly: the eigenvalues
of each block are clamped at 0) unless ``project=False``. Energies and gradients are plain differentiable
torch expressions of ``x`` (and ``weights``), so ``torch.autograd.grad(..., create_graph=True)`` works
through them (the solver's adjoint differentiates the gradient).

Common interface (:class:`ExternalEnergy`), with ``x: (N, 3)`` world positions in metres, ``weights: (N,)``
per-point weights (above), ``t`` time in seconds:

- ``kind``: "body" or "contact"
- ``energy(x, weights, t) -> ()``
- ``gradient(x, weights, t) -> (N, 3)``
- ``hessian(x, weights, t, project=True) -> (N, 3, 3)``
- ``energy_and_gradient(x, weights, t) -> ((), (N, 3))``: both in one pass (what the solver calls; use
  :func:`energy_and_gradient` for energies that only define the two separately)
- ``to_dict() -> dict`` and ``from_dict(d)``; :func:`external_from_dict` dispatches on ``d["type"]``
  ('gravity', 'floor', 'moving_floor', 'sphere').

Barriers also carry a Coulomb friction coefficient ``friction`` (μ ≥ 0; 0, the paper's frictionless contact, by
default) and the slip speed ``friction_velocity`` (ε_v, m/s) below which friction is smoothed to a stiff viscous
law, and give ``surface_velocity(x, t) -> (N, 3)``, the velocity of the barrier's surface at the points x (the
friction acts on the slip relative to it). The friction itself is a dissipation potential of the implicit step
(:class:`vid2sim.physics.reduced.StepProblem`), not an energy here.

World frame z-up (docs/architecture.md, "The paper's numbers"). Parameters are plain floats (serialisable); tensors are
built on the
device/dtype of ``x`` at each call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Mapping, Protocol, Sequence, runtime_checkable

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError

__all__ = [
    "AREA_CONTACT_STIFFNESS",
    "FRICTION_VELOCITY",
    "ExternalEnergy",
    "Gravity",
    "Floor",
    "MovingFloor",
    "SphereObstacle",
    "energy_and_gradient",
    "total_external",
    "external_from_dict",
]


@runtime_checkable
class ExternalEnergy(Protocol):
    """A per-point separable external potential (see the module docstring for shapes and units)."""

    kind: ClassVar[str]  # "body" (weights = masses, at cubature points) or "contact" (at contact points)

    def energy(self, x: Tensor, mass: Tensor, t: float) -> Tensor:
        """Total energy, a 0-d tensor."""
        ...

    def gradient(self, x: Tensor, mass: Tensor, t: float) -> Tensor:
        """∂E/∂x, (N, 3)."""
        ...

    def hessian(self, x: Tensor, mass: Tensor, t: float, project: bool = True) -> Tensor:
        """Per-point blocks ∂²E/∂x_i², (N, 3, 3); PSD-projected when ``project``."""
        ...

    def to_dict(self) -> dict:
        """A JSON/YAML-serialisable dict with a "type" key."""
        ...


#: Barrier stiffness κ (Pa per metre of penetration) for contact points weighted by their surface area
#: (m²): the FEM ground truth's floor and the reconstruction's contact points use it. At the small preset
#: it is about what the paper's 1e5 per point gives per FEM surface vertex (5–7e7); a resting 1 m object
#: sinks in by a fraction of a millimetre.
AREA_CONTACT_STIFFNESS = 5e7


# ---- validation helpers -------------------------------------------------------------------------

def _real(value: Any, name: str) -> float:
    if isinstance(value, bool) or (not isinstance(value, (int, float)) and not _is_numpy_scalar(value)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def _is_numpy_scalar(value: Any) -> bool:
    return type(value).__module__ == "numpy" and getattr(value, "shape", None) == ()


def _positive(value: Any, name: str) -> float:
    v = _real(value, name)
    if not v > 0:
        raise ValueError(f"{name} must be > 0, got {v}")
    return v


def _vector(value: Any, n: int, name: str) -> tuple[float, ...]:
    if isinstance(value, Tensor):
        value = value.detach().cpu().tolist()
    elif type(value).__module__ == "numpy":
        value = value.tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise ValueError(f"{name} must be a sequence of {n} numbers, got {value!r}")
    if len(value) != n:
        raise ValueError(f"{name} must have {n} components, got {len(value)}: {list(value)!r}")
    return tuple(_real(v, f"{name}[{i}]") for i, v in enumerate(value))


def _check_inputs(x: Tensor, mass: Tensor, t: float) -> float:
    if not isinstance(x, Tensor) or x.ndim != 2 or x.shape[1] != 3:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"positions x must have shape (N, 3), got {shape}")
    if not isinstance(mass, Tensor) or mass.shape != (x.shape[0],):
        shape = tuple(mass.shape) if isinstance(mass, Tensor) else type(mass).__name__
        raise ValueError(f"per-point weights must have shape ({x.shape[0]},) to match x, got {shape}")
    tf = float(t.detach()) if isinstance(t, Tensor) else t
    return _real(tf, "time t")


def _friction(value: Any, name: str) -> float:
    v = _real(value, name)
    if v < 0:
        raise ValueError(f"{name} must be a Coulomb coefficient >= 0 (0: frictionless), got {v}")
    return v


def _check_friction(obj: Any, cls: str) -> None:
    object.__setattr__(obj, "friction", _friction(obj.friction, f"{cls}.friction"))
    object.__setattr__(obj, "friction_velocity", _positive(obj.friction_velocity, f"{cls}.friction_velocity"))


#: ε_v (m/s): below this slip speed a barrier's Coulomb friction is smoothed to a viscous law (the stick regime
#: creeps at most this fast); the independent engine's default is the same.
FRICTION_VELOCITY = 1e-2


def _from_dict(cls, d: Mapping[str, Any], kind: str):
    if not isinstance(d, Mapping):
        raise ValueError(f"{kind} config must be a mapping, got {type(d).__name__}")
    if d.get("type", kind) != kind:
        raise ValueError(f"config type {d.get('type')!r} does not match {kind!r}")
    names = [f.name for f in fields(cls)]
    extra = sorted(set(d) - set(names) - {"type"})
    if extra:
        raise ValueError(f"unknown {kind} config field(s) {extra}; expected some of {names}")
    return cls(**{k: d[k] for k in names if k in d})


def _to_dict(obj, kind: str) -> dict:
    out: dict[str, Any] = {"type": kind}
    for f in fields(obj):
        v = getattr(obj, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def _penalty_energy(dist: Tensor, k: float, w: Tensor) -> Tensor:
    """k Σ_i w_i max(0, −dist_i)²."""
    pen = (-dist).clamp_min(0.0)
    return k * (w * pen * pen).sum()


# ---- gravity ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Gravity:
    """Uniform gravity, ``E = −Σ_i m_i g·x_i``.

    Attributes:
        acceleration: g in m/s² (3-vector); default (0, 0, −9.8) (z-up).
    """

    acceleration: tuple[float, float, float] = (0.0, 0.0, -9.8)
    kind: ClassVar[str] = "body"

    def __post_init__(self) -> None:
        object.__setattr__(self, "acceleration", _vector(self.acceleration, 3, "Gravity.acceleration"))

    def _g(self, x: Tensor) -> Tensor:
        return torch.tensor(self.acceleration, dtype=x.dtype, device=x.device)

    def energy(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """E: () = −Σ_i m_i g·x_i."""
        _check_inputs(x, mass, t)
        return -(mass * (x @ self._g(x))).sum()

    def gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """∂E/∂x_i = −m_i g, (N, 3)."""
        _check_inputs(x, mass, t)
        return -mass[:, None] * self._g(x)[None, :]

    def energy_and_gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        """(E, ∂E/∂x) in one pass."""
        _check_inputs(x, mass, t)
        g = self._g(x)
        return -(mass * (x @ g)).sum(), -mass[:, None] * g[None, :]

    def hessian(self, x: Tensor, mass: Tensor, t: float = 0.0, project: bool = True) -> Tensor:
        """Zero blocks, (N, 3, 3)."""
        _check_inputs(x, mass, t)
        return x.new_zeros(x.shape[0], 3, 3)

    def to_dict(self) -> dict:
        return _to_dict(self, "gravity")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Gravity":
        return _from_dict(cls, d, "gravity")


# ---- static floor -------------------------------------------------------------------------------

@dataclass(frozen=True)
class Floor:
    """The paper's floor barrier ``E = k Σ_i w_i max(0, h − z_i)²`` (plane z = h, z-up; w_i = 1 in the paper).

    Attributes:
        height: h in metres (the public release's canonical frame uses −0.7).
        stiffness: k, in J/m² per unit weight (paper: 1e5 per point with w = 1; with area weights in m²
            it is a contact pressure per metre of penetration, Pa/m).
        friction: Coulomb coefficient μ ≥ 0 of the floor (0: frictionless, the paper's).
        friction_velocity: ε_v (m/s), the slip speed below which friction is smoothed.
    """

    height: float
    stiffness: float = 1e5
    friction: float = 0.0
    friction_velocity: float = FRICTION_VELOCITY
    kind: ClassVar[str] = "contact"

    def __post_init__(self) -> None:
        object.__setattr__(self, "height", _real(self.height, "Floor.height"))
        object.__setattr__(self, "stiffness", _positive(self.stiffness, "Floor.stiffness"))
        _check_friction(self, "Floor")

    def surface_velocity(self, x: Tensor, t: float = 0.0) -> Tensor:
        """Zeros (N, 3): the floor stands still."""
        return torch.zeros_like(x)

    def signed_distance(self, x: Tensor, t: float = 0.0) -> Tensor:
        """z_i − h, (N,) (negative below the floor)."""
        return x[:, 2] - self.height

    def distance_derivatives(self, x: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor, Tensor | None]:
        """(s (N,), ∂s/∂x (N, 3), ∂²s/∂x² (N, 3, 3) or None when it is zero) of :meth:`signed_distance`."""
        n = x.new_zeros(x.shape[0], 3)
        n[:, 2] = 1.0
        return x[:, 2] - self.height, n, None

    def energy(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """E: () = k Σ w_i max(0, h − z_i)² (``mass`` holds the weights w)."""
        _check_inputs(x, mass, t)
        return _penalty_energy(self.signed_distance(x), self.stiffness, mass)

    def gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """(N, 3): (0, 0, −2k w_i max(0, h − z_i))."""
        _check_inputs(x, mass, t)
        pen = (-self.signed_distance(x)).clamp_min(0.0)
        zero = torch.zeros_like(pen)
        return torch.stack([zero, zero, -2.0 * self.stiffness * mass * pen], dim=1)

    def energy_and_gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        """(E, ∂E/∂x) in one pass."""
        _check_inputs(x, mass, t)
        pen = (self.height - x[:, 2]).clamp_min(0.0)
        wpen = mass * pen
        zero = torch.zeros_like(pen)
        return self.stiffness * (wpen * pen).sum(), torch.stack([zero, zero, -2.0 * self.stiffness * wpen], dim=1)

    def hessian(self, x: Tensor, mass: Tensor, t: float = 0.0, project: bool = True) -> Tensor:
        """(N, 3, 3): 2k w_i e_z e_zᵀ for points below the floor, else 0 (already PSD)."""
        _check_inputs(x, mass, t)
        active = (self.signed_distance(x) < 0).to(x.dtype)
        H = x.new_zeros(x.shape[0], 3, 3)
        H[:, 2, 2] = 2.0 * self.stiffness * mass * active
        return H

    def to_dict(self) -> dict:
        return _to_dict(self, "floor")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Floor":
        return _from_dict(cls, d, "floor")


# ---- moving floor -------------------------------------------------------------------------------

@dataclass(frozen=True)
class MovingFloor:
    """A floor plane that translates vertically and tilts over time; ``E = k Σ_i w_i max(0, −s(x_i, t))²``.

    The plane passes through the pivot point ``p(t) = (pivot_xy[0], pivot_xy[1], height(t))`` with

        height(t) = height + velocity · t + amplitude · sin(2π · frequency · t)
        θ(t)      = radians(tilt_deg + tilt_rate_deg · t)

    and unit normal ``n(t) = R(a, θ(t)) e_z`` — e_z rotated by θ(t) (right-hand rule) about the horizontal
    unit axis a = tilt_axis/‖tilt_axis‖, i.e. ``n = cos θ e_z + sin θ (a × e_z)``. The signed distance is
    ``s(x, t) = n(t)·(x − p(t))``, negative below the plane. With all motion parameters zero it equals
    :class:`Floor` of the same height and stiffness. Its surface moves with the pivot's vertical velocity and
    turns about the tilt axis through the pivot (:meth:`surface_velocity`), which friction drags along.

    Attributes:
        height: pivot height at t = 0 (m).
        velocity: vertical velocity of the pivot (m/s).
        amplitude: amplitude of the vertical oscillation (m).
        frequency: oscillation frequency (Hz, ≥ 0).
        tilt_deg: tilt angle at t = 0 (degrees).
        tilt_rate_deg: tilt angular velocity (degrees/s).
        tilt_axis: horizontal tilt axis (3-vector with zero z component, nonzero; normalised internally).
        pivot_xy: horizontal position (x, y) of the pivot (m).
        stiffness: k (paper's floor: 1e5).
        friction: Coulomb coefficient μ ≥ 0 (0: frictionless, the paper's).
        friction_velocity: ε_v (m/s), the slip speed below which friction is smoothed.
    """

    height: float
    velocity: float = 0.0
    amplitude: float = 0.0
    frequency: float = 0.0
    tilt_deg: float = 0.0
    tilt_rate_deg: float = 0.0
    tilt_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    pivot_xy: tuple[float, float] = (0.0, 0.0)
    stiffness: float = 1e5
    friction: float = 0.0
    friction_velocity: float = FRICTION_VELOCITY
    kind: ClassVar[str] = "contact"

    def __post_init__(self) -> None:
        for name in ("height", "velocity", "amplitude", "frequency", "tilt_deg", "tilt_rate_deg"):
            object.__setattr__(self, name, _real(getattr(self, name), f"MovingFloor.{name}"))
        if self.frequency < 0:
            raise ConfigError(f"MovingFloor.frequency must be >= 0 (Hz), got {self.frequency}")
        axis = _vector(self.tilt_axis, 3, "MovingFloor.tilt_axis")
        if axis[2] != 0.0 or math.hypot(axis[0], axis[1]) == 0.0:
            raise ConfigError(
                f"MovingFloor.tilt_axis must be a nonzero horizontal vector (z component 0), got {list(axis)}"
            )
        object.__setattr__(self, "tilt_axis", axis)
        object.__setattr__(self, "pivot_xy", _vector(self.pivot_xy, 2, "MovingFloor.pivot_xy"))
        object.__setattr__(self, "stiffness", _positive(self.stiffness, "MovingFloor.stiffness"))
        _check_friction(self, "MovingFloor")

    def height_at(self, t: float) -> float:
        """Pivot height at time t (m)."""
        return self.height + self.velocity * t + self.amplitude * math.sin(2.0 * math.pi * self.frequency * t)

    def _unit_axis(self) -> tuple[float, float]:
        """(a_x, a_y) of the unit tilt axis a."""
        ax, ay, _ = self.tilt_axis
        norm = math.hypot(ax, ay)
        return ax / norm, ay / norm

    def normal_at(self, t: float) -> tuple[float, float, float]:
        """Unit normal n(t) of the plane."""
        theta = math.radians(self.tilt_deg + self.tilt_rate_deg * t)
        ax, ay = self._unit_axis()
        c, s = math.cos(theta), math.sin(theta)
        return (s * ay, -s * ax, c)  # cos θ e_z + sin θ (a × e_z), a × e_z = (a_y, −a_x, 0)

    def surface_velocity(self, x: Tensor, t: float) -> Tensor:
        """(N, 3): the plane's material velocity at x, ṗ(t) + ω × (x − p(t)) with ṗ the pivot's vertical
        velocity and ω = θ̇ a the tilt's angular velocity."""
        _, p = self._plane(x, t)
        ax, ay = self._unit_axis()
        rate = math.radians(self.tilt_rate_deg)
        omega = torch.tensor((rate * ax, rate * ay, 0.0), dtype=x.dtype, device=x.device)
        climb = self.velocity + self.amplitude * 2.0 * math.pi * self.frequency \
            * math.cos(2.0 * math.pi * self.frequency * t)
        pdot = torch.tensor((0.0, 0.0, climb), dtype=x.dtype, device=x.device)
        return pdot + torch.linalg.cross(omega.expand_as(x), x - p)

    def _plane(self, x: Tensor, t: float) -> tuple[Tensor, Tensor]:
        n = torch.tensor(self.normal_at(t), dtype=x.dtype, device=x.device)
        p = torch.tensor((*self.pivot_xy, self.height_at(t)), dtype=x.dtype, device=x.device)
        return n, p

    def signed_distance(self, x: Tensor, t: float) -> Tensor:
        """s(x_i, t) = n(t)·(x_i − p(t)), (N,)."""
        n, p = self._plane(x, t)
        return (x - p) @ n

    def distance_derivatives(self, x: Tensor, t: float) -> tuple[Tensor, Tensor, Tensor | None]:
        """(s (N,), ∂s/∂x = n(t) (N, 3), None: the plane has no curvature)."""
        n, p = self._plane(x, t)
        return (x - p) @ n, n.expand(x.shape[0], 3), None

    def energy(self, x: Tensor, mass: Tensor, t: float) -> Tensor:
        """E: () = k Σ w_i max(0, −s(x_i, t))² (``mass`` holds the weights w)."""
        t = _check_inputs(x, mass, t)
        return _penalty_energy(self.signed_distance(x, t), self.stiffness, mass)

    def gradient(self, x: Tensor, mass: Tensor, t: float) -> Tensor:
        """(N, 3): −2k w_i max(0, −s_i) n(t)."""
        t = _check_inputs(x, mass, t)
        n, p = self._plane(x, t)
        pen = (-((x - p) @ n)).clamp_min(0.0)
        return (-2.0 * self.stiffness) * (mass * pen)[:, None] * n[None, :]

    def energy_and_gradient(self, x: Tensor, mass: Tensor, t: float) -> tuple[Tensor, Tensor]:
        """(E, ∂E/∂x) in one pass."""
        t = _check_inputs(x, mass, t)
        n, p = self._plane(x, t)
        pen = (-((x - p) @ n)).clamp_min(0.0)
        wpen = mass * pen
        return self.stiffness * (wpen * pen).sum(), (-2.0 * self.stiffness) * wpen[:, None] * n[None, :]

    def hessian(self, x: Tensor, mass: Tensor, t: float, project: bool = True) -> Tensor:
        """(N, 3, 3): 2k w_i n nᵀ for points below the plane, else 0 (already PSD)."""
        t = _check_inputs(x, mass, t)
        n, p = self._plane(x, t)
        active = (((x - p) @ n) < 0).to(x.dtype)
        return (2.0 * self.stiffness) * (mass * active)[:, None, None] * (n[:, None] * n[None, :])[None]

    def to_dict(self) -> dict:
        return _to_dict(self, "moving_floor")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "MovingFloor":
        return _from_dict(cls, d, "moving_floor")


# ---- sphere -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SphereObstacle:
    """A fixed solid ball, ``E = k Σ_i w_i max(0, r − ‖x_i − c‖)²``.

    With d = ‖x − c‖, n̂ = (x − c)/d and φ = max(0, r − d): gradient −2kφ n̂; exact Hessian
    2k [φ > 0] (n̂n̂ᵀ − φ/d (I − n̂n̂ᵀ)), whose eigenvalues are 2k (normal) and −2kφ/d (twice,
    tangential), so its exact PSD projection is 2k [φ > 0] n̂n̂ᵀ. At the centre itself (d = 0, where the
    energy has a cone tip) the direction is taken as n̂ = +e_z and the tangential term is dropped.

    Attributes:
        center: c (m), 3-vector.
        radius: r > 0 (m).
        stiffness: k > 0 (default 1e5, as the floor).
        friction: Coulomb coefficient μ ≥ 0 (0: frictionless, the paper's).
        friction_velocity: ε_v (m/s), the slip speed below which friction is smoothed.
    """

    center: tuple[float, float, float]
    radius: float
    stiffness: float = 1e5
    friction: float = 0.0
    friction_velocity: float = FRICTION_VELOCITY
    kind: ClassVar[str] = "contact"

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vector(self.center, 3, "SphereObstacle.center"))
        object.__setattr__(self, "radius", _positive(self.radius, "SphereObstacle.radius"))
        object.__setattr__(self, "stiffness", _positive(self.stiffness, "SphereObstacle.stiffness"))
        _check_friction(self, "SphereObstacle")

    def surface_velocity(self, x: Tensor, t: float = 0.0) -> Tensor:
        """Zeros (N, 3): the ball stands still."""
        return torch.zeros_like(x)

    def _geometry(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """d (N,), n̂ (N, 3), at_centre (N,) — differentiable where d > 0."""
        c = torch.tensor(self.center, dtype=x.dtype, device=x.device)
        diff = x - c
        d2 = (diff * diff).sum(dim=1)
        at_centre = d2 == 0
        d = torch.sqrt(torch.where(at_centre, torch.ones_like(d2), d2))
        up = torch.tensor((0.0, 0.0, 1.0), dtype=x.dtype, device=x.device)
        nhat = torch.where(at_centre[:, None], up, diff / d[:, None])
        d = torch.where(at_centre, torch.zeros_like(d), d)
        return d, nhat, at_centre

    def signed_distance(self, x: Tensor, t: float = 0.0) -> Tensor:
        """‖x_i − c‖ − r, (N,) (negative inside the ball)."""
        return self._geometry(x)[0] - self.radius

    def distance_derivatives(self, x: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor, Tensor | None]:
        """(s (N,), ∂s/∂x = n̂ (N, 3), ∂²s/∂x² = (I − n̂n̂ᵀ)/d (N, 3, 3); zero at the centre itself)."""
        d, nhat, at_centre = self._geometry(x)
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        inv_d = torch.where(at_centre, torch.zeros_like(d), 1.0 / torch.where(at_centre, torch.ones_like(d), d))
        curvature = inv_d[:, None, None] * (eye - nhat[:, :, None] * nhat[:, None, :])
        return d - self.radius, nhat, curvature

    def energy(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """E: () = k Σ w_i max(0, r − ‖x_i − c‖)² (``mass`` holds the weights w)."""
        _check_inputs(x, mass, t)
        return _penalty_energy(self.signed_distance(x), self.stiffness, mass)

    def gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> Tensor:
        """(N, 3): −2k w_i max(0, r − d_i) n̂_i (points inside are pushed outward)."""
        _check_inputs(x, mass, t)
        d, nhat, _ = self._geometry(x)
        pen = (self.radius - d).clamp_min(0.0)
        return (-2.0 * self.stiffness) * (mass * pen)[:, None] * nhat

    def energy_and_gradient(self, x: Tensor, mass: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        """(E, ∂E/∂x) in one pass."""
        _check_inputs(x, mass, t)
        d, nhat, _ = self._geometry(x)
        pen = (self.radius - d).clamp_min(0.0)
        wpen = mass * pen
        return self.stiffness * (wpen * pen).sum(), (-2.0 * self.stiffness) * wpen[:, None] * nhat

    def hessian(self, x: Tensor, mass: Tensor, t: float = 0.0, project: bool = True) -> Tensor:
        """(N, 3, 3): 2k n̂n̂ᵀ inside the ball (exact PSD projection); ``project=False`` adds the
        (negative) tangential term −2kφ/d (I − n̂n̂ᵀ)."""
        _check_inputs(x, mass, t)
        d, nhat, at_centre = self._geometry(x)
        pen = (self.radius - d).clamp_min(0.0)
        active = (pen > 0).to(x.dtype)
        nn = nhat[:, :, None] * nhat[:, None, :]
        H = (2.0 * self.stiffness) * active[:, None, None] * nn
        if not project:
            eye = torch.eye(3, dtype=x.dtype, device=x.device)
            safe_d = torch.where(at_centre, torch.ones_like(d), d)
            ratio = torch.where(at_centre, torch.zeros_like(d), pen / safe_d)
            H = H - (2.0 * self.stiffness) * ratio[:, None, None] * (eye - nn)
        return mass[:, None, None] * H

    def to_dict(self) -> dict:
        return _to_dict(self, "sphere")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SphereObstacle":
        return _from_dict(cls, d, "sphere")


# ---- sums and serialisation ---------------------------------------------------------------------

_TYPES = {"gravity": Gravity, "floor": Floor, "moving_floor": MovingFloor, "sphere": SphereObstacle}


def external_from_dict(d: Mapping[str, Any]) -> ExternalEnergy:
    """Build an external energy from its ``to_dict()`` form, dispatching on ``d["type"]``."""
    if not isinstance(d, Mapping):
        raise ValueError(f"external energy config must be a mapping with a 'type' key, got {type(d).__name__}")
    kind = d.get("type")
    if kind not in _TYPES:
        raise ValueError(f"unknown external energy type {kind!r}; expected one of {sorted(_TYPES)}")
    return _TYPES[kind].from_dict(d)


def energy_and_gradient(energy: ExternalEnergy, x: Tensor, weights: Tensor, t: float) -> tuple[Tensor, Tensor]:
    """(E (), ∂E/∂x (N, 3)) of one external energy: its ``energy_and_gradient`` when it has one, else its
    ``energy`` and ``gradient``."""
    both = getattr(energy, "energy_and_gradient", None)
    if both is not None:
        return both(x, weights, t)
    return energy.energy(x, weights, t), energy.gradient(x, weights, t)


def total_external(
    energies: Sequence[ExternalEnergy], x: Tensor, mass: Tensor, t: float, project: bool = True
) -> tuple[Tensor, Tensor, Tensor]:
    """Sum of several external energies: (E: (), gradient: (N, 3), per-point Hessian blocks: (N, 3, 3)).

    Hessian blocks are the sum of each energy's (projected, when ``project``) blocks; a sum of PSD blocks
    is PSD. With no energies returns zeros.
    """
    _check_inputs(x, mass, t)
    E = x.new_zeros(())
    g = torch.zeros_like(x)
    H = x.new_zeros(x.shape[0], 3, 3)
    for ext in energies:
        E = E + ext.energy(x, mass, t)
        g = g + ext.gradient(x, mass, t)
        H = H + ext.hessian(x, mass, t, project=project)
    return E, g, H
