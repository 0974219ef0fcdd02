"""Finite-element ground truth for the synthetic benchmark: linear tetrahedra, the paper's Neo-Hookean
energy, gravity, the floor penalty of docs/architecture.md and Kelvin–Voigt damping, integrated in time (BDF2 or implicit
Euler) with Newton's method.

Model
-----
* Elements: linear (P1) tetrahedra, constant deformation gradient F = D_s D_m⁻¹ per tet; elastic energy
  Σ_e V_e Ψ(F_e) with Ψ from :mod:`vid2sim.physics.materials` (Neo-Hookean by default, as in the paper).
* Mass: lumped, ρ V_e / 4 to each vertex of each tet (the same lumped-mass choice as the reduced
  simulator's ρ V / N per cubature point). Gravity energy −Σ_i m_i g·x_i.
* Floor: the plane z = h with a penalty on the surface, E_f = κ Σ_i a_i max(0, h − z_i)² over the boundary
  vertices with their lumped rest areas a_i (:func:`vid2sim.meshing.tetra.surface_vertex_areas`): a contact
  pressure κ · depth integrated over the surface, so the contact stiffness does not change when the mesh
  is refined (the paper's per-point k Σ max(0, h − z)² would grow with the number of surface vertices).
  κ = :data:`vid2sim.physics.external.AREA_CONTACT_STIFFNESS` by default; the reduced simulator uses
  the same law on area-weighted surface contact points. No friction (the paper's floor has none either).
* Damping: Kelvin–Voigt viscosity on the Green-strain rate, the same model and parameter as the reduced
  simulator (:mod:`vid2sim.physics.damping`): viscous Lamé parameters τ μ and τ λ with the retardation
  time τ = 2 ζ L √(ρ/E) from the damping ratio ζ (:attr:`FEMConfig.damping_ratio`) and the object's size
  L (rest bounding-box diagonal unless :attr:`FEMConfig.damping_length` is given). ζ = 0 is undamped.
* Time integration: ``substeps`` steps of h = dt / substeps per video frame with BDF2 (default) or
  implicit Euler (:mod:`vid2sim.physics.integrators`); each step minimises the incremental potential
  a₀²/(2h²) ‖x − x̂‖²_M + E(x) + (a₀ τ / h) Σ_e V_e ψ(F_e; C_ref,e) by Newton's method with a sparse
  Hessian (exact first; element tangents projected to positive semi-definite when the exact Hessian gives
  no descent direction, see :attr:`FEMConfig.hessian_projection`), solved by a sparse LDLᵀ
  (:attr:`FEMConfig.linear_solver`). Time steps keep the factorisation, turned with the object, while
  Newton contracts fast (:attr:`FEMConfig.reuse_factorization`). Backtracking line search from the full
  Newton step; a trial state with any det F ≤ 0, a non-finite energy or no
  sufficient decrease is rejected. A kept factorisation whose full step is rejected is refactorised at the
  current state rather than searched along: the floor penalty's Hessian jumps where a vertex crosses the
  floor, and halved steps of a factorisation made with the other contact set can cycle forever. Converged
  when the Newton step's largest vertex move is below ``newton_tol`` × the rest bounding-box diagonal.
  :func:`simulate_fem_converged` doubles the substeps until the trajectory no longer changes by more than a
  tolerance (the benchmark's ground truth).
* Fixed (Dirichlet) vertices: a boolean mask; those vertices keep their initial position.

Everything runs in float64 on the CPU with numpy/scipy (the per-element stress and tangent come from
:mod:`vid2sim.physics.materials` in torch); inputs on any device are moved there and results are
float64 CPU tensors. This is offline ground-truth generation, so exactness comes before speed.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.physics.damping import (
    DEFAULT_DAMPING_RATIO,
    check_damping_ratio,
    reference_metric,
    retardation_time,
    viscous_tangent,
)
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.integrators import INTEGRATORS, bdf_step
from vid2sim.physics.materials import (
    ELASTIC_MODELS,
    elastic_model,
    lame_parameters,
    neo_hookean_energy_and_pk1,
    project_tangent_psd,
    stvk_energy_and_pk1,
)
from vid2sim.physics.sparse_lu import SymmetricLU, nested_dissection
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
        raise ValueError(f"InitialPose.rotation must be a (3, 3) matrix or a (3,) axis-angle vector, got shape {r.shape}")
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


# ---- the discrete model ---------------------------------------------------------------------------

@dataclass
class NewtonStats:
    """Outcome of one Newton minimisation.

    Attributes:
        iterations: Newton iterations.
        line_search_halvings: backtracking halvings over all iterations.
        converged: the step fell below ``newton_tol``.
        cg_iterations: CG iterations over all linear solves.
        direct_solves: sparse LU factorisations (direct solver, or CG fallbacks).
        inverted_rejections: line-search trials rejected for inverting a tet.
        projected_solves: iterations whose exact Hessian gave no descent direction and were re-solved
            with the PSD-projected one (``hessian_projection="on_demand"`` only).
        factorizations: Hessians assembled (and factorised, with the direct solver); fewer than
            ``iterations`` when a factorisation is reused.
    """

    iterations: int = 0
    line_search_halvings: int = 0
    converged: bool = False
    cg_iterations: int = 0
    direct_solves: int = 0
    inverted_rejections: int = 0
    projected_solves: int = 0
    factorizations: int = 0


def _quadratic_gradients(gradL: np.ndarray) -> np.ndarray:
    """(Nt, 4, 10, 3) gradients of the 10-node shape functions at the 4 quadrature points of the degree-2
    rule, from the barycentric gradients gradL (Nt, 4, 3): ∇N_a = (4L_a − 1)∇L_a at the vertices and
    ∇N_ab = 4(L_a ∇L_b + L_b ∇L_a) at the midpoints of :data:`vid2sim.physics.tet_modes.TET_EDGES`."""
    from vid2sim.physics.tet_modes import TET_EDGES, quadrature_points

    out = np.empty((gradL.shape[0], 4, 10, 3))
    for q, L in enumerate(quadrature_points()):
        for a in range(4):
            out[:, q, a] = (4 * L[a] - 1) * gradL[:, a]
        for e, (a, b) in enumerate(TET_EDGES):
            out[:, q, 4 + e] = 4 * (L[a] * gradL[:, b] + L[b] * gradL[:, a])
    return out


def _contact_areas(X: np.ndarray, tets: np.ndarray, elements: np.ndarray, num_nodes: int) -> np.ndarray:
    """(N,) lumped rest boundary area per node: a third of each boundary triangle's area to each vertex
    (linear tets), or for quadratic tets HRZ on the 6-node triangle: A/19 per vertex and 16A/57 per edge
    midpoint."""
    from vid2sim.meshing.tetra import boundary_faces, surface_vertex_areas

    if elements.shape[1] == 4:
        return surface_vertex_areas(torch.from_numpy(X), torch.from_numpy(tets)).numpy()
    from vid2sim.physics.tet_modes import TET_EDGES

    faces = boundary_faces(torch.from_numpy(tets)).numpy()
    area = 0.5 * np.linalg.norm(np.cross(X[faces[:, 1]] - X[faces[:, 0]], X[faces[:, 2]] - X[faces[:, 0]]), axis=1)
    nv = len(X)
    midpoint = {}
    for e, (a, b) in enumerate(TET_EDGES):
        keys = np.minimum(tets[:, a], tets[:, b]) * nv + np.maximum(tets[:, a], tets[:, b])
        midpoint.update(zip(keys.tolist(), elements[:, 4 + e].tolist()))
    out = np.zeros(num_nodes)
    np.add.at(out, faces.ravel(), np.repeat(area / 19.0, 3))
    for a, b in ((0, 1), (1, 2), (0, 2)):
        keys = np.minimum(faces[:, a], faces[:, b]) * nv + np.maximum(faces[:, a], faces[:, b])
        np.add.at(out, np.array([midpoint[k] for k in keys.tolist()]), area * 16.0 / 57.0)
    return out


class TetFEM:
    """Tet-mesh FEM model (linear or quadratic tets): rest geometry, lumped masses, energies, gradients, sparse Hessians,
    and the Newton minimiser shared by :func:`simulate_fem` and :func:`static_solve`.

    Args:
        vertices: (Nv, 3) rest positions.
        tets: (Nt, 4) positively oriented tets (see :mod:`vid2sim.meshing.tetra`).
        config: material, floor and solver settings.
    """

    def __init__(self, vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig) -> None:
        X = np.asarray(vertices.detach().cpu() if isinstance(vertices, Tensor) else vertices, dtype=np.float64)
        T = np.asarray(tets.detach().cpu() if isinstance(tets, Tensor) else tets)
        if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] < 4 or not np.isfinite(X).all():
            raise ValueError(f"vertices must be a finite (Nv >= 4, 3) array, got shape {X.shape}")
        if T.ndim != 2 or T.shape[1] != 4 or T.shape[0] == 0 or not np.issubdtype(T.dtype, np.integer):
            raise ValueError(f"tets must be an integer (Nt > 0, 4) array, got shape {T.shape}, dtype {T.dtype}")
        if T.min() < 0 or T.max() >= X.shape[0]:
            raise ValueError(f"tet indices must lie in [0, {X.shape[0] - 1}], got [{T.min()}, {T.max()}]")
        self.config = config
        self.tets = T.astype(np.int64)
        self.order = config.element_order
        self._orders: dict[int, np.ndarray] = {}  # the Hessian's fill-reducing order per size (_factorize)
        if self.order == 2:
            from vid2sim.physics.tet_modes import quadratic_tet_nodes

            nodes, self.elements = quadratic_tet_nodes(X, self.tets)
        else:
            nodes, self.elements = X, self.tets
        #: (N, 3) rest positions of all nodes: the vertices, then (order 2) the edge midpoints
        self.rest = nodes
        self.num_vertices = nodes.shape[0]
        self.mu, self.lam = (float(c) for c in config.lame)
        self._psi, self._pk1, self._tangent = elastic_model(config.material)

        Dm = (X[self.tets[:, 1:]] - X[self.tets[:, :1]]).transpose(0, 2, 1)  # (Nt, 3, 3) columns x_a − x_0
        det = np.linalg.det(Dm)
        diag = float(np.linalg.norm(X.max(0) - X.min(0)))
        if np.any(det <= 1e-14 * diag ** 3):
            bad = int(np.sum(det <= 1e-14 * diag ** 3))
            raise ValueError(f"{bad} of {len(det)} tets have non-positive or zero rest volume; "
                             "reorient/clean the mesh with vid2sim.meshing.tetra.clean_tet_mesh")
        tet_volume = det / 6.0
        # barycentric gradients ∇L_a (Nt, 4, 3); F_ij = Σ_a x_{a,i} ∂_j N_a at every quadrature point
        gradL = np.concatenate([-np.linalg.inv(Dm).sum(axis=1, keepdims=True), np.linalg.inv(Dm)], axis=1)
        self.quad_per_element = 1 if self.order == 1 else 4
        #: (Nq, n, 3) shape-function gradients at the quadrature points (n = 4 or 10 nodes per element)
        self.dN = gradL if self.order == 1 else _quadratic_gradients(gradL).reshape(-1, 10, 3)
        #: (Nq,) quadrature weights (volumes): the elastic energy is Σ_q volumes_q Ψ(F_q)
        self.volumes = np.repeat(tet_volume / self.quad_per_element, self.quad_per_element)
        n = self.elements.shape[1]
        # B = ∂vec(F)/∂x_e, (Nq, 9, 3n): B[q, 3i + j, 3a + k] = δ_ik dN[q, a, j] (row-major vec, node-major x_e)
        B = np.zeros((len(self.volumes), 3, 3, n, 3))
        for i in range(3):
            B[:, i, :, :, i] = self.dN.transpose(0, 2, 1)
        self.B = B.reshape(len(self.volumes), 9, 3 * n)
        self.bbox_diagonal = diag
        m = np.zeros(self.num_vertices)
        # lumped masses: V/4 per vertex (order 1); HRZ (diagonal of the consistent mass, rescaled to the total):
        # V/36 per vertex and 4V/27 per edge midpoint (order 2)
        share = np.full(4, 0.25) if self.order == 1 else np.array([1 / 36] * 4 + [4 / 27] * 6)
        np.add.at(m, self.elements.ravel(), (config.density * tet_volume[:, None] * share[None, :]).ravel())
        if np.any(m <= 0):
            raise ValueError(f"{int(np.sum(m <= 0))} vertices belong to no tet; drop unreferenced vertices first")
        self.masses = m
        #: (N,) lumped rest surface area per node (0 inside): the floor penalty's weights
        self.contact_areas = _contact_areas(X, self.tets, self.elements, self.num_vertices)
        self.gravity = np.asarray(config.gravity, dtype=np.float64)
        #: damping length L (m) and Kelvin–Voigt retardation time τ (s); τ = 0 when undamped
        self.damping_length = float(config.damping_length) if config.damping_length is not None else diag
        self.tau = float(retardation_time(config.damping_ratio, config.youngs_modulus, config.density,
                                          self.damping_length))
        self._build_pattern()

    # -- sparse pattern: CSR structure of the 3Nv × 3Nv Hessian and where each element entry lands --
    def _build_pattern(self) -> None:
        # D (9Nt × 3Nv) with F[e, i, j] = Σ_a x[tets[e, a], i] G[e, a, j]: row 9e + 3i + j, column 3 tets[e, a] + i
        nq, ne = self.dN.shape[:2]
        node = np.repeat(self.elements, self.quad_per_element, axis=0)  # (Nq, ne) nodes of each point's element
        q, a, i, j = np.meshgrid(np.arange(nq), np.arange(ne), np.arange(3), np.arange(3), indexing="ij")
        self._F_operator = sp.csr_matrix(
            (self.dN[q, a, j].ravel(), ((9 * q + 3 * i + j).ravel(), (3 * node[q, a] + i).ravel())),
            shape=(9 * nq, 3 * self.num_vertices))
        self._F_operator_t = self._F_operator.T.tocsr()
        n = 3 * self.num_vertices
        k = 3 * ne
        edofs = (3 * self.elements[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, k)
        rows = np.broadcast_to(edofs[:, :, None], (len(edofs), k, k)).ravel()
        cols = np.broadcast_to(edofs[:, None, :], (len(edofs), k, k)).ravel()
        keys, inverse = np.unique(rows * n + cols, return_inverse=True)
        self._scatter = inverse.ravel()
        self._indices = (keys % n).astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // n, minlength=n))]).astype(np.int32)
        self._diag_pos = np.searchsorted(keys, np.arange(n) * n + np.arange(n))
        self._nnz = len(keys)

    def deformation_gradients(self, x: np.ndarray) -> np.ndarray:
        """F per tet, (Nt, 3, 3), for positions x (Nv, 3): one sparse product vec F = D x (D is built once)."""
        return (self._F_operator @ np.ascontiguousarray(x).reshape(-1)).reshape(-1, 3, 3)

    def min_det(self, x: np.ndarray) -> float:
        """Smallest det F over the tets (≤ 0 means an inverted tet)."""
        return float(_det3(self.deformation_gradients(x)).min())

    def energy_terms(self, x: np.ndarray) -> dict[str, float]:
        """Elastic, gravity (−Σ m g·x) and floor energies at positions x (Nv, 3); elastic is +inf if inverted."""
        F = self.deformation_gradients(x)
        if _det3(F).min() <= 0:
            elastic = math.inf
        else:
            elastic = float(self.volumes @ self._psi(torch.from_numpy(F), self.mu, self.lam).numpy())
        return {"elastic": elastic, "gravity": float(-(self.masses @ (x @ self.gravity))), "floor": self._floor(x)[0]}

    def viscous_term(self, coefficients: tuple[float, float, float], h: float, F_prev: np.ndarray,
                     F_prev2: np.ndarray | None) -> "ViscousTerm | None":
        """The damping part of a time step's incremental potential (None when undamped): reference metric
        C_ref (Nt, 3, 3) from the element F of the last one or two steps, weight a₀ τ / h."""
        if self.tau == 0.0:
            return None
        c_ref = reference_metric(coefficients, torch.from_numpy(F_prev),
                                 None if F_prev2 is None else torch.from_numpy(F_prev2))
        return ViscousTerm(c_ref, coefficients[0] * self.tau / h)

    def _floor(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """Floor energy and the per-vertex penetration depths max(0, h − z) (Nv,)."""
        if self.config.floor_height is None:
            return 0.0, np.zeros(self.num_vertices)
        d = np.maximum(0.0, self.config.floor_height - x[:, 2])
        return float(self.config.floor_stiffness * (self.contact_areas @ (d * d))), d

    def _evaluate(self, x: np.ndarray, x_tilde, inertia: float, x_ref: np.ndarray,
                  viscous: "ViscousTerm | None" = None) -> tuple[float, np.ndarray | None, Tensor | None, float]:
        """Φ(x) = inertia/2 ‖x − x̃‖²_M + Ψ(x) + w Σ V ψ(F; C_ref) + E_floor(x) − Σ m g·(x − x_ref), its gradient
        (3Nv,), the element F (Nt, 3, 3) and the round-off size of Φ (1e-12 × the sum of the magnitudes of its
        terms), in one pass; (inf, None, None, 0) if a tet is inverted."""
        F = self.deformation_gradients(x)
        if not _det3(F).min() > 0:
            return math.inf, None, None, 0.0
        Ft = torch.from_numpy(F)
        psi, P = self._energy_and_pk1(Ft)
        elastic = float(self.volumes @ psi.numpy())
        scale = float(self.volumes @ np.abs(psi.numpy()))
        phi = elastic
        if viscous is not None:
            psi_d, P_d = stvk_energy_and_pk1(Ft, self.mu, self.lam, viscous.c_ref)
            phi += viscous.weight * float(self.volumes @ psi_d.numpy())
            P = P + viscous.weight * P_d
        # forces ∂(Σ V Ψ)/∂x = Dᵀ vec(V P) with vec F = D x
        grad = (self._F_operator_t @ (self.volumes[:, None, None] * P.numpy()).reshape(-1)).reshape(-1, 3)
        grad -= self.masses[:, None] * self.gravity[None, :]
        gravity = float(self.masses @ ((x - x_ref) @ self.gravity))
        phi -= gravity
        scale += float(self.masses @ np.abs(x @ self.gravity))
        if self.config.floor_height is not None:
            d = np.maximum(0.0, self.config.floor_height - x[:, 2])
            floor = float(self.config.floor_stiffness * (self.contact_areas @ (d * d)))
            phi += floor
            scale += floor
            grad[:, 2] -= 2.0 * self.config.floor_stiffness * self.contact_areas * d
        if inertia:
            r = x - x_tilde
            kinetic = 0.5 * inertia * float(self.masses @ (r * r).sum(1))
            phi += kinetic
            scale += kinetic
            grad += inertia * self.masses[:, None] * r
        return phi, grad.ravel(), Ft, 1e-12 * scale

    def _energy_and_pk1(self, F: Tensor) -> tuple[Tensor, Tensor]:
        if self.config.material == "neo_hookean":
            psi, P, _ = neo_hookean_energy_and_pk1(F, self.mu, self.lam)
            return psi, P
        return stvk_energy_and_pk1(F, self.mu, self.lam)

    def _hessian(self, x: np.ndarray, inertia: float, F: Tensor, project: bool,
                 viscous: "ViscousTerm | None" = None) -> sp.csr_matrix:
        """Sparse Hessian of Φ at x (3Nv × 3Nv CSR) from the element F (Nt, 3, 3); element tangents are
        projected to PSD (making H PSD) if ``project``, else exact."""
        C = self._tangent(F, self.mu, self.lam)
        if project:
            C = project_tangent_psd(self.config.material, F, C, self.mu, self.lam)
        else:
            C = 0.5 * (C + C.transpose(1, 2))
        if viscous is not None:
            C = C + viscous.weight * viscous_tangent(F, viscous.c_ref, self.mu, self.lam, psd=project)
        # element Hessians Σ_q V_q B_qᵀ C_q B_q (Nt, 3n, 3n)
        Ke = self.volumes[:, None, None] * np.matmul(self.B.transpose(0, 2, 1), np.matmul(C.numpy(), self.B))
        if self.quad_per_element > 1:
            Ke = Ke.reshape(-1, self.quad_per_element, *Ke.shape[1:]).sum(axis=1)
        data = np.bincount(self._scatter, weights=Ke.ravel(), minlength=self._nnz)
        diag = np.zeros((self.num_vertices, 3))
        if self.config.floor_height is not None:
            diag[:, 2] += 2.0 * self.config.floor_stiffness * self.contact_areas * (self.config.floor_height - x[:, 2] > 0)
        if inertia:
            diag += inertia * self.masses[:, None]
        data[self._diag_pos] += diag.ravel()
        n = 3 * self.num_vertices
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))

    def minimize(self, x_start: np.ndarray, x_tilde: np.ndarray | None = None, inertia: float = 0.0,
                 free: np.ndarray | None = None, viscous: "ViscousTerm | None" = None,
                 factor: "FactorCache | None" = None, step_origin: np.ndarray | None = None
                 ) -> tuple[np.ndarray, NewtonStats]:
        """Newton minimisation of Φ(x) = inertia/2 ‖x − x̃‖²_M + E(x) (+ the viscous term) over the free vertices.

        Args:
            x_start: (Nv, 3) start positions (must have no inverted tet); fixed vertices keep these.
            x_tilde: (Nv, 3) inertial target x̂ of the time step (ignored when ``inertia`` is 0).
            inertia: a₀²/h² for a time step, 0 for a static equilibrium.
            free: (Nv,) bool, the vertices that move (default: all).
            viscous: the damping term of a time step (:meth:`viscous_term`), or None.
            factor: with the direct solver, a :class:`FactorCache` whose sparse factorisation is kept
                between calls and reused (rotated with the object) while the steps contract by at least
                ``FEMConfig.reuse_rate`` per iteration; None factorises at every iteration (plain Newton).
            step_origin: (Nv, 3) the positions at the start of the time step: the Newton tolerance is then
                also relative to the step's largest vertex move (``FEMConfig.newton_rtol``).

        Returns:
            ``(x (Nv, 3), NewtonStats)``.

        Raises:
            FEMSolverError: no valid descent step, or not converged within ``newton_max_iters``.
        """
        cfg = self.config
        x = np.array(x_start, dtype=np.float64)
        if not self.min_det(x) > 0:
            raise FEMSolverError(f"the start state has an inverted tet (min det F = {self.min_det(x):.3g})")
        free_dofs = None if free is None else np.repeat(np.asarray(free, dtype=bool), 3)
        stats = NewtonStats()
        use_cg = cfg.linear_solver == "cg"
        reuse = factor is not None and not use_cg
        factor = factor if reuse else FactorCache()
        always_project = cfg.hessian_projection == "always"

        def restrict(H: sp.csr_matrix) -> sp.csr_matrix:
            return H if free_dofs is None else H[free_dofs][:, free_dofs]

        def refresh(x: np.ndarray, F: Tensor) -> None:
            """Factorise (direct) or store (CG) the Hessian at x: exact when it is positive definite
            (``on_demand``), else with projected element tangents."""
            if not always_project:
                H = restrict(self._hessian(x, inertia, F, False, viscous))
                if use_cg:
                    factor.set(H, None, self._centred(x, free))
                    return
                lu = self._factorize(H, stats, exact=True)
                if lu is not None:
                    factor.set(H, lu, self._centred(x, free))
                    return
                stats.projected_solves += 1
            H = restrict(self._hessian(x, inertia, F, True, viscous))
            factor.set(H, None if use_cg else self._factorize(H, stats, exact=False), self._centred(x, free))

        phi, g, F, slack = self._evaluate(x, x_tilde, inertia, x_start, viscous)
        absolute = cfg.newton_tol * self.bbox_diagonal
        previous = math.inf
        step = np.zeros_like(x)
        for it in range(cfg.newton_max_iters):
            fresh = factor.stale or not reuse
            if fresh:
                refresh(x, F)
                stats.factorizations += 1
            p = self._direction(factor, g, x, free, free_dofs, use_cg, stats)
            gp = float(g @ p) if p is not None else math.nan
            if use_cg and not always_project and not gp < 0:  # CG found the exact Hessian indefinite: project
                stats.projected_solves += 1
                H = restrict(self._hessian(x, inertia, F, True, viscous))
                factor.set(H, None, self._centred(x, free))
                p = self._direction(factor, g, x, free, free_dofs, use_cg, stats)
                gp = float(g @ p)
            stats.iterations = it + 1
            step = p.reshape(-1, 3)
            size = float(np.abs(step).max())
            tol = absolute
            if step_origin is not None:  # a time step: also relative to how far it moves the vertices
                motion = float(np.abs(x + step - step_origin).max())
                tol = max(1e-12 * self.bbox_diagonal, min(absolute, cfg.newton_rtol * motion))
            if size <= tol:
                x_try = x + step
                if self.min_det(x_try) > 0:
                    x = x_try
                stats.converged = True
                return x, stats
            if not gp < 0:
                if not fresh:
                    factor.stale = True
                    continue
                raise FEMSolverError(f"Newton direction is not a descent direction (gᵀp = {gp:.3g}) at iteration {it}")
            alpha = 1.0
            halvings = 0
            accepted = False
            for _ in range(cfg.line_search_max_halvings):
                x_try = x + alpha * step
                phi_try, g_try, F_try, slack_try = self._evaluate(x_try, x_tilde, inertia, x_start, viscous)
                if phi_try <= phi + cfg.armijo * alpha * gp + slack:  # changes of Φ below its round-off pass
                    accepted = True
                    break
                stats.inverted_rejections += int(math.isinf(phi_try))
                if not fresh:
                    # A reused factorisation whose full step fails is not searched along: it was formed at
                    # another state, possibly with another floor-contact set (the penalty's Hessian jumps where
                    # a vertex crosses the floor), and its halved steps can cycle with the fresh step of that
                    # other set. Refactorise here instead.
                    break
                alpha *= 0.5
                halvings += 1
            if not accepted:
                if not fresh:
                    factor.stale = True
                    continue
                raise FEMSolverError(
                    f"line search found no valid step after {cfg.line_search_max_halvings} halvings at Newton iteration "
                    f"{it} (min det F along the step: {self.min_det(x + alpha * step):.3g}, max step "
                    f"{np.abs(step).max():.3g} m)")
            stats.line_search_halvings += halvings
            if halvings > 0 or (not fresh and size > cfg.reuse_rate * previous):
                factor.stale = True  # far from converged or slow contraction: refactorise at the next iteration
            previous = size
            x, phi, g, F, slack = x_try, phi_try, g_try, F_try, slack_try
        raise FEMSolverError(
            f"Newton did not converge in {cfg.newton_max_iters} iterations (last step "
            f"{np.abs(step).max():.3g} m > tolerance {tol:.3g} m); raise FEMConfig.newton_max_iters or substeps")

    def _centred(self, x: np.ndarray, free: np.ndarray | None) -> np.ndarray | None:
        """Mass-centred positions (for the rotation fit of a reused factorisation); None with fixed vertices
        (a clamped body does not turn as a whole)."""
        if free is not None and not free.all():
            return None
        return x - (self.masses @ x) / self.masses.sum()

    def _direction(self, factor: "FactorCache", g: np.ndarray, x: np.ndarray, free: np.ndarray | None,
                   free_dofs: np.ndarray | None, use_cg: bool, stats: NewtonStats) -> np.ndarray | None:
        """−H⁻¹ g over the free dofs (3Nv,) with the kept matrix, turned by the rotation the object made
        since it was formed: H(R x) = (I ⊗ R) H(x) (I ⊗ R)ᵀ for the rotation-invariant energy."""
        R = None
        if factor.points is not None:
            R = _fitted_rotation(factor.points, self._centred(x, free), self.masses)
        gg = g.reshape(-1, 3)
        if R is not None:
            gg = gg @ R  # rows Rᵀ g_i
        rhs = -gg.reshape(-1)
        if free_dofs is not None:
            rhs = rhs[free_dofs]
        if use_cg:
            sol, iterations, ok = _jacobi_pcg(factor.matrix, rhs, self.config.cg_rtol, self.config.cg_max_iters)
            stats.cg_iterations += iterations
            if not ok:
                lu = self._factorize(factor.matrix, stats, exact=False)
                sol = lu.solve(rhs)
        else:
            sol = factor.lu.solve(rhs)
        if not np.isfinite(sol).all():
            raise FEMSolverError("the Newton system produced a non-finite step (singular Hessian: is the object "
                                 "floating with no mass or are all vertices fixed?)")
        p = np.zeros(3 * self.num_vertices)
        if free_dofs is None:
            p = sol
        else:
            p[free_dofs] = sol
        if R is not None:
            p = (p.reshape(-1, 3) @ R.T).reshape(-1)
        return p

    def _factorize(self, H: sp.csr_matrix, stats: NewtonStats, exact: bool):
        """Sparse LDLᵀ of the symmetric H in nested-dissection order (:mod:`vid2sim.physics.sparse_lu`).

        The order depends only on H's pattern, so it is computed once per size (all vertices, or the free
        ones of a static solve) and reused. With ``exact`` (H may be indefinite) returns None when H is
        singular or not positive definite (Sylvester: a pivot ≤ 0); otherwise raises :class:`FEMSolverError`
        when H is singular.
        """
        stats.direct_solves += 1
        # H is symmetric, so its CSR arrays are also its CSC arrays
        Hc = sp.csc_matrix((H.data, H.indices, H.indptr), shape=H.shape)
        order = self._orders.get(H.shape[0])
        if order is None:
            order = self._orders[H.shape[0]] = nested_dissection(Hc)
        try:
            lu = SymmetricLU(Hc, order)
        except RuntimeError as err:  # SuperLU: "Factor is exactly singular"
            if exact:
                return None
            raise FEMSolverError(f"the Newton system is singular ({err}): is part of the mesh unconstrained in "
                                 "a static solve?") from None
        if exact and not lu.positive_definite:
            return None
        return lu

    def step(self, x: np.ndarray, v: np.ndarray, h: float, free: np.ndarray | None = None,
             history: tuple[np.ndarray, np.ndarray] | None = None,
             factor: "FactorCache | None" = None) -> tuple[np.ndarray, np.ndarray, NewtonStats]:
        """One time step of length h with ``config.integrator``: (x, v) (Nv, 3) each → (x', v', stats).

        Args:
            x, v: positions and velocities at the start of the step.
            h: step length (s).
            free: (Nv,) bool, the vertices that move (default: all).
            history: (x_prev, v_prev), the state one step earlier, or None (the first step, which BDF2
                takes as an implicit-Euler step).
            factor: a :class:`FactorCache` shared by consecutive steps (see :meth:`minimize`), or None.

        Newton starts from the extrapolation x + h(3/2 v − 1/2 v_prev) when there is history (error O(h³)),
        else from the inertial target x̂ (or x itself if that inverts a tet). All steps of a run have the
        same h.
        """
        bdf = bdf_step(self.config.integrator, h, h if history is not None else None)
        x_prev, v_prev = history if history is not None else (None, None)
        hist = bdf.needs_history
        x_hat = bdf.target(x, v, x_prev if hist else None, v_prev if hist else None)
        inertia = 1.0 / bdf.energy_scale
        viscous = self.viscous_term(bdf.coefficients, h, self.deformation_gradients(x),
                                    self.deformation_gradients(x_prev) if hist else None)
        start = x_hat if v_prev is None else bdf.start(x, v, v_prev)
        start = start.copy()
        if free is not None:
            start[~free] = x[~free]
        if not self.min_det(start) > 0:
            start = x
        x_new, stats = self.minimize(start, x_hat, inertia, free, viscous, factor, step_origin=x)
        v_new = bdf.velocity(x_new, x, x_prev if hist else None)
        if free is not None:
            v_new[~free] = 0.0
        return x_new, v_new, stats


@dataclass
class FactorCache:
    """The Newton matrix kept between iterations and time steps by :meth:`TetFEM.minimize`.

    Attributes:
        matrix: the (free-dof) Hessian it was made from (CSR).
        lu: its sparse factorisation (direct solver), or None.
        points: (Nv, 3) mass-centred positions where it was made (for the rotation fit), or None.
        stale: refactorise at the next iteration.
    """

    matrix: sp.csr_matrix | None = None
    lu: object | None = None
    points: np.ndarray | None = None
    stale: bool = True

    def set(self, matrix: sp.csr_matrix, lu, points: np.ndarray | None) -> None:
        self.matrix, self.lu, self.points, self.stale = matrix, lu, points, False


@dataclass
class ViscousTerm:
    """The Kelvin–Voigt part w Σ_e V_e ψ(F_e; C_ref,e) of a time step's incremental potential (FEM scale).

    Attributes:
        c_ref: (Nt, 3, 3) reference metric per tet (float64 tensor).
        weight: w = a₀ τ / h.
    """

    c_ref: Tensor
    weight: float


def _jacobi_pcg(H: sp.csr_matrix, b: np.ndarray, rtol: float, max_iters: int) -> tuple[np.ndarray, int, bool]:
    """Conjugate gradients on H x = b with the Jacobi preconditioner: (x, iterations, converged).

    Not converged (returns False) when the residual does not reach ``rtol``·‖b‖ in ``max_iters`` iterations,
    or when a search direction has pᵀHp ≤ 0 (H not positive definite along it) or a value is not finite.
    """
    d = H.diagonal()
    if not (d > 0).all():
        return np.zeros_like(b), 0, False
    dinv = 1.0 / d
    x = np.zeros_like(b)
    r = b.copy()
    z = dinv * r
    p = z.copy()
    rz = float(r @ z)
    target = rtol * float(np.linalg.norm(b))
    if float(np.linalg.norm(r)) <= target:
        return x, 0, True
    for it in range(1, max_iters + 1):
        Hp = H @ p
        curvature = float(p @ Hp)
        if not curvature > 0:
            return x, it, False
        a = rz / curvature
        x += a * p
        r -= a * Hp
        if float(np.linalg.norm(r)) <= target:
            return x, it, bool(np.isfinite(x).all())
        z = dinv * r
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, max_iters, False


def _det3(F: np.ndarray) -> np.ndarray:
    """Determinants of (N, 3, 3) matrices by the triple product (faster than LU for 3×3)."""
    return (F[:, 0, 0] * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
            - F[:, 0, 1] * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
            + F[:, 0, 2] * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))


def _fitted_rotation(reference: np.ndarray, x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The rotation R (3, 3) minimising Σ m_i ‖R a_i − b_i‖² for centred point sets a (reference) and b (x)
    (Kabsch, reflection removed)."""
    cov = (x * m[:, None]).T @ reference
    U, _, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    return (U * np.array([1.0, 1.0, d])) @ Vt


