"""``vid2sim bench capture``: capture twins of a suite's scenes, imported, reconstructed and compared with the clean
scenes (docs/capture.md)."""

from __future__ import annotations

import argparse
import os

from vid2sim.apps.bench.capture import BENCH_JSON, CaptureBenchConfig, format_capture_table, run_capture_bench
from vid2sim.cli.common import UserError
from vid2sim.synthetic.capture import CaptureTwinConfig


def run(args: argparse.Namespace) -> int:

    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    if args.iterations is not None and args.iterations < 0:
        raise UserError(f"--iterations must be >= 0, got {args.iterations}")
    photos = args.photos if args.photos is not None else (36 if args.sfm else 0)
    try:
        config = CaptureBenchConfig(twin=CaptureTwinConfig(seed=args.seed, lead_in_frames=args.lead_in,
                                                           photos=photos, resolution_scale=args.resolution_scale),
                                    reconstruct=not args.import_only, preset=args.preset, iterations=args.iterations,
                                    threads=args.threads, clean_results=args.clean, sfm=args.sfm)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    result = run_capture_bench(args.suite, args.out, config, progress=not args.quiet)
    print(format_capture_table(result))
    print(f"wrote {os.path.join(args.out, BENCH_JSON)}")
    return 0 if all(r.get("status") == "ok" for r in result["scenes"]) else 1


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench capture`` subcommand."""
    p = sub.add_parser("capture", help="capture twins of a suite: import (mask IoU, scale, gravity, floor errors), "
                       "reconstruct, evaluate against the clean scenes; capture_bench.json (resumable)")
    p.add_argument("suite", help="benchmark folder written by make-benchmark")
    p.add_argument("out", help="results folder: NAME/capture, NAME/imported, NAME/import.json, NAME/asset, "
                   "NAME/evaluation.json, capture_bench.json")
    p.add_argument("--import-only", action="store_true", help="only the twins and their import's figures")
    p.add_argument("--clean", default=None, metavar="RESULTS",
                   help="a bench suite output folder whose NAME/evaluation.json are the clean runs (default: run them)")
    p.add_argument("--preset", choices=["small", "full"], default="small", help="reconstruct preset (default small)")
    p.add_argument("--iterations", type=int, default=None,
                   help="the joint optimisation's iterations (Gauss-Newton steps with the default method; default: "
                        "the preset's)")
    p.add_argument("--seed", type=int, default=0, help="first twin seed (scene i uses seed + i)")
    p.add_argument("--lead-in", type=int, default=8, help="free-flight frames filmed before each scene (default 8)")
    p.add_argument("--sfm", action="store_true",
                   help="calibrate each twin by structure from motion (vid2sim calibrate-capture: COLMAP on its plates "
                        "and walkaround photos; needs pycolmap) instead of the calibration the twin writes")
    p.add_argument("--resolution-scale", type=int, default=2, metavar="K",
                   help="the twins film at K times the scene's resolution (default 2; structure from motion wants "
                        "plates of 480 px or more)")
    p.add_argument("--photos", type=int, default=None, metavar="N",
                   help="walkaround photos of the empty room per twin (default 36 with --sfm, else 0)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)
