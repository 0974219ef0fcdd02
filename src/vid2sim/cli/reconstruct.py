"""``vid2sim reconstruct SCENE OUT``: a scene folder in, a simulation-ready asset out."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.cli.reconstruct_options import add_reconstruct_options, reconstruct_config
from vid2sim.cli.report import write_asset_report
from vid2sim.reconstruct.pipeline import STAGES, reconstruct
from vid2sim.reconstruct.rollouts import spare_threads
from vid2sim.reconstruct.runner import StageSnapshots
from vid2sim.runtime.device import resolve_device


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    device = resolve_device(args.device)  # a bad --device fails before any work
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if args.share_stages and Path(args.share_stages).exists() and not Path(args.share_stages).is_dir():
        raise UserError(f"--share-stages {args.share_stages}: exists and is not a folder (the folder of stage "
                        "snapshots)")
    config = reconstruct_config(args)
    # every stage but the last: its output is the asset itself
    snapshots = StageSnapshots(Path(args.share_stages), STAGES[:-1]) if args.share_stages else None
    if args.restart and args.rerun_changed:
        raise UserError("--restart discards every finished stage and --rerun-changed keeps those whose settings "
                        "agree: give one of them")
    # the joint and continuation stages' rollouts also run on the threads beyond the first, in worker processes
    path = reconstruct(args.scene, out, config, progress=not args.quiet, restart=args.restart, device=device,
                       snapshots=snapshots, rerun_changed=args.rerun_changed, rollout_processes=spare_threads())
    material = json.loads((path / "material.json").read_text())
    lines = material_lines(material)
    print("\n".join([f"wrote {path}: {lines[0]}"] + lines[1:]))
    if not args.no_report:
        write_asset_report(path / "report", path, args.scene, quiet=args.quiet, device=device)
    return 0


def material_lines(material: dict) -> list[str]:
    """What ``reconstruct`` prints of a material.json: E and ν, then for log10 E and ν their interval and what the
    video says of them (the uncertainty's note: "found", "not identifiable from this video", left at its start when
    the fit moved nothing, or found at an end of the coarse search), where the record has them."""
    lines = [f"E = {material['E']:.4g} Pa (log10 E = {material['log10_E']:.3f}), nu = {material['nu']:.3f}"]
    unc = material.get("uncertainty") or {}
    level = unc.get("level")
    for key, label in (("log10_E", "log10 E"), ("nu", "nu")):
        entry = unc.get(key)
        if isinstance(entry, dict) and isinstance(entry.get("interval"), list) and level is not None:
            lo, hi = entry["interval"]
            lines.append(f"  {label}: {100 * level:.0f} % interval [{lo:.3f}, {hi:.3f}]; {entry.get('note', '')}")
    return lines


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``reconstruct`` subcommand."""
    rec = sub.add_parser("reconstruct", help="reconstruct a scene folder into a simulation-ready asset "
                         "(Gaussians, skinning field, material)",
                         usage="vid2sim reconstruct SCENE OUT [--preset {small,full}] [--config FILE] "
                               "[--SECTION.FIELD VALUE ...] [--device DEVICE] [--restart | --rerun-changed] "
                               "[--share-stages DIR] "
                               "[--overwrite] [--no-report] [--threads N] [--quiet]")
    rec.add_argument("scene", help="scene folder (scene.json + transforms.json)")
    rec.add_argument("out", help="asset folder to create (docs/asset-format.md)")
    add_reconstruct_options(rec)
    rec.add_argument("--device", default=None, help="torch device of the Gaussian fits, networks and joint "
                     "optimisation (default: cuda if available, else cpu; the asset is the same format either way)")
    rec.add_argument("--restart", action="store_true", help="discard an interrupted run's finished stages")
    rec.add_argument("--rerun-changed", action="store_true",
                     help="resume an interrupted run whose settings (or this release's) differ from a stage on: keep "
                          "the finished stages before it, run it and the later ones again (log.json 'rerun')")
    rec.add_argument("--share-stages", metavar="DIR", default=None,
                     help="keep a snapshot of each finished stage in DIR; a later reconstruction of the same scene "
                          "with the same DIR whose settings agree up to a stage starts after it (try other joint "
                          "settings without fitting the Gaussians again); log.json 'restored' says what it reused")
    rec.add_argument("--overwrite", action="store_true", help="replace an existing asset folder")
    rec.add_argument("--no-report", action="store_true", help="do not write the HTML report (OUT/report/index.html: "
                     "the asset against the scene, docs/report.md)")
    add_threads_option(rec)
    rec.add_argument("--quiet", action="store_true", help="no progress output")
    rec.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

