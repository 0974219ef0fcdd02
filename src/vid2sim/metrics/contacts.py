"""The motion around each contact: when a body touches the floor, and its orientation against a reference's.

A drop's errors grow at its contacts: where and how the body first touches the floor decides how it spins away.
These measures split a simulated motion's error into what each contact adds (issue #51, "contact and the
bounce"):

- :func:`body_rotations`: the rotation of a moving body from its first frame, per frame — the mass-weighted
  best rigid fit (Kabsch) of its points' positions around their centre of mass, so that a deforming body's
  squash does not count as a turn;
- :func:`rotation_angles`: the angle between two bodies' rotations per frame (degrees);
- :func:`contact_events`: the frames around which the floor pushed a body, from its centre of mass alone: in free
  flight the second difference of the height is −|g| dt²; a frame whose second difference is above
  −``threshold`` |g| dt² had a net upward push from the floor within one frame either side (a bounce between two
  frames included, which a test of the lowest point at the frames would miss);
- :func:`motion_around_contacts`: the two together for a simulated body against a reference, as ``vid2sim
  evaluate`` and ``bench identify`` report them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

from vid2sim.metrics.trajectory import best_rotation


def body_rotations(points: Tensor, masses: Tensor | None = None) -> Tensor:
    """The rotation of a body from its first frame to each frame, (T, 3, 3) float64.

    Args:
        points: (T, N, 3) positions of the body's points (N ≥ 3, not all on one line at frame 0).
        masses: (N,) weights ≥ 0 with a positive sum (default equal; a point of zero mass, e.g. a degenerate
            tet's centroid, does not count).

    Returns:
        R: (T, 3, 3) with R[0] = I: the proper rotation minimising Σ m_p ‖R (x_p(0) − c(0)) − (x_p(t) − c(t))‖²,
        c the weighted centre of mass.
    """
    X = torch.as_tensor(points).detach().to(torch.float64)
    if X.ndim != 3 or X.shape[-1] != 3 or X.shape[1] < 3:
        raise ValueError(f"points must have shape (T, N >= 3, 3), got {tuple(X.shape)}")
    m = torch.ones(X.shape[1], dtype=X.dtype) if masses is None else torch.as_tensor(masses).detach().double().cpu()
    if m.shape != (X.shape[1],) or not bool((m >= 0).all()) or not float(m.sum()) > 0:
        raise ValueError(f"masses must be ({X.shape[1]},), non-negative and not all zero, got shape "
                         f"{tuple(m.shape)} and sum {float(m.sum()) if m.numel() else 0.0}")
    return best_rotation(X[:1].expand_as(X), X, m.to(X.device))


def rotation_angles(a: Tensor, b: Tensor) -> list[float]:
    """Per frame, the angle (degrees) of the rotation a[t] b[t]ᵀ between two bodies' rotations a, b: (T, 3, 3)."""
    if a.shape != b.shape or a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"rotations must both be (T, 3, 3), got {tuple(a.shape)} and {tuple(b.shape)}")
    rel = a.double() @ b.double().transpose(1, 2)
    cos = ((rel.diagonal(dim1=1, dim2=2).sum(1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return [math.degrees(v) for v in torch.arccos(cos).tolist()]


@dataclass
class ContactEvent:
    """Consecutive frames around which the floor pushed the body.

    Attributes:
        first, last: the frames whose height's second difference shows the push (the contact lies within
            [first − 1, last + 1]).
        before: first − 1, the last frame before it; after: last + 1, the first frame after it (both exist: the
            second difference needs a frame either side).
    """

    first: int
    last: int

    @property
    def before(self) -> int:
        return self.first - 1

    @property
    def after(self) -> int:
        return self.last + 1


def contact_events(centre_heights: Tensor, dt: float, gravity: float, threshold: float = 0.5) -> list[ContactEvent]:
    """The contacts of a body with the floor from its centre of mass's height per frame.

    Args:
        centre_heights: (T,) height of the centre of mass along up (m), one per frame.
        dt: the time between frames (s), > 0.
        gravity: |g| (m/s²), > 0.
        threshold: the share of gravity the floor's mean push over the two frame intervals around a frame must
            exceed (0.5: a contact holds the body up by at least half its weight over 2 dt).

    Returns:
        the events in time order (empty for fewer than 3 frames or a free flight).
    """
    z = torch.as_tensor(centre_heights).detach().double().cpu().reshape(-1)
    if not (dt > 0 and gravity > 0 and 0 < threshold <= 1):
        raise ValueError(f"contact_events needs dt > 0, gravity > 0 and 0 < threshold <= 1, got {dt}, {gravity}, "
                         f"{threshold}")
    T = z.shape[0]
    if T < 3:
        return []
    accel = (z[2:] - 2.0 * z[1:-1] + z[:-2]) / (dt * dt)  # frames 1 … T−2
    touching = [t + 1 for t, a in enumerate(accel.tolist()) if a > -(1.0 - threshold) * gravity]
    events: list[ContactEvent] = []
    for t in touching:
        if events and t == events[-1].last + 1:
            events[-1].last = t
        else:
            events.append(ContactEvent(t, t))
    return events


def motion_around_contacts(points: Tensor, masses: Tensor, true_points: Tensor, true_masses: Tensor,
                           offset: Sequence[float], dt: float, gravity: Sequence[float], observed: Sequence[int],
                           future: Sequence[int]) -> dict[str, Any]:
    """A simulated body's rotation and its errors around each of the reference's contacts with the floor.

    Args:
        points, masses: (T, N, 3) the simulated body's points per frame and (N,) their masses.
        true_points, true_masses: (T, M, 3) and (M,) the same of the reference (the ground truth).
        offset: (T,) the distance between the two centres of mass per frame (m).
        dt: time between frames (s); gravity: (3,) the gravity vector (m/s², along −up).
        observed, future: the frames averaged as the observed and the future means (future may be empty).

    Returns:
        {"orientation": per-frame angles (deg) between the two bodies' rotations from frame 0 and their means,
        "contacts": the reference's contacts (:func:`contact_events` of its centre of mass) each with the
        centre-of-mass and rotation errors on the frames before and after it and what it added, the first contact's
        additions, and the simulated body's own contact frames}.
    """
    angles = rotation_angles(body_rotations(points, masses), body_rotations(true_points, true_masses))
    g = torch.as_tensor(gravity, dtype=torch.float64)
    up = -g / g.norm()

    def centre_heights(x: Tensor, m: Tensor) -> Tensor:
        w = torch.as_tensor(m).double().cpu()
        return (w[None, :, None] * torch.as_tensor(x).double().cpu()).sum(1) @ up / w.sum()

    def around(values: Sequence[float], event: ContactEvent) -> dict[str, float]:
        return {"before": values[event.before], "after": values[event.after],
                "added": values[event.after] - values[event.before]}

    events = contact_events(centre_heights(true_points, true_masses), dt, float(g.norm()))
    simulated = contact_events(centre_heights(points, masses), dt, float(g.norm()))
    return {
        "orientation": {
            "per_frame_deg": angles,
            "observed_mean_deg": sum(angles[f] for f in observed) / len(observed),
            "future_mean_deg": sum(angles[f] for f in future) / len(future) if future else None,
            "units": "degrees (the angle between the simulated body's rotation from frame 0 and the truth's, each "
                     "the mass-weighted best rigid fit of its points)",
        },
        "contacts": {
            "truth": [{"frames": [e.first, e.last], "before": e.before, "after": e.after,
                       "centre_of_mass_m": around(offset, e), "rotation_deg": around(angles, e)} for e in events],
            "first_added_centre_of_mass_m": around(offset, events[0])["added"] if events else None,
            "first_added_rotation_deg": around(angles, events[0])["added"] if events else None,
            "simulated_frames": [[e.first, e.last] for e in simulated],
            "what": "the frames around which the floor pushed the body (its centre of mass's height departs from "
                    "free fall by more than half of gravity), the truth's with the errors on the frame before and "
                    "after each and what the contact added (first_added_*: the first contact's); the simulated "
                    "body's frames for comparison",
        },
    }
