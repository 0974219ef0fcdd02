"""The optimisation loop that vid2sim's data-free trainings share (the skinning field, the Neural Jacobian, the
Stage I template and its per-object last layer): Adam (or AdamW) with a cosine learning-rate schedule to 0, one
loss per iteration from a ``step`` function, a check that it stays finite, a progress bar.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor
from tqdm.auto import tqdm


@dataclass
class Schedule:
    """How :func:`optimise` steps.

    Attributes:
        iterations: optimiser steps.
        lr: the peak learning rate.
        optimizer: "adam" or "adamw" (PyTorch's defaults otherwise).
        warmup: None: PyTorch's cosine schedule (``CosineAnnealingLR``, computed recursively); a number: that many
            iterations of linear warm-up, then the cosine computed in closed form at each step (``LambdaLR``; 0: no
            warm-up). The two round differently, and each training keeps the one its results were made with.
        foreach: PyTorch's multi-tensor optimiser update (None: its default for the device).
    """

    iterations: int
    lr: float
    optimizer: str = "adam"
    warmup: int | None = None
    foreach: bool | None = None

    def factor(self, i: int) -> float:
        """The learning rate at step ``i`` as a fraction of ``lr`` (the closed form, with warm-up)."""
        n = max(1, self.iterations)
        warm = min(1.0, (i + 1) / max(1, self.warmup or 0))
        return warm * 0.5 * (1.0 + math.cos(math.pi * min(i, n) / n))


@dataclass
class Progress:
    """The progress bar of :func:`optimise`: its label, and how often its figures are refreshed."""

    desc: str
    show: bool = True
    every: int = 50
    figures: dict[str, float] = field(default_factory=dict)


def optimise(params: Sequence[Tensor], step: Callable[[int], tuple[Tensor, Mapping[str, Tensor | float]]],
             schedule: Schedule, progress: Progress, what: str) -> list[float]:
    """Minimise ``step(i)``'s loss over ``params`` for ``schedule.iterations`` steps; returns the loss per step.

    Args:
        params: the tensors to train (leaves that require gradients); the others ``step`` uses stay untouched
            (the gradients are taken with respect to these alone, and cleared on return).
        step: iteration ``i`` → (the scalar loss, named parts of it shown on the bar and in the error).
        schedule: optimiser, learning rate and schedule (:class:`Schedule`).
        progress: the bar (:class:`Progress`).
        what: the training's name for error messages ("skinning training").
    Raises:
        FloatingPointError: the loss became NaN or infinite; the message names the iteration and the parts.
    """
    params = list(params)
    losses: list[float] = []
    if schedule.iterations == 0:
        return losses
    kind = {"adam": torch.optim.Adam, "adamw": torch.optim.AdamW}[schedule.optimizer]
    opt = kind(params, lr=schedule.lr, foreach=schedule.foreach)
    if schedule.warmup is None:
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=schedule.iterations)
    else:
        sched = torch.optim.lr_scheduler.LambdaLR(opt, schedule.factor)
    bar = tqdm(range(schedule.iterations), desc=progress.desc, unit="it", disable=not progress.show)
    try:
        for it in bar:
            loss, parts = step(it)
            value = float(loss.detach())  # the iteration's one synchronisation
            if not math.isfinite(value):
                detail = ", ".join(f"{k} {float(v):.4g}" for k, v in parts.items())
                raise FloatingPointError(f"{what}: the loss became {value} at iteration {it}"
                                         + (f" ({detail})" if detail else "") + "; try a smaller learning rate")
            grads = torch.autograd.grad(loss, params)
            for p, g in zip(params, grads):
                p.grad = g
            opt.step()
            sched.step()
            losses.append(value)
            if progress.show and (it % progress.every == 0 or it == schedule.iterations - 1):
                bar.set_postfix({"loss": f"{value:.4g}", **{k: f"{float(torch.as_tensor(v).detach()):.3g}"
                                                                for k, v in parts.items()}})
    finally:
        for p in params:
            p.grad = None
    return losses
