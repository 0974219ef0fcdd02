"""Return maps (vid2sim.physics.plasticity) checked against the paper's yield conditions and invariances."""

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vid2sim.physics.plasticity import (
    DruckerPrager,
    VonMises,
    plasticity_from_dict,
    return_map,
    rotation_svd,
    update_plastic_state,
    yield_function,
)

DT = torch.float64
MU, LAM = 4.0e3, 6.0e3
VM = VonMises(yield_stress=500.0)  # τ_Y/(2μ) = 0.0625
DP = DruckerPrager(friction_angle_deg=10.0)


def rotations(n: int, seed: int) -> torch.Tensor:
    """(n, 3, 3) uniformly random rotations (scipy)."""
    return torch.tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=DT)


def from_strain(eps: torch.Tensor, seed: int) -> torch.Tensor:
    """F = R1 diag(exp ε) R2 for Hencky strains ε: (N, 3)."""
    n = eps.shape[0]
    return rotations(n, seed) @ torch.diag_embed(torch.exp(eps)) @ rotations(n, seed + 1000)


def hencky(F: torch.Tensor):
    """(ε̂ norm, tr ε, deviatoric direction sorted) via numpy's SVD, independent of the module's SVD."""
    s = np.linalg.svd(F.numpy(), compute_uv=False)
    eps = np.log(s)
    tr = eps.sum(1)
    dev = eps - tr[:, None] / 3
    return np.linalg.norm(dev, axis=1), tr, dev


def polar_rotation(F: torch.Tensor) -> np.ndarray:
    U, _, Vh = np.linalg.svd(F.numpy())
    return U @ Vh


def test_rotation_svd_gives_rotations_and_positive_singular_values():
    gen = torch.Generator().manual_seed(0)
    F = torch.eye(3, dtype=DT) + 0.6 * torch.randn(64, 3, 3, generator=gen, dtype=DT)
    F = F[torch.linalg.det(F) > 0.05]
    # LAPACK returns reflection pairs (det U = det V = −1) for these: the sign fix is exercised
    special = torch.stack([
        torch.diag(torch.tensor([1.0, 2.0, 3.0], dtype=DT)),
        torch.diag(torch.tensor([-1.0, -2.0, 3.0], dtype=DT)),
        torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=DT),
    ])
    F = torch.cat([F, special])
    U, S, V = rotation_svd(F)
    assert torch.allclose(torch.linalg.det(U), torch.ones(F.shape[0], dtype=DT))
    assert torch.allclose(torch.linalg.det(V), torch.ones(F.shape[0], dtype=DT))
    assert bool((S > 0).all())
    assert torch.allclose((U * S[:, None, :]) @ V.transpose(1, 2), F, atol=1e-12)
    _, _, Vh_raw = torch.linalg.svd(special)
    assert bool((torch.linalg.det(Vh_raw) < 0).all())


def test_alpha_matches_the_paper():
    s = math.sin(math.radians(10.0))
    assert DP.alpha == pytest.approx(math.sqrt(2 / 3) * 2 * s / (3 - s))


def test_states_inside_the_yield_surface_are_unchanged():
    gen = torch.Generator().manual_seed(1)
    dev = torch.randn(10, 3, generator=gen, dtype=DT)
    dev = dev - dev.mean(1, keepdim=True)
    dev = 0.05 * dev / dev.norm(dim=1, keepdim=True)  # ‖ε̂‖ = 0.05 < 0.0625
    eps = dev + torch.linspace(-0.1, 0.1, 10, dtype=DT)[:, None]
    F = from_strain(eps, seed=2)
    assert bool((yield_function(VM, F, MU, LAM) < 0).all())
    assert torch.equal(return_map(VM, F, MU, LAM), F)
    # Drucker–Prager, compressed inside the cone: tr ε = −0.3, ‖ε̂‖ = 0.05 < α(3λ+2μ)·0.3/(2μ) ≈ 0.131
    F = from_strain(dev - 0.1, seed=3)
    assert bool((yield_function(DP, F, MU, LAM) < 0).all())
    assert torch.equal(return_map(DP, F, MU, LAM), F)


