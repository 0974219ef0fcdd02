"""Hyperelastic models (vid2sim.physics.materials) checked against finite differences and continuum mechanics."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vid2sim.physics.materials import (
    elastic_model,
    lame_parameters,
    neo_hookean_energy_density,
    neo_hookean_pk1,
    neo_hookean_tangent,
    project_psd,
    project_tangent_psd,
    stvk_energy_density,
    stvk_pk1,
    stvk_tangent,
)

MODELS = ["neo_hookean", "stvk"]
MU, LAM = 3.0e4, 7.0e4
DT = torch.float64


def random_rotations(n: int, seed: int) -> torch.Tensor:
    """(n, 3, 3) uniformly random rotations (scipy)."""
    return torch.tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=DT)


def random_F(n: int, seed: int, lo: float = 0.4, hi: float = 2.5) -> torch.Tensor:
    """det F > 0: near-identity ones plus large stretches/compressions R1 diag(s) R2."""
    gen = torch.Generator().manual_seed(seed)
    near = torch.eye(3, dtype=DT) + 0.15 * torch.randn(n, 3, 3, generator=gen, dtype=DT)
    near = near[torch.linalg.det(near) > 0.3]
    s = lo + (hi - lo) * torch.rand(n, 3, generator=gen, dtype=DT)
    large = random_rotations(n, seed) @ torch.diag_embed(s) @ random_rotations(n, seed + 1000)
    return torch.cat([near, large])


def fd_gradient(fun, F: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """Central differences of a per-point function fun(F) -> (N, *shape) w.r.t. the 9 entries of F."""
    cols = []
    for a in range(9):
        E = torch.zeros(9, dtype=F.dtype)
        E[a] = h
        E = E.reshape(3, 3)
        cols.append((fun(F + E) - fun(F - E)) / (2 * h))
    return torch.stack(cols, dim=-1)


@pytest.mark.parametrize("name", MODELS)
def test_pk1_matches_finite_differences_of_energy(name):
    psi, pk1, _ = elastic_model(name)
    F = random_F(8, seed=1)
    P = pk1(F, MU, LAM).reshape(-1, 9)
    P_fd = fd_gradient(lambda G: psi(G, MU, LAM), F)
    scale = P.abs().amax(dim=1, keepdim=True).clamp_min(1.0)
    assert torch.allclose(P / scale, P_fd / scale, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", MODELS)
def test_tangent_matches_finite_differences_of_pk1(name):
    _, pk1, tangent = elastic_model(name)
    F = random_F(8, seed=2)
    C = tangent(F, MU, LAM)
    C_fd = fd_gradient(lambda G: pk1(G, MU, LAM).reshape(-1, 9), F)  # [n, 3i+j, 3k+l]
    scale = C.abs().amax(dim=(1, 2), keepdim=True)
    assert torch.allclose(C / scale, C_fd / scale, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", MODELS)
def test_tangent_is_symmetric(name):
    _, _, tangent = elastic_model(name)
    C = tangent(random_F(8, seed=3), MU, LAM)
    assert torch.allclose(C, C.transpose(1, 2), atol=1e-9 * float(C.abs().max()), rtol=0)


@pytest.mark.parametrize("name", MODELS)
def test_rigid_rotations_store_no_energy_and_no_stress(name):
    psi, pk1, _ = elastic_model(name)
    R = random_rotations(6, seed=4)
    assert torch.allclose(psi(R, MU, LAM), torch.zeros(6, dtype=DT), atol=1e-8)
    assert torch.allclose(pk1(R, MU, LAM), torch.zeros(6, 3, 3, dtype=DT), atol=1e-8)


@pytest.mark.parametrize("name", MODELS)
def test_frame_indifference(name):
    psi, pk1, _ = elastic_model(name)
    F = random_F(6, seed=5)
    R = random_rotations(F.shape[0], seed=6)
    e, e_rot = psi(F, MU, LAM), psi(R @ F, MU, LAM)
    assert torch.allclose(e_rot, e, rtol=1e-10, atol=1e-9 * float(e.abs().max()))
    # P(RF) = R P(F)
    P, P_rot = pk1(F, MU, LAM), pk1(R @ F, MU, LAM)
    assert torch.allclose(P_rot, R @ P, rtol=0, atol=1e-9 * float(P.abs().max()))


@pytest.mark.parametrize("name", MODELS)
def test_tangent_at_rest_is_the_isotropic_elasticity_tensor(name):
    _, _, tangent = elastic_model(name)
    d = torch.eye(3, dtype=DT)
    C_lin = (
        LAM * torch.einsum("ij,kl->ijkl", d, d)
        + MU * (torch.einsum("ik,jl->ijkl", d, d) + torch.einsum("il,jk->ijkl", d, d))
    ).reshape(9, 9)
    C = tangent(torch.eye(3, dtype=DT)[None], MU, LAM)[0]
    assert torch.allclose(C, C_lin, rtol=0, atol=1e-9 * MU)


@pytest.mark.parametrize("name", MODELS)
def test_small_strain_energy_matches_linear_elasticity(name):
    psi, _, _ = elastic_model(name)
    gen = torch.Generator().manual_seed(7)
    H = torch.randn(5, 3, 3, generator=gen, dtype=DT)
    eps = 0.5 * (H + H.transpose(1, 2))
    tr = eps.diagonal(dim1=1, dim2=2).sum(-1)
    linear = MU * (eps * eps).sum(dim=(1, 2)) + 0.5 * LAM * tr * tr  # Ψ_lin(ε) for unit H
    delta = 1e-4
    ratio = psi(torch.eye(3, dtype=DT) + delta * H, MU, LAM) / delta**2
    assert torch.allclose(ratio, linear, rtol=1e-3)


def test_float32_in_float32_out():
    F = random_F(4, seed=8).float()
    for name in MODELS:
        for fn in elastic_model(name):
            assert fn(F, MU, LAM).dtype == torch.float32


def test_lame_parameter_values_and_gradients():
    mu, lam = lame_parameters(1e5, 0.3)
    assert mu == pytest.approx(1e5 / 2.6)
    assert lam == pytest.approx(1e5 * 0.3 / (1.3 * 0.4))
    E = torch.tensor(2e4, dtype=DT, requires_grad=True)
    nu = torch.tensor(0.25, dtype=DT, requires_grad=True)
    mu_t, lam_t = lame_parameters(E, nu)
    (dmu_dE,) = torch.autograd.grad(mu_t, E, retain_graph=True)
    assert float(dmu_dE) == pytest.approx(1 / 2.5)
    (dlam_dnu,) = torch.autograd.grad(lam_t, nu)
    # d/dν [Eν / ((1+ν)(1−2ν))] = E (1 + 2ν²) / ((1+ν)²(1−2ν)²)
    assert float(dlam_dnu) == pytest.approx(2e4 * (1 + 2 * 0.0625) / (1.25**2 * 0.5**2))


@pytest.mark.parametrize(
    "E, nu, match",
    [
        (0.0, 0.3, "Young"),
        (-5.0, 0.3, "Young"),
        (float("nan"), 0.3, "Young"),
        (float("inf"), 0.3, "Young"),
        (1e5, 0.5, "Poisson"),
        (1e5, 0.7, "Poisson"),
        (1e5, -1.0, "Poisson"),
        (1e5, float("nan"), "Poisson"),
    ],
)
def test_lame_parameter_errors(E, nu, match):
    with pytest.raises(ValueError, match=match):
        lame_parameters(E, nu)


def test_model_and_shape_errors():
    with pytest.raises(ValueError, match="unknown elastic model 'rubber'"):
        elastic_model("rubber")
    with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
        neo_hookean_energy_density(torch.eye(3), MU, LAM)
    with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
        stvk_pk1(torch.zeros(2, 2, 2), MU, LAM)
    with pytest.raises(ValueError, match=r"\(N, d, d\)"):
        project_psd(torch.zeros(2, 3, 4))


def _eig_clamp_reference(H: torch.Tensor) -> np.ndarray:
    """Independent reference: numpy eigendecomposition with eigenvalues clamped at 0."""
    A = H.numpy()
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    w, V = np.linalg.eigh(A)
    return np.einsum("nij,nj,nkj->nik", V, np.clip(w, 0, None), V)


def test_project_psd_clamps_negative_eigenvalues_and_keeps_pd_matrices():
    gen = torch.Generator().manual_seed(9)
    A = torch.randn(20, 6, 6, generator=gen, dtype=DT)
    sym = A + A.transpose(1, 2)  # indefinite
    out = project_psd(sym)
    assert float(torch.linalg.eigvalsh(out).min()) >= -1e-10
    assert np.allclose(out.numpy(), _eig_clamp_reference(sym), atol=1e-10)
    pd = A @ A.transpose(1, 2) + 0.1 * torch.eye(6, dtype=DT)
    assert torch.equal(project_psd(pd), pd)


def test_project_psd_is_idempotent_and_keeps_psd_eigenvectors():
    gen = torch.Generator().manual_seed(10)
    A = torch.randn(10, 5, 5, generator=gen, dtype=DT)
    once = project_psd(A + A.transpose(1, 2))
    assert torch.allclose(project_psd(once), once, atol=1e-10)


@pytest.mark.parametrize("name", MODELS)
def test_project_tangent_psd_equals_the_exact_eigenvalue_clamp(name):
    _, _, tangent = elastic_model(name)
    # compressed, sheared and stretched states where the tangents are indefinite
    F = torch.cat([random_F(6, seed=11, lo=0.3, hi=0.8), random_F(6, seed=12, lo=0.5, hi=2.0)])
    C = tangent(F, MU, LAM)
    assert float(torch.linalg.eigvalsh(C).min()) < 0  # the test exercises the projection
    out = project_tangent_psd(name, F, C, MU, LAM)
    scale = float(C.abs().max())
    assert float(torch.linalg.eigvalsh(out).min()) >= -1e-9 * scale
    assert np.allclose(out.numpy(), _eig_clamp_reference(C), atol=1e-6 * scale, rtol=0)


def test_neo_hookean_twist_modes_are_eigenvectors_with_known_eigenvalues():
    """The closed-form twist projection rests on D_ij = U (E_ij − E_ji) Vᵀ/√2 being eigenvectors of the
    Neo-Hookean tangent with eigenvalue μ − (μ − λ ln J)/(σ_i σ_j)."""
    F = random_F(4, seed=13, lo=0.4, hi=1.6)
    C = neo_hookean_tangent(F, MU, LAM)
    U, S, Vh = torch.linalg.svd(F)
    logj = torch.log(torch.linalg.det(F))
    for i, j in ((0, 1), (0, 2), (1, 2)):
        D = (U[:, :, i, None] * Vh[:, None, j, :] - U[:, :, j, None] * Vh[:, None, i, :]) / math.sqrt(2)
        d = D.reshape(-1, 9)
        ev = MU - (MU - LAM * logj) / (S[:, i] * S[:, j])
        assert torch.allclose((C @ d[:, :, None])[..., 0], ev[:, None] * d, atol=1e-8 * MU)


def test_stvk_matches_its_definition_on_a_uniaxial_stretch():
    """Independent closed form: F = diag(s, 1, 1) → G = diag((s²−1)/2, 0, 0), Ψ = (μ + λ/2) g², P_11 = s (2μ + λ) g."""
    s = torch.tensor([0.7, 1.3, 2.0], dtype=DT)
    F = torch.diag_embed(torch.stack([s, torch.ones_like(s), torch.ones_like(s)], dim=1))
    g = (s * s - 1) / 2
    assert torch.allclose(stvk_energy_density(F, MU, LAM), (MU + LAM / 2) * g * g)
    assert torch.allclose(stvk_pk1(F, MU, LAM)[:, 0, 0], s * (2 * MU + LAM) * g)
    assert torch.allclose(stvk_tangent(F, MU, LAM)[:, 0, 0], (2 * MU + LAM) * (3 * s * s - 1) / 2)


def test_neo_hookean_matches_its_definition_on_a_uniaxial_stretch():
    s = torch.tensor([0.6, 1.5], dtype=DT)
    F = torch.diag_embed(torch.stack([s, torch.ones_like(s), torch.ones_like(s)], dim=1))
    ln = torch.log(s)
    expect = 0.5 * MU * (s * s - 1) - MU * ln + 0.5 * LAM * ln * ln
    assert torch.allclose(neo_hookean_energy_density(F, MU, LAM), expect)
    assert torch.allclose(neo_hookean_pk1(F, MU, LAM)[:, 0, 0], MU * (s - 1 / s) + LAM * ln / s)


def test_fused_neo_hookean_viscous_tangent_equals_the_separate_tangents():
    """The damped step's exact tangent, assembled from outer and Kronecker products, equals
    k_e ∂P_NH/∂F + k_v ∂P_StVK(C_ref)/∂F, and the viscous part is the derivative of its stress."""
    from vid2sim.physics.damping import viscous_pk1
    from vid2sim.physics.materials import (
        neo_hookean_tangent,
        neo_hookean_viscous_tangent,
        stvk_tangent,
    )

    gen = torch.Generator().manual_seed(3)
    F = torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(40, 3, 3, generator=gen, dtype=torch.float64)
    C_ref = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(40, 3, 3, generator=gen, dtype=torch.float64)
    C_ref = 0.5 * (C_ref + C_ref.transpose(1, 2))
    mu, lam = torch.tensor(3.0, dtype=torch.float64), torch.tensor(5.0, dtype=torch.float64)
    fused = neo_hookean_viscous_tangent(F, mu, lam, 0.7, 0.3, C_ref)
    separate = 0.7 * neo_hookean_tangent(F, mu, lam) + 0.3 * stvk_tangent(F, mu, lam, C_ref)
    assert torch.allclose(fused, separate, atol=1e-12)
    assert torch.allclose(
        neo_hookean_viscous_tangent(F, mu, lam, 0.7, 0.0, None), 0.7 * neo_hookean_tangent(F, mu, lam), atol=1e-12
    )
    # the viscous tangent is the derivative of the viscous stress (central differences)
    d = torch.randn(40, 3, 3, generator=gen, dtype=torch.float64)
    eps = 1e-6
    fd = (viscous_pk1(F + eps * d, C_ref, mu, lam) - viscous_pk1(F - eps * d, C_ref, mu, lam)) / (2 * eps)
    lin = (stvk_tangent(F, mu, lam, C_ref) @ d.reshape(40, 9, 1)).reshape(40, 3, 3)
    assert torch.allclose(lin, fd, atol=1e-6)


def test_fused_neo_hookean_viscous_energy_and_stress_equal_the_separate_models():
    """The damped step's fused energy and stress equal k_e (Ψ, P)_NH + k_v (ψ, P)_StVK(C_ref), values and
    gradients (to F, μ, λ, k_v and C_ref: the adjoint differentiates them)."""
    from vid2sim.physics.materials import (
        neo_hookean_energy_and_pk1,
        neo_hookean_viscous_energy_and_pk1,
        stvk_energy_and_pk1,
    )

    gen = torch.Generator().manual_seed(5)
    F = random_F(30, 4).requires_grad_()
    C_ref = torch.eye(3, dtype=DT) + 0.1 * torch.randn(len(F), 3, 3, generator=gen, dtype=DT)
    C_ref = (0.5 * (C_ref + C_ref.transpose(1, 2))).requires_grad_()
    mu, lam, k_v = (torch.tensor(v, dtype=DT, requires_grad=True) for v in (3.0, 5.0, 0.3))
    psi, P, J = neo_hookean_viscous_energy_and_pk1(F, mu, lam, 0.7, k_v, C_ref)
    psi_e, P_e, J_e = neo_hookean_energy_and_pk1(F, mu, lam)
    psi_v, P_v = stvk_energy_and_pk1(F, mu, lam, C_ref)
    ref_psi, ref_P = 0.7 * psi_e + k_v * psi_v, 0.7 * P_e + k_v * P_v
    assert torch.allclose(psi, ref_psi, rtol=1e-12, atol=1e-12) and torch.allclose(P, ref_P, rtol=1e-12, atol=1e-12)
    assert torch.equal(J, J_e)
    none, P_only, _ = neo_hookean_viscous_energy_and_pk1(F, mu, lam, 0.7, k_v, C_ref, energy=False)
    assert none is None and torch.equal(P_only, P)
    w = torch.randn(P.shape, generator=gen, dtype=DT)
    leaves = [F, C_ref, mu, lam, k_v]
    got = torch.autograd.grad((P * w).sum() + psi.sum(), leaves)
    want = torch.autograd.grad((ref_P * w).sum() + ref_psi.sum(), leaves)
    for name, a, b in zip(("F", "C_ref", "mu", "lam", "k_v"), got, want):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-10), name
