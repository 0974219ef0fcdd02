"""Deforming Gaussians with a simulator's positions x and deformation gradients F.

Paper §3: each Gaussian's centre moves to φ(p) and its covariance becomes Σ' = L' L'ᵀ with
L' = F (R S), i.e. Σ' = F Σ Fᵀ, F = ∂φ/∂p. Computing Σ' through L' keeps it symmetric positive
semi-definite by construction. Everything is differentiable w.r.t. x and F, so image losses reach
whatever produced them (the reduced simulator, the skinning field, E and ν).

Colours keep their SH coefficients: view-dependent terms are evaluated in the world frame, not
rotated with the local rotation of F (vid2sim fits use low SH degrees, where this matters little).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from vid2sim.splats.gaussians import Gaussians, quat_to_rotmat, rotmat_to_quat
from vid2sim.splats.sh import sh_degree_from_bases
from vid2sim.splats.shading import Shading


@dataclass
class DeformedGaussians:
    """Gaussians after deformation, in the form :func:`vid2sim.splats.render.render` takes.

    Attributes:
        means: (N, 3) deformed centres x.
        covars: (N, 3, 3) deformed covariances F Σ Fᵀ.
        opacities: (N,) opacities in [0, 1].
        sh: (N, K, 3) SH colour coefficients (unchanged by the deformation).
    """

    means: Tensor
    covars: Tensor
    opacities: Tensor
    sh: Tensor

    @property
    def sh_degree(self) -> int:

        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def num(self) -> int:
        return self.means.shape[0]

    def to_gaussians(self) -> Gaussians:
        """Re-factor Σ' = R' S'² R'ᵀ (eigendecomposition) into a :class:`Gaussians` (e.g. to save a PLY).

        Differentiable except where two scales coincide (eigenvector ambiguity).
        """
        evals, evecs = torch.linalg.eigh(0.5 * (self.covars + self.covars.transpose(1, 2)))
        det = torch.linalg.det(evecs)
        evecs = evecs * torch.where(det < 0, -1.0, 1.0).to(evecs.dtype)[:, None, None]  # proper rotation
        scales = evals.clamp_min(1e-30).sqrt()
        op = self.opacities.clamp(1e-6, 1 - 1e-6)
        return Gaussians(
            means=self.means,
            log_scales=torch.log(scales),
            quats=rotmat_to_quat(evecs),
            opacity_logits=torch.log(op) - torch.log1p(-op),
            sh=self.sh,
        )


def deform_covariances(rs: Tensor, F: Tensor) -> Tensor:
    """Σ' = (F R S)(F R S)ᵀ from ``rs = R S: (N, 3, 3)`` and ``F: (N, 3, 3)`` → ``(N, 3, 3)``; F may carry leading
    batch dimensions (e.g. frames, (T, N, 3, 3) → (T, N, 3, 3))."""
    L = F @ rs
    return L @ L.transpose(-1, -2)


def _check(name: str, t: Tensor, shape: tuple[int, ...], like: Tensor) -> None:
    if not isinstance(t, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if t.dtype != like.dtype or t.device != like.device:
        raise ValueError(f"{name} is {t.dtype} on {t.device}; the Gaussians are {like.dtype} on {like.device}")


def deform_gaussians(gaussians: Gaussians, x: Tensor, F: Tensor, shading: Shading | None = None) -> DeformedGaussians:
    """Move Gaussians to ``x: (N, 3)`` and deform their covariances by ``F: (N, 3, 3)``.

    Returns :class:`DeformedGaussians` with means x, covariances F R S Sᵀ Rᵀ Fᵀ and the rest
    unchanged; differentiable w.r.t. x, F and the Gaussians' own parameters. With a
    :class:`~vid2sim.splats.shading.Shading` (N normals), the colours are albedos and come out lit by its
    world-fixed light, the normals carried by F.
    """
    n = gaussians.num
    _check("x", x, (n, 3), gaussians.means)
    _check("F", F, (n, 3, 3), gaussians.means)
    rs = quat_to_rotmat(gaussians.quats) * gaussians.scales[:, None, :]
    return DeformedGaussians(
        means=x,
        covars=deform_covariances(rs, F),
        opacities=gaussians.opacities,
        sh=gaussians.sh if shading is None else shading.shade(gaussians.sh, F),
    )
