"""Impact compliance of quadratic tets and of the skinning subspace against the free bar's analytic answer."""

import numpy as np
import pytest
import torch

from vid2sim.meshing.tetra import box_tet_mesh
from vid2sim.physics.contact_compliance import (
    contact_layer_calibration,
    subspace_impact_compliance,
    tet_impact_compliance,
)
from vid2sim.physics.tet_modes import TET_EDGES, quadratic_tet_nodes

L, W = 2.0, 0.5  # bar length (x) and square cross-section side


class _Field(torch.nn.Module):
    """LBS weights [x, 1] (one linear handle and the rigid one): its span holds the free bar's exact answer."""

    num_handles_total = 2

    def forward(self, X):
        return torch.stack([X[:, 0], torch.ones_like(X[:, 0])], dim=1)

    def weights_and_gradients(self, X):
        dw = torch.zeros(X.shape[0], 2, 3, dtype=X.dtype)
        dw[:, 0, 0] = 1.0
        return self(X), dw


class _RigidOnly(_Field):
    """Only the affine handle: uniform strain, stiffer than the bar under an end load."""

    num_handles_total = 1

    def forward(self, X):
        return torch.ones_like(X[:, :1])

    def weights_and_gradients(self, X):
        return self(X), torch.zeros(X.shape[0], 1, 3, dtype=X.dtype)


def _bar():
    mesh = box_tet_mesh((L, W, W), (8, 2, 2))
    return mesh.vertices.double().numpy(), mesh.tets.numpy()


def _end_traction(vertices, tets, total: float) -> tuple[np.ndarray, np.ndarray]:
    """Consistent P2 nodes and forces (along −x) of a uniform traction on the face x = L: each boundary
    triangle gives a third of its load to each edge midpoint and none to its corners."""
    nodes, elements = quadratic_tet_nodes(vertices, tets)
    midpoint = {}
    for e, (i, j) in enumerate(TET_EDGES):
        for a, b, m in zip(elements[:, i], elements[:, j], elements[:, 4 + e]):
            midpoint[(min(a, b), max(a, b))] = m
    on_end = np.isclose(vertices[:, 0], L)
    force = np.zeros_like(nodes)
    faces = set()
    for t in tets:
        for f in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
            tri = tuple(sorted(t[list(f)]))
            if all(on_end[list(tri)]):
                faces.add(tri)
    for a, b, c in faces:
        area = 0.5 * np.linalg.norm(np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a]))
        for p, q in ((a, b), (b, c), (a, c)):
            force[midpoint[(min(p, q), max(p, q))], 0] -= total * area / (3 * W * W)
    loaded = np.flatnonzero(np.abs(force).sum(1) > 0)
    return loaded, force[loaded]


def _exact(total: float) -> float:
    """The free bar pushed at one end, quasi-static with inertia relief: N(x) falls linearly to 0 at the far end,
    C = ∫ N² / (E A) dx = F² L / (3 E A) at E = 1, whatever ν (the strains are linear in x: compatible)."""
    return total ** 2 * L / (3 * W * W)


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.45])
def test_tet_compliance_matches_the_free_bar(nu):
    vertices, tets = _bar()
    nodes, _ = quadratic_tet_nodes(vertices, tets)
    loaded, forces = _end_traction(vertices, tets, 3.0)
    f = np.zeros_like(nodes)
    f[loaded] = forces
    # quadratic tets hold the exact (quadratic) displacement: agreement to round-off
    assert tet_impact_compliance(vertices, tets, f, nu) == pytest.approx(_exact(3.0), rel=1e-8)


