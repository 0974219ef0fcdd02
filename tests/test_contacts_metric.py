"""The contact and orientation measures of `evaluate` (vid2sim.metrics.contacts) against motions whose answer is
known in closed form."""

import math

import pytest
import torch

from vid2sim.metrics.contacts import body_rotations, contact_events, rotation_angles
from vid2sim.simulate.rotations import axis_angle_to_matrix


def _axis_angle(axis, angle: float) -> torch.Tensor:
    """The rotation about ``axis`` by ``angle`` radians."""
    return axis_angle_to_matrix([*axis, math.degrees(angle)])


def test_body_rotations_recover_a_rigid_turn_and_ignore_translation_and_a_symmetric_squash():
    g = torch.Generator().manual_seed(0)
    rest = torch.randn(40, 3, generator=g, dtype=torch.float64)
    masses = 0.5 + torch.rand(40, generator=g, dtype=torch.float64)
    truth = [_axis_angle((1.0, 2.0, -0.5), 0.3 * t) for t in range(5)]
    squash = torch.diag(torch.tensor([1.1, 1.1, 0.8], dtype=torch.float64))  # symmetric: a stretch, not a turn
    frames = torch.stack([(rest @ (R @ squash if t == 2 else R).T) + torch.tensor([t, -2.0 * t, 0.5])
                          for t, R in enumerate(truth)])
    found = body_rotations(frames, masses)
    assert torch.allclose(found[0], torch.eye(3, dtype=torch.float64), atol=1e-12)
    for t in (1, 3, 4):
        assert torch.allclose(found[t], truth[t], atol=1e-10)
    # the squash of frame 2 is about the rest shape's own axes, so the weighted fit keeps the turn to within a
    # small angle, well below the 0.6 rad the frame has turned
    assert rotation_angles(found[2:3], truth[2][None])[0] < 5.0
    with pytest.raises(ValueError, match=r"points must have shape \(T, N >= 3, 3\)"):
        body_rotations(torch.zeros(3, 2, 3))
    with pytest.raises(ValueError, match="masses must be"):
        body_rotations(frames, -masses)
    with pytest.raises(ValueError, match="not all zero"):
        body_rotations(frames, torch.zeros_like(masses))
    # a point without mass (a degenerate tet's centroid) does not count: moving it changes nothing
    massless = masses.clone()
    massless[0] = 0.0
    moved = frames.clone()
    moved[:, 0] += 5.0
    assert torch.allclose(body_rotations(moved, massless), body_rotations(frames, massless), atol=1e-10)


def test_rotation_angles_are_the_relative_rotations_angle_in_degrees():
    a = torch.stack([_axis_angle((0, 0, 1), math.radians(d)) for d in (0.0, 10.0, 90.0, 180.0)])
    b = torch.stack([_axis_angle((0, 0, 1), math.radians(d)) for d in (0.0, -5.0, 30.0, 0.0)])
    assert rotation_angles(a, b) == pytest.approx([0.0, 15.0, 60.0, 180.0], abs=1e-5)
    with pytest.raises(ValueError, match="rotations must both be"):
        rotation_angles(a, b[:2])


def test_contact_events_find_a_bounce_between_frames_a_resting_contact_and_no_free_flight():
    g, dt = 9.8, 0.05

    def bouncing(t: float) -> float:  # dropped from 0.5 m onto z = 0, elastic bounce (restitution 1) at t0
        t0 = math.sqrt(2 * 0.5 / g)
        s = t if t < t0 else 2 * t0 - t
        return 0.5 - 0.5 * g * s * s

    times = [k * dt for k in range(12)]
    # t0 = 0.319 s: between frames 6 and 7 (0.30 and 0.35 s); no frame sees the body at the floor
    events = contact_events(torch.tensor([bouncing(t) for t in times]), dt, g)
    assert [(e.first, e.last, e.before, e.after) for e in events] == [(6, 7, 5, 8)]
    assert contact_events(torch.tensor([2.0 - 0.5 * g * t * t for t in times]), dt, g) == []  # free fall
    landing = [max(0.1, 0.4 - 0.5 * g * t * t) for t in times]  # lands at 0.247 s (frames 4–5), stays there
    events = contact_events(torch.tensor(landing), dt, g)
    # frame 4's two intervals hold too short a push; the event runs to T − 2, the last frame with a difference
    assert [(e.first, e.last) for e in events] == [(5, 10)] and events[0].before * dt < 0.247 < events[0].first * dt
    assert contact_events(torch.tensor([0.0, 1.0]), dt, g) == []
    with pytest.raises(ValueError, match="dt > 0"):
        contact_events(torch.zeros(5), 0.0, g)


def test_motion_around_contacts_charges_a_bounce_with_the_turn_it_adds():
    """A reference body bounces; the 'simulated' one follows it exactly but turns 10° more about z from the frame
    after the bounce: the orientation error is 0 before and 10° after, the bounce adds 10° and no centre-of-mass
    error, and both bodies' contact frames are the same."""
    from vid2sim.metrics.contacts import motion_around_contacts

    g, dt, T = 9.8, 0.05, 12
    t0 = math.sqrt(2 * 0.5 / g)
    heights = [0.5 - 0.5 * g * (t if t < t0 else 2 * t0 - t) ** 2 for t in (k * dt for k in range(T))]
    rest = torch.randn(30, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    rest = rest - rest.mean(0)  # centred: the centre of mass follows the heights
    spin = [_axis_angle((1.0, 0.0, 0.0), 0.2 * k) for k in range(T)]
    truth = torch.stack([rest @ spin[k].T + torch.tensor([0.0, 0.0, heights[k]]) for k in range(T)])
    extra = _axis_angle((0.0, 0.0, 1.0), math.radians(10.0))
    sim = torch.stack([(rest @ (extra @ spin[k]).T if k >= 8 else rest @ spin[k].T) + torch.tensor([0, 0, heights[k]])
                       for k in range(T)])
    m = torch.ones(30, dtype=torch.float64)
    out = motion_around_contacts(sim, m, truth, m, [0.0] * T, dt, (0.0, 0.0, -g), range(1, 8), range(8, T))
    angles = out["orientation"]["per_frame_deg"]
    assert angles[:8] == pytest.approx([0.0] * 8, abs=1e-5) and angles[8:] == pytest.approx([10.0] * 4, abs=1e-5)
    assert out["orientation"]["future_mean_deg"] == pytest.approx(10.0, abs=1e-5)
    (event,) = out["contacts"]["truth"]
    assert (event["before"], event["after"]) == (5, 8)
    assert out["contacts"]["first_added_rotation_deg"] == pytest.approx(10.0, abs=1e-5)
    assert out["contacts"]["first_added_centre_of_mass_m"] == 0.0
    assert out["contacts"]["simulated_frames"] == [event["frames"]]
