"""The discrete model of the FEM ground truth: linear or quadratic tetrahedra, lumped masses, the floor, Kelvin–Voigt
damping, and the Newton solve of one time step (:class:`TetFEM`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor

from vid2sim.meshing.tetra import boundary_faces, surface_vertex_areas
from vid2sim.physics.damping import (
    reference_metric,
    retardation_time,
    viscous_tangent,
)
from vid2sim.physics.integrators import bdf_step
from vid2sim.physics.materials import (
    elastic_model,
    neo_hookean_energy_and_pk1,
    project_tangent_psd,
    stvk_energy_and_pk1,
)
from vid2sim.physics.sparse_lu import SymmetricLU, nested_dissection
from vid2sim.physics.tet_modes import TET_EDGES, quadratic_tet_nodes, quadrature_points
from vid2sim.synthetic.fem.config import FEMConfig, FEMSolverError

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

    out = np.empty((gradL.shape[0], 4, 10, 3))
    for q, L in enumerate(quadrature_points()):
        for a in range(4):
            out[:, q, a] = (4 * L[a] - 1) * gradL[:, a]
        for e, (a, b) in enumerate(TET_EDGES):
            out[:, q, 4 + e] = 4 * (L[a] * gradL[:, b] + L[b] * gradL[:, a])
    return out


def contact_areas(X: np.ndarray, tets: np.ndarray, elements: np.ndarray, num_nodes: int) -> np.ndarray:
    """(N,) lumped rest boundary area per node: a third of each boundary triangle's area to each vertex
    (linear tets), or for quadratic tets HRZ on the 6-node triangle: A/19 per vertex and 16A/57 per edge
    midpoint."""

    if elements.shape[1] == 4:
        return surface_vertex_areas(torch.from_numpy(X), torch.from_numpy(tets)).numpy()

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
    """Tet-mesh FEM model (linear or quadratic tets): rest geometry, lumped masses, energies, gradients, sparse
    Hessians,
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
        self.contact_areas = contact_areas(X, self.tets, self.elements, self.num_vertices)
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
            diag[:, 2] += (
                2.0 * self.config.floor_stiffness * self.contact_areas * (self.config.floor_height - x[:, 2] > 0)
            )
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
        run = _NewtonRun(self, x_start, x_tilde, inertia, free, viscous, factor)
        stats = run.stats
        phi, g, F, slack = self._evaluate(x, x_tilde, inertia, x_start, viscous)
        absolute = cfg.newton_tol * self.bbox_diagonal
        previous = math.inf
        step = np.zeros_like(x)
        for it in range(cfg.newton_max_iters):
            fresh = run.factor.stale or not run.reuse
            if fresh:
                run.refresh(x, F)
                stats.factorizations += 1
            p, gp = run.direction(x, g, F)
            stats.iterations = it + 1
            step = p.reshape(-1, 3)
            size = float(np.abs(step).max())
            tol = self._step_tolerance(absolute, x, step, step_origin)
            if size <= tol:
                x_try = x + step
                if self.min_det(x_try) > 0:
                    x = x_try
                stats.converged = True
                return x, stats
            if not gp < 0:
                if not fresh:
                    run.factor.stale = True
                    continue
                raise FEMSolverError(f"Newton direction is not a descent direction (gᵀp = {gp:.3g}) at iteration {it}")
            alpha, halvings, accepted = run.line_search(x, step, phi, gp, slack, fresh)
            if accepted is None:
                if not fresh:
                    run.factor.stale = True
                    continue
                raise self._line_search_failure(it, x, alpha, step)
            stats.line_search_halvings += halvings
            if halvings > 0 or (not fresh and size > cfg.reuse_rate * previous):
                run.factor.stale = True  # far from converged or slow contraction: refactorise at the next iteration
            previous = size
            x, phi, g, F, slack = accepted
        raise FEMSolverError(
            f"Newton did not converge in {cfg.newton_max_iters} iterations (last step "
            f"{np.abs(step).max():.3g} m > tolerance {tol:.3g} m); raise FEMConfig.newton_max_iters or substeps")

    def _step_tolerance(self, absolute: float, x: np.ndarray, step: np.ndarray, step_origin: np.ndarray | None
                        ) -> float:
        """The Newton step size (m) below which :meth:`minimize` has converged: ``absolute``, and in a time step
        (``step_origin`` (Nv, 3) given) also ``newton_rtol`` times the step's largest vertex move from x + step
        (Nv, 3), but not below 1e-12 of the size."""
        if step_origin is None:
            return absolute
        motion = float(np.abs(x + step - step_origin).max())  # a time step: how far it moves the vertices
        return max(1e-12 * self.bbox_diagonal, min(absolute, self.config.newton_rtol * motion))

    def _line_search_failure(self, it: int, x: np.ndarray, alpha: float, step: np.ndarray) -> FEMSolverError:
        """The error of a line search from x (Nv, 3) along ``step`` (Nv, 3) that found no valid step (``alpha``: the
        last fraction tried) at Newton iteration ``it``."""
        return FEMSolverError(
            f"line search found no valid step after {self.config.line_search_max_halvings} halvings at Newton "
            f"iteration "
            f"{it} (min det F along the step: {self.min_det(x + alpha * step):.3g}, max step "
            f"{np.abs(step).max():.3g} m)"
        )

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


