"""``vid2sim make-benchmark``: a deterministic suite of synthetic scenes."""

from __future__ import annotations

import argparse

from vid2sim.apps.bench.suite import suite_index
from vid2sim.cli.common import UserError, add_scenes_option, set_threads
from vid2sim.cli.scene_options import (
    add_scene_options,
    generation_errors,
    scene_config_error,
    scene_overrides,
)
from vid2sim.runtime.ray_runner import RayUnavailable
from vid2sim.synthetic.scenes import make_benchmark


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    if args.n < 1:
        raise UserError(f"--n must be >= 1 (the number of scenes), got {args.n}")
    scenes = None if args.scenes is None else list(range(args.n))[args.scenes]
    if scenes == []:
        raise UserError(f"--scenes selects none of the suite's {args.n} scenes (0 to {args.n - 1})")
    try:
        path = make_benchmark(args.n, args.out, preset=args.preset, seed=args.seed, progress=not args.quiet,
                              workers=args.workers, ray_address=args.ray_address, tets_from=args.tets_from,
                              scenes=scenes,
                              **scene_overrides(args))
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    except generation_errors() as exc:  # before ValueError, in case one of them is a ValueError
        raise UserError(f"{exc} (finished scenes are kept; run the command again to resume)") from exc
    except FileNotFoundError as exc:
        raise UserError(str(exc)) from exc
    except ValueError as exc:
        raise scene_config_error(exc) from exc
    if scenes is None:
        print(f"wrote {path} ({args.n} scene{'s' if args.n != 1 else ''}, index.json)")
    else:
        listed = len(suite_index(path)[1])
        print(f"wrote {path} (a shard of {len(scenes)} scene{'s' if len(scenes) != 1 else ''}; index.json lists "
              f"{listed} of the suite's {args.n})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``make-benchmark`` subcommand."""
    suite = sub.add_parser("make-benchmark", help="a deterministic suite of synthetic scenes (E, nu sampled)")
    suite.add_argument("out", help="benchmark folder (resumed if it holds an index.json)")
    suite.add_argument("--n", type=int, required=True, help="number of scenes")
    suite.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    suite.add_argument("--ray-address", default=None, metavar="ADDR",
                       help="make each scene as a Ray task: 'local' starts Ray on this machine, or a cluster "
                            "address (auto, HOST:6379); OUT must be a path every node sees (needs "
                            "pip install \"vid2sim[ray]\")")
    suite.add_argument("--tets-from", default=None, metavar="SUITE",
                       help="reuse the tet mesh of scene i of another suite for scene i (instead of fTetWild, which is "
                            "not reproducible): e.g. a --truth newton suite of the same drops on the same tets")
    add_scenes_option(suite, "make")
    add_scene_options(suite, material_options=False, default_element_order=2)
    suite.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

