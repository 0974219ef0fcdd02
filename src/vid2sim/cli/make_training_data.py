"""``vid2sim make-training-data``: Stage I training samples (docs/training-data.md)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from vid2sim.cli.common import UserError
from vid2sim.meshing.tetra import TetrahedralizationError
from vid2sim.physics import SimulationError
from vid2sim.predictor.data import TrainingDataConfig, make_training_data
from vid2sim.runtime.ray_runner import RayUnavailable
from vid2sim.synthetic.fem import FEMSolverError

# TrainingDataConfig fields and the flags that set them (for error messages)
_FLAGS = {"objects": "--objects", "draws_per_object": "--draws", "resolution": "--resolution", "frames": "--frames",
          "seed": "--seed", "fit_iterations": "--fit-iterations", "meshes": "--mesh", "template": "--template",
          "truth": "--truth", "views": "--views"}


def _config_error(exc: ValueError) -> UserError:
    message = str(exc)
    for name, flag in _FLAGS.items():
        message = re.sub(rf"TrainingDataConfig\.{name}\b", flag, message)
    return UserError(message)


def run(args: argparse.Namespace) -> int:

    if args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.ray_address is not None and not args.ray_address.strip():
        raise UserError("--ray-address must be 'local' or a Ray cluster address (HOST:PORT, auto, ray://...)")
    for m in args.mesh:
        if not Path(m).is_file():
            raise UserError(f"--mesh {m}: no such file")
    if args.template is not None and not Path(args.template).is_file():
        raise UserError(f"--template {args.template}: no such file")
    given = {"objects": args.objects, "draws_per_object": args.draws, "resolution": args.resolution,
             "frames": args.frames, "seed": args.seed, "meshes": tuple(args.mesh),
             "fit_iterations": args.fit_iterations, "template": args.template, "truth": args.truth,
             "views": args.views}
    try:
        config = TrainingDataConfig(**{k: v for k, v in given.items() if v is not None})
    except ValueError as exc:
        raise _config_error(exc) from exc

    try:
        index = make_training_data(config, args.out, workers=args.workers, threads=args.threads,
                                   ray_address=args.ray_address, progress=not args.quiet)
    except (FileExistsError, FileNotFoundError, ValueError, RayUnavailable) as exc:  # checked before any work
        raise UserError(str(exc)) from exc
    except (SimulationError, FEMSolverError, TetrahedralizationError) as exc:
        raise UserError(f"{exc} (finished shards and FEM draws are kept; index.json's last_run.failed lists the "
                        "objects that failed; run the command again to resume)") from exc
    run = index["last_run"]
    line = f"wrote {args.out}: {index['shards_written']} objects, {index['samples']} samples"
    if run["samples_made"]:
        per = run["seconds_per_sample"]
        line += (f"; made {run['samples_made']} samples in {run['wall_seconds']:.1f} s = "
                 f"{run['samples_per_second']:.3g} samples/s (median {run['median_sample_seconds']:.3g} s a sample, "
                 f"{run['median_sample_cpu_seconds']:.3g} s of CPU; "
                 "per sample, summed over workers: " + ", ".join(f"{k} {v:.2f} s" for k, v in per.items()) + ")")
    else:
        line += " (all shards were already there)"
    print(line)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "make-training-data",
        help="Stage I training data: procedural objects dropped with random E, nu, damping, pose and velocity, "
             "simulated by the FEM ground truth (or the reduced simulator), rendered from the front camera and "
             "its ring (shards + index.json; resumable)",
        description="Write Stage I training samples into OUT: one .npz shard per object (videos of D draws, "
                    "log10 E, nu, the 650 last-layer numbers) and index.json. Deterministic from --seed (FEM: given "
                    "each object's tet mesh, which fTetWild does not reproduce; it is kept); run again to resume. "
                    "Format: docs/training-data.md.")
    p.add_argument("out", help="dataset folder (created; an existing one is resumed)")
    p.add_argument("--objects", type=int, required=True, help="procedural objects (one shard each)")
    p.add_argument("--truth", choices=["fem", "reduced"], default="fem",
                   help="what simulates the drops: fem (default; the benchmark's ground truth: quadratic tets, "
                        "converged in time) or reduced (the reduced simulator: far cheaper, not the truth)")
    p.add_argument("--views", type=int, default=None,
                   help="cameras per draw: the front camera and views-1 more on its ring (default: fem 4, "
                        "reduced 1)")
    p.add_argument("--draws", type=int, default=None, help="material/drop draws per object (default: fem 2, reduced 4)")
    p.add_argument("--resolution", type=int, default=None, help="video side in pixels (default 224; 64 on a CPU)")
    p.add_argument("--frames", type=int, default=None, help="video frames (default 16)")
    p.add_argument("--seed", type=int, default=None, help="dataset seed (default 0)")
    p.add_argument("--mesh", action="append", default=[], metavar="FILE",
                   help="a user mesh (OBJ/GLB/GLTF/PLY) added as one more object; repeatable")
    p.add_argument("--fit-iterations", type=int, default=None,
                   help="Adam iterations of the last-layer fit after its closed-form start (default 0)")
    p.add_argument("--template", default=None, metavar="FILE",
                   help="template skinning network (default: the one shipped with vid2sim)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes side by side (default: all local cores)")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="run the objects as Ray tasks: 'local' (a private Ray instance) or a cluster address; "
                        "needs Ray (pip install \"vid2sim[ray]\") and OUT on a file system every node sees")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads per worker (default 1; shards are reproducible for a given value)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
