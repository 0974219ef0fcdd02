"""``vid2sim calibrate-capture``: COLMAP (pycolmap) on a capture's clean plates and photos, written to
``capture/colmap/``."""

from __future__ import annotations

import argparse

from vid2sim.cli.common import UserError
from vid2sim.scene.capture.colmap import SUPPORTED_MODELS
from vid2sim.scene.capture.sfm import SfmConfig, calibrate_capture


def run(args: argparse.Namespace) -> int:

    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    try:
        config = SfmConfig(camera_model=args.camera_model, max_features=args.max_features, threads=args.threads)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    report = calibrate_capture(args.capture, config, overwrite=args.overwrite, progress=not args.quiet)
    print(f"wrote {args.capture}/colmap: {len(report.cameras)} cameras registered ({report.photos_registered} of "
          f"{report.photos} photos linked them), {report.points} points, reprojection error "
          f"{report.mean_reprojection_error_px:.2f} px, {report.seconds:.0f} s; import it with vid2sim import-capture")
    if report.mapping != "default":
        print(f"mapping: {report.mapping}")
    for w in report.warnings:
        print(f"warning: {w}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``calibrate-capture`` subcommand."""
    p = sub.add_parser("calibrate-capture", help="calibrate a capture by structure from motion (COLMAP through "
                       "pycolmap) on its clean plates and photos/: writes capture/colmap/ (docs/capture.md)")
    p.add_argument("capture", help="capture folder with background/<cam>.png for every camera, and optionally "
                   "photos/ of the empty scene that link cameras far apart")
    p.add_argument("--camera-model", choices=SUPPORTED_MODELS, default="OPENCV",
                   help="COLMAP camera model, one camera per image (default OPENCV)")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per image (default 8192)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing colmap/ folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--threads", type=int, default=None, help="COLMAP's threads (default: all cores)")
    p.set_defaults(func=run, lock_output="capture")  # one writer per CAPTURE (runtime.locks)
