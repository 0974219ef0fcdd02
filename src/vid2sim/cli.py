"""The ``vid2sim`` command. Thin: parses arguments and calls the layers.

Each subcommand is a ``_cmd_*`` function taking the parsed arguments and returning an exit code.
Heavy imports (torch, the layers) happen inside those functions so ``vid2sim --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

from vid2sim import __version__


class UserError(Exception):
    """An error caused by the user's input; printed as one clear line, without a traceback."""


def _cmd_bench(args: argparse.Namespace) -> int:
    from vid2sim.bench.speed import run_speed_benchmark

    result = run_speed_benchmark(device=args.device, sections=args.only, quick=args.quick)
    if args.json:
        print(json.dumps(result, indent=2, sort_keys=True))
    else:
        for key, value in sorted(result.items()):
            print(f"{key:32s} {value}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``vid2sim`` command (one subparser per subcommand)."""
    parser = argparse.ArgumentParser(
        prog="vid2sim",
        description="Simulation-ready assets from posed multi-view videos, and their mesh-free simulation.",
    )
    parser.add_argument("--version", action="version", version=f"vid2sim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    bench = sub.add_parser("bench", help="run benchmarks and print their figures")
    bench_sub = bench.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    speed = bench_sub.add_parser("speed", help="speed figures of the simulator and renderer")
    speed.add_argument("--json", action="store_true", help="print one JSON object")
    speed.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    speed.add_argument(
        "--only", nargs="*", default=None, metavar="SECTION",
        help="run only these sections (physics, render); default: all",
    )
    speed.add_argument("--quick", action="store_true", help="fewer repetitions (for smoke tests)")
    speed.set_defaults(func=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vid2sim`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        return func(args)
    except (UserError, ValueError, OSError) as exc:
        print(f"vid2sim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vid2sim {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
