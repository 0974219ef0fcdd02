"""The 3D Gaussian model: raw (optimisable) parameters and their activated values.

A set of N Gaussians is stored the way 3D Gaussian Splatting optimises and saves it:

- ``means``          (N, 3)  centres p,
- ``log_scales``     (N, 3)  log of the standard deviations along the Gaussian's own axes,
- ``quats``          (N, 4)  rotations as quaternions (w, x, y, z); normalised when used,
- ``opacity_logits`` (N,)    logit of the opacity,
- ``sh``             (N, K, 3) spherical-harmonic colour coefficients, K = (degree + 1)², ``sh[:, 0]``
  is the DC term (see :mod:`vid2sim.splats.sh`).

The covariance is Σ = R S Sᵀ Rᵀ with R = R(q) and S = diag(exp(log_scales)).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Iterator, Sequence

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.sh import (
    num_sh_bases,
    rgb_to_sh_dc,
    sh_dc_to_rgb,
    sh_degree_from_bases,
)

_EPS_OPACITY = 1e-6


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions (w, x, y, z), ``quats: (..., 4)`` → ``(..., 3, 3)``.

    The quaternions are normalised first (they need not be unit); a zero quaternion is an error
    upstream (it gives NaN here).
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    return torch.stack([r00, r01, r02, r10, r11, r12, r20, r21, r22], dim=-1).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(rot: Tensor) -> Tensor:
    """Quaternions (w, x, y, z) with w ≥ 0 from rotation matrices ``rot: (..., 3, 3)`` → ``(..., 4)``.

    Uses the numerically stable branch on the largest of (w, x, y, z).
    """
    m = rot
    t = torch.stack(
        [
            1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        dim=-1,
    )
    best = t.argmax(dim=-1)
    s = 0.5 / t.clamp_min(1e-12).sqrt()  # (..., 4)
    cands = torch.stack(
        [
            torch.stack(
                [
                    0.25 / s[..., 0],
                    (m[..., 2, 1] - m[..., 1, 2]) * s[..., 0],
                    (m[..., 0, 2] - m[..., 2, 0]) * s[..., 0],
                    (m[..., 1, 0] - m[..., 0, 1]) * s[..., 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 2, 1] - m[..., 1, 2]) * s[..., 1],
                    0.25 / s[..., 1],
                    (m[..., 0, 1] + m[..., 1, 0]) * s[..., 1],
                    (m[..., 0, 2] + m[..., 2, 0]) * s[..., 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 0, 2] - m[..., 2, 0]) * s[..., 2],
                    (m[..., 0, 1] + m[..., 1, 0]) * s[..., 2],
                    0.25 / s[..., 2],
                    (m[..., 1, 2] + m[..., 2, 1]) * s[..., 2],
                ],
                -1,
            ),
            torch.stack(
                [
                    (m[..., 1, 0] - m[..., 0, 1]) * s[..., 3],
                    (m[..., 0, 2] + m[..., 2, 0]) * s[..., 3],
                    (m[..., 1, 2] + m[..., 2, 1]) * s[..., 3],
                    0.25 / s[..., 3],
                ],
                -1,
            ),
        ],
        dim=-2,
    )  # (..., 4 candidates, 4)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / q.norm(dim=-1, keepdim=True)


def covariances_from_scales_quats(scales: Tensor, quats: Tensor) -> Tensor:
    """Σ = R S Sᵀ Rᵀ from ``scales: (N, 3)`` (standard deviations) and ``quats: (N, 4)`` → ``(N, 3, 3)``."""
    m = quat_to_rotmat(quats) * scales[..., None, :]  # R S
    return m @ m.transpose(-1, -2)


def _logit(p: Tensor) -> Tensor:
    p = p.clamp(_EPS_OPACITY, 1 - _EPS_OPACITY)
    return torch.log(p) - torch.log1p(-p)


@dataclass
class Gaussians:
    """N 3D Gaussians in 3DGS's raw parametrisation (see module docstring for each field's shape)."""

    means: Tensor
    log_scales: Tensor
    quats: Tensor
    opacity_logits: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ConfigError(f"Gaussians.means must have shape (N, 3), got {tuple(self.means.shape)}")
        for name, shape in expected.items():
            t = getattr(self, name)
            if not isinstance(t, Tensor):
                raise ConfigError(f"Gaussians.{name} must be a torch.Tensor, got {type(t).__name__}")
            if tuple(t.shape) != shape:
                raise ConfigError(f"Gaussians.{name} must have shape {shape} (N={n}), got {tuple(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ConfigError(f"Gaussians.sh must have shape (N={n}, K, 3), got {tuple(self.sh.shape)}")
        sh_degree_from_bases(self.sh.shape[1])  # validates K
        dev, dt = self.means.device, self.means.dtype
        for f in fields(self):
            t = getattr(self, f.name)
            if t.device != dev or t.dtype != dt:
                raise ConfigError(
                    f"Gaussians.{f.name} is {t.dtype} on {t.device}; all fields must share means' {dt} on {dev}"
                )

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def from_values(
        cls,
        means: Tensor,
        scales: Tensor,
        colors: Tensor,
        opacities: Tensor,
        quats: Tensor | None = None,
        sh_degree: int = 0,
    ) -> "Gaussians":
        """Build from activated values.

        Args:
            means: (N, 3) centres.
            scales: (N, 3) positive standard deviations (or (N,) / (N, 1) for isotropic).
            colors: (N, 3) RGB in [0, 1] (stored as the SH DC term; higher bands start at zero).
            opacities: (N,) in (0, 1).
            quats: (N, 4) (w, x, y, z); identity when omitted.
            sh_degree: SH degree of the stored colour (0..3).
        """
        means = torch.as_tensor(means)
        n = means.shape[0]
        scales = torch.as_tensor(scales, dtype=means.dtype, device=means.device)
        if scales.ndim == 1 or (scales.ndim == 2 and scales.shape[1] == 1):
            scales = scales.reshape(n, 1).expand(n, 3)
        if scales.shape != (n, 3) or not bool((scales > 0).all()):
            raise ValueError(f"scales must be positive with shape (N={n}, 3) or (N,), got shape {tuple(scales.shape)}")
        colors = torch.as_tensor(colors, dtype=means.dtype, device=means.device)
        if colors.shape != (n, 3):
            raise ValueError(f"colors must have shape (N={n}, 3), got {tuple(colors.shape)}")
        opacities = torch.as_tensor(opacities, dtype=means.dtype, device=means.device).reshape(-1)
        if opacities.shape != (n,):
            raise ValueError(f"opacities must have shape (N={n},), got {tuple(opacities.shape)}")
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0
        sh = torch.zeros(n, num_sh_bases(sh_degree), 3, dtype=means.dtype, device=means.device)
        sh[:, 0] = rgb_to_sh_dc(colors)
        return cls(
            means=means.clone(),
            log_scales=torch.log(scales).clone(),
            quats=torch.as_tensor(quats, dtype=means.dtype, device=means.device).clone(),
            opacity_logits=_logit(opacities),
            sh=sh,
        )

    @staticmethod
    def cat(parts: Sequence["Gaussians"]) -> "Gaussians":
        """Concatenate several sets (same SH degree, dtype and device)."""
        if not parts:
            raise ValueError("Gaussians.cat needs at least one set")
        degrees = {p.sh_degree for p in parts}
        if len(degrees) != 1:
            raise ValueError(f"Gaussians.cat: all parts must have the same SH degree, got {sorted(degrees)}")
        return Gaussians(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Gaussians)})

    # ---- activated values --------------------------------------------------------------------
    @property
    def num(self) -> int:
        """Number of Gaussians N."""
        return self.means.shape[0]

    def __len__(self) -> int:
        return self.num

    @property
    def sh_degree(self) -> int:
        """SH degree held in ``sh`` (0..3)."""
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def scales(self) -> Tensor:
        """(N, 3) standard deviations exp(log_scales)."""
        return torch.exp(self.log_scales)

    @property
    def rotations(self) -> Tensor:
        """(N, 4) unit quaternions (w, x, y, z)."""
        return self.quats / self.quats.norm(dim=-1, keepdim=True)

    @property
    def rotation_matrices(self) -> Tensor:
        """(N, 3, 3) rotation matrices R."""
        return quat_to_rotmat(self.quats)

    @property
    def opacities(self) -> Tensor:
        """(N,) opacities sigmoid(opacity_logits)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors_dc(self) -> Tensor:
        """(N, 3) view-independent RGB of the DC term, clamped below at 0."""
        return torch.clamp_min(sh_dc_to_rgb(self.sh[:, 0]), 0.0)

    def covariances(self) -> Tensor:
        """(N, 3, 3) world covariances Σ = R S Sᵀ Rᵀ."""
        return covariances_from_scales_quats(self.scales, self.quats)

    # ---- tensor plumbing ---------------------------------------------------------------------
    def tensors(self) -> dict[str, Tensor]:
        """The five raw tensors by field name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __iter__(self) -> Iterator[Tensor]:  # pragma: no cover - convenience
        return iter(self.tensors().values())

    def _map(self, fn) -> "Gaussians":
        return Gaussians(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Gaussians":
        """Copy to ``device`` and/or floating ``dtype``."""
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "Gaussians":
        return self._map(lambda t: t.detach())

    def clone(self) -> "Gaussians":
        return self._map(lambda t: t.clone())

    def requires_grad_(self, flag: bool = True) -> "Gaussians":
        """Turn gradients on for all raw tensors in place; returns self."""
        for t in self.tensors().values():
            t.requires_grad_(flag)
        return self

    def __getitem__(self, index) -> "Gaussians":
        """Select Gaussians with a boolean mask (N,), index tensor or slice."""
        if isinstance(index, Tensor) and index.dtype == torch.bool and index.shape != (self.num,):
            raise ValueError(f"boolean mask must have shape (N={self.num},), got {tuple(index.shape)}")
        return self._map(lambda t: t[index])

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """Same Gaussians with SH truncated or zero-padded to ``degree``."""
        k = num_sh_bases(degree)
        sh = self.sh
        if sh.shape[1] >= k:
            sh = sh[:, :k]
        else:
            pad = torch.zeros(self.num, k - sh.shape[1], 3, dtype=sh.dtype, device=sh.device)
            sh = torch.cat([sh, pad], dim=1)
        return Gaussians(self.means, self.log_scales, self.quats, self.opacity_logits, sh)

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype
