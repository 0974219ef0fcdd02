"""Training the Stage I predictor (``vid2sim train-predictor``) and its checkpoint format.

:func:`train_predictor` reads a ``vid2sim make-training-data`` folder through
:class:`~vid2sim.predictor.dataset.TrainingData` (split by object, ``val_fraction`` held out), standardises
the labels with the training split's statistics (stored in the model), and trains with Adam on the loss of
:func:`~vid2sim.predictor.model.predictor_loss`.

- The whole split is decoded once into memory as uint8 frames (1 200 samples of 16 × 64² take 236 MB).
- Deterministic for a seed and thread count: the heads and backbone are seeded, and epoch k visits the training
  samples in the permutation drawn from ``seed + k``.
- Every ``eval_every`` steps (and at the end) it evaluates on the validation split, writes ``OUT/last.pt``
  (model, optimiser, step, log) and, when the validation loss is the lowest so far, ``OUT/best.pt``. Rerunning
  with the same OUT resumes from ``last.pt`` and continues the same sequence of batches.
- ``max_minutes`` stops early at a step boundary (after a final evaluation); rerun to continue.
- At the end ``OUT/predictor.pt`` is the best checkpoint in the shippable form (weights in float16, no
  optimiser) and ``OUT/train_log.json`` the record: the loss curve, the validation curve (MAE of log10 E and
  ν in label units, MSE of the standardised last layer) and the constant-mean baselines on the same split.

Checkpoint (``torch.save`` dict, format ``vid2sim-predictor/1``): {"format", "config" (PredictorConfig),
"backbone_config" (VideoMAEConfig dict), "state_dict" (includes the position table and label statistics),
"label_stats", "data_config" (the dataset's index config), "train_config", "metrics"}; ``last.pt`` adds
"optimizer", "step", "log". :func:`load_predictor` reads any of them.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vid2sim.predictor.dataset import IMAGENET_MEAN, IMAGENET_STD, TrainingData
from vid2sim.predictor.ensemble import ENSEMBLE_FORMAT, PredictorEnsemble
from vid2sim.predictor.model import (
    LabelPredictor,
    LossWeights,
    PhysicsPredictor,
    PredictorConfig,
    predictor_loss,
)
from vid2sim.predictor.predict import frame_for_model
from vid2sim.predictor.pretrain import pretrain_backbone
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.files import load_torch_file, save_torch_atomic

CHECKPOINT_FORMAT = "vid2sim-predictor/1"


@dataclass
class TrainConfig:
    """Settings of :func:`train_predictor`.

    Attributes:
        model: the architecture (:class:`PredictorConfig`).
        steps: optimiser steps in all.
        batch_size: samples per step.
        lr: Adam's learning rate (cosine decay to ``lr · final_lr_fraction`` after ``warmup`` linear steps).
            The paper gives 1e-5 for fine-tuning a pre-trained backbone; a small backbone from scratch needs more.
        final_lr_fraction, warmup: the schedule.
        weight_decay: Adam's L2 term.
        loss: the loss weights (the issue's 1, 100, 1).
        val_fraction, split_seed: the validation split (by object).
        eval_every: steps between validations and checkpoints.
        max_minutes: stop at the first step boundary after this wall time (None: run all steps); rerun resumes.
        seed: model initialisation and batch order.
        mirror: augment by mirroring each training video left-right with probability 1/2 (drawn from ``seed``
            and the step). The front view's world is symmetric about the camera's vertical plane (gravity, floor,
            an isotropic material), so log10 E and ν keep their labels; the last layer's label would be the
            mirrored field's, so mirrored samples leave the last-layer term.
        colour_permute: augment by permuting each training video's RGB channels (one of the 6 orders, uniformly,
            drawn from ``seed`` and the step). The renderer's light is white and the textures are arbitrary,
            so a permuted video is the render of the same drop with a recoloured texture: every label (log10 E,
            ν and the last layer, which depends on the shape only) is kept.
        pretrain_steps: masked-autoencoder steps on the training split's videos before the supervised steps
            (:mod:`vid2sim.predictor.pretrain`; 0: none).
        pretrain_batch_size, pretrain_lr, pretrain_mask_ratio, pretrain_decoder_layers: their batch, Adam's
            learning rate (the same schedule's shape), the share of patch positions hidden (VideoMAE's 0.9) and
            the decoder's depth.
    """

    model: PredictorConfig = field(default_factory=PredictorConfig)
    steps: int = 4000
    batch_size: int = 8
    lr: float = 3e-4
    final_lr_fraction: float = 0.02
    warmup: int = 100
    weight_decay: float = 0.0
    loss: LossWeights = field(default_factory=LossWeights)
    val_fraction: float = 0.1
    split_seed: int = 0
    eval_every: int = 200
    max_minutes: float | None = None
    seed: int = 0
    mirror: bool = True
    colour_permute: bool = False
    pretrain_steps: int = 0
    pretrain_batch_size: int = 16
    pretrain_lr: float = 3e-4
    pretrain_mask_ratio: float = 0.9
    pretrain_decoder_layers: int = 2

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "eval_every", "pretrain_batch_size", "pretrain_decoder_layers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"TrainConfig.{name} must be a positive integer, got {v!r}")
        if not (self.lr > 0 and 0 < self.final_lr_fraction <= 1 and self.warmup >= 0 and self.weight_decay >= 0):
            raise ConfigError("TrainConfig needs lr > 0, 0 < final_lr_fraction <= 1, warmup >= 0, weight_decay >= 0")
        if isinstance(self.pretrain_steps, bool) or not isinstance(self.pretrain_steps, int) or self.pretrain_steps < 0:
            raise ConfigError(f"TrainConfig.pretrain_steps must be an integer >= 0, got {self.pretrain_steps!r}")
        if not self.pretrain_lr > 0:
            raise ConfigError(f"TrainConfig.pretrain_lr must be positive, got {self.pretrain_lr}")
        if not 0 < self.pretrain_mask_ratio < 1:
            raise ConfigError(f"TrainConfig.pretrain_mask_ratio must lie in (0, 1), got {self.pretrain_mask_ratio}")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ConfigError(f"TrainConfig.max_minutes must be positive, got {self.max_minutes}")


# ---- data -----------------------------------------------------------------------------------------------

def release_freed_memory() -> None:
    """Give memory freed by Python and torch back to the operating system (glibc's ``malloc_trim``; nothing
    elsewhere).

    Decoding thousands of videos allocates and frees megabytes per sample. glibc's adaptive mmap threshold then
    serves them from the heap, where the small blocks that are kept pin the freed ones. Measured: 2.8 GB resident
    for 0.11 GB of kept frames (584 samples at 128² → 64²), and 13 GB for 6 000 samples, so a second training
    run was killed for lack of memory. Trimming every few samples keeps it at the kept data plus one sample.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if name is None:
        return
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # not glibc (macOS, musl): their allocators return memory themselves
        return
    trim(0)


