"""Finite-element ground truth for the synthetic benchmark: linear tetrahedra, the paper's Neo-Hookean
energy, gravity, the floor penalty of docs/architecture.md and Kelvin–Voigt damping, integrated in time (BDF2 or
implicit
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

from vid2sim.synthetic.fem.config import FEMConfig, FEMSolverError, InitialPose
from vid2sim.synthetic.fem.model import FactorCache, NewtonStats, TetFEM, ViscousTerm
from vid2sim.synthetic.fem.run import (
    FEMResult,
    StaticResult,
    simulate_fem,
    simulate_fem_converged,
    single_torch_thread,
    static_solve,
)

__all__ = ["FEMConfig", "FEMSolverError", "InitialPose", "FactorCache", "NewtonStats", "TetFEM", "ViscousTerm",
           "FEMResult", "StaticResult", "simulate_fem", "simulate_fem_converged", "single_torch_thread", "static_solve"]
