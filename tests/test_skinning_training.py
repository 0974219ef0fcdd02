"""Data-free skinning training: the energy terms against analytic values, and training behaviour."""

import math

import pytest
import torch

from vid2sim.physics.materials import lame_parameters, neo_hookean_energy_density
from vid2sim.physics.skinning import SkinningField, gradient_basis
from vid2sim.physics.skinning_training import (
    SkinningTrainingConfig,
    elastic_loss,
    orthogonality_loss,
    robust_neo_hookean_energy,
    sample_handle_transforms,
    train_skinning,
)

MU, LAM = lame_parameters(1e5, 0.3)


def _box(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (
        (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([1.0, 0.5, 0.5], dtype=torch.float64)
    ).to(dtype)


def _diag(s: torch.Tensor) -> torch.Tensor:
    """F = diag(s, 1, 1) for s: (M,)."""
    F = torch.eye(3, dtype=s.dtype).repeat(s.shape[0], 1, 1)
    F[:, 0, 0] = s
    return F


def test_robust_energy_is_exact_above_threshold_and_smooth_finite_below():
    g = torch.Generator().manual_seed(0)
    F = torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(50, 3, 3, generator=g, dtype=torch.float64)
    assert bool((torch.linalg.det(F) > 0.1).all())
    assert torch.allclose(
        robust_neo_hookean_energy(F, MU, LAM, 0.1), neo_hookean_energy_density(F, MU, LAM), rtol=1e-14
    )
    # along F = diag(s, 1, 1): value and slope continuous at J = s = 0.1; finite, convex, decreasing in s below
    s = torch.tensor([0.1 - 1e-9, 0.1 + 1e-9], dtype=torch.float64, requires_grad=True)
    psi = robust_neo_hookean_energy(_diag(s), MU, LAM, 0.1)
    (d,) = torch.autograd.grad(psi.sum(), s)
    assert float(psi[0].detach()) == pytest.approx(float(psi[1].detach()), rel=1e-7)
    assert float(d[0]) == pytest.approx(float(d[1]), rel=1e-5)
    s = torch.linspace(-1.0, 0.09, 60, dtype=torch.float64)
    psi = robust_neo_hookean_energy(_diag(s), MU, LAM, 0.1)
    assert bool(torch.isfinite(psi).all())
    assert bool((psi[1:] < psi[:-1]).all())  # more inverted → more energy
    assert bool((psi[2:] - 2 * psi[1:-1] + psi[:-2] > 0).all())  # convex in s
    # second derivative matches the exact energy's at the threshold (C²)
    def exact(x):
        return float(neo_hookean_energy_density(_diag(torch.tensor([x], dtype=torch.float64)), MU, LAM)[0])

    def robust(x):
        return float(robust_neo_hookean_energy(_diag(torch.tensor([x], dtype=torch.float64)), MU, LAM, 0.1)[0])

    h = 1e-4
    d2_exact = (exact(0.1 + 2 * h) - 2 * exact(0.1 + h) + exact(0.1)) / h**2
    d2_robust = (robust(0.1) - 2 * robust(0.1 - h) + robust(0.1 - 2 * h)) / h**2
    assert d2_robust == pytest.approx(d2_exact, rel=1e-2)


def test_orthogonality_loss_values():
    g = torch.Generator().manual_seed(1)
    Q, _ = torch.linalg.qr(torch.randn(40, 4, generator=g, dtype=torch.float64))
    assert float(orthogonality_loss(Q)) == pytest.approx(0.0, abs=1e-28)
    # W = 2 Q: WᵀW = 4 I → mean over 16 entries of (3² on 4 diagonal entries) = 36 / 16
    assert float(orthogonality_loss(2 * Q)) == pytest.approx(36 / 16, rel=1e-12)
    assert float(orthogonality_loss(torch.zeros(40, 4, dtype=torch.float64))) == pytest.approx(4 / 16)


def test_elastic_loss_of_a_uniform_stretch_on_the_rigid_handle_is_volume_times_psi():
    field = SkinningField(num_handles=3, width=16, hidden_layers=2, seed=0).double()
    X = _box(200)
    w, dw = field.weights_and_gradients(X)
    G = gradient_basis(X, w, dw)
    H = field.num_handles_total
    z = torch.zeros(2, 12 * H, dtype=torch.float64)
    Z = z.view(2, H, 3, 4)
    Z[1, -1, 0, 0] = 0.2  # F = diag(1.2, 1, 1) everywhere
    stretch = neo_hookean_energy_density(_diag(torch.tensor([1.2], dtype=torch.float64)), MU, LAM)[0]
    # analytic Neo-Hookean: μ/2 (1.44 − 1) − μ ln 1.2 + λ/2 (ln 1.2)²
    analytic = 0.5 * MU * 0.44 - MU * math.log(1.2) + 0.5 * LAM * math.log(1.2) ** 2
    assert float(stretch) == pytest.approx(analytic, rel=1e-12)
    le = elastic_loss(G, z, MU, LAM, volume=0.25).detach()
    assert float(le) == pytest.approx(0.25 * analytic / 2, rel=1e-12)  # batch mean of (0, volume·Ψ)


def test_sampled_transforms_leave_the_rigid_handle_at_rest():
    g = torch.Generator().manual_seed(0)
    z = sample_handle_transforms(500, 4, 0.1, g).view(500, 4, 12)
    assert float(z[:, -1].abs().max()) == 0.0
    assert float(z[:, :-1].std()) == pytest.approx(0.1, rel=0.03)
    z = sample_handle_transforms(500, 4, 0.1, g, rigid=True).view(500, 4, 12)
    assert float(z[:, -1].std()) == pytest.approx(0.1, rel=0.05)


def _components(field, X, seed=123):
    w, dw = field.weights_and_gradients(X)
    z = sample_handle_transforms(8, field.num_handles_total, 0.1, torch.Generator().manual_seed(seed)).to(X)
    with torch.no_grad():
        return float(elastic_loss(gradient_basis(X, w, dw), z, MU, LAM)), float(orthogonality_loss(w[:, :-1]))


def test_training_lowers_the_loss_and_the_orthogonality_term():
    pts = _box(500, dtype=torch.float32)
    probe = pts[:250]  # the Gram matrix is not normalised by the point count: probe with points_per_step points
    field = SkinningField(num_handles=3, width=32, hidden_layers=2, seed=0)
    _, ortho0 = _components(field, probe)
    assert ortho0 > 0.3  # small initial output layer: W ≈ 0, MSE(WᵀW, I) ≈ 3/9
    cfg = SkinningTrainingConfig(iterations=200, points_per_step=250, batch_size=4, lr=3e-3, seed=0)
    losses = train_skinning(field, pts, cfg, progress=False)
    assert len(losses) == 200 and all(math.isfinite(v) for v in losses)
    early = sum(losses[:10]) / 10
    late = sum(losses[-10:]) / 10
    assert late < 0.05 * early
    el1, ortho1 = _components(field, probe)
    assert ortho1 < 0.03 * ortho0
    # Σ_p w_j² ≈ 1 over points_per_step points, i.e. |w| ≈ 1/√250, and the handles are nearly orthogonal
    w = field(pts)[:, :-1].detach()
    gram = w.T @ w * (250 / 500)
    assert torch.allclose(torch.diag(gram), torch.ones(3), atol=0.1)
    assert float((gram - torch.diag(torch.diag(gram))).abs().max()) < 0.1
    assert el1 > 0


def test_training_is_reproducible_and_last_layer_only_freezes_the_rest():
    pts = _box(300, dtype=torch.float32)
    cfg = SkinningTrainingConfig(iterations=15, points_per_step=100, batch_size=2, seed=4)
    a = SkinningField(num_handles=2, width=16, hidden_layers=2, seed=1)
    b = SkinningField(num_handles=2, width=16, hidden_layers=2, seed=1)
    la = train_skinning(a, pts, cfg, progress=False)
    lb = train_skinning(b, pts, cfg, progress=False)
    assert la == lb
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)

    c = SkinningField(num_handles=2, width=16, hidden_layers=2, seed=1)
    before = {k: v.clone() for k, v in c.state_dict().items()}
    cfg_last = SkinningTrainingConfig(iterations=40, points_per_step=100, batch_size=2, seed=4, last_layer_only=True)
    losses = train_skinning(c, pts, cfg_last, progress=False)
    after = c.state_dict()
    for k in before:
        if k.startswith(f"layers.{len(c.layers) - 1}."):
            assert not torch.equal(before[k], after[k])
        else:
            assert torch.equal(before[k], after[k]), k
    assert sum(losses[-5:]) < sum(losses[:5])
    assert all(p.grad is None for p in c.parameters())


def test_large_random_transforms_invert_points_and_training_stays_finite():
    pts = _box(200, dtype=torch.float64)
    field = SkinningField(num_handles=2, width=16, hidden_layers=1, seed=2).double()
    # make the weights O(1) so that z_std = 1 certainly inverts some points
    with torch.no_grad():
        field.last_layer.bias.fill_(1.0)
    w, dw = field.weights_and_gradients(pts)
    z = sample_handle_transforms(4, 3, 1.0, torch.Generator().manual_seed(0)).double()
    from vid2sim.physics.skinning import deformation_gradient

    J = torch.linalg.det(deformation_gradient(gradient_basis(pts, w, dw), z))
    assert bool((J <= 0).any())
    cfg = SkinningTrainingConfig(iterations=10, points_per_step=200, batch_size=4, z_std=1.0, seed=0)
    losses = train_skinning(field, pts, cfg, progress=False)
    assert all(math.isfinite(v) for v in losses)
    assert all(bool(torch.isfinite(p).all()) for p in field.parameters())


def test_bad_configuration_and_inputs():
    with pytest.raises(ValueError, match="iterations"):
        SkinningTrainingConfig(iterations=-1)
    with pytest.raises(ValueError, match="z_std"):
        SkinningTrainingConfig(z_std=0.0)
    with pytest.raises(ValueError, match="poisson_ratio"):
        SkinningTrainingConfig(poisson_ratio=0.5)
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0)
    with pytest.raises(ValueError, match=r"points must be a tensor of shape \(N, 3\)"):
        train_skinning(field, torch.zeros(10, 2), SkinningTrainingConfig(iterations=1), progress=False)
    with pytest.raises(ValueError, match="must match"):
        train_skinning(field, _box(10), SkinningTrainingConfig(iterations=1), progress=False)
    with pytest.raises(ValueError, match="volume"):
        train_skinning(
            field, _box(10, dtype=torch.float32), SkinningTrainingConfig(iterations=1), progress=False, volume=-1.0
        )
    assert (
        train_skinning(field, _box(10, dtype=torch.float32), SkinningTrainingConfig(iterations=0), progress=False) == []
    )