class Split:
    """One split decoded into memory: uint8 videos (N, T, 3, S, S) and labels (frames framed as the model's
    ``framing`` says and resized to side ``size`` by area averaging, as :func:`frame_for_model` does)."""

    def __init__(self, data: TrainingData, size: int | None = None, framing: str = "full") -> None:

        n = len(data)
        mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        logE, nu, layers = [], [], []
        self.videos = torch.zeros(0, dtype=torch.uint8)
        for i in range(n):  # in order: each shard is decoded once
            if i % 32 == 0:
                release_freed_memory()
            v, t = data[i]
            u = v * std + mean if data.normalize == "imagenet" else v
            if framing != "full" or (size is not None and u.shape[-1] != size):
                u = frame_for_model(u.permute(0, 2, 3, 1), size or u.shape[-1], framing) * std + mean
            if i == 0:
                self.videos = torch.empty((n, *u.shape), dtype=torch.uint8)
            self.videos[i] = (u * 255.0).round().clamp(0, 255)
            logE.append(t["log10_E"])
            nu.append(t["nu"])
            layers.append(t["last_layer"])
        release_freed_memory()
        self.targets = {"log10_E": torch.stack(logE) if n else torch.zeros(0),
                        "nu": torch.stack(nu) if n else torch.zeros(0),
                        "last_layer": torch.stack(layers) if n else torch.zeros(0, 650)}

    @classmethod
    def cached(cls, data: TrainingData, size: int | None, framing: str, path: Path) -> "Split":
        """The split decoded once and kept in ``path`` (a torch file read memory-mapped on later runs).

        Decoding 20 000 videos takes tens of minutes, and a long training resumes over several sittings. The
        file records what it was made from (the data folder's shards, the draws, the size and the framing);
        when any of that differs the split is decoded again and the file replaced.
        """
        key = {"shards": list(data.shards), "draws": data.draws, "size": size, "framing": framing,
               "normalize": data.normalize}
        if path.is_file():
            try:
                stored = torch.load(path, mmap=True, weights_only=True)
            except (RuntimeError, OSError, ValueError, EOFError):  # torn or foreign: decode again
                stored = None
            if stored is not None and stored.get("key") == json.dumps(key):
                split = cls.__new__(cls)
                split.videos, split.targets = stored["videos"], stored["targets"]
                return split
        split = cls(data, size, framing)
        save_torch_atomic({"key": json.dumps(key), "videos": split.videos, "targets": split.targets}, path)
        return split

    def __len__(self) -> int:
        return int(self.videos.shape[0])

    def batch(self, idx: torch.Tensor, channel_orders: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Normalised videos (B, T, 3, R, R) and targets of the samples ``idx`` (B,); ``channel_orders`` (B, 3)
        permutes each video's RGB channels first."""
        frames = self.videos[idx]
        if channel_orders is not None:
            frames = torch.stack([f[:, order] for f, order in zip(frames, channel_orders)])
        return normalise_video(frames), {k: v[idx] for k, v in self.targets.items()}


def random_channel_orders(n: int, generator: torch.Generator) -> torch.Tensor:
    """(n, 3) independent uniform permutations of (0, 1, 2)."""
    return torch.stack([torch.randperm(3, generator=generator) for _ in range(n)]) if n else torch.zeros(0, 3,
                                                                                                          dtype=torch.long)


def normalise_video(frames: torch.Tensor) -> torch.Tensor:
    """uint8 (…, T, 3, R, R) frames → float32 ImageNet-normalised (what :class:`TrainingData` gives)."""
    mean = torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(3, 1, 1)
    return (frames.float() / 255.0 - mean) / std


# ---- evaluation -----------------------------------------------------------------------------------------

@torch.no_grad()
def evaluate(model: LabelPredictor, split: Split, weights: LossWeights, batch_size: int = 16) -> dict[str, float]:
    """Validation figures of ``model`` on ``split``: loss, MAE of log10 E and ν (label units), MSE of the
    standardised last layer."""
    model.eval()
    n = len(split)
    if n == 0:
        return {}
    preds: dict[str, list[torch.Tensor]] = {"log10_E": [], "nu": [], "last_layer": []}
    zs: list[torch.Tensor] = []
    for s in range(0, n, batch_size):
        idx = torch.arange(s, min(n, s + batch_size))
        video, _ = split.batch(idx)
        z = model(video)
        y = model.unstandardise(z)
        for k in preds:
            preds[k].append(y[k])
        zs.append(z["last_layer"])
    y = {k: torch.cat(v) for k, v in preds.items()}
    t = split.targets
    z = {"log10_E": model.standardise({"log10_E": y["log10_E"]})["log10_E"],
         "nu": model.standardise({"nu": y["nu"]})["nu"], "last_layer": torch.cat(zs)}
    loss, parts = predictor_loss(model, z, t, weights)
    return {"loss": float(loss), "mae_log10_E": float((y["log10_E"] - t["log10_E"]).abs().mean()),
            "mae_nu": float((y["nu"] - t["nu"]).abs().mean()), "mse_last_layer_std": parts["last_layer"],
            "samples": n, "by_log10_E": errors_by_range(y["log10_E"], t["log10_E"])}


def errors_by_range(pred: torch.Tensor, true: torch.Tensor, width: float = 0.25) -> list[dict[str, float]]:
    """Errors of log10 E predictions ``pred`` (N,) against ``true`` (N,) per bin of the true value ``width``
    decades wide: [{"lo", "hi", "n", "mae", "bias"}] for the non-empty bins (bias = mean of pred − true)."""
    pred, true = pred.flatten().double(), true.flatten().double()
    if true.numel() == 0:
        return []
    out = []
    lo = math.floor(float(true.min()) / width) * width
    while lo <= float(true.max()):
        k = (true >= lo) & (true < lo + width)
        if bool(k.any()):
            d = pred[k] - true[k]
            out.append({"lo": round(lo, 6), "hi": round(lo + width, 6), "n": int(k.sum()),
                        "mae": float(d.abs().mean()), "bias": float(d.mean())})
        lo += width
    return out


def constant_baselines(stats: dict[str, dict[str, torch.Tensor]], split: Split) -> dict[str, float]:
    """MAE on ``split`` of the constant predictor that always answers the training split's mean (label units),
    and the standardised last layer's MSE for the mean last layer."""
    t = split.targets
    z = (t["last_layer"] - stats["last_layer"]["mean"]) / torch.where(
        stats["last_layer"]["std"] > 1e-8, stats["last_layer"]["std"], torch.ones_like(stats["last_layer"]["std"]))
    return {"mae_log10_E": float((t["log10_E"] - stats["log10_E"]["mean"]).abs().mean()),
            "mae_nu": float((t["nu"] - stats["nu"]["mean"]).abs().mean()),
            "mse_last_layer_std": float((z ** 2).mean())}


def evaluate_predictor(path: str | Path, data_folder: str | Path, split: str = "all", val_fraction: float = 0.1,
                       split_seed: int = 0) -> dict[str, Any]:
    """Figures of the checkpoint at ``path`` on a training-data folder — typically a test set generated with
    another ``--seed``, whose objects and draws the training never saw.

    The videos are framed and resized as the checkpoint's model expects. The constant baselines answer the
    checkpoint's own training-split label means (what the model knows without looking at the video).

    Returns:
        {"checkpoint", "data", "split", "samples", "mae_log10_E", "mae_nu", "mse_last_layer_std", "loss",
        "baseline_mae_log10_E", "baseline_mae_nu", "baseline_mse_last_layer_std", "framing", "seconds"}.
    Raises:
        FileNotFoundError / ValueError: no checkpoint or not a training-data folder; videos of another frame
        count than the model's.
    """
    t0 = time.perf_counter()
    model = load_predictor(path)
    data = TrainingData(data_folder, split, val_fraction, split_seed)
    frames = int(data.index["config"]["frames"])
    if frames != model.num_frames:
        raise InputError(f"{data_folder}: videos of {frames} frames, the predictor takes {model.num_frames}")
    if len(data) == 0:
        raise InputError(f"{data_folder}: the {split!r} split has no samples")
    part = Split(data, model.image_size, model.config.framing)
    with torch.no_grad():
        figures = evaluate(model, part, LossWeights())
    stats = model.label_statistics()
    base = constant_baselines(stats, part)
    return {"checkpoint": str(path), "data": str(data_folder), "split": split, "framing": model.config.framing,
            **figures, **{f"baseline_{k}": v for k, v in base.items()}, "seconds": time.perf_counter() - t0}


# ---- checkpoints ----------------------------------------------------------------------------------------


def checkpoint_payload(model: PhysicsPredictor, *, half: bool = False, label_stats: dict | None = None,
                       data_config: dict | None = None, train_config: dict | None = None,
                       metrics: dict | None = None) -> dict[str, Any]:
    """The checkpoint dict of ``model`` (module docstring); ``half`` stores floating weights as float16."""
    sd = {k: (v.detach().half() if half and v.is_floating_point() and "label_" not in k else v.detach().clone())
          for k, v in model.state_dict().items()}
    return {"format": CHECKPOINT_FORMAT, "config": model.config.to_dict(),
            "backbone_config": model.backbone.config.to_dict(), "state_dict": sd,
            "label_stats": _plain(label_stats), "data_config": data_config, "train_config": train_config,
            "metrics": metrics}


def save_predictor(model: PhysicsPredictor, path: str | Path, half: bool = False, **info: Any) -> Path:
    """Write ``model`` as a checkpoint at ``path`` atomically (``info``: label_stats, data_config, train_config,
    metrics)."""
    path = Path(path)
    save_torch_atomic(checkpoint_payload(model, half=half, **info), path)
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict at ``path``. Raises FileNotFoundError / ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"predictor checkpoint {path} does not exist")

    payload = load_torch_file(path, "a vid2sim predictor checkpoint")
    if not isinstance(payload, dict) or payload.get("format") not in (CHECKPOINT_FORMAT, ENSEMBLE_FORMAT):
        raise InputError(f"{path} is not a vid2sim predictor checkpoint (format {CHECKPOINT_FORMAT} or "
                         f"{ENSEMBLE_FORMAT})")
    return payload