# ---- results and drivers --------------------------------------------------------------------------

@dataclass
class FEMResult:
    """A simulated FEM trajectory.

    Attributes:
        rest_vertices: (N, 3) rest positions of the nodes: the mesh's Nv vertices, then (quadratic tets) one
            node per edge midpoint.
        tets: (Nt, 4) tets (vertex indices).
        trajectory: (T, N, 3) node positions at the video frames; frame 0 is the initial pose.
        velocities: (T, Nv, 3) vertex velocities at the frames.
        times: (T,) seconds.
        energies: name → (T,) total mechanical energy parts: 'kinetic', 'elastic', 'gravity' (−Σ m g·x),
            'floor', 'total'.
        min_det: (T,) smallest det F over the tets per frame.
        newton_iterations: (T − 1, substeps) Newton iterations of every substep.
        line_search_halvings: (T − 1,) backtracking halvings per frame.
        inverted_rejections: (T − 1,) line-search trial states rejected per frame because a tet inverted.
        config: the FEMConfig used.
        pose: the InitialPose used.
        fixed: (Nv,) bool mask of fixed vertices.
        wall_time: seconds spent simulating.
        time_convergence: how the time step was checked (:func:`simulate_fem_converged`): the substeps
            compared, the trajectory difference between them (percent of the size, mean over frames 1 … T−1
            and the largest frame), the tolerance, every comparison made and the wall time of all runs;
            None for a single run.
        elements: (Nt, 10) node indices of the quadratic tets (:func:`vid2sim.physics.tet_modes.quadratic_tet_nodes`
            order), or None for linear tets.
    """

    rest_vertices: Tensor
    tets: Tensor
    trajectory: Tensor
    velocities: Tensor
    times: Tensor
    energies: dict[str, Tensor]
    min_det: Tensor
    newton_iterations: Tensor
    line_search_halvings: Tensor
    inverted_rejections: Tensor
    config: FEMConfig
    pose: InitialPose
    fixed: Tensor
    wall_time: float = 0.0
    time_convergence: dict | None = None
    elements: Tensor | None = None

    @property
    def embedding_elements(self) -> Tensor:
        """The elements that interpolate positions inside the mesh: ``elements`` (Nt, 10) for quadratic
        tets, else ``tets`` (Nt, 4); for :func:`vid2sim.synthetic.embedding.apply_embedding`."""
        return self.tets if self.elements is None else self.elements

    def contact_areas(self) -> Tensor:
        """(N,) the lumped rest boundary area per node that the floor penalty used (0 inside)."""
        X = self.rest_vertices.numpy()[: int(self.tets.max()) + 1]
        T = self.tets.numpy().astype(np.int64)
        elements = T if self.elements is None else self.elements.numpy().astype(np.int64)
        return torch.from_numpy(_contact_areas(X, T, elements, self.rest_vertices.shape[0]))

    @property
    def max_penetration(self) -> float:
        """Largest floor penetration max(0, h − z) over all frames and vertices (0 without a floor)."""
        if self.config.floor_height is None:
            return 0.0
        return float((self.config.floor_height - self.trajectory[..., 2]).clamp_min(0).max())

    def save(self, path: str | Path) -> Path:
        """Write everything to one ``.npz`` (config and pose as JSON strings); returns the path."""
        path = Path(path)
        arrays = {k: getattr(self, k).numpy() for k in
                  ("rest_vertices", "tets", "trajectory", "velocities", "times", "min_det", "newton_iterations",
                   "line_search_halvings", "inverted_rejections", "fixed")}
        arrays.update({f"energy_{k}": v.numpy() for k, v in self.energies.items()})
        if self.elements is not None:
            arrays["elements"] = self.elements.numpy()
        np.savez_compressed(path, config=json.dumps(asdict(self.config)), pose=json.dumps(asdict(self.pose)),
                            wall_time=self.wall_time, time_convergence=json.dumps(self.time_convergence), **arrays)
        return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")

    @classmethod
    def load(cls, path: str | Path) -> "FEMResult":
        """Read a file written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"FEM result file {path} does not exist")
        with np.load(path, allow_pickle=False) as z:
            missing = {"config", "pose", "rest_vertices", "tets", "trajectory"} - set(z.files)
            if missing:
                raise ValueError(f"{path} is not an FEM result file: missing {sorted(missing)}")
            cfg = json.loads(str(z["config"]))
            cfg["gravity"] = tuple(cfg["gravity"])
            t = lambda k: torch.from_numpy(z[k].copy())  # noqa: E731
            return cls(rest_vertices=t("rest_vertices"), tets=t("tets"), trajectory=t("trajectory"),
                       velocities=t("velocities"), times=t("times"),
                       energies={k[len("energy_"):]: t(k) for k in z.files if k.startswith("energy_")},
                       min_det=t("min_det"), newton_iterations=t("newton_iterations"),
                       line_search_halvings=t("line_search_halvings"), inverted_rejections=t("inverted_rejections"),
                       config=FEMConfig(**cfg), pose=InitialPose(**json.loads(str(z["pose"]))),
                       fixed=t("fixed"), wall_time=float(z["wall_time"]),
                       time_convergence=json.loads(str(z["time_convergence"])) if "time_convergence" in z.files else None,
                       elements=t("elements") if "elements" in z.files else None)


def _fixed_mask(fixed, num_vertices: int) -> np.ndarray:
    if fixed is None:
        return np.zeros(num_vertices, dtype=bool)
    f = np.asarray(fixed.detach().cpu() if isinstance(fixed, Tensor) else fixed)
    if f.shape != (num_vertices,) or f.dtype != bool:
        raise ValueError(f"fixed must be a boolean mask of shape ({num_vertices},), got shape {f.shape}, dtype {f.dtype}")
    return f


def _mechanical_energy(model: TetFEM, x: np.ndarray, v: np.ndarray) -> dict[str, float]:
    e = model.energy_terms(x)
    e["kinetic"] = 0.5 * float(model.masses @ (v * v).sum(1))
    e["total"] = e["kinetic"] + e["elastic"] + e["gravity"] + e["floor"]
    return e


def simulate_fem(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig | None = None,
                 pose: InitialPose | None = None, frames: int = 24, fixed: Tensor | np.ndarray | None = None,
                 initial_velocity: Tensor | np.ndarray | None = None, progress: bool = True,
                 on_frame: Callable[[], None] | None = None) -> FEMResult:
    """Simulate an elastic tet mesh dropped onto the floor.

    Args:
        vertices: (Nv, 3) rest positions (canonical frame).
        tets: (Nt, 4) positively oriented tets.
        config: FEMConfig (defaults if None).
        pose: initial pose (rotation about the centre of mass, drop height, rigid velocity); None
            keeps the rest positions where they are with zero velocity.
        frames: number of video frames T >= 1 (frame 0 is the initial state; T − 1 frame steps).
        fixed: (Nv,) bool mask of vertices held at their initial positions (Dirichlet), or None.
        initial_velocity: (Nv, 3) velocity overriding the pose's rigid velocity (e.g. a mode shape).
        progress: show a tqdm bar over frames.
        on_frame: called after every simulated frame (progress reporting from another process).

    Returns:
        FEMResult with (T, Nv, 3) trajectory and velocities, energies, Newton statistics.

    Raises:
        FEMSolverError: a step could not be solved (see :meth:`TetFEM.minimize`).
    """
    config = config or FEMConfig()
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    with single_torch_thread():
        return _simulate(vertices, tets, config, pose, frames, fixed, initial_velocity, progress, on_frame)


@contextlib.contextmanager
def single_torch_thread():
    """Run torch on one intra-op thread inside the block (restored after).

    The FEM alternates small torch kernels (per-tet stresses) with numpy/scipy work; with several torch
    threads their OpenMP workers keep spinning through the numpy parts and slow both down (measured 4.5×
    on a 13 000-tet mesh with 2 threads). Parallelism comes from running independent simulations side by
    side instead (:func:`simulate_fem_converged`).
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _simulate(vertices, tets, config: FEMConfig, pose, frames: int, fixed, initial_velocity, progress: bool,
              on_frame: Callable[[], None] | None) -> FEMResult:
    model = TetFEM(vertices, tets, config)
    fixed_np = _fixed_mask(fixed, model.num_vertices)
    free = None if not fixed_np.any() else ~fixed_np
    rest = torch.from_numpy(model.rest)
    if pose is None:
        x0, v0 = rest.clone(), torch.zeros_like(rest)
        pose_used = InitialPose(drop_height=0.0)
    else:
        x0, v0 = pose.apply(rest, torch.from_numpy(model.masses), config.floor_height)
        pose_used = pose
    x, v = x0.numpy().copy(), v0.numpy().copy()
    if initial_velocity is not None:
        iv = np.asarray(initial_velocity.detach().cpu() if isinstance(initial_velocity, Tensor) else initial_velocity,
                        dtype=np.float64)
        if iv.shape != x.shape or not np.isfinite(iv).all():
            raise ValueError(f"initial_velocity must be a finite ({model.num_vertices}, 3) array, got shape {iv.shape}")
        v = iv.copy()
    v[fixed_np] = 0.0
    if not model.min_det(x) > 0:
        raise ValueError("the initial state has inverted tets")

    h = config.dt / config.substeps
    traj, vels, dets = [x.copy()], [v.copy()], [model.min_det(x)]
    energies = {k: [val] for k, val in _mechanical_energy(model, x, v).items()}
    iters = np.zeros((frames - 1, config.substeps), dtype=np.int64)
    halvings = np.zeros(frames - 1, dtype=np.int64)
    rejections = np.zeros(frames - 1, dtype=np.int64)
    start = time.perf_counter()
    history = None
    factor = FactorCache() if config.reuse_factorization else None
    for f in tqdm(range(frames - 1), desc="FEM frames", disable=not progress):
        for s in range(config.substeps):
            try:
                x_new, v_new, stats = model.step(x, v, h, free, history, factor)
                history, x, v = (x, v), x_new, v_new
            except FEMSolverError as err:
                raise FEMSolverError(f"frame {f + 1}, substep {s + 1}/{config.substeps}: {err}") from None
            iters[f, s] = stats.iterations
            halvings[f] += stats.line_search_halvings
            rejections[f] += stats.inverted_rejections
        traj.append(x.copy())
        vels.append(v.copy())
        dets.append(model.min_det(x))
        for k, val in _mechanical_energy(model, x, v).items():
            energies[k].append(val)
        if on_frame is not None:
            on_frame()
    wall = time.perf_counter() - start
    return FEMResult(
        rest_vertices=rest, tets=torch.from_numpy(model.tets), trajectory=torch.from_numpy(np.stack(traj)),
        velocities=torch.from_numpy(np.stack(vels)), times=torch.arange(frames, dtype=torch.float64) * config.dt,
        energies={k: torch.tensor(val, dtype=torch.float64) for k, val in energies.items()},
        min_det=torch.tensor(dets, dtype=torch.float64), newton_iterations=torch.from_numpy(iters),
        line_search_halvings=torch.from_numpy(halvings), inverted_rejections=torch.from_numpy(rejections),
        config=config, pose=pose_used, fixed=torch.from_numpy(fixed_np), wall_time=wall,
        elements=None if model.order == 1 else torch.from_numpy(model.elements))


