"""``vid2sim import-capture``: a real capture (videos, calibration, clean plates) in, a scene folder out."""

from __future__ import annotations

import argparse

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.scene.capture import CaptureImportConfig, import_capture, parse_axis
from vid2sim.scene.capture.metric import MetricConfig


def _frames(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B (frame indices, B exclusive), got {text!r}") from None
    return a, b


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame indices, got {text!r}") from None


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    if args.gravity is not None and not args.gravity > 0:
        raise UserError(f"--gravity must be a positive number (m/s^2), got {args.gravity}")
    config = CaptureImportConfig(
        calibration=args.calibration, fps=args.fps, frames=args.frames,
        gravity_axis=None if args.gravity_axis is None else parse_axis(args.gravity_axis),
        scale=args.scale, floor=args.floor, observed_views=args.observed_views, held_out_views=args.held_out_views,
        held_out_frames=args.held_out_frames, colour_reference=args.colour_reference, layout=args.layout,
        downscale=args.downscale, every=args.every,
        threads=args.threads, metric=MetricConfig(gravity=args.gravity if args.gravity is not None else 9.81))
    if args.floor is not None and args.gravity_axis is None:
        raise UserError("--floor is a height along the up axis: give --gravity-axis with it")
    out = import_capture(args.capture, args.scene, config, overwrite=args.overwrite, progress=not args.quiet)
    print(f"wrote {out} (checks and estimates: {out}/capture_report.json)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``import-capture`` subcommand."""
    p = sub.add_parser("import-capture", help="a real capture (videos, calibration, clean plates) in, a scene "
                       "folder out: undistortion, masks, metric scale, gravity and floor, colour (docs/capture.md)")
    p.add_argument("capture", help="capture folder: videos/<cam>.mp4 or frames/<cam>/, background/<cam>.png, "
                   "colmap/ or transforms.json (docs/capture.md)")
    p.add_argument("scene", help="scene folder to write (appears complete or not at all)")
    p.add_argument("--calibration", choices=["colmap", "transforms"], default="colmap",
                   help="which calibration to use when both are there (default colmap)")
    p.add_argument("--fps", type=float, default=None, help="frame rate, when the videos and capture.json do not say")
    p.add_argument("--frames", type=_frames, default=None, metavar="A:B",
                   help="keep frames A..B-1 in the scene (scale and gravity are measured on all frames)")
    p.add_argument("--every", type=int, default=1, metavar="N",
                   help="keep every N-th of those frames (film at 60 fps, keep 20: the free fall is measured on all)")
    p.add_argument("--gravity-axis", default=None, metavar="AXIS",
                   help="the direction gravity points in the calibration's frame: x, -y, +z, ... or gx,gy,gz "
                        "(default: measured from the object's free fall)")
    p.add_argument("--scale", type=float, default=None, metavar="M",
                   help="metres per calibration unit (default: measured from the free fall)")
    p.add_argument("--floor", type=float, default=None, metavar="H",
                   help="the floor's height in calibration units along up (= -gravity axis); needs --gravity-axis")
    p.add_argument("--gravity", type=float, default=None, metavar="G",
                   help="|g| in m/s^2 used to turn the free fall into metres (default 9.81)")
    p.add_argument("--observed-views", type=_names, default=None, metavar="CAMS",
                   help="cameras used for fitting, by name or index, comma-separated (default: all but held-out)")
    p.add_argument("--held-out-views", type=_names, default=None, metavar="CAMS",
                   help="cameras kept for novel-view evaluation, by name or index, comma-separated")
    p.add_argument("--held-out-frames", type=_ints, default=None, metavar="T",
                   help="scene frames kept for future prediction, comma-separated (default: after the 16th)")
    p.add_argument("--colour-reference", default=None, metavar="CAM",
                   help="the camera whose colours the others are matched to (default: the first observed)")
    p.add_argument("--downscale", type=int, default=1, metavar="K",
                   help="keep the frames reduced K times (block averages; masks are found at full size first)")
    p.add_argument("--layout", choices=["rgba", "rgb+mask", "video"], default="rgba", help="scene folder layout")
    p.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_threads_option(p)
    p.set_defaults(func=run, lock_output="scene")  # one writer per SCENE (runtime.locks)
