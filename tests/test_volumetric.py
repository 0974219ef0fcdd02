"""The projected volumetric term (``Simulator(volumetric="projected")``): exact derivatives, exact adjoint,
the bulk response kept, and the subspace's volumetric locking removed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vid2sim.meshing.tetra import box_tet_mesh, sample_points_in_tets
from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.external import Floor, Gravity
from vid2sim.physics.integrators import bdf_step
from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.modes import (
    stiffness_calibration_curve,
    subspace_frequencies,
    subspace_stiffness_parts,
)
from vid2sim.physics.neural_jacobian import NeuralJacobian
from vid2sim.physics.skinning import SkinningField
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.physics.solver import Material, SimConfig, Simulator, _StepSpec
from vid2sim.physics.tet_modes import tet_frequencies
from vid2sim.physics.volumetric import project, projection_basis

BOX = (0.6, 0.2, 0.3)
TIGHT = dict(newton_tol=1e-13, newton_rtol=1e-12, newton_max_iters=60)


@pytest.fixture(scope="module")
def box_field():
    """A data-free-trained 4-handle field on a 0.6 × 0.2 × 0.3 m box, its rest tets and interior points."""
    mesh = box_tet_mesh(BOX, (12, 4, 6))
    pts, _, _ = sample_points_in_tets(mesh.vertices.double(), mesh.tets, 1500, seed=0)
    torch.manual_seed(0)
    field = SkinningField(num_handles=4, seed=0).double()
    train_skinning(field, pts, SkinningTrainingConfig(iterations=200, points_per_step=500, batch_size=4, seed=0),
                   progress=False)
    for p in field.parameters():
        p.requires_grad_(False)
    return field, pts, mesh


def _sim(field, pts, k=120, material=None, externals=(), config=None, **kw):
    idx, w = sample_cubature(pts, k, volume=float(np.prod(BOX)), seed=0)
    return Simulator(field, pts[idx], w, material or Material(2e4, 0.45, 1000.0, damping_ratio=0.1),
                     list(externals), config or SimConfig(substeps=2, **TIGHT), volumetric="projected", **kw)


def _problem(sim, basis, y_prev, ydot_prev, tau):
    mu, lam = sim.lame()
    spec = _StepSpec(sim.X, sim.vol, torch.eye(3, dtype=sim.X.dtype).expand(sim.X.shape[0], 3, 3), basis.structured,
                     "neo_hookean", sim.externals, 0.01, bdf_step("bdf2", 0.005, None), sim.config)
    return spec.problem(y_prev, ydot_prev, None, None, mu, lam, tau, sim.masses(), basis.b, basis.basis, None,
                        None, None, basis.volumetric)


def test_the_projection_is_v_orthogonal_onto_the_weights_span(box_field):
    field, pts, _ = box_field
    sim = _sim(field, pts)
    w = field(sim.X)
    Wo = projection_basis(w, sim.vol)
    assert torch.allclose(Wo.T @ (sim.vol[:, None] * Wo), torch.eye(w.shape[1], dtype=w.dtype), atol=1e-12)
    for column in (torch.ones_like(sim.vol), w[:, 0], w[:, 2] - 3 * w[:, 1]):  # the span is kept as it is
        assert torch.allclose(project(Wo, sim.vol, column), column, atol=1e-10)
    values = torch.randn(sim.X.shape[0], dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    residual = values - project(Wo, sim.vol, values)  # orthogonal to every weight
    assert float((w.T @ (sim.vol * residual)).abs().max()) < 1e-12
    with pytest.raises(ValueError, match="linearly dependent"):
        projection_basis(torch.cat([w, w[:, :1]], dim=1), sim.vol)


def test_affine_states_keep_the_pointwise_energy_and_others_cost_no_more(box_field):
    """A uniform volume change is projected onto itself, so an affine deformation has the Neo-Hookean
    energy exactly; for any state the projected λ term is at most the pointwise one (‖P ℓ‖_V ≤ ‖ℓ‖_V)."""
    field, pts, _ = box_field
    sim = _sim(field, pts, material=Material(2e4, 0.45, 1000.0, damping_ratio=0.0))
    pointwise = Simulator(sim.field, sim.X, sim.vol, sim.material, [], sim.config)
    H = field.num_handles_total
    affine = torch.zeros(H, 3, 4, dtype=torch.float64)
    affine[-1, :, :3] = torch.tensor([[-0.1, 0.02, 0.0], [0.01, -0.08, 0.03], [0.0, 0.02, 0.05]])  # F = I + this
    states = {"affine": affine.reshape(-1)}
    g = torch.Generator().manual_seed(2)
    states["bent"] = 0.03 * torch.randn(12 * H, dtype=torch.float64, generator=g)
    energies = {}
    for name, z in states.items():
        for label, s in (("projected", sim), ("pointwise", pointwise)):
            basis = s.reduced_basis()
            y = z[s._perm]
            energies[name, label] = float(_problem(s, basis, y, torch.zeros_like(y), None).potential(y)[0])
    assert energies["affine", "projected"] == pytest.approx(energies["affine", "pointwise"], rel=1e-12)
    assert energies["bent", "projected"] < energies["bent", "pointwise"]


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize("neural_jacobian", [False, True])
def test_gradient_and_hessian_match_finite_differences(box_field, damped, neural_jacobian):
    field, pts, _ = box_field
    kw = {}
    if neural_jacobian:  # the dense-basis path (B_p from a (K, 9, 12H) basis)
        kw = dict(jacobian=NeuralJacobian(field.num_handles_total, encoding_dim=16, widths=(32, 32), seed=0).double(),
                  use_neural_jacobian=True)
    sim = _sim(field, pts, k=60, externals=[Gravity(), Floor(height=-0.2)], **kw)
    basis = sim.reduced_basis()
    g = torch.Generator().manual_seed(3)
    D = sim.num_dofs
    y_prev, ydot_prev = (
        0.02 * torch.randn(D, generator=g, dtype=torch.float64),
        0.1 * torch.randn(D, generator=g, dtype=torch.float64),
    )
    problem = _problem(sim, basis, y_prev, ydot_prev, sim.retardation_time() if damped else None)
    y = y_prev + 0.02 * torch.randn(D, generator=g, dtype=torch.float64)
    d = torch.randn(D, generator=g, dtype=torch.float64)
    eps = 1e-6
    phi_p, g_p, _ = problem.evaluate(y + eps * d)
    phi_m, g_m, _ = problem.evaluate(y - eps * d)
    _, grad, ok = problem.evaluate(y)
    assert ok
    fd = (phi_p - phi_m) / (2 * eps)
    assert abs(float((grad @ d - fd).detach())) <= 1e-7 * abs(float(fd.detach()))
    H = problem.hessian(y, project=False)
    fd_h = (g_p - g_m) / (2 * eps)
    assert float((H @ d - fd_h).detach().norm()) <= 1e-7 * float(fd_h.detach().norm())
    assert float(torch.linalg.eigvalsh(problem.hessian(y, project=True).detach()).min()) > 0  # Newton's is PD


def test_the_rest_hessian_is_the_projected_modal_stiffness(box_field):
    """At rest the step's elastic Hessian is μ K_μ + λ K_λ with K_λ projected (what the calibration uses)."""
    field, pts, _ = box_field
    sim = _sim(field, pts, material=Material(1.0, 0.4, 1.0, damping_ratio=0.0))
    basis = sim.reduced_basis()
    y = torch.zeros(sim.num_dofs, dtype=torch.float64)
    problem = _problem(sim, basis, y, y, None)
    elastic = (problem.hessian(y, project=False) - problem.mass_matrix) / problem.step.energy_scale
    w, dw = field.weights_and_gradients(sim.X)
    K_mu, K_lam, _ = subspace_stiffness_parts(sim.X, w, dw, 1.0, sim.vol, volumetric="projected")
    mu, lam = lame_parameters(1.0, 0.4)
    assert torch.allclose(elastic, mu * K_mu + lam * K_lam, atol=1e-9 * float(K_mu.abs().max()))


