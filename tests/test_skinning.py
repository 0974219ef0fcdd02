"""Skinning field, LBS and the closed-form deformation gradient, checked against finite differences."""

import math

import pytest
import torch

from vid2sim.physics.skinning import (
    SkinningField,
    deform,
    deformation_gradient,
    dF_dz,
    gradient_basis,
    lbs_matrix,
)


def _points(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [1.0, 0.6, 0.4], dtype=torch.float64
    )


def _z(H: int, std: float = 0.1, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return std * torch.randn(12 * H, generator=g, dtype=torch.float64)


def _rotation(axis, angle: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    K = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@pytest.fixture(scope="module")
def field() -> SkinningField:
    # default architecture (3-64-…-64-10), float64
    return SkinningField(num_handles=10, seed=7).double()


def test_architecture_and_last_layer_layout(field):
    linears = [m for m in field.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(3, 64)] + [(64, 64)] * 8 + [(64, 10)]
    assert field.num_handles_total == 11
    assert field.last_layer_size == 650
    vec = field.get_last_layer()
    assert vec.shape == (650,)
    assert torch.equal(vec[:640].reshape(10, 64), field.last_layer.weight.detach())
    assert torch.equal(vec[640:], field.last_layer.bias.detach())
    other = SkinningField(num_handles=10, seed=99).double()
    other.set_last_layer(vec)
    assert torch.equal(other.get_last_layer(), vec)
    with pytest.raises(ValueError, match="650"):
        other.set_last_layer(torch.zeros(649, dtype=torch.float64))
    with pytest.raises(ValueError, match="NaN"):
        other.set_last_layer(torch.full((650,), float("nan"), dtype=torch.float64))


def test_seed_makes_initialisation_deterministic():
    a, b, c = SkinningField(seed=3), SkinningField(seed=3), SkinningField(seed=4)
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)
    assert not torch.equal(a.layers[0].weight, c.layers[0].weight)
    # hidden layers Kaiming-uniform |w| <= sqrt(6 / fan_in); output layer small, zero bias
    wmax = float(a.layers[1].weight.detach().abs().max())
    assert 0.9 * math.sqrt(6 / 64) < wmax <= math.sqrt(6 / 64) + 1e-7
    assert float(a.last_layer.weight.detach().abs().max()) <= 0.01 / 8 + 1e-9
    assert float(a.last_layer.bias.detach().abs().max()) == 0.0


def test_initial_features_are_well_conditioned():
    """The last hidden features over a box keep >= 10 directions with O(0.1) singular values (see class doc)."""
    f = SkinningField(seed=0).double()
    X = _points(1000, seed=3)
    h = X
    with torch.no_grad():
        for layer in f.layers[:-1]:
            h = torch.nn.functional.elu(layer(h))
        s = torch.linalg.svdvals(torch.cat([h, torch.ones(1000, 1, dtype=h.dtype)], 1) / 1000**0.5)
    assert float(s[10]) > 0.2


def test_rigid_column_and_forward_agree(field):
    X = _points(50)
    w, dw = field.weights_and_gradients(X)
    assert w.shape == (50, 11) and dw.shape == (50, 11, 3)
    assert torch.equal(w[:, -1], torch.ones(50, dtype=torch.float64))
    assert torch.equal(dw[:, -1], torch.zeros(50, 3, dtype=torch.float64))
    assert torch.allclose(field(X), w, atol=1e-14, rtol=0)


def test_closed_form_weight_gradient_matches_central_differences(field):
    X = _points(40, seed=2)
    _, dw = field.weights_and_gradients(X)
    h = 1e-6
    fd = torch.empty_like(dw)
    with torch.no_grad():
        for c in range(3):
            e = torch.zeros(3, dtype=torch.float64)
            e[c] = h
            fd[:, :, c] = (field(X + e) - field(X - e)) / (2 * h)
    scale = float(dw.detach().abs().max())
    assert scale > 1e-3  # a non-trivial field
    assert float((dw.detach() - fd).abs().max()) < 1e-7 * max(1.0, scale)


def test_input_frame_maps_world_points_to_the_canonical_network():
    canonical = SkinningField(num_handles=4, width=16, hidden_layers=2, seed=3).double()
    world = SkinningField(num_handles=4, width=16, hidden_layers=2, seed=3).double()
    centre, scale = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64), 0.25
    world.set_input_frame(centre, scale)
    Xc = _points(30, seed=4)
    Xw = centre + scale * Xc
    w_c, dw_c = canonical.weights_and_gradients(Xc)
    w_w, dw_w = world.weights_and_gradients(Xw)
    assert torch.allclose(w_w, w_c) and torch.allclose(world(Xw), w_c)
    assert torch.allclose(dw_w, dw_c / scale)  # chain rule of the input frame
    h = 1e-6
    with torch.no_grad():
        for c in range(3):
            e = torch.zeros(3, dtype=torch.float64)
            e[c] = h
            fd = (world(Xw + e) - world(Xw - e)) / (2 * h)
            assert float((dw_w[:, :, c] - fd).abs().max()) < 1e-6 * float(dw_w.abs().max())
    state = world.state_dict()  # the frame is saved with the weights
    again = SkinningField(num_handles=4, width=16, hidden_layers=2).double()
    again.load_state_dict(state)
    assert torch.allclose(again(Xw), w_c)
    with pytest.raises(ValueError, match="scale"):
        world.set_input_frame(centre, 0.0)


