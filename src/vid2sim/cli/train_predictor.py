"""``vid2sim train-predictor``: train the Stage I predictor on a ``make-training-data`` folder (docs/predictor.md)."""

from __future__ import annotations

import argparse

from vid2sim.cli.common import UserError, add_threads_option, set_threads


def _cmd_train_predictor(args: argparse.Namespace) -> int:
    from pathlib import Path

    if not (Path(args.data) / "index.json").is_file():
        raise UserError(f"{args.data}: no index.json; expected a training-data folder (vid2sim make-training-data)")
    if args.pretrained is not None and not Path(args.pretrained).exists() and "/" not in args.pretrained:
        raise UserError(f"--pretrained {args.pretrained}: not a folder nor a model id (owner/name) of the local "
                        "Hugging Face cache")
    set_threads(args.threads)

    import json

    from vid2sim.predictor.model import LossWeights, PredictorConfig
    from vid2sim.predictor.train import TrainConfig, train_predictor

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
    state = "done" if record["complete"] else f"stopped at step {record['steps_done']} of {args.steps} (rerun to resume)"
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
    p.set_defaults(func=_cmd_train_predictor)

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
    q.set_defaults(func=_cmd_eval_predictor)

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
    e.set_defaults(func=_cmd_ensemble_predictors)


def _cmd_ensemble_predictors(args: argparse.Namespace) -> int:
    from pathlib import Path

    for c in args.checkpoints:
        if not Path(c).is_file():
            raise UserError(f"{c}: no such predictor checkpoint")
    if args.val_data is not None and not (Path(args.val_data) / "index.json").is_file():
        raise UserError(f"--val-data {args.val_data}: no index.json; expected a training-data folder")
    set_threads(args.threads)
    from vid2sim.predictor.ensemble import save_ensemble
    from vid2sim.predictor.train import read_checkpoint

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


def _cmd_eval_predictor(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    if not Path(args.checkpoint).is_file():
        raise UserError(f"{args.checkpoint}: no such predictor checkpoint")
    if not (Path(args.data) / "index.json").is_file():
        raise UserError(f"{args.data}: no index.json; expected a training-data folder (vid2sim make-training-data)")
    set_threads(args.threads)
    from vid2sim.predictor.train import evaluate_predictor

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
