"""``vid2sim fit-gaussians``: 3D Gaussians fitted to one frame of a scene folder."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

import torch
from PIL import Image

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.runtime.device import resolve_device
from vid2sim.scene.folder import SceneFormatError, load_scene, move_into_place
from vid2sim.splats.fitting import FitConfig, fit_gaussians
from vid2sim.splats.losses import psnr
from vid2sim.splats.ply import save_ply
from vid2sim.splats.preview import comparison_image
from vid2sim.splats.render import render_gaussians


def _parse_views(text: str | None, num_views: int) -> list[int]:
    """``"0,6"`` → [0, 6]: sorted distinct view indices in 0..num_views − 1, leaving at least one view."""
    if not text:
        return []
    try:
        views = sorted({int(part) for part in text.split(",")})
    except ValueError:
        raise UserError(f"--test-views must be comma-separated view indices, e.g. 0,6; got {text!r}") from None
    bad = [v for v in views if not 0 <= v < num_views]
    if bad:
        raise UserError(f"--test-views {bad} outside the scene's views 0..{num_views - 1}")
    if len(views) == num_views:
        raise UserError(f"--test-views holds out all {num_views} views; leave at least one to fit")
    return views


def run(args: argparse.Namespace) -> int:



    set_threads(args.threads)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if out.exists() and not (out / "gaussians.ply").exists() and any(out.iterdir()):
        raise UserError(f"{out} is a non-empty folder without gaussians.ply; refusing to replace it")
    given = {"iterations": args.iterations, "sh_degree": args.sh_degree, "views_per_step": args.views_per_step}
    try:
        config = FitConfig(seed=args.seed, **{k: v for k, v in given.items() if v is not None})
    except ValueError as exc:  # name the flag typed, not the config field
        message = str(exc)
        for name in given:
            message = message.replace(f"FitConfig.{name} ", f"--{name.replace('_', '-')} ")
        raise UserError(message) from exc
    device = resolve_device(args.device)
    try:
        scene = load_scene(args.scene, progress=not args.quiet)
    except SceneFormatError as exc:
        raise UserError(str(exc)) from exc
    T = scene.images.shape[1]
    if not 0 <= args.frame < T:
        raise UserError(f"--frame {args.frame} is outside the scene's frames 0..{T - 1}")
    V = len(scene.cameras)
    test = _parse_views(args.test_views, V)
    train = [v for v in range(V) if v not in test]
    images = scene.images[:, args.frame].to(device)
    masks = scene.masks[:, args.frame].to(device)
    start = time.perf_counter()
    fitted = fit_gaussians(images[train], masks[train], [scene.cameras[v] for v in train], config,
                           progress=not args.quiet)
    seconds = time.perf_counter() - start
    cams = [c.to(device) for c in scene.cameras]
    with torch.no_grad():
        rgb = render_gaussians(fitted, cams, background=config.background, backend=config.backend).rgb

    def scores(views: list[int]) -> tuple[float | None, list[float]]:
        if not views:
            return None, []
        return (round(psnr(rgb[views], images[views]), 3),
                [round(psnr(rgb[v : v + 1], images[v : v + 1]), 3) for v in views])

    (train_psnr, train_per_view), (test_psnr, test_per_view) = scores(train), scores(test)
    report = {
        "scene": str(Path(args.scene).resolve()), "frame": args.frame, "device": str(device),
        "gaussians": fitted.num, "seconds": round(seconds, 2),
        "train_views": train, "psnr_db": train_psnr, "psnr_db_per_view": train_per_view,
        "test_views": test, "psnr_db_test": test_psnr, "psnr_db_test_per_view": test_per_view,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.writing-", dir=out.parent))
    try:
        save_ply(fitted, tmp / "gaussians.ply")
        (tmp / "fit_config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
        (tmp / "fit_report.json").write_text(json.dumps(report, indent=2) + "\n")
        labels = [f"view {v}{' (held out)' if v in test else ''}: {psnr(rgb[v : v + 1], images[v : v + 1]):.1f} dB"
                  for v in range(V)]
        Image.fromarray(comparison_image(images, rgb, labels)).save(tmp / "comparison.png")
        move_into_place(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    held_out = f", {test_psnr:.2f} dB on the {len(test)} held-out views" if test else ""
    print(f"wrote {out / 'gaussians.ply'}: {fitted.num} Gaussians, {train_psnr:.2f} dB on the "
          f"{len(train)} training views of frame {args.frame}{held_out}, {seconds:.1f} s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fit-gaussians`` subcommand."""
    fit = sub.add_parser(
        "fit-gaussians", help="fit 3D Gaussians to one frame of a scene folder (all views, or all but --test-views)"
    )
    fit.add_argument("scene", help="scene folder (scene.json + transforms.json)")
    fit.add_argument("out", help="output folder: gaussians.ply (3DGS layout), comparison.png (target | render | "
                     "error per view), fit_config.json, fit_report.json")
    fit.add_argument("--frame", type=int, default=0, help="frame index to fit (default 0)")
    fit.add_argument("--iterations", type=int, default=None, help="optimisation steps (default: FitConfig's, 1000)")
    fit.add_argument("--sh-degree", type=int, default=None, choices=range(4),
                     help="spherical-harmonics degree (default: FitConfig's, 3)")
    fit.add_argument("--views-per-step", type=int, default=None, help="views rendered per step (default: all)")
    fit.add_argument("--test-views", default=None, metavar="I,J,...",
                     help="views held out of the fit (initialisation included) and scored separately")
    fit.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    fit.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    fit.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    add_threads_option(fit)
    fit.add_argument("--quiet", action="store_true", help="no progress output")
    fit.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

