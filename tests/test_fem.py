"""FEM ground truth, validated against independent references:

* scikit-fem's P1 linear elasticity on the identical mesh (static cantilever under gravity),
* Euler–Bernoulli beam theory (static tip deflection, first bending period),
* the mesh's own first eigenperiod from scikit-fem's stiffness matrix (the time integrator),
* the closed-form implicit-Euler and BDF2 free falls, finite differences of the energy (elastic and viscous),
  force balance on the floor,
* Kelvin–Voigt damping: the measured decay of the first bending mode against ζ₁ = τ ω₁ / 2, and no damping
  of a rigid spin.
"""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from vid2sim.meshing.tetra import box_tet_mesh, surface_vertex_areas
from vid2sim.synthetic.fem import (
    FEMConfig,
    FEMResult,
    FEMSolverError,
    InitialPose,
    TetFEM,
    simulate_fem,
    simulate_fem_converged,
    static_solve,
)

skfem = importlib.import_module("skfem")  # a declared test dependency: a broken install fails
from skfem.models.elasticity import lame_parameters as skfem_lame  # noqa: E402
from skfem.models.elasticity import linear_elasticity  # noqa: E402

# Cantilever along x, clamped at x = 0, square cross-section b × b, gravity −z.
BEAM_L, BEAM_B, BEAM_E, BEAM_RHO, G = 1.0, 0.1, 1e8, 1000.0, 9.8


def _beam(resolution):
    mesh = box_tet_mesh((BEAM_L, BEAM_B, BEAM_B), resolution)
    X, T = mesh.vertices.numpy(), mesh.tets.numpy()
    return X, T, X[:, 0] < 1e-9, X[:, 0] > BEAM_L - 1e-9


def _beam_config(nu, **kw):
    return FEMConfig(youngs_modulus=BEAM_E, poisson_ratio=nu, density=BEAM_RHO, floor_height=None, **kw)


def _skfem_basis_and_stiffness(X, T, nu):
    basis = skfem.Basis(skfem.MeshTet(X.T.copy(), T.T.copy()), skfem.ElementVector(skfem.ElementTetP1()))
    K = skfem.asm(linear_elasticity(*skfem_lame(BEAM_E, nu)), basis)
    return basis, K


def _skfem_static_displacement(X, T, fixed, nu):
    """Linear-elastic P1 displacement (Nv, 3) under the body force ρ g, clamped vertices fixed."""
    basis, K = _skfem_basis_and_stiffness(X, T, nu)

    @skfem.LinearForm
    def weight(v, w):
        return -BEAM_RHO * G * v[2]

    f = skfem.asm(weight, basis)
    u = skfem.solve(*skfem.condense(K, f, D=basis.nodal_dofs[:, fixed].ravel()))
    return u[basis.nodal_dofs].T


def test_static_cantilever_matches_scikit_fem_on_identical_mesh():
    X, T, fixed, tip = _beam((20, 3, 3))
    nu = 0.3
    ours = static_solve(X, T, _beam_config(nu, newton_tol=1e-9), fixed).positions.numpy() - X
    ref = _skfem_static_displacement(X, T, fixed, nu)
    tip_ours, tip_ref = -ours[tip, 2].mean(), -ref[tip, 2].mean()
    rel = abs(tip_ours / tip_ref - 1)
    print(f"\n[FEM validation] cantilever tip deflection: ours {tip_ours:.6e} m, scikit-fem {tip_ref:.6e} m, "
          f"rel. error {100 * rel:.3f} %")
    assert tip_ref > 1e-3  # a real load: 0.5 % of the length, small enough for linear theory
    assert rel < 0.02
    # the whole displacement field agrees, not only the tip (Neo-Hookean vs linear: O(deflection/L))
    assert np.abs(ours - ref).max() < 0.02 * np.abs(ref).max()
    assert np.abs(ours[fixed]).max() == 0.0


