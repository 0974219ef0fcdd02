"""Simulation samples of a closed triangle mesh: interior points, volume, and surface contact points.

Stage I's training objects are meshes (procedural or the user's), not visual hulls, so their interior is
sampled from the surface directly:

- **Interior points** by vertical ray parity. A regular grid of ``columns`` × ``columns`` vertical lines
  (over the x–y extent of the bounding box, the longer side cut into ``columns`` cells) is intersected with
  every triangle; sorted, the crossings of one line pair up into the intervals of z inside the (watertight)
  surface. A sample picks a cell with probability ∝ its inside length, x and y uniform in the cell, an
  interval ∝ its length and z uniform in it — uniform in the solid up to half a cell at steep side walls.
  The line positions carry a tiny fixed irrational offset so that no line runs exactly through a vertex or
  an edge of a grid-aligned mesh. The volume is Σ cell area × inside length (against the divergence
  theorem: 0.1–0.3 % off at 64 columns on the procedural objects).
- **Contact points**: the mesh vertices with their lumped areas (a third of each adjacent triangle's area,
  m²), reduced to at most ``max_contact_points`` by farthest-point sampling, each kept point taking the
  area of the vertices nearest to it — as :mod:`vid2sim.reconstruct.stages.points` does for the visual hull's
  surface voxels, so the floor acts as a contact pressure (``AREA_CONTACT_STIFFNESS``) independent of the
  sampling.

Everything is deterministic from ``seed`` (a CPU ``torch.Generator``; float64 geometry).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from vid2sim.physics.cubature import farthest_point_sampling

_OFFSET = (math.sqrt(2.0) - 1.0) * 1e-4, (math.sqrt(3.0) - 1.0) * 1e-4  # cells; breaks grid-aligned ties


@dataclass
class SolidSamples:
    """Samples of a closed mesh for the simulator (all float32, the mesh's frame, metres).

    Attributes:
        points: (N, 3) interior points, uniform in the solid.
        volume: enclosed volume (m³) from the same column intervals.
        contact_points: (S, 3) surface points (a subset of the vertices); contact_areas: (S,) their areas (m²),
            summing to the surface area.
    """

    points: Tensor
    volume: float
    contact_points: Tensor
    contact_areas: Tensor


def _column_intervals(vertices: Tensor, faces: Tensor, columns: int) -> tuple[Tensor, Tensor, Tensor, float]:
    """Crossings of the vertical grid lines with the surface.

    Returns:
        centres: (C, 2) x–y of the lines; z: (C, K) sorted crossing heights padded with +inf; counts: (C,)
        crossings per line (even for a closed surface); cell: the cell side (m).
    """
    V = vertices.to(torch.float64)
    lo, hi = V.min(0).values, V.max(0).values
    ext = hi - lo
    cell = float(max(ext[0], ext[1])) / columns
    nx = max(1, math.ceil(float(ext[0]) / cell))
    ny = max(1, math.ceil(float(ext[1]) / cell))
    xs = lo[0] + (torch.arange(nx, dtype=torch.float64) + 0.5 + _OFFSET[0]) * cell
    ys = lo[1] + (torch.arange(ny, dtype=torch.float64) + 0.5 + _OFFSET[1]) * cell
    centres = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1).reshape(-1, 2)  # (C, 2)
    tri = V[faces]  # (F, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])  # (F,)
    keep = det.abs() > 1e-18  # vertical triangles are never crossed by a vertical line
    a, b, c, det = a[keep], b[keep], c[keep], det[keep]
    # candidate (line, triangle) pairs: the lines within each triangle's x–y bounding box (a ragged enumeration)
    tlo = torch.minimum(torch.minimum(a[:, :2], b[:, :2]), c[:, :2])
    thi = torch.maximum(torch.maximum(a[:, :2], b[:, :2]), c[:, :2])
    off = torch.tensor(_OFFSET, dtype=torch.float64)
    first = torch.ceil((tlo - lo[:2]) / cell - 0.5 - off).long().clamp_min(0)
    last = torch.floor((thi - lo[:2]) / cell - 0.5 - off).long()
    last = torch.minimum(last, torch.tensor([nx - 1, ny - 1]))
    span = (last - first + 1).clamp_min(0)  # (F, 2)
    count = span[:, 0] * span[:, 1]
    fi = torch.repeat_interleave(torch.arange(a.shape[0]), count)
    k = torch.arange(fi.shape[0]) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    ix = first[fi, 0] + k // span[fi, 1]
    iy = first[fi, 1] + k % span[fi, 1]
    pi = ix * ny + iy
    q = centres[pi]
    aa, bb, cc, dd = a[fi], b[fi], c[fi], det[fi]
    u = ((bb[:, 0] - q[:, 0]) * (cc[:, 1] - q[:, 1]) - (cc[:, 0] - q[:, 0]) * (bb[:, 1] - q[:, 1])) / dd
    v = ((cc[:, 0] - q[:, 0]) * (aa[:, 1] - q[:, 1]) - (aa[:, 0] - q[:, 0]) * (cc[:, 1] - q[:, 1])) / dd
    w = 1.0 - u - v
    hit = (u >= 0) & (v >= 0) & (w >= 0)
    z = u * aa[:, 2] + v * bb[:, 2] + w * cc[:, 2]
    hits_c, hits_z = [pi[hit]], [z[hit]]
    C = centres.shape[0]
    if hits_c[0].numel() == 0:
        return centres, torch.full((C, 0), math.inf, dtype=torch.float64), torch.zeros(C, dtype=torch.long), cell
    hc, hz = torch.cat(hits_c), torch.cat(hits_z)
    counts = torch.bincount(hc, minlength=C)
    K = int(counts.max())
    order = torch.argsort(hz, stable=True)  # by height, then (stable) by line
    hc, hz = hc[order], hz[order]
    order = torch.argsort(hc, stable=True)
    hc, hz = hc[order], hz[order]
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(hc.shape[0]) - start[hc]
    z = torch.full((C, K), math.inf, dtype=torch.float64)
    z[hc, slot] = hz
    return centres, z, counts, cell


def sample_solid(vertices: Tensor, faces: Tensor, num_points: int = 5000, columns: int = 64,
                 max_contact_points: int = 1000, seed: int = 0, name: str = "mesh") -> SolidSamples:
    """Interior points, volume and contact points of a closed, outward-wound surface (module docstring).

    Args:
        vertices: (Nv, 3) positions (m); faces: (Nf, 3) vertex indices.
        num_points: interior samples.
        columns: grid lines along the longer horizontal side of the bounding box.
        max_contact_points: at most this many contact points.
        seed: seeds the samples and the farthest-point start.
        name: the mesh's name for error messages.
    Raises:
        ValueError: a surface with an odd number of crossings on some line (not watertight) or no inside.
    """

    if num_points < 1 or columns < 2 or max_contact_points < 1:
        raise ValueError(f"num_points >= 1, columns >= 2 and max_contact_points >= 1 are needed, got "
                         f"{num_points}, {columns}, {max_contact_points}")
    V = torch.as_tensor(vertices).detach().to(torch.float64).cpu()
    Fc = torch.as_tensor(faces).detach().long().cpu()
    centres, z, counts, cell = _column_intervals(V, Fc, columns)
    odd = int((counts % 2 == 1).sum())
    if odd:
        raise ValueError(f"{name}: {odd} of {counts.numel()} vertical lines cross the surface an odd number of "
                         "times; the surface is not closed (watertight)")
    K = z.shape[1]
    if K == 0:
        raise ValueError(f"{name}: no vertical line meets the surface; the mesh encloses no volume")
    zin, zout = z[:, 0::2], z[:, 1::2]
    lengths = torch.where(torch.isfinite(zin), zout - zin, torch.zeros_like(zin)).clamp_min(0.0)  # (C, K/2)
    flat = lengths.reshape(-1)
    total = float(flat.sum())
    if not total > 0:
        raise ValueError(f"{name}: the surface encloses no volume")
    volume = total * cell * cell
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    pick = torch.multinomial(flat, num_points, replacement=True, generator=gen)
    col, iv = pick // lengths.shape[1], pick % lengths.shape[1]
    r = torch.rand(num_points, 3, generator=gen, dtype=torch.float64)
    xy = centres[col] + (r[:, :2] - 0.5 - torch.tensor(_OFFSET, dtype=torch.float64)) * cell
    zz = zin[col, iv] + r[:, 2] * lengths[col, iv]
    points = torch.cat([xy, zz[:, None]], dim=1)

    tri = V[Fc]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1)
    vert_area = torch.zeros(V.shape[0], dtype=torch.float64).index_add_(0, Fc.reshape(-1),
                                                                     (area / 3).repeat_interleave(3))
    used = vert_area > 0
    contact, areas = V[used], vert_area[used]
    if contact.shape[0] > max_contact_points:
        keep = farthest_point_sampling(contact, max_contact_points, seed=int(seed))
        nearest = torch.cdist(contact, contact[keep]).argmin(dim=1)
        areas = torch.zeros(len(keep), dtype=torch.float64).index_add_(0, nearest, areas)
        contact = contact[keep]
    return SolidSamples(points.float(), float(volume), contact.float(), areas.float())
