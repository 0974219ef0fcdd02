"""The template skinning network: hidden layers trained once over many shapes, a last layer per object.

Stage I's hypernetwork predicts only the last layer of the skinning MLP (paper §4.1: "regressing only the
weights and biases of the final linear layer, keeping the other layers fixed"). The hidden layers are a
**template** shared by every object. vid2sim ships one, ``template_skinning.pt`` beside this module, trained
data-free over many procedural shapes by :func:`train_template`
(``python -m vid2sim.predictor.make_template``).

**The last layer of one object** (:func:`fit_last_layer`, the training label):

1. The trunk's features h(X) (N, 64) and their spatial gradients (N, 3, 64) at the object's points are
   computed once (:func:`trunk_features`); the hidden layers stay frozen.
2. Closed-form start (:func:`spectral_last_layer`). To second order in the random handle transforms, the
   data-free loss of :mod:`vid2sim.physics.skinning_training` is a quadratic form in each handle's 65
   last-layer numbers (:func:`energy_matrices`), and its orthogonality term asks the handles to be
   orthonormal under the points' second-moment matrix. The optimum is the 10 lowest generalised
   eigenvectors — one symmetric eigenproblem of size 65.
3. Optionally (``iterations`` > 0), Adam on the exact data-free loss: the same loss, random transforms and
   Neo-Hookean energy as ``train_skinning``, with no trip through the hidden layers per iteration. It gains
   about 1 % and moves the label by a few percent with its random draws, so the dataset's default is 0
   (docs/training-data.md).
4. A canonical gauge (:func:`canonical_gauge`). The data-free loss does not change when the 10 weight
   functions are mixed by an orthogonal 10 × 10 matrix Q: w → Qw turns the random handle transforms into
   equally distributed ones and leaves WᵀW's distance to I alone. So a fitted last layer is only defined
   up to O(10). The gauge aligns the handles (orthogonal Procrustes) with the template's fixed reference
   handles — the closed form of a ball — at the object's points. The label is then a function of the object,
   not of the fit's history. The simulated motion does not change: the handles span the same subspace.

**The template** (:func:`train_template`, settings in :class:`TemplateConfig`):

- A pool of ``shapes`` procedural objects with seeds ``shape_seed_base + k``, disjoint from the training
  data's.
- Each is turned by a random rotation and re-normalised to the canonical frame: centred bounding box,
  half-diagonal 0.5. This is the frame in which a posed object is seen at frame 0.
- Each is filled with interior points (:mod:`vid2sim.predictor.solid`).
- Each step draws ``shapes_per_step`` pool shapes. For each, the head (last layer) is the spectral start
  solved on ``spectral_points`` of the shape's points, *differentiated through* (Cholesky and eigh). The loss
  is then taken on an independent draw of ``points_per_step`` points, and Adam updates the trunk. That loss
  is the orthogonality term exactly, plus the elastic term as its mean over the random transforms to second
  order. The trunk thus learns features in which the closed-form head — the label's first step — has a low
  true loss, including the orthogonality term's sampling variance, which the closed form ignores.
- That loss is exactly invariant under O(10), so the eigenvectors' derivative within the 10 handles (the
  1/(λᵢ − λⱼ) terms of eigh's backward) does not enter it.
- Two simpler schemes were measured and dropped. Persistent per-shape heads trained by Adam beside the
  trunk could not follow its changes: with 48 shapes the orthogonality term grew a thousandfold in 300
  steps. Heads re-solved every step but held constant in the trunk's gradient made held-out shapes 1–3 %
  *worse* after 2 500 steps.
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as Fn

from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.skinning import SkinningField, gradient_basis
from vid2sim.physics.skinning_training import (
    SkinningTrainingConfig,
    elastic_loss,
    orthogonality_loss,
    sample_handle_transforms,
    train_skinning,
)
from vid2sim.predictor.solid import sample_solid
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.files import write_file_atomic
from vid2sim.runtime.training import Progress, Schedule, optimise
from vid2sim.synthetic.meshes import normalize_to_canonical
from vid2sim.synthetic.shapes import ProceduralShapeConfig, make_procedural_object, random_rotation

#: the shipped template (package data)
TEMPLATE_PATH = Path(__file__).with_name("template_skinning.pt")
TEMPLATE_FORMAT = "vid2sim-template-skinning/1"
#: the gauge's reference shape: a solid ball of this radius (canonical frame), sampled with this many points
REFERENCE_RADIUS, REFERENCE_POINTS = 0.5, 20000


@dataclass
class SkinningLoss:
    """The data-free loss shared by the template's training and every last-layer fit (the defaults of
    :class:`vid2sim.physics.SkinningTrainingConfig`, the paper's).

    Attributes:
        points_per_step: interior points drawn per step (the orthogonality term normalises WᵀW over them).
        batch_size: random handle transforms per step; z_std: their standard deviation.
        elastic_weight, orthogonality_weight: loss = elastic_weight · elastic + orthogonality_weight · MSE(WᵀW, I).
        youngs_modulus, poisson_ratio: the Neo-Hookean material of the elastic term (Pa, −).
        inversion_threshold: J below which Ψ is continued quadratically.
    """

    points_per_step: int = 1000
    batch_size: int = 10
    z_std: float = 0.1
    elastic_weight: float = 0.1
    orthogonality_weight: float = 1e6
    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    inversion_threshold: float = 0.1

    def __post_init__(self) -> None:
        for name in ("points_per_step", "batch_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"SkinningLoss.{name} must be an integer >= 1, got {v!r}")
        lame_parameters(self.youngs_modulus, self.poisson_ratio)
        for name in ("z_std", "inversion_threshold", "elastic_weight", "orthogonality_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
                raise ConfigError(f"SkinningLoss.{name} must be a finite positive number, got {v!r}")


# ---- the trunk's features -------------------------------------------------------------------------------

@dataclass
class Features:
    """The trunk's output at fixed points: everything a last layer needs.

    Attributes:
        points: (N, 3) the points (in the field's input frame).
        h: (N, width) last hidden features; dh: (N, 3, width) their gradients, ``dh[p, c, k] = ∂h_k/∂X_c``.
    """

    points: Tensor
    h: Tensor
    dh: Tensor

    def weights(self, A: Tensor, b: Tensor, idx: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """(X (n, 3), w (n, H), dw (n, H, 3)) for the last layer A: (m, width), b: (m,), with the rigid column
        appended (as :meth:`SkinningField.weights_and_gradients`), at the points ``idx`` (all if None)."""
        X, h, dh = (self.points, self.h, self.dh) if idx is None else (self.points[idx], self.h[idx], self.dh[idx])
        w = h @ A.T + b
        dw = (dh @ A.T).transpose(1, 2)
        w = torch.cat([w, torch.ones_like(w[:, :1])], dim=1)
        dw = torch.cat([dw, torch.zeros_like(dw[:, :1])], dim=1)
        return X, w, dw


def trunk_features(field_: SkinningField, points: Tensor) -> Features:
    """The hidden layers' features and their spatial gradients at ``points: (N, 3)`` (forward mode, exactly as
    :meth:`SkinningField.weights_and_gradients` up to the last layer). Differentiable w.r.t. the trunk."""
    h = field_._canonical(points)
    n = points.shape[0]
    D = (torch.eye(3, dtype=points.dtype, device=points.device) / field_.input_scale).expand(n, 3, 3)
    for layer in field_.layers[:-1]:
        u = layer(h)
        D = D @ layer.weight.T
        h = Fn.elu(u)
        D = D * torch.where(u > 0, 1.0, h + 1.0)[:, None, :]
    return Features(points, h, D)


def _frozen_features(template: SkinningField, points: Tensor) -> Features:
    with torch.no_grad():
        return trunk_features(template, points.detach().to(template.last_layer.weight.dtype))


def _split(vec: Tensor, m: int, width: int) -> tuple[Tensor, Tensor]:
    return vec[: m * width].reshape(m, width), vec[m * width:]


def _check_last_layer(template: SkinningField, vec: Tensor) -> None:
    if not isinstance(vec, Tensor) or vec.shape != (template.last_layer_size,):
        shape = tuple(vec.shape) if isinstance(vec, Tensor) else type(vec).__name__
        raise InputError(f"a last layer must be a tensor of shape ({template.last_layer_size},), got {shape}")


def _check_points(points: Tensor) -> None:
    if not isinstance(points, Tensor) or points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 2:
        shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise InputError(f"points must be a tensor of shape (N, 3) with N >= 2, got {shape}")
    if not bool(torch.isfinite(points).all()):
        raise InputError("points contain NaN or infinite values")


# ---- the closed-form start and the gauge ----------------------------------------------------------------

def energy_matrices(features: Features, ridge: float = 1e-8) -> tuple[Tensor, Tensor]:
    """The second-order data-free loss of one handle as two (width+1)² matrices (float64).

    A learned weight w = ã·[h, 1] under random handle transforms Z (entries z_std·N(0, 1), independent
    between handles) has the mean small-strain energy σ²(2μ + λ/2)·mean_p ‖B_p‖², where
    B = w [I; 0] + [X; 1] ∇wᵀ (4 × 3), i.e. ‖B‖² = 3w² + 2w X·∇w + (|X|² + 1)|∇w|². That is the
    quadratic form ãᵀKã, with no coupling between handles. The expected Gram matrix of the orthogonality
    term is ãⱼᵀ(n M)ãₖ with M = mean_p [h, 1][h, 1]ᵀ.

    Returns:
        (K, M); M has ``ridge`` × its mean diagonal added.
    """
    X = features.points.to(torch.float64)
    h = features.h.to(torch.float64)
    n = h.shape[0]
    ht = torch.cat([h, torch.ones(n, 1, dtype=torch.float64)], dim=1)  # (N, d)
    dht = torch.cat([features.dh.to(torch.float64), torch.zeros(n, 3, 1, dtype=torch.float64)], dim=2)  # (N, 3, d)
    xd = torch.einsum("pc,pcd->pd", X, dht)  # X·∇h̃
    r2 = (X * X).sum(1) + 1.0
    K = (3.0 * ht.T @ ht + ht.T @ xd + xd.T @ ht + torch.einsum("p,pcd,pce->de", r2, dht, dht)) / n
    M = ht.T @ ht / n
    M = M + ridge * float(M.diagonal().mean().detach()) * torch.eye(M.shape[0], dtype=torch.float64)
    return 0.5 * (K + K.T), M


def spectral_last_layer(template: SkinningField, points: Tensor, loss: SkinningLoss | None = None,
                        features: Features | None = None) -> Tensor:
    """The closed-form second-order optimum of the data-free loss over the last layer.

    The ``num_handles`` lowest generalised eigenvectors of (K, M) (:func:`energy_matrices`), scaled so that
    the expected Gram matrix over ``points_per_step`` points is I, lowest energy first (signs as the
    eigensolver returns them; :func:`canonical_gauge` fixes the basis).

    Args:
        template: the template (its trunk); points: (N, 3) the object's points in its input frame.
    Returns:
        (last_layer_size,) float64.
    """
    loss = loss or SkinningLoss()
    features = features if features is not None else _frozen_features(template, points)
    K, M = energy_matrices(features)
    L = torch.linalg.cholesky(M)
    Li = torch.linalg.inv(L)
    _, V = torch.linalg.eigh(Li @ K @ Li.T)
    m, width = template.num_handles, template.width
    a = (Li.T @ V[:, :m]) / math.sqrt(loss.points_per_step)  # (d, m) with aᵀ (n M) a = I
    return torch.cat([a[:width].T.reshape(-1), a[width]])


def reference_last_layer(template: SkinningField) -> Tensor:
    """The gauge's reference handles: the closed-form last layer (:func:`spectral_last_layer`) of a solid ball
    of radius 0.5 centred in the canonical frame (20 000 uniform points from a fixed seed). (last_layer_size,)
    float64. Stored in the template file when it is saved, so labels do not depend on the eigensolver."""
    g = torch.Generator(device="cpu").manual_seed(0)
    d = torch.randn(REFERENCE_POINTS, 3, generator=g, dtype=torch.float64)
    r = REFERENCE_RADIUS * torch.rand(REFERENCE_POINTS, 1, generator=g, dtype=torch.float64) ** (1.0 / 3.0)
    ball = (d / d.norm(dim=1, keepdim=True) * r).to(template.last_layer.weight.dtype)
    return spectral_last_layer(template, ball)


def gauge_reference(template: SkinningField) -> Tensor:
    """The template's stored reference last layer (``template.gauge_reference``, set by :func:`load_template`),
    or :func:`reference_last_layer` computed now (and kept on the module)."""
    ref = getattr(template, "gauge_reference", None)
    if ref is None:
        ref = reference_last_layer(template)
        template.gauge_reference = ref
    return ref.to(torch.float64)


def canonical_gauge(template: SkinningField, last_layer: Tensor, points: Tensor,
                    features: Features | None = None) -> Tensor:
    """The same handle subspace with the last layer in the canonical O(10) gauge (module docstring).

    Orthogonal Procrustes onto the template's reference handles r (:func:`gauge_reference`, the closed form of
    a ball) at the object's points. With W (N, 10) the handles' values at ``points`` and R the reference's,
    Q = U Vᵀ from the SVD U S Vᵀ = WᵀR maximises Σ_k ⟨(WQ)_k, r_k⟩, and the handles become w' = Qᵀw.
    Handle k of every object is thus the one most like reference handle k. Q is unique and continuous in the
    object while WᵀR is non-singular. A mixture of the handles by any orthogonal matrix gives the same result.

    Args:
        last_layer: (last_layer_size,); points: (N, 3) the object's points in the template's input frame.
    Returns:
        (last_layer_size,) in the dtype of ``last_layer``.
    """
    _check_last_layer(template, last_layer)
    m, width = template.num_handles, template.width
    features = features if features is not None else _frozen_features(template, points)
    h = features.h.to(torch.float64)
    A, b = _split(last_layer.detach().to(torch.float64), m, width)
    Ar, br = _split(gauge_reference(template), m, width)
    W, R = h @ A.T + b, h @ Ar.T + br
    U, _, Vh = torch.linalg.svd(W.T @ R)
    Q = U @ Vh
    return torch.cat([(Q.T @ A).reshape(-1), Q.T @ b]).to(last_layer.dtype)


# ---- the fit ----------------------------------------------------------------------------------------------

def step_loss(features: Features, A: Tensor, b: Tensor, loss: SkinningLoss, gen: torch.Generator,
              volume: float) -> tuple[Tensor, Tensor]:
    """One stochastic draw of the data-free loss's two terms (elastic, orthogonality), 0-d tensors, for the
    last layer (A (m, width), b (m,)): ``points_per_step`` points drawn with replacement and
    ``batch_size`` random handle transforms, both from ``gen`` (as ``train_skinning`` draws them)."""
    n = features.points.shape[0]
    idx = torch.randint(n, (loss.points_per_step,), generator=gen)
    X, w, dw = features.weights(A, b, idx)
    z = sample_handle_transforms(loss.batch_size, w.shape[1], loss.z_std, gen).to(X.dtype)
    mu, lam = lame_parameters(loss.youngs_modulus, loss.poisson_ratio)
    le = elastic_loss(gradient_basis(X, w, dw), z, mu, lam, volume, loss.inversion_threshold)
    lo = orthogonality_loss(w[:, :-1])
    return le, lo


@dataclass
class FitLog:
    """What a last-layer fit did: the per-iteration total, elastic and orthogonality losses, and seconds
    (``seconds_features``: the trunk's features and the spectral start)."""

    loss: list[float] = field(default_factory=list)
    elastic: list[float] = field(default_factory=list)
    orthogonality: list[float] = field(default_factory=list)
    seconds: float = 0.0
    seconds_features: float = 0.0


def fit_last_layer(template: SkinningField, points: Tensor, iterations: int = 0, lr: float = 3e-5,
                   seed: int = 0, volume: float = 1.0, loss: SkinningLoss | None = None, gauge: bool = True,
                   log: FitLog | None = None) -> Tensor:
    """Fit only the last layer of ``template`` to one object (hidden layers frozen); the training label.

    Spectral start, ``iterations`` Adam steps on the exact data-free loss (cosine learning-rate schedule to
    0), canonical gauge (module docstring). Deterministic for a given ``seed`` and thread count.

    Args:
        template: the template field (not modified).
        points: (N, 3) interior points of the object in the template's input frame (the canonical frame:
            centred bounding box, half-diagonal 0.5).
        iterations: Adam iterations after the closed-form start (0: the start itself, gauge-fixed).
        lr: Adam's learning rate.
        seed: seeds the drawn points and handle transforms.
        volume: the object's volume in that frame (integration weight volume / n, as ``train_skinning``).
        loss: :class:`SkinningLoss` (default: the paper's).
        gauge: put the result in the canonical gauge (:func:`canonical_gauge`).
        log: filled with the loss curve and timings if given.
    Returns:
        (last_layer_size,) = (650,) float32, in :meth:`SkinningField.get_last_layer`'s layout (weights
        row-major (10, 64), then the 10 biases).
    """
    loss = loss or SkinningLoss()
    _check_points(points)
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise InputError(f"iterations must be an integer >= 0, got {iterations!r}")
    if not (isinstance(volume, (int, float)) and 0 < volume < math.inf):
        raise InputError(f"volume must be a finite positive number, got {volume!r}")
    t0 = time.perf_counter()
    dtype = template.last_layer.weight.dtype
    feats = _frozen_features(template, points)
    m, width = template.num_handles, template.width
    A0, b0 = _split(spectral_last_layer(template, points, loss, feats).to(dtype), m, width)
    if log is not None:
        log.seconds_features = time.perf_counter() - t0
    A = A0.clone().requires_grad_(True)
    b = b0.clone().requires_grad_(True)
    gen = torch.Generator(device="cpu").manual_seed(int(seed))

    def step(it: int) -> tuple[Tensor, dict[str, Tensor]]:
        le, lo = step_loss(feats, A, b, loss, gen, volume)
        if log is not None:
            log.elastic.append(float(le.detach()))
            log.orthogonality.append(float(lo.detach()))
        return loss.elastic_weight * le + loss.orthogonality_weight * lo, {"elastic": le, "ortho": lo}

    losses = optimise([A, b], step, Schedule(iterations, lr), Progress("last-layer fit", False), "last-layer fit")
    if log is not None:
        log.loss.extend(losses)
    vec = torch.cat([A.detach().reshape(-1), b.detach()])
    if gauge:
        vec = canonical_gauge(template, vec, points, features=feats)
    if log is not None:
        log.seconds = time.perf_counter() - t0
    return vec.float()


def field_from_last_layer(template: SkinningField, last_layer: Tensor) -> SkinningField:
    """A new :class:`SkinningField`: the template's hidden layers (and input frame) with ``last_layer: (650,)``
    (:meth:`SkinningField.get_last_layer`'s layout)."""
    out = copy.deepcopy(template)
    out.set_last_layer(torch.as_tensor(last_layer))
    return out


@torch.no_grad()
def skinning_loss_value(field_: SkinningField, points: Tensor, volume: float = 1.0, loss: SkinningLoss | None = None,
                        repeats: int = 32, seed: int = 12345) -> dict[str, float]:
    """A low-noise estimate of the data-free loss of ``field_`` on one object, for comparing fits: the mean of
    ``repeats`` draws (``points_per_step`` points and ``batch_size`` transforms each) from a fixed seed.

    Returns:
        {"elastic", "orthogonality", "total"} (total = the weighted sum the training minimises).
    """
    loss = loss or SkinningLoss()
    feats = _frozen_features(field_, points)
    A, b = _split(field_.get_last_layer().to(field_.last_layer.weight.dtype), field_.num_handles, field_.width)
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    draws = [step_loss(feats, A, b, loss, gen, volume) for _ in range(repeats)]
    el = float(np.mean([float(d[0]) for d in draws]))
    orth = float(np.mean([float(d[1]) for d in draws]))
    return {"elastic": el, "orthogonality": orth, "total": loss.elastic_weight * el + loss.orthogonality_weight * orth}


# ---- training the template ------------------------------------------------------------------------------

@dataclass
class TemplateConfig:
    """Settings of :func:`train_template` (the shipped template's are these defaults).

    Attributes:
        seed: seeds the trunk's initialisation, the pool's rotations and every draw.
        shapes: procedural objects in the pool (one head each).
        shape_seed_base: pool shape k is ``make_procedural_object(shape_seed_base + k)`` (far from the seeds
            of the training data, which start at 0).
        points_per_shape: interior points sampled per pool shape.
        iterations: training steps.
        shapes_per_step: pool shapes whose losses are added per step.
        spectral_points: points per step on which a shape's head is solved (the loss uses others).
        lr: Adam's learning rate of the trunk (linear warm-up over ``warmup`` steps, then a cosine schedule
            to 0).
        loss: the data-free loss.
        num_handles, width, hidden_layers: the skinning MLP (the paper's: 10, 64, 8).
        eval_shapes: held-out shapes (seeds ``shape_seed_base + shapes + k``) for the report.
        eval_iterations: iterations of the report's last-layer fits and full trainings.
    """

    seed: int = 0
    shapes: int = 48
    shape_seed_base: int = 1_000_000
    points_per_shape: int = 4000
    iterations: int = 4000
    shapes_per_step: int = 2
    spectral_points: int = 2000
    lr: float = 3e-4
    warmup: int = 200
    loss: SkinningLoss = field(default_factory=SkinningLoss)
    num_handles: int = 10
    width: int = 64
    hidden_layers: int = 8
    eval_shapes: int = 4
    eval_iterations: int = 300

    def __post_init__(self) -> None:
        if isinstance(self.loss, dict):
            self.loss = SkinningLoss(**self.loss)
        for name in ("shapes", "points_per_shape", "shapes_per_step", "spectral_points", "num_handles", "width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"TemplateConfig.{name} must be an integer >= 1, got {v!r}")
        for name in ("seed", "shape_seed_base", "iterations", "warmup", "hidden_layers", "eval_shapes",
                     "eval_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"TemplateConfig.{name} must be an integer >= 0, got {v!r}")
        if self.shapes_per_step > self.shapes:
            raise ConfigError(f"TemplateConfig.shapes_per_step ({self.shapes_per_step}) exceeds shapes ({self.shapes})")
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not 0 < self.lr < math.inf:
            raise ConfigError(f"TemplateConfig.lr must be a finite positive number, got {self.lr!r}")


def procedural_shape_points(seed: int, rotation_seed: Sequence[int] | int, num_points: int,
                            sample_seed: int = 0) -> tuple[Tensor, float]:
    """Interior points of ``make_procedural_object(seed)`` turned by a random rotation (from ``rotation_seed``)
    and re-normalised to the canonical frame; returns (points (N, 3) float32, volume in that frame)."""

    mesh = make_procedural_object(seed, ProceduralShapeConfig(texture_size=8))
    R = torch.from_numpy(random_rotation(np.random.default_rng(rotation_seed)))
    v, _ = normalize_to_canonical(mesh.vertices.double() @ R.T)
    s = sample_solid(v, mesh.faces, num_points=num_points, max_contact_points=1, seed=sample_seed,
                     name=mesh.name)
    return s.points, s.volume


def _eval_report(trunk: SkinningField, shapes: list[tuple[Tensor, float]], config: TemplateConfig,
                 full: bool) -> list[dict[str, float]]:
    """Per held-out shape: the data-free loss of the spectral start, of the last-layer fit with
    ``eval_iterations``, and (``full``) of a full data-free training of a fresh field with as many iterations."""

    out = []
    for k, (pts, vol) in enumerate(shapes):
        row: dict[str, float] = {}
        start = spectral_last_layer(trunk, pts, config.loss).float()
        row.update({f"spectral_{key}": v for key, v in
                    skinning_loss_value(field_from_last_layer(trunk, start), pts, vol, config.loss).items()})
        fitted = fit_last_layer(trunk, pts, config.eval_iterations, seed=k, volume=vol, loss=config.loss)
        row.update({f"last_layer_{key}": v for key, v in
                    skinning_loss_value(field_from_last_layer(trunk, fitted), pts, vol, config.loss).items()})
        if full:
            f = SkinningField(config.num_handles, config.width, config.hidden_layers, seed=config.seed + 1 + k)
            lc = config.loss
            tc = SkinningTrainingConfig(iterations=config.eval_iterations, points_per_step=lc.points_per_step,
                                        batch_size=lc.batch_size, z_std=lc.z_std, elastic_weight=lc.elastic_weight,
                                        orthogonality_weight=lc.orthogonality_weight,
                                        youngs_modulus=lc.youngs_modulus, poisson_ratio=lc.poisson_ratio,
                                        seed=k, inversion_threshold=lc.inversion_threshold)
            train_skinning(f, pts, tc, progress=False, volume=vol)
            row.update({f"full_{key}": v for key, v in skinning_loss_value(f, pts, vol, config.loss).items()})
        out.append(row)
    return out


def train_template(config: TemplateConfig | None = None, progress: bool = True) -> tuple[SkinningField, dict]:
    """Train the template's hidden layers over a pool of procedural shapes (module docstring).

    Deterministic from ``config.seed`` for a given thread count. The returned field's last layer is its seeded
    initialisation (fits start from the spectral solution, not from it).

    Returns:
        (the template field, an info dict: the config, seconds, the loss curve (mean per 50 steps) and the
        held-out report before and after training (:func:`_eval_report`)).
    """
    from tqdm.auto import tqdm

    cfg = config or TemplateConfig()
    t_start = time.perf_counter()
    trunk = SkinningField(cfg.num_handles, cfg.width, cfg.hidden_layers, seed=cfg.seed)
    init_last = trunk.get_last_layer()
    pool_seeds = [cfg.shape_seed_base + k for k in range(cfg.shapes)]
    eval_seeds = [cfg.shape_seed_base + cfg.shapes + k for k in range(cfg.eval_shapes)]
    bar = tqdm(total=len(pool_seeds) + len(eval_seeds), desc="template shapes", unit="shape", disable=not progress)
    pool = []
    for s in pool_seeds + eval_seeds:
        pool.append(procedural_shape_points(s, [cfg.seed, s], cfg.points_per_shape, sample_seed=cfg.seed))
        bar.update(1)
    bar.close()
    shapes, held_out = pool[: cfg.shapes], pool[cfg.shapes:]
    t_shapes = time.perf_counter() - t_start
    before = _eval_report(trunk, held_out, cfg, full=True) if held_out else []

    m, width = cfg.num_handles, cfg.width
    trunk_params = [p for layer in trunk.layers[:-1] for p in layer.parameters()]
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    mu, lam = lame_parameters(cfg.loss.youngs_modulus, cfg.loss.poisson_ratio)

    def step(it: int) -> tuple[Tensor, dict[str, Tensor]]:
        picks = torch.randperm(len(shapes), generator=gen)[: cfg.shapes_per_step].tolist()
        total = torch.zeros(())
        for k in picks:
            pts, vol = shapes[k]
            # the head: the spectral start solved on one draw of the shape's points, differentiated through
            # (Cholesky, eigh) — the loss below is exactly O(10)-invariant, so the eigenvectors' derivative
            # within the 10 handles (1/(λᵢ − λⱼ) terms) does not enter
            fit_idx = torch.randint(pts.shape[0], (cfg.spectral_points,), generator=gen)
            head = spectral_last_layer(trunk, pts[fit_idx], cfg.loss, features=trunk_features(trunk, pts[fit_idx]))
            A, b = _split(head, m, width)
            # the loss on an independent draw: the orthogonality term exactly, the elastic term as its mean over
            # the random handle transforms to second order (energy_matrices)
            idx = torch.randint(pts.shape[0], (cfg.loss.points_per_step,), generator=gen)
            feats = trunk_features(trunk, pts[idx])
            _, w, _ = feats.weights(A.float(), b.float())
            lo = orthogonality_loss(w[:, :-1])
            K, _ = energy_matrices(feats)
            a = torch.cat([A.T, b[None]], dim=0)
            le = vol * cfg.loss.z_std ** 2 * (2 * mu + lam / 2) * torch.trace(a.T @ K @ a)
            total = total + cfg.loss.elastic_weight * le.float() + cfg.loss.orthogonality_weight * lo
        return total / len(picks), {}

    losses = optimise(trunk_params, step, Schedule(cfg.iterations, cfg.lr, warmup=min(cfg.warmup, cfg.iterations)),
                      Progress("template training", progress), "template training")
    curve = [float(np.mean(losses[i:i + 50])) for i in range(0, len(losses), 50)]  # the loss per 50 steps
    t_train = time.perf_counter() - t_start - t_shapes
    trunk.set_last_layer(init_last)
    after = _eval_report(trunk, held_out, cfg, full=False) if held_out else []
    for row, old in zip(after, before):
        row.update({k: v for k, v in old.items() if k.startswith("full_")})
        row.update({f"untrained_{k}": v for k, v in old.items() if not k.startswith("full_")})
    info = {"format": TEMPLATE_FORMAT, "config": asdict(cfg), "seconds_shapes": t_shapes, "seconds_training": t_train,
            "seconds_total": time.perf_counter() - t_start, "threads": torch.get_num_threads(),
            "torch": str(torch.__version__), "loss_curve_per_50_steps": curve, "held_out": after}
    return trunk, info


def save_template(template: SkinningField, info: dict, path: str | Path) -> Path:
    """Write the template (its state dict, float32, and ``info``) to ``path`` atomically."""
    payload = {"format": TEMPLATE_FORMAT, "num_handles": template.num_handles, "width": template.width,
               "hidden_layers": template.hidden_layers,
               "state_dict": {k: v.detach().float().clone() for k, v in template.state_dict().items()},
               "reference_last_layer": reference_last_layer(template).to(torch.float64), "info": info}
    return write_file_atomic(path, lambda tmp: torch.save(payload, tmp))


def _read(path: str | Path | None) -> dict:
    path = Path(path) if path is not None else TEMPLATE_PATH
    if not path.is_file():
        raise FileNotFoundError(f"template skinning network {path} does not exist"
                                + (" (the package was installed without its data; reinstall vid2sim)"
                                   if path == TEMPLATE_PATH else ""))
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != TEMPLATE_FORMAT:
        raise InputError(f"{path} is not a vid2sim template skinning network (format {TEMPLATE_FORMAT})")
    return payload


def load_template(path: str | Path | None = None) -> SkinningField:
    """The template :class:`SkinningField` (default: the shipped ``template_skinning.pt``), float32, CPU, with
    its gauge reference as the attribute ``gauge_reference`` (not in its state dict)."""
    payload = _read(path)
    f = SkinningField(int(payload["num_handles"]), int(payload["width"]), int(payload["hidden_layers"]), seed=0)
    f.load_state_dict(payload["state_dict"])
    f.gauge_reference = payload["reference_last_layer"].to(torch.float64)
    return f


def template_info(path: str | Path | None = None) -> dict:
    """The training record stored with a template (config, seconds, loss curve, held-out report)."""
    return _read(path)["info"]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m vid2sim.predictor.make_template [--out FILE] [--iterations N] [--shapes S] [--seed S]``."""
    p = argparse.ArgumentParser(prog="python -m vid2sim.predictor.make_template",
                                description="train the template skinning network (data-free, many shapes)")
    p.add_argument("--out", default=str(TEMPLATE_PATH), help=f"output file (default {TEMPLATE_PATH})")
    defaults = TemplateConfig()
    for name in ("seed", "shapes", "iterations", "shapes_per_step", "eval_shapes", "eval_iterations",
                 "points_per_shape"):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=getattr(defaults, name))
    p.add_argument("--lr", type=float, default=defaults.lr)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = TemplateConfig(**{k: getattr(args, k) for k in ("seed", "shapes", "iterations", "shapes_per_step", "lr",
                                                          "eval_shapes", "eval_iterations", "points_per_shape")})
    template, info = train_template(cfg, progress=not args.quiet)
    save_template(template, info, args.out)
    print(f"wrote {args.out}: {info['seconds_total']:.0f} s "
          f"(shapes {info['seconds_shapes']:.0f} s, training {info['seconds_training']:.0f} s)")
    for k, row in enumerate(info["held_out"]):
        totals = ", ".join(f"{key} {v:.4g}" for key, v in sorted(row.items()) if key.endswith("total"))
        print(f"held-out shape {k}: {totals}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