def test_static_cantilever_matches_euler_bernoulli():
    X, T, fixed, tip = _beam((60, 1, 8))  # slender mesh: 8 layers through the bending direction
    ours = static_solve(X, T, _beam_config(0.0, newton_tol=1e-8), fixed).positions.numpy() - X
    delta = -ours[tip, 2].mean()
    inertia = BEAM_B ** 4 / 12
    q = BEAM_RHO * G * BEAM_B * BEAM_B
    delta_eb = q * BEAM_L ** 4 / (8 * BEAM_E * inertia)
    rel = abs(delta / delta_eb - 1)
    print(f"\n[FEM validation] Euler-Bernoulli tip deflection: ours {delta:.6e} m, theory {delta_eb:.6e} m, "
          f"rel. error {100 * rel:.2f} %")
    assert rel < 0.10
    # the deflected shape follows w(x) = q x² (6L² − 4Lx + x²) / (24 EI) along the beam's bottom edge
    line = (np.abs(X[:, 1]) < 1e-9) & (np.abs(X[:, 2]) < 1e-9)
    xs = X[line, 0]
    w_eb = q * xs ** 2 * (6 * BEAM_L ** 2 - 4 * BEAM_L * xs + xs ** 2) / (24 * BEAM_E * inertia)
    assert np.abs(-ours[line, 2] - w_eb).max() < 0.10 * delta_eb


def _zero_crossings(t, s):
    idx = np.where(np.sign(s[:-1]) != np.sign(s[1:]))[0]
    return np.array([t[i] - s[i] * (t[i + 1] - t[i]) / (s[i + 1] - s[i]) for i in idx])


def _first_bending(resolution=(40, 1, 6), nu=0.0):
    """(X, T, fixed, tip, mesh first eigenperiod from scikit-fem's stiffness with our lumped masses,
    Euler–Bernoulli first period)."""
    X, T, fixed, tip = _beam(resolution)
    inertia = BEAM_B ** 4 / 12
    omega_eb = 1.8751 ** 2 * math.sqrt(BEAM_E * inertia / (BEAM_RHO * BEAM_B ** 2 * BEAM_L ** 4))
    model = TetFEM(X, T, _beam_config(nu))
    basis, K = _skfem_basis_and_stiffness(X, T, nu)
    mass = np.zeros(K.shape[0])
    mass[basis.nodal_dofs.T.ravel()] = np.repeat(model.masses, 3)
    free = np.setdiff1d(np.arange(K.shape[0]), basis.nodal_dofs[:, fixed].ravel())
    w2 = spla.eigsh(K[free][:, free].tocsc(), k=1, M=sp.diags(mass[free]).tocsc(), sigma=0, which="LM")[0]
    return X, T, fixed, tip, 2 * math.pi / math.sqrt(w2[0]), 2 * math.pi / omega_eb


def _tip_oscillation(X, T, fixed, tip, cfg, frames):
    """(times, tip height minus its static value) of the beam released undeformed under gravity."""
    result = simulate_fem(X, T, cfg, None, frames=frames, fixed=fixed, progress=False)
    static_tip = static_solve(X, T, cfg, fixed).positions.numpy()[tip, 2].mean()
    assert bool((result.min_det > 0).all())
    return result.times.numpy(), result.trajectory[:, tip, 2].mean(1).numpy() - static_tip


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_cantilever_first_bending_period(integrator):
    """Release the beam undeformed under gravity: it oscillates about the static deflection in (mostly)
    its first bending mode. The period from zero crossings matches (a) the first eigenperiod of the same
    mesh from scikit-fem's stiffness and our lumped masses (checks the time integrator) and (b)
    Euler–Bernoulli theory. Undamped: only the integrator's own dissipation is left."""
    X, T, fixed, tip, period_modal, period_eb = _first_bending()
    steps_per_period = 25
    cfg = _beam_config(0.0, dt=period_eb / steps_per_period, substeps=1, integrator=integrator, damping_ratio=0.0)
    t, s = _tip_oscillation(X, T, fixed, tip, cfg, int(1.9 * steps_per_period) + 1)
    crossings = _zero_crossings(t, s)
    assert len(crossings) >= 4
    period = np.diff(crossings[:4]).mean() * 2  # crossings of an oscillation are half a period apart
    rel_modal = abs(period / period_modal - 1)
    rel_eb = abs(period / period_eb - 1)
    print(f"\n[FEM validation] {integrator}: first bending period {period:.5f} s, mesh eigenperiod "
          f"{period_modal:.5f} s ({100 * rel_modal:.2f} %), Euler-Bernoulli {period_eb:.5f} s ({100 * rel_eb:.2f} %)")
    swing = -s.min() / s[0]
    if integrator == "implicit_euler":
        # implicit Euler lengthens the period by ≈ (ωh)²/3 = 2.1 % at 25 steps per period, and damps
        # strongly: the swing below equilibrium is clearly smaller than the initial offset above it
        assert rel_modal < 0.04
        assert 0.5 < swing < 0.9
    else:
        # BDF2 is second order with a smaller error constant: ≈ (ωh)²·2/9 ≈ 1.4 % longer, and nearly
        # conservative at this resolution
        assert rel_modal < 0.025
        assert swing > 0.9
    assert rel_eb < 0.10


