"""A rigid motion applied to a reduced state (vid2sim.physics.rigid_motion): exact on positions, velocities and F,
and the elastic dynamics without external forces commute with it (objectivity)."""

import math

import pytest
import torch

from vid2sim.physics import Material, SimConfig, Simulator
from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.rigid_motion import rigidly_moved, rotation_matrix

MOVE = dict(rotation=[0.3, -0.5, 0.8], translation=[0.1, -0.2, 0.05], linear=[0.4, 0.0, -0.3],
            angular=[1.5, -2.0, 0.5], centre=[0.05, 0.02, -0.1])


def _simulator(field, pts, externals):
    idx, w = sample_cubature(pts, 120, volume=1.0, seed=0)
    return Simulator(field, pts[idx], w, Material(1e5, 0.3, damping_ratio=0.05), externals, SimConfig(substeps=4))


def _moving_deformed_state(sim):
    with torch.no_grad():
        start = sim.rigid_velocity_state([0.2, 0.1, -0.5], [3.0, -1.0, 2.0])
        start.zdot = start.zdot + 0.3 * torch.linspace(-1.0, 1.0, start.zdot.numel(), dtype=start.zdot.dtype)
        return sim.rollout(start, 3)[-1]  # deformed, spinning, with a multistep history


def test_rodrigues_is_a_rotation_about_the_vector():
    r = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    R = rotation_matrix(r)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-14)
    assert float(torch.det(R)) == pytest.approx(1.0, abs=1e-14)
    assert torch.allclose(R @ r, r, atol=1e-14)  # the axis stays
    assert math.acos((float(torch.trace(R)) - 1) / 2) == pytest.approx(float(r.norm()), abs=1e-12)
    assert torch.equal(rotation_matrix(torch.zeros(3, dtype=torch.float64)), torch.eye(3, dtype=torch.float64))


def test_the_moved_state_puts_every_point_where_the_rigid_map_does(trained_field):
    field, pts = trained_field
    sim = _simulator(field, pts, [])
    state = _moving_deformed_state(sim)
    moved = rigidly_moved(state, **MOVE)
    R = rotation_matrix(torch.tensor(MOVE["rotation"], dtype=torch.float64))
    c, t = (torch.tensor(MOVE[k], dtype=torch.float64) for k in ("centre", "translation"))
    dv, dw = (torch.tensor(MOVE[k], dtype=torch.float64) for k in ("linear", "angular"))
    probe = pts[::7]
    with torch.no_grad():
        x, x2 = sim.positions(probe, state.z), sim.positions(probe, moved.z)
        v, v2 = sim.positions(probe, state.zdot) - probe, sim.positions(probe, moved.zdot) - probe  # x is linear in z
        F, F2 = sim.deformation_gradients(probe, state.z), sim.deformation_gradients(probe, moved.z)
    assert torch.allclose(x2, (x - c) @ R.T + c + t, atol=1e-12)
    assert torch.allclose(v2, v @ R.T + dv + torch.cross(dw.expand_as(x2), x2 - c - t, dim=1), atol=1e-12)
    assert torch.allclose(F2, R @ F, atol=1e-12)  # the same strain, turned
    assert moved.t == state.t and moved.z_prev is None
    assert float((x2 - x).norm(dim=1).max()) > 0.05  # it did move
    still = rigidly_moved(state, [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 2, 3])
    assert torch.equal(still.z, state.z) and torch.allclose(still.zdot, state.zdot, atol=1e-15)


def test_elastic_motion_without_external_forces_commutes_with_the_rigid_map(trained_field):
    """Objectivity: simulating the turned and shifted body is turning and shifting the simulated one (no gravity,
    no floor), to the Newton solver's tolerance."""
    field, pts = trained_field
    sim = _simulator(field, pts, [])
    state = _moving_deformed_state(sim)
    pose = dict(MOVE, linear=[0, 0, 0], angular=[0, 0, 0])
    start = rigidly_moved(state, **dict(pose, rotation=[0, 0, 0], translation=[0, 0, 0]))  # the same, no history
    with torch.no_grad():
        a = sim.rollout(rigidly_moved(start, **pose), 4)
        b = [rigidly_moved(s, **pose) for s in sim.rollout(start, 4)]
    size = float((pts.max(0).values - pts.min(0).values).norm())
    probe = pts[::7]
    for s, r in zip(a, b):
        assert float((sim.positions(probe, s.z) - sim.positions(probe, r.z)).norm(dim=1).max()) <= 1e-6 * size
    drift = (sim.positions(probe, a[-1].z) - sim.positions(probe, rigidly_moved(start, **pose).z)).norm(dim=1)
    assert float(drift.max()) > 0.05 * size  # it moved and deformed meanwhile


def test_bad_vectors_are_named(trained_field):
    field, pts = trained_field
    state = _simulator(field, pts, []).rest_state()
    with pytest.raises(ValueError, match="translation must hold 3 numbers"):
        rigidly_moved(state, **dict(MOVE, translation=[0.0, 1.0]))
