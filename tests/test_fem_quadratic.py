"""Quadratic (10-node) tets in the FEM ground truth: against scikit-fem, Euler–Bernoulli, finite differences,
closed forms, and the modal reference of :mod:`vid2sim.physics.tet_modes`."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from vid2sim.meshing.tetra import box_tet_mesh
from vid2sim.physics.tet_modes import (
    quadratic_tet_nodes,
    tet_stiffness_and_mass,
)
from vid2sim.synthetic.embedding import apply_embedding, embed_points
from vid2sim.synthetic.fem import (
    FEMConfig,
    FEMResult,
    InitialPose,
    TetFEM,
    simulate_fem,
    static_solve,
)

skfem = importlib.import_module("skfem")  # a declared test dependency: a broken install fails
from skfem.models.elasticity import lame_parameters as skfem_lame  # noqa: E402
from skfem.models.elasticity import linear_elasticity  # noqa: E402

BEAM_L, BEAM_B, BEAM_E, BEAM_RHO, G = 1.0, 0.1, 1e8, 1000.0, 9.8


def _box(res=(2, 1, 1), size=(0.3, 0.2, 0.2)):
    mesh = box_tet_mesh(size, res, origin=tuple(-s / 2 for s in size))
    return mesh.vertices.numpy(), mesh.tets.numpy()


def _beam(resolution):
    mesh = box_tet_mesh((BEAM_L, BEAM_B, BEAM_B), resolution)
    return mesh.vertices.numpy(), mesh.tets.numpy()


def _config(**kw):
    base = dict(youngs_modulus=BEAM_E, poisson_ratio=0.0, density=BEAM_RHO, floor_height=None, element_order=2,
                damping_ratio=0.0)
    return FEMConfig(**{**base, **kw})


def test_nodes_masses_and_contact_areas():
    X, T = _box()
    model = TetFEM(X, T, _config())
    nodes, elements = quadratic_tet_nodes(X, T)
    assert np.array_equal(model.rest, nodes) and np.array_equal(model.elements, elements)
    assert model.volumes.shape == (4 * len(T),) and model.volumes.sum() == pytest.approx(0.3 * 0.2 * 0.2)
    assert model.masses.sum() == pytest.approx(BEAM_RHO * 0.3 * 0.2 * 0.2) and (model.masses > 0).all()
    # HRZ on the 6-node boundary triangles: areas sum to the surface, interior nodes carry none
    surface = 2 * (0.3 * 0.2 * 2 + 0.2 * 0.2)
    assert model.contact_areas.sum() == pytest.approx(surface)
    on_boundary = (np.abs(np.abs(nodes) - np.array([0.15, 0.1, 0.1])) < 1e-12).any(axis=1)
    assert np.array_equal(model.contact_areas > 0, on_boundary)


def test_hessian_at_rest_is_scikit_fems_quadratic_stiffness():
    """At rest Neo-Hookean is linear elasticity: our Hessian equals the P2 stiffness of
    :mod:`vid2sim.physics.tet_modes`, and that has the eigenvalues of scikit-fem's ElementTetP2 stiffness."""
    X, T = _box()
    nu = 0.3
    model = TetFEM(X, T, _config(poisson_ratio=nu))
    F = torch.from_numpy(model.deformation_gradients(model.rest))
    H = model._hessian(model.rest, 0.0, F, False)
    K, _, _ = tet_stiffness_and_mass(X, T, BEAM_E, nu, BEAM_RHO, order=2)
    assert abs(H - K).max() < 1e-12 * abs(K).max()
    basis = skfem.Basis(skfem.MeshTet(X.T.copy(), T.T.copy()), skfem.ElementVector(skfem.ElementTetP2()))
    Ks = skfem.asm(linear_elasticity(*skfem_lame(BEAM_E, nu)), basis)
    ours, theirs = np.linalg.eigvalsh(K.toarray()), np.linalg.eigvalsh(Ks.toarray())
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9 * theirs.max())


def test_static_cantilever_matches_euler_bernoulli_on_a_coarse_mesh():
    """Linear tets need 60 × 1 × 8 cells to come within 10 % (tests/test_fem.py); quadratic tets on 10 × 1 × 2
    are within 2 % of the slender-beam tip deflection q L⁴ / (8 E I)."""
    X, T = _beam((10, 1, 2))
    model = TetFEM(X, T, _config())
    nodes = model.rest
    fixed = nodes[:, 0] < 1e-9
    tip = nodes[:, 0] > BEAM_L - 1e-9
    positions = static_solve(X, T, _config(newton_tol=1e-9), fixed).positions.numpy()
    delta = -(positions - nodes)[tip, 2].mean()
    delta_eb = BEAM_RHO * G * BEAM_B ** 2 * BEAM_L ** 4 / (8 * BEAM_E * BEAM_B ** 4 / 12)
    assert abs(delta / delta_eb - 1) < 0.02, (delta, delta_eb)