def test_kelvin_voigt_damping_decays_the_first_mode_at_its_predicted_rate():
    """With Kelvin–Voigt viscosity (viscous Lamé parameters τμ, τλ) the small-strain model is Rayleigh damping
    C = τK: the first bending mode must decay with the damping ratio ζ₁ = τ ω₁ / 2. Measured from the
    logarithmic decrement of the tip's swing with BDF2 at 64 steps per period (numerical damping ≪ ζ₁)."""
    X, T, fixed, tip, period_modal, period_eb = _first_bending()
    omega1 = 2 * math.pi / period_modal
    zeta1 = 0.04
    tau = 2 * zeta1 / omega1
    length = 1.0
    # the damping ratio at ω_ref = √(E/ρ)/L that gives this τ
    zeta_ref = tau * math.sqrt(BEAM_E / BEAM_RHO) / (2 * length)
    steps_per_period = 64
    cfg = _beam_config(0.0, dt=period_modal / steps_per_period, substeps=1, damping_ratio=zeta_ref,
                       damping_length=length)
    assert TetFEM(X, T, cfg).tau == pytest.approx(tau)
    t, s = _tip_oscillation(X, T, fixed, tip, cfg, 4 * steps_per_period + 1)
    # successive extrema (peaks and troughs) about the static deflection, after the higher modes died out
    extrema = [i for i in range(1, len(s) - 1) if (s[i] - s[i - 1]) * (s[i + 1] - s[i]) < 0]
    amplitudes = np.abs(s[extrema])[1:]
    decrement = np.log(amplitudes[:-1] / amplitudes[1:]).mean()  # per half period: π ζ / √(1 − ζ²)
    zeta_measured = decrement / math.sqrt(math.pi ** 2 + decrement ** 2)
    undamped = _tip_oscillation(X, T, fixed, tip, replace_config(cfg, damping_ratio=0.0), 4 * steps_per_period + 1)[1]
    und_ext = [i for i in range(1, len(undamped) - 1)
               if (undamped[i] - undamped[i - 1]) * (undamped[i + 1] - undamped[i]) < 0]
    und_amp = np.abs(undamped[und_ext])[1:]
    zeta_numerical = np.log(und_amp[:-1] / und_amp[1:]).mean() / math.pi
    print(f"\n[FEM validation] Kelvin-Voigt: first-mode damping ratio measured {zeta_measured:.4f}, predicted "
          f"{zeta1:.4f}; BDF2 alone {zeta_numerical:.4f}")
    assert zeta_numerical < 0.1 * zeta1
    assert zeta_measured == pytest.approx(zeta1 + zeta_numerical, rel=0.1)


def replace_config(cfg, **changes):
    from dataclasses import replace

    return replace(cfg, **changes)


def test_rigid_spin_is_not_damped():
    """The viscosity acts on the Green-strain rate, which a rigid motion leaves at zero: a strongly damped,
    stiff box spinning freely keeps its kinetic energy and angular momentum, while the same box set
    vibrating loses most of its energy."""
    V, T = _small_box()
    cfg = FEMConfig(youngs_modulus=1e7, floor_height=None, gravity=(0.0, 0.0, 0.0), damping_ratio=0.5, substeps=8)
    spin = InitialPose(drop_height=0.0, angular_velocity=(0.3, 1.0, 2.0))
    result = simulate_fem(V, T, cfg, spin, frames=21, progress=False)
    kinetic = result.energies["kinetic"].numpy()
    assert abs(kinetic[-1] / kinetic[0] - 1) < 2e-3
    model = TetFEM(V, T, cfg)
    m = torch.from_numpy(model.masses)[:, None]
    momentum = [(m * torch.linalg.cross(x, v, dim=1)).sum(0) for x, v in zip(result.trajectory, result.velocities)]
    assert float((momentum[-1] - momentum[0]).norm()) < 1e-3 * float(momentum[0].norm())
    # a vibration of the same box (a stretch mode as initial velocity) is damped out
    X = model.rest
    stretch = np.zeros_like(X)
    stretch[:, 0] = X[:, 0] - X[:, 0].mean()
    vib = simulate_fem(V, T, cfg, None, frames=21, initial_velocity=stretch, progress=False)
    assert vib.energies["total"][-1] < 0.05 * vib.energies["total"][0]


