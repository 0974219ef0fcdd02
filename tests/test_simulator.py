"""Physics tests of the reduced implicit-Euler simulator and its adjoint."""

from __future__ import annotations

import math

import pytest
import torch

from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.external import Floor, Gravity, SphereObstacle
from vid2sim.physics.materials import energy_and_pk1, neo_hookean_indefinite
from vid2sim.physics.reduced import y_to_z_index, z_to_y_index
from vid2sim.physics.skinning import SkinningField, dF_dz, gradient_basis
from vid2sim.physics.solver import (
    Material,
    SimConfig,
    SimState,
    SimulationError,
    Simulator,
)

G = 9.8


def _sim(field, pts, material=None, externals=None, k=120, config=None, dtype=torch.float64):
    idx, w = sample_cubature(pts, k, volume=1.0, seed=0)
    field = field.to(dtype)
    return Simulator(field, pts[idx].to(dtype), w.to(dtype), material or Material(1e5, 0.3),
                     [Gravity(), Floor(height=-0.5)] if externals is None else externals,
                     config or SimConfig())


def _extent_z(sim, pts, z) -> float:
    x = sim.positions(pts, z).detach()
    return float(x[:, 2].max() - x[:, 2].min())


def test_layout_permutations_are_inverse():
    perm, inv = z_to_y_index(3), y_to_z_index(3)
    z = torch.arange(36.0)
    assert torch.equal(z[perm][inv], z)
    # y row a holds row a of every handle: y[a*L + 4j + k] = Z_j[a, k]
    Z = z.reshape(3, 3, 4)
    assert torch.equal(z[perm].reshape(3, 3, 4), Z.permute(1, 0, 2))


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2"])
def test_free_fall_matches_the_integrators_closed_form(trained_field, integrator):
    """Free fall is a rigid motion (no elastic or viscous force, with the default damping on) that follows
    the integrator's closed form: implicit Euler x_n = −g h² n(n+1)/2; BDF2 (first step implicit Euler,
    then exact for quadratics) x_n = −g h² n²/2 − (3/4) g h² (1 − 3⁻ⁿ), n substeps of h."""
    field, pts = trained_field
    sim = _sim(field, pts, externals=[Gravity()], config=SimConfig(substeps=3, integrator=integrator))
    assert float(sim.damping_ratio) > 0
    states = sim.rollout(sim.rest_state(), 6)
    h = sim.config.dt / 3
    for f, st in enumerate(states, start=1):
        n = 3 * f
        if integrator == "implicit_euler":
            expected = -G * h**2 * n * (n + 1) / 2
        else:
            expected = -G * h**2 * n * n / 2 - 0.75 * G * h**2 * (1 - 3.0**-n)
        x = sim.positions(pts[:200], st.z) - pts[:200]
        assert torch.allclose(x[:, 2], torch.full_like(x[:, 2], expected), atol=1e-8)
        assert float(x[:, :2].abs().max()) < 1e-8
        F = sim.deformation_gradients(pts[:200], st.z)
        assert float((F - torch.eye(3, dtype=F.dtype)).abs().max()) < 1e-7  # no deformation in free fall
        assert st.converged


def test_automatic_substeps_follow_the_material_time_scale(trained_field):
    from vid2sim.physics.integrators import auto_substeps

    assert [auto_substeps(0.05, E, 1000.0, 1.0) for E in (1e4, 1e5, 1e6, 1e8)] == [4, 8, 26, 64]
    field, pts = trained_field
    sim = _sim(field, pts, material=Material(1e6, 0.3))
    assert sim.config.substeps is None
    assert sim.substeps() == auto_substeps(0.05, 1e6, 1000.0, sim.length_scale)
    with torch.no_grad():
        sim.log10_E.fill_(4.0)
    assert sim.substeps() == 4
    assert _sim(field, pts, config=SimConfig(substeps=7)).substeps() == 7
    with pytest.raises(ValueError, match="substeps"):
        SimConfig(substeps=0)


def test_bdf2_converges_at_second_order_and_beats_implicit_euler(trained_field):
    """A damped, tumbling drop onto the floor: halving the substep divides BDF2's trajectory change by
    about 4 (implicit Euler: 2), and BDF2 at 4 substeps is closer to the refined answer than implicit
    Euler at 16."""
    from vid2sim.metrics import trajectory_distance

    field, pts = trained_field
    P = pts[::5]
    size = float((pts.max(0).values - pts.min(0).values).norm())

    def run(n, integrator="bdf2"):
        sim = _sim(field, pts, material=Material(5e4, 0.35),
                   config=SimConfig(substeps=n, integrator=integrator, newton_tol=1e-10))
        start = sim.rigid_velocity_state([0.3, 0.0, -1.5], [2.0, 1.0, 0.0])
        with torch.no_grad():
            states = sim.rollout(start, 12)
        return torch.stack([sim.positions(P, start.z)] + [sim.positions(P, s.z) for s in states])

    bdf = {n: run(n) for n in (4, 8, 16, 64)}
    ie = {n: run(n, "implicit_euler") for n in (8, 16)}
    ref = bdf[64]
    err = {n: trajectory_distance(bdf[n], ref, size).mean for n in (4, 8, 16)}
    assert 3.0 < err[4] / err[8] < 6.0 and 3.0 < err[8] / err[16] < 6.0
    ie_err = {n: trajectory_distance(ie[n], ref, size).mean for n in (8, 16)}
    assert 1.5 < ie_err[8] / ie_err[16] < 2.6
    assert err[4] < ie_err[16]


def test_reused_hessian_reaches_the_same_states_with_fewer_factorisations(trained_field):
    """Chord Newton (the kept Hessian, turned with the object) converges to the same minimiser as plain
    Newton on a tumbling impact, with far fewer Hessian factorisations."""
    import vid2sim.physics.solver as solver

    field, pts = trained_field
    counts = {}
    original = solver.newton_solve

    def counting(*args, **kwargs):
        y, stats = original(*args, **kwargs)
        counts[mode] = counts.get(mode, 0) + stats.hessians
        return y, stats

    runs = {}
    solver.newton_solve = counting
    try:
        for mode in (True, False):
            sim = _sim(field, pts, material=Material(3e4, 0.4),
                       config=SimConfig(substeps=8, reuse_hessian=mode, newton_tol=1e-10, newton_rtol=1e-9))
            with torch.no_grad():
                states = sim.rollout(sim.rigid_velocity_state([0.5, 0.0, -2.0], [0.0, 4.0, 1.0]), 10)
            runs[mode] = torch.stack([s.z for s in states])
    finally:
        solver.newton_solve = original
    assert torch.allclose(runs[True], runs[False], atol=1e-8)
    assert counts[True] * 3 < counts[False]


