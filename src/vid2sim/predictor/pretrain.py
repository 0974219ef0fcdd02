"""Self-supervised pre-training of the predictor's backbone: VideoMAE's masked-video autoencoder on our own videos.

The paper starts Stage I from a VideoMAE backbone pre-trained by masked autoencoding on large video sets. Those
weights cannot be downloaded here, and a vision transformer trained from scratch on a few thousand labelled
videos underfits. VideoMAE's own answer for small data is to pre-train on the same videos without labels
(Tong et al. 2022, "data-efficient learners"). :func:`pretrain_backbone` does that before the supervised steps
of :func:`~vid2sim.predictor.train.train_predictor` (``TrainConfig.pretrain_steps`` > 0):

- **Model.** ``transformers.VideoMAEForPreTraining`` built from the backbone's config, plus a small decoder
  (``pretrain_decoder_layers`` layers, half the backbone's width when the heads divide it, MLP 4×). Its
  encoder starts from the backbone's weights and uses the predictor's position table.
- **Masking.** Tube masking, as VideoMAE: per video one random set of ``round(mask_ratio · h·w)`` spatial
  patches is hidden in every tubelet (:func:`tube_mask`), so a hidden patch cannot be copied from the next
  frame. The loss is the MSE of the hidden patches' pixels, each patch normalised by its own mean and standard
  deviation (``norm_pix_loss``, transformers' implementation).
- **Data.** The training split's videos, in batches of ``pretrain_batch_size``, mirrored left-right with
  probability ½ (as the supervised steps). Labels are not used.
- **Optimiser.** Adam (β₂ = 0.95, as VideoMAE) at ``pretrain_lr`` with the supervised schedule's shape
  (linear warm-up, cosine decay to ``final_lr_fraction``).
- **Checkpoint and resume.** ``OUT/pretrain.pt`` (format ``vid2sim-predictor-pretrain/1``) holds the encoder
  and decoder, the optimiser, the step and the loss curve; it is written every ``eval_every`` steps and at the
  end. A rerun with the same settings continues from it bit for bit; other settings are refused.
- **Determinism.** Batches, mirroring and masks are drawn from generators keyed by the seed and the step.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import save_torch_atomic

if TYPE_CHECKING:  # pragma: no cover
    from vid2sim.predictor.model import PhysicsPredictor
    from vid2sim.predictor.train import Split, TrainConfig

PRETRAIN_FORMAT = "vid2sim-predictor-pretrain/1"
PRETRAIN_FILE = "pretrain.pt"
#: offsets that keep the pre-training's random streams apart from the supervised steps'
_BATCH_SEED, _MASK_SEED, _FLIP_SEED = 7_919, 104_729, 1_299_709


def tube_mask(batch: int, grid: tuple[int, int, int], ratio: float, generator: torch.Generator) -> Tensor:
    """VideoMAE's tube masking: (batch, t·h·w) bool, True = hidden.

    Each video hides the same ``round(ratio · h·w)`` spatial positions (drawn independently per video) in all
    t tubelets; tokens are in VideoMAE's order (time, row, column). Every row hides the same number of tokens,
    which ``VideoMAEForPreTraining`` needs.

    Args:
        grid: (t, h, w) tokens; ratio: share of spatial positions hidden, in (0, 1).
    Raises:
        ValueError: the ratio hides no position or all of them.
    """
    t, h, w = grid
    hidden = int(round(ratio * h * w))
    if not 0 < hidden < h * w:
        raise InputError(f"mask ratio {ratio} hides {hidden} of {h * w} patch positions; it must hide at least one "
                         "and leave at least one visible")
    order = torch.argsort(torch.rand(batch, h * w, generator=generator), dim=1)
    spatial = torch.zeros(batch, h * w, dtype=torch.bool)
    spatial.scatter_(1, order[:, :hidden], True)
    return spatial[:, None, :].expand(batch, t, h * w).reshape(batch, t * h * w)


def decoder_width(width: int, heads: int) -> int:
    """The decoder's width: half the encoder's when ``heads`` divides it, else the encoder's."""
    half = width // 2
    return half if half >= heads and half % heads == 0 else width


def build_pretraining_model(model: "PhysicsPredictor", decoder_layers: int, seed: int):
    """``VideoMAEForPreTraining`` whose encoder is a copy of ``model.backbone`` (weights and position table)
    and whose decoder is new (seeded by ``seed``)."""
    from transformers import VideoMAEConfig, VideoMAEForPreTraining

    bc = model.backbone.config
    heads = int(bc.num_attention_heads)
    dw = decoder_width(int(bc.hidden_size), heads)
    cfg = VideoMAEConfig.from_dict({**bc.to_dict(), "decoder_hidden_size": dw, "decoder_num_hidden_layers":
                                    int(decoder_layers), "decoder_num_attention_heads": heads,
                                    "decoder_intermediate_size": 4 * dw, "norm_pix_loss": True})
    torch.manual_seed(seed)
    pre = VideoMAEForPreTraining(cfg)
    pre.videomae.load_state_dict(model.backbone.state_dict())
    pre.videomae.embeddings.position_embeddings = model.position_table
    return pre


def token_grid(model: "PhysicsPredictor") -> tuple[int, int, int]:
    """(t, h, w) token grid of ``model``'s backbone."""
    return model.backbone.config.token_grid


