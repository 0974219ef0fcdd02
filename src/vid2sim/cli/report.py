"""``vid2sim report ASSET OUT [--scene SCENE]``: the self-contained HTML report of an asset (docs/report.md).

With ``--scene`` the asset is simulated and rendered in every camera of the scene and compared with its
frames (the metrics come from ``ASSET/evaluation.json`` when it was computed on that scene, otherwise the
evaluation runs); without, the asset's own drop is rendered in a ring of cameras.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vid2sim.apps.report import asset_report
from vid2sim.asset.folder import AssetFormatError
from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.report import ReportConfig, ReportInputError
from vid2sim.scene.validation import SceneFormatError


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    asset = Path(args.asset)
    if not asset.is_dir():
        raise UserError(f"ASSET {asset}: no such folder (an asset folder written by vid2sim reconstruct)")
    if args.scene is not None and not Path(args.scene).is_dir():
        raise UserError(f"--scene {args.scene}: no such folder (a scene folder with scene.json)")
    start = time.perf_counter()
    try:
        config = ReportConfig(video_format=args.video_format, crop=not args.full_frame)
        out = asset_report(args.out, asset, scene=args.scene, progress=not args.quiet, config=config)
    except (ReportInputError, AssetFormatError, SceneFormatError) as exc:
        raise UserError(str(exc)) from exc
    files = [p for p in out.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in files)
    print(
        f"wrote {out / 'index.html'} ({len(files)} files, {size / 1e6:.2f} MB) in {time.perf_counter() - start:.1f} s"
    )
    return 0


def write_asset_report(out, asset, scene, quiet: bool, evaluation=None, renders=None) -> None:
    """The HTML report of ``asset`` compared with ``scene`` (vid2sim.report), and one line saying where it is."""
    try:
        path = asset_report(out, asset, scene=scene, evaluation=evaluation, renders=renders, progress=not quiet)
    except ReportInputError as exc:
        raise UserError(f"the report could not be written: {exc}") from exc
    print(f"report: {path / 'index.html'}")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``report`` subcommand."""
    p = sub.add_parser("report", help="write a self-contained HTML report of an asset: ground truth | reconstruction "
                       "| error videos per view, metrics, material found vs truth, optimisation curves")
    p.add_argument("asset", help="asset folder written by vid2sim reconstruct")
    p.add_argument("out", help="report folder to write (index.html + media/; a previous report there is replaced)")
    p.add_argument("--scene", default=None, help="the scene folder to compare with (default: none, the asset's drop "
                   "in a ring of cameras)")
    p.add_argument("--video-format", choices=["webm", "webp"], default="webm",
                   help="webm: VP9 videos with synchronised controls (default); webp: animated images")
    p.add_argument("--full-frame", action="store_true", help="show whole frames instead of each view cropped to "
                   "the object's trajectory")
    add_threads_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)