def model_from_payload(payload: dict[str, Any]) -> PhysicsPredictor:
    """The network of a single-network checkpoint dict (float32, CPU, eval mode)."""
    cfg = dict(payload["config"])
    cfg.setdefault("framing", "full")  # checkpoints made before the object framing existed
    model = PhysicsPredictor(PredictorConfig(**cfg), backbone_config=payload["backbone_config"])
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in payload["state_dict"].items()})
    return model.eval()


def load_predictor(path: str | Path) -> LabelPredictor:
    """The model stored at ``path`` — a :class:`PhysicsPredictor`, or a
    :class:`~vid2sim.predictor.ensemble.PredictorEnsemble` for an ensemble checkpoint — (float32, CPU, eval
    mode), with the checkpoint's ``metrics`` and ``data_config`` (an ensemble's: its first member's) as
    attributes of the same names."""

    payload = read_checkpoint(path)
    try:
        if payload["format"] == ENSEMBLE_FORMAT:
            model: LabelPredictor = PredictorEnsemble([model_from_payload(m) for m in payload["members"]],
                                                      mirror=payload["mirror"]).eval()
            data_config = payload["members"][0].get("data_config")
        else:
            model, data_config = model_from_payload(payload), payload.get("data_config")
    except (KeyError, IndexError, TypeError, AttributeError, RuntimeError, ValueError) as exc:
        # a checkpoint with the right format tag but broken contents (missing or mistyped entries, tensors of
        # the wrong shape)
        raise InputError(f"{path}: a damaged predictor checkpoint ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:200] if str(exc) else ''})") from None
    model.metrics = payload.get("metrics")
    model.data_config = data_config
    return model


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, torch.Tensor):
        return x.tolist()
    return x


