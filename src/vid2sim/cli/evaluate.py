"""``vid2sim evaluate ASSET SCENE``: an asset scored on a scene."""

from __future__ import annotations

import argparse
from pathlib import Path

from vid2sim.cli.common import add_device_option, add_threads_option, set_threads
from vid2sim.cli.report import write_asset_report
from vid2sim.evaluate.scores import evaluate, write_evaluation
from vid2sim.report.inputs import GROUPS
from vid2sim.runtime.device import resolve_device


def run(args: argparse.Namespace) -> int:


    set_threads(args.threads)
    device = resolve_device(args.device)  # a bad --device fails before any work
    report, renders = evaluate(args.asset, args.scene, fovvdp=args.fovvdp, progress=not args.quiet,
                               return_renders=True, true_motion=args.true_motion, device=device)
    out = Path(args.out) if args.out else Path(args.asset) / "evaluation.json"
    write_evaluation(report, out)
    lines = []
    for key in GROUPS:
        if report[key]:
            lines.append(f"{key}: PSNR {report[key]['psnr']:.2f} dB, SSIM {report[key]['ssim']:.4f}")
        if key == "future" and report["future"].get("starts_from") == "continuation":
            single = report["future_from_start"]
            lines[-1] += " (from the state fitted to the last observed frames)"
            lines.append(f"future, one rollout from frame 0: PSNR {single['psnr']:.2f} dB, SSIM {single['ssim']:.4f}")
    for key, group in report.get("true_motion", {}).items():
        if isinstance(group, dict) and group:
            lines.append(f"{key} on the true motion: PSNR {group['psnr']:.2f} dB, SSIM {group['ssim']:.4f}")
    mat = report["material"]
    if "abs_error_log10_E" in mat:
        lines.append(f"|d log10 E| = {mat['abs_error_log10_E']:.3f}, |d nu| = {mat['abs_error_nu']:.3f}")
        start = mat.get("start")
        if start is not None and "abs_error_nu" in start:
            lines.append(f"  at the start ({start['source']}: E = {start['E']:.3e} Pa, nu = {start['nu']:.3f}): "
                         f"|d log10 E| = {start['abs_error_log10_E']:.3f}, |d nu| = {start['abs_error_nu']:.3f}")
    if "true_floor_friction" in mat:
        lines.append(f"floor friction {mat['fitted']['floor_friction']:.3f} (truth {mat['true_floor_friction']:.3f})")
    for key, what in (("chamfer", "Chamfer to the true surface"), ("centre_of_mass", "centre of mass off the truth's")):
        if key in report:
            future, first = report[key]["future_mean"], report[key].get("frame_0")
            lines.append(f"{what}: " + (f"{100 * first:.2f} cm at frame 0, " if first is not None else "")
                         + f"{100 * report[key]['observed_mean']:.2f} cm observed"
                         + (f", {100 * future:.2f} cm future" if future is not None else ""))
    turn = report.get("orientation")
    if turn is not None:
        future = turn["future_mean_deg"]
        lines.append(f"rotation off the truth's: {turn['observed_mean_deg']:.1f} deg observed"
                     + (f", {future:.1f} deg future" if future is not None else ""))
        for event in report["contacts"]["truth"]:
            com, rot = event["centre_of_mass_m"], event["rotation_deg"]
            first, last = event["frames"]
            lines.append(f"  contact at frames {first}-{last}: from frame {event['before']} to {event['after']} the "
                         f"centre of mass error {100 * com['before']:.2f} -> {100 * com['after']:.2f} cm, the rotation "
                         f"error {rot['before']:.1f} -> {rot['after']:.1f} deg")
    shape = report.get("geometry_stiffness")
    if shape is not None:
        lines.append(f"the solid's lowest elastic mode: {shape['lowest_frequency_ratio']:.3f} x the truth's "
                     f"(its shape alone implies log10 E {shape['implied_log10_E_offset']:+.3f})")
    solid = report.get("solid")
    if solid is not None:
        lines.append(f"the simulation solid: {solid['volume_ratio']:.3f} x the truth's volume, "
                     f"{100 * solid['outside_truth_fraction']:.1f} % of it outside the object; its lowest point "
                     f"{100 * solid['bottom_offset_m']:+.2f} cm, its highest {100 * solid['top_offset_m']:+.2f} cm "
                     "from the object's (frame 0, along gravity)")
    print("\n".join(lines + [f"wrote {out}"]))
    if not args.no_report:
        write_asset_report(Path(args.asset) / "report", args.asset, args.scene, quiet=args.quiet, evaluation=report,
                           renders=renders, device=device)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``evaluate`` subcommand."""
    ev = sub.add_parser("evaluate", help="score an asset on a scene: PSNR/SSIM on observed, future and novel "
                        "views, material, Chamfer and centre-of-mass errors against ground truth")
    ev.add_argument("asset", help="asset folder written by reconstruct")
    ev.add_argument("scene", help="scene folder")
    ev.add_argument("--out", default=None, help="JSON report (default ASSET/evaluation.json)")
    ev.add_argument("--fovvdp", action="store_true", help="also FoVVDP (needs the optional pyfvvdp, CC BY-NC)")
    ev.add_argument("--no-report", action="store_true", help="do not write the HTML report (ASSET/report/index.html)")
    ev.add_argument("--true-motion", action="store_true",
                    help="also score the asset's Gaussians moved by the ground truth's motion (needs the "
                         "tet_trajectory extra): the appearance's share of the image error")
    add_device_option(ev, "the simulation and rendering (the scores are computed on the CPU)")
    add_threads_option(ev)
    ev.add_argument("--quiet", action="store_true", help="no progress output")
    ev.set_defaults(func=run)
