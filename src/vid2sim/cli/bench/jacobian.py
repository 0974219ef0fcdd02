"""``vid2sim bench jacobian``: the Neural Jacobian trained data-free, and its error."""

from __future__ import annotations

import argparse
import json

from vid2sim.apps.bench import jacobian_accuracy
from vid2sim.cli.common import add_threads_option, set_threads
from vid2sim.runtime.device import resolve_device


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    result = jacobian_accuracy.run(resolve_device(args.device), iterations=args.iterations, progress=not args.quiet,
                                   quick=args.quick)
    print(json.dumps(result, indent=2, sort_keys=True))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench jacobian`` subcommand."""
    jac = sub.add_parser("jacobian", help="train the Neural Jacobian data-free and report its error")
    jac.add_argument("--iterations", type=int, default=1000, help="training iterations (paper: 10000)")
    jac.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    jac.add_argument("--quick", action="store_true", help="a small object and a 3-frame rollout (smoke tests)")
    jac.add_argument("--quiet", action="store_true", help="no progress bar")
    add_threads_option(jac)
    jac.set_defaults(func=run)
