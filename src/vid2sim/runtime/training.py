"""The optimisation loop that vid2sim's data-free trainings share (the skinning field, the Neural Jacobian, the
Stage I template and its per-object last layer): Adam (or AdamW) with a cosine learning-rate schedule to 0, one
loss per iteration from a ``step`` function, a check that it stays finite, a progress bar.

**CUDA graphs.** A data-free iteration is a few hundred small kernels on a few thousand points: on a GPU it is
bound by launching them, not by running them (an H200 ran the skinning field's at 77 it/s). When the parameters
are on CUDA and the caller splits its step into the iteration's random ``inputs`` (device tensors of the same
shapes every iteration) and a ``step`` of those inputs that never waits for the device, :func:`optimise` runs the
first :data:`GRAPH_WARMUP` iterations eagerly, captures one whole iteration (loss, gradients, the optimiser's
update) in a CUDA graph and replays it for the others: one launch per iteration. The optimiser is then
``capturable`` (its step count and learning rate live on the device; the schedule's rate is written there before
each replay), and the losses are read back and checked every :data:`GRAPH_CHECK_EVERY` iterations instead of at
each: a loss that became NaN or infinite is still reported at the iteration it first did (the parameters are
then those at the end of its block, not the last finite ones an eager loop leaves).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor
from tqdm.auto import tqdm

#: Eager iterations before the capture (they make the optimiser's state and the libraries' workspaces).
GRAPH_WARMUP = 3
#: Iterations between two reads of the graph's losses (each read waits for the device).
GRAPH_CHECK_EVERY = 64

StepResult = tuple[Tensor, Mapping[str, Tensor | float]]


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
        cuda_graph: replay the iteration as a CUDA graph where it can be (parameters on CUDA, a step split into
            ``inputs`` and ``step``; the module docstring); False: always eager.
    """

    iterations: int
    lr: float
    optimizer: str = "adam"
    warmup: int | None = None
    foreach: bool | None = None
    cuda_graph: bool = True

    def factor(self, i: int) -> float:
        """The learning rate at step ``i`` as a fraction of ``lr`` (the closed form, with warm-up)."""
        n = max(1, self.iterations)
        warm = min(1.0, (i + 1) / max(1, self.warmup or 0))
        return warm * 0.5 * (1.0 + math.cos(math.pi * min(i, n) / n))

    def learning_rates(self) -> list[float]:
        """The learning rate of each of the ``iterations`` steps, as the eager loop's scheduler sets them."""
        probe = torch.zeros(1, requires_grad=True)
        opt = torch.optim.SGD([probe], lr=self.lr)
        sched = self._scheduler(opt)
        rates = []
        for _ in range(self.iterations):
            rates.append(float(opt.param_groups[0]["lr"]))
            opt.step()  # no gradient, no update: the scheduler's order as the loop's
            sched.step()
        return rates

    def _scheduler(self, opt: torch.optim.Optimizer) -> torch.optim.lr_scheduler.LRScheduler:
        if self.warmup is None:
            return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=self.iterations)
        return torch.optim.lr_scheduler.LambdaLR(opt, self.factor)


@dataclass
class Progress:
    """The progress bar of :func:`optimise`: its label, and how often its figures are refreshed."""

    desc: str
    show: bool = True
    every: int = 50
    figures: dict[str, float] = field(default_factory=dict)