def test_contact_points_default_to_the_cubature_points_with_unit_weights(trained_field):
    field, pts = trained_field
    base = _sim(field, pts)
    explicit = _sim(field, pts)
    explicit.contact_points = base.X.clone()
    explicit.contact_weights = torch.ones(base.X.shape[0], dtype=torch.float64)
    a = base.rollout(base.rest_state(), 10)[-1].z
    b = explicit.rollout(explicit.rest_state(), 10)[-1].z
    assert torch.allclose(a, b, atol=1e-10)
    with pytest.raises(ValueError, match="contact_weights"):
        Simulator(field, base.X, base.vol, Material(), contact_points=base.X, contact_weights=-base.vol)


def test_rigid_spin_is_not_damped_and_a_vibration_decays_at_the_predicted_rate(trained_field):
    """Kelvin–Voigt damping acts on the strain rate: a heavily damped object spinning freely keeps its
    kinetic energy; its lowest elastic mode (from the reduced stiffness and mass matrices) decays with the
    damping ratio ζ₁ = τ ω₁ / 2 (small amplitude: the reduced model is Rayleigh damping C = τK)."""
    from scipy.linalg import eigh

    from vid2sim.physics.integrators import BDFStep
    from vid2sim.physics.solver import _StepSpec

    field, pts = trained_field
    # stiff, so that the centrifugal stretch (ρ ω² L² / E ~ 1e-4) stores no energy worth mentioning
    stiff = _sim(field, pts, material=Material(1e7, 0.3, damping_ratio=0.5), externals=[],
                 config=SimConfig(substeps=8))
    spin = stiff.rigid_velocity_state([0.0, 0.0, 0.0], [0.4, 1.0, 1.5])
    with torch.no_grad():
        states = stiff.rollout(spin, 20)

    def kinetic(state):  # ½ Σ m_p |v_p|² over the simulated (cubature) masses; velocities are linear in zdot
        v = stiff.positions(stiff.X, state.zdot) - stiff.X
        return 0.5 * float((stiff.masses()[:, None] * v * v).sum())

    assert abs(kinetic(states[-1]) / kinetic(spin) - 1) < 2e-3
    sim = _sim(field, pts, material=Material(2e4, 0.3, damping_ratio=0.02), externals=[],
               config=SimConfig(substeps=8))
    # the lowest elastic mode of the reduced model
    basis = sim.reduced_basis()
    mu, lam = sim.lame()
    K = sim.X.shape[0]
    A = torch.eye(3, dtype=torch.float64).expand(K, 3, 3)
    spec = _StepSpec(sim.X, sim.vol, A, True, "neo_hookean", [], 1.0, BDFStep(1.0, 1.0, 0.0, 1.0), sim.config)
    y0 = torch.zeros(sim.num_dofs, dtype=torch.float64)
    prob = spec.problem(y0, y0, None, None, mu, lam, None, sim.masses(), basis.b, basis.basis, None)
    M = prob.mass_matrix
    Kr = prob.hessian(y0, project=False) - M  # h = 1: the stiffness
    w2, modes = eigh(Kr.numpy(), M.numpy())
    first = int((w2 > 1e-6 * w2.max()).argmax())
    omega = math.sqrt(w2[first])
    tau = float(sim.retardation_time())
    zeta = tau * omega / 2
    assert 0.02 < zeta < 0.3
    # release the mode with a small velocity and measure its decay over one period
    mode = torch.from_numpy(modes[:, first])
    period = 2 * math.pi / omega
    sim.config = SimConfig(dt=period / 16, substeps=4, newton_tol=1e-12)
    start = SimState(torch.zeros(sim.num_dofs, dtype=torch.float64), 1e-3 * mode[sim._inv])
    with torch.no_grad():
        states = sim.rollout(start, 48)
    amplitude = torch.stack([s.z[sim._perm] @ (M @ mode) for s in states]).numpy()
    peaks = [abs(amplitude[i]) for i in range(1, len(amplitude) - 1)
             if abs(amplitude[i]) >= abs(amplitude[i - 1]) and abs(amplitude[i]) >= abs(amplitude[i + 1])]
    decrement = math.log(peaks[0] / peaks[2])  # over one period (peaks of |a| are half a period apart)
    measured = decrement / math.sqrt(4 * math.pi**2 + decrement**2)
    assert measured == pytest.approx(zeta, rel=0.1)


def test_dropped_elastic_object_comes_to_rest_on_floor(trained_field):
    field, pts = trained_field
    sim = _sim(field, pts, material=Material(1e5, 0.3, damping_ratio=0.1))
    states = sim.rollout(sim.rest_state(), 60)
    zs = torch.stack([s.z for s in states])
    assert bool(torch.isfinite(zs).all())
    x = sim.positions(pts, states[-1].z)
    size = float((pts.max(0).values - pts.min(0).values).norm())
    penetration = max(0.0, -0.5 - float(x[:, 2].min()))
    # the paper's floor acts on the ~10 cubature points near the bottom: m g / (2 k n) ≈ 1 cm at rest
    assert penetration < 0.015 * size
    assert float(x[:, 2].min()) < -0.5 + 0.02 * size  # it is on the floor, not hovering
    # at rest: the last steps barely move the centre of mass
    com_v = (sim.positions(pts, states[-1].z) - sim.positions(pts, states[-2].z)).mean(0) / sim.config.dt
    assert float(com_v.norm()) < 0.05


def test_projected_and_on_demand_newton_reach_the_same_steps(trained_field):
    """Both Hessian strategies minimise the same incremental potential: tight tolerances, same answer;
    the exact Hessian (positive definite here thanks to the inertia term) converges quadratically, the
    projected one only linearly, so on demand takes fewer iterations."""
    field, pts = trained_field
    runs, iterations = {}, {}
    for mode in ("always", "on_demand"):  # one step per frame: large steps, strong compression at impact
        cfg = SimConfig(substeps=1, newton_tol=1e-12, newton_rtol=1e-10, newton_max_iters=60,
                        hessian_projection=mode, reuse_hessian=False)
        sim = _sim(field, pts, material=Material(3e4, 0.4), config=cfg)
        states = sim.rollout(sim.rest_state(), 12)
        assert all(s.converged for s in states)
        runs[mode] = torch.stack([s.z for s in states])
        iterations[mode] = sum(s.newton_iterations for s in states)
    assert torch.allclose(runs["always"], runs["on_demand"], atol=1e-8)
    assert iterations["on_demand"] < iterations["always"]
    # the impact compresses points, so the projection really changes tangents on this run
    mu, lam = sim.lame()
    compressed = [neo_hookean_indefinite(sim.deformation_gradients_at_cubature(z), mu, lam).twist_index.numel()
                  for z in runs["always"]]
    assert max(compressed) > 0
    with pytest.raises(ValueError, match="hessian_projection"):
        SimConfig(hessian_projection="sometimes")