class _NewtonRun:
    """The linear algebra of one :meth:`TetFEM.minimize` call: the Hessian restricted to the free dofs, factorised
    (direct solver) or kept (CG) in ``factor`` (reused between iterations and calls when one is given), the Newton
    direction from it, and the backtracking line search along that direction."""

    def __init__(self, fem: TetFEM, x_start: np.ndarray, x_tilde: np.ndarray | None, inertia: float,
                 free: np.ndarray | None, viscous: "ViscousTerm | None", factor: "FactorCache | None") -> None:
        cfg = fem.config
        self.fem, self.x_start, self.x_tilde, self.inertia, self.free, self.viscous = (
            fem, x_start, x_tilde, inertia, free, viscous)
        #: (3Nv,) bool, the free degrees of freedom (None: all)
        self.free_dofs = None if free is None else np.repeat(np.asarray(free, dtype=bool), 3)
        self.stats = NewtonStats()
        self.use_cg = cfg.linear_solver == "cg"
        self.reuse = factor is not None and not self.use_cg
        self.factor = factor if self.reuse else FactorCache()
        self.always_project = cfg.hessian_projection == "always"

    def restrict(self, H: sp.csr_matrix) -> sp.csr_matrix:
        """The Hessian (3Nv × 3Nv) restricted to the free dofs."""
        return H if self.free_dofs is None else H[self.free_dofs][:, self.free_dofs]

    def refresh(self, x: np.ndarray, F: Tensor) -> None:
        """Factorise (direct) or store (CG) the Hessian at x (Nv, 3) from the element F (Nt, 3, 3): exact when it
        is positive definite (``on_demand``), else with projected element tangents."""
        fem, stats, factor = self.fem, self.stats, self.factor
        if not self.always_project:
            H = self.restrict(fem._hessian(x, self.inertia, F, False, self.viscous))
            if self.use_cg:
                factor.set(H, None, fem._centred(x, self.free))
                return
            lu = fem._factorize(H, stats, exact=True)
            if lu is not None:
                factor.set(H, lu, fem._centred(x, self.free))
                return
            stats.projected_solves += 1
        H = self.restrict(fem._hessian(x, self.inertia, F, True, self.viscous))
        factor.set(H, None if self.use_cg else fem._factorize(H, stats, exact=False), fem._centred(x, self.free))

    def direction(self, x: np.ndarray, g: np.ndarray, F: Tensor) -> tuple[np.ndarray, float]:
        """The Newton direction p (3Nv,) at x (Nv, 3) for the gradient g (3Nv,), and gᵀp; with CG, an exact
        Hessian found indefinite is replaced by the projected one and the direction solved again."""
        fem, stats = self.fem, self.stats
        p = fem._direction(self.factor, g, x, self.free, self.free_dofs, self.use_cg, stats)
        gp = float(g @ p) if p is not None else math.nan
        if self.use_cg and not self.always_project and not gp < 0:  # CG found the exact Hessian indefinite: project
            stats.projected_solves += 1
            H = self.restrict(fem._hessian(x, self.inertia, F, True, self.viscous))
            self.factor.set(H, None, fem._centred(x, self.free))
            p = fem._direction(self.factor, g, x, self.free, self.free_dofs, self.use_cg, stats)
            gp = float(g @ p)
        return p, gp

    def line_search(self, x: np.ndarray, step: np.ndarray, phi: float, gp: float, slack: float, fresh: bool
                    ) -> tuple[float, int, tuple | None]:
        """Backtrack from the full ``step`` (Nv, 3) until Armijo's condition holds (a change of Φ below its
        round-off ``slack`` passes); a reused (not ``fresh``) factorisation tries the full step only.

        Returns:
            the last step fraction tried, the halvings, and the accepted ``(x, Φ, gradient, F, slack)`` at the
            new positions, or None when no step was accepted.
        """
        cfg = self.fem.config
        alpha = 1.0
        halvings = 0
        for _ in range(cfg.line_search_max_halvings):
            x_try = x + alpha * step
            phi_try, g_try, F_try, slack_try = self.fem._evaluate(x_try, self.x_tilde, self.inertia, self.x_start,
                                                                  self.viscous)
            if phi_try <= phi + cfg.armijo * alpha * gp + slack:  # changes of Φ below its round-off pass
                return alpha, halvings, (x_try, phi_try, g_try, F_try, slack_try)
            self.stats.inverted_rejections += int(math.isinf(phi_try))
            if not fresh:
                # A reused factorisation whose full step fails is not searched along: it was formed at
                # another state, possibly with another floor-contact set (the penalty's Hessian jumps where
                # a vertex crosses the floor), and its halved steps can cycle with the fresh step of that
                # other set. Refactorise here instead.
                break
            alpha *= 0.5
            halvings += 1
        return alpha, halvings, None


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


