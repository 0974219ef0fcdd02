"""External energies (vid2sim.physics.external) checked against finite differences and closed forms."""

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vid2sim.physics.external import (
    ExternalEnergy,
    Floor,
    Gravity,
    MovingFloor,
    SphereObstacle,
    external_from_dict,
    total_external,
)

DT = torch.float64
K = 1e5


def points(n: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = 0.6 * torch.randn(n, 3, generator=gen, dtype=DT)
    mass = 0.1 + torch.rand(n, generator=gen, dtype=DT)
    return x, mass


MOVING = MovingFloor(
    height=-0.1, velocity=0.3, amplitude=0.2, frequency=0.8, tilt_deg=12.0, tilt_rate_deg=25.0,
    tilt_axis=(1.0, 2.0, 0.0), pivot_xy=(0.2, -0.3),
)
ENERGIES = {
    "gravity": Gravity(),
    "gravity_tilted": Gravity((1.0, -2.0, -9.8)),
    "floor": Floor(height=-0.05),
    "moving_floor": MOVING,
    "sphere": SphereObstacle(center=(0.1, 0.0, -0.2), radius=0.7),
}
TIMES = [0.0, 0.37, 1.3]


def away_from_kink(energy, x, t, margin=1e-3):
    """Points whose signed distance is not within ``margin`` of the contact kink (FD step is 1e-6)."""
    if not hasattr(energy, "signed_distance"):
        return x
    return x[energy.signed_distance(x, t).abs() > margin]


def fd_gradient(energy, x, mass, t, h=1e-6):
    g = torch.zeros_like(x)
    for a in range(3):
        e = torch.zeros(3, dtype=DT)
        e[a] = h
        for i in range(x.shape[0]):  # per point: the energy is separable, one point moves at a time
            xp, xm = x.clone(), x.clone()
            xp[i] += e
            xm[i] -= e
            g[i, a] = (energy.energy(xp, mass, t) - energy.energy(xm, mass, t)) / (2 * h)
    return g


def fd_hessian(energy, x, mass, t, h=1e-6):
    H = torch.zeros(x.shape[0], 3, 3, dtype=DT)
    for b in range(3):  # separable: moving every point's b-coordinate at once gives all blocks' column b
        e = torch.zeros(3, dtype=DT)
        e[b] = h
        H[:, :, b] = (energy.gradient(x + e, mass, t) - energy.gradient(x - e, mass, t)) / (2 * h)
    return H


@pytest.mark.parametrize("name", sorted(ENERGIES))
@pytest.mark.parametrize("t", TIMES)
def test_gradient_matches_finite_differences(name, t):
    energy = ENERGIES[name]
    x, mass = points(12, seed=1)
    x = away_from_kink(energy, x, t)
    mass = mass[: x.shape[0]]
    g = energy.gradient(x, mass, t)
    assert int((g.abs().amax(dim=1) > 0).sum()) >= 3  # some points are in contact
    scale = max(float(g.abs().max()), 1.0)
    assert torch.allclose(g, fd_gradient(energy, x, mass, t), atol=1e-6 * scale, rtol=0)


@pytest.mark.parametrize("name", sorted(ENERGIES))
@pytest.mark.parametrize("t", TIMES)
def test_hessian_matches_finite_differences_and_is_psd(name, t):
    energy = ENERGIES[name]
    x, mass = points(60, seed=2)
    x = away_from_kink(energy, x, t)
    mass = mass[: x.shape[0]]
    H_exact = energy.hessian(x, mass, t, project=False)
    H_fd = fd_hessian(energy, x, mass, t)
    assert torch.allclose(H_exact, H_fd, atol=1e-8 * K, rtol=0)
    H = energy.hessian(x, mass, t)
    # the projected blocks are the exact eigenvalue clamp of the true (finite-difference) Hessian
    w, V = torch.linalg.eigh(0.5 * (H_fd + H_fd.transpose(1, 2)))
    clamp = (V * w.clamp_min(0)[:, None, :]) @ V.transpose(1, 2)
    assert torch.allclose(H, clamp, atol=1e-8 * K, rtol=0)
    assert float(torch.linalg.eigvalsh(H).min()) >= -1e-9 * K


def test_the_tests_see_contact_and_an_indefinite_sphere_hessian():
    x, mass = points(60, seed=2)
    for name in ("floor", "moving_floor", "sphere"):
        assert int((ENERGIES[name].hessian(x, mass, 0.37).abs().amax(dim=(1, 2)) > 0).sum()) >= 5, name
    H = ENERGIES["sphere"].hessian(x, mass, 0.0, project=False)
    assert float(torch.linalg.eigvalsh(H).min()) < -1.0


@pytest.mark.parametrize("name", sorted(ENERGIES))
def test_autograd_gradient_and_hessian_vector_products(name):
    """The energy is a differentiable torch expression; autograd agrees with the analytic gradient, and
    differentiating the analytic gradient (create_graph) gives the exact Hessian."""
    energy = ENERGIES[name]
    x, mass = points(30, seed=3)
    x = away_from_kink(energy, x, 0.37).requires_grad_(True)
    mass = mass[: x.shape[0]]
    (g_auto,) = torch.autograd.grad(energy.energy(x, mass, 0.37), x, create_graph=True)
    g = energy.gradient(x, mass, 0.37)
    assert torch.allclose(g_auto, g, atol=1e-9 * max(1.0, float(g.detach().abs().max())))
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(4), dtype=DT)
    if g.requires_grad:
        (hv,) = torch.autograd.grad((g * v).sum(), x)
    else:  # gravity: constant gradient
        hv = torch.zeros_like(x)
    H = energy.hessian(x.detach(), mass, 0.37, project=False)
    assert torch.allclose(hv, (H @ v[:, :, None])[..., 0], atol=1e-10 * K)