def test_stiffer_material_deforms_less_at_impact(trained_field):
    field, pts = trained_field
    strains = []
    for E in (2e4, 2e5, 2e6):
        sim = _sim(field, pts, material=Material(E, 0.3))
        states = sim.rollout(sim.rest_state(), 14)
        rest_h = _extent_z(sim, pts, torch.zeros_like(states[0].z))
        strains.append(max(abs(_extent_z(sim, pts, s.z) - rest_h) / rest_h for s in states))
    assert strains[0] > strains[1] > strains[2]
    assert strains[0] > 2 * strains[2]


def test_plasticine_keeps_permanent_deformation_elastic_recovers(trained_field):
    from vid2sim.physics.plasticity import VonMises

    field, pts = trained_field
    finals = {}
    for name, mat in {
        "elastic": Material(1e5, 0.3, model="stvk"),
        "plastic": Material(1e5, 0.3, model="stvk", plasticity=VonMises(yield_stress=1000.0)),
    }.items():
        sim = _sim(field, pts, material=mat)
        state = sim.rigid_velocity_state([0.0, 0.0, -2.0])
        states = sim.rollout(state, 40)
        assert all(bool(torch.isfinite(s.z).all()) for s in states)
        rest_h = _extent_z(sim, pts, torch.zeros_like(states[0].z))
        finals[name] = _extent_z(sim, pts, states[-1].z) / rest_h
        if name == "plastic":
            assert states[-1].Fp_inv is not None
            assert float((states[-1].Fp_inv - torch.eye(3, dtype=pts.dtype)).abs().max()) > 1e-3
    # the elastic object recovers its height up to the small static sag; the plastic one stays squashed
    assert abs(finals["elastic"] - 1.0) < 0.04
    assert finals["plastic"] < finals["elastic"] - 0.15



def test_a_point_crushed_flat_in_the_plastic_update_stops_the_simulation(trained_field, monkeypatch):
    """A point whose elastic det F comes out of the step at -7e-14 (found by `bench fuzz`, seed 119: a soft
    plasticine object spun onto the floor) is a failed simulation (SimulationError naming the point and time), not
    a ValueError from inside the return map."""
    from vid2sim.physics.plasticity import VonMises

    field, pts = trained_field
    sim = _sim(field, pts, material=Material(2e3, 0.49, model="stvk", plasticity=VonMises(yield_stress=66.0)))
    n = sim.X.shape[0]
    flat = torch.diag(torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)).repeat(n, 1, 1)
    flat[3, 2, 2] = -7e-14
    monkeypatch.setattr(sim, "deformation_gradients_at_cubature", lambda z: flat)
    mu, lam = sim.lame()
    eye = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    with pytest.raises(SimulationError, match=r"cubature point 3 is crushed flat at t = 0\.25 s"):
        sim._update_plastic(eye, torch.zeros(sim.num_dofs, dtype=torch.float64), mu, lam, 0.25)

def _window_loss(sim, pts, steps=5):
    state = sim.rigid_velocity_state([0.2, 0.0, -2.0], [0.0, 6.0, 2.0])
    states = sim.rollout(state, steps)
    x = sim.positions(pts[::10], states[-1].z)
    weights = torch.linspace(-1.0, 1.0, x.numel(), dtype=x.dtype).reshape(x.shape)
    return (x * weights).sum()


TIGHT = dict(newton_tol=1e-13, newton_rtol=1e-12, newton_max_iters=60)


def test_adjoint_gradients_match_finite_differences(trained_field):
    """Adjoint vs central differences on a smooth problem (a spinning, deforming, damped object in free
    fall, BDF2 with 3 substeps per frame): gradients to log10 E, ν, density, the damping ratio and a
    skinning weight, relative error < 1e-3.

    Contact makes the loss only piecewise smooth, which spoils finite differences; contact is covered by
    the comparison with unrolled autograd below.
    """
    field, pts = trained_field
    field = SkinningField(num_handles=4, seed=0).double()
    field.load_state_dict(trained_field[0].state_dict())
    sim = _sim(field, pts, material=Material(3e4, 0.35, damping_ratio=0.2), externals=[Gravity()],
               config=SimConfig(substeps=3, **TIGHT))
    names = ("log10_E", "nu", "density", "damping_ratio")
    for name in names:
        getattr(sim, name).requires_grad_(True)
    W = list(field.parameters())[-2]
    loss = _window_loss(sim, pts)
    grads = torch.autograd.grad(loss, [getattr(sim, name) for name in names] + [W])

    def loss_at(**kw) -> float:
        with torch.no_grad():
            saved = {k: getattr(sim, k).detach().clone() for k in names}
            for k, v in kw.items():
                setattr(sim, k, v)
            value = float(_window_loss(sim, pts))
            for k, v in saved.items():
                setattr(sim, k, v)
        return value

    for i, (name, h) in enumerate(zip(names, (1e-3, 1e-3, 1.0, 1e-3))):
        base = getattr(sim, name).detach()
        fd = (loss_at(**{name: base + h}) - loss_at(**{name: base - h})) / (2 * h)
        assert abs(float(grads[i]) - fd) <= 1e-3 * abs(fd), (name, float(grads[i]), fd)
    for a, b in ((0, 3), (2, 17)):
        h = 1e-4  # the central difference's own error is ~1e-3 relative at h = 1e-3 (it falls as h²)
        old = float(W[a, b].detach())
        with torch.no_grad():
            W[a, b] = old + h
            lp = loss_at()
            W[a, b] = old - h
            lm = loss_at()
            W[a, b] = old
        fd = (lp - lm) / (2 * h)
        assert abs(float(grads[4][a, b]) - fd) <= 1e-3 * abs(fd), (a, b, float(grads[4][a, b]), fd)


def test_adjoint_gradients_wrt_the_initial_state_match_finite_differences(trained_field):
    """Through BDF2 substeps, including the history state (z, ż one substep back) a resumed rollout
    starts from."""
    field, pts = trained_field
    sim = _sim(field, pts, material=Material(3e4, 0.35), externals=[Gravity()], config=SimConfig(substeps=3, **TIGHT))
    start = sim.rollout(sim.rigid_velocity_state([0.2, 0.0, -2.0], [0.0, 6.0, 2.0]), 1)[-1]
    target_w = torch.linspace(-1.0, 1.0, 3 * pts[::10].shape[0], dtype=torch.float64).reshape(-1, 3)
    keys = ("z", "zdot", "z_prev")

    def loss_of(values: dict) -> torch.Tensor:
        state = SimState(values["z"], values["zdot"], start.t, None, z_prev=values["z_prev"],
                         zdot_prev=start.zdot_prev, h_prev=start.h_prev)
        states = sim.rollout(state, 3)
        return (sim.positions(pts[::10], states[-1].z) * target_w).sum()

    base = {k: getattr(start, k).detach().clone() for k in keys}
    leaves = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    grads = dict(zip(keys, torch.autograd.grad(loss_of(leaves), [leaves[k] for k in keys])))
    h = 1e-5
    for which in keys:
        for i in (3, 14, 25):  # a translation, a learned handle's entry, another handle's entry
            e = torch.zeros_like(start.z)
            e[i] = h
            with torch.no_grad():
                fd = (loss_of({**base, which: base[which] + e}) - loss_of({**base, which: base[which] - e})) / (2 * h)
            g = float(grads[which][i])
            assert abs(g - float(fd)) <= 1e-3 * abs(float(fd)) + 1e-9, (which, i, g, float(fd))


