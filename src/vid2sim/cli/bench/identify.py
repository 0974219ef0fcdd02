"""``vid2sim bench identify``: E, ν and damping from perfect-geometry 3-D motion (the pipeline's upper bound).

Its settings are :class:`~vid2sim.apps.bench.identify.IdentifyConfig`, whose sections are reconstruct's: one flag per
field, generated as ``reconstruct``'s are (``--networks.handles 30``, ``--simulator.mass cubature``), with the
spellings of the flat flags before them kept as aliases (``--handles``, ``--mass``, ``--n``, ``--psnr``)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from vid2sim.apps.bench import identify
from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.cli.reconstruct_options import ALIASES as RECONSTRUCT_ALIASES
from vid2sim.cli.scene_options import generation_errors
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.files import read_json

#: short flag → the setting it sets: reconstruct's, where identify has the setting (``--handles``, ``--mass``, …),
#: and the other flat spellings ``bench identify`` had before its flags were generated
ALIASES = {
    **{flag: path for flag, path in RECONSTRUCT_ALIASES.items()
       if path in configs.flag_names(identify.IdentifyConfig)},
    "--n": "scenes", "--skinning-iterations": "networks.skinning_iterations",
    "--fit-iterations": "fit_iterations", "--skinning-points": "skinning_points",
    "--cubature-weights": "cubature_weights", "--fem-element-order": "fem_element_order",
    "--contact-layer": "contact_layer", "--fit-contact-layer": "fit_contact_layer",
    "--calibrate-contact": "calibrate_contact", "--nu-sensitivity": "nu_sensitivity", "--psnr": "render_psnr",
    "--fit-damping": "fit_damping",
}
#: settings without a generated flag: ``nu_scan`` (``--nu-scan STEP`` makes its grid), the fields of reconstruct's
#: sections that identify does not use, and ``networks.jacobian`` (identify takes only the closed form)
NO_FLAG = ("nu_scan", "networks.jacobian", *identify.UNUSED)


def _nu_grid(step: float) -> tuple[float, ...]:
    """The ν grid of ``--nu-scan STEP``: STEP, 2·STEP, … below 0.5."""
    if not 0 < step < 0.25:
        raise UserError(f"--nu-scan must be a step in (0, 0.25), got {step}")
    return tuple(round(k * step, 10) for k in range(1, int(0.5 / step) + 1) if k * step < 0.5 - 1e-9)


def identify_config(args: argparse.Namespace) -> identify.IdentifyConfig:
    """The configuration the options describe: the defaults (or ``--config``'s file) with the flags on top.
    ``--volumetric pointwise`` takes two calibration factors unless ``--calibration-nu`` says otherwise.

    Raises:
        UserError: a bad value, naming the flag; a ``--config`` file that is not a configuration.
    """
    overrides = configs.flag_overrides(args)
    if args.nu_scan is not None:
        overrides["nu_scan"] = list(_nu_grid(args.nu_scan))
    if overrides.get("simulator", {}).get("volumetric") == "pointwise" and "nu" not in overrides.get("calibration", {}):
        overrides.setdefault("calibration", {})["nu"] = "two_factor"  # the pointwise term locks as ν grows: λ too
    try:
        base = identify.IdentifyConfig()
        if args.config is not None:
            data = read_json(args.config, "an identify report or its configuration")
            base = identify.IdentifyConfig.from_dict(data["config"] if "summary" in data else data)
        return configs.merge(base, overrides)
    except ConfigError as exc:
        raise UserError(configs.name_flags(str(exc), identify.IdentifyConfig, ALIASES)) from exc


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    config = identify_config(args)
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
    ident.add_argument("--config", metavar="FILE", default=None,
                       help="start from the settings of this report (--out) or its configuration instead of the "
                            "defaults; the flags below override them")
    defaults = configs.to_dict(identify.IdentifyConfig())

    def default(path: str) -> str:
        value = defaults
        for part in path.split("."):
            value = value[part]
        return f"default {value}"

    configs.add_flags(ident, identify.IdentifyConfig, ALIASES, defaults=default, skip=NO_FLAG,
                      group_title="settings (each --field or --section.field; IdentifyConfig)")
    ident.add_argument("--fixed-damping", dest="config:fit_damping", action="store_const", const=False,
                       default=argparse.SUPPRESS,
                       help="keep the damping ratio at the prior, as reconstruct does (the default; --no-fit-damping)")
    ident.add_argument("--nu-scan", type=float, default=None, metavar="STEP",
                       help="also evaluate the observed-frame loss at the true E over nu = STEP, 2 STEP, ... < 0.5 "
                            "and report its minimum: where the model puts nu when E is right (default off)")
    ident.add_argument("--workdir", default="vid2sim-identify", help="cache of FEM runs and skinning fields "
                       "(default ./vid2sim-identify)")
    ident.add_argument("--out", default=None, help="write the full JSON report here")
    ident.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                       help="scenes run at once in separate processes, each with --threads torch threads (default 1 "
                            "each); default: min(2, CPU count)")
    add_threads_option(ident)
    ident.add_argument("--quiet", action="store_true", help="no progress bars")
    ident.set_defaults(func=run)

