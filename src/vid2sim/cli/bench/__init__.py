"""``vid2sim bench KIND``: the benchmarks, one module per kind."""

from __future__ import annotations

import argparse
import importlib

#: the kinds, each a module of this package
KINDS = ("speed", "jacobian", "fem", "predictability", "identify", "suite", "table", "ablation", "fuzz", "capture")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench`` subcommand and its kinds."""
    bench = sub.add_parser("bench", help="run benchmarks and print their figures")
    kinds = bench.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    for kind in KINDS:
        importlib.import_module(f"{__name__}.{kind}").register(kinds)