@pytest.mark.parametrize("layer, beta, friction", [(0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                   (0.0, 0.0, 0.6)])
def test_adjoint_matches_unrolled_autograd(trained_field, layer, beta, friction):
    """The per-step adjoint equals backpropagation through many plain Newton iterations: BDF2 with
    damping, 2 substeps per frame, over a floor impact; also with a contact layer (``contact_layer``, which
    makes the floor's effective stiffness depend on E and ν: here it halves it), with a contact dashpot
    (``contact_damping``, gradient to β as well) and with floor friction (the spinning object slips)."""
    from vid2sim.physics.integrators import bdf_step
    from vid2sim.physics.reduced import ElasticBasis, StepProblem, lbs_rows

    field, pts = trained_field
    floor = Floor(height=-0.3, friction=friction, friction_velocity=0.5)
    sim = _sim(field, pts, material=Material(5e4, 0.3, damping_ratio=0.1), externals=[Gravity(), floor],
               k=60, config=SimConfig(substeps=2, friction_iterations=2, friction_tol=1e-12, **TIGHT))
    sim.contact_layer = torch.tensor(layer, dtype=torch.float64, requires_grad=True) if layer else 0.0
    sim.contact_damping.fill_(beta)
    names = ("log10_E", "nu", "damping_ratio") + (("contact_damping",) if beta else ()) \
        + (("contact_layer",) if layer else ())
    for name in names:
        getattr(sim, name).requires_grad_(True)
    wrt = [getattr(sim, name) for name in names]  # a tensor layer h: the gradient to h too (bench identify fits it)
    state = sim.rigid_velocity_state([0.0, 0.0, -3.0], [1.0, 0.0, 0.0])
    states = sim.rollout(state, 3)
    loss = (states[-1].z * torch.linspace(0.5, 1.5, states[-1].z.numel(), dtype=torch.float64)).sum()
    g_adj = torch.autograd.grad(loss, wrt)

    # unrolled reference: differentiable Newton with autograd Hessians, no line search (states are close)
    mu, lam = sim.lame()
    tau = sim.retardation_time()
    w, dw = field.weights_and_gradients(sim.X)
    basis = ElasticBasis(torch.eye(3, dtype=torch.float64).expand(sim.X.shape[0], 3, 3), gradient_basis(sim.X, w, dw))
    b = lbs_rows(sim.X, w)
    perm, inv = z_to_y_index(field.num_handles_total), y_to_z_index(field.num_handles_total)
    y, ydot, y2, ydot2, t = state.z[perm], state.zdot[perm], None, None, 0.0
    h = sim.config.dt / 2

    def in_contact(y, t):  # a point below the floor (the simulator's test for friction)
        return bool((floor.signed_distance(sim.positions(sim.X, y.detach()[inv]), t) < 0).any())

    for _ in range(6):
        t += h
        step = bdf_step("bdf2", h, h if y2 is not None else None)

        def newton(friction_state, start):
            prob = StepProblem(sim.X, sim.vol, sim.masses(), b, basis, mu, lam, "neo_hookean", sim.externals, t,
                               step, y, ydot, y2 if step.needs_history else None,
                               ydot2 if step.needs_history else None, tau,
                               contact_layer_stiffness=sim.contact_layer_stiffness(),
                               contact_damping=sim.contact_dashpot(), friction_state=friction_state)
            yk = start
            for _ in range(12):
                yk = yk - torch.linalg.solve(prob.hessian(yk, project=False), prob.gradient(yk))
            return yk

        yk = newton(None, y.detach().clone() + 0 * mu)  # start at the previous state, keep the graph
        lagged = friction and in_contact(y, t - h)
        for _ in range(sim.config.friction_iterations if friction else 0):  # the normal force's fixed point
            contact = in_contact(yk, t)
            if not contact and not lagged:
                break
            yk, lagged = newton(yk, yk.detach().clone() + 0 * mu), contact
        y2, ydot2, y, ydot = y, ydot, yk, step.velocity(yk, y, y2 if step.needs_history else None)
    loss_ref = (y[inv] * torch.linspace(0.5, 1.5, y.numel(), dtype=torch.float64)).sum()
    g_ref = torch.autograd.grad(loss_ref, wrt)
    assert torch.allclose(y[inv].detach(), states[-1].z.detach(), atol=1e-8)
    for ga, gr in zip(g_adj, g_ref):
        assert abs(float(ga) - float(gr)) <= 2e-5 * abs(float(gr)) + 1e-12
    if layer:
        k_b = float(sim.contact_layer_stiffness().detach())
        assert k_b == pytest.approx(5e4 / ((1 - 0.09) * layer)) and 0.3 < 1 / (1 + 1e5 / k_b) < 0.7
        sim.contact_layer = 0.0
        with torch.no_grad():
            stiff = sim.rollout(state, 3)[-1].z
        assert float((stiff - states[-1].z.detach()).abs().max()) > 1e-3  # the layer is in contact and matters
    if beta:
        with torch.no_grad():
            sim.contact_damping = torch.tensor(0.0, dtype=torch.float64)
            undamped = sim.rollout(state, 3)[-1].z
        assert float((undamped - states[-1].z.detach()).abs().max()) > 1e-3  # the dashpot acted
    if friction:
        sim.externals[1] = Floor(height=-0.3)
        with torch.no_grad():
            frictionless = sim.rollout(state, 3)[-1].z
        assert float((frictionless - states[-1].z.detach()).abs().max()) > 1e-3  # the friction acted


def _friction_problem(trained_field, eps: float):
    """One BDF2 step's problem with the floor's friction, points in contact at the start of the step and slipping
    over a range of speeds (the body spins and slides), and a state near its solution."""
    from vid2sim.physics.integrators import bdf_step
    from vid2sim.physics.reduced import ElasticBasis, StepProblem, lbs_rows

    field, pts = trained_field
    sim = _sim(field, pts, material=Material(5e4, 0.3, damping_ratio=0.1),
               externals=[Gravity(), Floor(height=-0.25, friction=0.7, friction_velocity=eps)], k=60)
    mu, lam = sim.lame()
    w, dw = field.weights_and_gradients(sim.X)
    basis = ElasticBasis(torch.eye(3, dtype=torch.float64).expand(sim.X.shape[0], 3, 3), gradient_basis(sim.X, w, dw))
    perm = z_to_y_index(field.num_handles_total)
    state = sim.rigid_velocity_state([1.5, 0.4, -0.5], [0.0, 0.0, 3.0])
    y, ydot = state.z[perm], state.zdot[perm]
    h = 0.01
    y_prev2, y_prev = y - h * ydot, y  # a rigid motion one step back
    problem = StepProblem(sim.X, sim.vol, sim.masses(), lbs_rows(sim.X, w), basis, mu, lam, "neo_hookean",
                          sim.externals, 2 * h, bdf_step("bdf2", h, h), y_prev, ydot, y_prev2, ydot,
                          sim.retardation_time())
    gen = torch.Generator().manual_seed(3)
    y_eval = problem.y_pred + 1e-3 * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    return problem, y_eval


@pytest.mark.parametrize("eps", [0.02, 5.0])
def test_friction_potential_gradient_and_hessian_match_finite_differences(trained_field, eps):
    """The step's potential with floor friction: ∇Φ against central differences of Φ, the exact Hessian against
    those of ∇Φ, with points in contact slipping faster than ε_v (ε = 0.02) and slower (ε = 5: the smoothed
    stick law); the friction's Hessian is positive semi-definite."""
    problem, y = _friction_problem(trained_field, eps)
    (index, _, _, _, c, _), = problem._friction_reference
    assert 3 <= index.numel() < problem.X.shape[0] and bool((c > 0).all())
    x = problem._contact_positions(y)[index]
    _, _, _, n, _, _ = problem._friction_reference[0]
    _, sigma = problem._slip(x, *problem._friction_reference[0][1:4])
    assert (bool((sigma > eps).all()) if eps < 0.1 else bool((sigma < eps).all()))
    g = problem.gradient(y)
    H = problem.hessian(y, project=False)
    d = 1e-6
    fd_g = torch.zeros_like(y)
    fd_H = torch.zeros_like(H)
    for i in range(y.numel()):
        e = torch.zeros_like(y)
        e[i] = d
        fd_g[i] = (problem.potential(y + e)[0] - problem.potential(y - e)[0]) / (2 * d)
        fd_H[:, i] = (problem.gradient(y + e) - problem.gradient(y - e)) / (2 * d)
    assert torch.allclose(g, fd_g, rtol=1e-6, atol=1e-6 * float(g.abs().max()))
    assert torch.allclose(H, fd_H, rtol=1e-5, atol=1e-6 * float(H.abs().max()))
    H_f = problem._friction_hessian(y)
    assert float(torch.linalg.eigvalsh(H_f).min()) >= -1e-9 * float(H_f.abs().max())


def test_friction_holds_a_box_on_a_slope_it_would_slide_down(trained_field):
    """A stiff box set down at rest on a floor tilted by 20°: frictionless it accelerates downhill at g sin 20°;
    with μ = 0.6 > tan 20° it stays (creeping below the smoothing's slip speed); with μ = 0.2 < tan 20° it slides
    at g (sin 20° − μ cos 20°)."""
    from vid2sim.physics.external import MovingFloor

    field, pts = trained_field
    theta = math.radians(20.0)
    down = torch.tensor([0.0, -math.cos(theta), -math.sin(theta)], dtype=torch.float64)  # downhill along the plane
    travel = {}
    for mu in (0.0, 0.2, 0.6):
        sim = _sim(field, pts, material=Material(1e6, 0.3), config=SimConfig(dt=0.02, substeps=8), k=120)
        # the box turned onto the plane (about +x, as the plane's tilt) and set just on it
        c, s = math.cos(theta), math.sin(theta)
        R = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
        posed = sim.X @ R.T
        n = torch.tensor([0.0, -s, c], dtype=torch.float64)
        floor = MovingFloor(height=float((posed @ n).min()) / c - 1e-4, tilt_deg=20.0, stiffness=1e8, friction=mu)
        sim.externals[1] = floor
        state = sim.rest_state()
        H = field.num_handles_total
        z = state.z.clone().reshape(H, 3, 4)
        z[H - 1, :, :3] = R - torch.eye(3, dtype=torch.float64)  # the constant handle carries the rigid turn
        state.z = z.reshape(-1)
        with torch.no_grad():
            states = sim.rollout(state, 25)
        start = sim.positions(sim.X, state.z).mean(0)
        travel[mu] = [float((sim.positions(sim.X, st.z).mean(0) - start) @ down) for st in states]
    t = 25 * 0.02
    assert travel[0.0][-1] == pytest.approx(0.5 * G * math.sin(theta) * t * t, rel=0.05)
    assert travel[0.2][-1] == pytest.approx(0.5 * G * (math.sin(theta) - 0.2 * math.cos(theta)) * t * t, rel=0.1)
    assert abs(travel[0.6][-1]) < 0.02 * travel[0.0][-1]


def test_a_sliding_box_stops_where_coulomb_says_and_converges_in_the_step(trained_field):
    """A stiff box launched along the floor at v₀ = 2 m/s with μ = 0.5 decelerates at μg and stops after
    v₀² / (2μg) = 0.408 m (within 2 %, with 8 and 32 substeps per frame, which agree within 1 %); on the
    frictionless floor it keeps its speed."""
    field, pts = trained_field
    v0, mu = 2.0, 0.5
    travel = {}
    for friction, substeps in ((mu, 8), (mu, 32), (0.0, 8)):
        sim = _sim(field, pts, material=Material(1e6, 0.3), config=SimConfig(dt=0.02, substeps=substeps), k=120)
        sim.externals[1] = Floor(height=float(sim.X[:, 2].min()) - 1e-4, stiffness=1e8, friction=friction)
        with torch.no_grad():
            states = sim.rollout(sim.rigid_velocity_state([v0, 0.0, 0.0]), 30)
        x = torch.tensor([float(sim.positions(sim.X, s.z)[:, 0].mean()) for s in states], dtype=torch.float64)
        x = torch.cat([sim.X[:, 0].mean().view(1), x])
        travel[(friction, substeps)] = x - x[0]
        if friction:
            v = (x[1:] - x[:-1]) / 0.02
            slope = float(torch.linalg.lstsq(torch.stack([torch.arange(3, 16.0, dtype=torch.float64),
                                                           torch.ones(13, dtype=torch.float64)], 1),
                                             v[3:16, None]).solution[0]) / 0.02
            assert slope == pytest.approx(-mu * G, rel=0.1)
    stop = v0 * v0 / (2 * mu * G)
    assert float(travel[(mu, 8)][-1]) == pytest.approx(stop, rel=0.02)
    assert float(travel[(mu, 32)][-1]) == pytest.approx(stop, rel=0.02)
    assert float((travel[(mu, 8)] - travel[(mu, 32)]).abs().max()) < 0.01 * stop
    assert float(travel[(0.0, 8)][-1]) == pytest.approx(v0 * 0.6, rel=0.01)


def test_the_implicit_normal_force_converges_a_tumbling_drop_with_friction_in_the_step(trained_field):
    """A box thrown spinning onto a floor with μ = 0.5 bounces, slides and tips: with the normal force of the start
    of each step (``friction_iterations=0``) friction's one-step lag is a first-order error; with it made implicit
    (the default fixed point) the automatic 8 substeps per frame follow 64 within a fraction of that error."""
    field, pts = trained_field
    com = {}
    for iterations, substeps in ((0, 8), (0, 16), (4, 8), (4, 64)):
        sim = _sim(field, pts, material=Material(1e5, 0.3), externals=[Gravity(), Floor(height=-0.6, friction=0.5)],
                   config=SimConfig(substeps=substeps, friction_iterations=iterations), k=120)
        with torch.no_grad():
            states = sim.rollout(sim.rigid_velocity_state([1.5, 0.5, -2.0], [3.0, -2.0, 1.0]), 12)
        com[(iterations, substeps)] = torch.stack([sim.positions(sim.X, s.z).mean(0) for s in states])
    reference = com[(4, 64)]
    error = {key: float((c - reference).norm(dim=1).max()) for key, c in com.items() if key != (4, 64)}
    size = float((pts.amax(0) - pts.amin(0)).norm())
    assert error[(0, 8)] > 1e-3 * size  # the lag matters here
    assert 1.5 < error[(0, 8)] / error[(0, 16)] < 3  # first order: halving the step halves it
    assert error[(4, 8)] < 0.25 * error[(0, 8)]


def test_the_simulation_computes_in_its_configs_dtype_whatever_its_inputs(trained_field):
    """A float32 field and float32 points make a float64 simulation by default (its state, its parameters), the
    positions come back in the points' dtype, and the drop is the one of the float64 inputs; ``dtype="float32"``
    computes in float32; an unknown dtype is a named error."""
    import copy

    from vid2sim.runtime.errors import ConfigError

    field, pts = trained_field
    field32 = copy.deepcopy(field).float()
    idx, w = sample_cubature(pts, 80, volume=1.0, seed=0)
    runs = {}
    for name, f, X, config in (("f64 inputs", field, pts[idx], SimConfig(substeps=4)),
                               ("f32 inputs", field32, pts[idx].float(), SimConfig(substeps=4)),
                               ("f32 sim", field32, pts[idx].float(), SimConfig(substeps=4, dtype="float32"))):
        sim = Simulator(f, X, w.to(X), Material(1e5, 0.3), [Gravity(), Floor(height=-0.5)], config)
        with torch.no_grad():
            state = sim.rollout(sim.rigid_velocity_state([0.5, 0.0, -1.0], [0.0, 2.0, 0.0]), 6)[-1]
            runs[name] = (state.z, sim.log10_E.dtype, sim.positions(X, state.z))
    assert runs["f32 inputs"][0].dtype == torch.float64 and runs["f32 inputs"][1] == torch.float64
    assert runs["f32 inputs"][2].dtype == torch.float32
    assert runs["f32 sim"][0].dtype == torch.float32
    assert float((runs["f32 inputs"][0] - runs["f64 inputs"][0]).abs().max()) < 1e-4  # the field's float32 basis
    assert float((runs["f32 sim"][0].double() - runs["f64 inputs"][0]).abs().max()) < 1e-3
    with pytest.raises(ConfigError, match="dtype"):
        SimConfig(dtype="float16")


def test_contact_dashpot_takes_the_bounce_and_only_dissipates(trained_field):
    """A drop on the floor with the contact dashpot β: the rebound falls as β grows, the mechanical energy
    after the bounce falls with it, and before the first contact nothing changes (the dashpot acts only on
    points in contact). β < 0 is a named error."""
    field, pts = trained_field
    results = []
    for beta in (0.0, 0.3, 3.0):
        sim = _sim(
            field,
            pts,
            material=Material(1e5, 0.3, damping_ratio=0.0),
            externals=[Gravity(), Floor(height=-0.6)],
            config=SimConfig(substeps=8),
            k=80,
        )
        sim.contact_damping.fill_(beta)
        with torch.no_grad():
            states = sim.rollout(sim.rigid_velocity_state([0.0, 0.0, -2.0]), 12)
            centre = [float(sim.positions(pts[::5], s.z)[:, 2].mean()) for s in states]
            last = states[-1]
            x = sim.positions(sim.X, last.z)
            v = sim.positions(sim.X, last.z + last.zdot) - x  # LBS is linear in z: the velocity field
            m = sim.masses()
            kinetic = 0.5 * float((m[:, None] * v * v).sum())
            potential = float((m * G * x[:, 2]).sum()) + float(sim.externals[1].energy(x, torch.ones_like(m)))
            psi = energy_and_pk1("neo_hookean", sim.deformation_gradients_at_cubature(last.z), *sim.lame())[0]
            elastic = float(sim.vol @ psi)
        results.append((centre, kinetic + potential + elastic))
    (c0, e0), (c1, e1), (c2, e2) = results
    for f in (0, 1):  # no contact before frame 3
        assert c0[f] == pytest.approx(c1[f], abs=1e-12) and c0[f] == pytest.approx(c2[f], abs=1e-12)
    rebound = [max(c[3:]) for c in (c0, c1, c2)]
    assert rebound[0] > rebound[1] > rebound[2]
    assert e0 > e1 > e2  # kinetic + gravity + floor + elastic energy at frame 10
    with pytest.raises(ValueError, match="contact_damping must be"):
        _sim(field, pts).__class__(field, pts[:10], torch.ones(10, dtype=torch.float64), Material(), [],
                                   contact_damping=-1.0)


def test_neural_jacobian_switch_uses_the_given_basis(trained_field):
    """With a 'network' that returns the exact dF/dz, the Neural-Jacobian path reproduces the exact one."""
    field, pts = trained_field

    class ExactJacobian(torch.nn.Module):
        def forward(self, X):
            w, dw = field.weights_and_gradients(X)
            return dF_dz(gradient_basis(X, w, dw))

    exact = _sim(field, pts)
    idx, wts = sample_cubature(pts, 120, volume=1.0, seed=0)
    neural = Simulator(field, pts[idx], wts.double(), Material(1e5, 0.3), [Gravity(), Floor(height=-0.5)],
                       SimConfig(), jacobian=ExactJacobian(), use_neural_jacobian=True)
    a = exact.rollout(exact.rest_state(), 10)[-1].z
    b = neural.rollout(neural.rest_state(), 10)[-1].z
    assert torch.allclose(a, b, atol=1e-7)


def test_sphere_obstacle_is_never_penetrated(trained_field):
    field, pts = trained_field
    center = torch.tensor([0.0, 0.0, -0.9], dtype=torch.float64)
    sim = _sim(field, pts, externals=[Gravity(), SphereObstacle(center=(0.0, 0.0, -0.9), radius=0.5, stiffness=1e6)])
    states = sim.rollout(sim.rest_state(), 24)
    gaps = [float((sim.positions(pts, s.z).detach() - center).norm(dim=1).min()) - 0.5 for s in states]
    assert min(gaps) > -0.015  # the (stiffer) barrier holds the object out of the ball (≈ 1 cm at impact)
    assert min(gaps) < 0.01  # and it did land on it
    assert all(bool(torch.isfinite(s.z).all()) for s in states)


def test_float32_drop_runs_and_converges(trained_field):
    field, pts = trained_field
    f32 = SkinningField(num_handles=4, seed=0)
    f32.load_state_dict({k: v.float() for k, v in field.state_dict().items()})
    sim = _sim(f32, pts.float(), dtype=torch.float32)
    states = sim.rollout(sim.rest_state(), 20)
    assert all(bool(torch.isfinite(s.z).all()) for s in states)
    assert sum(s.converged for s in states) >= 18


def test_bad_inputs_give_clear_errors(trained_field):
    field, pts = trained_field
    with pytest.raises(ValueError, match="Poisson"):
        Material(1e5, 0.5)
    with pytest.raises(ValueError, match="Young"):
        Material(-1.0, 0.3)
    with pytest.raises(ValueError, match="density"):
        Material(1e5, 0.3, density=0.0)
    with pytest.raises(ValueError, match="model"):
        Material(model="rubber")
    with pytest.raises(ValueError, match="cubature_points"):
        Simulator(field, torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.float64), Material())
    with pytest.raises(ValueError, match="dt"):
        SimConfig(dt=0.0)
    with pytest.raises(ValueError, match="integrator"):
        SimConfig(integrator="rk4")
    with pytest.raises(ValueError, match="damping_ratio"):
        Material(damping_ratio=-0.1)
    sim = _sim(field, pts)
    st = sim.rest_state()
    with pytest.raises(ValueError, match="shape"):
        sim.step(SimState(st.z[:5], st.zdot[:5]))
    with pytest.raises(SimulationError, match="NaN"):
        sim.step(SimState(st.z * float("nan"), st.zdot))
    # a state with inverted cubature points: mirror the object through the rigid handle
    H = field.num_handles_total
    Z = torch.zeros(H, 3, 4, dtype=torch.float64)
    Z[-1, 0, 0] = -2.0  # x -> -x: det F = -1
    with pytest.raises(SimulationError, match="inverted"):
        sim.step(SimState(Z.reshape(-1), torch.zeros(12 * H, dtype=torch.float64)))