def test_adjoint_gradients_match_finite_differences(box_field):
    """Gradients of a window (a spinning, deforming, damped object in free fall, BDF2, 2 substeps) to log10 E,
    ν, the damping ratio and a skinning weight (which moves the projection too): relative error < 1e-3."""
    field0, pts, _ = box_field
    field = SkinningField(num_handles=4, seed=0).double()
    field.load_state_dict(field0.state_dict())
    sim = _sim(field, pts, k=80, material=Material(3e4, 0.45, 1000.0, damping_ratio=0.2), externals=[Gravity()])
    names = ("log10_E", "nu", "damping_ratio")
    for name in names:
        getattr(sim, name).requires_grad_(True)
    W = list(field.parameters())[-2]
    probe = pts[::15]

    def loss_of() -> torch.Tensor:
        state = sim.rigid_velocity_state([0.2, 0.0, -2.0], [0.0, 8.0, 3.0])
        z = sim.rollout(state, 4)[-1].z
        x = sim.positions(probe, z)
        return (x * torch.linspace(-1.0, 1.0, x.numel(), dtype=x.dtype).reshape(x.shape)).sum()

    grads = torch.autograd.grad(loss_of(), [getattr(sim, n) for n in names] + [W])

    def value(**kw) -> float:
        with torch.no_grad():
            saved = {k: getattr(sim, k).detach().clone() for k in names}
            for k, v in kw.items():
                setattr(sim, k, v)
            out = float(loss_of())
            for k, v in saved.items():
                setattr(sim, k, v)
        return out

    for i, name in enumerate(names):
        base, h = getattr(sim, name).detach(), 1e-4
        fd = (value(**{name: base + h}) - value(**{name: base - h})) / (2 * h)
        assert abs(float(grads[i]) - fd) <= 1e-3 * abs(fd), (name, float(grads[i]), fd)
    a, b, h = 1, 5, 1e-4
    old = float(W[a, b].detach())
    with torch.no_grad():
        W[a, b] = old + h
        lp = value()
        W[a, b] = old - h
        lm = value()
        W[a, b] = old
    fd = (lp - lm) / (2 * h)
    assert abs(float(grads[3][a, b]) - fd) <= 1e-3 * abs(fd), (float(grads[3][a, b]), fd)


