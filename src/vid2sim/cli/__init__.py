"""The ``vid2sim`` command: dispatches to one module per subcommand.

Each subcommand is a module of this package with ``register(subparsers)`` (its parser, whose default ``func`` is
the module's ``run(args) -> exit code``). Only the module of the command being run is imported: the layers import
torch (about 2 s), and ``vid2sim --help`` should answer at once — that is why the table below names modules
instead of importing them.

Commands that write an output folder for long declare ``lock_output="out"`` (the argument naming it) in their
parser's defaults; :func:`main` then holds :func:`vid2sim.runtime.locks.output_lock` on it while the command runs,
so a second process on the same output stops at once with one line naming the first.

Errors: vid2sim's input errors (:class:`~vid2sim.runtime.errors.InputError`:
a file, folder, option or setting that is not what vid2sim can use; the commands' own
:class:`~vid2sim.cli.common.UserError` is one) and operating-system errors (a missing file, a full
disk) print one line and exit with 2. Anything else is a bug in vid2sim: a line asking for a report, then Python's
traceback
(exit code 1).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Callable, Sequence

from vid2sim import __version__
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.locks import output_lock

#: subcommand → (module of this package, one-line help for ``vid2sim --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("demo", "the whole pipeline once on a synthetic drop: scene, reconstruction, evaluation, a new "
             "simulation, HTML report"),
    "reconstruct": ("reconstruct", "reconstruct a scene folder into a simulation-ready asset (Gaussians, skinning "
                    "field, material)"),
    "evaluate": ("evaluate", "score an asset on a scene: PSNR/SSIM on observed, future and novel views, material, "
                 "Chamfer and centre-of-mass errors"),
    "simulate": ("simulate", "simulate an asset in a new situation (material, floor, obstacles, cameras)"),
    "report": ("report", "write a self-contained HTML report of an asset"),
    "export": ("export", "export an asset or Gaussians to glTF/GLB, PLY sequences or a simulation rig"),
    "fit-gaussians": ("fit_gaussians", "fit 3D Gaussians to one frame of a scene folder"),
    "make-scene": ("make_scene", "simulate (FEM) and render one synthetic scene folder"),
    "make-benchmark": ("make_benchmark", "a deterministic suite of synthetic scenes (E, nu sampled)"),
    "make-capture": ("make_capture", "the capture twin of a synthetic scene: what real cameras would have filmed"),
    "calibrate-capture": ("calibrate_capture", "calibrate a capture by structure from motion (COLMAP) on its "
                          "clean plates and photos"),
    "import-capture": ("import_capture", "a real capture (videos, calibration, clean plates) in, a scene folder out"),
    "make-training-data": ("make_training_data", "Stage I training samples (simulated, rendered drops)"),
    "train-predictor": ("train_predictor", "train the Stage I predictor"),
    "eval-predictor": ("eval_predictor", "score a Stage I checkpoint on a training-data folder"),
    "ensemble-predictors": ("ensemble_predictors", "combine trained Stage I checkpoints into one ensemble"),
    "bench": ("bench", "run benchmarks and print their figures (speed, identify, suite, ablation, ...)"),
}


def _top_parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    parser = argparse.ArgumentParser(
        prog="vid2sim",
        description="Simulation-ready assets from posed multi-view videos, and their mesh-free simulation.",
    )
    parser.add_argument("--version", action="version", version=f"vid2sim {__version__}")
    return parser, parser.add_subparsers(dest="command", metavar="COMMAND")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of ``vid2sim``: every subcommand's full parser, or only ``command``'s (the others then
    appear by name and help alone, so that ``vid2sim --help`` imports no layer)."""
    parser, sub = _top_parser()
    for name, (module, help_text) in COMMANDS.items():
        if command is None or name == command:
            importlib.import_module(f"{__name__}.{module}").register(sub)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand named in ``argv`` (its first word that is not an option), or None."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vid2sim`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _command_of(argv)
    parser = build_parser(command) if command is not None else build_parser("")
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        lock = getattr(args, "lock_output", None)  # long commands hold their output's lock (vid2sim.runtime.locks)
        if lock is None:
            return func(args)
        with output_lock(getattr(args, lock), " ".join(["vid2sim", *argv])[:300]):
            return func(args)
    except (InputError, OSError) as exc:  # UserError is an InputError
        print(f"vid2sim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vid2sim {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception:  # a bug: say so, and let Python show where (exit code 1)
        print(f"vid2sim {args.command}: internal error, a bug in vid2sim {__version__}; please report it with the "
              "traceback below", file=sys.stderr)
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