@pytest.mark.cuda
def test_cuda_rollout_and_adjoint_match_cpu(trained_field):
    """The same drop (floor impact included) and its adjoint gradients on CUDA and on the CPU, float64."""
    field, pts = trained_field
    idx, w = sample_cubature(pts, 120, volume=1.0, seed=0)

    def run(device: str):
        f = SkinningField(num_handles=4, seed=0).double()
        f.load_state_dict(field.state_dict())
        f = f.to(device)
        sim = Simulator(f, pts[idx].to(device), w.to(device), Material(1e5, 0.3),
                        [Gravity(), Floor(height=-0.5)], SimConfig())
        sim.log10_E.requires_grad_(True)
        sim.nu.requires_grad_(True)
        states = sim.rollout(sim.rest_state(), 15)
        x = sim.positions(pts[:300].to(device), states[-1].z)
        loss = (x * x).sum()
        grads = torch.autograd.grad(loss, [sim.log10_E, sim.nu])
        assert all(s.z.device.type == device for s in states)
        return x.detach().cpu(), [float(g) for g in grads], [s.converged for s in states]

    x_cpu, g_cpu, conv_cpu = run("cpu")
    x_gpu, g_gpu, conv_gpu = run("cuda")
    assert conv_cpu == conv_gpu and all(conv_gpu)
    assert torch.allclose(x_gpu, x_cpu, atol=1e-8)
    for a, b in zip(g_cpu, g_gpu):
        assert abs(a - b) <= 1e-6 * abs(a), (a, b)


