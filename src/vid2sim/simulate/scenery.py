"""What a simulated object meets, made visible: the floor and sphere obstacles as flat Gaussians.

``vid2sim simulate`` renders the asset's Gaussians; without the floor and the obstacles a viewer sees an
object bounce off nothing. :func:`scenery_gaussians` builds, for one time t, Gaussians lying on each contact
surface — a chequered square patch of the floor plane around the object's motion (it follows a moving or
tilting floor) and a shell of discs on each sphere obstacle — to be rendered together with the object. They
are only drawn: the physics is the externals' own, and the per-frame PLY files hold the object alone.

Each surface Gaussian is a disc tangent to the surface: covariance s² (I − n nᵀ) + (s/20)² n nᵀ with s about
0.6 of the sample spacing, so neighbours overlap into a closed surface.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.physics.external import Floor, MovingFloor, SphereObstacle
from vid2sim.splats.deform import DeformedGaussians
from vid2sim.splats.sh import C0

FLOOR_COLOURS = ((0.80, 0.80, 0.78), (0.62, 0.62, 0.60))  # the chequer's two greys (linear RGB in [0, 1])
OBSTACLE_COLOUR = (0.45, 0.55, 0.75)
OPACITY = 0.97
THICKNESS = 1.0 / 20.0  # disc thickness as a fraction of its radius


def _discs(centres: Tensor, normals: Tensor, radius: float, colours: Tensor, sh_bases: int) -> DeformedGaussians:
    """Flat discs (N,) at ``centres`` (N, 3) with unit ``normals`` (N, 3) and RGB ``colours`` (N, 3)."""
    nn = normals[:, :, None] * normals[:, None, :]
    eye = torch.eye(3, dtype=centres.dtype, device=centres.device)
    covars = radius ** 2 * (eye - nn) + (THICKNESS * radius) ** 2 * nn
    sh = torch.zeros(centres.shape[0], sh_bases, 3, dtype=centres.dtype, device=centres.device)
    sh[:, 0] = (colours - 0.5) / C0
    opacities = torch.full((centres.shape[0],), OPACITY, dtype=centres.dtype, device=centres.device)
    return DeformedGaussians(means=centres, covars=covars, opacities=opacities, sh=sh)


def _plane_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors spanning the plane of unit normal ``n`` (3,)."""
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype) if abs(float(n[0])) < 0.9 else \
        torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype)
    u = torch.linalg.cross(n, helper)
    u = u / u.norm()
    return u, torch.linalg.cross(n, u)


def floor_patch(normal: Sequence[float], point: Sequence[float], centre_xy: Sequence[float], half_size: float,
                cells: int = 8, per_cell: int = 6, sh_bases: int = 1, dtype: torch.dtype = torch.float32
                ) -> DeformedGaussians:
    """A chequered square of the plane through ``point`` with unit ``normal``, centred under ``centre_xy``.

    Args:
        normal: (3,) the plane's unit normal; point: (3,) a point of the plane (m).
        centre_xy: the patch's centre is the plane point below/above (x, y).
        half_size: half the square's side (m).
        cells: chequer cells per side; per_cell: discs per cell side.
    """
    n = torch.tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    p = torch.tensor(point, dtype=torch.float64)
    # the plane point under (x, y): move along z until on the plane (n_z > 0 for a floor that is not vertical)
    c = torch.tensor([centre_xy[0], centre_xy[1], 0.0], dtype=torch.float64)
    c[2] = p[2] - (n[0] * (c[0] - p[0]) + n[1] * (c[1] - p[1])) / n[2]
    u, v = _plane_basis(n)
    m = cells * per_cell
    step = 2.0 * half_size / m
    grid = (torch.arange(m, dtype=torch.float64) + 0.5) * step - half_size
    a, b = torch.meshgrid(grid, grid, indexing="ij")
    centres = c + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    parity = ((a.reshape(-1) + half_size) // (per_cell * step) + (b.reshape(-1) + half_size) // (per_cell * step)) % 2
    colours = torch.tensor(FLOOR_COLOURS, dtype=torch.float64)[parity.long()]
    normals = n.expand(centres.shape[0], 3)
    return _discs(centres.to(dtype), normals.to(dtype), 0.6 * step, colours.to(dtype), sh_bases)


def sphere_shell(centre: Sequence[float], radius: float, count: int = 600, sh_bases: int = 1,
                 dtype: torch.dtype = torch.float32) -> DeformedGaussians:
    """``count`` discs on a sphere (Fibonacci lattice), shaded a little by height so its shape reads."""
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    normals = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1)
    centres = torch.tensor(centre, dtype=torch.float64) + radius * normals
    spacing = radius * math.sqrt(4.0 * math.pi / count)
    shade = (0.75 + 0.25 * z)[:, None]
    colours = shade * torch.tensor(OBSTACLE_COLOUR, dtype=torch.float64)
    return _discs(centres.to(dtype), normals.to(dtype), 0.6 * spacing, colours.to(dtype), sh_bases)


def scenery_gaussians(externals: Sequence[object], t: float, centre_xy: Sequence[float], half_size: float,
                      sh_bases: int = 1, dtype: torch.dtype = torch.float32,
                      device: torch.device | str = "cpu") -> DeformedGaussians | None:
    """The floor (static or moving) and sphere obstacles among ``externals`` at time ``t`` (s) as Gaussians on
    ``device`` (None when there are none); the floor patch is centred under ``centre_xy`` with half side
    ``half_size``."""

    parts: list[DeformedGaussians] = []
    for e in externals:
        if isinstance(e, Floor):
            parts.append(floor_patch((0.0, 0.0, 1.0), (0.0, 0.0, e.height), centre_xy, half_size,
                                     sh_bases=sh_bases, dtype=dtype))
        elif isinstance(e, MovingFloor):
            pivot = (e.pivot_xy[0], e.pivot_xy[1], e.height_at(t))
            parts.append(floor_patch(e.normal_at(t), pivot, centre_xy, half_size, sh_bases=sh_bases, dtype=dtype))
        elif isinstance(e, SphereObstacle):
            parts.append(sphere_shell(e.center, e.radius, sh_bases=sh_bases, dtype=dtype))
    if not parts:
        return None
    g = concatenate(parts)
    return DeformedGaussians(means=g.means.to(device), covars=g.covars.to(device), opacities=g.opacities.to(device),
                             sh=g.sh.to(device))


def concatenate(parts: Sequence[DeformedGaussians]) -> DeformedGaussians:
    """One :class:`DeformedGaussians` holding all of ``parts`` (same SH size)."""
    return DeformedGaussians(means=torch.cat([p.means for p in parts]), covars=torch.cat([p.covars for p in parts]),
                             opacities=torch.cat([p.opacities for p in parts]), sh=torch.cat([p.sh for p in parts]))
