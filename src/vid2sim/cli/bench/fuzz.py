"""``vid2sim bench fuzz``: the reliability and security campaign (:mod:`vid2sim.apps.bench.fuzz`,
docs/reliability.md); prints one JSON object of figures."""

from __future__ import annotations

import argparse
import json

from vid2sim.apps.bench.fuzz import FuzzConfig, run_fuzz
from vid2sim.cli.common import UserError
from vid2sim.runtime.locks import output_lock


def run(args: argparse.Namespace) -> int:

    chosen = {"physics": args.physics, "inputs": args.inputs, "kills": args.kills}
    values = {k: v for k, v in chosen.items() if v is not None}
    if args.hostile:
        values["hostile"] = True
    common = {"seed": args.seed, "workers": args.workers, "threads": args.threads, "browser": not args.no_browser}
    if args.timeout is not None:
        common["timeout"] = args.timeout
    if args.quick:
        config = FuzzConfig.quick_run(**values, **common)
    elif not values:
        raise UserError("nothing to run: give --physics N, --inputs N, --hostile, --kills N, or --quick")
    else:
        config = FuzzConfig(**values, **common)
    if args.out is not None:
        with output_lock(args.out, "bench fuzz"):
            figures = run_fuzz(config, args.out, progress=args.progress)
    else:
        figures = run_fuzz(config, None, progress=args.progress)
    print(json.dumps(figures, indent=2, sort_keys=True))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench fuzz`` subcommand."""
    p = sub.add_parser("fuzz", help="reliability campaign: random simulations, corrupted and hostile inputs, kills",
                       description="Random simulations, corrupted and hostile inputs, and killed-and-resumed "
                                   "commands; prints one JSON object of figures (docs/reliability.md).")
    p.add_argument("--physics", type=int, default=None, metavar="N", help="N random simulations")
    p.add_argument("--inputs", type=int, default=None, metavar="N", help="N corrupted-input cases")
    p.add_argument("--hostile", action="store_true", help="the hostile-file checks")
    p.add_argument("--kills", type=int, default=None, metavar="N", help="N kill-and-resume cases")
    p.add_argument("--quick", action="store_true", help="a few cases of every section (the test suite's run)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="keep every case's record in DIR/<section>.jsonl; the same command resumes from them")
    p.add_argument("--seed", type=int, default=0, help="seed of the first case (case i: seed + i)")
    p.add_argument("--workers", type=int, default=1, help="processes running physics cases side by side")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    p.add_argument("--timeout", type=float, default=None, help="seconds an input case may take (default 60)")
    p.add_argument("--no-browser", action="store_true", help="skip the headless-Chromium report check")
    p.add_argument("--progress", action="store_true", help="a line per finished case on stdout")
    p.set_defaults(func=run)