def test_deformation_gradient_matches_finite_differences_of_deform(field):
    X = _points(30, seed=3)
    H = field.num_handles_total
    z = _z(H, std=0.5)
    w, dw = field.weights_and_gradients(X)
    F = deformation_gradient(gradient_basis(X, w, dw), z)
    h = 1e-6
    fd = torch.empty_like(F)
    with torch.no_grad():
        for c in range(3):
            e = torch.zeros(3, dtype=torch.float64)
            e[c] = h
            xp = deform(X + e, field(X + e), z)
            xm = deform(X - e, field(X - e), z)
            fd[:, :, c] = (xp - xm) / (2 * h)
    assert float((F.detach() - torch.eye(3, dtype=torch.float64)).abs().max()) > 1e-3
    assert torch.allclose(F, fd, atol=1e-8, rtol=0)


def test_dF_dz_is_consistent_and_block_structured(field):
    X = _points(25, seed=4)
    H = field.num_handles_total
    z = _z(H)
    w, dw = field.weights_and_gradients(X)
    G = gradient_basis(X, w, dw)
    J = dF_dz(G)
    assert J.shape == (25, 9, 12 * H)
    F = deformation_gradient(G, z)
    assert torch.allclose(F.reshape(25, 9), torch.eye(3, dtype=torch.float64).reshape(9) + J @ z, atol=1e-14)
    # row a of F depends only on row a of each Z_j
    Jr = J.reshape(25, 3, 3, H, 3, 4)  # [p, a, c, j, a', k]
    for a in range(3):
        for b in range(3):
            if a != b:
                assert float(Jr[:, a, :, :, b, :].detach().abs().max()) == 0.0
    # and dF/dz agrees with autograd through deformation_gradient
    Jauto = torch.autograd.functional.jacobian(lambda zz: deformation_gradient(G, zz).reshape(25, 9), z)
    assert torch.allclose(J, Jauto, atol=1e-14)
    # batched z gives the per-sample F
    zb = torch.stack([z, 2 * z, -z])
    Fb = deformation_gradient(G, zb)
    assert Fb.shape == (3, 25, 3, 3)
    assert torch.allclose(Fb[1], deformation_gradient(G, 2 * z), atol=1e-14)


def test_lbs_matrix_matches_deform_and_the_formula(field):
    X = _points(20, seed=5)
    H = field.num_handles_total
    z = _z(H, std=0.3)
    w = field(X)
    B = lbs_matrix(X, w)
    assert B.shape == (20, 3, 12 * H)
    x = deform(X, w, z)
    assert torch.allclose(X + B @ z, x, atol=1e-14)
    # direct formula x = X + Σ_j w_j Z_j [X; 1]
    Z = z.reshape(H, 3, 4)
    Xh = torch.cat([X, torch.ones(20, 1, dtype=torch.float64)], dim=1)
    direct = X + torch.einsum("pj,jak,pk->pa", w, Z, Xh)
    assert torch.allclose(x, direct, atol=1e-14)
    # layout z[12 j + 4 a + k] = Z_j[a, k]
    z1 = torch.zeros(12 * H, dtype=torch.float64)
    z1[12 * 2 + 4 * 1 + 3] = 1.0  # handle 2, row y, translation column
    moved = deform(X, w, z1) - X
    assert torch.allclose(moved[:, 1], w[:, 2], atol=1e-15)
    assert float(moved[:, [0, 2]].detach().abs().max()) == 0.0