def test_a_material_with_an_unknown_plasticity_is_refused_when_made():
    with pytest.raises(ValueError, match="Material.plasticity must be None, VonMises"):
        Material(plasticity="x")
    assert Material(plasticity={"type": "von_mises", "yield_stress": 300.0}).plasticity.yield_stress == 300.0


def test_newton_cache_fits_the_rotation_from_its_kept_moments():
    """The kept factor's rotation fit uses Σ m x aᵀ = Xa + Y Ba (no per-point work): for cubature points
    moved rigidly by R (exactly representable through the rigid handle's columns [X, 1]), it recovers R."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from vid2sim.physics.solver import NewtonCache

    g = torch.Generator().manual_seed(0)
    K, H = 40, 3
    X = torch.rand(K, 3, generator=g, dtype=torch.float64) - 0.5
    w = torch.rand(K, H - 1, generator=g, dtype=torch.float64)
    b = torch.cat([(w[:, :, None] * torch.cat([X, torch.ones(K, 1, dtype=torch.float64)], 1)[:, None]).reshape(K, -1),
                   X, torch.ones(K, 1, dtype=torch.float64)], 1)  # (K, 4H); the last handle is rigid
    m = 0.5 + torch.rand(K, generator=g, dtype=torch.float64)
    problem = SimpleNamespace(X=X, b=b, mass=m, positions=lambda y: X + b @ y.reshape(3, -1).T)
    Y0 = 0.05 * torch.randn(3, 4 * H, generator=g, dtype=torch.float64)
    R = torch.tensor(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix(), dtype=torch.float64)
    t = torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64)
    Y1 = R @ Y0
    Y1[:, -4:-1] += R - torch.eye(3, dtype=torch.float64)
    Y1[:, -1] += t
    y0, y1 = Y0.reshape(-1), Y1.reshape(-1)
    assert torch.allclose(problem.positions(y1), problem.positions(y0) @ R.T + t, atol=1e-12)
    cache = NewtonCache()
    cache.keep(torch.eye(12 * H, dtype=torch.float64), problem, y0)
    assert torch.equal(cache.rotation, torch.eye(3, dtype=torch.float64)) and not cache.stale
    grad = torch.randn(12 * H, generator=g, dtype=torch.float64)
    d = cache.direction(problem, y1, grad)
    assert torch.allclose(cache.rotation, R, atol=1e-12)
    # with the identity factor the chord step is −(R ⊗ I)(R ⊗ I)ᵀ g = −g
    assert torch.allclose(d, -grad, atol=1e-12)


def test_stiffness_scale_is_a_modulus_factor_and_keeps_the_materials_gradient(trained_field):
    """A simulator at E with stiffness_scale s moves exactly as one at E·s (energy, damping and substeps),
    and d(loss)/d(log10 E) is the same: scaling E by a constant leaves its logarithm's derivative."""
    field, pts = trained_field
    s = 0.6
    runs = []
    for E, scale in ((2e5, s), (2e5 * s, 1.0)):
        idx, w = sample_cubature(pts, 120, volume=1.0, seed=0)
        sim = Simulator(field, pts[idx], w, Material(E, 0.3, damping_ratio=0.1), [Gravity(), Floor(height=-0.5)],
                        SimConfig(**TIGHT), stiffness_scale=scale)
        sim.log10_E.requires_grad_(True)
        loss = _window_loss(sim, pts, steps=4)
        (grad,) = torch.autograd.grad(loss, sim.log10_E)
        runs.append((sim.substeps(), float(loss.detach()), float(grad)))
    assert runs[0][0] == runs[1][0]
    assert runs[0][1] == pytest.approx(runs[1][1], rel=1e-12)
    assert runs[0][2] == pytest.approx(runs[1][2], rel=1e-8)
    idx, w = sample_cubature(pts, 120, volume=1.0, seed=0)
    for bad in (0.0, -1.0, math.inf, True):
        with pytest.raises(ValueError, match="stiffness_scale"):
            Simulator(field, pts[idx], w, Material(1e5, 0.3), stiffness_scale=bad)