def test_the_projection_removes_the_subspace_s_volumetric_locking(box_field):
    """Against quadratic tets on the same box, the pointwise subspace's lowest frequency rises with ν (locking:
    ≥ 10 % from ν = 0.3 to 0.49 with 4 handles); the projected one stays within 3 % of its value at 0.3."""
    field, pts, mesh = box_field
    idx, w = sample_cubature(pts, 300, volume=float(np.prod(BOX)), seed=0)
    ratio = {}
    for nu in (0.3, 0.49):
        ref = tet_frequencies(mesh.vertices, mesh.tets, 1.0, nu, 1.0, k=1, order=2)[0]
        for term in ("pointwise", "projected"):
            ratio[term, nu] = subspace_frequencies(field, pts[idx], w, 1.0, nu, 1.0, k=1, volumetric=term)[0] / ref
    assert ratio["pointwise", 0.49] / ratio["pointwise", 0.3] > 1.1
    assert abs(ratio["projected", 0.49] / ratio["projected", 0.3] - 1) < 0.03
    assert ratio["projected", 0.49] < ratio["pointwise", 0.49]


def test_bad_volumetric_settings_are_refused(box_field):
    field, pts, mesh = box_field
    idx, w = sample_cubature(pts, 50, volume=float(np.prod(BOX)), seed=0)
    with pytest.raises(ValueError, match="volumetric must be one of"):
        Simulator(field, pts[idx], w, Material(1e4, 0.3), volumetric="mixed")
    with pytest.raises(ValueError, match="needs the neo_hookean model"):
        Simulator(field, pts[idx], w, Material(1e4, 0.3, model="stvk"), volumetric="projected")
    with pytest.raises(ValueError, match="factors=1"):
        stiffness_calibration_curve(field, pts[idx], w, mesh.vertices, mesh.tets, factors=2, volumetric="projected")
    with pytest.raises(ValueError, match="volumetric must be"):
        subspace_stiffness_parts(pts[idx], *field.weights_and_gradients(pts[idx]), 1.0, w, volumetric="bbar")