def test_von_mises_analytic_diagonal_case():
    eps = torch.tensor([0.3, -0.1, -0.2], dtype=DT) + 0.05  # ε̂ = (0.3, −0.1, −0.2), tr ε = 0.15
    F = torch.diag(torch.exp(eps))[None]
    dev = torch.tensor([0.3, -0.1, -0.2], dtype=DT)
    target = 500.0 / (2 * MU)
    expected = torch.diag(torch.exp(0.05 + dev * target / dev.norm()))[None]
    assert torch.allclose(return_map(VM, F, MU, LAM), expected, atol=1e-14)


def test_von_mises_projects_onto_the_yield_surface_and_keeps_volume():
    gen = torch.Generator().manual_seed(4)
    eps = 0.4 * torch.randn(40, 3, generator=gen, dtype=DT)
    F = from_strain(eps, seed=5)
    norm0, tr0, dev0 = hencky(F)
    yielded = norm0 > 500.0 / (2 * MU)
    assert yielded.sum() > 30
    out = return_map(VM, F, MU, LAM)
    norm1, tr1, dev1 = hencky(out)
    assert np.allclose(norm1[yielded], 500.0 / (2 * MU), atol=1e-6)
    assert np.allclose(tr1, tr0, atol=1e-10)  # volumetric part unchanged
    # deviatoric direction kept (sorted singular values keep their order), and the polar rotation too
    assert np.allclose(dev1 / norm1[:, None], dev0 / norm0[:, None], atol=1e-9)
    assert np.allclose(polar_rotation(out), polar_rotation(F), atol=1e-9)
    # projection: a second application changes nothing measurable
    assert torch.allclose(return_map(VM, out, MU, LAM), out, atol=1e-12)


@pytest.mark.parametrize("model", [VM, DP], ids=["von_mises", "drucker_prager"])
def test_return_map_is_isotropic(model):
    gen = torch.Generator().manual_seed(6)
    F = from_strain(0.4 * torch.randn(20, 3, generator=gen, dtype=DT), seed=7)
    R, Q = rotations(20, 8), rotations(20, 9)
    out = return_map(model, F, MU, LAM)
    assert torch.allclose(return_map(model, R @ F, MU, LAM), R @ out, atol=1e-11)
    assert torch.allclose(return_map(model, F @ Q, MU, LAM), out @ Q, atol=1e-11)


def test_drucker_prager_expansion_releases_all_elastic_strain():
    gen = torch.Generator().manual_seed(10)
    eps = 0.2 * torch.randn(20, 3, generator=gen, dtype=DT)
    eps = eps - eps.mean(1, keepdim=True) + 0.05  # tr ε = 0.15 > 0
    F = from_strain(eps, seed=11)
    out = return_map(DP, F, MU, LAM)
    eye = torch.eye(3, dtype=DT).expand(20, 3, 3)
    assert torch.allclose(out.transpose(1, 2) @ out, eye, atol=1e-12)  # a pure rotation …
    assert torch.allclose(torch.linalg.det(out), torch.ones(20, dtype=DT))
    assert np.allclose(out.numpy(), polar_rotation(F), atol=1e-12)  # … namely U Vᵀ


def test_drucker_prager_compression_outside_the_cone_lands_on_the_cone():
    gen = torch.Generator().manual_seed(12)
    dev = torch.randn(30, 3, generator=gen, dtype=DT)
    dev = dev - dev.mean(1, keepdim=True)
    dev = 0.3 * dev / dev.norm(dim=1, keepdim=True)
    tr = -torch.linspace(0.01, 0.2, 30, dtype=DT)
    F = from_strain(dev + tr[:, None] / 3, seed=13)
    cone = -DP.alpha * (3 * LAM + 2 * MU) * tr.numpy() / (2 * MU)
    assert (0.3 > cone).all()  # every point starts outside
    out = return_map(DP, F, MU, LAM)
    norm1, tr1, _ = hencky(out)
    assert np.allclose(tr1, tr.numpy(), atol=1e-10)
    assert np.allclose(norm1, cone, atol=1e-9)  # δγ(out) = 0
    assert torch.allclose(yield_function(DP, out, MU, LAM), torch.zeros(30, dtype=DT), atol=1e-9)
    assert np.allclose(polar_rotation(out), polar_rotation(F), atol=1e-9)