# ---- training -------------------------------------------------------------------------------------------

def lr_factor(step: int, steps: int, warmup: int, final_fraction: float) -> float:
    """The learning-rate factor at ``step`` of ``steps``: linear warm-up over ``warmup`` steps, then cosine decay
    from 1 to ``final_fraction``."""
    if warmup and step < warmup:
        return (step + 1) / warmup
    frac = min(1.0, (step - warmup) / max(1, steps - warmup))
    return final_fraction + (1 - final_fraction) * 0.5 * (1 + math.cos(math.pi * frac))


def optimiser_step(opt: torch.optim.Optimizer, loss: torch.Tensor, what: str, step: int) -> float:
    """One optimiser step on the scalar ``loss``; its value. Raises FloatingPointError (naming ``what`` and
    ``step``) when the loss is not finite."""
    if not torch.isfinite(loss):
        raise FloatingPointError(f"{what}: the loss became {float(loss)} at step {step}")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def config_dict(cfg: TrainConfig) -> dict[str, Any]:
    d = asdict(cfg)
    d.pop("max_minutes")
    return d


def train_predictor(data_folder: str | Path, out: str | Path, config: TrainConfig | None = None,
                    progress: bool = True, stop_at_step: int | None = None) -> dict[str, Any]:
    """Train (or resume training) the predictor on ``data_folder`` into the folder ``out`` (module docstring).

    ``stop_at_step`` ends this call once that many steps are done in all (a checkpoint is written; rerun to
    continue), like ``max_minutes`` but in steps.

    Returns:
        the training log (also ``OUT/train_log.json``): {"config", "data", "baselines", "train_curve",
        "val_curve", "best", "final", "seconds", "steps_done", "complete", "threads", ...}.
    Raises:
        ValueError: the data folder has too few samples, or ``OUT/last.pt`` was made with other settings.
    """
    from tqdm.auto import tqdm

    cfg = config or TrainConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    train_data, val_data, stats, train, val = _training_splits(data_folder, cfg, out)
    data_cfg = train_data.index.get("config")
    t_data = time.perf_counter() - t_start

    model = PhysicsPredictor(cfg.model)
    model.set_label_statistics(stats)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    last_path = out / "last.pt"
    cfg_dict = config_dict(cfg)
    step, log = _resume(model, opt, last_path, cfg_dict)
    baselines = constant_baselines(stats, val)
    deadline = None if cfg.max_minutes is None else time.perf_counter() + 60.0 * cfg.max_minutes
    data_record = {"folder": str(data_folder), "train_samples": len(train), "val_samples": len(val),
                   "train_objects": len(train_data.shards), "val_objects": len(val_data.shards),
                   "data_config": data_cfg, "seconds_loading": t_data}
    if cfg.pretrain_steps and not last_path.is_file():
        log["pretrain"] = pretrain_backbone(model, train, cfg, out, deadline, progress)
        if not log["pretrain"]["complete"]:
            record = {"config": cfg_dict, "data": data_record, "baselines_constant_mean": baselines,
                      "pretrain": log["pretrain"], "train_curve": [], "val_curve": [], "best": None, "final": None,
                      "steps_done": 0, "complete": False, "seconds_training": 0.0,
                      "threads": torch.get_num_threads(), "torch": str(torch.__version__)}
            return _write_train_log(out, record)
    info = {"label_stats": stats, "data_config": data_cfg, "train_config": cfg_dict}
    run = _TrainingRun(model, opt, cfg, train, val, log, step, info, out)
    run.bar = tqdm(total=cfg.steps, initial=step, desc="train-predictor", unit="step", disable=not progress)
    stopped_early = run.train(deadline, stop_at_step)
    run.bar.close()
    if stopped_early and (not log["val_curve"] or log["val_curve"][-1]["step"] != run.step):
        run.validate_when_stopped()
    step = run.step
    complete = step >= cfg.steps
    _ship_predictor(run, baselines, complete)
    record = {"config": cfg_dict, "data": data_record, "pretrain": log.get("pretrain"),
              "label_stats": _plain({k: {"mean": v["mean"], "std": v["std"]} for k, v in stats.items()
                                     if k != "last_layer"}),
              "baselines_constant_mean": baselines, "train_curve": log["train_curve"], "val_curve": log["val_curve"],
              "best": log["best"], "final": log["val_curve"][-1] if log["val_curve"] else None, "steps_done": step,
              "complete": complete, "seconds_training": log.get("seconds_training", 0.0),
              "threads": torch.get_num_threads(), "torch": str(torch.__version__)}
    return _write_train_log(out, record)


