"""The Stage I backbone: a VideoMAE video transformer (Tong et al. 2022) in plain PyTorch.

The network is VideoMAE's encoder as ``transformers.VideoMAEModel`` defines it, with the same parameter names, so
that a state dict moves between the two unchanged (``VideoMAEForPreTraining``'s encoder in
:mod:`vid2sim.predictor.pretrain`, a user's checkpoint loaded through transformers in
:func:`vid2sim.predictor.model.build_backbone`), and the same outputs (tests/test_predictor_model.py compares them
on random and shipped weights). It is written here so that *using* a predictor needs neither transformers nor its
import, which costs 2-5 s (it brings in torch's compiler); transformers stays for masked-autoencoder pre-training and
for reading a user's VideoMAE checkpoint.

- **Tubelet embedding**: a Conv3d of kernel = stride = (tubelet, patch, patch) over (B, C, T, H, W); tokens in the
  order (time, row, column).
- **Positions**: a fixed table (1, N, D) added to the tokens, passed to :meth:`VideoMAEBackbone.forward` by the
  caller (the predictor keeps the table it was trained with; :func:`vid2sim.predictor.model.sinusoid_table`).
- **Blocks** (pre-norm): x + Attention(LN(x)), then y + MLP(LN(y)) with GELU; queries and values have biases
  (``qv_bias``), keys none; attention scaled by 1/√(head width).
- **Output**: the last hidden states (B, N, D); a final LayerNorm only when ``use_mean_pooling`` is false.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from torch import Tensor, nn
from torch.nn import functional as Fn

from vid2sim.runtime.errors import ConfigError


def square_side(value: Any) -> int:
    """A square side from an int or a (height, width) pair."""
    if isinstance(value, (tuple, list)):
        if len(value) != 2 or int(value[0]) != int(value[1]):
            raise ConfigError(f"VideoMAE: only square images and patches are supported, got {value!r}")
        return int(value[0])
    return int(value)


@dataclass
class BackboneConfig:
    """The architecture of :class:`VideoMAEBackbone`: the fields of transformers' ``VideoMAEConfig`` that the
    encoder uses, with its names and defaults (``to_dict`` / ``from_dict`` read and write that config's dict)."""

    image_size: int = 224
    patch_size: int = 16
    num_channels: int = 3
    num_frames: int = 16
    tubelet_size: int = 2
    hidden_size: int = 768
    num_hidden_layers: int = 12
    num_attention_heads: int = 12
    intermediate_size: int = 3072
    hidden_act: str = "gelu"
    hidden_dropout_prob: float = 0.0
    attention_probs_dropout_prob: float = 0.0
    initializer_range: float = 0.02
    layer_norm_eps: float = 1e-12
    qv_bias: bool = True
    use_mean_pooling: bool = True

    def __post_init__(self) -> None:
        self.image_size, self.patch_size = square_side(self.image_size), square_side(self.patch_size)
        for name in ("image_size", "patch_size", "num_channels", "num_frames", "tubelet_size", "hidden_size",
                     "num_hidden_layers", "num_attention_heads", "intermediate_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"VideoMAE config: {name} must be a positive integer, got {value!r}")
        if self.hidden_act != "gelu":
            raise ConfigError(f"VideoMAE config: hidden_act {self.hidden_act!r} is not supported (only 'gelu')")
        if self.hidden_size % self.num_attention_heads:
            raise ConfigError(f"VideoMAE config: hidden_size {self.hidden_size} is not a multiple of "
                              f"num_attention_heads {self.num_attention_heads}")
        if self.image_size % self.patch_size or self.num_frames % self.tubelet_size:
            raise ConfigError(f"VideoMAE config: image_size {self.image_size} must be a multiple of patch_size "
                              f"{self.patch_size} and num_frames {self.num_frames} of tubelet_size {self.tubelet_size}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BackboneConfig:
        """From a ``VideoMAEConfig.to_dict()`` (as a predictor checkpoint stores it); other keys are ignored."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def to_dict(self) -> dict[str, Any]:
        """A dict ``transformers.VideoMAEConfig.from_dict`` reads (``model_type`` "videomae")."""
        return {**asdict(self), "model_type": "videomae"}

    @property
    def token_grid(self) -> tuple[int, int, int]:
        """(t, h, w): the tokens of a video in time, rows and columns (frames / tubelet, side / patch, side / patch)."""
        side = self.image_size // self.patch_size
        return (self.num_frames // self.tubelet_size, side, side)

    @property
    def num_patches(self) -> int:
        """Tokens per video: t · h · w of :attr:`token_grid`."""
        t, h, w = self.token_grid
        return t * h * w


class _PatchEmbeddings(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        kernel = (c.tubelet_size, c.patch_size, c.patch_size)
        self.projection = nn.Conv3d(c.num_channels, c.hidden_size, kernel_size=kernel, stride=kernel)


class _Embeddings(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        self.patch_embeddings = _PatchEmbeddings(c)


class _SelfAttention(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        self.heads = c.num_attention_heads
        self.dropout = c.attention_probs_dropout_prob
        self.query = nn.Linear(c.hidden_size, c.hidden_size, bias=c.qv_bias)
        self.key = nn.Linear(c.hidden_size, c.hidden_size, bias=False)
        self.value = nn.Linear(c.hidden_size, c.hidden_size, bias=c.qv_bias)

    def forward(self, x: Tensor) -> Tensor:
        b, n, d = x.shape

        def split(t: Tensor) -> Tensor:  # (B, N, D) -> (B, heads, N, D / heads)
            return t.view(b, n, self.heads, d // self.heads).transpose(1, 2)

        out = Fn.scaled_dot_product_attention(split(self.query(x)), split(self.key(x)), split(self.value(x)),
                                              dropout_p=self.dropout if self.training else 0.0)
        return out.transpose(1, 2).reshape(b, n, d)


class _Dense(nn.Module):
    """A linear layer under the name ``dense`` (the parameter names transformers uses)."""

    def __init__(self, n_in: int, n_out: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.dense = nn.Linear(n_in, n_out)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: Tensor) -> Tensor:
        return self.dropout(self.dense(x))


class _Attention(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        self.attention = _SelfAttention(c)
        self.output = _Dense(c.hidden_size, c.hidden_size, c.hidden_dropout_prob)


class _Layer(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        self.attention = _Attention(c)
        self.intermediate = _Dense(c.hidden_size, c.intermediate_size)
        self.output = _Dense(c.intermediate_size, c.hidden_size, c.hidden_dropout_prob)
        self.layernorm_before = nn.LayerNorm(c.hidden_size, eps=c.layer_norm_eps)
        self.layernorm_after = nn.LayerNorm(c.hidden_size, eps=c.layer_norm_eps)

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.attention.output(self.attention.attention(self.layernorm_before(x)))
        return x + self.output(Fn.gelu(self.intermediate(self.layernorm_after(x))))


class _Encoder(nn.Module):
    def __init__(self, c: BackboneConfig) -> None:
        super().__init__()
        self.layer = nn.ModuleList(_Layer(c) for _ in range(c.num_hidden_layers))


class VideoMAEBackbone(nn.Module):
    """VideoMAE's encoder (module docstring); parameters named as in ``transformers.VideoMAEModel``.

    Args:
        config: the architecture (a :class:`BackboneConfig`, or a ``VideoMAEConfig`` dict).
    """

    def __init__(self, config: BackboneConfig | dict[str, Any]) -> None:
        super().__init__()
        self.config = c = config if isinstance(config, BackboneConfig) else BackboneConfig.from_dict(config)
        self.embeddings = _Embeddings(c)
        self.encoder = _Encoder(c)
        self.layernorm = None if c.use_mean_pooling else nn.LayerNorm(c.hidden_size, eps=c.layer_norm_eps)
        self.apply(self._init_weights)

    def _init_weights(self, module: nn.Module) -> None:
        """VideoMAE's initialisation: linear and convolution weights N(0, initializer_range), biases 0, layer
        norms 1 and 0."""
        if isinstance(module, (nn.Linear, nn.Conv3d)):
            nn.init.normal_(module.weight, std=self.config.initializer_range)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.LayerNorm):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)

    def forward(self, video: Tensor, position_table: Tensor) -> Tensor:
        """The last hidden states.

        Args:
            video: (B, T, C, H, W) frames (T = ``num_frames``, H = W = ``image_size``).
            position_table: (1, N, D) or (N, D) position embeddings, N = ``num_patches``, D = ``hidden_size``.
        Returns:
            (B, N, D).
        """
        c = self.config
        if video.ndim != 5 or video.shape[2] != c.num_channels or video.shape[1] != c.num_frames or \
                tuple(video.shape[-2:]) != (c.image_size, c.image_size):
            raise ValueError(f"VideoMAE: video must be (B, {c.num_frames}, {c.num_channels}, {c.image_size}, "
                             f"{c.image_size}), got {tuple(video.shape)}")
        if position_table.shape[-2:] != (c.num_patches, c.hidden_size):
            raise ValueError(f"VideoMAE: position table must be (1, {c.num_patches}, {c.hidden_size}), got "
                             f"{tuple(position_table.shape)}")
        x = self.embeddings.patch_embeddings.projection(video.transpose(1, 2)).flatten(2).transpose(1, 2)
        x = x + position_table.to(device=x.device, dtype=x.dtype).reshape(1, c.num_patches, c.hidden_size)
        for layer in self.encoder.layer:
            x = layer(x)
        return x if self.layernorm is None else self.layernorm(x)
