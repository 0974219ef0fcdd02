"""Finite-element ground truth for the synthetic benchmark: linear tetrahedra, the paper's Neo-Hookean
energy, gravity and the floor penalty of DESIGN.md, integrated with implicit Euler and Newton's method.

Model
-----
* Elements: linear (P1) tetrahedra, constant deformation gradient F = D_s D_m⁻¹ per tet; elastic energy
  Σ_e V_e Ψ(F_e) with Ψ from :mod:`vid2sim.physics.materials` (Neo-Hookean by default, as in the paper).
* Mass: lumped, ρ V_e / 4 to each vertex of each tet (the same lumped-mass choice as the reduced
  simulator's ρ V / N per cubature point). Gravity energy −Σ_i m_i g·x_i.
* Floor: the plane z = h with the paper's penalty E_f = k Σ_i max(0, h − z_i)² (k = 1e5 by default),
  summed **per mesh vertex** (only surface vertices can reach the floor). The reduced simulator sums the
  same formula over its cubature points, so the two models see the same total contact stiffness only
  when about as many points touch the floor; a FEM mesh usually has more contact vertices than the
  reduced model has contact cubature points, so its penetration is smaller. The resting penetration is
  m g / (2 k n_contact); :attr:`FEMResult.max_penetration` reports it. No friction (the paper's floor
  has none either).
* Damping: none besides implicit Euler's numerical dissipation (the paper's model has none either);
  it is what makes a dropped object settle, and it depends on h — see :attr:`FEMConfig.substeps`.
* Time integration: implicit Euler with ``substeps`` steps of h = dt / substeps per video frame; each
  step minimises the incremental potential ½‖x − x_n − h v_n‖²_M / h² + E(x) by Newton's method with a
  sparse Hessian whose per-element 9×9 tangent C = ∂P/∂F is projected to positive semi-definite (so
  every element Hessian V Bᵀ C⁺ B, B = ∂vec(F)/∂x_e, is PSD and the system matrix M/h² + K⁺ + floor
  is SPD). Linear systems: Jacobi-preconditioned CG for time steps, sparse direct LU for statics
  (:attr:`FEMConfig.linear_solver`). Backtracking line
  search from the full Newton step; a trial state with any det F ≤ 0, a non-finite energy or no
  sufficient decrease is rejected. Converged when the Newton step's largest vertex move is below
  ``newton_tol`` × the rest bounding-box diagonal.
* Fixed (Dirichlet) vertices: a boolean mask; those vertices keep their initial position.

Everything runs in float64 on the CPU with numpy/scipy (the per-element stress and tangent come from
:mod:`vid2sim.physics.materials` in torch); inputs on any device are moved there and results are
float64 CPU tensors. This is offline ground-truth generation, so exactness comes before speed.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.physics.materials import ELASTIC_MODELS, elastic_model, lame_parameters, project_tangent_psd


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
        substeps: implicit-Euler steps per frame (h = dt / substeps = 3.1 ms by default). Measured on
            random drops of a 0.6 × 0.4 × 0.3 m box (E = 1e4…1e6): up to the first impact (frames
            0–7) the trajectory is first-order convergent and 16 substeps stay within 0.3–1.3 % of the
            bounding-box diagonal (mean vertex distance) of a 64-substep run; over all 24 frames the
            mean distance is 2–15 %, because the model has no physical damping (elastic body,
            conservative penalty floor, no friction) and after an impact implicit Euler's numerical
            dissipation — which shrinks with h — decides how high the object bounces and how it
            tumbles. 16 is a cost/accuracy compromise; raise it for more faithful post-impact motion.
        floor_height: z of the floor plane, or None for no floor.
        floor_stiffness: k of the floor penalty k Σ_vertices max(0, h − z)².
        gravity: (3,) acceleration (m/s²).
        newton_max_iters: Newton iterations per step before :class:`FEMSolverError`.
        newton_tol: convergence when max_i |Δx_i| ≤ newton_tol × rest bounding-box diagonal.
        line_search_max_halvings: backtracking halvings before :class:`FEMSolverError`.
        armijo: sufficient-decrease constant.
        linear_solver: Newton system solver: 'direct' (sparse LU, symmetric ordering), 'cg'
            (Jacobi-preconditioned conjugate gradients; a system CG cannot solve to ``cg_rtol`` in
            ``cg_max_iters`` is re-solved directly and counted in :attr:`NewtonStats.direct_solves`), or
            'auto': CG for implicit-Euler steps (the mass term M/h² makes them well conditioned; several
            times faster on 3D meshes, whose direct factors fill in badly) and direct for static solves.
        cg_rtol: relative residual at which CG stops (the Newton convergence test is on the step, so
            this only needs to make the step accurate to well below ``newton_tol``).
        cg_max_iters: CG iterations before the direct solver takes over.
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
    floor_height: float | None = -0.7
    floor_stiffness: float = 1e5
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    newton_max_iters: int = 100
    newton_tol: float = 1e-6
    line_search_max_halvings: int = 40
    armijo: float = 1e-4
    linear_solver: str = "auto"
    cg_rtol: float = 1e-6
    cg_max_iters: int = 1000
    hessian_projection: str = "on_demand"

    def __post_init__(self) -> None:
        lame_parameters(self.youngs_modulus, self.poisson_ratio)  # validates E and ν
        if self.hessian_projection not in ("always", "on_demand"):
            raise ValueError(
                f"FEMConfig.hessian_projection must be 'always' or 'on_demand', got {self.hessian_projection!r}")
        if self.material not in ELASTIC_MODELS:
            raise ValueError(f"FEMConfig.material must be one of {sorted(ELASTIC_MODELS)}, got {self.material!r}")
        if self.linear_solver not in ("auto", "direct", "cg"):
            raise ValueError(f"FEMConfig.linear_solver must be 'auto', 'direct' or 'cg', got {self.linear_solver!r}")
        for name in ("density", "dt", "floor_stiffness", "newton_tol", "cg_rtol"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0 and math.isfinite(value)):
                raise ValueError(f"FEMConfig.{name} must be a positive finite number, got {value!r}")
        for name in ("substeps", "newton_max_iters", "line_search_max_halvings", "cg_max_iters"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"FEMConfig.{name} must be an integer >= 1, got {value!r}")
        if self.floor_height is not None and not math.isfinite(self.floor_height):
            raise ValueError(f"FEMConfig.floor_height must be finite or None, got {self.floor_height}")
        g = tuple(float(c) for c in self.gravity)
        if len(g) != 3 or not all(math.isfinite(c) for c in g):
            raise ValueError(f"FEMConfig.gravity must be three finite numbers, got {self.gravity!r}")
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
                raise ValueError(f"InitialPose.{name} must be three finite numbers, got {getattr(self, name)!r}")
            setattr(self, name, tuple(float(c) for c in value))
        if not (math.isfinite(self.drop_height) and self.drop_height >= 0):
            raise ValueError(f"InitialPose.drop_height must be a finite number >= 0, got {self.drop_height}")
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
    """

    iterations: int = 0
    line_search_halvings: int = 0
    converged: bool = False
    cg_iterations: int = 0
    direct_solves: int = 0
    inverted_rejections: int = 0
    projected_solves: int = 0


