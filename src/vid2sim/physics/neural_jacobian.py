"""Neural Jacobian: a network predicting J(X) = ∂F(X, z)/∂z per point (paper §4.2, supplementary "LBS and Jacobian
Network").

F is linear in z, so J depends on X only: ``F(X, z).reshape(9) = I.flatten() + J(X) @ z`` with J: (9, 12H) in the
layout of :func:`vid2sim.physics.skinning.dF_dz`. The network is trained data-free against the exact F of
a skinning field (closed form, :mod:`vid2sim.physics.skinning`), with an L1 loss on J(X) z + I − F(X, z)
for random points X and random handle transforms z.

Architecture (paper): positional encoding of X into ``encoding_dim`` (512) features, four residual blocks
of widths 512, 512, 1024, 1024, each two Linear layers with GELU, and a linear output of 9·12·H numbers.

Decisions:

- **Positional encoding**: Gaussian random Fourier features (Tancik et al. 2020),
  γ(X) = [sin(2π B X), cos(2π B X)] with B: (encoding_dim/2, 3) drawn once from N(0, σ²) and stored as a
  buffer (saved with the weights). σ = ``frequency_scale`` (default 2 cycles per unit length; the canonical
  object fits in a ball of radius 0.5, so this spans from the object scale down to a few centimetres),
  isotropic — no preferred axes, unlike per-axis NeRF bands.
- **Residual block**: ``y = GELU(P x + L₂ GELU(L₁ x))`` with P a bias-free projection where the width changes,
  the identity otherwise.
- **Output layer initialised to zero**, so a fresh network predicts J = 0 (relative error exactly 1) instead
  of random values orders of magnitude larger than the true J.
- **Training z** is drawn on *all* H handles, the rigid one included: the solver uses every column of J
  (rigid motions go through the rigid handle's 12 columns).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as Fn

from vid2sim.physics.input_frame import InputFrame, uniform_
from vid2sim.physics.skinning import (
    SkinningField,
    deformation_gradient_unchecked,
    dF_dz,
    gradient_basis,
    gradient_basis_unchecked,
)
from vid2sim.physics.skinning_training import RandomDraws
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.training import Progress, Schedule, optimise


def _init_linear(layer: nn.Linear, gen: torch.Generator | None) -> None:
    bound = 1.0 / math.sqrt(layer.in_features)
    for p in (layer.weight, layer.bias):
        if p is not None:
            uniform_(p, bound, gen)


class _ResidualBlock(nn.Module):
    """y = GELU(P x + L₂ GELU(L₁ x)); P is a bias-free Linear when widths differ, else the identity."""

    def __init__(self, d_in: int, d_out: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(d_in, d_out)
        self.fc2 = nn.Linear(d_out, d_out)
        self.proj = nn.Linear(d_in, d_out, bias=False) if d_in != d_out else None

    def forward(self, x: Tensor) -> Tensor:
        skip = x if self.proj is None else self.proj(x)
        return Fn.gelu(skip + self.fc2(Fn.gelu(self.fc1(x))))


class NeuralJacobian(InputFrame):
    """J_θ(X): (N, 9, 12H), the predicted ∂F/∂z per point.

    Args:
        num_handles_total: H, handles including the rigid one (11 by default).
        encoding_dim: number of positional-encoding features (even).
        widths: widths of the residual blocks (one block per entry).
        seed: deterministic initialisation (Fourier matrix and weights) when given; global RNG otherwise.
        frequency_scale: σ of the Gaussian Fourier-feature frequencies, in cycles per unit length.
    """

    def __init__(
        self,
        num_handles_total: int = 11,
        encoding_dim: int = 512,
        widths: tuple[int, ...] = (512, 512, 1024, 1024),
        seed: int | None = None,
        frequency_scale: float = 2.0,
    ) -> None:
        super().__init__()
        if isinstance(num_handles_total, bool) or not isinstance(num_handles_total, int) or num_handles_total < 1:
            raise ValueError(f"num_handles_total must be an integer >= 1, got {num_handles_total!r}")
        if isinstance(encoding_dim, bool) or not isinstance(encoding_dim, int) or encoding_dim < 2 or encoding_dim % 2:
            raise ValueError(f"encoding_dim must be an even integer >= 2 (sin and cos pairs), got {encoding_dim!r}")
        widths = tuple(widths)
        if len(widths) == 0 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in widths):
            raise ValueError(f"widths must be a non-empty tuple of positive integers, got {widths!r}")
        if not (0 < float(frequency_scale) < math.inf):
            raise ValueError(f"frequency_scale must be a finite positive number, got {frequency_scale!r}")
        self.num_handles_total = num_handles_total
        self.encoding_dim = encoding_dim
        self.widths = widths
        self.frequency_scale = float(frequency_scale)
        gen = None
        if seed is not None:
            gen = torch.Generator(device="cpu")
            gen.manual_seed(int(seed))
        freqs = torch.randn(encoding_dim // 2, 3, generator=gen, dtype=torch.float64) * self.frequency_scale
        self.register_buffer("frequencies", freqs.to(torch.get_default_dtype()))
        self._init_input_frame()  # encodes (X − input_centre) / input_scale; identity unless set
        dims = (encoding_dim,) + widths
        self.blocks = nn.ModuleList(_ResidualBlock(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.output = nn.Linear(widths[-1], 9 * 12 * num_handles_total)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                _init_linear(m, gen)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    def encode(self, X: Tensor) -> Tensor:
        """Fourier features γ(X) = [sin 2πBX, cos 2πBX]: (N, encoding_dim) for X: (N, 3)."""
        proj = (2.0 * math.pi) * (self._canonical(X) @ self.frequencies.T)
        return torch.cat([torch.sin(proj), torch.cos(proj)], dim=1)

    def forward(self, X: Tensor) -> Tensor:
        """J: (N, 9, 12H) for rest positions X: (N, 3) (layout of :func:`~vid2sim.physics.skinning.dF_dz`)."""
        self._in_parameters_dtype(X, self.output.weight)  # checks X
        return self.jacobian_unchecked(X)

    def jacobian_unchecked(self, X: Tensor) -> Tensor:
        """:meth:`forward` without checking X's values (for a caller that did: nothing waits for the device)."""
        h = self.encode(X.to(self.output.weight.dtype))  # returned in X's dtype
        for block in self.blocks:
            h = block(h)
        return self.output(h).reshape(X.shape[0], 9, 12 * self.num_handles_total).to(X.dtype)