def simulate_fem_converged(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig | None = None,
                           pose: InitialPose | None = None, frames: int = 24, tolerance: float = 1.0,
                           start_substeps: int | None = None, max_substeps: int = 256,
                           progress: bool = True, workers: int = 1) -> FEMResult:
    """An FEM trajectory converged in time: simulate with n and 2n substeps per frame, doubling n until the
    two trajectories differ by at most ``tolerance`` percent of the object's size (mean over frames 1 … T−1
    of the mean vertex distance, :func:`vid2sim.metrics.trajectory_distance`); return the finer run with
    :attr:`FEMResult.time_convergence` filled in.

    Args:
        vertices, tets, pose, frames: as :func:`simulate_fem`.
        config: FEMConfig; its ``substeps`` is replaced.
        tolerance: largest allowed change under 2× refinement, in percent of the rest bounding-box diagonal.
        start_substeps: the first n; default half of :func:`vid2sim.physics.integrators.auto_substeps` for the
            material (at least 4), so that stiff materials start finer.
        max_substeps: give up (:class:`FEMSolverError`) rather than go beyond this.
        progress: show a progress bar.
        workers: processes for the first pair of runs (n and 2n are independent, so 2 workers take about
            the time of the finer run alone); 1 (default) runs everything in this process. Workers are
            spawned, so a script calling this with ``workers > 1`` needs the usual
            ``if __name__ == "__main__":`` guard.

    Raises:
        FEMSolverError: a step failed, or the tolerance was not met with ``max_substeps``.
    """
    from vid2sim.metrics.trajectory import trajectory_distance
    from vid2sim.physics.integrators import auto_substeps

    config = config or FEMConfig()
    X = np.asarray(vertices.detach().cpu() if isinstance(vertices, Tensor) else vertices, dtype=np.float64)
    T = np.asarray(tets.detach().cpu() if isinstance(tets, Tensor) else tets)
    size = float(np.linalg.norm(X.max(0) - X.min(0)))
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive percentage, got {tolerance!r}")
    if start_substeps is None:
        length = config.damping_length if config.damping_length is not None else size
        start_substeps = max(4, auto_substeps(config.dt, config.youngs_modulus, config.density, length) // 2)
    n = int(start_substeps)
    if n < 1 or 2 * n > max_substeps:
        raise ValueError(f"start_substeps must be in [1, {max_substeps // 2}], got {start_substeps!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")

    coarse, fine = _simulate_each(X, T, [replace(config, substeps=n), replace(config, substeps=2 * n)], pose,
                                  frames, workers, progress)
    history = []
    total = coarse.wall_time + fine.wall_time
    while True:
        d = trajectory_distance(coarse.trajectory, fine.trajectory, size)
        history.append({"substeps": [n, 2 * n], "mean_percent": round(d.mean, 4), "max_percent": round(d.max, 4)})
        if d.mean <= tolerance:
            fine.time_convergence = {
                "substeps": [n, 2 * n], "kept": 2 * n, "tolerance_percent": tolerance,
                "mean_percent": d.mean, "max_percent": d.max, "per_frame_percent": d.per_frame,
                "measure": "mean over frames 1..T-1 of the mean vertex distance, percent of the rest bounding-box "
                           "diagonal, between the runs with n and 2n substeps",
                "comparisons": history, "wall_time_all_runs": total}
            return fine
        if 4 * n > max_substeps:
            raise FEMSolverError(
                f"the trajectory is not converged in time: {n} and {2 * n} substeps per frame differ by {d.mean:.2f} % "
                f"of the size (tolerance {tolerance} %) and {4 * n} would exceed max_substeps={max_substeps}")
        n, coarse = 2 * n, fine
        (fine,) = _simulate_each(X, T, [replace(config, substeps=2 * n)], pose, frames, 1, progress)
        total += fine.wall_time


def _simulate_each(vertices: np.ndarray, tets: np.ndarray, configs: list[FEMConfig], pose, frames: int,
                   workers: int, progress: bool) -> list[FEMResult]:
    """simulate_fem for each config, in up to ``workers`` processes, with one progress bar over all frames."""
    label = "FEM frames (" + ", ".join(f"{c.substeps} substeps" for c in configs) + ")"
    if workers == 1 or len(configs) == 1:
        with tqdm(total=len(configs) * (frames - 1), desc=label, disable=not progress) as bar:
            return [simulate_fem(vertices, tets, c, pose, frames, progress=False, on_frame=lambda: bar.update())
                    for c in configs]
    import multiprocessing as mp
    from concurrent.futures import wait

    from vid2sim.runtime.workers import process_pool

    with mp.get_context("spawn").Manager() as manager:
        queue = manager.Queue()
        with process_pool(min(workers, len(configs))) as pool, \
                tqdm(total=len(configs) * (frames - 1), desc=label, disable=not progress) as bar:
            futures = [pool.submit(_simulate_in_worker, vertices, tets, c, pose, frames, queue) for c in configs]
            pending = set(futures)
            while pending:
                _, pending = wait(pending, timeout=0.5)
                while not queue.empty():
                    bar.update(queue.get())
            return [f.result() for f in futures]


def _simulate_in_worker(vertices, tets, config, pose, frames, queue) -> FEMResult:
    return simulate_fem(vertices, tets, config, pose, frames, progress=False, on_frame=lambda: queue.put(1))


@dataclass
class StaticResult:
    """A static equilibrium: positions (Nv, 3) and the Newton statistics of each load step."""

    positions: Tensor
    stats: list[NewtonStats] = field(default_factory=list)


def static_solve(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig,
                 fixed: Tensor | np.ndarray, load_steps: int = 1) -> StaticResult:
    """Static equilibrium under gravity (and the floor, if configured) with fixed vertices at rest.
    Uses the direct solver unless ``config.linear_solver`` is 'cg'.

    Minimises Σ V Ψ(F) + E_floor − Σ m g·x over the free vertices, applying gravity in ``load_steps``
    equal increments (each solved to convergence) for robustness under large loads.

    Args:
        vertices: (Nv, 3) rest positions.
        tets: (Nt, 4) tets.
        config: FEMConfig (its dt and substeps are unused).
        fixed: (Nv,) bool mask of clamped vertices (at least one; the problem is singular otherwise).
        load_steps: number of gravity increments >= 1.

    Returns:
        StaticResult with the equilibrium positions.
    """
    if not (isinstance(load_steps, int) and load_steps >= 1):
        raise ValueError(f"load_steps must be an integer >= 1, got {load_steps!r}")
    model = TetFEM(vertices, tets, config)
    fixed_np = _fixed_mask(fixed, model.num_vertices)
    if not fixed_np.any():
        raise ValueError("static_solve needs at least one fixed vertex: a free body has no unique equilibrium "
                         "(the frictionless floor leaves horizontal motion unconstrained)")
    g_full = model.gravity.copy()
    x = model.rest.copy()
    all_stats = []
    for i in range(1, load_steps + 1):
        model.gravity = g_full * (i / load_steps)
        x, stats = model.minimize(x, free=~fixed_np)
        all_stats.append(stats)
    return StaticResult(positions=torch.from_numpy(x), stats=all_stats)