def test_gravity_closed_form_and_mass_derivative():
    x, mass = points(10, seed=5)
    mass = mass.requires_grad_(True)
    E = Gravity().energy(x, mass, 0.0)
    assert float(E.detach()) == pytest.approx(float((mass.detach() * 9.8 * x[:, 2]).sum()))
    (dm,) = torch.autograd.grad(E, mass)
    assert torch.allclose(dm, 9.8 * x[:, 2])
    g = Gravity().gradient(x, mass, 0.0)
    assert torch.allclose(g, torch.stack([0 * mass, 0 * mass, 9.8 * mass], 1))
    assert g.requires_grad  # differentiable w.r.t. the masses (the adjoint needs it)


def test_no_contact_means_zero_energy_gradient_and_hessian():
    x, mass = points(30, seed=6)
    x = x + torch.tensor([5.0, 0.0, 10.0], dtype=DT)  # far above and away from every obstacle
    for name in ("floor", "moving_floor", "sphere"):
        E, g, H = total_external([ENERGIES[name]], x, mass, 0.37)
        assert float(E) == 0.0 and not bool(g.any()) and not bool(H.any()), name


def test_floor_closed_form():
    x = torch.tensor([[0.0, 0.0, -0.8], [1.0, 2.0, -0.6], [0.0, 0.0, -0.7]], dtype=DT)
    floor = Floor(height=-0.7)
    m = torch.ones(3, dtype=DT)
    assert float(floor.energy(x, m, 0.0)) == pytest.approx(K * 0.1**2)
    assert torch.allclose(floor.gradient(x, m, 0.0)[:, 2], torch.tensor([-2 * K * 0.1, 0.0, 0.0], dtype=DT))
    assert torch.allclose(floor.hessian(x, m, 0.0)[:, 2, 2], torch.tensor([2 * K, 0.0, 0.0], dtype=DT))


def test_moving_floor_without_motion_equals_floor():
    x, mass = points(50, seed=7)
    floor, moving = Floor(height=-0.2, stiffness=3e4), MovingFloor(height=-0.2, stiffness=3e4)
    for t in TIMES:
        assert torch.allclose(moving.energy(x, mass, t), floor.energy(x, mass, t), rtol=1e-14)
        assert torch.allclose(moving.gradient(x, mass, t), floor.gradient(x, mass, t), rtol=1e-14, atol=0)
        assert torch.allclose(moving.hessian(x, mass, t), floor.hessian(x, mass, t), rtol=1e-14, atol=0)


@pytest.mark.parametrize("name", sorted(ENERGIES))
def test_energy_and_gradient_in_one_pass_equals_the_separate_calls(name):
    from vid2sim.physics.external import energy_and_gradient

    x, w = points(60, seed=11)
    energy = ENERGIES[name]
    for t in TIMES:
        E, g = energy_and_gradient(energy, x, w, t)
        assert torch.allclose(E, energy.energy(x, w, t), rtol=1e-13)
        assert torch.allclose(g, energy.gradient(x, w, t), rtol=1e-13, atol=1e-12)