def test_a_stiffness_curve_is_its_value_at_the_current_nu_and_carries_the_gradient_to_nu(trained_field):
    """With ``stiffness_scale=StiffnessCurve`` the simulator moves as with the number s(ν), and the adjoint's
    d(loss)/dν includes ds/dν: central differences in float64, relative error < 1e-3."""
    from vid2sim.physics.stiffness_curve import StiffnessCurve

    field, pts = trained_field
    curve = StiffnessCurve((0.2, 0.3, 0.4, 0.45, 0.49), (0.95, 0.9, 0.8, 0.7, 0.55))  # steep: ds/dν matters
    idx, w = sample_cubature(pts, 120, volume=1.0, seed=0)

    def make(scale):
        return Simulator(field, pts[idx], w, Material(3e4, 0.42, damping_ratio=0.2), [Gravity()],
                         SimConfig(substeps=3, **TIGHT), stiffness_scale=scale)

    sim, fixed = make(curve), make(curve.at(0.42))
    assert float(sim.effective_youngs_modulus()) == pytest.approx(3e4 * curve.at(0.42), rel=1e-12)
    sim.nu.requires_grad_(True)
    fixed.nu.requires_grad_(True)
    loss = _window_loss(sim, pts)
    assert float(loss.detach()) == pytest.approx(float(_window_loss(fixed, pts).detach()), rel=1e-12)
    (grad,) = torch.autograd.grad(loss, sim.nu)
    (grad_fixed,) = torch.autograd.grad(_window_loss(fixed, pts), fixed.nu)

    def loss_at(nu: float) -> float:
        with torch.no_grad():
            sim.nu = torch.tensor(nu, dtype=torch.float64)
            return float(_window_loss(sim, pts))

    h = 1e-4
    fd = (loss_at(0.42 + h) - loss_at(0.42 - h)) / (2 * h)
    assert abs(float(grad) - fd) <= 1e-3 * abs(fd), (float(grad), fd)
    assert abs(float(grad) - float(grad_fixed)) > 0.05 * abs(fd)  # the curve's slope is part of the gradient


