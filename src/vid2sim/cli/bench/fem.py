"""``vid2sim bench fem``: the FEM ground truth's time, exact-Hessian Newton against projecting."""

from __future__ import annotations

import argparse
import json

from vid2sim.apps.bench import fem_speed
from vid2sim.cli.common import UserError
from vid2sim.cli.scene_options import generation_errors


def run(args: argparse.Namespace) -> int:

    try:
        result = fem_speed.run(args.preset, seed=args.seed, frames=args.frames, progress=not args.quiet)
    except generation_errors() as exc:
        raise UserError(str(exc)) from exc
    print(json.dumps(result, indent=2, sort_keys=True))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench fem`` subcommand."""
    fem = sub.add_parser("fem", help="FEM ground-truth time: exact-Hessian Newton vs projecting every iteration")
    fem.add_argument("--preset", choices=["full", "small"], default="small", help="scene preset (default small)")
    fem.add_argument("--seed", type=int, default=0, help="object and pose seed (default 0)")
    fem.add_argument("--frames", type=int, default=None, help="frames to simulate (default: the preset's 24)")
    fem.add_argument("--quiet", action="store_true", help="no progress bars")
    fem.set_defaults(func=run)

