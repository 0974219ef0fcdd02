"""``vid2sim make-scene``: simulate (FEM) and render one synthetic scene folder."""

from __future__ import annotations

import argparse

from vid2sim.cli.common import UserError, set_threads
from vid2sim.cli.scene_options import (
    add_scene_options,
    generation_errors,
    scene_config_error,
    scene_overrides,
)
from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    try:
        config = SyntheticSceneConfig.preset(args.preset, seed=args.seed, mesh=args.mesh, tet_mesh=args.tet_mesh,
                                             **scene_overrides(args))
    except ValueError as exc:
        raise scene_config_error(exc) from exc
    try:
        path = make_scene(config, args.out, overwrite=args.overwrite, progress=not args.quiet, workers=args.workers)
    except generation_errors() as exc:
        raise UserError(f"{exc} (nothing was written)") from exc
    print(f"wrote {path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``make-scene`` subcommand."""
    scene = sub.add_parser("make-scene", help="simulate (FEM) and render one synthetic scene folder")
    scene.add_argument("out", help="scene folder to create")
    scene.add_argument("--mesh", default=None, help="a watertight textured mesh (OBJ/GLB/GLTF/PLY) instead of a "
                       "procedural shape")
    scene.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the procedural shape and texture (unless --mesh) and of the initial pose (default 0)",
    )
    scene.add_argument("--tet-mesh", default=None, help="reuse the tet mesh of an earlier scene (its fem_result.npz) "
                       "instead of fTetWild, which is not reproducible; same settings then give the same scene")
    scene.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    add_scene_options(scene, material_options=True)
    scene.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