def test_barrier_weights_scale_each_points_penalty():
    """Barriers take per-point weights: w = 1 is the paper's per-point penalty k Σ max(0, −s)²; surface
    samples weighted by their area make k a contact pressure per metre of penetration, so splitting one
    contact point into two half-weight points changes nothing."""
    x = torch.tensor([[0.0, 0.0, -0.8], [1.0, 2.0, -0.75], [0.0, 0.0, -0.6]], dtype=DT)
    w = torch.tensor([2.0, 0.5, 3.0], dtype=DT)
    for barrier in (Floor(height=-0.7), MovingFloor(height=-0.7), SphereObstacle(center=(0.0, 0.0, -2.0), radius=1.3)):
        depth = -barrier.signed_distance(x, 0.0).clamp(max=0.0)
        assert float(barrier.energy(x, w, 0.0)) == pytest.approx(float(K * (w * depth**2).sum()), rel=1e-12)
        split = torch.cat([x, x[:1]])
        w_split = torch.cat([w, w[:1]])
        w_split[0] = w_split[-1] = w[0] / 2
        assert float(barrier.energy(split, w_split, 0.0)) == pytest.approx(float(barrier.energy(x, w, 0.0)))
        H = barrier.hessian(x, w, 0.0, project=False)
        H1 = barrier.hessian(x, torch.ones_like(w), 0.0, project=False)
        assert torch.allclose(H, w[:, None, None] * H1)


def test_moving_floor_height_follows_its_schedule():
    mf = MovingFloor(height=-0.5, velocity=0.2, amplitude=0.1, frequency=2.0)
    x = torch.tensor([[0.3, -0.4, -0.45]], dtype=DT)
    m = torch.ones(1, dtype=DT)
    for t in (0.0, 0.1, 0.55, 1.0):
        h = -0.5 + 0.2 * t + 0.1 * math.sin(2 * math.pi * 2.0 * t)
        assert mf.height_at(t) == pytest.approx(h)
        assert float(mf.energy(x, m, t)) == pytest.approx(K * max(0.0, h + 0.45) ** 2, abs=1e-9)


def test_moving_floor_tilt_matches_a_rotation_of_the_up_vector():
    mf = MOVING
    axis = np.array(mf.tilt_axis) / np.linalg.norm(mf.tilt_axis)
    for t in TIMES:
        theta = math.radians(mf.tilt_deg + mf.tilt_rate_deg * t)
        n_ref = Rotation.from_rotvec(theta * axis).apply([0.0, 0.0, 1.0])
        assert np.allclose(mf.normal_at(t), n_ref, atol=1e-14)
        # the pivot lies on the plane; a point at distance δ along the normal has signed distance δ
        pivot = torch.tensor([[*mf.pivot_xy, mf.height_at(t)]], dtype=DT)
        n = torch.tensor(n_ref, dtype=DT)
        d = torch.tensor([-0.3, 0.0, 0.25], dtype=DT)
        s = mf.signed_distance(pivot + d[:, None] * n, t)
        assert torch.allclose(s, d, atol=1e-14)
        # a point displaced within the plane stays at distance 0
        tangent = torch.tensor(np.cross(n_ref, [0.3, 0.1, 0.5]), dtype=DT)
        assert abs(float(mf.signed_distance(pivot + tangent, t))) < 1e-14


def test_sphere_pushes_points_outward():
    sphere = ENERGIES["sphere"]
    x, mass = points(200, seed=8)
    c = torch.tensor(sphere.center, dtype=DT)
    inside = (x - c).norm(dim=1) < sphere.radius
    assert int(inside.sum()) > 20
    force = -sphere.gradient(x, mass, 0.0)
    radial = (force * (x - c)).sum(1)
    assert bool((radial[inside] > 0).all()) and not bool(force[~inside].any())
    # magnitude 2k w (r − d), along the radius
    d = (x - c).norm(dim=1)
    assert torch.allclose(force.norm(dim=1)[inside], 2 * K * mass[inside] * (sphere.radius - d[inside]))