def _captured_step(monkeypatch, module, train):
    """(step, inputs) that ``train()`` hands to ``module``'s ``optimise`` (which then returns without training)."""
    seen = {}

    def fake(params, step, schedule, progress, what, inputs=None):
        seen.update(step=step, inputs=inputs, params=params)
        return []

    monkeypatch.setattr(module, "optimise", fake)
    train()
    return seen["step"], seen["inputs"], seen["params"]


@pytest.mark.parametrize("objective", ["modal", "random_z"])
def test_a_skinning_iteration_never_waits_for_the_device(monkeypatch, no_device_waits, objective):
    """The iteration, gradients included, reads no value back (so a CUDA graph can capture it); a check of values
    inside it (an `.item()`, a `bool`, a boolean mask) fails here on the CPU."""
    import vid2sim.physics.skinning_training as module

    field = SkinningField(num_handles=3, width=16, hidden_layers=1, seed=0).double()
    pts = _box(400)
    config = SkinningTrainingConfig(iterations=5, points_per_step=100, batch_size=3, objective=objective)
    step, inputs, params = _captured_step(monkeypatch, module, lambda: train_skinning(field, pts, config,
                                                                                       progress=False))
    drawn = inputs(0)
    with no_device_waits:
        loss, parts = step(*drawn)
        grads = torch.autograd.grad(loss, params)
    assert all(isinstance(v, torch.Tensor) for v in parts.values())
    assert math.isfinite(float(loss)) and all(bool(torch.isfinite(g).all()) for g in grads)


