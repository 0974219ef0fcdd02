"""The contact surface without the hull's keel (reconstruct.stages.points.floor_carved_contact): a 4-view hull reaches
below the object, and the joint stage's coarse search can try the contact surface without the voxels that the tracked
rigid poses put below the floor (JointConfig.contact_search)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vid2sim.reconstruct.config import JointConfig, PointsConfig
from vid2sim.reconstruct.stages.points import (
    contact_surface,
    floor_carved_contact,
    points_from_occupancy,
    rigid_frames,
)
from vid2sim.runtime.errors import ConfigError

BIG = PointsConfig(num_points=500, max_contact_points=10_000)


def _box(layers: int = 8):
    """A 6 × 4 × ``layers`` box of 1 cm voxels in a 10³ grid whose corner is the origin: its occupancy and points."""
    occ = torch.zeros(10, 10, 10, dtype=torch.bool)
    occ[2:8, 3:7, 1:1 + layers] = True
    return occ, points_from_occupancy(occ, torch.zeros(3), 0.01, BIG)


def test_the_contact_surface_is_the_boxs_faces_with_their_area():
    """Every surface voxel of a 6 × 4 × 8 box, each with its exposed faces' area × 2/3: in all, 2/3 of the box's
    surface (the staircase correction); the points' own contact surface is the same."""
    occ, obj = _box()
    points, areas = contact_surface(occ, torch.zeros(3), 0.01, 10_000, seed=0)
    assert points.shape == (6 * 4 * 8 - 4 * 2 * 6, 3)
    surface = 2 * (0.06 * 0.04 + 0.06 * 0.08 + 0.04 * 0.08)
    assert float(areas.sum()) == pytest.approx(surface / 1.5, rel=1e-5)
    assert torch.equal(points, obj.contact_points) and torch.equal(areas, obj.contact_areas)


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_the_floor_carve_removes_what_any_pose_puts_below_the_floor():
    """Voxel centres lie at z = 0.015 … 0.085. Posed 4 cm down (frame 1) the two lowest layers (centres at −0.025 and
    −0.015) lie more than a voxel (1 cm) under the floor z = 0; posed unmoved (frame 0) nothing does: the carve
    takes those two layers, and the new bottom is a full face again. Tilted 90° about y about the box's centre, one
    side's layers go instead. Poses that put nothing below keep the hull's own surface, and a carve that would leave
    fewer than 8 voxels, or poses of the wrong shape, are errors."""
    occ, obj = _box()
    still = (np.stack([np.eye(3), np.eye(3)]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.04]]))
    points, areas, removed = floor_carved_contact(obj, *still, floor_height=0.0, config=BIG)
    assert removed == 2 * 6 * 4
    z = obj.contact_points[:, 2]
    assert float(points[:, 2].min()) == pytest.approx(float(z.min()) + 0.02, abs=1e-6)
    assert float(points[:, 2].max()) == pytest.approx(float(z.max()), abs=1e-6)
    assert float(areas.sum()) == pytest.approx(2 * (0.06 * 0.04 + 0.06 * 0.06 + 0.04 * 0.06) / 1.5, rel=1e-5)
    # a quarter turn about y through the box's centre (0.05, 0.05, 0.05): x ↦ z; the floor under its lowest layer
    R = _rotation_y(np.pi / 2)
    c = np.array([0.05, 0.05, 0.05])
    tilted = (R[None], (c - R @ c)[None] + np.array([0.0, 0.0, 0.0]))
    posed_z = (obj.contact_points.double().numpy() @ R.T + tilted[1][0])[:, 2]
    floor = float(posed_z.min()) + 0.015  # the lowest posed layer is 1.5 cm under it: only that layer goes
    points, _, removed = floor_carved_contact(obj, *tilted, floor_height=floor, config=BIG)
    assert removed == 8 * 4  # one x-layer of the 6 × 4 × 8 box
    assert float(points[:, 0].max()) == pytest.approx(float(obj.contact_points[:, 0].max()) - 0.01, abs=1e-6)
    none = floor_carved_contact(obj, *still, floor_height=-1.0, config=BIG)
    assert none[2] == 0 and torch.equal(none[0], obj.contact_points)
    with pytest.raises(ValueError, match="only 0 of 192 voxels"):
        floor_carved_contact(obj, *still, floor_height=1.0, config=BIG)
    with pytest.raises(ValueError, match=r"rotations must be \(T, 3, 3\)"):
        floor_carved_contact(obj, np.eye(3), np.zeros(3), floor_height=0.0)


def test_joint_config_contact_search_is_on_by_default():
    assert JointConfig().contact_search is True
    assert JointConfig().contact_search_residual_ratio == 1.25
    assert JointConfig(contact_search_residual_ratio=None).contact_search_residual_ratio is None
    for bad in (0.9, float("inf"), float("nan"), True, "2"):
        with pytest.raises(ConfigError, match="contact_search_residual_ratio"):
            JointConfig(contact_search_residual_ratio=bad)


