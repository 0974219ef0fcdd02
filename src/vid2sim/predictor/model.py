"""The Stage I network: a VideoMAE backbone, mean-pooled tokens, and heads for log10 E, ν and the skinning
field's last layer (paper §4.1; docs/architecture.md, "The paper's numbers").

- **Backbone**: VideoMAE's encoder (:class:`~vid2sim.predictor.videomae.VideoMAEBackbone`, parameters named and
  outputs as ``transformers.VideoMAEModel``'s; transformers is needed only to read a user's checkpoint and to
  pre-train). By default a small configuration trained from scratch
  (:class:`PredictorConfig` defaults: 64² input, 16 frames, 16² patches, tubelets of 2 → 128 tokens; width
  192, 4 layers, 3 heads, MLP 768: 1.8 M backbone parameters). Any VideoMAE checkpoint on the local disk (a
  folder, or a model id already in the Hugging Face cache; loaded with ``local_files_only=True``) can replace
  it (:attr:`PredictorConfig.pretrained`).
- **Position embeddings**: in transformers, VideoMAE's are a fixed sine–cosine table over the *flattened*
  token index, an attribute computed from the config (not a parameter, not in the state dict). The table a
  checkpoint was trained with therefore encodes (frame, row, column) only through its own grid. When the
  input size or frame count differs, :func:`interpolate_position_table` reshapes the checkpoint's table to its
  (T/tubelet, H/patch, W/patch) grid and resamples it trilinearly to the new grid (an identity when the grid
  is the same). The table in use is a buffer of :class:`PhysicsPredictor` (``position_table``), so it is
  saved with the checkpoint.
- **Pooling**: the mean of all tokens' last hidden states (no masking).
- **Heads** (GELU between layers), scaled to the backbone width w: log10 E and ν each
  w → 2w/3 → w/3 → w/6 → 1 (768-512-256-128-1 for w = 768, as the paper's, docs/architecture.md), and the hypernetwork
  w → 650 → 650 → 650 → 650.
- **Outputs** are standardised: each head predicts (label − mean) / std with the training split's
  statistics, which are buffers of the model (``label_mean_*``, ``label_std_*``) and so travel with it;
  :meth:`PhysicsPredictor.predict` returns them in label units.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as Fn

from vid2sim.predictor.videomae import BackboneConfig, VideoMAEBackbone, square_side
from vid2sim.runtime.errors import ConfigError

#: the skinning field's last layer: 10 handles × (64 weights + 1 bias)
LAST_LAYER_SIZE = 650


@dataclass
class PredictorConfig:
    """Architecture of :class:`PhysicsPredictor`.

    Attributes:
        image_size: input side in pixels (square frames).
        num_frames: input frames (the paper: 16).
        patch_size, tubelet_size: VideoMAE's space and time patching.
        hidden_size, num_layers, num_heads, intermediate_size: the transformer (ignored when ``pretrained``).
        pretrained: a local VideoMAE checkpoint (folder, or a model id in the local Hugging Face cache) to start
            from instead of a from-scratch backbone (None: from scratch). Its patch and tubelet sizes are kept.
        last_layer_size: outputs of the hypernetwork (650 for the shipped template).
        framing: what of each frame the model sees: "object" (a square around the object's whole motion,
            :func:`vid2sim.predictor.predict.object_crop`) or "full" (the whole frame).
        seed: initialises the heads (and a from-scratch backbone).
    """

    image_size: int = 64
    num_frames: int = 16
    patch_size: int = 16
    tubelet_size: int = 2
    hidden_size: int = 192
    num_layers: int = 4
    num_heads: int = 3
    intermediate_size: int = 768
    pretrained: str | None = None
    last_layer_size: int = LAST_LAYER_SIZE
    framing: str = "object"
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("image_size", "num_frames", "patch_size", "tubelet_size", "hidden_size", "num_layers",
                     "num_heads", "intermediate_size", "last_layer_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"PredictorConfig.{name} must be a positive integer, got {v!r}")
        if self.framing not in ("object", "full"):
            raise ConfigError(f"PredictorConfig.framing must be 'object' or 'full', got {self.framing!r}")
        if self.pretrained is None:
            if self.image_size % self.patch_size or self.num_frames % self.tubelet_size:
                raise ConfigError(f"PredictorConfig: image_size {self.image_size} must be a multiple of patch_size "
                                 f"{self.patch_size} and num_frames {self.num_frames} of tubelet_size "
                                 f"{self.tubelet_size}")
            if self.hidden_size % self.num_heads:
                raise ConfigError(f"PredictorConfig: hidden_size {self.hidden_size} must be a multiple of num_heads "
                                 f"{self.num_heads}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def head_widths(width: int) -> list[int]:
    """Layer widths of a scalar head for backbone width ``width``: [w, 2w/3, w/3, w/6, 1] (rounded, ≥ 1)."""
    return [width, max(1, round(2 * width / 3)), max(1, round(width / 3)), max(1, round(width / 6)), 1]


def mlp(widths: list[int]) -> nn.Sequential:
    """Linear layers through ``widths`` with GELU between them (none after the last)."""
    layers: list[nn.Module] = []
    for k, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(nn.Linear(a, b))
        if k < len(widths) - 2:
            layers.append(nn.GELU())
    return nn.Sequential(*layers)


def sinusoid_table(n: int, dim: int) -> Tensor:
    """(n, dim) the fixed sine–cosine table VideoMAE uses: angle pos / 10000^(2⌊j/2⌋/dim), sin on even j, cos on
    odd j (float64 computed, float32 returned)."""
    pos = torch.arange(n, dtype=torch.float64)[:, None]
    j = torch.arange(dim, dtype=torch.float64)[None]
    angle = pos / torch.pow(
        torch.tensor(10000.0, dtype=torch.float64), 2 * torch.div(j, 2, rounding_mode="floor") / dim
    )
    table = torch.where(j.long() % 2 == 0, torch.sin(angle), torch.cos(angle))
    return table.float()


def interpolate_position_table(table: Tensor, old_grid: tuple[int, int, int], new_grid: tuple[int, int, int]) -> Tensor:
    """Resample a flattened position table to another token grid.

    Args:
        table: (N, D) or (1, N, D), N = t·h·w of ``old_grid`` (tokens in VideoMAE's order: time, row, column).
        old_grid, new_grid: (t, h, w) token grids.
    Returns:
        (1, t'·h'·w', D): trilinear resampling (align_corners=False) of the table seen as a (t, h, w) volume of
        D-vectors; the same table when the grids are equal.
    """
    t = table.reshape(-1, table.shape[-1])
    if t.shape[0] != math.prod(old_grid):
        raise ValueError(f"position table has {t.shape[0]} rows, expected {math.prod(old_grid)} for grid {old_grid}")
    if tuple(old_grid) == tuple(new_grid):
        return t[None].clone()
    vol = t.T.reshape(1, t.shape[1], *old_grid).float()
    out = Fn.interpolate(vol, size=tuple(new_grid), mode="trilinear", align_corners=False)
    return out.reshape(t.shape[1], -1).T[None].contiguous()


def build_backbone(cfg: PredictorConfig, backbone_config: dict | None = None) -> tuple[VideoMAEBackbone, Tensor]:
    """The VideoMAE backbone and its (1, N, D) position table (module docstring).

    ``backbone_config`` (a ``VideoMAEConfig`` dict, as stored in a predictor checkpoint) builds the architecture
    with untrained weights and a zero table, both to be filled from a state dict; it wins over ``cfg``. Only
    ``cfg.pretrained`` needs transformers (to read a user's checkpoint).

    Raises:
        OSError: ``cfg.pretrained`` is not a local checkpoint. ImportError: ``cfg.pretrained`` given and
            transformers is missing.
    """
    if backbone_config is not None:
        model = VideoMAEBackbone(dict(backbone_config))
        return model, torch.zeros(1, model.config.num_patches, model.config.hidden_size)
    if cfg.pretrained is None:
        torch.manual_seed(cfg.seed)
        model = VideoMAEBackbone(BackboneConfig(
            image_size=cfg.image_size, num_frames=cfg.num_frames, patch_size=cfg.patch_size,
            tubelet_size=cfg.tubelet_size, hidden_size=cfg.hidden_size, num_hidden_layers=cfg.num_layers,
            num_attention_heads=cfg.num_heads, intermediate_size=cfg.intermediate_size, use_mean_pooling=True))
        table = sinusoid_table(model.config.num_patches, cfg.hidden_size)[None]
        return model, table
    try:
        from transformers import VideoMAEConfig, VideoMAEModel
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("reading a pretrained VideoMAE checkpoint needs transformers (pip install transformers)") \
            from exc
    src = VideoMAEConfig.from_pretrained(cfg.pretrained, local_files_only=True)
    old = BackboneConfig.from_dict(src.to_dict()).token_grid
    if cfg.image_size % square_side(src.patch_size) or cfg.num_frames % src.tubelet_size:
        raise ValueError(f"PredictorConfig: image_size {cfg.image_size} / num_frames {cfg.num_frames} must be "
                         f"multiples of {cfg.pretrained}'s patch size {src.patch_size} / tubelet {src.tubelet_size}")
    read = VideoMAEModel.from_pretrained(cfg.pretrained, local_files_only=True, image_size=cfg.image_size,
                                         num_frames=cfg.num_frames)
    model = VideoMAEBackbone(read.config.to_dict())
    model.load_state_dict(read.state_dict())
    table = interpolate_position_table(sinusoid_table(math.prod(old), src.hidden_size), old, model.config.token_grid)
    return model, table


class LabelPredictor(nn.Module):
    """What inference needs of a Stage I model: ``forward`` (standardised outputs), ``unstandardise`` and
    :meth:`predict` in label units. :class:`PhysicsPredictor` is one network;
    :class:`~vid2sim.predictor.ensemble.PredictorEnsemble` several."""

    def unstandardise(self, z: dict[str, Tensor]) -> dict[str, Tensor]:
        raise NotImplementedError

    def label_statistics(self) -> dict[str, dict[str, Tensor]]:
        """The standardisation in use: {"log10_E" | "nu": {"mean": (), "std": ()}, "last_layer": {"mean": (650,),
        "std": (650,)}} in label units."""
        raise NotImplementedError

    @torch.no_grad()
    def predict(self, video: Tensor) -> dict[str, Tensor]:
        """Labels of ``video`` (B, T, 3, H, W) or (T, 3, H, W): {"log10_E", "nu", "last_layer"} (batch kept as
        given), ν clamped to [0, 0.49] (the joint stage's default bounds)."""
        single = video.ndim == 4
        out = self.unstandardise(self(video[None] if single else video))
        out["nu"] = out["nu"].clamp(0.0, 0.49)
        return {k: v[0] for k, v in out.items()} if single else out


class PhysicsPredictor(LabelPredictor):
    """Video → (log10 E, ν, last layer) (module docstring).

    Args:
        config: the architecture (default :class:`PredictorConfig`).
        backbone_config: a stored ``VideoMAEConfig`` dict (:func:`build_backbone`; used when loading).
    """

    def __init__(self, config: PredictorConfig | None = None, backbone_config: dict | None = None) -> None:
        super().__init__()
        self.config = cfg = config or PredictorConfig()
        self.backbone, table = build_backbone(cfg, backbone_config)
        bc = self.backbone.config
        self.width = bc.hidden_size
        self.image_size, self.num_frames = bc.image_size, bc.num_frames
        self.register_buffer("position_table", table.float())
        torch.manual_seed(cfg.seed + 1)
        self.head_E = mlp(head_widths(self.width))
        self.head_nu = mlp(head_widths(self.width))
        self.hyper = mlp([self.width] + [cfg.last_layer_size] * 4)
        for name, n in (("log10_E", 1), ("nu", 1), ("last_layer", cfg.last_layer_size)):
            self.register_buffer(f"label_mean_{name}", torch.zeros(n))
            self.register_buffer(f"label_std_{name}", torch.ones(n))

    def set_label_statistics(self, stats: dict[str, dict[str, Tensor]]) -> None:
        """Store the training split's label means and standard deviations (``TrainingData.label_statistics``);
        standard deviations below 1e-8 become 1."""
        for name in ("log10_E", "nu", "last_layer"):
            mean = torch.as_tensor(stats[name]["mean"], dtype=torch.float32).reshape(-1)
            std = torch.as_tensor(stats[name]["std"], dtype=torch.float32).reshape(-1)
            getattr(self, f"label_mean_{name}").copy_(mean)
            getattr(self, f"label_std_{name}").copy_(torch.where(std > 1e-8, std, torch.ones_like(std)))

    def label_statistics(self) -> dict[str, dict[str, Tensor]]:
        stats = {k: {"mean": getattr(self, f"label_mean_{k}"), "std": getattr(self, f"label_std_{k}")}
                 for k in ("log10_E", "nu", "last_layer")}
        for k in ("log10_E", "nu"):
            stats[k] = {"mean": stats[k]["mean"][0], "std": stats[k]["std"][0]}
        return stats

    def features(self, video: Tensor) -> Tensor:
        """(B, width) mean-pooled last hidden states of ``video`` (B, T, 3, H, W), ImageNet-normalised."""
        if video.ndim != 5 or video.shape[2] != 3:
            raise ValueError(f"video must be (B, T, 3, H, W), got {tuple(video.shape)}")
        if video.shape[1] != self.num_frames or tuple(video.shape[-2:]) != (self.image_size, self.image_size):
            raise ValueError(f"video must have {self.num_frames} frames of {self.image_size}x{self.image_size}, got "
                             f"{tuple(video.shape)}")
        return self.backbone(video, self.position_table).mean(dim=1)

    def forward(self, video: Tensor) -> dict[str, Tensor]:
        """Standardised predictions: {"log10_E": (B,), "nu": (B,), "last_layer": (B, 650)}."""
        h = self.features(video)
        return {"log10_E": self.head_E(h)[:, 0], "nu": self.head_nu(h)[:, 0], "last_layer": self.hyper(h)}

    def unstandardise(self, z: dict[str, Tensor]) -> dict[str, Tensor]:
        """Standardised outputs → label units (log10 Pa, −, last-layer numbers)."""
        return {k: z[k] * getattr(self, f"label_std_{k}") + getattr(self, f"label_mean_{k}") for k in z}

    def standardise(self, y: dict[str, Tensor]) -> dict[str, Tensor]:
        """Labels → standardised values (the inverse of :meth:`unstandardise`)."""
        return {k: (y[k] - getattr(self, f"label_mean_{k}")) / getattr(self, f"label_std_{k}") for k in y}



@dataclass
class LossWeights:
    """loss = log10_E · MSE(log10 E) + nu · MSE(ν) + last_layer · MSE(650) (the issue's 1, 100, 1).

    The first two are taken in label units (log10 Pa, −), as the paper; the last on the standardised components:
    the raw numbers have a standard deviation of about 0.007, so their MSE (≈ 1e-4) would teach nothing.
    """

    log10_E: float = 1.0
    nu: float = 100.0
    last_layer: float = 1.0

    def __post_init__(self) -> None:
        for name in ("log10_E", "nu", "last_layer"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < math.inf:
                raise ConfigError(f"LossWeights.{name} must be a finite number >= 0, got {v!r}")


def predictor_loss(model: PhysicsPredictor, z: dict[str, Tensor], targets: dict[str, Tensor],
                   weights: LossWeights | None = None,
                   last_layer_mask: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
    """The training loss of standardised outputs ``z`` against label-unit ``targets`` (:class:`LossWeights`).

    ``last_layer_mask`` (B,) bool, when given, keeps only those samples in the last-layer term (a mirrored
    video's label would be the mirrored skinning field's, which is not the stored one); with no sample kept
    the term is 0.

    Returns:
        (the scalar loss, its parts {"log10_E", "nu", "last_layer"} as floats, unweighted MSEs).
    """
    w = weights or LossWeights()
    y = model.unstandardise({"log10_E": z["log10_E"], "nu": z["nu"]})
    zl = model.standardise({"last_layer": targets["last_layer"]})["last_layer"]
    if last_layer_mask is None:
        layer = Fn.mse_loss(z["last_layer"], zl)
    elif bool(last_layer_mask.any()):
        layer = Fn.mse_loss(z["last_layer"][last_layer_mask], zl[last_layer_mask])
    else:
        layer = z["last_layer"].sum() * 0.0
    parts = {"log10_E": Fn.mse_loss(y["log10_E"], targets["log10_E"]),
             "nu": Fn.mse_loss(y["nu"], targets["nu"]), "last_layer": layer}
    loss = w.log10_E * parts["log10_E"] + w.nu * parts["nu"] + w.last_layer * parts["last_layer"]
    return loss, {k: float(v.detach()) for k, v in parts.items()}


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
