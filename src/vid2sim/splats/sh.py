"""Real spherical harmonics up to degree 3, in the basis and sign convention of 3D Gaussian Splatting.

A Gaussian's colour seen along the unit direction d (from the camera centre to the Gaussian) is

    rgb(d) = max(0, Σ_k Y_k(d) · sh[k] + 0.5),

with ``sh: (..., K, 3)``, ``K = (degree + 1)²`` and ``Y_k`` the real SH basis below (the same
constants and ordering that the reference 3DGS code, gsplat and the common PLY viewers use, so that
coefficients read from a ``.ply`` file render the same everywhere). The DC term alone gives
``rgb = C0 · sh[0] + 0.5``.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per colour channel for ``degree`` (0..3): (degree + 1)²."""
    if not isinstance(degree, int) or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be an integer in [0, {MAX_SH_DEGREE}], got {degree!r}")
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    """Inverse of :func:`num_sh_bases`: the degree whose basis count is ``k`` (1, 4, 9 or 16)."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"number of SH coefficients per channel must be one of 1, 4, 9, 16; got {k}")


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """SH basis values ``Y_k(d)`` for unit directions ``dirs: (..., 3)`` → ``(..., (degree+1)²)``.

    ``dirs`` must already be normalised; the polynomials are evaluated as written.
    """
    num_sh_bases(degree)
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """View-dependent RGB from SH coefficients, as 3DGS renders it.

    Args:
        degree: SH degree to use (0..3); may be lower than the degree ``sh`` holds.
        sh: (..., K, 3) coefficients with K ≥ (degree + 1)².
        dirs: (..., 3) viewing directions (camera → Gaussian); normalised here. Ignored for degree 0.

    Returns:
        (..., 3) colours ``max(0, Σ_k Y_k(d) sh[k] + 0.5)``.
    """
    k = num_sh_bases(degree)
    if sh.shape[-1] != 3 or sh.shape[-2] < k:
        raise ValueError(f"sh must have shape (..., K>={k}, 3) for degree {degree}, got {tuple(sh.shape)}")
    if degree == 0:
        return torch.clamp_min(C0 * sh[..., 0, :] + 0.5, 0.0)
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, d)  # (..., k)
    rgb = (basis[..., :, None] * sh[..., :k, :]).sum(dim=-2)
    return torch.clamp_min(rgb + 0.5, 0.0)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """DC coefficient giving colour ``rgb`` (any shape): (rgb − 0.5) / C0."""
    return (rgb - 0.5) / C0


def sh_dc_to_rgb(dc: Tensor) -> Tensor:
    """Colour of a DC coefficient (any shape), without the clamp: C0 · dc + 0.5."""
    return C0 * dc + 0.5
