"""``vid2sim ensemble-predictors OUT CHECKPOINT...``: trained Stage I checkpoints combined into one ensemble."""

from __future__ import annotations

import argparse
from pathlib import Path

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.predictor.ensemble import save_ensemble
from vid2sim.predictor.train import read_checkpoint


def run(args: argparse.Namespace) -> int:

    for c in args.checkpoints:
        if not Path(c).is_file():
            raise UserError(f"{c}: no such predictor checkpoint")
    if args.val_data is not None and not (Path(args.val_data) / "index.json").is_file():
        raise UserError(f"--val-data {args.val_data}: no index.json; expected a training-data folder")
    set_threads(args.threads)

    try:
        out = save_ensemble(args.checkpoints, args.out, mirror=not args.no_mirror, val_data=args.val_data)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    met = read_checkpoint(out)["metrics"]
    size = out.stat().st_size / 2 ** 20
    print(f"wrote {out} ({len(args.checkpoints)} networks, mirroring {'off' if args.no_mirror else 'on'}, "
          f"{size:.1f} MB)")
    if met:
        print(f"  validation ({met['samples']} samples): MAE log10 E {met['mae_log10_E']:.3f} (constant mean "
              f"{met['baseline_mae_log10_E']:.3f}), MAE nu {met['mae_nu']:.4f} (constant mean "
              f"{met['baseline_mae_nu']:.4f})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``ensemble-predictors`` subcommand."""
    e = sub.add_parser("ensemble-predictors", help="combine trained Stage I checkpoints into one ensemble checkpoint "
                       "(their mean, with test-time mirroring)",
                       description="Write OUT: one checkpoint that answers the mean of the CHECKPOINTs (networks "
                       "trained with other --seed), each also run on the left-right mirrored video unless "
                       "--no-mirror. reconstruct --predictor and eval-predictor read it like a single network. "
                       "Details: docs/predictor.md.")
    e.add_argument("out", help="the ensemble checkpoint to write")
    e.add_argument("checkpoints", nargs="+", help="train-predictor's predictor.pt files")
    e.add_argument("--no-mirror", action="store_true", help="no test-time mirroring (default: E and nu are "
                   "averaged over each video and its mirror image)")
    e.add_argument("--val-data", metavar="DATA", default=None,
                   help="the members' training-data folder: score the ensemble on their common validation split "
                        "and store the figures in OUT")
    add_threads_option(e)
    e.set_defaults(func=run)
