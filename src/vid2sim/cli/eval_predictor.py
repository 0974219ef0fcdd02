"""``vid2sim eval-predictor CHECKPOINT DATA``: a Stage I checkpoint scored on a training-data folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.predictor.train import evaluate_predictor


def run(args: argparse.Namespace) -> int:

    if not Path(args.checkpoint).is_file():
        raise UserError(f"{args.checkpoint}: no such predictor checkpoint")
    if not (Path(args.data) / "index.json").is_file():
        raise UserError(f"{args.data}: no index.json; expected a training-data folder (vid2sim make-training-data)")
    set_threads(args.threads)

    try:
        r = evaluate_predictor(args.checkpoint, args.data, args.split)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    print(f"{r['samples']} videos of {args.data} ({args.split}), framing {r['framing']}:")
    print(f"  MAE log10 E  {r['mae_log10_E']:.3f}   (constant mean {r['baseline_mae_log10_E']:.3f})")
    print(f"  MAE nu       {r['mae_nu']:.4f}  (constant mean {r['baseline_mae_nu']:.4f})")
    print(f"  last layer   {r['mse_last_layer_std']:.3f}   (constant mean {r['baseline_mse_last_layer_std']:.3f}; "
          "standardised MSE)")
    print("  log10 E by true value:  " + "  ".join(f"[{b['lo']:.2f},{b['hi']:.2f}) {b['mae']:.2f}{b['bias']:+.2f}"
                                                   for b in r["by_log10_E"]) + "  (MAE, bias)")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2) + "\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``eval-predictor`` subcommand."""
    q = sub.add_parser("eval-predictor", help="score a Stage I checkpoint on a training-data folder (a held-out "
                       "test set) against the constant-mean baseline",
                       description="Score the predictor CHECKPOINT on the videos of DATA (make a test set with "
                       "`vid2sim make-training-data` and another --seed): MAE of log10 E and nu and the last "
                       "layer's standardised MSE, beside the constant guess of the checkpoint's training means.")
    q.add_argument("checkpoint", help="predictor checkpoint (train-predictor's predictor.pt)")
    q.add_argument("data", help="training-data folder to score on")
    q.add_argument("--split", choices=("all", "val", "train"), default="all",
                   help="which objects of DATA (default all: a separate test set)")
    q.add_argument("--json", metavar="FILE", default=None, help="also write the figures to FILE")
    add_threads_option(q)
    q.set_defaults(func=run)