def pretrain_settings(cfg: "TrainConfig") -> dict[str, Any]:
    """The settings a ``pretrain.pt`` must share with a run that resumes it."""
    from vid2sim.predictor.train import config_dict

    d = config_dict(cfg)
    keep = ("model", "seed", "mirror", "val_fraction", "split_seed", "final_lr_fraction", "warmup", "eval_every")
    return json.loads(json.dumps({k: v for k, v in d.items() if k in keep or k.startswith("pretrain_")}))


def pretrain_backbone(model: "PhysicsPredictor", train: "Split", cfg: "TrainConfig", out: Path,
                      deadline: float | None = None, progress: bool = True,
                      stop_at_step: int | None = None) -> dict[str, Any]:
    """Masked-autoencoder pre-training of ``model.backbone`` on the videos of ``train`` (module docstring).

    When it completes, ``model.backbone`` holds the pre-trained encoder. Stopped by ``deadline`` (a
    ``time.perf_counter()`` value) or at ``stop_at_step``, it writes ``OUT/pretrain.pt`` and leaves the backbone
    as it was; a rerun continues.

    Returns:
        {"steps", "steps_done", "complete", "curve" [{"step", "loss"}], "seconds", "decoder_width",
        "decoder_layers", "mask_ratio"}.
    Raises:
        ValueError: ``OUT/pretrain.pt`` was written with other settings, or the split has fewer videos than a
            batch.
    """
    from tqdm.auto import tqdm

    from vid2sim.predictor.train import (
        lr_factor,
        normalise_video,
        optimiser_step,
    )

    steps, bs = cfg.pretrain_steps, cfg.pretrain_batch_size
    if len(train) < bs:
        raise InputError(f"pre-training: {len(train)} training videos, fewer than one batch ({bs})")
    pre = build_pretraining_model(model, cfg.pretrain_decoder_layers, cfg.seed + 2)
    grid = token_grid(model)
    opt = torch.optim.Adam(pre.parameters(), lr=cfg.pretrain_lr, betas=(0.9, 0.95))
    path = out / PRETRAIN_FILE
    settings = pretrain_settings(cfg)
    step, curve, seconds = 0, [], 0.0
    if path.is_file():
        ck = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(ck, dict) or ck.get("format") != PRETRAIN_FORMAT:
            raise InputError(f"{path} is not a vid2sim pre-training checkpoint ({PRETRAIN_FORMAT})")
        if ck.get("settings") != settings:
            raise InputError(f"{path} was written with other pre-training settings; use another output folder or "
                             "the same settings to resume")
        pre.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        step, curve, seconds = int(ck["step"]), list(ck["curve"]), float(ck["seconds"])
    info = {"steps": steps, "decoder_width": int(pre.config.decoder_hidden_size),
            "decoder_layers": int(pre.config.decoder_num_hidden_layers), "mask_ratio": cfg.pretrain_mask_ratio}

    def save() -> None:
        save_torch_atomic({"format": PRETRAIN_FORMAT, "settings": settings, "state_dict": pre.state_dict(),
                      "optimizer": opt.state_dict(), "step": step, "curve": curve, "seconds": seconds}, path)

    per_epoch = max(1, len(train) // bs)
    perm, perm_epoch = None, -1
    window: list[float] = []
    t_mark = time.perf_counter()
    bar = tqdm(total=steps, initial=step, desc="pretrain-backbone", unit="step", disable=not progress)
    pre.train()
    while step < steps:
        if (deadline is not None and time.perf_counter() > deadline) or (
                stop_at_step is not None and step >= stop_at_step):
            break
        epoch, pos = divmod(step, per_epoch)
        if epoch != perm_epoch:
            perm = torch.randperm(len(train), generator=torch.Generator().manual_seed(cfg.seed + _BATCH_SEED
                                                                                      + 1000 * epoch))
            perm_epoch = epoch
        idx = perm[pos * bs:(pos + 1) * bs]
        video = normalise_video(train.videos[idx])
        if cfg.mirror:
            g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + _FLIP_SEED + step)
            flip = torch.rand(len(idx), generator=g) < 0.5
            video = torch.where(flip.view(-1, 1, 1, 1, 1), video.flip(-1), video)
        mask = tube_mask(len(idx), grid, cfg.pretrain_mask_ratio,
                         torch.Generator().manual_seed(cfg.seed * 1_000_003 + _MASK_SEED + step))
        for group in opt.param_groups:
            group["lr"] = cfg.pretrain_lr * lr_factor(step, steps, cfg.warmup, cfg.final_lr_fraction)
        window.append(optimiser_step(opt, pre(pixel_values=video, bool_masked_pos=mask).loss, "pre-training", step))
        step += 1
        bar.update(1)
        if step % cfg.eval_every == 0 or step == steps:
            curve.append({"step": step, "loss": float(np.mean(window))})
            bar.set_postfix(loss=f"{curve[-1]['loss']:.4f}")
            window = []
            seconds += time.perf_counter() - t_mark
            t_mark = time.perf_counter()
            save()
    bar.close()
    if step < steps:
        if window:
            curve.append({"step": step, "loss": float(np.mean(window))})
        seconds += time.perf_counter() - t_mark
        save()
    complete = step >= steps
    if complete:
        model.backbone.load_state_dict(pre.videomae.state_dict())
    return dict(info, steps_done=step, complete=complete, curve=curve, seconds=seconds,
                final_loss=curve[-1]["loss"] if curve else math.nan)