def test_a_neural_jacobian_iteration_never_waits_for_the_device(monkeypatch, no_device_waits):
    import vid2sim.physics.neural_jacobian as module
    from vid2sim.physics.neural_jacobian import NeuralJacobian, NeuralJacobianTrainingConfig, train_neural_jacobian

    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0).double()
    net = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(16, 16), seed=0).double()
    pts = _box(300)
    config = NeuralJacobianTrainingConfig(iterations=5, points_per_step=100, batch_size=3)
    step, inputs, params = _captured_step(monkeypatch, module, lambda: train_neural_jacobian(net, field, pts, config,
                                                                                             progress=False))
    with no_device_waits:
        loss, _ = step(*inputs(0))
        torch.autograd.grad(loss, params)
    assert math.isfinite(float(loss))


@pytest.mark.cuda
@pytest.mark.parametrize("objective", ["modal", "random_z"])
def test_cuda_graphed_skinning_training_matches_the_eager_one(objective):
    """The default on CUDA (one captured iteration replayed) against eager iterations: the same losses to float32
    rounding over 200 iterations (and the same weights where the loss fixes them), and no warning (a capture that
    failed would say so)."""
    import warnings

    pts = _box(3000, dtype=torch.float32).cuda()
    config = SkinningTrainingConfig(iterations=200, points_per_step=500, batch_size=4, objective=objective)
    runs = {}
    for graph in (True, False):
        field = SkinningField(num_handles=4, seed=0).cuda()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            runs[graph] = (train_skinning(field, pts, config, progress=False, cuda_graph=graph), field)
    (lg, fg), (le, fe) = runs[True], runs[False]
    assert len(lg) == 200 and all(math.isfinite(v) for v in lg)
    assert lg[:3] == pytest.approx(le[:3], rel=1e-4)  # the eager warm-up iterations (capturable Adam rounds apart)
    assert lg[-1] == pytest.approx(le[-1], rel=2e-2, abs=1e-4)
    if objective == "random_z":  # the modal loss leaves the weights' mixing free (its gauge), so they drift apart
        X = pts[:500]
        assert torch.allclose(fg.weights_and_gradients(X)[0], fe.weights_and_gradients(X)[0], rtol=0.05, atol=2e-3)


def test_a_modal_loss_without_a_definite_ridge_is_nan_and_the_training_says_what_to_raise(monkeypatch):
    """No ridge at the dtype's precision makes an indefinite mass definite: the loss is NaN (read on the device, no
    exception inside the step), and the training's error names the setting that keeps the Gram matrices definite."""
    import vid2sim.physics.skinning_training as module
    from vid2sim.physics.skinning_training import modal_loss

    eye = torch.eye(6, dtype=torch.float64)
    assert math.isfinite(float(modal_loss(2 * eye, eye, 1.0, trace_weight=1e-2)))
    assert math.isnan(float(modal_loss(eye, -2 * eye, 1.0)))  # K + αM = -I
    monkeypatch.setattr(module, "modal_loss", lambda K, M, alpha, w: modal_loss(K, -M, alpha, w))
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0).double()
    with pytest.raises(FloatingPointError, match=r"iteration 0 \(modal nan.*raise modal_orthogonality_weight"):
        train_skinning(field, _box(300), SkinningTrainingConfig(iterations=3, points_per_step=100,
                                                                objective="modal"), progress=False)
