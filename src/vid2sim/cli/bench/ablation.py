"""``vid2sim bench ablation``: the paper's Stage I ablation on a make-benchmark suite."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from vid2sim.apps.bench.ablation import (
    ABLATION_JSON,
    format_ablation_table,
    run_ablation,
)
from vid2sim.apps.bench.suite import SuiteConfig
from vid2sim.cli.common import (
    UserError,
    add_suite_run_options,
)
from vid2sim.cli.reconstruct_options import add_reconstruct_options, reconstruct_config
from vid2sim.reconstruct.config import Stage1Config
from vid2sim.runtime.ray_runner import RayUnavailable


def run(args: argparse.Namespace) -> int:

    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    base = reconstruct_config(args)  # its stage1 section is the variants' to set; --predictor is theirs
    config = SuiteConfig(preset=args.preset, reconstruct=dataclasses.replace(base, stage1=Stage1Config()),
                         threads=args.threads)
    try:
        result = run_ablation(args.suite, args.out, config, predictor=base.stage1.predictor, progress=not args.quiet,
                              ray_address=args.ray_address)
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    print(format_ablation_table(result))
    path = os.path.join(args.out, ABLATION_JSON)
    failed = [f"{name}/{r['name']}" for name, v in result["variants"].items() for r in v["scenes"]
              if r["status"] != "ok"]
    if failed:
        total = sum(len(v["scenes"]) for v in result["variants"].values())
        print(f"vid2sim bench ablation: {len(failed)} of {total} variant scenes failed ({', '.join(failed)}); the "
              f"others finished. Wrote {path}; each failed scene's traceback is in OUT/VARIANT/NAME/error.txt; run "
              "the command again to retry the failed scenes.", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench ablation`` subcommand."""
    babl = sub.add_parser("ablation", help="the paper's Stage I ablation on a make-benchmark suite: Stage I "
                                "alone, Stage I + II, Stage II from the prior; one table row each, ablation.json "
                                "(resumable)")
    babl.add_argument("suite", help="benchmark folder written by make-benchmark (index.json + scenes)")
    babl.add_argument("out", help="results folder: one bench-suite folder per variant (stage1_only, stage1_stage2, "
                      "stage2_prior) and ablation.json (resumed if it holds them)")
    add_reconstruct_options(babl)
    add_suite_run_options(babl)
    babl.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