def _small_box(res=(3, 2, 2), size=(0.3, 0.2, 0.2)):
    mesh = box_tet_mesh(size, res, origin=tuple(-s / 2 for s in size))
    return mesh.vertices, mesh.tets


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_free_fall_matches_the_closed_form(integrator):
    """Before contact every vertex moves rigidly (zero elastic and viscous force, also for a rotated body)
    and follows the integrator's closed form under constant gravity g: implicit Euler
    x_n = x_0 + n h v_0 + h² g n(n+1)/2; BDF2 (first step implicit Euler, then exact for quadratics)
    x_n = x_0 + n h v_0 + h² g n²/2 + (3/4) h² g (1 − 3⁻ⁿ), velocities exact."""
    V, T = _small_box()
    # a tilted, non-default gravity: the closed form must follow the configured vector
    cfg = FEMConfig(floor_height=-100.0, substeps=4, dt=0.05, newton_tol=1e-10, gravity=(0.8, -0.3, -9.0),
                    integrator=integrator)
    pose = InitialPose(drop_height=1.0, rotation=(0.3, -0.2, 0.5), linear_velocity=(0.5, -0.2, 1.0))
    result = simulate_fem(V, T, cfg, pose, frames=6, progress=False)
    x0 = result.trajectory[0].numpy()
    assert x0[:, 2].min() == pytest.approx(-99.0)
    h, g, v0 = cfg.dt / cfg.substeps, np.array(cfg.gravity), np.array(pose.linear_velocity)
    for f in range(6):
        n = f * cfg.substeps
        if integrator == "implicit_euler":
            expected = x0 + n * h * v0 + h * h * g * n * (n + 1) / 2
        else:
            expected = x0 + n * h * v0 + h * h * g * n * n / 2 + 0.75 * h * h * g * (1 - 3.0 ** -n)
        np.testing.assert_allclose(result.trajectory[f].numpy(), expected, atol=1e-8)
        np.testing.assert_allclose(result.velocities[f].numpy(), np.broadcast_to(v0 + n * h * g, x0.shape), atol=1e-6)
    assert result.energies["elastic"].abs().max() < 1e-9


@pytest.mark.parametrize("floor_stiffness", [5e7, 1e7])
def test_dropped_box_comes_to_rest_on_floor(floor_stiffness):
    V, T = _small_box(res=(3, 3, 2), size=(0.3, 0.3, 0.2))
    cfg = FEMConfig(youngs_modulus=1e5, substeps=8, floor_height=-0.7, floor_stiffness=floor_stiffness)
    pose = InitialPose(drop_height=0.1)
    result = simulate_fem(V, T, cfg, pose, frames=30, progress=False)
    traj = result.trajectory.numpy()
    assert np.isfinite(traj).all()
    assert bool((result.min_det > 0).all())
    model = TetFEM(V, T, cfg)
    weight = model.masses.sum() * 9.8
    total = result.energies["total"].numpy()
    assert total[-1] < total[0] - 0.5 * weight * 0.1  # most of the drop's energy is dissipated by the damping
    assert total.max() <= total[0] + 1e-3 * weight * 0.1
    # at rest, lying flat on the floor
    assert result.energies["kinetic"][-1] < 1e-3 * weight * 0.1
    # force balance: the floor's contact pressure 2κ·d over the lumped areas a_i carries the weight, and
    # the penetration is small
    areas = surface_vertex_areas(V, T).numpy()
    np.testing.assert_allclose(areas, model.contact_areas)
    assert areas.sum() == pytest.approx(2 * (0.3 * 0.3 + 2 * 0.3 * 0.2))
    depth = np.maximum(0.0, cfg.floor_height - traj[-1, :, 2])
    assert 2 * cfg.floor_stiffness * (areas * depth).sum() == pytest.approx(weight, rel=0.02)
    bottom_area = 0.3 * 0.3
    assert depth.max() < 5 * weight / (2 * cfg.floor_stiffness * bottom_area)
    # during the impact: at most the whole drop energy stored in the contact pressure of the flat bottom
    assert result.max_penetration < math.sqrt(weight * pose.drop_height / (cfg.floor_stiffness * bottom_area))
    # the elastic box sags under its own weight: its height shrinks a little, by the order ρ g H² / (2E)
    height = traj[-1, :, 2].max() - traj[-1, :, 2].min()
    assert 0 < 0.2 - height < 5 * 1000 * 9.8 * 0.2 ** 2 / (2 * 1e5)


