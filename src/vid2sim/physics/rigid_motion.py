"""A rigid motion applied to a reduced state: the same deformation, placed and moving otherwise.

The reduced model's last handle is the constant one (weight 1 everywhere, :meth:`Simulator.rigid_velocity_state`),
so any rigid map of the world, g(x) = R (x − c) + c + t, composes exactly with the skinning: with handle transforms
Z_j (3 × 4) and x = X + Σ_j w_j(X) Z_j [X; 1],

    g(x) = X + Σ_j w_j R Z_j [X; 1] + (R − I) X + c − R c + t,

so the moved state is Z_j' = R Z_j, with [R − I | c − R c + t] added to the constant handle. A velocity change
Δv + Δω × (x' − c'), c' = c + t, is linear in the moved positions and adds (S = [Δω]×) S Z_j' to every handle's
velocity, and [S | Δv − S c'] to the constant handle's. The body's shape and strain are unchanged; it is only put
elsewhere, turned, and given another rigid velocity (its deformation's rate turned with it).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.solver import SimState


def rotation_matrix(rotation_vector: Tensor) -> Tensor:
    """(3, 3) the rotation about ``rotation_vector``: (3,) (its direction the axis, its norm the angle in rad),
    by Rodrigues' formula."""
    r = rotation_vector
    K = skew(r)
    angle = float(r.norm())
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    if angle < 1e-12:
        return eye + K
    return eye + (torch.sin(r.norm()) / angle) * K + ((1 - torch.cos(r.norm())) / angle ** 2) * (K @ K)


def skew(w: Tensor) -> Tensor:
    """(3, 3) the cross-product matrix [w]× of w: (3,), so that [w]× x = w × x."""
    z = torch.zeros((), dtype=w.dtype, device=w.device)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


def rigidly_moved(state: SimState, rotation: Sequence[float], translation: Sequence[float],
                  linear: Sequence[float], angular: Sequence[float], centre: Sequence[float]) -> SimState:
    """``state`` carried by the rigid map x ↦ R(x − c) + c + t and given the velocity Δv + Δω × (x' − c − t) on
    top of its own (turned by R) — the module docstring's formulas.

    Args:
        state: a reduced state (z, zdot: (12H,), the last handle the constant one).
        rotation: (3,) the rotation vector of R (rad); translation: (3,) t (m); linear: (3,) Δv (m/s);
        angular: (3,) Δω (rad/s); centre: (3,) c (m), the point R turns about.
    Returns:
        a new :class:`SimState` at the same time, without the multistep history (its first substep is an implicit
        Euler step) and with the same plastic state (a rigid map does not change the material's).
    Raises:
        ValueError: a vector that does not hold 3 numbers, or a state whose size is not a multiple of 12.
    """
    vectors = {"rotation": rotation, "translation": translation, "linear": linear, "angular": angular,
               "centre": centre}
    dt, dev = state.z.dtype, state.z.device
    v = {k: torch.as_tensor(x, dtype=torch.float64, device=dev).reshape(-1) for k, x in vectors.items()}
    for k, x in v.items():
        if x.numel() != 3:
            raise ValueError(f"rigidly_moved: {k} must hold 3 numbers, got {x.numel()}")
    if state.z.numel() % 12 or state.z.shape != state.zdot.shape:
        raise ValueError(f"rigidly_moved: z and zdot must be (12H,), got {tuple(state.z.shape)}, "
                         f"{tuple(state.zdot.shape)}")
    H = state.z.numel() // 12
    R, S = rotation_matrix(v["rotation"]), skew(v["angular"])
    c, t = v["centre"], v["translation"]
    eye = torch.eye(3, dtype=torch.float64, device=dev)
    Z = R @ state.z.detach().double().reshape(H, 3, 4)
    Z[H - 1, :, :3] += R - eye
    Z[H - 1, :, 3] += c - R @ c + t
    Zd = R @ state.zdot.detach().double().reshape(H, 3, 4) + S @ Z
    Zd[H - 1, :, :3] += S
    Zd[H - 1, :, 3] += v["linear"] - S @ (c + t)
    return SimState(Z.reshape(-1).to(dt), Zd.reshape(-1).to(dt), state.t, state.Fp_inv)