class TetFEM:
    """Linear-tetrahedron FEM model: rest geometry, lumped masses, energies, gradients, sparse Hessians,
    and the Newton minimiser shared by :func:`simulate_fem` and :func:`static_solve`.

    Args:
        vertices: (Nv, 3) rest positions.
        tets: (Nt, 4) positively oriented tets (see :mod:`vid2sim.data.tetra`).
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
        self.rest = X
        self.tets = T.astype(np.int64)
        self.num_vertices = X.shape[0]
        self.mu, self.lam = (float(c) for c in config.lame)
        self._psi, self._pk1, self._tangent = elastic_model(config.material)

        Dm = (X[self.tets[:, 1:]] - X[self.tets[:, :1]]).transpose(0, 2, 1)  # (Nt, 3, 3) columns x_a − x_0
        det = np.linalg.det(Dm)
        diag = float(np.linalg.norm(X.max(0) - X.min(0)))
        if np.any(det <= 1e-14 * diag ** 3):
            bad = int(np.sum(det <= 1e-14 * diag ** 3))
            raise ValueError(f"{bad} of {len(det)} tets have non-positive or zero rest volume; "
                             "reorient/clean the mesh with vid2sim.data.tetra.clean_tet_mesh")
        self.volumes = det / 6.0
        Dm_inv = np.linalg.inv(Dm)
        # shape-function gradients G[e, a, j] = ∂N_a/∂X_j; F_ij = Σ_a x_{a,i} G_aj
        self.G = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)  # (Nt, 4, 3)
        # B = ∂vec(F)/∂x_e, (Nt, 9, 12): B[e, 3i + j, 3a + k] = δ_ik G[e, a, j] (row-major vec, vertex-major x_e)
        B = np.zeros((len(T), 3, 3, 4, 3))
        for i in range(3):
            B[:, i, :, :, i] = self.G.transpose(0, 2, 1)
        self.B = B.reshape(len(T), 9, 12)
        self.bbox_diagonal = diag
        m = np.zeros(self.num_vertices)
        np.add.at(m, self.tets.ravel(), np.repeat(config.density * self.volumes / 4.0, 4))
        if np.any(m <= 0):
            raise ValueError(f"{int(np.sum(m <= 0))} vertices belong to no tet; drop unreferenced vertices first")
        self.masses = m
        self.gravity = np.asarray(config.gravity, dtype=np.float64)
        self._build_pattern()

    # -- sparse pattern: CSR structure of the 3Nv × 3Nv Hessian and where each element entry lands --
    def _build_pattern(self) -> None:
        n = 3 * self.num_vertices
        edofs = (3 * self.tets[:, :, None] + np.arange(3)[None, None, :]).reshape(-1, 12)
        rows = np.broadcast_to(edofs[:, :, None], (len(edofs), 12, 12)).ravel()
        cols = np.broadcast_to(edofs[:, None, :], (len(edofs), 12, 12)).ravel()
        keys, inverse = np.unique(rows * n + cols, return_inverse=True)
        self._scatter = inverse.ravel()
        self._indices = (keys % n).astype(np.int32)
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(keys // n, minlength=n))]).astype(np.int32)
        self._diag_pos = np.searchsorted(keys, np.arange(n) * n + np.arange(n))
        self._nnz = len(keys)

    def deformation_gradients(self, x: np.ndarray) -> np.ndarray:
        """F per tet, (Nt, 3, 3), for positions x (Nv, 3)."""
        return np.matmul(x[self.tets].transpose(0, 2, 1), self.G)

    def min_det(self, x: np.ndarray) -> float:
        """Smallest det F over the tets (≤ 0 means an inverted tet)."""
        return float(np.linalg.det(self.deformation_gradients(x)).min())

    def energy_terms(self, x: np.ndarray) -> dict[str, float]:
        """Elastic, gravity (−Σ m g·x) and floor energies at positions x (Nv, 3); elastic is +inf if inverted."""
        F = self.deformation_gradients(x)
        if np.linalg.det(F).min() <= 0:
            elastic = math.inf
        else:
            elastic = float(self.volumes @ self._psi(torch.from_numpy(F), self.mu, self.lam).numpy())
        return {"elastic": elastic, "gravity": float(-(self.masses @ (x @ self.gravity))), "floor": self._floor(x)[0]}

    def _floor(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """Floor energy and the per-vertex penetration depths max(0, h − z) (Nv,)."""
        if self.config.floor_height is None:
            return 0.0, np.zeros(self.num_vertices)
        d = np.maximum(0.0, self.config.floor_height - x[:, 2])
        return float(self.config.floor_stiffness * (d @ d)), d

    def _objective(self, x, x_tilde, inertia, x_ref) -> float:
        """Φ(x) = inertia/2 ‖x − x̃‖²_M + Ψ(x) + E_floor(x) − Σ m g·(x − x_ref); +inf if any tet is inverted."""
        F = self.deformation_gradients(x)
        if not np.linalg.det(F).min() > 0:
            return math.inf
        phi = float(self.volumes @ self._psi(torch.from_numpy(F), self.mu, self.lam).numpy())
        phi += self._floor(x)[0] - float(self.masses @ ((x - x_ref) @ self.gravity))
        if inertia:
            r = x - x_tilde
            phi += 0.5 * inertia * float(self.masses @ (r * r).sum(1))
        return phi

    def _roundoff(self, x, x_tilde, inertia) -> float:
        """Size of the round-off in Φ: 1e-12 × the sum of the magnitudes of its terms (energy units)."""
        F = self.deformation_gradients(x)
        scale = float(self.volumes @ np.abs(self._psi(torch.from_numpy(F), self.mu, self.lam).numpy()))
        scale += self._floor(x)[0] + float(self.masses @ np.abs(x @ self.gravity))
        if inertia:
            r = x - x_tilde
            scale += 0.5 * inertia * float(self.masses @ (r * r).sum(1))
        return 1e-12 * scale

    def _gradient_hessian(self, x, x_tilde, inertia, project: bool) -> tuple[np.ndarray, sp.csr_matrix, Tensor]:
        """∇Φ (3Nv,), the sparse Hessian (3Nv × 3Nv CSR; element tangents PSD-projected if ``project``) and
        the element deformation gradients F (Nt, 3, 3) for :meth:`_hessian`."""
        F = torch.from_numpy(self.deformation_gradients(x))
        P = self._pk1(F, self.mu, self.lam).numpy()
        vol = self.volumes
        # element forces: ∂(V Ψ)/∂x_{a,i} = V Σ_j P_ij G_aj
        fe = vol[:, None, None] * np.matmul(self.G, P.transpose(0, 2, 1))  # (Nt, 4, 3)
        flat = self.tets.ravel()
        grad = np.stack([np.bincount(flat, weights=fe[..., c].ravel(), minlength=self.num_vertices)
                         for c in range(3)], axis=1)
        grad -= self.masses[:, None] * self.gravity[None, :]
        if self.config.floor_height is not None:
            d = np.maximum(0.0, self.config.floor_height - x[:, 2])
            grad[:, 2] -= 2.0 * self.config.floor_stiffness * d
        if inertia:
            grad += inertia * self.masses[:, None] * (x - x_tilde)
        return grad.ravel(), self._hessian(x, inertia, F, project), F

    def _hessian(self, x: np.ndarray, inertia: float, F: Tensor, project: bool) -> sp.csr_matrix:
        """Sparse Hessian of Φ at x (3Nv × 3Nv CSR) from the element F (Nt, 3, 3); element tangents are
        projected to PSD (making H PSD) if ``project``, else exact."""
        C = self._tangent(F, self.mu, self.lam)
        if project:
            C = project_tangent_psd(self.config.material, F, C, self.mu, self.lam)
        else:
            C = 0.5 * (C + C.transpose(1, 2))
        # element Hessians V Bᵀ C B (Nt, 12, 12)
        Ke = self.volumes[:, None, None] * np.matmul(self.B.transpose(0, 2, 1), np.matmul(C.numpy(), self.B))
        data = np.bincount(self._scatter, weights=Ke.ravel(), minlength=self._nnz)
        diag = np.zeros((self.num_vertices, 3))
        if self.config.floor_height is not None:
            diag[:, 2] += 2.0 * self.config.floor_stiffness * (self.config.floor_height - x[:, 2] > 0)
        if inertia:
            diag += inertia * self.masses[:, None]
        data[self._diag_pos] += diag.ravel()
        n = 3 * self.num_vertices
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))

    def minimize(self, x_start: np.ndarray, x_tilde: np.ndarray | None = None, inertia: float = 0.0,
                 free: np.ndarray | None = None) -> tuple[np.ndarray, NewtonStats]:
        """Newton minimisation of Φ(x) = inertia/2 ‖x − x̃‖²_M + E(x) over the free vertices.

        Args:
            x_start: (Nv, 3) start positions (must have no inverted tet); fixed vertices keep these.
            x_tilde: (Nv, 3) inertial target x_n + h v_n (ignored when ``inertia`` is 0).
            inertia: 1/h² for an implicit-Euler step, 0 for a static equilibrium.
            free: (Nv,) bool, the vertices that move (default: all).

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
        use_cg = cfg.linear_solver == "cg" or (cfg.linear_solver == "auto" and inertia > 0)
        always_project = cfg.hessian_projection == "always"

        def direction(H: sp.csr_matrix, g: np.ndarray, exact: bool) -> tuple[np.ndarray | None, float]:
            """Newton step p (3Nv,) and gᵀp over the free dofs; (None, nan) if the exact H gives none."""
            if free_dofs is None:
                p = self._solve(H, -g, use_cg, stats, exact)
            else:
                sol = self._solve(H[free_dofs][:, free_dofs], -g[free_dofs], use_cg, stats, exact)
                p = None if sol is None else np.zeros_like(g)
                if p is not None:
                    p[free_dofs] = sol
            return (None, math.nan) if p is None else (p, float(g @ p))

        phi = self._objective(x, x_tilde, inertia, x_start)
        tol = cfg.newton_tol * self.bbox_diagonal
        for it in range(cfg.newton_max_iters):
            g, H, F = self._gradient_hessian(x, x_tilde, inertia, project=always_project)
            p, gp = direction(H, g, exact=not always_project)
            if not always_project and not gp < 0:  # exact Hessian indefinite here: project it
                stats.projected_solves += 1
                p, gp = direction(self._hessian(x, inertia, F, project=True), g, exact=False)
            stats.iterations = it + 1
            step = p.reshape(-1, 3)
            if np.abs(step).max() <= tol:
                x_try = x + step
                if self.min_det(x_try) > 0:
                    x = x_try
                stats.converged = True
                return x, stats
            if gp >= 0:
                raise FEMSolverError(f"Newton direction is not a descent direction (gᵀp = {gp:.3g}) at iteration {it}")
            alpha = 1.0
            slack = self._roundoff(x, x_tilde, inertia)  # accept changes of Φ below its round-off
            for _ in range(cfg.line_search_max_halvings):
                x_try = x + alpha * step
                phi_try = self._objective(x_try, x_tilde, inertia, x_start)
                if phi_try <= phi + cfg.armijo * alpha * gp + slack:
                    break
                stats.inverted_rejections += int(math.isinf(phi_try))
                alpha *= 0.5
                stats.line_search_halvings += 1
            else:
                raise FEMSolverError(
                    f"line search found no valid step after {cfg.line_search_max_halvings} halvings at Newton iteration "
                    f"{it} (min det F along the step: {self.min_det(x + alpha * step):.3g}, max step "
                    f"{np.abs(step).max():.3g} m)")
            x, phi = x_try, phi_try
        raise FEMSolverError(
            f"Newton did not converge in {cfg.newton_max_iters} iterations (last step "
            f"{np.abs(step).max():.3g} m > tolerance {tol:.3g} m); raise FEMConfig.newton_max_iters or substeps")

    def _solve(self, H: sp.csr_matrix, rhs: np.ndarray, use_cg: bool, stats: NewtonStats,
               exact: bool = False) -> np.ndarray | None:
        """Solve the symmetric system H p = rhs: Jacobi-preconditioned CG if ``use_cg`` (direct if CG does not
        reach ``cg_rtol``), else a sparse direct LU with a symmetric ordering.

        With ``exact`` (H may be indefinite), returns None instead of falling back or raising when CG does
        not converge, or the factorisation is singular or shows H is not positive definite; the caller
        then projects H. Without it H must be positive (semi-)definite.
        """
        if use_cg:
            count = [0]

            def tick(_):
                count[0] += 1

            p, info = spla.cg(H, rhs, rtol=self.config.cg_rtol, maxiter=self.config.cg_max_iters,
                              M=sp.diags(1.0 / H.diagonal()), callback=tick)
            stats.cg_iterations += count[0]
            if info == 0 and np.isfinite(p).all():
                return p
            if exact:
                return None
        stats.direct_solves += 1
        # H is symmetric, so its CSR arrays are also its CSC arrays
        Hc = sp.csc_matrix((H.data, H.indices, H.indptr), shape=H.shape)
        try:
            lu = spla.splu(Hc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as err:  # SuperLU: "Factor is exactly singular"
            if exact:
                return None
            raise FEMSolverError(f"the Newton system is singular ({err}): is part of the mesh unconstrained in "
                                 "a static solve?") from None
        if exact:
            # diagonal pivoting with the same row and column order is a symmetric LDLᵀ (D = diag U):
            # by Sylvester's law H is positive definite iff every pivot is positive
            if not (np.array_equal(lu.perm_r, lu.perm_c) and (lu.U.diagonal() > 0).all()):
                return None
        p = lu.solve(rhs)
        if not np.isfinite(p).all():
            if exact:
                return None
            raise FEMSolverError("the Newton system produced a non-finite step (singular Hessian: is the object "
                                 "floating with no mass or are all vertices fixed?)")
        return p

    def step(self, x: np.ndarray, v: np.ndarray, h: float, free: np.ndarray | None = None,
             v_prev: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, NewtonStats]:
        """One implicit-Euler step of length h: (x, v) (Nv, 3) each → (x', v', stats), v' = (x' − x)/h.

        Newton starts from the candidate with the lowest incremental potential among x + h(2v − v_prev)
        (constant-acceleration extrapolation, when the previous velocity ``v_prev`` is given), the
        inertial prediction x + h v, and x itself; the start only affects the iteration count.
        """
        x_tilde = x + h * v
        inertia = 1.0 / (h * h)
        candidates = [x_tilde, x] if v_prev is None else [x + h * (2.0 * v - v_prev), x_tilde, x]
        best, best_phi = x, math.inf
        for c in candidates:
            c = c.copy()
            if free is not None:
                c[~free] = x[~free]
            phi = self._objective(c, x_tilde, inertia, x)
            if phi < best_phi:
                best, best_phi = c, phi
        x_new, stats = self.minimize(best, x_tilde, inertia, free)
        v_new = (x_new - x) / h
        if free is not None:
            v_new[~free] = 0.0
        return x_new, v_new, stats


# ---- results and drivers --------------------------------------------------------------------------

@dataclass
class FEMResult:
    """A simulated FEM trajectory.

    Attributes:
        rest_vertices: (Nv, 3) rest positions.
        tets: (Nt, 4) tets.
        trajectory: (T, Nv, 3) positions at the video frames; frame 0 is the initial pose.
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
        np.savez_compressed(path, config=json.dumps(asdict(self.config)), pose=json.dumps(asdict(self.pose)),
                            wall_time=self.wall_time, **arrays)
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
                       fixed=t("fixed"), wall_time=float(z["wall_time"]))


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
                 initial_velocity: Tensor | np.ndarray | None = None, progress: bool = True) -> FEMResult:
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

    Returns:
        FEMResult with (T, Nv, 3) trajectory and velocities, energies, Newton statistics.

    Raises:
        FEMSolverError: a step could not be solved (see :meth:`TetFEM.minimize`).
    """
    config = config or FEMConfig()
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
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
    v_prev = None
    for f in tqdm(range(frames - 1), desc="FEM frames", disable=not progress):
        for s in range(config.substeps):
            try:
                x, v_new, stats = model.step(x, v, h, free, v_prev)
                v_prev, v = v, v_new
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
    wall = time.perf_counter() - start
    return FEMResult(
        rest_vertices=rest, tets=torch.from_numpy(model.tets), trajectory=torch.from_numpy(np.stack(traj)),
        velocities=torch.from_numpy(np.stack(vels)), times=torch.arange(frames, dtype=torch.float64) * config.dt,
        energies={k: torch.tensor(val, dtype=torch.float64) for k, val in energies.items()},
        min_det=torch.tensor(dets, dtype=torch.float64), newton_iterations=torch.from_numpy(iters),
        line_search_halvings=torch.from_numpy(halvings), inverted_rejections=torch.from_numpy(rejections),
        config=config, pose=pose_used, fixed=torch.from_numpy(fixed_np), wall_time=wall)


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