def test_random_pose_drop_is_valid_and_solvers_agree():
    V, T = _small_box()
    pose = InitialPose.random(7)
    results = {}
    for solver in ("cg", "direct"):
        cfg = FEMConfig(youngs_modulus=2e4, substeps=4, linear_solver=solver)
        results[solver] = simulate_fem(V, T, cfg, pose, frames=9, progress=False)
    r = results["cg"]
    assert r.trajectory.shape == (9, V.shape[0], 3)
    assert bool(torch.isfinite(r.trajectory).all()) and bool((r.min_det > 0).all())
    assert r.trajectory[:, :, 2].min() < -0.69  # it reached the floor
    total = r.energies["total"].numpy()
    assert total[-1] < total[0]
    assert torch.allclose(results["cg"].trajectory, results["direct"].trajectory, atol=1e-5)
    # the direct solver kept its factorisation for most steps (chord Newton), and got the same answer
    assert int(results["direct"].newton_iterations.sum()) > 0


def test_violent_impact_never_inverts():
    """A soft body thrown into the floor at 8 m/s with one big step per frame: full Newton steps would
    invert tets; the line search rejects them and the converged states have all tets positive."""
    V, T = _small_box()
    cfg = FEMConfig(youngs_modulus=5e3, substeps=1, newton_max_iters=300)
    pose = InitialPose(drop_height=0.0, linear_velocity=(0.0, 0.0, -8.0), angular_velocity=(3.0, 0.0, 0.0))
    result = simulate_fem(V, T, cfg, pose, frames=3, progress=False)
    assert int(result.inverted_rejections.sum()) > 0  # the guard was exercised
    assert bool((result.min_det > 0).all())
    assert float(result.min_det.min()) < 0.5  # strongly compressed
    assert bool(torch.isfinite(result.trajectory).all())
    # with too few Newton iterations the same step fails cleanly, naming the frame
    with pytest.raises(FEMSolverError, match="frame 1, substep 1/1.*did not converge"):
        simulate_fem(V, T, FEMConfig(youngs_modulus=5e3, substeps=1, newton_max_iters=5), pose, frames=2,
                     progress=False)


def _grad(model, x, x_tilde, inertia, viscous=None):
    return model._evaluate(x, x_tilde, inertia, model.rest, viscous)[1]


def _hess(model, x, inertia, project, viscous=None):
    F = torch.from_numpy(model.deformation_gradients(x))
    return model._hessian(x, inertia, F, project, viscous)


@pytest.mark.parametrize("damped", [False, True])
def test_gradient_and_hessian_match_finite_differences(damped):
    V, T = _small_box(res=(2, 1, 1))
    cfg = FEMConfig(youngs_modulus=1e4, poisson_ratio=0.35, floor_height=-0.08, damping_ratio=0.3)
    model = TetFEM(V, T, cfg)
    rng = np.random.default_rng(0)
    X = model.rest
    # a uniformly dilated state (all tangents positive definite, so the PSD projection leaves them
    # unchanged), partly below the floor, with an inertia term and (damped) the BDF2 viscous term
    x = 1.05 * X + 0.002 * rng.normal(size=X.shape)
    x_tilde = X + 0.01 * rng.normal(size=X.shape)
    inertia = 400.0
    viscous = None
    if damped:
        x_prev, x_prev2 = 1.02 * X, 1.01 * X + 0.001 * rng.normal(size=X.shape)
        viscous = model.viscous_term((1.5, 2.0, -0.5), 0.01, model.deformation_gradients(x_prev),
                                     model.deformation_gradients(x_prev2))
    assert (x[:, 2] < cfg.floor_height).any()
    g = _grad(model, x, x_tilde, inertia, viscous)
    H = _hess(model, x, inertia, False, viscous)
    phi = lambda y: model._evaluate(y, x_tilde, inertia, X, viscous)[0]  # noqa: E731
    eps = 1e-6
    fd = np.zeros(x.size)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = eps
        fd[i] = (phi(x + e.reshape(x.shape)) - phi(x - e.reshape(x.shape))) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    d = rng.normal(size=x.size)
    g_plus = _grad(model, x + eps * d.reshape(x.shape), x_tilde, inertia, viscous)
    g_minus = _grad(model, x - eps * d.reshape(x.shape), x_tilde, inertia, viscous)
    np.testing.assert_allclose(H @ d, (g_plus - g_minus) / (2 * eps), rtol=1e-5, atol=1e-6 * np.abs(H @ d).max())
    # the Hessian is symmetric positive definite, and projecting it changes nothing here
    Hd = H.toarray()
    assert np.abs(Hd - Hd.T).max() < 1e-9 * np.abs(Hd).max()
    assert np.linalg.eigvalsh(Hd).min() > 0
    H_projected = _hess(model, x, inertia, True, viscous).toarray()
    np.testing.assert_allclose(H_projected, Hd, rtol=0, atol=1e-9 * np.abs(Hd).max())


