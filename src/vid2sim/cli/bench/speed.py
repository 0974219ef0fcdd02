"""``vid2sim bench speed``: speed figures of the simulator and renderer (:mod:`vid2sim.apps.bench.speed`)."""

from __future__ import annotations

import argparse
import json

from vid2sim.apps.bench.speed import run_speed_benchmark
from vid2sim.cli.common import add_threads_option, set_threads


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    result = run_speed_benchmark(device=args.device, sections=args.only, quick=args.quick)
    if args.json:
        print(json.dumps(result, indent=2, sort_keys=True))
    else:
        for key, value in sorted(result.items()):
            print(f"{key:32s} {value}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench speed`` subcommand."""
    speed = sub.add_parser("speed", help="speed figures of the simulator and renderer")
    speed.add_argument("--json", action="store_true", help="print one JSON object")
    speed.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    speed.add_argument(
        "--only", nargs="*", default=None, metavar="SECTION",
        help="run only these sections (physics, training, render, joint, modes, predictor); default: all",
    )
    speed.add_argument("--quick", action="store_true",
                       help="fewer repetitions, and the joint section at 1 500 Gaussians and 64² (a smoke test: the "
                            "figures come out, they measure little)")
    add_threads_option(speed)
    speed.set_defaults(func=run)