def test_sphere_centre_is_finite():
    sphere = SphereObstacle(center=(0.0, 0.0, 0.0), radius=0.5)
    x = torch.zeros(2, 3, dtype=DT, requires_grad=True)
    m = torch.ones(2, dtype=DT)
    E = sphere.energy(x, m, 0.0)
    assert float(E.detach()) == pytest.approx(2 * K * 0.25)
    (g_auto,) = torch.autograd.grad(E, x)
    g = sphere.gradient(x, m, 0.0)
    assert bool(torch.isfinite(g_auto).all())
    assert torch.allclose(g, torch.tensor([[0.0, 0.0, -K]] * 2, dtype=DT))  # pushed along +z
    for project in (True, False):
        assert bool(torch.isfinite(sphere.hessian(x.detach(), m, 0.0, project=project)).all())


def test_total_external_sums_the_parts():
    x, mass = points(40, seed=9)
    parts = [ENERGIES["gravity"], ENERGIES["floor"], ENERGIES["moving_floor"], ENERGIES["sphere"]]
    E, g, H = total_external(parts, x, mass, 0.37)
    assert torch.allclose(E, sum(p.energy(x, mass, 0.37) for p in parts))
    assert torch.allclose(g, sum(p.gradient(x, mass, 0.37) for p in parts))
    assert torch.allclose(H, sum(p.hessian(x, mass, 0.37) for p in parts))
    assert float(torch.linalg.eigvalsh(H).min()) >= -1e-9 * K
    E0, g0, H0 = total_external([], x, mass, 0.0)
    assert float(E0) == 0.0 and g0.shape == (40, 3) and H0.shape == (40, 3, 3) and not bool(H0.any())


def test_float32_in_float32_out():
    x, mass = points(10, seed=10)
    E, g, H = total_external(list(ENERGIES.values()), x.float(), mass.float(), 0.37)
    assert E.dtype == g.dtype == H.dtype == torch.float32