def optimise(params: Sequence[Tensor], step: Callable[..., StepResult], schedule: Schedule, progress: Progress,
             what: str, inputs: Callable[[int], tuple[Tensor, ...]] | None = None) -> list[float]:
    """Minimise the loss of ``step`` over ``params`` for ``schedule.iterations`` steps; returns the loss per step.

    Args:
        params: the tensors to train (leaves that require gradients); the others ``step`` uses stay untouched
            (the gradients are taken with respect to these alone, and cleared on return).
        step: without ``inputs``, iteration ``i`` → (the scalar loss, named parts of it shown on the bar and in the
            error); with ``inputs``, ``step(*inputs(i))`` → the same, and then it must not wait for the device
            (no ``.item()``, ``bool(tensor)``, checks of values) and its parts must be tensors: it may be replayed
            as a CUDA graph (the module docstring).
        schedule: optimiser, learning rate and schedule (:class:`Schedule`).
        progress: the bar (:class:`Progress`).
        what: the training's name for error messages ("skinning training").
        inputs: iteration ``i`` → that iteration's random inputs, tensors on the parameters' device whose shapes
            and dtypes are the same at every iteration (asked for in order, once per iteration).
    Raises:
        FloatingPointError: the loss became NaN or infinite; the message names the iteration and the parts.
    """
    params = list(params)
    if schedule.iterations == 0:
        return []
    graphed = (inputs is not None and schedule.cuda_graph and params[0].is_cuda
               and schedule.iterations > GRAPH_WARMUP)
    call = step if inputs is None else (lambda i: step(*inputs(i)))
    loop = _GraphLoop(params, step, inputs, schedule, what) if graphed else _EagerLoop(params, call, schedule)
    bar = tqdm(total=schedule.iterations, desc=progress.desc, unit="it", disable=not progress.show)
    losses: list[float] = []
    try:
        while len(losses) < schedule.iterations:
            it = len(losses)
            values, parts = loop.run(it)
            for k, value in enumerate(values):
                if not math.isfinite(value):
                    detail = ", ".join(f"{name} {_part(v, k):.4g}" for name, v in parts.items())
                    raise FloatingPointError(f"{what}: the loss became {value} at iteration {it + k}"
                                             + (f" ({detail})" if detail else "") + "; try a smaller learning rate")
            losses.extend(values)
            bar.update(len(values))
            last = len(losses) - 1
            if progress.show and (last // progress.every > (it - 1) // progress.every or
                                  last == schedule.iterations - 1):
                bar.set_postfix({"loss": f"{values[-1]:.4g}",
                                 **{k: f"{_part(v, len(values) - 1):.3g}" for k, v in parts.items()}})
    finally:
        bar.close()
        loop.close()
    return losses


def _part(value: Tensor | float | list[float], k: int) -> float:
    """The ``k``-th iteration's value of a part that :meth:`_EagerLoop.run` (one iteration: a tensor or a number) or
    :meth:`_GraphLoop.run` (a block: a list) returned."""
    return value[k] if isinstance(value, list) else float(torch.as_tensor(value).detach())


def _make_optimizer(params: list[Tensor], schedule: Schedule, capturable: bool) -> torch.optim.Optimizer:
    kind = {"adam": torch.optim.Adam, "adamw": torch.optim.AdamW}[schedule.optimizer]
    if not capturable:
        return kind(params, lr=schedule.lr, foreach=schedule.foreach)
    lr = torch.tensor(schedule.lr, dtype=torch.float32, device=params[0].device)
    return kind(params, lr=lr, foreach=schedule.foreach, capturable=True)


def _update(params: list[Tensor], loss: Tensor, opt: torch.optim.Optimizer) -> None:
    """One optimiser step on the gradients of ``loss`` with respect to ``params`` alone."""
    grads = torch.autograd.grad(loss, params)
    for p, g in zip(params, grads):
        p.grad = g
    opt.step()


def _detached(parts: Mapping[str, Tensor | float]) -> dict[str, Tensor | float]:
    return {k: v.detach() if isinstance(v, Tensor) else v for k, v in parts.items()}


class _EagerLoop:
    """One iteration at a time: the loss read back (the iteration's one synchronisation) before the update."""

    def __init__(self, params: list[Tensor], call: Callable[[int], StepResult], schedule: Schedule) -> None:
        self.params, self.call = params, call
        self.opt = _make_optimizer(params, schedule, capturable=False)
        self.sched = schedule._scheduler(self.opt)

    def run(self, it: int) -> tuple[list[float], Mapping[str, Tensor | float]]:
        """Iteration ``it``: ([its loss], its parts); no update when the loss is not finite."""
        loss, parts = self.call(it)
        parts = _detached(parts)
        value = float(loss.detach())
        if not math.isfinite(value):  # before the update: the parameters stay those of the last finite loss
            return [value], parts
        _update(self.params, loss, self.opt)
        self.sched.step()
        return [value], parts

    def close(self) -> None:
        for p in self.params:
            p.grad = None


