"""Physics tests of the reduced implicit-Euler simulator and its adjoint."""

from __future__ import annotations

import math

import pytest
import torch

from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.external import Floor, Gravity, SphereObstacle
from vid2sim.physics.materials import neo_hookean_indefinite
from vid2sim.physics.reduced import y_to_z_index, z_to_y_index
from vid2sim.physics.skinning import SkinningField, dF_dz, gradient_basis
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.physics.solver import Material, SimConfig, SimState, SimulationError, Simulator

G = 9.8


def _box(n: int, seed: int, size=(0.6, 0.4, 0.6), dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    s = torch.tensor(size, dtype=torch.float64)
    s = s * (0.5 / float(s.norm() / 2))
    return ((torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * s).to(dtype)


@pytest.fixture(scope="module")
def trained_field() -> tuple[SkinningField, torch.Tensor]:
    """A small data-free-trained skinning field (4 learned handles) on a box, float64."""
    torch.manual_seed(0)
    pts = _box(1500, 0)
    field = SkinningField(num_handles=4, seed=0).double()
    train_skinning(field, pts, SkinningTrainingConfig(iterations=150, points_per_step=500, batch_size=4, seed=0),
                   progress=False)
    for p in field.parameters():
        p.requires_grad_(False)
    return field, pts


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


def test_free_fall_matches_discrete_implicit_euler(trained_field):
    field, pts = trained_field
    sim = _sim(field, pts, externals=[Gravity()])
    states = sim.rollout(sim.rest_state(), 6)
    for n, st in enumerate(states, start=1):
        # implicit Euler under constant gravity: v_n = -g n dt, x_n = -g dt² n(n+1)/2
        expected = -G * sim.config.dt**2 * n * (n + 1) / 2
        x = sim.positions(pts[:200], st.z) - pts[:200]
        assert torch.allclose(x[:, 2], torch.full_like(x[:, 2], expected), atol=1e-8)
        assert float(x[:, :2].abs().max()) < 1e-8
        F = sim.deformation_gradients(pts[:200], st.z)
        assert float((F - torch.eye(3, dtype=F.dtype)).abs().max()) < 1e-7  # no deformation in free fall
        assert st.converged


def test_dropped_elastic_object_comes_to_rest_on_floor(trained_field):
    field, pts = trained_field
    sim = _sim(field, pts, material=Material(1e5, 0.3))
    states = sim.rollout(sim.rest_state(), 40)
    zs = torch.stack([s.z for s in states])
    assert bool(torch.isfinite(zs).all())
    x = sim.positions(pts, states[-1].z)
    size = float((pts.max(0).values - pts.min(0).values).norm())
    penetration = max(0.0, -0.5 - float(x[:, 2].min()))
    assert penetration < 0.01 * size
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
    for mode in ("always", "on_demand"):
        cfg = SimConfig(newton_rtol=1e-11, newton_max_iters=60, hessian_projection=mode)
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


def _window_loss(sim, pts, steps=5):
    state = sim.rigid_velocity_state([0.2, 0.0, -2.0], [0.0, 6.0, 2.0])
    states = sim.rollout(state, steps)
    x = sim.positions(pts[::10], states[-1].z)
    weights = torch.linspace(-1.0, 1.0, x.numel(), dtype=x.dtype).reshape(x.shape)
    return (x * weights).sum()


def test_adjoint_gradients_match_finite_differences(trained_field):
    """Adjoint vs central differences on a smooth problem (a spinning, deforming object in free fall).

    Contact makes the loss only piecewise smooth, which spoils finite differences; contact is covered by
    the comparison with unrolled autograd below.
    """
    field, pts = trained_field
    field = SkinningField(num_handles=4, seed=0).double()
    field.load_state_dict(trained_field[0].state_dict())
    sim = _sim(field, pts, material=Material(3e4, 0.35), externals=[Gravity()],
               config=SimConfig(newton_rtol=1e-10, newton_max_iters=40))
    for t in (sim.log10_E, sim.nu, sim.density):
        t.requires_grad_(True)
    W = list(field.parameters())[-2]
    loss = _window_loss(sim, pts)
    grads = torch.autograd.grad(loss, [sim.log10_E, sim.nu, sim.density, W])

    def loss_at(**kw) -> float:
        with torch.no_grad():
            saved = {k: getattr(sim, k).detach().clone() for k in ("log10_E", "nu", "density")}
            for k, v in kw.items():
                if k in saved:
                    setattr(sim, k, v)
            value = float(_window_loss(sim, pts))
            for k, v in saved.items():
                setattr(sim, k, v)
        return value

    for i, (name, h) in enumerate((("log10_E", 1e-3), ("nu", 1e-3), ("density", 1.0))):
        base = getattr(sim, name).detach()
        fd = (loss_at(**{name: base + h}) - loss_at(**{name: base - h})) / (2 * h)
        assert abs(float(grads[i]) - fd) <= 1e-3 * abs(fd), (name, float(grads[i]), fd)
    for a, b in ((0, 3), (2, 17)):
        h = 1e-3
        old = float(W[a, b].detach())
        with torch.no_grad():
            W[a, b] = old + h
            lp = loss_at()
            W[a, b] = old - h
            lm = loss_at()
            W[a, b] = old
        fd = (lp - lm) / (2 * h)
        assert abs(float(grads[3][a, b]) - fd) <= 1e-3 * abs(fd), (a, b, float(grads[3][a, b]), fd)


def test_adjoint_gradients_wrt_the_initial_state_match_finite_differences(trained_field):
    field, pts = trained_field
    sim = _sim(field, pts, material=Material(3e4, 0.35), externals=[Gravity()],
               config=SimConfig(newton_rtol=1e-10, newton_max_iters=40))
    start = sim.rigid_velocity_state([0.2, 0.0, -2.0], [0.0, 6.0, 2.0])
    target_w = torch.linspace(-1.0, 1.0, 3 * pts[::10].shape[0], dtype=torch.float64).reshape(-1, 3)

    def loss_of(z0: torch.Tensor, zdot0: torch.Tensor) -> torch.Tensor:
        states = sim.rollout(SimState(z0, zdot0), 4)
        return (sim.positions(pts[::10], states[-1].z) * target_w).sum()

    z0 = start.z.clone().requires_grad_(True)
    zdot0 = start.zdot.clone().requires_grad_(True)
    g_z, g_zdot = torch.autograd.grad(loss_of(z0, zdot0), [z0, zdot0])
    h = 1e-5
    for which, grad in (("z", g_z), ("zdot", g_zdot)):
        for i in (3, 14, 25):  # a translation, a learned handle's entry, another handle's entry
            e = torch.zeros_like(start.z)
            e[i] = h
            with torch.no_grad():
                if which == "z":
                    fd = (loss_of(start.z + e, start.zdot) - loss_of(start.z - e, start.zdot)) / (2 * h)
                else:
                    fd = (loss_of(start.z, start.zdot + e) - loss_of(start.z, start.zdot - e)) / (2 * h)
            assert abs(float(grad[i]) - float(fd)) <= 1e-3 * abs(float(fd)) + 1e-9, (which, i, float(grad[i]), float(fd))


def test_adjoint_matches_unrolled_autograd(trained_field):
    """The per-step adjoint equals backpropagation through many plain Newton iterations."""
    from vid2sim.physics.reduced import ElasticBasis, StepProblem, lbs_rows

    field, pts = trained_field
    sim = _sim(field, pts, material=Material(5e4, 0.3), externals=[Gravity(), Floor(height=-0.3)], k=60,
               config=SimConfig(newton_rtol=1e-11, newton_max_iters=50))
    sim.log10_E.requires_grad_(True)
    sim.nu.requires_grad_(True)
    state = sim.rigid_velocity_state([0.0, 0.0, -3.0], [1.0, 0.0, 0.0])
    states = sim.rollout(state, 3)
    loss = (states[-1].z * torch.linspace(0.5, 1.5, states[-1].z.numel(), dtype=torch.float64)).sum()
    g_adj = torch.autograd.grad(loss, [sim.log10_E, sim.nu])

    # unrolled reference: differentiable Newton with autograd Hessians, no line search (states are close)
    mu, lam = sim.lame()
    w, dw = field.weights_and_gradients(sim.X)
    basis = ElasticBasis(torch.eye(3, dtype=torch.float64).expand(sim.X.shape[0], 3, 3), gradient_basis(sim.X, w, dw))
    b = lbs_rows(sim.X, w)
    perm, inv = z_to_y_index(field.num_handles_total), y_to_z_index(field.num_handles_total)
    y, ydot, t = state.z[perm], state.zdot[perm], 0.0
    for _ in range(3):
        t += sim.config.dt
        prob = StepProblem(sim.X, sim.vol, sim.masses(), b, basis, mu, lam, "neo_hookean", sim.externals, t,
                           sim.config.dt, y, ydot)
        yk = y.detach().clone() + 0 * mu  # start at the previous state, keep the graph
        for _ in range(12):
            yk = yk - torch.linalg.solve(prob.hessian(yk, project=False), prob.gradient(yk))
        ydot = (yk - y) / sim.config.dt
        y = yk
    loss_ref = (y[inv] * torch.linspace(0.5, 1.5, y.numel(), dtype=torch.float64)).sum()
    g_ref = torch.autograd.grad(loss_ref, [sim.log10_E, sim.nu])
    assert torch.allclose(y[inv].detach(), states[-1].z.detach(), atol=1e-8)
    for ga, gr in zip(g_adj, g_ref):
        assert abs(float(ga) - float(gr)) <= 2e-5 * abs(float(gr)) + 1e-12


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
    assert min(gaps) > -0.01  # the (stiffer) barrier holds the object out of the ball
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