def _write_train_log(out: Path, record: dict[str, Any]) -> dict[str, Any]:
    """Write the training log ``record`` to ``OUT/train_log.json``; returns it."""
    (out / "train_log.json").write_text(json.dumps(record, indent=1))
    return record


def _training_splits(data_folder: str | Path, cfg: TrainConfig, out: Path
                     ) -> tuple[TrainingData, TrainingData, dict[str, dict[str, torch.Tensor]], Split, Split]:
    """The training and validation data of ``data_folder`` (checked: at least one batch, the model's frame count),
    the label statistics of the training data, and both splits decoded once into ``out`` (``OUT/split_*.pt``,
    memory-mapped on a resume)."""
    train_data = TrainingData(data_folder, "train", cfg.val_fraction, cfg.split_seed)
    val_data = TrainingData(data_folder, "val", cfg.val_fraction, cfg.split_seed)
    if len(train_data) < cfg.batch_size:
        raise InputError(f"{data_folder}: {len(train_data)} training samples, fewer than one batch "
                         f"({cfg.batch_size})")
    data_cfg = train_data.index.get("config")
    if int(data_cfg["frames"]) != cfg.model.num_frames:
        raise InputError(f"{data_folder}: videos of {data_cfg['frames']} frames, the model takes "
                         f"{cfg.model.num_frames}")
    stats = train_data.label_statistics()
    train = Split.cached(train_data, cfg.model.image_size, cfg.model.framing, out / "split_train.pt")
    val = Split.cached(val_data, cfg.model.image_size, cfg.model.framing, out / "split_val.pt")
    return train_data, val_data, stats, train, val