def test_degenerate_and_extreme_states_do_not_produce_nan():
    s = torch.tensor([0.5, 1.0, 2.0], dtype=DT)
    dilations = torch.eye(3, dtype=DT) * s[:, None, None]  # ε̂ = 0 exactly
    assert torch.equal(return_map(VM, dilations, MU, LAM), dilations)
    dp = return_map(DP, dilations, MU, LAM)
    assert torch.equal(dp[:2], dilations[:2])  # tr ε ≤ 0, δγ ≤ 0
    assert torch.allclose(dp[2], torch.eye(3, dtype=DT))  # expansion → U Vᵀ = I
    extreme = from_strain(torch.tensor([[-12.0, 3.0, 4.0], [8.0, -9.0, 0.5]], dtype=DT), seed=14)
    for model in (VM, DP):
        out = return_map(model, extreme, MU, LAM)
        assert bool(torch.isfinite(out).all()) and bool((torch.linalg.det(out) > 0).all())


def test_float32_and_parameter_tensors():
    F = from_strain(0.3 * torch.randn(6, 3, generator=torch.Generator().manual_seed(15), dtype=DT), seed=16)
    mu = torch.tensor(MU, requires_grad=True)
    out32 = return_map(VM, F.float(), mu, torch.tensor(LAM))
    assert out32.dtype == torch.float32 and not out32.requires_grad
    assert torch.allclose(out32.double(), return_map(VM, F, MU, LAM), atol=1e-5)
    # per-point Lamé parameters: (N,)
    mus = torch.full((6,), MU, dtype=DT)
    assert torch.allclose(return_map(VM, F, mus, LAM), return_map(VM, F, MU, LAM))


@pytest.mark.parametrize("model", [VM, DP], ids=["von_mises", "drucker_prager"])
def test_update_plastic_state_keeps_F_equal_to_Fe_Fp(model):
    gen = torch.Generator().manual_seed(17)
    Fp = from_strain(0.1 * torch.randn(25, 3, generator=gen, dtype=DT), seed=18)
    Fe_trial = from_strain(
        0.3 * torch.randn(25, 3, generator=gen, dtype=DT) * torch.linspace(0, 1, 25, dtype=DT)[:, None], seed=19
    )
    F, Fp_inv = Fe_trial @ Fp, torch.linalg.inv(Fp)  # trial elastic strains from 0 to large
    new = update_plastic_state(model, F, Fp_inv, MU, LAM)
    Fe = return_map(model, F @ Fp_inv, MU, LAM)
    assert torch.allclose(Fe @ torch.linalg.inv(new), F, atol=1e-12)  # F = F_e F_p
    assert torch.allclose(F @ new, Fe, atol=1e-12)
    elastic = (Fe == F @ Fp_inv).flatten(1).all(1)
    assert bool(elastic.any()) and not bool(elastic.all())
    assert torch.equal(new[elastic], Fp_inv[elastic])  # untouched where nothing yielded