def test_serialisation_round_trip():
    for energy in ENERGIES.values():
        assert isinstance(energy, ExternalEnergy)
        d = json.loads(json.dumps(energy.to_dict()))
        assert external_from_dict(d) == energy
        assert type(energy).from_dict(d) == energy
    assert Floor(height=-0.7).to_dict() == {"type": "floor", "height": -0.7, "stiffness": 1e5, "friction": 0.0,
                                            "friction_velocity": 1e-2}
    assert external_from_dict({"type": "floor", "height": 0, "friction": 0.4}) == Floor(0.0, friction=0.4)
    assert external_from_dict({"type": "sphere", "center": [0, 0, 1], "radius": 2}) == SphereObstacle(
        (0.0, 0.0, 1.0), 2.0
    )


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: SphereObstacle((0, 0, 0), 0.0), "SphereObstacle.radius must be > 0"),
        (lambda: SphereObstacle((0, 0, 0), -1.0), "SphereObstacle.radius must be > 0"),
        (lambda: SphereObstacle((0, 0), 1.0), r"SphereObstacle.center must have 3 components"),
        (lambda: SphereObstacle((0, float("nan"), 0), 1.0), r"SphereObstacle.center\[1\] must be finite"),
        (lambda: SphereObstacle((0, 0, 0), 1.0, stiffness=0.0), "SphereObstacle.stiffness must be > 0"),
        (lambda: Floor(height=float("inf")), "Floor.height must be finite"),
        (lambda: Floor(height="low"), "Floor.height must be a real number"),
        (lambda: Floor(height=0.0, stiffness=-1.0), "Floor.stiffness must be > 0"),
        (lambda: Floor(height=0.0, friction=-0.1), "Floor.friction must be a Coulomb coefficient >= 0"),
        (lambda: Floor(height=0.0, friction_velocity=0.0), "Floor.friction_velocity must be > 0"),
        (lambda: MovingFloor(0.0, friction=float("nan")), "MovingFloor.friction must be finite"),
        (lambda: SphereObstacle((0, 0, 0), 1.0, friction=-1), "SphereObstacle.friction must be a Coulomb"),
        (lambda: Gravity((0.0, -9.8)), "Gravity.acceleration must have 3 components"),
        (lambda: Gravity("down"), "Gravity.acceleration must be a sequence"),
        (lambda: MovingFloor(0.0, frequency=-1.0), "MovingFloor.frequency must be >= 0"),
        (lambda: MovingFloor(0.0, tilt_axis=(0, 0, 1)), "tilt_axis must be a nonzero horizontal vector"),
        (lambda: MovingFloor(0.0, tilt_axis=(0, 0, 0)), "tilt_axis must be a nonzero horizontal vector"),
        (lambda: MovingFloor(0.0, pivot_xy=(0, 0, 0)), "MovingFloor.pivot_xy must have 2 components"),
        (lambda: MovingFloor(0.0, velocity=float("nan")), "MovingFloor.velocity must be finite"),
        (lambda: external_from_dict({"type": "wall"}), "unknown external energy type 'wall'"),
        (lambda: external_from_dict([1, 2]), "must be a mapping"),
        (lambda: external_from_dict({"type": "floor", "height": 0, "hieght": 1}), r"unknown floor config field"),
        (lambda: Floor.from_dict({"type": "sphere", "height": 0}), "does not match"),
    ],
)
def test_bad_parameters_raise_clear_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_inputs_raise_clear_errors():
    x, mass = points(5, seed=11)
    floor = Floor(0.0)
    with pytest.raises(ValueError, match=r"positions x must have shape \(N, 3\)"):
        floor.energy(x[:, :2], mass, 0.0)
    with pytest.raises(ValueError, match=r"per-point weights must have shape \(5,\)"):
        floor.gradient(x, mass[:3], 0.0)
    with pytest.raises(ValueError, match="time t must be finite"):
        MOVING.energy(x, mass, float("nan"))
    with pytest.raises(ValueError, match=r"per-point weights must have shape"):
        total_external([Gravity()], x, mass[None], 0.0)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    x, mass = points(40, seed=12)
    parts = list(ENERGIES.values())
    cpu = total_external(parts, x, mass, 0.37)
    gpu = total_external(parts, x.cuda(), mass.cuda(), 0.37)
    for a, b in zip(cpu, gpu):
        assert b.device.type == "cuda" and torch.allclose(a, b.cpu(), rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("name", ["floor", "moving_floor", "sphere"])
@pytest.mark.parametrize("t", TIMES)
def test_distance_derivatives_are_those_of_the_signed_distance(name, t):
    """(s, ∂s/∂x, ∂²s/∂x²) of every barrier (the contact dashpot's geometry) against autograd of
    ``signed_distance``."""
    barrier = ENERGIES[name]
    x, _ = points(40, seed=5)
    s, ds, curvature = barrier.distance_derivatives(x, t)
    assert torch.allclose(s, barrier.signed_distance(x, t), atol=1e-14)
    xg = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(barrier.signed_distance(xg, t).sum(), xg, create_graph=True)
    assert torch.allclose(ds, grad, atol=1e-12)
    if grad.requires_grad:
        hess = torch.stack([torch.autograd.grad(grad[:, c].sum(), xg, retain_graph=True)[0] for c in range(3)], dim=1)
    else:  # a plane: the gradient is a constant of x
        hess = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    if curvature is None:
        assert float(hess.abs().max()) == 0.0
    else:
        assert torch.allclose(curvature, hess, atol=1e-10) and float(hess.abs().max()) > 0


@pytest.mark.parametrize("t", TIMES)
def test_surface_velocity_is_that_of_the_moving_planes_material_points(t):
    """A point riding on the moving floor (carried by its pivot's climb and turned with its tilt about the axis
    through the pivot) moves at ``surface_velocity``: central differences of its path over ±δ; the fixed
    barriers' surfaces stand still."""
    x, _ = points(12, seed=21)
    axis = np.array(MOVING.tilt_axis) / np.linalg.norm(MOVING.tilt_axis)

    def carried(tt: float) -> np.ndarray:
        turn = Rotation.from_rotvec(math.radians(MOVING.tilt_rate_deg) * (tt - t) * axis).as_matrix()
        pivot = lambda time: np.array([*MOVING.pivot_xy, MOVING.height_at(time)])  # noqa: E731
        return pivot(tt) + (x.numpy() - pivot(t)) @ turn.T

    delta = 1e-6
    expected = (carried(t + delta) - carried(t - delta)) / (2 * delta)
    assert np.allclose(MOVING.surface_velocity(x, t).numpy(), expected, atol=1e-7)
    s0 = MOVING.signed_distance(torch.from_numpy(carried(t + delta)), t + delta)
    assert torch.allclose(s0, MOVING.signed_distance(x, t), atol=1e-9)  # riding points keep their distance
    for fixed in (ENERGIES["floor"], ENERGIES["sphere"]):
        assert torch.equal(fixed.surface_velocity(x, t), torch.zeros_like(x))