def _resume(model: PhysicsPredictor, opt: torch.optim.Optimizer, last_path: Path, cfg_dict: dict[str, Any]
            ) -> tuple[int, dict[str, Any]]:
    """The step and training log to start from: those of ``last_path`` (whose weights and optimiser state are
    loaded into ``model`` and ``opt``; InputError if it was written with other settings), else 0 and a new log."""
    log: dict[str, Any] = {"train_curve": [], "val_curve": [], "best": None, "seconds_training": 0.0}
    step = 0
    if last_path.is_file():
        ck = read_checkpoint(last_path)
        if ck.get("train_config") != json.loads(json.dumps(cfg_dict)) and ck.get("train_config") != cfg_dict:
            raise InputError(f"{last_path} was written with other training settings; use another output folder or "
                             "the same settings to resume")
        model.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        step, log = int(ck["step"]), ck["log"]
    return step, log


class _TrainingRun:
    """One run of :func:`train_predictor`'s loop: the model, its optimiser, the step, the log and the checkpoints
    (``OUT/last.pt`` at every evaluation, ``OUT/best.pt`` when the validation loss improves)."""

    def __init__(self, model: PhysicsPredictor, opt: torch.optim.Optimizer, cfg: TrainConfig, train: Split,
                 val: Split, log: dict[str, Any], step: int, info: dict[str, Any], out: Path) -> None:
        self.model, self.opt, self.cfg, self.train_split, self.val = model, opt, cfg, train, val
        self.log, self.step, self.info = log, step, info
        self.last_path, self.best_path = out / "last.pt", out / "best.pt"
        self.steps_per_epoch = max(1, len(train) // cfg.batch_size)
        self.t_mark = time.perf_counter()
        self.bar: Any = None  # the tqdm bar, set before training
        self.window: list[float] = []  # the training losses since the last evaluation
        self.perm: torch.Tensor | None = None  # the epoch's order of the training samples
        self.perm_epoch = -1

    def train(self, deadline: float | None, stop_at_step: int | None) -> bool:
        """Train until ``cfg.steps`` (evaluating and checkpointing every ``eval_every``), the deadline or
        ``stop_at_step``; whether it stopped early."""
        cfg = self.cfg
        while self.step < cfg.steps:
            if (deadline is not None and time.perf_counter() > deadline) or (
                    stop_at_step is not None and self.step >= stop_at_step):
                return True
            self.train_step()
            self.bar.update(1)
            if self.step % cfg.eval_every == 0 or self.step == cfg.steps:
                self.log["train_curve"].append({"step": self.step, "loss": float(np.mean(self.window))})
                self.window = []
                metrics = evaluate(self.model, self.val, cfg.loss)
                if metrics:
                    self.log["val_curve"].append(dict(metrics, step=self.step))
                    self.bar.set_postfix(val_mae_logE=f"{metrics['mae_log10_E']:.3f}",
                                         val_mae_nu=f"{metrics['mae_nu']:.4f}")
                self.checkpoint(metrics)
        return False

    def train_step(self) -> None:
        """One optimiser step on the step's batch: the epoch's seeded order, the scheduled learning rate, seeded
        colour permutations and mirroring (its loss goes to ``window``)."""
        cfg, step = self.cfg, self.step
        epoch, pos = divmod(step, self.steps_per_epoch)
        if epoch != self.perm_epoch:
            self.perm = torch.randperm(len(self.train_split),
                                       generator=torch.Generator().manual_seed(cfg.seed + 1000 * epoch))
            self.perm_epoch = epoch
        idx = self.perm[pos * cfg.batch_size:(pos + 1) * cfg.batch_size]
        self.model.train()
        for g in self.opt.param_groups:
            g["lr"] = cfg.lr * lr_factor(step, cfg.steps, cfg.warmup, cfg.final_lr_fraction)
        orders = None
        if cfg.colour_permute:
            orders = random_channel_orders(len(idx), torch.Generator().manual_seed(cfg.seed * 1_000_003 + step + 7919))
        video, targets = self.train_split.batch(idx, orders)  # (B, T, 3, R, R)
        mask = None
        if cfg.mirror:
            flip = torch.rand(len(idx), generator=torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)) < 0.5
            video = torch.where(flip.view(-1, 1, 1, 1, 1), video.flip(-1), video)
            mask = ~flip
        loss, _ = predictor_loss(self.model, self.model(video), targets, cfg.loss, last_layer_mask=mask)
        self.window.append(optimiser_step(self.opt, loss, "train-predictor", step))
        self.step += 1

    def validate_when_stopped(self) -> None:
        """Close the curves at the step where training stopped early, evaluate and checkpoint."""
        if self.window:
            self.log["train_curve"].append({"step": self.step, "loss": float(np.mean(self.window))})
        metrics = evaluate(self.model, self.val, self.cfg.loss)
        if metrics:
            self.log["val_curve"].append(dict(metrics, step=self.step))
        self.checkpoint(metrics)

    def checkpoint(self, metrics: dict) -> None:
        """Add the seconds since the last checkpoint to the log, save ``best.pt`` if ``metrics`` improve on the best
        loss, and ``last.pt`` (weights, optimiser, step and log) always."""
        log = self.log
        log["seconds_training"] = log.get("seconds_training", 0.0) + (time.perf_counter() - self.t_mark)
        self.t_mark = time.perf_counter()
        if metrics and (log["best"] is None or metrics["loss"] < log["best"]["loss"]):
            log["best"] = dict(metrics, step=self.step)
            save_predictor(self.model, self.best_path, metrics=dict(metrics, step=self.step), **self.info)
        payload = checkpoint_payload(self.model, metrics=metrics, **self.info)
        payload.update(optimizer=self.opt.state_dict(), step=self.step, log=log)
        save_torch_atomic(payload, self.last_path)


def _ship_predictor(run: _TrainingRun, baselines: dict[str, float], complete: bool) -> None:
    """Write ``OUT/predictor.pt`` (half precision): the best checkpoint, or the trained model when a complete run
    had no validation split (so no best); nothing otherwise."""
    train, val, info = run.train_split, run.val, run.info
    out = run.best_path.parent
    if run.best_path.is_file():
        best_model = load_predictor(run.best_path)
        shipped = dict(run.log["best"] or {}, **{f"baseline_{k}": v for k, v in baselines.items()},
                       val_samples=len(val), train_samples=len(train))
        save_predictor(best_model, out / "predictor.pt", half=True, metrics=shipped, **info)
    elif complete and len(val) == 0:  # no validation split, so no best: the trained model is the one to ship
        # (before, a run whose --val-fraction held out no object printed "done: OUT/predictor.pt" and wrote none;
        # found by vid2sim bench fuzz --kills)
        save_predictor(run.model, out / "predictor.pt", half=True,
                       metrics={f"baseline_{k}": v for k, v in baselines.items()} | {"val_samples": 0,
                                                                                     "train_samples": len(train)},
                       **info)
