"""The modal skinning objective: the subspace's stiffness and mass, its Ritz eigenvalues, and training."""

import functools
import math

import numpy as np
import pytest
import torch
from scipy.linalg import eigh

from vid2sim.physics.materials import lame_parameters, neo_hookean_energy_density
from vid2sim.physics.modes import subspace_frequencies, subspace_stiffness_and_mass
from vid2sim.physics.reduced import ElasticBasis, lbs_rows
from vid2sim.physics.skinning import SkinningField, gradient_basis
from vid2sim.physics.skinning_training import (
    SkinningTrainingConfig,
    modal_loss,
    train_skinning,
)

BAR = (2.0, 0.4, 0.4)
BAR_VOLUME = BAR[0] * BAR[1] * BAR[2]


def _bar(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(BAR, dtype=torch.float64)


def _field(handles: int = 3) -> SkinningField:
    return SkinningField(num_handles=handles, seed=1).double()


def _ritz(K: torch.Tensor, M: torch.Tensor) -> np.ndarray:
    return eigh(K.detach().numpy(), M.detach().numpy(), eigvals_only=True)


def test_stiffness_and_mass_are_the_hessians_of_neo_hookean_and_kinetic_energy_at_rest():
    X = _bar(40, 0)
    field = _field()
    with torch.no_grad():
        w, dw = field.weights_and_gradients(X)
    nu, volume = 0.35, 0.7
    K, M = subspace_stiffness_and_mass(X, w, dw, volume, nu)
    mu, lam = lame_parameters(1.0, nu)
    basis = ElasticBasis(torch.eye(3, dtype=X.dtype).expand(len(X), 3, 3), gradient_basis(X, w, dw), None)
    b = lbs_rows(X, w)

    def elastic(y):
        return neo_hookean_energy_density(basis.deformation_gradient(y), mu, lam).sum() * (volume / len(X))

    def kinetic(y):  # ½ Σ_p v |Y b_p|² (unit density): its Hessian is the mass matrix
        return 0.5 * ((y.reshape(3, -1) @ b.T) ** 2).sum() * (volume / len(X))

    y0 = torch.zeros(K.shape[0], dtype=X.dtype)
    assert torch.allclose(K, torch.autograd.functional.hessian(elastic, y0), rtol=1e-9, atol=1e-12)
    assert torch.allclose(M, torch.autograd.functional.hessian(kinetic, y0), rtol=1e-12, atol=1e-15)


def test_ritz_values_depend_on_the_subspace_only_and_the_loss_sums_them():
    X = _bar(300, 1)
    field = _field(3)
    with torch.no_grad():
        w, dw = field.weights_and_gradients(X)
    K, M = subspace_stiffness_and_mass(X, w, dw, BAR_VOLUME, 0.3)
    lam = _ritz(K, M)
    # mix the learned weight functions (the rigid column stays 1): same span, same Ritz values
    R = torch.tensor([[1.0, 0.3, -0.2], [0.5, 2.0, 0.1], [-0.4, 0.2, 0.7]], dtype=X.dtype)
    wm, dwm = w.clone(), dw.clone()
    wm[:, :3] = w[:, :3] @ R
    dwm[:, :3] = torch.einsum("pjc,jk->pkc", dw[:, :3], R)
    Km, Mm = subspace_stiffness_and_mass(X, wm, dwm, BAR_VOLUME, 0.3)
    assert np.allclose(_ritz(Km, Mm), lam, rtol=1e-7, atol=1e-9 * lam.max())
    # six rigid motions cost nothing
    assert np.sum(np.abs(lam) < 1e-8 * lam.max()) == 6
    alpha = 2.5
    expected = -np.sum(alpha / (np.clip(lam, 0, None) + alpha))
    assert float(modal_loss(K, M, alpha)) == pytest.approx(expected, rel=1e-6)  # K + αM carries a 1e-12 ridge


def test_the_modal_loss_leaves_out_a_direction_the_subspace_spans_twice():
    """On a bar, the handles w = x and w = x² give LBS columns x·x and x²·1 that coincide: the subspace's mass and
    stiffness are singular. In float64 the loss's 1e-12 ridge copes; in float32 (a reconstruction's field) that ridge
    is below the precision and the Cholesky failed (a seed-3 benchmark scene's rod stopped there). The ridge at the
    dtype's precision leaves the doubled direction out: the float32 loss is the float64 one."""
    X = _bar(400, 2)
    x = X[:, :1]
    zero = torch.zeros_like(x)
    w = torch.cat([x, x * x, torch.ones_like(x)], dim=1)  # two learned handles and the rigid column
    dw = torch.stack([torch.cat([torch.ones_like(x), zero, zero], 1), torch.cat([2 * x, zero, zero], 1),
                      torch.zeros(len(X), 3, dtype=X.dtype)], dim=1)
    K, M = subspace_stiffness_and_mass(X, w, dw, BAR_VOLUME, 0.3)
    assert np.sum(np.abs(np.linalg.eigvalsh(M.numpy())) < 1e-12 * float(M.diagonal().max())) >= 3  # x·x = x²·1, ×3
    alpha = 2.5
    exact = float(modal_loss(K, M, alpha, trace_weight=1e-2))
    assert math.isfinite(exact)
    single = float(modal_loss(K.float(), M.float(), alpha, trace_weight=1e-2))
    assert single == pytest.approx(exact, rel=1e-3)


class _GivenWeights:
    """A stand-in skinning field with given weight functions of x: ``weights_and_gradients`` as the field's."""

    def __init__(self, *functions):
        self.functions = functions  # each x ↦ (w, dw/dx)

    def weights_and_gradients(self, X):
        x = X[:, :1]
        w = torch.cat([f(x)[0] for f in self.functions] + [torch.ones_like(x)], dim=1)
        dw = torch.stack([torch.cat([f(x)[1], torch.zeros_like(x), torch.zeros_like(x)], 1) for f in self.functions]
                         + [torch.zeros(len(X), 3, dtype=X.dtype)], dim=1)
        return w, dw


def test_the_subspace_frequencies_of_a_handle_given_twice_are_those_of_it_once():
    """A handle given twice spans its four columns twice: the mass is singular there (and the stiffness), and the
    Ritz values are those of the subspace with it once — also for the two-factor calibration's pencil, which failed
    on a seed-3 benchmark scene's rod (scipy: the mass is not positive definite)."""
    from vid2sim.physics.modes import stiffness_calibration_curve

    X = _bar(500, 3)
    volumes = torch.full((500,), BAR_VOLUME / 500, dtype=torch.float64)
    linear = (lambda x: (x, torch.ones_like(x)))
    square = (lambda x: (x * x - 1 / 3, 2 * x))
    once = subspace_frequencies(_GivenWeights(linear, square), X, volumes, 1.0, 0.3, 1.0, k=6)
    twice = subspace_frequencies(_GivenWeights(linear, square, square), X, volumes, 1.0, 0.3, 1.0, k=6)
    np.testing.assert_allclose(twice, once, rtol=1e-8)
    # "tets" whose six lowest modes are 0.9 × the subspace's at ν = 0.3 and 0.35: both factors come out 0.81
    at_35 = subspace_frequencies(_GivenWeights(linear, square), X, volumes, 1.0, 0.35, 1.0, k=6)
    reference = np.stack([0.9 * once, 0.9 * at_35])
    for weights in ((linear, square), (linear, square, square)):
        curve = stiffness_calibration_curve(_GivenWeights(*weights), X, volumes, None, None, (0.3, 0.35), factors=2,
                                            reference=reference)
        assert curve.scale[0] == pytest.approx(0.81, rel=1e-5) and curve.lam_scale[0] == pytest.approx(0.81, rel=1e-4)


@functools.lru_cache(maxsize=None)
def _trained_bar(objective: str, n: int) -> SkinningField:
    """A 4-handle field trained for 150 iterations (500 points a step) on ``_bar(n, 0)`` (made once per module).
    At 300 iterations the figures below were modal 0.968, random_z 1.262, 300-point in-sample 0.10; at 150 they are
    0.978, 1.210 and 0.28 (× Euler–Bernoulli) in half the time."""
    field = SkinningField(num_handles=4, seed=0).double()
    train_skinning(field, _bar(n, 0), SkinningTrainingConfig(iterations=150, points_per_step=min(n, 500),
                                                             objective=objective), progress=False, volume=BAR_VOLUME)
    return field


def _lowest(field: SkinningField, X: torch.Tensor) -> float:
    """The subspace's lowest non-rigid frequency on the points ``X`` over Euler–Bernoulli's first free–free bending
    frequency ω = 4.730² √(E I / (ρ A L⁴)) of the bar."""
    omega_eb = 4.730**2 * math.sqrt(BAR[1] ** 2 / 12 / BAR[0] ** 4)
    with torch.no_grad():
        w, dw = field.weights_and_gradients(X)
        lam = _ritz(*subspace_stiffness_and_mass(X, w, dw, BAR_VOLUME, 0.3))
    return math.sqrt(lam[lam > 1e-8 * lam.max()][0]) / omega_eb


def test_modal_training_finds_the_bending_mode_the_paper_objective_misses():
    """A free 2 × 0.4 × 0.4 bar, 4 handles, 150 iterations on 20 000 points. The subspace's lowest frequency
    (Rayleigh–Ritz, quadrature on 20 000 independent points) is compared with Euler–Bernoulli's first free–free bending
    frequency, ω = 4.730² √(E I / (ρ A L⁴)). The continuum lies a few percent below Euler–Bernoulli (shear
    and rotary inertia at slenderness 5), and every subspace lies above the continuum."""
    lowest = {objective: _lowest(_trained_bar(objective, 20000), _bar(20000, 1)) for objective in ("random_z", "modal")}
    assert 0.85 < lowest["modal"] < 1.08, lowest  # measured 0.978
    assert lowest["random_z"] > 1.15 * lowest["modal"], lowest  # measured 1.210 (1.24 ×)


def test_modal_training_on_too_few_points_overfits_them():
    """The modal objective rewards low Ritz values on the points it is trained on. On a 300-point set the
    network finds a subspace that is nearly free *on those points* (in-sample lowest frequency ≈ 0.3 × Euler–
    Bernoulli) and stiff between them (≈ 1.2 × on independent points). Trained on a 20 000-point pool, the two
    agree — why ``bench identify`` trains on ``skinning_points`` = 30 000 and the pipeline on its 20 000
    interior samples."""
    Q = _bar(20000, 1)
    for n in (300, 20000):
        field = _trained_bar("modal", n)  # the 20 000-point field is the one the test above judges
        in_sample, independent = _lowest(field, _bar(n, 0)), _lowest(field, Q)
        if n == 300:
            assert in_sample < 0.5 * independent, (in_sample, independent)
        else:
            assert in_sample == pytest.approx(independent, rel=0.03)
            assert 0.85 < independent < 1.08


def test_config_rejects_unknown_objective_and_bad_modal_settings():
    with pytest.raises(ValueError, match="objective must be one of"):
        SkinningTrainingConfig(objective="eigen")
    with pytest.raises(ValueError, match="modal_shift"):
        SkinningTrainingConfig(modal_shift=0.0)
    with pytest.raises(ValueError, match="modal_orthogonality_weight"):
        SkinningTrainingConfig(modal_orthogonality_weight=-1.0)


def test_subspace_frequencies_are_the_scaled_ritz_values_of_the_simulators_quadrature():
    X = _bar(300, 1)
    field = _field(3)
    with torch.no_grad():
        w, dw = field.weights_and_gradients(X)
    lam = _ritz(*subspace_stiffness_and_mass(X, w, dw, BAR_VOLUME, 0.3))
    volumes = torch.full((300,), BAR_VOLUME / 300, dtype=X.dtype)
    omega = subspace_frequencies(field, X, volumes, 4.0, 0.3, 1.0, k=6)
    assert np.allclose(omega, 2.0 * np.sqrt(lam[6:12]), rtol=1e-8)
    # K and M share the quadrature: scaling every weight leaves the frequencies; reweighting moves them
    assert np.allclose(subspace_frequencies(field, X, 3 * volumes, 4.0, 0.3, 1.0, k=6), omega, rtol=1e-8)
    uneven = volumes * torch.linspace(0.5, 1.5, 300, dtype=X.dtype)
    assert not np.allclose(subspace_frequencies(field, X, uneven, 4.0, 0.3, 1.0, k=6), omega, rtol=1e-3)
    with pytest.raises(ValueError, match="k = 200"):
        subspace_frequencies(field, X, volumes, 4.0, 0.3, 1.0, k=200)


def test_stiffness_calibration_brings_the_subspaces_lowest_mode_to_the_tets():
    """The modal subspace of a free bar lies above quadratic tets (Rayleigh–Ritz); the calibration factor s is
    (ω_tets / ω_subspace)² < 1, and at E·s the subspace's lowest frequency is the tets' at E, for any E, ρ."""
    from vid2sim.meshing.tetra import box_tet_mesh
    from vid2sim.physics.modes import stiffness_calibration
    from vid2sim.physics.tet_modes import tet_frequencies

    mesh = box_tet_mesh(BAR, (10, 2, 2))
    field = _trained_bar("modal", 20000)
    cubature = _bar(4000, 2)
    volumes = torch.full((4000,), BAR_VOLUME / 4000, dtype=cubature.dtype)
    s = stiffness_calibration(field, cubature, volumes, mesh.vertices, mesh.tets, 0.3)
    assert 0.5 < s < 1.0
    for E, rho in ((1.0, 1.0), (3e5, 800.0)):
        tets = tet_frequencies(mesh.vertices, mesh.tets, E, 0.3, rho, k=1, order=2)[0]
        assert subspace_frequencies(field, cubature, volumes, E * s, 0.3, rho, k=1)[0] == pytest.approx(tets, rel=1e-8)


def test_two_factor_curve_matches_six_modes_better_than_one_factor_and_the_simulator_uses_it():
    """Two factors (μ by s, λ by s_λ) per ν: the lowest mode stays on the tets' (weighted), the six lowest
    modes agree better than with one factor on the whole energy, the locking shows as s_λ < s at high ν, and
    ``Simulator.lame()`` applies the two factors, differentiably in ν."""
    from vid2sim.meshing.tetra import box_tet_mesh
    from vid2sim.physics import Material, SimConfig, Simulator
    from vid2sim.physics.modes import (
        CURVE_NUS,
        stiffness_calibration_curve,
        subspace_stiffness_parts,
    )
    from vid2sim.physics.tet_modes import tet_frequency_curve

    mesh = box_tet_mesh(BAR, (10, 2, 2))
    field = _trained_bar("modal", 20000)
    cubature = _bar(1500, 2)
    volumes = torch.full((1500,), BAR_VOLUME / 1500, dtype=cubature.dtype)
    nus = (0.2, 0.35, 0.45)
    one = stiffness_calibration_curve(field, cubature, volumes, mesh.vertices, mesh.tets, nus)
    two = stiffness_calibration_curve(field, cubature, volumes, mesh.vertices, mesh.tets, nus, factors=2)
    assert one.lam_scale is None and two.lam_scale is not None
    with torch.no_grad():
        w, dw = field.weights_and_gradients(cubature)
        K_mu, K_lam, M = subspace_stiffness_parts(cubature, w, dw, 1.0, volumes)
    K, M1 = subspace_stiffness_and_mass(cubature, w, dw, 1.0, 0.3, weights=volumes)
    mu3, lam3 = lame_parameters(1.0, 0.3)
    assert torch.allclose(mu3 * K_mu + lam3 * K_lam, K) and torch.equal(M, M1)
    reference = tet_frequency_curve(mesh.vertices, mesh.tets, nus, k=6, order=2)  # what the calibration matches
    rms: dict[str, list[float]] = {"one": [], "two": []}
    for nu, ref in zip(nus, reference):
        mu, lam = lame_parameters(1.0, nu)
        errors = {}
        for name, s_mu, s_lam in (("one", one.at(nu), one.at(nu)), ("two", two.at(nu), two.lam_at(nu))):
            omega = np.sqrt(_ritz(s_mu * mu * K_mu + s_lam * lam * K_lam, M)[6:12])
            errors[name] = np.log(omega / ref)
            rms[name].append(float(np.sqrt((errors[name] ** 2).mean())))
        assert abs(errors["one"][0]) < 1e-6 and abs(errors["two"][0]) < 5e-3
    # over the grid (the fit trades a little at one ν for smoothness across them)
    assert np.mean(rms["two"]) < np.mean(rms["one"])
    assert two.lam_at(0.45) < two.at(0.45)  # λ carries the locking
    # on a fine grid towards ν = ½ the fits follow one branch (each starts from the last): the locking grows
    # smoothly, s rising and s_λ falling
    fine = stiffness_calibration_curve(field, cubature, volumes, mesh.vertices, mesh.tets,
                                       (0.3, 0.4, 0.43, 0.46, 0.48, 0.49), factors=2)
    assert np.all(np.diff(fine.scale) > 0) and np.all(np.diff(fine.lam_scale) < 0)
    # the whole grid, ν = 0 included, where λ vanishes and the modes do not determine s_λ: it follows s there
    # instead of running to a bound, and between grid values the interpolated factors still match the lowest
    # mode (the tets' frequency interpolated linearly in ν)
    whole_reference = tet_frequency_curve(mesh.vertices, mesh.tets, CURVE_NUS, k=6, order=2)
    whole = stiffness_calibration_curve(field, cubature, volumes, None, None, CURVE_NUS, factors=2,
                                        reference=whole_reference)
    assert 1 / 3 < whole.lam_at(0.0) / whole.at(0.0) < 3
    for nu in (0.5 * (a + b) for a, b in zip(CURVE_NUS, CURVE_NUS[1:])):
        mu, lam = lame_parameters(1.0, nu)
        lowest = math.sqrt(_ritz(whole.at(nu) * mu * K_mu + whole.lam_at(nu) * lam * K_lam, M)[6])
        assert abs(math.log(lowest / np.interp(nu, CURVE_NUS, whole_reference[:, 0]))) < 5e-3, nu
    # the same branch for a slightly different mesh: 0.5 % noise on the tets' frequencies moves the factors a
    # little (fitted ν by ν, such noise moved log s_λ by up to 8 on benchmark solids)
    rng = np.random.default_rng(0)
    for _ in range(2):
        noisy = whole_reference * np.exp(0.005 * rng.standard_normal(whole_reference.shape))
        other = stiffness_calibration_curve(field, cubature, volumes, None, None, CURVE_NUS, factors=2,
                                            reference=noisy)
        assert np.abs(np.log(np.array(other.lam_scale) / whole.lam_scale)).max() < math.log(2)
        assert np.abs(np.log(np.array(other.scale) / whole.scale)).max() < 0.05
    sim = Simulator(field, cubature, volumes, Material(2e5, 0.35), [], SimConfig(), stiffness_scale=two)
    mu, lam = sim.lame()
    mu0, lam0 = lame_parameters(2e5, 0.35)
    assert float(mu) == pytest.approx(two.at(0.35) * mu0, rel=1e-10)
    assert float(lam) == pytest.approx(two.lam_at(0.35) * lam0, rel=1e-10)
    sim.nu = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)  # between grid values (C¹ there)
    (g,) = torch.autograd.grad(sim.lame()[1], sim.nu)
    h = 1e-6

    def lam_at(nu: float) -> float:
        with torch.no_grad():
            sim.nu = torch.tensor(nu, dtype=torch.float64)
            return float(sim.lame()[1])

    assert float(g) == pytest.approx((lam_at(0.4 + h) - lam_at(0.4 - h)) / (2 * h), rel=1e-6)
    with pytest.raises(ValueError, match="factors must be 1"):
        stiffness_calibration_curve(field, cubature, volumes, mesh.vertices, mesh.tets, nus, factors=3)
