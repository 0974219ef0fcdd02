"""The FEM ground truth's settings (:class:`FEMConfig`), its error, and the initial pose of a drop."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.physics.damping import (
    DEFAULT_DAMPING_RATIO,
    check_damping_ratio,
)
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.integrators import INTEGRATORS
from vid2sim.physics.materials import (
    ELASTIC_MODELS,
    lame_parameters,
)
from vid2sim.runtime.errors import ConfigError


class FEMSolverError(RuntimeError):
    """A Newton solve could not make progress (no valid line-search step, or no convergence)."""


@dataclass
class FEMConfig:
    """Material, scene and solver settings of the FEM ground truth (SI units).

    Attributes:
        youngs_modulus: E in Pa.
        poisson_ratio: ν in (−1, 0.5).
        density: ρ in kg/m³.
        material: elastic model, 'neo_hookean' (the paper's) or 'stvk'.
        dt: time between video frames (s).
        substeps: time steps per frame (h = dt / substeps). :func:`simulate_fem_converged` refines this
            until the trajectory is converged in time; see docs/architecture.md for measured figures.
        integrator: 'bdf2' (second order, default) or 'implicit_euler' (first order, strongly
            dissipative at large h: on an undamped drop 16 substeps were 14 % of the object's size away
            from 64 over 24 frames).
        damping_ratio: ζ of the Kelvin–Voigt material damping at ω_ref = √(E/ρ)/L (0 = undamped).
        damping_length: L in metres for that reference frequency; None = the rest bounding-box diagonal.
        floor_height: z of the floor plane, or None for no floor.
        floor_stiffness: κ of the floor penalty κ Σ_i a_i max(0, h − z_i)² over the surface vertices with
            their lumped areas a_i (Pa per metre of penetration).
        gravity: (3,) acceleration (m/s²).
        newton_max_iters: Newton iterations per step before :class:`FEMSolverError`.
        newton_tol: convergence when the Newton step's largest vertex move is at most newton_tol × the rest
            bounding-box diagonal and, in a time step, at most ``newton_rtol`` × the step's largest vertex
            move (otherwise the small leftover of many short steps would add up).
        newton_rtol: that relative part of the tolerance.
        line_search_max_halvings: backtracking halvings before :class:`FEMSolverError`.
        armijo: sufficient-decrease constant.
        linear_solver: Newton system solver: 'direct' (sparse LU with a symmetric ordering and diagonal
            pivoting, an LDLᵀ; default) or 'cg' (Jacobi-preconditioned conjugate gradients on a fresh Hessian
            every iteration; a system CG cannot solve to ``cg_rtol`` in ``cg_max_iters`` is solved directly).
        reuse_factorization: with the direct solver, keep the factorised Hessian across Newton iterations
            and time steps (turned with the object by a fitted rotation) and refactorise only when an
            iteration contracts the step by less than ``reuse_rate`` or needs the line search (a chord
            Newton method: most steps then cost one gradient and one triangular solve). Static solves
            always refactorise.
        reuse_rate: the contraction per iteration below which a kept factorisation is reused.
        cg_rtol: relative residual at which CG stops (the Newton convergence test is on the step, so
            this only needs to make the step accurate to well below ``newton_tol``).
        cg_max_iters: CG iterations before the direct solver takes over.
        element_order: 1 — linear tets (one quadrature point each); 2 — quadratic 10-node tets on the same
            mesh (a node on every edge midpoint, 4 quadrature points per tet, HRZ-lumped masses and contact
            areas). Linear tets are stiff in bending: on the ``bench identify`` shapes at the small preset's
            mesh their lowest frequency is 3–20 % above the converged one, while quadratic tets are within
            0.6 % (:mod:`vid2sim.physics.tet_modes`). Positions are then given for all nodes, vertices first.
        hessian_projection: "on_demand" — Newton uses the exact Hessian while it gives a descent
            direction (CG converges and gᵀp < 0, or the direct factorisation shows it positive definite)
            and the Hessian with every element tangent projected to PSD otherwise; "always" — the
            projected one every iteration. Projection is robust but slows Newton to linear convergence
            whenever elements are compressed into the indefinite range of Neo-Hookean (at impacts:
            50+ iterations instead of 6), so the exact Hessian comes first.
    """

    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    material: str = "neo_hookean"
    dt: float = 0.05
    substeps: int = 16
    integrator: str = "bdf2"
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    damping_length: float | None = None
    floor_height: float | None = -0.7
    floor_stiffness: float = AREA_CONTACT_STIFFNESS
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    newton_max_iters: int = 100
    newton_tol: float = 1e-6
    newton_rtol: float = 1e-4
    line_search_max_halvings: int = 40
    armijo: float = 1e-4
    linear_solver: str = "direct"
    reuse_factorization: bool = True
    reuse_rate: float = 0.5
    cg_rtol: float = 1e-6
    cg_max_iters: int = 1000
    hessian_projection: str = "on_demand"
    element_order: int = 1

    def __post_init__(self) -> None:
        lame_parameters(self.youngs_modulus, self.poisson_ratio)  # validates E and ν
        if self.element_order not in (1, 2) or isinstance(self.element_order, bool):
            raise ConfigError(f"FEMConfig.element_order must be 1 (linear tets) or 2 (quadratic tets), "
                             f"got {self.element_order!r}")
        if self.hessian_projection not in ("always", "on_demand"):
            raise ConfigError(
                f"FEMConfig.hessian_projection must be 'always' or 'on_demand', got {self.hessian_projection!r}")
        if self.material not in ELASTIC_MODELS:
            raise ConfigError(f"FEMConfig.material must be one of {sorted(ELASTIC_MODELS)}, got {self.material!r}")
        if self.integrator not in INTEGRATORS:
            raise ConfigError(f"FEMConfig.integrator must be one of {list(INTEGRATORS)}, got {self.integrator!r}")
        self.damping_ratio = check_damping_ratio(self.damping_ratio, "FEMConfig.damping_ratio")
        if self.damping_length is not None and not (isinstance(self.damping_length, (int, float))
                                                    and math.isfinite(self.damping_length) and self.damping_length > 0):
            raise ConfigError(f"FEMConfig.damping_length must be a positive number of metres or None, "
                             f"got {self.damping_length!r}")
        if self.linear_solver not in ("direct", "cg"):
            raise ConfigError(f"FEMConfig.linear_solver must be 'direct' or 'cg', got {self.linear_solver!r}")
        if not 0 < self.reuse_rate < 1:
            raise ConfigError(f"FEMConfig.reuse_rate must be in (0, 1), got {self.reuse_rate!r}")
        for name in ("density", "dt", "floor_stiffness", "newton_tol", "newton_rtol", "cg_rtol"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0 and math.isfinite(value)):
                raise ConfigError(f"FEMConfig.{name} must be a positive finite number, got {value!r}")
        for name in ("substeps", "newton_max_iters", "line_search_max_halvings", "cg_max_iters"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"FEMConfig.{name} must be an integer >= 1, got {value!r}")
        if self.floor_height is not None and not math.isfinite(self.floor_height):
            raise ConfigError(f"FEMConfig.floor_height must be finite or None, got {self.floor_height}")
        g = tuple(float(c) for c in self.gravity)
        if len(g) != 3 or not all(math.isfinite(c) for c in g):
            raise ConfigError(f"FEMConfig.gravity must be three finite numbers, got {self.gravity!r}")
        self.gravity = g

    @property
    def lame(self) -> tuple[float, float]:
        """(μ, λ)."""
        return lame_parameters(self.youngs_modulus, self.poisson_ratio)


# ---- initial pose ---------------------------------------------------------------------------------

def _as_matrix3(rotation) -> np.ndarray:
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape == (3,):  # axis-angle
        angle = float(np.linalg.norm(r))
        if angle == 0.0:
            return np.eye(3)
        k = r / angle
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    if r.shape != (3, 3):
        raise ValueError(
            f"InitialPose.rotation must be a (3, 3) matrix or a (3,) axis-angle vector, got shape {r.shape}"
        )
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError(f"InitialPose.rotation must be a proper rotation (RᵀR = I, det R = +1), got {r.tolist()}")
    return r


@dataclass
class InitialPose:
    """How the object starts: rotated about its centre of mass, lifted so that its lowest vertex is
    ``drop_height`` above the floor (x, y of the centre of mass unchanged), moving rigidly.

    Attributes:
        drop_height: clearance (m) between the lowest vertex and the floor after rotation. Without a
            floor the centre of mass stays where it is and this is ignored.
        rotation: (3, 3) rotation matrix, or (3,) axis-angle vector (radians), applied about the
            centre of mass. Stored as a nested tuple (3×3).
        linear_velocity: (3,) velocity of the centre of mass (m/s).
        angular_velocity: (3,) angular velocity (rad/s, world frame); v_i = v + ω × (x_i − c).
    """

    drop_height: float = 0.2
    rotation: Sequence = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    linear_velocity: Sequence[float] = (0.0, 0.0, 0.0)
    angular_velocity: Sequence[float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        self.rotation = tuple(tuple(float(c) for c in row) for row in _as_matrix3(self.rotation))
        for name in ("linear_velocity", "angular_velocity"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (3,) or not np.isfinite(value).all():
                raise ConfigError(f"InitialPose.{name} must be three finite numbers, got {getattr(self, name)!r}")
            setattr(self, name, tuple(float(c) for c in value))
        if not (math.isfinite(self.drop_height) and self.drop_height >= 0):
            raise ConfigError(f"InitialPose.drop_height must be a finite number >= 0, got {self.drop_height}")
        self.drop_height = float(self.drop_height)

    @classmethod
    def random(cls, seed: int, drop_height: tuple[float, float] = (0.05, 0.3), max_horizontal_speed: float = 0.5,
               max_downward_speed: float = 1.0, max_angular_speed: float = 2.0) -> "InitialPose":
        """A reproducible random pose: uniformly random rotation (normalised Gaussian quaternion),
        drop height uniform in ``drop_height``, horizontal velocity components uniform in
        ±``max_horizontal_speed``, vertical velocity uniform in [−``max_downward_speed``, 0], angular
        velocity along a uniformly random axis with magnitude uniform in [0, ``max_angular_speed``]."""
        lo, hi = drop_height
        if not 0 <= lo <= hi:
            raise ValueError(f"drop_height range must satisfy 0 <= low <= high, got {drop_height}")
        rng = np.random.default_rng(seed)
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        rot = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        height = rng.uniform(lo, hi)
        lin = np.array([rng.uniform(-max_horizontal_speed, max_horizontal_speed),
                        rng.uniform(-max_horizontal_speed, max_horizontal_speed),
                        rng.uniform(-max_downward_speed, 0.0)])
        axis = rng.normal(size=3)
        ang = axis / np.linalg.norm(axis) * rng.uniform(0.0, max_angular_speed)
        return cls(drop_height=float(height), rotation=rot, linear_velocity=lin, angular_velocity=ang)

    def apply(self, vertices: Tensor, masses: Tensor, floor_height: float | None) -> tuple[Tensor, Tensor]:
        """Posed positions and velocities.

        Args:
            vertices: (Nv, 3) rest positions.
            masses: (Nv,) vertex masses (for the centre of mass).
            floor_height: the floor's z, or None.

        Returns:
            ``(x0 (Nv, 3), v0 (Nv, 3))`` in the dtype of ``vertices``.
        """
        R = torch.tensor(self.rotation, dtype=vertices.dtype, device=vertices.device)
        c = (masses[:, None] * vertices).sum(0) / masses.sum()
        x = (vertices - c) @ R.T + c
        if floor_height is not None:
            x[:, 2] += floor_height + self.drop_height - x[:, 2].min()
        c_new = (masses[:, None] * x).sum(0) / masses.sum()
        lin = torch.tensor(self.linear_velocity, dtype=vertices.dtype, device=vertices.device)
        ang = torch.tensor(self.angular_velocity, dtype=vertices.dtype, device=vertices.device)
        v = lin + torch.cross(ang.expand_as(x), x - c_new, dim=1)
        return x, v


