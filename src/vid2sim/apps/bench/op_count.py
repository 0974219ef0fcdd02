"""Counting the aten operators a callable dispatches (``vid2sim bench speed``: ``joint_iter_ops``,
``skinning_iter_ops``).

Definition. :func:`count_aten_ops` runs the callable once under :class:`torch.profiler.profile` (CPU activity,
which records the operator calls of every thread, the autograd engine's backward thread included) and counts
the **top-level aten operators**: profiler events named ``aten::…`` that are not nested inside another
``aten::`` event of the same thread. A composite operator (``aten::linear``, ``aten::einsum``) counts once,
not once per operator it calls; a view (``aten::reshape``, ``aten::select``) counts like any other call.
On a GPU each such call costs a host-side dispatch (a few µs) and launches at most a few kernels, so the count
is a device-independent measure of launch-bound work. The count is deterministic for a deterministic callable
(unlike a timing), so tests may bound it.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import torch


@dataclass
class OpCount:
    """What :func:`count_aten_ops` found.

    Attributes:
        top_level: aten operators not nested in another aten operator (the figure reported).
        total: every aten operator event, nested ones included.
        by_name: top-level count per operator name, most frequent first.
    """

    top_level: int
    total: int
    by_name: Counter = field(default_factory=Counter)


def _events(fn: Callable[[], object]) -> list:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return list(prof.events())


def _nested_in_aten(event) -> bool:
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith("aten::"):
            return True
        parent = parent.cpu_parent
    return False


def count_aten_ops(fn: Callable[[], object]) -> OpCount:
    """Run ``fn()`` once under the profiler and count the aten operators it dispatched (see the module
    docstring for the definition)."""
    aten = [e for e in _events(fn) if e.name.startswith("aten::")]
    top = [e for e in aten if not _nested_in_aten(e)]
    return OpCount(len(top), len(aten), Counter(e.name for e in top))
