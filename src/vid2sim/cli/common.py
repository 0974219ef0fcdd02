"""What every subcommand module of :mod:`vid2sim.cli` shares: the user-error type and the threads option."""

from __future__ import annotations

import argparse


class UserError(Exception):
    """An error caused by the user's input; printed as one clear line, without a traceback."""


def add_threads_option(p: argparse.ArgumentParser) -> None:
    """``--threads N``: torch's intra-op threads (on a shared machine, other processes' threads can slow torch
    tenfold; pass the cores you really have)."""
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: torch's; on a shared machine give the cores that are free)")


def set_threads(threads: int | None) -> None:
    """Apply ``--threads`` (None keeps torch's default); raises :class:`UserError` for a value below 1."""
    import torch

    if threads is not None:
        if threads < 1:
            raise UserError(f"--threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