def test_exact_hessian_matches_finite_differences_under_compression():
    """The exact (unprojected) Hessian is the derivative of the gradient also where it is indefinite."""
    V, T = _small_box(res=(2, 1, 1))
    model = TetFEM(V, T, FEMConfig(floor_height=None))
    rng = np.random.default_rng(1)
    x = model.rest * np.array([0.5, 0.6, 1.0]) + 0.002 * rng.normal(size=model.rest.shape)
    H = _hess(model, x, 0.0, False)
    assert np.linalg.eigvalsh(H.toarray()).min() < 0  # compressed Neo-Hookean: indefinite
    eps = 1e-6
    for _ in range(3):
        d = rng.normal(size=x.size)
        g_plus = _grad(model, x + eps * d.reshape(x.shape), x, 0.0)
        g_minus = _grad(model, x - eps * d.reshape(x.shape), x, 0.0)
        np.testing.assert_allclose(H @ d, (g_plus - g_minus) / (2 * eps), rtol=1e-5,
                                   atol=1e-6 * np.abs(H @ d).max())


def test_psd_projection_under_compression():
    """Under strong compression the Neo-Hookean tangent is indefinite; the assembled Hessian is still PSD."""
    V, T = _small_box(res=(2, 1, 1))
    model = TetFEM(V, T, FEMConfig(floor_height=None))
    x = model.rest * np.array([0.5, 0.6, 1.0])
    H_exact = _hess(model, x, 0.0, False)
    assert np.linalg.eigvalsh(H_exact.toarray()).min() < 0
    H = _hess(model, x, 0.0, True)
    ev = np.linalg.eigvalsh(H.toarray())
    assert ev.min() > -1e-8 * ev.max()


def test_exact_hessian_newton_matches_projected_and_converges_faster():
    """The impact of a soft box: Newton on the exact Hessian (projected only where it is indefinite)
    reaches the same states as Newton on the always-projected Hessian, which slows to linear
    convergence while tets are compressed into Neo-Hookean's indefinite range."""
    V, T = _small_box()
    pose = InitialPose(drop_height=0.0, linear_velocity=(0.0, 0.0, -8.0), angular_velocity=(3.0, 0.0, 0.0))
    results = {mode: simulate_fem(V, T, FEMConfig(youngs_modulus=5e3, substeps=1, newton_max_iters=300,
                                                  hessian_projection=mode, reuse_factorization=False), pose,
                                  frames=3, progress=False)
               for mode in ("always", "on_demand")}
    exact, projected = results["on_demand"], results["always"]
    assert float(exact.min_det.min()) < 0.5  # strongly compressed
    assert torch.allclose(exact.trajectory, projected.trajectory, atol=2e-5)
    assert int(exact.newton_iterations.max()) * 3 < int(projected.newton_iterations.max())


