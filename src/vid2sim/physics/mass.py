"""The body's mass properties on the cubature points: moment-matched lumped masses.

The reduced simulator lumps the mass at its K cubature points (ρ·v_p). A few hundred random points get the
total mass right (Σ v_p is the volume) but not where it sits: on the ``bench identify`` objects 500 points put
the centre of mass 3–4 mm (of a 1 m object) off and the second moments (the inertia tensor) 6–7 % off. The
kinetic energy of a rigid — indeed of any affine — motion depends on exactly these moments, and a bounce
splits the floor's impulse between translation and rotation by them: with the sampled moments the reduced
model of two benchmark objects rebounded too low and a fit of ν compensated with a ν far too low.

:func:`moment_matched_volumes` corrects the lumped volumes, as little as it can in relative entropy, so that
they integrate 1, x and x xᵀ exactly (10 linear constraints) and stay positive:

    v_p' = v_p exp(a_pᵀ λ),   a_p = (1, x_p, upper triangle of x_p x_pᵀ),   Σ_p v_p' a_p = m,

with m the body's moments: exact from a tet mesh
(:func:`tet_moments`) or from many uniform samples of the body (:func:`sampled_moments`). The elastic energy
keeps its own cubature weights; only the inertia and the body forces (gravity) use these
(``Simulator(mass_volumes=...)``).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: the number of moments matched: volume, first moments (3), second moments (6)
NUM_MOMENTS = 10


def moment_features(points: Tensor) -> Tensor:
    """a_p = (1, x, y, z, xx, xy, xz, yy, yz, zz) per point: (N, 10) for points (N, 3)."""
    iu = torch.triu_indices(3, 3, device=points.device)
    second = (points[:, :, None] * points[:, None, :])[:, iu[0], iu[1]]
    return torch.cat([torch.ones_like(points[:, :1]), points, second], dim=1)


def tet_moments(vertices: Tensor, tets: Tensor) -> Tensor:
    """∫ a(x) dV over a tet mesh, exact: (10,) in the layout of :func:`moment_features`.

    Args:
        vertices: (Nv, 3); tets: (Nt, 4) vertex indices (either orientation).
    Uses ∫_T x xᵀ dV = |T| / 20 (Σ_i v_i v_iᵀ + s sᵀ) with s = Σ_i v_i over the tet's four vertices.
    """
    v = vertices[tets.long()]  # (Nt, 4, 3)
    vol = torch.linalg.det(v[:, 1:] - v[:, :1]).abs() / 6.0
    s = v.sum(1)
    second = (torch.einsum("tia,tib->tab", v, v) + s[:, :, None] * s[:, None, :]) * (vol / 20.0)[:, None, None]
    iu = torch.triu_indices(3, 3, device=vertices.device)
    return torch.cat([vol.sum()[None], (s * (vol / 4.0)[:, None]).sum(0), second.sum(0)[iu[0], iu[1]]])


def voxel_moments(occupancy: Tensor, origin: Tensor, voxel: float) -> Tensor:
    """∫ a(x) dV over the union of the occupied voxels, exact: (10,).

    Args:
        occupancy: (A, B, C) bool; voxel (i, j, k) is the cube origin + [i, i+1] × [j, j+1] × [k, k+1] · voxel.
        origin: (3,) the grid's corner; voxel: the side (m).
    A cube of side a about c has ∫ x xᵀ = a³ (c cᵀ + a²/12 I).
    """
    centres = origin.double() + (torch.nonzero(occupancy).double() + 0.5) * float(voxel)
    cube = float(voxel) ** 3
    m = moment_features(centres).sum(0) * cube
    m[[4, 7, 9]] += centres.shape[0] * cube * float(voxel) ** 2 / 12.0  # the diagonal (xx, yy, zz)
    return m


def sampled_moments(points: Tensor, volume: float) -> Tensor:
    """The moments of a body estimated from (N, 3) uniform samples of it and its volume: (10,)."""
    return moment_features(points).mean(0) * volume


def lumped_moments(points: Tensor, volumes: Tensor) -> Tensor:
    """The moments Σ_p v_p a(x_p) (10,), float64 on the CPU, of volumes (K,) lumped at points (K, 3)."""
    return (moment_features(points.double()).T @ volumes.double()).cpu()


def translated_moments(moments: Tensor, offset: Tensor) -> Tensor:
    """The moments (10,) of the same body translated by ``offset`` (3,): its centre of mass moves by the offset,
    its volume and its second moments about the centre of mass (the inertia tensor) stay.

    ∫ (x + d)(x + d)ᵀ = S + f dᵀ + d fᵀ + V d dᵀ and ∫ (x + d) = f + V d, with f, S the first and second moments."""
    return _moments_in_frame(moments.double().cpu(), -offset.double().cpu(), 1.0)


def centre_shifted_volumes(points: Tensor, volumes: Tensor, offset: Tensor) -> Tensor:
    """Lumped volumes (K,) on the same points whose centre of mass lies ``offset`` (3,) from that of ``volumes``
    (K,), with the same total and the same inertia about the centre (:func:`moment_matched_volumes` on
    :func:`translated_moments` of their own moments). A zero offset gives ``volumes`` back.

    Raises:
        ValueError: when no positive volumes on these points have those moments (an offset too large for them)."""
    if offset.shape != (3,):
        raise ValueError(f"centre_shifted_volumes: offset must be (3,), got {tuple(offset.shape)}")
    if not bool(offset.ne(0).any()):
        return volumes
    moments = translated_moments(lumped_moments(points, volumes), offset)
    return moment_matched_volumes(points, volumes, moments.to(volumes))


def moment_matched_volumes(points: Tensor, volumes: Tensor, moments: Tensor, max_iterations: int = 100) -> Tensor:
    """Lumped volumes (K,) closest to ``volumes`` that integrate 1, x, x xᵀ to ``moments``; positive by construction.

    "Closest" in relative entropy Σ v' ln(v'/v) − v' + v: the solution is the exponential tilt v'_p = v_p exp(a_pᵀ λ),
    λ found by Newton's method on the convex dual Σ_p v_p exp(a_pᵀ λ) − λᵀ m.

    Args:
        points: (K, 3) the cubature points (K ≥ 10, not all on one quadric).
        volumes: (K,) their volumes, > 0.
        moments: (10,) the body's moments (:func:`tet_moments`, :func:`voxel_moments` or :func:`sampled_moments`),
            in the points' frame and units.
        max_iterations: Newton iterations.
    Raises:
        ValueError: when the points cannot carry the moments — too few of them, all on a quadric, or moments
            outside what positive volumes on these points can make (e.g. of another body or frame).
    """
    if points.ndim != 2 or points.shape[1] != 3 or volumes.shape != points.shape[:1]:
        raise ValueError(f"moment_matched_volumes: points must be (K, 3) and volumes (K,), got {tuple(points.shape)} "
                         f"and {tuple(volumes.shape)}")
    if moments.shape != (NUM_MOMENTS,):
        raise ValueError(f"moment_matched_volumes: moments must be ({NUM_MOMENTS},), got {tuple(moments.shape)}")
    if points.shape[0] < NUM_MOMENTS:
        raise ValueError(f"moment_matched_volumes: {NUM_MOMENTS} moments need at least {NUM_MOMENTS} points, "
                         f"got {points.shape[0]}")
    x, v, m = points.double().cpu(), volumes.double().cpu(), moments.double().cpu()
    centre = x.mean(0)
    scale = float((x - centre).norm(dim=1).max()) or 1.0
    A = moment_features((x - centre) / scale)  # conditioned: centred, unit-size coordinates, the same span
    target = _moments_in_frame(m, centre, scale)
    if torch.linalg.matrix_rank(A * v.sqrt()[:, None]) < NUM_MOMENTS:
        raise ValueError(f"moment_matched_volumes: the {points.shape[0]} points lie on a quadric and cannot carry "
                         "the body's moments")
    lam = torch.zeros(NUM_MOMENTS, dtype=torch.float64)

    def dual(l: Tensor) -> float:
        return float((v * torch.exp(A @ l)).sum() - l @ target)

    for _ in range(max_iterations):
        tilted = v * torch.exp(A @ lam)
        grad = A.T @ tilted - target
        if float(grad.norm()) <= 1e-12 * float(target.norm()):
            return (v * torch.exp(A @ lam)).to(device=volumes.device, dtype=volumes.dtype)
        step = torch.linalg.solve(A.T @ (tilted[:, None] * A), grad)
        t, f0, decrease = 1.0, dual(lam), float(grad @ step)  # the Newton decrement², ≥ 0
        # Backtrack on the dual's value, unless the predicted decrease is below the rounding of its two terms: there
        # (the quadratically convergent end) the Armijo test would judge rounding noise and stall; take the full step.
        if decrease > 1e-13 * (float(tilted.sum()) + abs(float(lam @ target))):
            while t > 1e-10 and not dual(lam - t * step) <= f0 - 1e-4 * t * decrease:
                t *= 0.5
        lam = lam - t * step
    raise ValueError(f"moment_matched_volumes: no positive volumes on these {points.shape[0]} points carry the "
                     "body's moments (Newton did not converge); use more cubature points or check that the moments "
                     "are of the same body in the same frame")


def _moments_in_frame(m: Tensor, centre: Tensor, scale: float) -> Tensor:
    """The moments (10,) of the same body in the coordinates x' = (x − c) / s."""
    iu = torch.triu_indices(3, 3)
    V, first = m[0], m[1:4]
    second = torch.zeros(3, 3, dtype=m.dtype)
    second[iu[0], iu[1]] = m[4:]
    second = second + second.T - torch.diag(second.diagonal())
    # ∫ (x − c)(x − c)ᵀ = S − f cᵀ − c fᵀ + V c cᵀ
    shifted = (
        second - first[:, None] * centre[None, :] - centre[:, None] * first[None, :] + V * torch.outer(centre, centre)
    )
    return torch.cat([V[None], (first - V * centre) / scale, shifted[iu[0], iu[1]] / scale**2])