def test_subspace_compliance_matches_the_free_bar_when_its_span_holds_the_answer():
    vertices, tets = _bar()
    n = (80, 20, 20)  # a midpoint grid: quadrature error O(h²)
    axes = [(np.arange(k) + 0.5) / k * s for k, s in zip(n, (L, W, W))]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    X = torch.from_numpy(grid)
    vol = torch.full((len(grid),), L * W * W / len(grid), dtype=torch.float64)
    loaded, forces = _end_traction(vertices, tets, 3.0)
    nodes, _ = quadratic_tet_nodes(vertices, tets)
    for nu in (0.0, 0.3):
        c = subspace_impact_compliance(_Field(), X, vol, torch.from_numpy(nodes[loaded]), forces, nu)
        assert c == pytest.approx(_exact(3.0), rel=2e-3)
        stiff = subspace_impact_compliance(_RigidOnly(), X, vol, torch.from_numpy(nodes[loaded]), forces, nu)
        # Rayleigh–Ritz: a smaller span is stiffer; uniform strain gives exactly 1/4 of the bar's here:
        # the best uniform N is the mean of the linear profile, C = F² L / (4 E A)
        assert stiff == pytest.approx(0.75 * _exact(3.0), rel=2e-3)

    areas = np.full(len(loaded), W * W / len(loaded))
    exact_span = contact_layer_calibration(_Field(), X, vol, vertices, tets, loaded, forces, areas, 0.3)
    assert abs(exact_span.raw_layer) < 1e-2 * L and exact_span.compliance_ratio == pytest.approx(1.0, rel=3e-3)
    rigid = contact_layer_calibration(_RigidOnly(), X, vol, vertices, tets, loaded, forces, areas, 0.3)
    # the layer adds the missing quarter: (1 − ν²) h / 2 · Σ |F|² / a = C_tet − C_sub
    missing = _exact(3.0) * 0.25
    per_area = float(((forces ** 2).sum(1) / areas).sum())
    assert rigid.layer == pytest.approx(2 * missing / ((1 - 0.09) * per_area), rel=3e-3)
    assert rigid.compliance_ratio == pytest.approx(4 / 3, rel=3e-3)
    # a stiffness scale below 1 already softens the subspace: s = 0.5 makes it the softer one, clamped to 0
    soft = contact_layer_calibration(_RigidOnly(), X, vol, vertices, tets, loaded, forces, areas, 0.3,
                                     stiffness_scale=0.5)
    assert soft.raw_layer < 0 and soft.layer == 0.0


def test_bad_loads_are_named():
    vertices, tets = _bar()
    X = torch.rand(50, 3, dtype=torch.float64)
    vol = torch.full((50,), 0.01, dtype=torch.float64)
    with pytest.raises(ValueError, match="forces"):
        contact_layer_calibration(_Field(), X, vol, vertices, tets, np.array([0, 1]), np.zeros((3, 3)),
                                  np.ones(2), 0.3)
    with pytest.raises(ValueError, match="areas"):
        contact_layer_calibration(_Field(), X, vol, vertices, tets, np.array([0]), np.ones((1, 3)),
                                  np.zeros(1), 0.3)
    with pytest.raises(ValueError, match="node_forces"):
        tet_impact_compliance(vertices, tets, np.zeros((3, 3)), 0.3)


def _bar_simulator(k_floor: float = 5e7):
    """A reduced simulator of the bar (an untrained 2-handle field) whose contact points are the bottom face's
    quadratic nodes, with equal areas, above a floor at z = 0."""
    from vid2sim.physics import (
        Floor,
        Gravity,
        Material,
        SimConfig,
        Simulator,
        SkinningField,
    )

    vertices, tets = _bar()
    nodes, _ = quadratic_tet_nodes(vertices, tets)
    bottom = np.flatnonzero(np.isclose(nodes[:, 2], 0.0))
    g = torch.Generator().manual_seed(0)
    X = torch.rand(400, 3, generator=g, dtype=torch.float64) * torch.tensor([L, W, W], dtype=torch.float64)
    vol = torch.full((400,), L * W * W / 400, dtype=torch.float64)
    field = SkinningField(num_handles=2, seed=0).double()
    for p in field.parameters():
        p.requires_grad_(False)
    sim = Simulator(field, X, vol, Material(1e5, 0.3, 1000.0), [Gravity(), Floor(height=0.0, stiffness=k_floor)],
                    SimConfig(), length_scale=1.0, contact_points=torch.from_numpy(nodes[bottom]),
                    contact_weights=torch.full((len(bottom),), L * W / len(bottom), dtype=torch.float64))
    return sim, vertices, tets, bottom


