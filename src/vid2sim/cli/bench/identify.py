"""``vid2sim bench identify``: E, ν and damping from perfect-geometry 3-D motion (the pipeline's upper bound)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from vid2sim.apps.bench import identify
from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.cli.scene_options import generation_errors


def _index_list(text: str) -> tuple[int, ...]:
    """argparse type: comma-separated non-negative integers ("4,5")."""
    try:
        values = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated scene indices, e.g. 4,5; got {text!r}") from None
    if any(v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"scene indices must be >= 0, got {text!r}")
    return values


def _nu_grid(step: float) -> tuple[float, ...]:
    """The ν grid of ``--nu-scan STEP``: STEP, 2·STEP, … below 0.5."""
    if not 0 < step < 0.25:
        raise UserError(f"--nu-scan must be a step in (0, 0.25), got {step}")
    return tuple(round(k * step, 10) for k in range(1, int(0.5 / step) + 1) if k * step < 0.5 - 1e-9)


def run(args: argparse.Namespace) -> int:


    set_threads(args.threads)
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    given = {"scenes": args.n, "only": args.only, "seed": args.seed, "preset": args.preset, "handles": args.handles,
             "skinning_iterations": args.skinning_iterations, "fit_iterations": args.fit_iterations,
             "points": args.points, "skinning_points": args.skinning_points, "truth": args.truth,
             "skinning_objective": args.skinning_objective,
             "cubature_weights": args.cubature_weights, "fem_element_order": args.fem_element_order,
             "loss": args.loss, "calibrate_stiffness": args.calibrate_stiffness,
             "calibration_nu": args.calibration_nu, "contact_layer": args.contact_layer,
             "calibrate_contact": True if args.calibrate_contact else None,
             "fit_contact_layer": True if args.fit_contact_layer else None,
             "fit_damping": args.fit_damping, "nu_sensitivity": args.nu_sensitivity,
             "nu_scan": _nu_grid(args.nu_scan) if args.nu_scan is not None else None,
             "render_psnr": True if args.psnr else None, "volumetric": args.volumetric, "mass": args.mass}
    if args.volumetric == "pointwise" and args.calibration_nu is None:
        given["calibration_nu"] = "two_factor"  # the pointwise term locks as nu grows: a factor on lambda too
    flags = {"scenes": "--n", "only": "--only", "seed": "--seed", "preset": "--preset", "handles": "--handles",
             "skinning_iterations": "--skinning-iterations", "fit_iterations": "--fit-iterations", "points": "--points",
             "skinning_points": "--skinning-points", "nu_sensitivity": "--nu-sensitivity",
             "nu_scan": "--nu-scan"}
    try:
        config = identify.IdentifyConfig(**{k: v for k, v in given.items() if v is not None})
    except ValueError as exc:
        message = str(exc)
        for field, flag in flags.items():
            message = message.replace(f"IdentifyConfig.{field} ", f"{flag} ")
        raise UserError(message) from exc
    try:
        report = identify.run(config, args.workdir, progress=not args.quiet, workers=args.workers,
                              threads_per_worker=args.threads or 1)
    except generation_errors() as exc:
        raise UserError(f"{exc} (finished scenes are cached in {args.workdir}; run again to resume)") from exc
    text = json.dumps(report, indent=2)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(text + "\n")
        tmp.replace(out)
    summary = report["summary"]
    rows = [
        "scene  object           log10E true/fit    nu true/fit     zeta true/fit   model err obs/fut %  fitted err "
        "obs/fut %"
    ]
    for r in report["scenes"]:
        t, f, m, e = r["true"], r["fitted"], r["model_error_at_truth_percent"], r["trajectory_error_fitted_percent"]
        rows.append(f"{r['scene']:5d}  {r['object']:15s}  {t['log10_E']:5.2f} / {f['log10_E']:5.2f}     "
                    f"{t['nu']:.3f} / {f['nu']:.3f}   {t['damping_ratio']:.3f} / {f['damping_ratio']:.3f}   "
                    f"{m['observed_percent']:5.2f} / {m['future_percent']:5.2f}       "
                    f"{e['observed_percent']:5.2f} / {e['future_percent']:5.2f}")
    if any(r.get("nu_sensitivity") for r in report["scenes"]):
        rows.append("scene  truth moved by dnu obs/fut %   per 0.05 obs %   nu worth the model error")
        for r in report["scenes"]:
            n = r["nu_sensitivity"]
            rows.append(
                f"{r['scene']:5d}  dnu {n['dnu']:+.3f}: {n['observed_percent']:5.2f} / {n['future_percent']:5.2f}"
                f"      {n['observed_percent_per_0_05']:5.2f}            {n['nu_equivalent_of_model_error']:.3f}"
            )
    if any(r.get("nu_scan") for r in report["scenes"]):
        rows.append("scene  nu true   loss minimum over nu at the true E   (error)")
        for r in report["scenes"]:
            n = r["nu_scan"]
            rows.append(f"{r['scene']:5d}  {r['true']['nu']:.3f}     {n['argmin_nu']:.3f}"
                        f"                                ({n['argmin_error']:+.3f})")
    if any(r.get("images_at_truth") for r in report["scenes"]):
        rows.append("scene  PSNR dynamic/future at truth   fitted")
        for r in report["scenes"]:
            a, f = r["images_at_truth"], r["images_fitted"]
            rows.append(f"{r['scene']:5d}  {a['dynamic']['psnr']:6.2f} / {a['future']['psnr']:6.2f}"
                        f"           {f['dynamic']['psnr']:6.2f} / {f['future']['psnr']:6.2f}")
    print("\n".join(rows), file=sys.stderr)
    print(json.dumps(summary, indent=2) if not args.out else f"wrote {args.out}\n" + json.dumps(summary, indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench identify`` subcommand."""
    ident = sub.add_parser("identify", help="identify E, nu and damping from perfect-geometry 3-D motion "
                                 "(the upper bound of the video pipeline)")
    ident.add_argument("--n", type=int, default=None, help="scenes (default 6)")
    ident.add_argument("--only", type=_index_list, default=None, metavar="I,J,...",
                       help="run just these scenes of the suite (0-based, e.g. 4,5) from the same work folder; "
                            "the means are then the subset's")
    ident.add_argument("--seed", type=int, default=None, help="suite seed (default 0)")
    ident.add_argument("--preset", choices=["small", "full"], default=None, help="tet resolution (default small)")
    ident.add_argument("--handles", type=int, default=None, help="learned skinning handles (default 30)")
    ident.add_argument(
        "--skinning-iterations", type=int, default=None, help="data-free skinning iterations (default 2000)"
    )
    ident.add_argument("--fit-iterations", type=int, default=None, help="L-BFGS iterations (default 12)")
    ident.add_argument("--points", type=int, default=None, help="sample points (default 3000)")
    ident.add_argument("--skinning-points", type=int, default=None,
                       help="points the skinning field is trained on (default 30000)")
    ident.add_argument("--skinning-objective", choices=["random_z", "modal"], default=None,
                       help="skinning training objective: the subspace's lowest modes (default) or the paper's "
                            "random handle transforms")
    ident.add_argument("--cubature-weights", choices=["equal", "voronoi"], default=None,
                       help="cubature integration weights: the paper's equal weights (default) or Voronoi cell volumes")
    ident.add_argument("--fem-element-order", type=int, choices=[1, 2], default=None,
                       help="the ground truth's tets: 2 quadratic (default; converged in space) or 1 linear "
                            "(10-20x faster, 3-20 %% too stiff)")
    ident.add_argument("--truth", choices=["fem", "reduced"], default=None,
                       help="fit the FEM's motion (default) or the reduced model's own motion at the true "
                            "parameters (identifiability without model error)")
    ident.add_argument("--loss", choices=["shape_and_centre", "positions"], default=None,
                       help="the fit's 3-D loss: centre of mass + shape after a rigid alignment per frame "
                            "(default; blind to the chaotic rocking of the orientation) or the plain point distance")
    ident.add_argument("--calibrate-stiffness", action=argparse.BooleanOptionalAction, default=None,
                       help="scale the reduced model's elastic energy so that its lowest mode vibrates at the "
                            "frequency of quadratic tets on the rest mesh (default on; --no-calibrate-stiffness "
                            "turns it off): the subspace is stiffer than the continuum, and the fit's E then is the "
                            "material's")
    ident.add_argument("--calibration-nu", choices=["curve", "two_factor", "prior"], default=None,
                       help="with --calibrate-stiffness: one factor on E at a grid of nu, used at the fit's current "
                            "nu (curve, the default with the projected volumetric term), two factors (on mu and on "
                            "lambda) matched to the six lowest modes (two_factor, the default with --volumetric "
                            "pointwise, whose locking grows with nu and sits in lambda), or one factor at the prior nu")
    ident.add_argument("--volumetric", choices=["pointwise", "projected"], default=None,
                       help="the reduced model's volumetric term: projected onto the skinning weights' span "
                            "(default), which removes the subspace's volumetric locking, or pointwise (implies "
                            "--calibration-nu two_factor unless that is given)")
    ident.add_argument("--mass", choices=["moments", "cubature"], default=None,
                       help="the reduced model's lumped masses: the cubature volumes corrected to the tet mesh's mass, "
                            "centre of mass and inertia tensor (moments, the default) or the cubature volumes as they "
                            "are (cubature)")
    ident.add_argument("--fit-contact-layer", action="store_true",
                       help="also fit the contact layer (a fraction of the size) with E and nu; experimental")
    damping = ident.add_mutually_exclusive_group()
    damping.add_argument("--fit-damping", dest="fit_damping", action="store_const", const=True, default=None,
                         help="also fit the damping ratio (it trades off against nu)")
    damping.add_argument("--fixed-damping", dest="fit_damping", action="store_const", const=False,
                         help="keep the damping ratio at the prior (0.05), as reconstruct does (the default)")
    ident.add_argument("--contact-layer", type=float, default=None,
                       help="experimental: the reduced model's barriers act through a layer of the body in series, "
                            "this fraction of the object's size deep (default 0: none)")
    ident.add_argument("--calibrate-contact", action="store_true",
                       help="experimental: set that layer from the object's quadratic tets instead, so that the "
                            "subspace has their compliance under the floor loads of its own simulation (measured: "
                            "it makes the contact too soft and the fits worse; docs/architecture.md)")
    ident.add_argument("--nu-sensitivity", type=float, default=None, metavar="DNU",
                       help="also run the FEM at nu - DNU per scene and report how far that moves the truth "
                            "against the model error (default off)")
    ident.add_argument("--nu-scan", type=float, default=None, metavar="STEP",
                       help="also evaluate the observed-frame loss at the true E over nu = STEP, 2 STEP, ... < 0.5 "
                            "and report its minimum: where the model puts nu when E is right (default off)")
    ident.add_argument("--psnr", action="store_true",
                       help="also render the truth's and the model's motion of the textured object in the preset's "
                            "observed cameras and report PSNR/SSIM: the model's image ceiling")
    ident.add_argument("--workdir", default="vid2sim-identify", help="cache of FEM runs and skinning fields "
                       "(default ./vid2sim-identify)")
    ident.add_argument("--out", default=None, help="write the full JSON report here")
    ident.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                       help="scenes run at once in separate processes, each with --threads torch threads (default 1 "
                            "each); default: min(2, CPU count)")
    add_threads_option(ident)
    ident.add_argument("--quiet", action="store_true", help="no progress bars")
    ident.set_defaults(func=run)

