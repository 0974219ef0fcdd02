"""The depth of the surface the Gaussians show: where the opacity accumulated along each pixel's ray reaches a level.

The renderer's depth (:class:`~vid2sim.splats.render.RenderOutput` ``depth``) is the *expected* depth
Σ wᵢ zᵢ / Σ wᵢ. Where the front Gaussians are not opaque — half of a fitted set has opacity below 0.35 on the
small suite — it mixes the surface with the Gaussians behind it and lies too deep. Carving a visual hull with it
(:func:`vid2sim.reconstruct.stages.points.object_points`) then removes part of the object: on the small suite's
scene 1 the carving lost 12 % of the object's volume (docs/architecture.md, "The surface the depth carving
trusts").

:func:`surface_depth` is instead the depth at which the accumulated opacity reaches ``opacity``: at ½ the *median*
depth (the convention of 2DGS and Gaussian Opacity Fields for surfaces); lower, the first surface the ray meets.
Where the front Gaussians are faint (a layer that stops less than half the light) the median lies behind them, so
a carving that must not cut into the object takes a lower level. No rasteriser pass gives this depth directly, so
it is found on depth planes: per view, the Gaussians are split at ``planes`` depths spanning their centres' range,
the opacity accumulated by the Gaussians in front of each plane is rendered (one batched call per view, the
Gaussians behind a plane mirrored through the camera's centre, where the near plane culls them), and the crossing
of the level is interpolated linearly between the planes that bracket it. A Gaussian counts as in front of a plane
by its centre, so the depth resolves to about the plane spacing and the Gaussians' own extent.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from vid2sim.splats.cameras import Camera, stack_cameras
from vid2sim.splats.gaussians import Gaussians
from vid2sim.splats.render import render


def surface_depth(gaussians: Gaussians, cameras: Sequence[Camera], planes: int = 32,
                  opacity: float = 0.5) -> tuple[Tensor, Tensor]:
    """The depth where each pixel's accumulated opacity crosses ``opacity``, and the total opacity.

    Args:
        gaussians: N Gaussians (any device; computed without gradients).
        cameras: V cameras of one image size W×H.
        planes: depth planes per view (the resolution of the answer: the range of the centres' depths / planes).
        opacity: the accumulated opacity that marks the surface, in (0, 1) (½: the median depth).
    Returns:
        depth (V, H, W): camera depth of the surface, +inf where the pixel's total opacity stays below ``opacity``;
        alpha (V, H, W): the pixel's total opacity.
    """
    if planes < 2 or not 0 < opacity < 1:
        raise ValueError(f"surface_depth needs planes >= 2 and 0 < opacity < 1, got {planes}, {opacity}")
    viewmats, _, _, _ = stack_cameras(list(cameras))
    with torch.no_grad():
        means = gaussians.means.detach()
        opacities = gaussians.opacities.detach()
        covars = gaussians.covariances().detach()
        viewmats = viewmats.to(means)
        zeros = torch.zeros(means.shape[0], 1, dtype=means.dtype, device=means.device)
        depths, alphas = [], []
        for v, cam in enumerate(cameras):
            rotation, translation = viewmats[v, :3, :3], viewmats[v, :3, 3]
            z = means @ rotation[2] + translation[2]
            eye = -(rotation.T @ translation)
            cuts = torch.linspace(float(z.min()), float(z.max()), planes + 1, dtype=means.dtype,
                                  device=means.device)[1:]  # the last plane holds every Gaussian
            behind = z[None, :] > cuts[:, None]  # (K, N)
            per_plane = torch.where(behind[..., None], 2 * eye - means, means)  # mirrored behind the camera: culled
            a = render(per_plane, opacities, zeros, [cam] * planes, covars=covars.expand(planes, -1, -1, -1),
                       background=None).alpha[..., 0]  # (K, H, W), non-decreasing in K
            depths.append(_crossing(a, cuts, float(z.min()), opacity))
            alphas.append(a[-1])
        return torch.stack(depths), torch.stack(alphas)


def _crossing(alpha: Tensor, cuts: Tensor, first: float, level: float) -> Tensor:
    """(H, W) depth where ``alpha`` (K, H, W), accumulated up to the planes ``cuts`` (K,), crosses ``level``,
    interpolated between the planes that bracket it (from 0 at depth ``first``); +inf where it never does."""
    K = alpha.shape[0]
    reached = alpha >= level
    k = torch.where(reached.any(0), reached.to(torch.uint8).argmax(0), torch.full_like(alpha[0], K, dtype=torch.long))
    below = (k - 1).clamp_min(0)
    at = k.clamp_max(K - 1)
    a0 = torch.where(k > 0, alpha.gather(0, below[None])[0], torch.zeros_like(alpha[0]))
    a1 = alpha.gather(0, at[None])[0]
    z0 = torch.where(k > 0, cuts[below], torch.full_like(alpha[0], first))
    z1 = cuts[at]
    frac = ((level - a0) / (a1 - a0).clamp_min(1e-12)).clamp(0, 1)
    return torch.where(k < K, z0 + frac * (z1 - z0), torch.full_like(alpha[0], float("inf")))
