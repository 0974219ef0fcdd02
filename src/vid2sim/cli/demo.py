"""``vid2sim demo [OUT]``: a synthetic drop in, a simulation-ready asset, its scores, a simulation of it in a
new situation and an HTML report out (:mod:`vid2sim.apps.demo`)."""

from __future__ import annotations

import argparse
import math
import time

from vid2sim.apps.demo import DemoConfig, run_demo
from vid2sim.cli.common import UserError, add_device_option, add_threads_option, set_threads
from vid2sim.runtime.device import resolve_device


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    device = resolve_device(args.device)  # a bad --device fails before any work
    try:
        config = DemoConfig(size=args.size, seed=args.seed)
    except ValueError as exc:
        raise UserError(str(exc).replace("DemoConfig.size", "--size")) from exc
    start = time.perf_counter()
    try:
        result = run_demo(args.out, config, progress=not args.quiet, device=device)
    except FileExistsError as exc:
        raise UserError(str(exc)) from exc
    minutes = (time.perf_counter() - start) / 60.0
    e = result.evaluation
    lines = [
        "",
        f"vid2sim demo finished in {minutes:.1f} min (this run; {sum(result.seconds.values()) / 60:.1f} min of steps "
        "in all)",
        f"  Young's modulus E: true {result.true_E:.3g} Pa, recovered {result.found_E:.3g} Pa "
        f"(log10 error {abs(math.log10(result.found_E / result.true_E)):.2f})",
        f"  Poisson's ratio nu: true {result.true_nu:.3f}, recovered {result.found_nu:.3f}",
    ]
    for key, name in (("dynamic", "observed frames"), ("future", "future frames"), ("novel_views", "held-out views")):
        if e.get(key):
            lines.append(f"  PSNR on {name}: {e[key]['psnr']:.1f} dB")
    lines += [
        f"  asset:      {result.asset}  (load it with vid2sim.asset.folder.load_asset)",
        f"  simulation: {result.simulation}  (videos/, one 3DGS PLY per frame in ply/)",
        f"  report:     {result.report / 'index.html'}  <- open it in a browser",
    ]
    if args.size == "tiny":
        lines.append("  (--size tiny checks the installation; its numbers mean nothing)")
    print("\n".join(lines))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` subcommand."""
    p = sub.add_parser("demo", help="the whole pipeline once on a synthetic drop (about 6 minutes on 2 CPU cores): "
                       "scene, reconstruction, evaluation, a new simulation, HTML report")
    p.add_argument("out", nargs="?", default="vid2sim-demo",
                   help="output folder (default ./vid2sim-demo; running again resumes after the last finished step)")
    p.add_argument("--size", choices=["small", "tiny"], default="small",
                   help="small: the real demo (6 views, 128x128, the small reconstruction preset); tiny: toy sizes "
                        "in about a minute, to check an installation")
    p.add_argument("--seed", type=int, default=0, help="seed of the object, its texture and its drop (default 0)")
    add_device_option(p, "the reconstruction, evaluation, simulation and report")
    add_threads_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