@pytest.mark.parametrize("damped", [False, True])
def test_gradient_and_hessian_match_finite_differences(damped):
    X, T = _box(res=(1, 1, 1))
    cfg = FEMConfig(youngs_modulus=1e4, poisson_ratio=0.35, floor_height=-0.08, damping_ratio=0.3, element_order=2)
    model = TetFEM(X, T, cfg)
    rng = np.random.default_rng(0)
    R = model.rest
    x = 1.05 * R + 0.002 * rng.normal(size=R.shape)
    x_tilde = R + 0.01 * rng.normal(size=R.shape)
    viscous = None
    if damped:
        viscous = model.viscous_term((1.5, 2.0, -0.5), 0.01, model.deformation_gradients(1.02 * R),
                                     model.deformation_gradients(1.01 * R))
    assert (x[:, 2] < cfg.floor_height).any()
    g = model._evaluate(x, x_tilde, 400.0, R, viscous)[1]
    H = model._hessian(x, 400.0, torch.from_numpy(model.deformation_gradients(x)), False, viscous)
    eps = 1e-6
    d = rng.normal(size=x.size)
    phi = lambda y: model._evaluate(y, x_tilde, 400.0, R, viscous)[0]  # noqa: E731
    fd = (phi(x + eps * d.reshape(x.shape)) - phi(x - eps * d.reshape(x.shape))) / (2 * eps)
    assert g @ d == pytest.approx(fd, rel=1e-6)
    g_plus = model._evaluate(x + eps * d.reshape(x.shape), x_tilde, 400.0, R, viscous)[1]
    g_minus = model._evaluate(x - eps * d.reshape(x.shape), x_tilde, 400.0, R, viscous)[1]
    np.testing.assert_allclose(H @ d, (g_plus - g_minus) / (2 * eps), rtol=1e-5, atol=1e-6 * np.abs(H @ d).max())


def test_free_fall_is_rigid_and_exact():
    """BDF2 under constant gravity: x_n = x_0 + n h v_0 + h² g n²/2 + (3/4) h² g (1 − 3⁻ⁿ) at every node."""
    X, T = _box()
    cfg = FEMConfig(floor_height=-100.0, substeps=4, dt=0.05, newton_tol=1e-10, element_order=2)
    pose = InitialPose(drop_height=1.0, rotation=(0.3, -0.2, 0.5), linear_velocity=(0.5, -0.2, 1.0))
    result = simulate_fem(X, T, cfg, pose, frames=4, progress=False)
    assert result.elements is not None and result.trajectory.shape[1] == len(result.rest_vertices) > len(X)
    x0 = result.trajectory[0].numpy()
    h, g, v0 = cfg.dt / cfg.substeps, np.array(cfg.gravity), np.array(pose.linear_velocity)
    for f in range(4):
        n = f * cfg.substeps
        expected = x0 + n * h * v0 + h * h * g * n * n / 2 + 0.75 * h * h * g * (1 - 3.0 ** -n)
        np.testing.assert_allclose(result.trajectory[f].numpy(), expected, atol=1e-8)


def test_cantilever_vibrates_at_its_eigenperiod():
    """Released undeformed under gravity, the clamped beam swings about its static deflection at the first
    eigenperiod of the same discretisation (our Hessian at rest and lumped masses), to BDF2's O((ωh)²)."""
    X, T = _beam((10, 1, 2))
    model = TetFEM(X, T, _config())
    nodes = model.rest
    fixed = nodes[:, 0] < 1e-9
    tip = nodes[:, 0] > BEAM_L - 1e-9
    K = model._hessian(nodes, 0.0, torch.from_numpy(model.deformation_gradients(nodes)), False)
    free = np.repeat(~fixed, 3)
    M = sp.diags(np.repeat(model.masses, 3)).tocsr()
    w2 = spla.eigsh(K[free][:, free].tocsc(), k=1, M=M[free][:, free].tocsc(), sigma=0, which="LM")[0]
    period_modal = 2 * math.pi / math.sqrt(w2[0])
    steps = 40
    cfg = _config(dt=period_modal / steps, substeps=1)
    result = simulate_fem(X, T, cfg, None, frames=int(1.6 * steps), fixed=fixed, progress=False)
    static_tip = static_solve(X, T, cfg, fixed).positions.numpy()[tip, 2].mean()
    s = result.trajectory[:, tip, 2].mean(1).numpy() - static_tip
    t = result.times.numpy()
    idx = np.where(np.sign(s[:-1]) != np.sign(s[1:]))[0]
    crossings = np.array([t[i] - s[i] * (t[i + 1] - t[i]) / (s[i + 1] - s[i]) for i in idx])
    assert len(crossings) >= 3
    period = np.diff(crossings[:3]).mean() * 2
    assert abs(period / period_modal - 1) < 0.015, (period, period_modal)


def test_quadratic_embedding_carries_quadratic_fields_exactly():
    X, T = _box(res=(2, 2, 1))
    nodes, elements = quadratic_tet_nodes(X, T)

    def field(p):
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        return np.stack([x + 0.3 * x * y - z * z, y + 0.2 * x * x, z - 0.5 * y * z + 0.1], axis=-1)

    rng = np.random.default_rng(1)
    points = torch.from_numpy(rng.uniform(-0.09, 0.09, size=(200, 3)))
    tet_index, bary = embed_points(points, torch.from_numpy(X), torch.from_numpy(T))
    moved = apply_embedding(torch.from_numpy(field(nodes)), tet_index, bary, torch.from_numpy(elements))
    np.testing.assert_allclose(moved.numpy(), field(points.numpy()), atol=1e-12)
    # the linear tets alone cannot: the midpoints carry the curvature
    linear = apply_embedding(torch.from_numpy(field(nodes)), tet_index, bary, torch.from_numpy(T))
    assert np.abs(linear.numpy() - field(points.numpy())).max() > 1e-4


def test_result_round_trip_keeps_the_elements(tmp_path):
    X, T = _box(res=(1, 1, 1))
    result = simulate_fem(X, T, FEMConfig(substeps=1, element_order=2), InitialPose.random(1), frames=2,
                          progress=False)
    loaded = FEMResult.load(result.save(tmp_path / "fem.npz"))
    assert torch.equal(loaded.elements, result.elements)
    assert torch.equal(loaded.embedding_elements, result.elements)
    assert torch.allclose(loaded.contact_areas(), torch.from_numpy(TetFEM(X, T, result.config).contact_areas))
    with pytest.raises(ValueError, match="element_order"):
        FEMConfig(element_order=3)
