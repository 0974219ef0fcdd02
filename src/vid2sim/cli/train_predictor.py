"""``vid2sim train-predictor``: train the Stage I predictor on a ``make-training-data`` folder (docs/predictor.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.predictor.model import LossWeights, PredictorConfig
from vid2sim.predictor.train import TrainConfig, train_predictor


def run(args: argparse.Namespace) -> int:

    if not (Path(args.data) / "index.json").is_file():
        raise UserError(f"{args.data}: no index.json; expected a training-data folder (vid2sim make-training-data)")
    if args.pretrained is not None and not Path(args.pretrained).exists() and "/" not in args.pretrained:
        raise UserError(f"--pretrained {args.pretrained}: not a folder nor a model id (owner/name) of the local "
                        "Hugging Face cache")
    set_threads(args.threads)



    try:
        frames = int(json.loads((Path(args.data) / "index.json").read_text())["config"]["frames"])
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{args.data}/index.json: no readable config.frames ({exc})") from exc
    try:
        model = PredictorConfig(image_size=args.image_size, num_frames=frames, patch_size=args.patch_size,
                                tubelet_size=args.tubelet_size, hidden_size=args.width, num_layers=args.layers,
                                num_heads=args.heads, intermediate_size=4 * args.width, pretrained=args.pretrained,
                                framing=args.framing, seed=args.seed)
        cfg = TrainConfig(model=model, steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                          val_fraction=args.val_fraction, eval_every=args.eval_every, max_minutes=args.max_minutes,
                          seed=args.seed, mirror=not args.no_mirror, colour_permute=args.colour_permute,
                          pretrain_steps=args.pretrain_steps,
                          pretrain_mask_ratio=args.pretrain_mask_ratio,
                          pretrain_batch_size=args.pretrain_batch_size,
                          loss=LossWeights(*args.loss_weights))
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    try:
        record = train_predictor(args.data, args.out, cfg, progress=not args.quiet)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    best, base = record["best"] or {}, record["baselines_constant_mean"]
    state = (
        "done" if record["complete"] else f"stopped at step {record['steps_done']} of {args.steps} (rerun to resume)"
    )
    print(f"{state}: {args.out}/predictor.pt; validation ({record['data']['val_samples']} samples) best step "
          f"{best.get('step')}: MAE log10 E {best.get('mae_log10_E', float('nan')):.3f} (constant mean "
          f"{base.get('mae_log10_E', float('nan')):.3f}), MAE nu {best.get('mae_nu', float('nan')):.4f} "
          f"(constant mean {base.get('mae_nu', float('nan')):.4f})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``train-predictor`` to the ``vid2sim`` command."""
    p = sub.add_parser("train-predictor", help="train the Stage I predictor (VideoMAE; E, nu and the skinning "
                       "field's last layer from a front-view video) on a make-training-data folder",
                       description="Train the Stage I predictor on DATA into the folder OUT: OUT/predictor.pt (the "
                       "best validation checkpoint, float16), best.pt, last.pt and train_log.json. Rerun with the "
                       "same OUT and settings to resume. Details: docs/predictor.md.")
    p.add_argument("data", help="training-data folder (vid2sim make-training-data)")
    p.add_argument("out", help="output folder (created; an existing one with last.pt is resumed)")
    p.add_argument("--steps", type=int, default=4000, help="optimiser steps (default 4000)")
    p.add_argument("--batch-size", type=int, default=8, help="samples per step (default 8)")
    p.add_argument("--lr", type=float, default=3e-4, help="Adam learning rate, cosine-decayed (default 3e-4; "
                   "about 1e-5 to fine-tune a pre-trained backbone)")
    p.add_argument("--val-fraction", type=float, default=0.1, help="share of objects held out (default 0.1)")
    p.add_argument("--eval-every", type=int, default=200, help="steps between validations/checkpoints (default 200)")
    p.add_argument("--max-minutes", type=float, default=None, help="stop after this wall time (rerun resumes)")
    p.add_argument("--image-size", type=int, default=64, help="model input side (default 64; the data's is resized)")
    p.add_argument("--framing", choices=("object", "full"), default="object",
                   help="what of each frame the model sees: a square around the object's motion (default) or the "
                        "whole frame")
    p.add_argument("--colour-permute", action="store_true",
                   help="permute each training video's RGB channels at random (the light is white: every label is "
                        "kept; default off)")
    p.add_argument("--no-mirror", action="store_true",
                   help="no left-right mirroring of training videos (default: each mirrored with probability 1/2; "
                        "E and nu keep their labels)")
    p.add_argument("--patch-size", type=int, default=16, help="patch side in pixels (default 16)")
    p.add_argument("--tubelet-size", type=int, default=2, help="frames per token (default 2)")
    p.add_argument("--width", type=int, default=192, help="transformer width (default 192; MLP 4x)")
    p.add_argument("--layers", type=int, default=4, help="transformer layers (default 4)")
    p.add_argument("--heads", type=int, default=3, help="attention heads (default 3)")
    p.add_argument("--pretrained", metavar="PATH_OR_ID", default=None,
                   help="start from a local VideoMAE checkpoint (folder or a model id in the Hugging Face cache; "
                   "never downloaded); --width/--layers/--heads are then the checkpoint's")
    p.add_argument("--pretrain-steps", type=int, default=0,
                   help="masked-autoencoder pre-training steps of the backbone on the training videos before the "
                        "supervised steps (VideoMAE's self-supervised objective; default 0: none)")
    p.add_argument("--pretrain-batch-size", type=int, default=16,
                   help="videos per pre-training step (default 16)")
    p.add_argument("--pretrain-mask-ratio", type=float, default=0.9,
                   help="share of patch positions hidden in pre-training (default 0.9, VideoMAE's)")
    p.add_argument("--loss-weights", type=float, nargs=3, default=(1.0, 100.0, 1.0), metavar=("E", "NU", "LAYER"),
                   help="weights of MSE(log10 E), MSE(nu) and the last layer's MSE in the loss (default 1 100 1, "
                        "the paper's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the initialisation and batch order (default 0)")
    add_threads_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
