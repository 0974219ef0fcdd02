"""``vid2sim bench suite``: reconstruct + evaluate every scene of a make-benchmark suite."""

from __future__ import annotations

import argparse
import os
import sys

from vid2sim.apps.bench.suite import SUITE_JSON, SuiteConfig, format_table, run_suite
from vid2sim.cli.common import (
    UserError,
    add_scenes_option,
    add_suite_run_options,
)
from vid2sim.cli.reconstruct_options import add_reconstruct_options, reconstruct_config
from vid2sim.runtime.ray_runner import RayUnavailable


def run(args: argparse.Namespace) -> int:
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    config = SuiteConfig(preset=args.preset, reconstruct=reconstruct_config(args), threads=args.threads)
    try:
        result = run_suite(args.suite, args.out, config, progress=not args.quiet, ray_address=args.ray_address,
                           rerun_changed=args.rerun_changed, scenes=args.scenes)
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    print(format_table(result))
    path = os.path.join(args.out, SUITE_JSON)
    failed = [r["name"] for r in result["scenes"] if r["status"] != "ok"]
    if failed:
        print(f"vid2sim bench suite: {len(failed)} of {len(result['scenes'])} scenes failed ({', '.join(failed)}); "
              f"the others finished. Wrote {path}; each failed scene's traceback is in OUT/NAME/error.txt; run "
              "the command again to retry only the failed scenes.", file=sys.stderr)
        return 1
    print(f"wrote {path}; report: {os.path.join(args.out, 'report', 'index.html')}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench suite`` subcommand."""
    bsuite = sub.add_parser("suite", help="reconstruct + evaluate every scene of a make-benchmark suite; "
                                  "per-scene table and means, suite.json (resumable)")
    bsuite.add_argument("suite", help="benchmark folder written by make-benchmark (index.json + scenes)")
    bsuite.add_argument("out", help="results folder: NAME/asset, NAME/evaluation.json per scene, suite.json "
                        "(resumed if it holds a suite_config.json)")
    add_reconstruct_options(bsuite)
    add_suite_run_options(bsuite)
    add_scenes_option(bsuite, "reconstruct and evaluate")
    bsuite.add_argument("--rerun-changed", action="store_true",
                        help="a scene's interrupted reconstruction whose settings differ from a stage on (a release "
                             "that added a setting, say) keeps the stages before it and runs the rest again, instead "
                             "of failing")
    bsuite.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