def _posed(sim, angle: float, shift) -> "object":
    """The rest state moved rigidly: rotated by ``angle`` about x, then translated by ``shift``."""
    state = sim.rest_state()
    c, s = np.cos(angle), np.sin(angle)
    R = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)
    z = state.z.reshape(-1, 3, 4).clone()
    z[-1, :, :3] = R - torch.eye(3, dtype=torch.float64)
    z[-1, :, 3] = torch.as_tensor(shift, dtype=torch.float64)
    state.z = z.reshape(-1)
    return state


def test_simulated_contact_loads_are_the_floor_forces_in_the_rest_frame():
    from vid2sim.physics.contact_compliance import simulated_contact_loads

    sim, *_ = _bar_simulator()
    above = _posed(sim, 0.0, (0.0, 0.0, 0.1))
    down = _posed(sim, 0.0, (0.0, 0.0, -0.01))
    loads = simulated_contact_loads(sim, [above, down])
    assert len(loads) == 1  # the state above the floor has none
    touching, forces = loads[0]
    w = sim.contact_weights.numpy()
    assert len(touching) == len(w)
    np.testing.assert_allclose(forces[:, 2], 2 * 5e7 * w * 0.01, rtol=1e-9)
    np.testing.assert_allclose(forces[:, :2], 0.0, atol=1e-9)
    # tilted by 0.3 rad about x: the floor normal seen from the body is Rᵀ e_z, the depths follow the tilt
    tilted = _posed(sim, 0.3, (0.0, 0.0, -0.2))
    touching, forces = simulated_contact_loads(sim, [tilted])[0]
    up = np.array([0.0, np.sin(0.3), np.cos(0.3)])
    np.testing.assert_allclose(forces / np.linalg.norm(forces, axis=1, keepdims=True), np.tile(up, (len(forces), 1)),
                               atol=1e-9)
    x = sim.positions(sim.contact_points, tilted.z).numpy()[touching]
    np.testing.assert_allclose(np.linalg.norm(forces, axis=1), 2 * 5e7 * w[touching] * (-x[:, 2]), rtol=1e-9)
    # a contact layer acts in series with the floor: the same depth gives less force
    sim.contact_layer = 0.05
    k_b = float(sim.contact_layer_stiffness())
    softened = simulated_contact_loads(sim, [down])[0][1]
    np.testing.assert_allclose(softened[:, 2], 2 * 5e7 / (1 + 5e7 / k_b) * w * 0.01, rtol=1e-9)


def test_contact_layer_from_simulation_adds_the_compliance_the_subspace_misses():
    from vid2sim.physics.contact_compliance import (
        TetCompliance,
        contact_layer_from_simulation,
        simulated_contact_loads,
    )

    sim, vertices, tets, bottom = _bar_simulator()
    tet = TetCompliance(vertices, tets, 0.3)
    states = [_posed(sim, 0.0, (0.0, 0.0, -0.01)), _posed(sim, 0.3, (0.0, 0.0, -0.2))]
    cal = contact_layer_from_simulation(sim, states, tet, bottom, 0.3, 0.8)
    # the same sums by hand, load by load
    c_tet = c_sub = per_area = 0.0
    w = sim.contact_weights.numpy()
    for touching, forces in simulated_contact_loads(sim, states):
        f = np.zeros_like(tet.nodes)
        f[bottom[touching]] = forces
        c_tet += tet.compliance(f)
        c_sub += subspace_impact_compliance(sim.field, sim.X, sim.vol, sim.contact_points[touching], forces, 0.3)
        per_area += float(((forces ** 2).sum(1) / w[touching]).sum())
    assert cal.tet_compliance == pytest.approx(c_tet) and cal.subspace_compliance == pytest.approx(c_sub)
    assert cal.raw_layer == pytest.approx(2 * (0.8 * c_tet - c_sub) / (0.91 * per_area))
    # a two-handle subspace is far stiffer than the bar under a face load: a positive layer
    assert cal.layer == cal.raw_layer > 0 and cal.compliance_ratio > 1
    with pytest.raises(ValueError, match="never touches"):
        contact_layer_from_simulation(sim, [_posed(sim, 0.0, (0.0, 0.0, 0.1))], tet, bottom, 0.3, 0.8)
