"""What every subcommand module of :mod:`vid2sim.cli` shares: the user-error type and the threads option."""

from __future__ import annotations

import argparse

import torch

from vid2sim.runtime.errors import InputError


class UserError(InputError):
    """A command-line option or argument the command cannot use; printed as one clear line, without a traceback."""


def add_threads_option(p: argparse.ArgumentParser) -> None:
    """``--threads N``: torch's intra-op threads (on a shared machine, other processes' threads can slow torch
    tenfold; pass the cores you really have)."""
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: torch's; on a shared machine give the cores that are free)")


def set_threads(threads: int | None) -> None:
    """Apply ``--threads`` (None keeps torch's default); raises :class:`UserError` for a value below 1."""

    if threads is not None:
        if threads < 1:
            raise UserError(f"--threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)


def add_device_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--device DEVICE``: the torch device that runs ``what`` (default: cuda if available, else cpu)."""
    p.add_argument("--device", default=None,
                   help=f"torch device of {what} (default: cuda if available, else cpu)")


def scene_slice(text: str) -> slice:
    """argparse type of ``--scenes A:B``: the suite's scenes A to B - 1 (either end may be left out: ``8:``,
    ``:4``; one index ``5`` is ``5:6``), as a slice of ``range(n)``."""
    parts = text.split(":")
    try:
        if len(parts) == 1:
            start = int(parts[0])
            return slice(start, start + 1)
        if len(parts) == 2:
            return slice(int(parts[0]) if parts[0].strip() else None, int(parts[1]) if parts[1].strip() else None)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected A:B (scene indices, B excluded: 8:12, 8:, :4) or one index, got "
                                     f"{text!r}")


def add_scenes_option(p: argparse.ArgumentParser, verb: str) -> None:
    """--scenes A:B of the commands that work on a shard of a suite."""
    p.add_argument("--scenes", type=scene_slice, default=None, metavar="A:B",
                   help=f"{verb} only the suite's scenes A to B-1 (8:12, 8:, :4, or one index), a shard: other runs, "
                        "here or on other machines, do the rest into the same folder (default: all)")


def add_suite_run_options(p: argparse.ArgumentParser) -> None:
    """--ray-address, --threads and --quiet of the commands that run a benchmark suite."""
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="run each scene as a Ray task: 'local' starts Ray on this machine, or a cluster address "
                        "(auto, HOST:6379); OUT must be a path every node sees (needs pip install \"vid2sim[ray]\")")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads per scene, and CPUs each Ray task reserves (default: torch's; 1 per Ray task)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