class _GraphLoop:
    """:data:`GRAPH_WARMUP` eager iterations, then one captured iteration replayed, the losses read every
    :data:`GRAPH_CHECK_EVERY` iterations (the module docstring)."""

    def __init__(self, params: list[Tensor], step: Callable[..., StepResult],
                 inputs: Callable[[int], tuple[Tensor, ...]], schedule: Schedule, what: str) -> None:
        self.params, self.step, self.inputs, self.schedule = params, step, inputs, schedule
        self.device = params[0].device
        self.opt = _make_optimizer(params, schedule, capturable=True)
        self.lr = self.opt.param_groups[0]["lr"]
        self.rates = schedule.learning_rates()
        self.graph: torch.cuda.CUDAGraph | None = None
        self.static: tuple[Tensor, ...] = ()
        self.record: Tensor | None = None  # the captured iteration's [loss, *parts]
        self.names: list[str] = []
        self.what = what
        self.eager_only = False

    def _eager(self, it: int, drawn: tuple[Tensor, ...]) -> tuple[list[float], Mapping[str, Tensor | float]]:
        self.lr.fill_(self.rates[it])
        loss, parts = self.step(*drawn)
        parts = _detached(parts)  # nothing of this iteration's autograd graph outlives it (its streams' nodes)
        value = float(loss.detach())
        if math.isfinite(value):
            _update(self.params, loss, self.opt)
        return [value], parts

    def _capture(self, drawn: tuple[Tensor, ...]) -> None:
        """Record one iteration on the static copies of ``drawn`` (the capture runs nothing: the iteration whose
        inputs these are is replayed next, like the others)."""
        self.static = tuple(t.clone() for t in drawn)
        for p in self.params:
            p.grad = None
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            loss, parts = self.step(*self.static)
            self.names = list(parts)
            self.record = torch.stack([loss.detach(), *(v.detach().to(loss) for v in parts.values())])
            _update(self.params, loss, self.opt)
        self.graph = graph

    def run(self, it: int) -> tuple[list[float], Mapping[str, Tensor | float | list[float]]]:
        """Iteration ``it`` alone (a warm-up), or the block of up to :data:`GRAPH_CHECK_EVERY` from it, up to the
        first non-finite loss: (their losses, their parts)."""
        if it < GRAPH_WARMUP:  # on a side stream, as torch.cuda.graphs asks of the iterations before a capture
            drawn = self.inputs(it)
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):
                out = self._eager(it, drawn)
            torch.cuda.current_stream(self.device).wait_stream(side)
            return out
        if self.eager_only:
            return self._eager(it, self.inputs(it))
        n = min(GRAPH_CHECK_EVERY, self.schedule.iterations - it)
        book = None
        for k in range(n):
            drawn = self.inputs(it + k)
            if self.graph is None:
                try:
                    self._capture(drawn)
                except RuntimeError as error:  # an operation CUDA cannot capture: said, and the training goes on
                    warnings.warn(f"{self.what}: the iteration could not be captured as a CUDA graph ({error}); "
                                  "it runs eagerly (slower, the same results)", RuntimeWarning, stacklevel=3)
                    self.eager_only = True
                    for p in self.params:
                        p.grad = None
                    return self._eager(it, drawn)
            else:
                for buf, new in zip(self.static, drawn):
                    buf.copy_(new)
            if book is None:
                book = torch.empty(n, self.record.shape[0], dtype=self.record.dtype, device=self.device)
            self.lr.fill_(self.rates[it + k])
            self.graph.replay()
            book[k].copy_(self.record)
        rows = book.cpu().tolist()  # the block's one synchronisation
        values = [r[0] for r in rows]
        bad = next((k for k, v in enumerate(values) if not math.isfinite(v)), None)
        keep = len(values) if bad is None else bad + 1
        parts = {name: [r[j + 1] for r in rows[:keep]] for j, name in enumerate(self.names)}
        return values[:keep], parts

    def close(self) -> None:
        self.graph = None
        for p in self.params:
            p.grad = None
