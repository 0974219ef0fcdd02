"""``vid2sim bench table``: the table of a ``bench suite`` results folder so far, while it runs or after."""

from __future__ import annotations

import argparse

from vid2sim.apps.bench.suite import format_table, suite_so_far


def run(args: argparse.Namespace) -> int:
    print(format_table(suite_so_far(args.out)))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench table`` subcommand (read-only: it takes no lock, so it runs beside the suite itself)."""
    p = sub.add_parser("table", help="print the table of a bench suite results folder as it stands: the finished "
                       "scenes and their means, the failed and pending ones named (read-only; also while the suite "
                       "runs)")
    p.add_argument("out", help="results folder of vid2sim bench suite (it holds suite_config.json)")
    p.set_defaults(func=run)