@dataclass
class NeuralJacobianTrainingConfig:
    """Data-free Neural Jacobian training settings (paper defaults; AdamW with a cosine schedule to 0)."""

    iterations: int = 10_000
    points_per_step: int = 1000
    batch_size: int = 10
    z_std: float = 0.1
    lr: float = 1e-3
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("iterations", "points_per_step", "batch_size"):
            v = getattr(self, name)
            lo = 0 if name == "iterations" else 1
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ConfigError(f"NeuralJacobianTrainingConfig.{name} must be an integer >= {lo}, got {v!r}")
        for name in ("z_std", "lr"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not (0 < float(v) < math.inf):
                raise ConfigError(f"NeuralJacobianTrainingConfig.{name} must be a finite positive number, got {v!r}")


def _check_pair(net: NeuralJacobian, field: SkinningField, points: Tensor) -> None:
    if not isinstance(net, NeuralJacobian):
        raise TypeError(f"net must be a NeuralJacobian, got {type(net).__name__}")
    if not isinstance(field, SkinningField):
        raise TypeError(f"field must be a SkinningField, got {type(field).__name__}")
    if net.num_handles_total != field.num_handles_total:
        raise ValueError(
            f"the Neural Jacobian predicts {net.num_handles_total} handles but the skinning field has "
            f"{field.num_handles_total} (learned + rigid)"
        )
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise ValueError(f"points must be a tensor of shape (N, 3) with N >= 1, got {shape}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError("points contain NaN or infinite values")
    for name, module in (("Neural Jacobian", net), ("skinning field", field)):
        device = next(module.parameters()).device
        if device != points.device:
            raise ValueError(f"points are on {points.device} but the {name}'s parameters are on {device}")


def train_neural_jacobian(
    net: NeuralJacobian,
    field: SkinningField,
    points: Tensor,
    config: NeuralJacobianTrainingConfig | None = None,
    progress: bool = True,
    cuda_graph: bool = True,
) -> list[float]:
    """Train ``net`` in place, data-free, to reproduce ∂F/∂z of ``field`` (which is not modified).

    Each step draws ``points_per_step`` points (uniformly, with replacement) and ``batch_size`` transforms
    z ~ z_std·N(0, 1) on all H handles; loss = mean |J_θ(X) z + I − F(X, z)| with the exact F in closed form.

    Args:
        net, field: same H, dtype and device as ``points``.
        points: (N, 3) points in the object (canonical frame).
        cuda_graph: on CUDA, replay the iteration as a CUDA graph (:mod:`vid2sim.runtime.training`); False: eager.
    Returns:
        the loss at each iteration.
    Raises:
        FloatingPointError: if the loss becomes NaN or infinite.
    """
    config = config or NeuralJacobianTrainingConfig()
    _check_pair(net, field, points)
    if config.iterations == 0:
        return []
    params = [p for p in net.parameters() if p.requires_grad]
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(config.seed))
    H = net.num_handles_total
    eye = torch.eye(3, dtype=points.dtype, device=points.device).reshape(9)
    draws = RandomDraws(gen, points.shape[0], config, H, True, points, rigid=True)

    def step(idx: Tensor, z: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        # without checks of values (the points were checked above): it may be captured as a CUDA graph
        X = points[idx]
        with torch.no_grad():
            w, dw = field._weights_and_gradients(X.to(field.last_layer.weight.dtype))
            G = gradient_basis_unchecked(X, w.to(X.dtype), dw.to(X.dtype))
            F_true = deformation_gradient_unchecked(G, z).reshape(config.batch_size, X.shape[0], 9)
        J = net.jacobian_unchecked(X)  # (n, 9, 12H)
        F_pred = eye + torch.einsum("pik,bk->bpi", J, z)
        return (F_pred - F_true).abs().mean(), {}

    was_training = net.training
    net.train()
    try:
        return optimise(params, step, Schedule(config.iterations, config.lr, optimizer="adamw", cuda_graph=cuda_graph),
                        Progress("neural Jacobian (data-free)", progress), "Neural Jacobian training",
                        inputs=draws.next)
    finally:
        net.train(was_training)


@torch.no_grad()
def jacobian_error(net: NeuralJacobian, field: SkinningField, points: Tensor, chunk: int = 2048) -> dict[str, float]:
    """Errors of J_θ against the exact J = dF/dz of ``field`` at ``points: (N, 3)`` (evaluated in chunks).

    Returns:
        ``mse``: (1/N) Σ_i ‖J_θ(X_i) − J(X_i)‖²_F — the paper's Table (supplementary) metric;
        ``mse_per_entry``: the same divided by the 9·12H entries per point;
        ``relative_frobenius``: ‖J_θ − J‖_F / ‖J‖_F over all points;
        ``max_abs``: largest absolute entry error.
    """
    _check_pair(net, field, points)
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    sq_err = 0.0
    sq_ref = 0.0
    max_abs = 0.0
    n = points.shape[0]
    for s in range(0, n, chunk):
        X = points[s : s + chunk]
        w, dw = field.weights_and_gradients(X)
        J_true = dF_dz(gradient_basis(X, w, dw))
        diff = net(X) - J_true
        sq_err += float((diff.double() ** 2).sum())
        sq_ref += float((J_true.double() ** 2).sum())
        max_abs = max(max_abs, float(diff.abs().max()))
    entries = 9 * 12 * net.num_handles_total
    return {
        "mse": sq_err / n,
        "mse_per_entry": sq_err / (n * entries),
        "relative_frobenius": math.sqrt(sq_err / sq_ref) if sq_ref > 0 else float("inf"),
        "max_abs": max_abs,
    }