def test_centre_of_mass_of_a_spinning_vibrating_body_in_flight_falls_like_a_point(trained_field):
    """Elastic and viscous forces depend on F only, so they do not move the centre of mass: in flight it falls
    like a point while the body spins and vibrates. Its frames then follow free fall's closed form under
    BDF2 (see the free-fall test; the start's velocity adds an exact linear motion): the second difference
    of the centre (:func:`vid2sim.evaluate.scores.simulated_centre_of_mass`) about frame f (n = 3f
    substeps of h) is −g dt² + (3/4) g h² (3^−(n−3) − 2·3^−n + 3^−(n+3)), to the Newton tolerance."""
    from vid2sim.asset.motion import simulated_centre_of_mass

    field, pts = trained_field
    sim = _sim(field, pts, externals=[Gravity()], config=SimConfig(substeps=3))
    rest = sim.rest_state()
    zdot = 0.5 * torch.randn(rest.z.shape, generator=torch.Generator().manual_seed(3), dtype=rest.z.dtype)
    states = [SimState(rest.z, zdot)] + sim.rollout(SimState(rest.z, zdot), 8)
    x = sim.positions(pts[:300], states[-1].z) - sim.positions(pts[:300], states[0].z)
    assert float((x - x.mean(0)).norm(dim=1).max()) > 0.05  # the body turns and deforms, not only translates
    c = simulated_centre_of_mass(sim, states)
    assert c.shape == (9, 3) and c.dtype == torch.float64
    second = c[2:] - 2 * c[1:-1] + c[:-2]  # about frames 1..7
    dt = sim.config.dt
    h = dt / 3
    expected = torch.zeros_like(second)
    for i, f in enumerate(range(1, 8)):
        n = 3 * f
        expected[i, 2] = -G * dt**2 + 0.75 * G * h**2 * (3.0 ** -(n - 3) - 2 * 3.0 ** -n + 3.0 ** -(n + 3))
    torch.testing.assert_close(second, expected, atol=1e-9, rtol=0)
    assert float((second[0, 2] - (-G * dt**2)).abs()) > 1e-5  # the start's transient is resolved, not hidden


def test_the_fixed_points_solves_start_from_its_last_solution(trained_field):
    """Each solve of friction's fixed point starts Newton at the previous solve's state (``friction_state``), which
    lies within the fixed point's change of the answer: on a tumbling drop with μ = 0.5 the fixed point's re-solves
    add few Newton iterations to the lagged step's (they took as many as the first solve when they started from the
    step's extrapolation), and the states are those of a much tighter solve."""
    field, pts = trained_field
    runs = {}
    for iterations, tol in ((0, 1e-6), (4, 1e-6), (4, 1e-10)):
        sim = _sim(field, pts, material=Material(1e5, 0.3), externals=[Gravity(), Floor(height=-0.6, friction=0.5)],
                   config=SimConfig(substeps=8, friction_iterations=iterations, newton_tol=tol,
                                    newton_rtol=100 * tol, friction_tol=100 * tol), k=120)
        with torch.no_grad():
            states = sim.rollout(sim.rigid_velocity_state([1.5, 0.5, -2.0], [3.0, -2.0, 1.0]), 12)
        runs[(iterations, tol)] = (sum(s.newton_iterations for s in states), torch.stack([s.z for s in states]))
    lagged, implicit = runs[(0, 1e-6)][0], runs[(4, 1e-6)][0]
    assert implicit < 1.5 * lagged
    assert float((runs[(4, 1e-6)][1] - runs[(4, 1e-10)][1]).abs().max()) < 1e-3
