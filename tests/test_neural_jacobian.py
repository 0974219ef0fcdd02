"""Neural Jacobian: architecture, metric definitions, and data-free training against the exact dF/dz."""

import math

import pytest
import torch

from vid2sim.physics.neural_jacobian import (
    NeuralJacobian,
    NeuralJacobianTrainingConfig,
    jacobian_error,
    train_neural_jacobian,
)
from vid2sim.physics.skinning import SkinningField, dF_dz, gradient_basis


def _points(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) - 0.5


def test_paper_architecture():
    net = NeuralJacobian(seed=0)
    linears = [(m.in_features, m.out_features) for m in net.modules() if isinstance(m, torch.nn.Linear)]
    # 4 residual blocks of two Linear layers (+ projections where the width changes) and the output layer
    assert linears == [
        (512, 512), (512, 512),
        (512, 512), (512, 512),
        (512, 1024), (1024, 1024), (512, 1024),
        (1024, 1024), (1024, 1024),
        (1024, 9 * 12 * 11),
    ]
    assert net.frequencies.shape == (256, 3)
    J = net(_points(7))
    assert J.shape == (7, 9, 132)
    assert float(J.detach().abs().max()) == 0.0  # zero-initialised output layer


def test_encoding_and_seed():
    a = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(8, 8), seed=5)
    b = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(8, 8), seed=5)
    c = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(8, 8), seed=6)
    for (ka, pa), (_, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(pa, pb), ka
    assert not torch.equal(a.frequencies, c.frequencies)
    X = _points(11)
    e = a.encode(X)
    assert e.shape == (11, 16)
    assert torch.allclose(e[:, :8] ** 2 + e[:, 8:] ** 2, torch.ones(11, 8), atol=1e-6)
    assert torch.allclose(e[:, :8], torch.sin(2 * math.pi * X @ a.frequencies.T), atol=1e-6)


def test_jacobian_error_definitions():
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0)
    net = NeuralJacobian(num_handles_total=3, encoding_dim=8, widths=(8,), seed=0)
    with torch.no_grad():
        net.output.weight.normal_(0, 0.1, generator=torch.Generator().manual_seed(0))
    X = _points(50, seed=1)
    w, dw = field.weights_and_gradients(X)
    J_true = dF_dz(gradient_basis(X, w, dw)).detach()
    diff = (net(X) - J_true).detach().double()
    err = jacobian_error(net, field, X, chunk=16)  # chunking must not change the result
    assert err["mse"] == pytest.approx(float((diff**2).sum()) / 50, rel=1e-6)
    assert err["mse_per_entry"] == pytest.approx(float((diff**2).mean()), rel=1e-6)
    assert err["relative_frobenius"] == pytest.approx(float(diff.norm() / J_true.double().norm()), rel=1e-6)
    assert err["max_abs"] == pytest.approx(float(diff.abs().max()), rel=1e-6)
    fresh = NeuralJacobian(num_handles_total=3, encoding_dim=8, widths=(8,), seed=0)
    assert jacobian_error(fresh, field, X)["relative_frobenius"] == pytest.approx(1.0)


def test_data_free_training_reduces_the_error():
    pts = _points(2000, seed=2) * torch.tensor([1.0, 0.6, 0.4])
    field = SkinningField(num_handles=3, width=16, hidden_layers=2, seed=0)
    net = NeuralJacobian(num_handles_total=4, encoding_dim=32, widths=(32, 32, 64, 64), seed=0, frequency_scale=1.0)
    ev = pts[:500]
    before = jacobian_error(net, field, ev)
    cfg = NeuralJacobianTrainingConfig(iterations=150, points_per_step=128, batch_size=4, lr=3e-3, seed=0)
    params_field = [p.clone() for p in field.parameters()]
    losses = train_neural_jacobian(net, field, pts, cfg, progress=False)
    after = jacobian_error(net, field, ev)
    assert len(losses) == 150 and all(math.isfinite(v) for v in losses)
    assert sum(losses[-10:]) < 0.2 * sum(losses[:10])
    assert before["relative_frobenius"] == pytest.approx(1.0)
    assert after["relative_frobenius"] < 0.1
    assert after["mse"] < 0.01 * before["mse"]
    for p, q in zip(field.parameters(), params_field):  # the field is only read
        assert torch.equal(p, q)
    # reproducible from the seed
    runs = []
    for _ in range(2):
        n2 = NeuralJacobian(num_handles_total=4, encoding_dim=32, widths=(32, 32, 64, 64), seed=0, frequency_scale=1.0)
        small = NeuralJacobianTrainingConfig(iterations=5, points_per_step=64, batch_size=2, seed=3)
        runs.append((train_neural_jacobian(n2, field, pts, small, progress=False), n2.output.weight.detach().clone()))
    assert runs[0][0] == runs[1][0]
    assert torch.equal(runs[0][1], runs[1][1])


def test_bad_inputs():
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0)
    net = NeuralJacobian(num_handles_total=4, encoding_dim=8, widths=(8,), seed=0)
    with pytest.raises(ValueError, match="handles"):
        jacobian_error(net, field, _points(5))
    with pytest.raises(ValueError, match="even"):
        NeuralJacobian(encoding_dim=7)
    with pytest.raises(ValueError, match="widths"):
        NeuralJacobian(widths=())
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        net(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="NaN"):
        net(torch.full((2, 3), float("nan")))
    with pytest.raises(ValueError, match="iterations"):
        NeuralJacobianTrainingConfig(iterations=-3)
    with pytest.raises(ValueError, match="lr"):
        NeuralJacobianTrainingConfig(lr=0)


@pytest.mark.cuda
def test_cuda_training_step_runs_and_matches_layout():
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0).cuda()
    net = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(16, 16), seed=0).cuda()
    pts = _points(300).cuda()
    losses = train_neural_jacobian(
        net, field, pts, NeuralJacobianTrainingConfig(iterations=30, points_per_step=64, batch_size=2), progress=False
    )
    assert losses[-1] < losses[0]
    assert net(pts[:4]).shape == (4, 9, 36)


@pytest.mark.cuda
def test_training_names_parameters_on_another_device_than_the_points():
    field = SkinningField(num_handles=2, width=8, hidden_layers=1, seed=0)
    net = NeuralJacobian(num_handles_total=3, encoding_dim=16, widths=(16, 16), seed=0)
    with pytest.raises(ValueError, match=r"points are on cuda:0 but the Neural Jacobian's parameters are on cpu"):
        train_neural_jacobian(net, field, _points(300).float().cuda(), NeuralJacobianTrainingConfig(iterations=2),
                              progress=False)
