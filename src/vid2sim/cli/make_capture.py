"""``vid2sim make-capture``: the capture twin of a synthetic scene (what real cameras would have filmed)."""

from __future__ import annotations

import argparse

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.synthetic.capture import CaptureTwinConfig, make_capture_twin, read_truth


def run(args: argparse.Namespace) -> int:

    set_threads(args.threads)
    try:
        config = CaptureTwinConfig(seed=args.seed, resolution_scale=args.resolution_scale,
                                   frame_rate_scale=args.frame_rate_scale,
                                   lead_in_frames=args.lead_in, frames_format=args.format,
                                   colmap_format=args.colmap_format, write_transforms=not args.no_transforms,
                                   photos=args.photos)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    try:
        out = make_capture_twin(args.scene, args.out, config, overwrite=args.overwrite, progress=not args.quiet)
    except (FileNotFoundError, FileExistsError) as exc:
        raise UserError(str(exc)) from exc

    truth, _ = read_truth(out)
    lead = truth["lead_in_frames"]
    print(f"wrote {out}; import it with: vid2sim import-capture {out} SCENE --frames {lead}:{truth['frames']} "
          f"--every {truth['frame_step']} --downscale {truth['resolution_scale']} "
          f"--gravity {abs(truth['gravity_world'][2]):g}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``make-capture`` subcommand."""
    p = sub.add_parser("make-capture", help="the capture twin of a make-scene folder: room, shadow, lens distortion, "
                       "camera colours, noise, H.264, COLMAP/nerfstudio calibration in a random frame, ground truth")
    p.add_argument("scene", help="a folder written by make-scene (or make-benchmark)")
    p.add_argument("out", help="capture folder to write (ground truth in OUT/ground_truth/)")
    p.add_argument("--seed", type=int, default=0, help="seed of the twin's random choices (default 0)")
    p.add_argument("--resolution-scale", type=int, default=2, metavar="K",
                   help="film at K times the scene's resolution (import with --downscale K; default 2)")
    p.add_argument("--frame-rate-scale", type=int, default=3, metavar="M",
                   help="film M frames per scene frame (import with --every M; default 3: 60 fps for a 20 fps scene)")
    p.add_argument("--lead-in", type=int, default=8, metavar="N",
                   help="frames of free flight filmed before the scene's first frame (fewer when the object would "
                        "reach the floor or leave a view; default 8)")
    p.add_argument("--format", choices=["video", "frames"], default="video",
                   help="H.264 videos (default) or PNG frame folders + capture.json")
    p.add_argument("--colmap-format", choices=["text", "binary", "both", "none"], default="text",
                   help="COLMAP model files to write (default text)")
    p.add_argument("--photos", type=int, default=0, metavar="N",
                   help="also write N walkaround photos of the empty room to OUT/photos/, for structure from motion "
                   "(vid2sim calibrate-capture; default 0)")
    p.add_argument("--no-transforms", action="store_true", help="do not write nerfstudio's transforms.json")
    p.add_argument("--overwrite", action="store_true", help="replace an existing capture twin")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_threads_option(p)
    p.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