@pytest.mark.parametrize("solver", ["direct", "cg"])
def test_newton_from_a_compressed_state_converges_with_either_solver(solver):
    """From a box squeezed to half its width with weak inertia the exact Hessian is indefinite: the
    direct solver sees it in its pivots and projects; CG still returns descent directions. Both converge
    to the state the always-projected Newton finds, a stationary point of the incremental potential."""
    V, T = _small_box()
    model = TetFEM(V, T, FEMConfig(floor_height=None, linear_solver=solver))
    x = model.rest * np.array([0.5, 0.5, 1.0])
    v = np.zeros_like(x)
    h = 0.05
    x_new, _, stats = model.step(x, v, h)
    assert stats.converged
    if solver == "direct":
        assert stats.projected_solves > 0
    reference = TetFEM(V, T, FEMConfig(floor_height=None, linear_solver=solver, hessian_projection="always"))
    x_ref, _, ref_stats = reference.step(x, v, h)
    assert ref_stats.projected_solves == 0
    np.testing.assert_allclose(x_new, x_ref, atol=1e-5)
    viscous = model.viscous_term((1.0, 1.0, 0.0), h, model.deformation_gradients(x), None)
    g = model._evaluate(x_new, x + h * v, 1.0 / h**2, model.rest, viscous)[1]
    weight = float(model.masses.sum()) * 9.8
    assert np.abs(g).max() < 1e-4 * weight



def test_a_kept_factorisation_whose_full_step_fails_is_refactorised_not_searched_along():
    """A kept factorisation made at another state (here: one whose steps are 100× too long, as a factorisation
    made with another floor-contact set can be for the vertices that crossed the floor) is not line-searched
    along: its rejected full step makes Newton refactorise at the current state. Halving along such steps
    cycled forever with the fresh step of the other contact set in a quadratic-tet drop (Newton stagnated
    at 1.5× its tolerance). The result is the plain-Newton state."""
    from vid2sim.synthetic.fem import FactorCache

    V, T = _small_box()
    model = TetFEM(V, T, FEMConfig(youngs_modulus=1e4, floor_height=-0.09))
    x = model.rest.copy()
    v = np.zeros_like(x)
    v[:, 2] = -1.0
    h = 0.01
    x_plain, _, plain = model.step(x, v, h)  # no kept factorisation: factorises at every iteration
    assert plain.converged and plain.factorizations == plain.iterations
    H = model._hessian(x, 1.0 / h**2, torch.from_numpy(model.deformation_gradients(x)), True) * 0.01
    bad = FactorCache()
    bad.set(H, model._factorize(H, plain.__class__(), exact=False), model._centred(x, None))
    x_kept, _, kept = model.step(x, v, h, factor=bad)
    assert kept.converged
    assert kept.line_search_halvings == 0  # the bad factor's step was rejected, not halved
    assert kept.factorizations >= 1 and kept.iterations > kept.factorizations  # then the fresh one was kept
    np.testing.assert_allclose(x_kept, x_plain, atol=model.config.newton_tol * model.bbox_diagonal)  # both converged

def test_initial_pose_apply_and_random():
    V, T = _small_box()
    masses = torch.from_numpy(TetFEM(V, T, FEMConfig()).masses)
    pose = InitialPose(drop_height=0.25, rotation=(0.0, 0.0, math.pi / 2), linear_velocity=(1.0, 0.0, 0.0),
                       angular_velocity=(0.0, 0.0, 2.0))
    x, v = pose.apply(V, masses, floor_height=-0.7)
    assert float(x[:, 2].min()) == pytest.approx(-0.45)
    c = (masses[:, None] * x).sum(0) / masses.sum()
    np.testing.assert_allclose(c[:2].numpy(), [0.0, 0.0], atol=1e-12)
    # a quarter turn about z swaps the box's x and y extents
    np.testing.assert_allclose((x.max(0).values - x.min(0).values).numpy(), [0.2, 0.3, 0.2], atol=1e-12)
    expected_v = torch.tensor([1.0, 0.0, 0.0], dtype=x.dtype) + torch.linalg.cross(
        torch.tensor([0.0, 0.0, 2.0], dtype=x.dtype).expand_as(x), x - c)
    assert torch.allclose(v, expected_v)
    a, b, c2 = InitialPose.random(3), InitialPose.random(3), InitialPose.random(4)
    assert a == b and a != c2
    R = np.array(a.rotation)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert 0.05 <= a.drop_height <= 0.3 and a.linear_velocity[2] <= 0
    with pytest.raises(ValueError, match="rotation"):
        InitialPose(rotation=((1, 0, 0), (0, 1, 0), (0, 0, -1)))
    with pytest.raises(ValueError, match="drop_height"):
        InitialPose(drop_height=-1.0)
    with pytest.raises(ValueError, match="angular_velocity"):
        InitialPose(angular_velocity=(1.0, 2.0))