def test_rest_state_is_identity(field):
    X = _points(15, seed=6)
    H = field.num_handles_total
    w, dw = field.weights_and_gradients(X)
    z0 = torch.zeros(12 * H, dtype=torch.float64)
    assert torch.equal(deform(X, w, z0), X)
    F = deformation_gradient(gradient_basis(X, w, dw), z0)
    assert torch.equal(F, torch.eye(3, dtype=torch.float64).expand(15, 3, 3))


def test_rigid_motion_on_the_rigid_handle_gives_F_equal_R(field):
    X = _points(40, seed=8)
    H = field.num_handles_total
    R = _rotation([0.3, -1.0, 0.5], 1.1)
    t = torch.tensor([0.2, -0.4, 1.5], dtype=torch.float64)
    Z = torch.zeros(H, 3, 4, dtype=torch.float64)
    Z[-1, :, :3] = R - torch.eye(3, dtype=torch.float64)
    Z[-1, :, 3] = t
    z = Z.reshape(-1)
    w, dw = field.weights_and_gradients(X)
    F = deformation_gradient(gradient_basis(X, w, dw), z)
    assert torch.allclose(F, R.expand(40, 3, 3), atol=1e-14)
    assert torch.allclose(deform(X, w, z), X @ R.T + t, atol=1e-14)


def test_gradients_through_weights_and_gradients_match_finite_differences():
    tiny = SkinningField(num_handles=2, width=5, hidden_layers=1, seed=1).double()
    X = _points(6, seed=9)
    g = torch.Generator().manual_seed(2)
    cw = torch.randn(6, 3, generator=g, dtype=torch.float64)
    cd = torch.randn(6, 3, 3, generator=g, dtype=torch.float64)

    def objective() -> torch.Tensor:  # a generic scalar of w and dw (what the solver's adjoint sees)
        w, dw = tiny.weights_and_gradients(X)
        return (cw * w).sum() + (cd * dw).sum() + (dw**2).sum()

    params = list(tiny.parameters())
    grads = torch.autograd.grad(objective(), params)
    h = 1e-6
    checked = 0
    with torch.no_grad():
        for p, gp in zip(params, grads):
            flat, gflat = p.view(-1), gp.reshape(-1)
            for i in range(flat.numel()):
                old = float(flat[i])
                flat[i] = old + h
                up = float(objective())
                flat[i] = old - h
                down = float(objective())
                flat[i] = old
                assert abs((up - down) / (2 * h) - float(gflat[i])) < 1e-7 * max(1.0, abs(float(gflat[i])))
                checked += 1
    assert checked == 3 * 5 + 5 + 5 * 5 + 5 + 5 * 2 + 2
    assert max(float(gp.abs().max()) for gp in grads) > 1e-2


def test_bad_inputs_raise_clear_errors(field):
    X = _points(5)
    H = field.num_handles_total
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        field(torch.zeros(5, 2, dtype=torch.float64))
    bad = X.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        field.weights_and_gradients(bad)
    w = field(X)
    w32 = field(X.float())  # another dtype: evaluated in the field's, returned in the points'
    assert w32.dtype == torch.float32 and torch.allclose(w32.double(), w, atol=1e-6)
    with pytest.raises(ValueError, match=r"z must have shape \(132,\)"):
        deform(X, w, torch.zeros(12 * H - 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="w must have shape"):
        lbs_matrix(X, w[:4])
    with pytest.raises(ValueError, match="dw must have shape"):
        gradient_basis(X, w, torch.zeros(5, H, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"G must have shape"):
        dF_dz(torch.zeros(5, 3, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match="num_handles"):
        SkinningField(num_handles=0)


@pytest.mark.cuda
def test_cuda_matches_cpu(field):
    X = _points(64, seed=10)
    z = _z(field.num_handles_total)
    w, dw = field.weights_and_gradients(X)
    F = deformation_gradient(gradient_basis(X, w, dw), z)
    fc = SkinningField(num_handles=10, seed=7).double().cuda()
    wc, dwc = fc.weights_and_gradients(X.cuda())
    Fc = deformation_gradient(gradient_basis(X.cuda(), wc, dwc), z.cuda())
    assert torch.allclose(Fc.cpu(), F, atol=1e-12)
    assert torch.allclose(deform(X.cuda(), wc, z.cuda()).cpu(), deform(X, w, z), atol=1e-12)