def test_rigid_frames_take_the_flight_and_leave_out_the_squash():
    """The residuals of a soft twin's track (docs/capture.md, seventh entry): in flight about 0.27 px, rising from
    frame 4 as the body squashes. The limit is 1.25 × the median of frames 0–2 (0.2726 → 0.341): frames 0–3 and 13
    fit as in flight; the squash (4–12, 14, 15) is left out. A track that stays rigid keeps every frame."""
    soft = [0.2902, 0.2726, 0.2587, 0.2797, 0.3504, 0.3635, 0.413, 0.4259, 0.4471, 0.4379, 0.4026, 0.4335, 0.3963,
            0.3042, 0.3622, 0.3935]
    assert list(np.nonzero(rigid_frames(soft, 1.25))[0]) == [0, 1, 2, 3, 13]
    assert rigid_frames(soft, 2.0).all()
    stiff = [0.2294, 0.2084, 0.2016, 0.1979, 0.207, 0.2153, 0.2188, 0.2164, 0.2341, 0.2383]
    assert rigid_frames(stiff, 1.25).all() and rigid_frames([0.3], 1.25).all()
    with pytest.raises(ValueError, match="ratio must be >= 1"):
        rigid_frames(soft, 0.5)
    with pytest.raises(ValueError, match="non-empty"):
        rigid_frames([], 1.25)


def test_the_joint_stages_candidates_record_the_carve_and_skip_one_that_sinks_the_hull(monkeypatch):
    """contact_candidates offers the hull's surface, and the floor-carved one when the tracked poses put voxels below
    the floor; poses that would sink nearly all of it offer the hull alone and say why (the run goes on)."""
    from types import SimpleNamespace

    from vid2sim.reconstruct.stages import joint

    _, obj = _box()
    poses = SimpleNamespace(rotations=np.stack([np.eye(3)] * 2), translations=np.array([[0, 0, 0], [0, 0, -0.04]]),
                            num_frames=2, residuals_px=np.array([0.1, 0.2]))
    monkeypatch.setattr(joint, "track_poses", lambda *args, **kwargs: poses)
    state = SimpleNamespace(obj_cpu=obj)

    def candidates(floor: float, ratio: float | None = 1.25):
        config = SimpleNamespace(points=BIG, joint=JointConfig(contact_search_residual_ratio=ratio))
        ctx = SimpleNamespace(observed=SimpleNamespace(masks_cpu=None, cameras_cpu=None, floor_height=floor),
                              config=config)
        return joint.contact_candidates(ctx, state)

    contacts, record = candidates(0.0)
    assert list(contacts) == ["hull", "floor-carved"] and record["floor_carved_voxels"] == 48
    assert record["voxels"] == 192 and record["tracked_frames"] == 2 and record["residuals_px"] == [0.1, 0.2]
    assert record["rigid_frames"] == [0] and record["floor_carved_rigid_voxels"] == 0  # frame 0 sinks nothing
    # a squash: frames 2 and 3 fit twice as badly as in flight and sink 4 and 6 cm; frame 1 fits as in flight and
    # sinks 3 cm (a keel). Every frame's carve takes four layers, the rigid frames' one layer: three surfaces
    poses.rotations = np.stack([np.eye(3)] * 4)
    poses.translations = np.array([[0, 0, 0], [0, 0, -0.03], [0, 0, -0.04], [0, 0, -0.06]])
    poses.num_frames, poses.residuals_px = 4, np.array([0.1, 0.1, 0.2, 0.2])
    contacts, record = candidates(0.0)
    assert list(contacts) == ["hull", "floor-carved", "floor-carved-rigid"]
    assert record["floor_carved_voxels"] == 96 and record["floor_carved_rigid_voxels"] == 24
    assert record["rigid_frames"] == [0, 1]
    assert float(contacts["floor-carved-rigid"][0][:, 2].min()) == pytest.approx(
        float(obj.contact_points[:, 2].min()) + 0.01, abs=1e-6)
    contacts, record = candidates(0.0, None)  # no third surface
    assert list(contacts) == ["hull", "floor-carved"] and "rigid_frames" not in record
    # a squash that sinks the whole box below the floor: no carve of every frame, but the rigid frames' remains
    poses.translations = np.array([[0, 0, 0], [0, 0, -0.03], [0, 0, -0.04], [0, 0, -0.2]])
    contacts, record = candidates(0.0)
    assert list(contacts) == ["hull", "floor-carved-rigid"] and record["floor_carved_voxels"] is None
    assert "only 0 of 192 voxels" in record["skipped"] and record["floor_carved_rigid_voxels"] == 24
    poses.rotations = np.stack([np.eye(3)] * 2)
    poses.translations = np.array([[0, 0, 0], [0, 0, -0.04]])
    poses.num_frames, poses.residuals_px = 2, np.array([0.1, 0.2])
    contacts, record = candidates(-1.0)
    assert list(contacts) == ["hull"] and record["floor_carved_voxels"] == 0
    contacts, record = candidates(1.0)
    assert list(contacts) == ["hull"] and record["floor_carved_voxels"] is None
    assert "only 0 of 192 voxels" in record["skipped"]