def test_config_and_input_errors():
    with pytest.raises(ValueError, match="substeps"):
        FEMConfig(substeps=0)
    with pytest.raises(ValueError, match="Poisson"):
        FEMConfig(poisson_ratio=0.5)
    with pytest.raises(ValueError, match="linear_solver"):
        FEMConfig(linear_solver="magic")
    with pytest.raises(ValueError, match="hessian_projection"):
        FEMConfig(hessian_projection="sometimes")
    with pytest.raises(ValueError, match="floor_stiffness"):
        FEMConfig(floor_stiffness=-1.0)
    with pytest.raises(ValueError, match="integrator"):
        FEMConfig(integrator="rk4")
    with pytest.raises(ValueError, match="damping_ratio"):
        FEMConfig(damping_ratio=-0.1)
    with pytest.raises(ValueError, match="damping_length"):
        FEMConfig(damping_length=0.0)
    V, T = _small_box()
    with pytest.raises(ValueError, match="rest volume"):
        TetFEM(V, T[:, [0, 2, 1, 3]], FEMConfig())
    with pytest.raises(ValueError, match="tet indices"):
        TetFEM(V, T + 1000, FEMConfig())
    with pytest.raises(ValueError, match="fixed"):
        simulate_fem(V, T, FEMConfig(), frames=2, fixed=np.zeros(3, dtype=bool), progress=False)
    with pytest.raises(ValueError, match="fixed vertex"):
        static_solve(V, T, FEMConfig(), fixed=np.zeros(V.shape[0], dtype=bool))
    with pytest.raises(ValueError, match="frames"):
        simulate_fem(V, T, FEMConfig(), frames=0, progress=False)
    model = TetFEM(V, T, FEMConfig())
    inverted = model.rest.copy()
    inverted[:, 0] *= -1
    with pytest.raises(FEMSolverError, match="inverted"):
        model.minimize(inverted)


def test_result_save_load_roundtrip(tmp_path):
    V, T = _small_box(res=(1, 1, 1))
    result = simulate_fem(V, T, FEMConfig(substeps=1), InitialPose.random(1), frames=3, progress=False)
    path = result.save(tmp_path / "fem.npz")
    loaded = FEMResult.load(path)
    assert loaded.config == result.config and loaded.pose == result.pose
    for name in ("rest_vertices", "tets", "trajectory", "velocities", "times", "min_det", "newton_iterations",
                 "line_search_halvings", "inverted_rejections", "fixed"):
        assert torch.equal(getattr(loaded, name), getattr(result, name)), name
    assert set(loaded.energies) == {"kinetic", "elastic", "gravity", "floor", "total"}
    assert loaded.time_convergence is None
    with pytest.raises(FileNotFoundError, match="does not exist"):
        FEMResult.load(tmp_path / "missing.npz")


def test_converged_drop_is_second_order_and_records_its_convergence(tmp_path):
    """simulate_fem_converged doubles the substeps until 2× refinement moves the trajectory by at most the
    tolerance, keeps the finer run and records the comparison; BDF2 converges at second order (a halving
    of h cuts the change about 4×, until it approaches the ~0.05 % at which finer steps start to resolve
    the penalty contact's vertex chatter); a tolerance out of reach fails with a clear error."""
    V, T = _small_box()
    cfg = FEMConfig(youngs_modulus=3e4, poisson_ratio=0.4)
    pose = InitialPose.random(5)
    result = simulate_fem_converged(V, T, cfg, pose, frames=10, tolerance=0.2, start_substeps=2, progress=False)
    info = result.time_convergence
    n, fine = info["substeps"]
    assert fine == 2 * n == info["kept"] == result.config.substeps
    assert info["mean_percent"] <= 0.2
    changes = [c["mean_percent"] for c in info["comparisons"]]
    assert len(changes) >= 3 and changes[:-1] == sorted(changes[:-1], reverse=True)
    assert all(c > 0.2 for c in changes[:-1])
    assert 3.0 < changes[-2] / changes[-1] < 6.0  # second order
    direct = simulate_fem(V, T, replace_config(cfg, substeps=fine), pose, frames=10, progress=False)
    assert torch.equal(direct.trajectory, result.trajectory)
    loaded = FEMResult.load(result.save(tmp_path / "conv.npz"))
    assert loaded.time_convergence == info
    with pytest.raises(FEMSolverError, match="not converged in time"):
        simulate_fem_converged(V, T, cfg, pose, frames=10, tolerance=1e-3, start_substeps=2, max_substeps=8,
                               progress=False)
