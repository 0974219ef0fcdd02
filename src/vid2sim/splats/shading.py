"""Diffuse shading under a light fixed in the world, for Gaussians that turn with a deforming object.

Gaussians fitted to frame 0 carry that frame's shading in their colours. When the object turns after a bounce, a
light fixed in the world lights it differently, and baked colours are wrong. :class:`Shading` separates the two:
each Gaussian's stored colour is an *albedo* ``a``, and the rendered colour is

    c = a · (k + (1 − k) · max(0, n · l)),

Lambert's law with an ambient share k, ``l`` the unit direction towards one directional light (world frame) and
``n`` the Gaussian's unit normal in the world. Normals are stored in the rest frame and carried by the
deformation gradient the way surface normals are: n ∝ cof(F) N = det(F) F⁻ᵀ N (Nanson's formula), so a turn
of the body turns them and a stretch tilts them correctly.

The factor s = k + (1 − k) max(0, n · l) is a scalar per Gaussian. It is applied to the spherical-harmonic
coefficients, so every renderer takes shaded Gaussians unchanged: with 3DGS's colour ``Σ Y_k sh_k + 0.5``,
scaling the colour by s means scaling every coefficient by s and adding (s − 1) · 0.5 / C0 to the DC one
(:func:`scale_sh_colour`). Fitted colours of view-dependent bands are scaled the same way.

This is the generator's own light model (:mod:`vid2sim.synthetic.mesh_render`) and the simplest physical one
for a matte object under a sun or a lamp far away. A real capture lit by many lights is only approximated by it;
the fitted ambient share says how directional the light was.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.sh import C0


def cofactor(F: Tensor) -> Tensor:
    """cof(F) = det(F) F⁻ᵀ from ``F: (..., 3, 3)`` → ``(..., 3, 3)``, without an inverse (its columns are
    cross products of F's columns: f₂ × f₃, f₃ × f₁, f₁ × f₂)."""
    f1, f2, f3 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    return torch.stack([torch.linalg.cross(f2, f3), torch.linalg.cross(f3, f1), torch.linalg.cross(f1, f2)], dim=-1)


def scale_sh_colour(sh: Tensor, factor: Tensor) -> Tensor:
    """SH coefficients whose 3DGS colour is ``factor`` times that of ``sh`` (before the renderer's clamp at 0).

    Args:
        sh: (N, K, 3) coefficients (colour = Σ_k Y_k sh_k + 0.5, with Y_0 = C0).
        factor: (N,) or (N, 3) scale per Gaussian (or per Gaussian and channel).

    Returns:
        (N, K, 3) coefficients: every one times the factor, the DC one plus (factor − 1) · 0.5 / C0.
    """
    f = factor if factor.ndim == 2 else factor[:, None].expand(-1, 3)
    out = sh * f[:, None, :]
    return torch.cat([out[:, :1] + ((f - 1.0) * (0.5 / C0))[:, None, :], out[:, 1:]], dim=1)


def outward_normals(centres: Tensor, interior: Tensor, bandwidth: float, pairs_per_chunk: int = 4_000_000) -> Tensor:
    """Unit outward normals at ``centres: (N, 3)`` from samples of the object's interior ``interior: (P, 3)``.

    The normal is minus the gradient of a Gaussian kernel density of the interior samples (bandwidth in metres):
    the direction away from the nearby mass of the object. Near the surface that is the surface normal; deep
    inside it is arbitrary, which does not matter for shading (hidden Gaussians are not seen).

    Returns:
        (N, 3) unit vectors (the +z axis where the density is flat, i.e. far from every sample). Centres are taken
        in chunks of at most ``pairs_per_chunk`` centre-sample pairs, which bounds the memory.
    """
    if centres.ndim != 2 or centres.shape[1] != 3 or interior.ndim != 2 or interior.shape[1] != 3:
        raise ValueError(f"outward_normals: centres (N, 3) and interior (P, 3) expected, got "
                         f"{tuple(centres.shape)} and {tuple(interior.shape)}")
    if interior.shape[0] == 0 or not bandwidth > 0:
        raise ValueError(f"outward_normals: need interior samples and a positive bandwidth, got "
                         f"{interior.shape[0]} samples and bandwidth {bandwidth}")
    origin = interior.to(centres.dtype).mean(0)
    p = interior.to(centres.dtype) - origin  # centred: the difference below loses less to rounding
    centres = centres - origin
    chunk = max(1, pairs_per_chunk // p.shape[0])
    out = []
    for start in range(0, centres.shape[0], chunk):
        x = centres[start:start + chunk]
        k = torch.exp(-torch.cdist(x, p).square() / (2.0 * bandwidth ** 2))  # (n, P)
        out.append(x * k.sum(1, keepdim=True) - k @ p)  # Σ_j k_j (x − p_j)
    g = torch.cat(out)
    norm = g.norm(dim=1, keepdim=True)
    up = torch.zeros_like(g)
    up[:, 2] = 1.0
    return torch.where(norm > 1e-12 * (1.0 + norm.max()), g / norm.clamp_min(1e-30), up)


@dataclass
class Shading:
    """A directional light and per-Gaussian rest-frame normals (see the module docstring).

    Attributes:
        normals: (N, 3) rest-frame normals of the N Gaussians (normalised when used).
        light: (3,) world direction towards the light (normalised when used).
        ambient_logit: () logit of the ambient share k ∈ (0, 1).
    """

    normals: Tensor
    light: Tensor
    ambient_logit: Tensor

    def __post_init__(self) -> None:
        n = self.normals
        if n.ndim != 2 or n.shape[1] != 3:
            raise ConfigError(f"Shading.normals must have shape (N, 3), got {tuple(n.shape)}")
        if tuple(self.light.shape) != (3,) or float(self.light.detach().norm()) == 0.0:
            raise ConfigError(f"Shading.light must be a non-zero 3-vector, got {self.light.tolist()}")
        if self.ambient_logit.ndim != 0:
            raise ConfigError(f"Shading.ambient_logit must be a scalar, got shape {tuple(self.ambient_logit.shape)}")

    @classmethod
    def create(cls, normals: Tensor, light: Tensor | list[float], ambient: float) -> "Shading":
        """From normals (N, 3), a light direction (3,) and an ambient share in (0, 1)."""
        if not 0.0 < ambient < 1.0:
            raise ValueError(f"Shading: ambient must lie in (0, 1), got {ambient}")
        like = normals
        light = torch.as_tensor(light, dtype=like.dtype, device=like.device).reshape(-1)
        a = torch.tensor(ambient, dtype=like.dtype, device=like.device)
        return cls(normals, light, torch.log(a) - torch.log1p(-a))

    @property
    def num(self) -> int:
        return int(self.normals.shape[0])

    @property
    def ambient(self) -> Tensor:
        """() the ambient share k."""
        return torch.sigmoid(self.ambient_logit)

    def factor(self, F: Tensor | None = None) -> Tensor:
        """(N,) shading factor k + (1 − k) max(0, n · l) with normals carried by ``F: (N, 3, 3)`` (None: the
        rest frame)."""
        n = self.normals if F is None else (cofactor(F.to(self.normals.dtype)) @ self.normals[:, :, None])[..., 0]
        n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-30)
        l = self.light / self.light.norm()
        k = self.ambient
        return k + (1.0 - k) * (n @ l).clamp_min(0.0)

    def shade(self, sh: Tensor, F: Tensor | None = None) -> Tensor:
        """(N, K, 3) SH coefficients of the shaded colours: albedo ``sh`` (N, K, 3) times :meth:`factor`."""
        if sh.shape[0] != self.num:
            raise ValueError(f"Shading.shade: {self.num} normals for {sh.shape[0]} Gaussians")
        return scale_sh_colour(sh, self.factor(F))

    def unshade(self, sh: Tensor) -> Tensor:
        """(N, K, 3) albedo coefficients whose rest-frame shading gives the colours ``sh`` (N, K, 3): the
        inverse of :meth:`shade` at F = I (used to start from Gaussians fitted with the light baked in)."""
        return scale_sh_colour(sh, 1.0 / self.factor())

    def detach(self) -> "Shading":
        return Shading(self.normals.detach(), self.light.detach(), self.ambient_logit.detach())

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Shading":
        return Shading(self.normals.to(device=device, dtype=dtype), self.light.to(device=device, dtype=dtype),
                       self.ambient_logit.to(device=device, dtype=dtype))

    def select(self, index: Tensor) -> "Shading":
        """The shading of a subset of the Gaussians (``index``: a boolean mask (N,) or indices)."""
        return Shading(self.normals[index], self.light, self.ambient_logit)

    def to_record(self) -> dict:
        """JSON-able light ({"light": unit [3], "ambient": k}); the normals are saved separately (N × 3)."""
        l = self.light.detach() / self.light.detach().norm()
        return {"model": "lambert", "light": [float(v) for v in l], "ambient": float(self.ambient.detach())}