def test_von_mises_plastic_flow_is_isochoric_and_persists():
    """Large simple shear: the plastic part absorbs the excess (det F_p = 1), the elastic part sits on the
    yield surface, and holding the same F afterwards yields no further."""
    gamma = torch.tensor([0.5, 1.0], dtype=DT)
    F = torch.eye(3, dtype=DT).repeat(2, 1, 1)
    F[:, 0, 1] = gamma
    Fp_inv = torch.eye(3, dtype=DT).repeat(2, 1, 1)
    new = update_plastic_state(VM, F, Fp_inv, MU, LAM)
    assert torch.allclose(torch.linalg.det(new), torch.ones(2, dtype=DT), atol=1e-12)
    norm, _, _ = hencky(F @ new)
    assert np.allclose(norm, 500.0 / (2 * MU), atol=1e-9)
    again = update_plastic_state(VM, F, new, MU, LAM)
    assert torch.allclose(again, new, atol=1e-12)
    # unloading in one step to the rest shape F = I overshoots the elastic range and re-yields in
    # reverse: the elastic part is back on the yield surface and a permanent set F_p ≠ I remains
    # (with ‖ε̂(F_p)‖ = ‖ε̂(F_e⁻¹)‖ = τ_Y/2μ)
    rest = torch.eye(3, dtype=DT).repeat(2, 1, 1)
    after = update_plastic_state(VM, rest, new, MU, LAM)
    norm_rest, _, _ = hencky(after)
    assert np.allclose(norm_rest, 500.0 / (2 * MU), atol=1e-9)
    Fp_final = torch.linalg.inv(after)
    norm_fp, _, _ = hencky(Fp_final)
    assert np.allclose(norm_fp, 500.0 / (2 * MU), atol=1e-9)
    assert torch.allclose(torch.linalg.det(Fp_final), torch.ones(2, dtype=DT), atol=1e-12)


def test_serialisation_round_trip():
    for model in (VM, DP, VonMises(123.0), DruckerPrager(35.0)):
        d = json.loads(json.dumps(model.to_dict()))
        assert plasticity_from_dict(d) == model
        assert type(model).from_dict(d) == model


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: VonMises(0.0), "yield_stress must be > 0"),
        (lambda: VonMises(-1.0), "yield_stress must be > 0"),
        (lambda: VonMises(float("nan")), "yield_stress must be finite"),
        (lambda: VonMises("500"), "yield_stress must be a real number"),
        (lambda: DruckerPrager(0.0), "0 < theta_f < 90"),
        (lambda: DruckerPrager(90.0), "0 < theta_f < 90"),
        (lambda: DruckerPrager(float("inf")), "friction_angle_deg must be finite"),
        (lambda: plasticity_from_dict({"type": "mohr_coulomb"}), "unknown plasticity type 'mohr_coulomb'"),
        (lambda: plasticity_from_dict({"type": "von_mises", "yield": 3}), r"unknown von_mises config field"),
        (lambda: VonMises.from_dict({"type": "drucker_prager"}), "does not match"),
    ],
)
def test_bad_parameters_raise_clear_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_inputs_raise_clear_errors():
    F = torch.eye(3, dtype=DT).repeat(2, 1, 1)
    inverted = F.clone()
    inverted[1, 2, 2] = -1.0
    with pytest.raises(ValueError, match=r"point 1 has det F = -1"):
        return_map(VM, inverted, MU, LAM)
    with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
        return_map(VM, torch.eye(3, dtype=DT), MU, LAM)
    with pytest.raises(ValueError, match="non-finite"):
        return_map(VM, F * float("nan"), MU, LAM)
    with pytest.raises(ValueError, match="mu"):
        return_map(VM, F, -1.0, LAM)
    with pytest.raises(ValueError, match=r"mu must be a scalar or have shape \(2,\)"):
        return_map(VM, F, torch.ones(3, dtype=DT), LAM)
    with pytest.raises(ValueError, match="VonMises or DruckerPrager"):
        return_map("von_mises", F, MU, LAM)
    with pytest.raises(ValueError, match="Fp_inv must have the shape"):
        update_plastic_state(VM, F, torch.eye(3, dtype=DT).repeat(3, 1, 1), MU, LAM)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    gen = torch.Generator().manual_seed(20)
    F = from_strain(0.3 * torch.randn(50, 3, generator=gen, dtype=DT), seed=21)
    Fp_inv = torch.linalg.inv(from_strain(0.1 * torch.randn(50, 3, generator=gen, dtype=DT), seed=22))
    for model in (VM, DP):
        out = update_plastic_state(model, F.cuda(), Fp_inv.cuda(), torch.tensor(MU).cuda(), LAM)
        assert out.device.type == "cuda"
        assert torch.allclose(out.cpu(), update_plastic_state(model, F, Fp_inv, MU, LAM), atol=1e-10)
