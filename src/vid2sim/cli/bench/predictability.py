"""``vid2sim bench predictability``: how far a synthetic scene's frames can be predicted at all."""

from __future__ import annotations

import argparse
import os

from vid2sim.apps.bench.predictability import (
    PREDICTABILITY_JSON,
    format_summary,
    predictability,
)
from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.cli.scene_options import generation_errors


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    try:
        report = predictability(args.scene, args.out, height_offset=args.height_offset, progress=not args.quiet,
                                workers=args.workers)
    except generation_errors() as exc:
        raise UserError(f"{exc} (the twin was not written)") from exc
    print(format_summary(report))
    print(f"wrote {os.path.join(args.out, PREDICTABILITY_JSON)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench predictability`` subcommand."""
    pred = sub.add_parser("predictability", help="a synthetic scene's truth simulated again from a start "
                                "1 mm higher and scored like an asset: how far its frames can be predicted at all")
    pred.add_argument("scene", help="synthetic scene folder (make-scene / make-benchmark)")
    pred.add_argument("out", help="results folder: twin/ (a scene folder, reused) and predictability.json")
    pred.add_argument("--height-offset", type=float, default=1e-3, metavar="M",
                      help="how much higher the twin starts, in metres (default 0.001)")
    pred.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                      help="processes for the FEM's first pair of time resolutions (default: min(2, CPU count))")
    add_threads_option(pred)
    pred.add_argument("--quiet", action="store_true", help="no progress bars")
    pred.set_defaults(func=run)

