"""Data-free training of the skinning field (Simplicits-style; paper §3, §4.2 and supplementary).

No simulation data is needed: at every step a batch of random handle transforms is drawn, the points are
deformed by LBS, and the network is asked for weights under which those random deformations are cheap in
elastic energy (so the handles span low-energy, "natural" deformation modes), while an orthogonality term
keeps the handles' weight functions independent.

    loss = elastic_weight · mean_b [ volume/n · Σ_p Ψ(F_p(z_b)) ] + orthogonality_weight · MSE(WᵀW, I)

with z_b ~ z_std·N(0, 1) on the learned handles (the rigid handle's Z is 0: rigid motions cost nothing
anyway), Ψ the Neo-Hookean energy density and W: (n, num_handles) the learned weights at the n sampled
points (the constant rigid column is excluded).

**The modal objective** (``objective="modal"``, our addition). The random-z objective spreads its effort
over every handle direction, including the stiff ones, and leaves the subspace's lowest vibration modes
9–102 % above the converged ones (quadratic tets; the ``bench identify`` shapes, 500 cubature points).
Those modes are what a drop excites and what identifies E. The modal objective asks instead for the
subspace whose lowest Rayleigh–Ritz eigenvalues λ_i of (K, M) are smallest. K is the linear-elastic stiffness and M the
mass of the LBS subspace, both at rest
with E = ρ = 1 and the batch's points as quadrature:

    loss = −Σ_i α / (λ_i + α) + modal_trace_weight · Σ_i λ_i / (α n)
           + modal_orthogonality_weight · MSE(WᵀW, I),     α = modal_shift / size², n = 12H

The first term is −α·tr((K + αM)⁻¹M): one Cholesky solve and no eigendecomposition, so it stays smooth
where eigenvalues cross. Eigenvalues far below α count ≈ −1 each, and those far above it ≈ 0, so the
subspace is pushed to hold as many modes below α as it can. The Ritz values depend on the subspace only,
not on how the weight functions mix, so the orthogonality term only fixes that gauge and keeps M
invertible; its weight is ``modal_orthogonality_weight``. A small mean-Ritz-value term
(``modal_trace_weight``) keeps the directions the sum ignores from growing rough between quadrature points.

**Train it on many points.** The objective rewards low Ritz values on the points it sees, and a network
trained on a few thousand fixed points learns a subspace that is nearly free *on those points* and stiff
between them: on a 3 000-point set, two of the six ``bench identify`` shapes got lowest "frequencies" of
0.45 and 0.77 × the converged ones on cubature drawn from the set, against 1.17 and 1.38 × on independent
points. On a 30 000-point pool (1 000 drawn per step) the two agree, and with 10 handles the lowest mode
on 500 cubature points comes to 1.04–1.20 × quadratic tets' (mean 1.10) against 1.09–2.02 (mean 1.48) for
random z. ``bench identify`` trains on ``skinning_points`` = 30 000, the pipeline on its 20 000 interior
samples. See docs/architecture.md, "Subspace stiffness".

Decisions (documented here because the paper leaves them open):

- **Orthogonality normalisation.** Simplicits (kaolin ``loss_ortho``) uses ``MSELoss(WᵀW, I)`` with the
  *unnormalised* Gram matrix over the sampled points, i.e. the mean over the H² entries of (WᵀW − I)². We do
  the same, because the paper's coefficients (0.1 elastic, 1e6 orthogonality, z ~ 0.1·N(0,1)) were tuned for
  it. Consequence: Σ_p w_j(X_p)² ≈ 1 over a step's ``points_per_step`` points, so the learned weights have
  magnitude ≈ 1/√points_per_step (≈ 0.03 at the default 1000); the physical deformation is w·z, so this is
  only a scale convention of z.
- **Batch reduction.** The elastic term is the *mean* over the batch of random z (kaolin sums over the
  batch; to reproduce its balance exactly multiply ``elastic_weight`` by ``batch_size``).
- **Inverted samples.** Random z can give J = det F ≤ 0, where Ψ's ln J is undefined. Points with
  J > ``inversion_threshold`` (default 0.1) use the exact Neo-Hookean density from
  :func:`vid2sim.physics.materials.neo_hookean_energy_density`; below it, the volumetric part
  g(J) = −μ ln J + λ/2 (ln J)² is replaced by its second-order Taylor expansion at the threshold (a C²,
  convex, finite continuation that keeps pushing J back up), while the isochoric part μ/2 (tr FᵀF − 3) is
  unchanged. Simplicits instead uses a log-free Neo-Hookean variant and a linear-elastic warm-up; our
  continuation keeps the exact energy the solver uses wherever the state is physical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from vid2sim.physics.materials import det3, lame_parameters
from vid2sim.physics.modes import subspace_stiffness_and_mass
from vid2sim.physics.skinning import (
    SkinningField,
    deformation_gradient,
    deformation_gradient_unchecked,
    gradient_basis_unchecked,
)
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.training import Progress, Schedule, optimise

#: training objectives of :func:`train_skinning`
OBJECTIVES = ("random_z", "modal")


@dataclass
class SkinningTrainingConfig:
    """Data-free skinning training settings (defaults: the paper / its public release).

    ``objective`` is "random_z" (the paper's: elastic energy of random handle transforms, the weights
    ``elastic_weight``, ``z_std``, ``batch_size``, ``orthogonality_weight``) or "modal" (the lowest Ritz
    eigenvalues of the subspace, the weights ``modal_shift``, ``modal_orthogonality_weight``; see the module
    docstring). Both draw ``points_per_step`` points per iteration.
    """

    iterations: int = 10_000
    points_per_step: int = 1000
    batch_size: int = 10
    z_std: float = 0.1
    elastic_weight: float = 0.1
    orthogonality_weight: float = 1e6
    lr: float = 1e-3
    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    last_layer_only: bool = False
    seed: int = 0
    inversion_threshold: float = 0.1
    objective: str = "random_z"
    modal_shift: float = 10.0
    modal_orthogonality_weight: float = 1.0
    modal_trace_weight: float = 1e-2

    def __post_init__(self) -> None:
        for name in ("iterations", "points_per_step", "batch_size"):
            v = getattr(self, name)
            lo = 0 if name == "iterations" else 1
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ConfigError(f"SkinningTrainingConfig.{name} must be an integer >= {lo}, got {v!r}")
        for name in ("z_std", "lr", "youngs_modulus", "inversion_threshold"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not (0 < float(v) < math.inf):
                raise ConfigError(f"SkinningTrainingConfig.{name} must be a finite positive number, got {v!r}")
        for name in ("elastic_weight", "orthogonality_weight"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not (0 <= float(v) < math.inf):
                raise ConfigError(f"SkinningTrainingConfig.{name} must be a finite number >= 0, got {v!r}")
        if not isinstance(self.poisson_ratio, (int, float)) or not (-1.0 < float(self.poisson_ratio) < 0.5):
            raise ConfigError(
                f"SkinningTrainingConfig.poisson_ratio must satisfy -1 < nu < 0.5, got {self.poisson_ratio!r}"
            )
        if self.objective not in OBJECTIVES:
            raise ConfigError(f"SkinningTrainingConfig.objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if not isinstance(self.modal_shift, (int, float)) or not (0 < float(self.modal_shift) < math.inf):
            raise ConfigError(
                f"SkinningTrainingConfig.modal_shift must be a finite positive number, got {self.modal_shift!r}"
            )
        for name in ("modal_orthogonality_weight", "modal_trace_weight"):
            w = getattr(self, name)
            if not isinstance(w, (int, float)) or not (0 <= float(w) < math.inf):
                raise ConfigError(f"SkinningTrainingConfig.{name} must be a finite number >= 0, got {w!r}")


def robust_neo_hookean_energy(F: Tensor, mu: float | Tensor, lam: float | Tensor, threshold: float = 0.1) -> Tensor:
    """Neo-Hookean Ψ(F): (M,) for F: (M, 3, 3), continued C² below J = ``threshold`` so inverted F is finite.

    For J > threshold this is exactly :func:`~vid2sim.physics.materials.neo_hookean_energy_density`. Below,
    g(J) = −μ ln J + λ/2 (ln J)² becomes g(J₀) + g'(J₀)(J − J₀) + ½ g''(J₀)(J − J₀)² with
    g'(J) = (λ ln J − μ)/J and g''(J) = (μ + λ − λ ln J)/J².
    """
    if F.ndim != 3 or F.shape[1:] != (3, 3):
        raise ValueError(f"F must have shape (M, 3, 3), got {tuple(F.shape)}")
    if not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    J = det3(F)
    # both branches at every point, chosen per point (no synchronisation, no gathers): the exact density where
    # J > threshold (its ln J taken of det F clamped at the threshold so that it is finite everywhere)
    isochoric = 0.5 * mu * ((F * F).sum(dim=(1, 2)) - 3.0)
    logj = torch.log(det3(F).clamp_min(threshold))
    exact = isochoric - mu * logj + 0.5 * lam * logj * logj
    j0 = threshold
    l0 = math.log(j0)
    g0 = -mu * l0 + 0.5 * lam * l0 * l0
    g1 = (lam * l0 - mu) / j0
    g2 = (mu + lam - lam * l0) / (j0 * j0)
    dj = J - j0
    return torch.where(J > threshold, exact, isochoric + g0 + g1 * dj + 0.5 * g2 * dj * dj)


def orthogonality_loss(w: Tensor) -> Tensor:
    """MSE(WᵀW, I) over the m×m entries for learned weights W = ``w: (n, m)`` (Simplicits' normalisation)."""
    if w.ndim != 2:
        raise ValueError(f"w must have shape (n, m), got {tuple(w.shape)}")
    gram = w.T @ w
    eye = torch.eye(w.shape[1], dtype=w.dtype, device=w.device)
    return ((gram - eye) ** 2).mean()


def elastic_loss(
    G: Tensor, z: Tensor, mu: float | Tensor, lam: float | Tensor, volume: float = 1.0, threshold: float = 0.1,
    trusted: bool = False,
) -> Tensor:
    """Mean over the batch of the elastic energy volume/n · Σ_p Ψ(F_p(z_b)).

    Args:
        G: (n, 3, 4H) gradient basis at the sampled points (:func:`~vid2sim.physics.skinning.gradient_basis`).
        z: (B, 12H) random handle transforms.
        trusted: G and z were made by the caller (a training loop): their checks are skipped.
    Returns:
        0-d tensor.
    """
    F = deformation_gradient_unchecked(G, z) if trusted else deformation_gradient(G, z)  # (B, n, 3, 3)
    B, n = F.shape[:2]
    psi = robust_neo_hookean_energy(F.reshape(B * n, 3, 3), mu, lam, threshold)
    return psi.reshape(B, n).sum(dim=1).mean() * (volume / n)


def _ridge_cholesky(A: Tensor) -> Tensor:
    """The Cholesky factor of the symmetric part of A (m, m) plus a ridge of 1e-12 × its mean diagonal, or, when
    that is not positive definite, of 100 ε of the dtype: a subspace can span a direction twice (on a rod, the
    handles w = z and w = z² give z·[X, 1] and z²·[X, 1], whose columns z·z and z²·1 coincide), and its Gram
    matrices are then singular to the dtype's precision; the ridge leaves that direction, with no mass and no
    stiffness, out of the Ritz problem (a seed-3 benchmark scene's rod, float32, stopped here without it).

    The choice is made on the device, without waiting for it (a training iteration may be a CUDA graph): the small
    ridge is tried without gradients, the ridge it calls for is then factorised with them; where neither works, the
    factor is NaN, and so is the loss made with it."""
    A = 0.5 * (A + A.T)
    eye = torch.eye(A.shape[0], dtype=A.dtype, device=A.device)
    scale = A.diagonal().mean()
    small, large = 1e-12, 100 * torch.finfo(A.dtype).eps
    with torch.no_grad():
        info = torch.linalg.cholesky_ex(A + (small * scale) * eye)[1]
    ridge = torch.where(info == 0, small, large).to(A.dtype) * scale
    factor, info = torch.linalg.cholesky_ex(A + ridge * eye)
    return torch.where(info == 0, factor, torch.full_like(factor, math.nan))


def _trace_of_solve(factor: Tensor, B: Tensor) -> Tensor:
    """tr(A⁻¹ B) for A = L Lᵀ with L = ``factor`` (two triangular solves: cuBLAS kernels on a GPU, which a CUDA
    graph can capture)."""
    Y = torch.linalg.solve_triangular(factor, B, upper=False)
    return torch.linalg.solve_triangular(factor.T, Y, upper=True).diagonal().sum()


def modal_loss(K: Tensor, M: Tensor, alpha: float, trace_weight: float = 0.0) -> Tensor:
    """−Σ_i α / (λ_i + α) + trace_weight · Σ_i λ_i / (α·n) over the n Ritz eigenvalues λ_i of (K, M); 0-d tensor.

    The first sum is −α·tr((K + αM)⁻¹ M), the second tr(M⁻¹K) / (α·n): the mean Ritz value, which keeps the
    directions the first sum ignores (λ ≫ α) from growing rough between the quadrature points. NaN where K + αM
    or M is not positive definite even with a ridge at the dtype's precision (:func:`_ridge_cholesky`)."""
    n = K.shape[0]
    loss = -alpha * _trace_of_solve(_ridge_cholesky(K + alpha * M), M)
    if trace_weight > 0:
        loss = loss + trace_weight * _trace_of_solve(_ridge_cholesky(M), K) / (alpha * n)
    return loss


def sample_handle_transforms(
    batch_size: int, num_handles_total: int, z_std: float, generator: torch.Generator, rigid: bool = False
) -> Tensor:
    """Random z: (B, 12H) with entries z_std·N(0, 1) (CPU, float64); the rigid (last) handle is 0 unless ``rigid``."""
    z = z_std * torch.randn(batch_size, num_handles_total, 12, generator=generator, dtype=torch.float64)
    if not rigid:
        z[:, -1] = 0.0
    return z.reshape(batch_size, 12 * num_handles_total)


class RandomDraws:
    """The random point indices (points_per_step,) and handle transforms (batch_size, 12H) of a data-free
    training's iterations, drawn on the CPU generator in the order the loops used to draw them one iteration at a
    time (the indices, then the transforms), but :data:`DRAW_CHUNK` iterations at a time and moved to the device in
    one copy each (a copy from the CPU waits for the device: one per iteration was one synchronisation more).

    Args:
        gen: the CPU generator (seeded by the caller).
        n_all: the number of points drawn from.
        config: a training config with ``iterations``, ``points_per_step``, ``batch_size`` and ``z_std``.
        H: handles (learned + rigid).
        transforms: draw transforms (False: indices only).
        like: the tensor whose dtype and device the transforms take (the indices take its device).
        rigid: draw the rigid (last) handle's transform too (else it is 0).
    """

    def __init__(self, gen: torch.Generator, n_all: int, config, H: int, transforms: bool, like: Tensor,
                 rigid: bool = False) -> None:
        self.gen, self.n_all, self.config, self.H, self.transforms, self.like = gen, n_all, config, H, transforms, like
        self.rigid = rigid
        self.start, self.idx, self.z = 0, None, None

    def next(self, it: int) -> tuple[Tensor, Tensor | None]:
        """(indices, transforms or None) of iteration ``it`` (asked for in order)."""
        if self.idx is None or it - self.start >= self.idx.shape[0]:
            self._draw(it)
        k = it - self.start
        return self.idx[k], None if self.z is None else self.z[k]

    def _draw(self, it: int) -> None:
        c = self.config
        n = min(DRAW_CHUNK, c.iterations - it)
        idx, z = [], []
        for _ in range(n):
            idx.append(torch.randint(self.n_all, (c.points_per_step,), generator=self.gen))
            if self.transforms:
                z.append(sample_handle_transforms(c.batch_size, self.H, c.z_std, self.gen, rigid=self.rigid))
        self.start = it
        self.idx = torch.stack(idx).to(self.like.device)
        self.z = torch.stack(z).to(dtype=self.like.dtype, device=self.like.device) if z else None


#: Training iterations whose random draws are made and moved to the device together.
DRAW_CHUNK = 64


def _check_points(points: Tensor, field: torch.nn.Module) -> None:
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise ValueError(f"points must be a tensor of shape (N, 3) with N >= 1, got {shape}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError("points contain NaN or infinite values")
    p = next(field.parameters())
    if points.dtype != p.dtype or points.device != p.device:
        raise ValueError(
            f"points ({points.dtype}, {points.device}) must match the field's parameters ({p.dtype}, {p.device})"
        )


def train_skinning(
    field: SkinningField,
    points: Tensor,
    config: SkinningTrainingConfig | None = None,
    progress: bool = True,
    volume: float = 1.0,
    cuda_graph: bool = True,
) -> list[float]:
    """Train ``field`` in place, data-free (see the module docstring for the loss).

    Args:
        field: the skinning field; its dtype/device decide those of the computation.
        points: (N, 3) points sampled in the object (canonical frame); each step draws
            ``points_per_step`` of them uniformly with replacement.
        config: :class:`SkinningTrainingConfig` (Adam, cosine learning-rate schedule to 0).
            ``last_layer_only=True`` updates only the output layer; all other parameters stay bit-identical.
        progress: show a tqdm bar.
        volume: the object's volume (integration weight volume/n per point).
        cuda_graph: on CUDA, replay the iteration as a CUDA graph (:mod:`vid2sim.runtime.training`; the same
            results to rounding, several times faster); False: eager.
    Returns:
        the total loss at each iteration (length ``config.iterations``).
    Raises:
        FloatingPointError: if the loss becomes NaN or infinite (the iteration is named).
    """
    config = config or SkinningTrainingConfig()
    if not isinstance(field, SkinningField):
        raise TypeError(f"field must be a SkinningField, got {type(field).__name__}")
    _check_points(points, field)
    if not isinstance(volume, (int, float)) or not (0 < float(volume) < math.inf):
        raise ValueError(f"volume must be a finite positive number, got {volume!r}")
    mu, lam = lame_parameters(config.youngs_modulus, config.poisson_ratio)
    params = list(field.last_layer.parameters()) if config.last_layer_only else list(field.parameters())
    if config.iterations == 0:
        return []
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(config.seed))
    H = field.num_handles_total
    modal = config.objective == "modal"
    size = float((points.max(0).values - points.min(0).values).norm()) if modal else 1.0
    if modal and not size > 0:
        raise ValueError("the modal objective needs points that span a volume (their bounding box is a point)")
    alpha = config.modal_shift / size**2
    draws = RandomDraws(gen, points.shape[0], config, H, not modal, points)

    def inputs(it: int) -> tuple[Tensor, ...]:
        idx, z = draws.next(it)
        return (idx,) if z is None else (idx, z)

    def step(idx: Tensor, z: Tensor | None = None) -> tuple[Tensor, dict[str, Tensor]]:
        # without checks of values (the points were checked above): it may be captured as a CUDA graph
        X = points[idx]
        w, dw = field._weights_and_gradients(X)
        lo = orthogonality_loss(w[:, :-1])
        if modal:
            K, M = subspace_stiffness_and_mass(X, w, dw, float(volume), config.poisson_ratio, trusted=True)
            le = modal_loss(K, M, alpha, config.modal_trace_weight)
            return le + config.modal_orthogonality_weight * lo, {"modal": le, "ortho": lo}
        G = gradient_basis_unchecked(X, w, dw)
        le = elastic_loss(G, z, mu, lam, float(volume), config.inversion_threshold, trusted=True)
        return config.elastic_weight * le + config.orthogonality_weight * lo, {"elastic": le, "ortho": lo}

    was_training = field.training
    field.train()
    try:  # foreach: one multi-tensor update (the same values)
        return optimise(params, step, Schedule(config.iterations, config.lr, foreach=True, cuda_graph=cuda_graph),
                        Progress("skinning (data-free)", progress), "skinning training", inputs=inputs)
    except FloatingPointError as error:
        if modal and "modal nan" in str(error):  # modal_loss is NaN where no ridge made the Gram matrices definite
            raise FloatingPointError(f"{error}; a NaN modal term means the subspace's mass or stiffness is not "
                                     "positive definite even with a ridge at the dtype's precision: raise "
                                     "modal_orthogonality_weight") from None
        raise
    finally:
        field.train(was_training)
