"""The ``vid2sim`` command. Thin: parses arguments and calls the layers.

Each subcommand is a ``_cmd_*`` function taking the parsed arguments and returning an exit code.
Heavy imports (torch, the layers) happen inside those functions so ``vid2sim --help`` stays fast.
Newer subcommands live in their own modules of this package (``vid2sim.cli.<name>``), each with a
``register(subparsers)`` function that adds its parser; :func:`build_parser` finds them.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import pkgutil
import sys
from typing import Callable, Sequence

from vid2sim import __version__
from vid2sim.cli.common import UserError, add_threads_option, set_threads

SHARED_MODULES = ("common",)  # modules of this package that are not subcommands


def _cmd_bench(args: argparse.Namespace) -> int:
    from vid2sim.apps.bench.speed import run_speed_benchmark

    set_threads(args.threads)
    result = run_speed_benchmark(device=args.device, sections=args.only, quick=args.quick)
    if args.json:
        print(json.dumps(result, indent=2, sort_keys=True))
    else:
        for key, value in sorted(result.items()):
            print(f"{key:32s} {value}")
    return 0


def _cmd_bench_jacobian(args: argparse.Namespace) -> int:
    from vid2sim.apps.bench import jacobian_accuracy
    from vid2sim.runtime.device import resolve_device

    result = jacobian_accuracy.run(resolve_device(args.device), iterations=args.iterations, progress=True)
    print(json.dumps(result, indent=2, sort_keys=True))
    return 0


def _cmd_bench_fem(args: argparse.Namespace) -> int:
    from vid2sim.apps.bench import fem_speed

    try:
        result = fem_speed.run(args.preset, seed=args.seed, frames=args.frames, progress=not args.quiet)
    except _generation_errors() as exc:
        raise UserError(str(exc)) from exc
    print(json.dumps(result, indent=2, sort_keys=True))
    return 0


def _cmd_bench_predictability(args: argparse.Namespace) -> int:
    from vid2sim.apps.bench.predictability import PREDICTABILITY_JSON, format_summary, predictability

    set_threads(args.threads)
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    try:
        report = predictability(args.scene, args.out, height_offset=args.height_offset, progress=not args.quiet,
                                workers=args.workers)
    except _generation_errors() as exc:
        raise UserError(f"{exc} (the twin was not written)") from exc
    print(format_summary(report))
    print(f"wrote {os.path.join(args.out, PREDICTABILITY_JSON)}")
    return 0


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


def _cmd_bench_identify(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vid2sim.apps.bench import identify

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
    except _generation_errors() as exc:
        raise UserError(f"{exc} (finished scenes are cached in {args.workdir}; run again to resume)") from exc
    text = json.dumps(report, indent=2)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(text + "\n")
        tmp.replace(out)
    summary = report["summary"]
    rows = ["scene  object           log10E true/fit    nu true/fit     zeta true/fit   model err obs/fut %  fitted err obs/fut %"]
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
            rows.append(f"{r['scene']:5d}  dnu {n['dnu']:+.3f}: {n['observed_percent']:5.2f} / {n['future_percent']:5.2f}"
                        f"      {n['observed_percent_per_0_05']:5.2f}            {n['nu_equivalent_of_model_error']:.3f}")
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


def _cmd_bench_suite(args: argparse.Namespace) -> int:
    from vid2sim.runtime.ray_runner import RayUnavailable
    from vid2sim.apps.bench.suite import SUITE_JSON, SuiteConfig, format_table, run_suite

    if args.iterations is not None and args.iterations < 0:
        raise UserError(f"--iterations must be >= 0, got {args.iterations}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    config = SuiteConfig(preset=args.preset, iterations=args.iterations, threads=args.threads)
    try:
        result = run_suite(args.suite, args.out, config, progress=not args.quiet, ray_address=args.ray_address)
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    print(format_table(result))
    path = os.path.join(args.out, SUITE_JSON)
    failed = [r["name"] for r in result["scenes"] if r["status"] != "ok"]
    if failed:
        print(f"vid2sim bench suite: {len(failed)} of {len(result['scenes'])} scenes failed ({', '.join(failed)}); "
              f"the others finished. Wrote {path}; each failed scene's traceback is in OUT/NAME/error.txt; run "
              "the command again to retry only the failed scenes.", file=sys.stderr)
        return 1
    print(f"wrote {path}; report: {os.path.join(args.out, 'report', 'index.html')}")
    return 0


def _cmd_bench_ablation(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vid2sim.apps.bench.ablation import ABLATION_JSON, format_ablation_table, run_ablation
    from vid2sim.runtime.ray_runner import RayUnavailable
    from vid2sim.apps.bench.suite import SuiteConfig

    if args.iterations is not None and args.iterations < 0:
        raise UserError(f"--iterations must be >= 0, got {args.iterations}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    if args.predictor is not None and not Path(args.predictor).is_file():
        raise UserError(f"--predictor {args.predictor}: no such checkpoint file (train one with "
                        "`vid2sim train-predictor`)")
    config = SuiteConfig(preset=args.preset, iterations=args.iterations, threads=args.threads)
    try:
        result = run_ablation(args.suite, args.out, config, predictor=args.predictor, progress=not args.quiet,
                              ray_address=args.ray_address)
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    print(format_ablation_table(result))
    path = os.path.join(args.out, ABLATION_JSON)
    failed = [f"{name}/{r['name']}" for name, v in result["variants"].items() for r in v["scenes"]
              if r["status"] != "ok"]
    if failed:
        total = sum(len(v["scenes"]) for v in result["variants"].values())
        print(f"vid2sim bench ablation: {len(failed)} of {total} variant scenes failed ({', '.join(failed)}); the "
              f"others finished. Wrote {path}; each failed scene's traceback is in OUT/VARIANT/NAME/error.txt; run "
              "the command again to retry the failed scenes.", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


_SCENE_OPTIONS = {  # CLI option → SyntheticSceneConfig field
    "E": "youngs_modulus", "nu": "poisson_ratio", "density": "density", "material": "material",
    "drop_height": "drop_height", "views": "views", "resolution": "resolution", "frames": "frames",
    "observed_frames": "observed_frames", "substeps": "substeps", "layout": "layout",
    "damping_ratio": "damping_ratio", "held_out_views": "held_out_views", "element_order": "element_order",
}


def _scene_overrides(args: argparse.Namespace) -> dict:
    """The SyntheticSceneConfig fields given on the command line (make-benchmark has no --E / --nu)."""
    values = {field: getattr(args, opt, None) for opt, field in _SCENE_OPTIONS.items()}
    return {field: value for field, value in values.items() if value is not None}


def _scene_config_error(exc: ValueError) -> UserError:
    """A SyntheticSceneConfig error with the command-line flag the user typed instead of the field's name."""
    message = str(exc)
    for opt, field in _SCENE_OPTIONS.items():
        flag = "--" + opt.replace("_", "-") if opt != "damping_ratio" else "--damping"
        message = message.replace(f"SyntheticSceneConfig.{field} ", f"{flag} ")
    return UserError(message)


def _generation_errors() -> tuple[type[Exception], ...]:
    from vid2sim.synthetic.fem import FEMSolverError
    from vid2sim.meshing.tetra import TetrahedralizationError

    return (FEMSolverError, TetrahedralizationError)


def _cmd_make_scene(args: argparse.Namespace) -> int:
    from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene

    set_threads(args.threads)
    try:
        config = SyntheticSceneConfig.preset(args.preset, seed=args.seed, mesh=args.mesh, tet_mesh=args.tet_mesh,
                                             **_scene_overrides(args))
    except ValueError as exc:
        raise _scene_config_error(exc) from exc
    try:
        path = make_scene(config, args.out, overwrite=args.overwrite, progress=not args.quiet, workers=args.workers)
    except _generation_errors() as exc:
        raise UserError(f"{exc} (nothing was written)") from exc
    print(f"wrote {path}")
    return 0


def _cmd_make_benchmark(args: argparse.Namespace) -> int:
    from vid2sim.runtime.ray_runner import RayUnavailable
    from vid2sim.synthetic.scenes import make_benchmark

    set_threads(args.threads)
    if args.n < 1:
        raise UserError(f"--n must be >= 1 (the number of scenes), got {args.n}")
    try:
        path = make_benchmark(args.n, args.out, preset=args.preset, seed=args.seed, progress=not args.quiet,
                              workers=args.workers, ray_address=args.ray_address, **_scene_overrides(args))
    except RayUnavailable as exc:
        raise UserError(str(exc)) from exc
    except _generation_errors() as exc:  # before ValueError, in case one of them is a ValueError
        raise UserError(f"{exc} (finished scenes are kept; run the command again to resume)") from exc
    except ValueError as exc:
        raise _scene_config_error(exc) from exc
    print(f"wrote {path} ({args.n} scene{'s' if args.n != 1 else ''}, index.json)")
    return 0


def _cmd_fit_gaussians(args: argparse.Namespace) -> int:
    import dataclasses
    import shutil
    import tempfile
    import time
    from pathlib import Path

    import torch
    from PIL import Image

    from vid2sim.runtime.device import resolve_device
    from vid2sim.scene.folder import SceneFormatError, load_scene, move_into_place
    from vid2sim.splats.fitting import FitConfig, fit_gaussians
    from vid2sim.splats.losses import psnr
    from vid2sim.splats.ply import save_ply
    from vid2sim.splats.preview import comparison_image
    from vid2sim.splats.render import render_gaussians

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


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vid2sim.runtime.device import resolve_device
    from vid2sim.reconstruct.pipeline import ReconstructConfig, reconstruct

    set_threads(args.threads)
    device = resolve_device(args.device)  # a bad --device fails before any work
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    overrides = {}
    if args.jacobian is not None:
        overrides["jacobian"] = args.jacobian
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.handles is not None:
        if args.handles < 1:
            raise UserError(f"--handles must be >= 1, got {args.handles}")
        overrides["handles"] = args.handles
    if args.skinning_objective is not None:
        overrides["skinning_objective"] = args.skinning_objective
    if args.stage1 is not None:
        overrides["stage1"] = args.stage1
    if args.calibrate_stiffness is not None:
        overrides["calibrate_stiffness"] = args.calibrate_stiffness
    if args.calibration_nu is not None:
        overrides["calibration_nu"] = args.calibration_nu
    if args.volumetric is not None:
        overrides["volumetric"] = args.volumetric
        if args.volumetric == "projected" and args.calibration_nu is None:
            overrides["calibration_nu"] = "curve"  # the projected term does not lock: one factor
    if args.mass is not None:
        overrides["mass"] = args.mass
    if args.motion_geometry is not None:
        overrides["motion_appearance_geometry"] = args.motion_geometry
    if args.shading is not None:
        overrides["motion_appearance_shading"] = args.shading
    if args.motion_loss_power is not None:
        if not 0 < args.motion_loss_power <= 1:
            raise UserError(f"--motion-loss-power must be in (0, 1], got {args.motion_loss_power}")
        overrides["motion_appearance_loss_power"] = args.motion_loss_power
    if args.predictor is not None:
        if not Path(args.predictor).is_file():
            raise UserError(f"--predictor {args.predictor}: no such checkpoint file (train one with "
                            "`vid2sim train-predictor`)")
        overrides["predictor"] = str(Path(args.predictor).resolve())
        overrides.setdefault("stage1", True)  # a checkpoint given is a checkpoint to use
    config = ReconstructConfig.preset(args.preset, **overrides)
    if args.iterations is not None:
        if args.iterations < 0:
            raise UserError(f"--iterations must be >= 0, got {args.iterations}")
        config.joint.iterations = args.iterations
    if args.sh_degree is not None:
        if not 0 <= args.sh_degree <= 3:
            raise UserError(f"--sh-degree must be 0, 1, 2 or 3, got {args.sh_degree}")
        config.gaussians.sh_degree = args.sh_degree
    if args.centre_of_mass_step is not None:
        if not 0 <= args.centre_of_mass_step < 0.5:
            raise UserError(f"--centre-of-mass-step must be a fraction of the object's size in [0, 0.5), "
                            f"got {args.centre_of_mass_step}")
        config.joint.centre_of_mass_step = args.centre_of_mass_step
    if args.frame_rounds is not None:
        if args.frame_rounds < 0:
            raise UserError(f"--frame-rounds must be >= 0, got {args.frame_rounds}")
        config.points.frame_rounds = args.frame_rounds
    path = reconstruct(args.scene, out, config, progress=not args.quiet, restart=args.restart, device=device)
    material = json.loads((path / "material.json").read_text())
    print(f"wrote {path}: E = {material['E']:.4g} Pa (log10 E = {material['log10_E']:.3f}), nu = {material['nu']:.3f}")
    if not args.no_report:
        _write_report(path / "report", path, args.scene, quiet=args.quiet)
    return 0


def _write_report(out, asset, scene, quiet: bool, evaluation=None, renders=None) -> None:
    """The HTML report of ``asset`` compared with ``scene`` (vid2sim.report), and one line saying where it is."""
    from vid2sim.report import ReportInputError, write_report

    try:
        path = write_report(out, asset, scene=scene, evaluation=evaluation, renders=renders, progress=not quiet)
    except ReportInputError as exc:
        raise UserError(f"the report could not be written: {exc}") from exc
    print(f"report: {path / 'index.html'}")


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vid2sim.evaluate.scores import evaluate, write_report

    set_threads(args.threads)
    report, renders = evaluate(args.asset, args.scene, fovvdp=args.fovvdp, progress=not args.quiet,
                               return_renders=True, true_motion=args.true_motion)
    out = Path(args.out) if args.out else Path(args.asset) / "evaluation.json"
    write_report(report, out)
    lines = []
    for key in ("dynamic", "future", "novel_views"):
        if report[key]:
            lines.append(f"{key}: PSNR {report[key]['psnr']:.2f} dB, SSIM {report[key]['ssim']:.4f}")
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
    for key, what in (("chamfer", "Chamfer to the true surface"), ("centre_of_mass", "centre of mass off the truth's")):
        if key in report:
            future = report[key]["future_mean"]
            lines.append(f"{what}: {100 * report[key]['observed_mean']:.2f} cm observed"
                         + (f", {100 * future:.2f} cm future" if future is not None else ""))
    print("\n".join(lines + [f"wrote {out}"]))
    if not args.no_report:
        _write_report(Path(args.asset) / "report", args.asset, args.scene, quiet=args.quiet, evaluation=report,
                      renders=renders)
    return 0


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


def _add_scene_options(p: argparse.ArgumentParser, material_options: bool, default_element_order: int = 1) -> None:
    p.add_argument("--preset", choices=["full", "small"], default="full",
                   help="full: 12 + 2 held-out views, 448x448, 24 frames (the paper); small: 4 + 2 held-out views, "
                        "128x128, 24 frames (CPU)")
    if material_options:
        p.add_argument("--E", type=float, default=None, help="Young's modulus in Pa (default 1e5)")
        p.add_argument("--nu", type=float, default=None, help="Poisson's ratio (default 0.3)")
    p.add_argument("--density", type=float, default=None, help="kg/m^3 (default 1000)")
    p.add_argument("--material", default=None, help="FEM elastic model: neo_hookean (default) or stvk")
    p.add_argument("--drop-height", type=float, default=None, help="m above the floor (default: random from the seed)")
    p.add_argument("--views", type=int, default=None, help="cameras on the ring (held-out ones included)")
    p.add_argument("--held-out-views", type=int, default=None,
                   help="ring cameras held out as novel views, spread evenly (preset: 2)")
    p.add_argument("--resolution", type=int, default=None, help="image side in pixels")
    p.add_argument("--frames", type=int, default=None, help="frames T")
    p.add_argument("--observed-frames", type=int, default=None, help="observed frames (the rest are held out)")
    p.add_argument("--substeps", type=int, default=None,
                   help="the FEM's first substep count per frame; it doubles them until the trajectory is converged "
                        "in time (default: from the material's stiffness)")
    p.add_argument("--damping", type=float, default=None, dest="damping_ratio",
                   help="material damping ratio zeta (Kelvin-Voigt; default 0.05, 0 = undamped)")
    p.add_argument("--element-order", type=int, choices=[1, 2], default=None,
                   help="the FEM's tets: 1 linear or 2 quadratic (converged in space, the FEM about 20x slower); default "
                        f"{default_element_order}"
                        + ("; a suite's quadratic tets have the small preset's size at every preset"
                           if default_element_order == 2 else ""))
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="processes for the FEM's side-by-side time resolutions (default: 2, or 1 on a 1-CPU machine)")
    p.add_argument("--layout", choices=["rgba", "rgb+mask", "video"], default=None, help="scene folder layout")
    add_threads_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _add_suite_run_options(p: argparse.ArgumentParser) -> None:
    """--ray-address, --threads and --quiet of the commands that run a benchmark suite."""
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="run each scene as a Ray task: 'local' starts Ray on this machine, or a cluster address "
                        "(auto, HOST:6379); OUT must be a path every node sees (needs pip install \"vid2sim[ray]\")")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads per scene, and CPUs each Ray task reserves (default: torch's; 1 per Ray task)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``vid2sim`` command (one subparser per subcommand)."""
    parser = argparse.ArgumentParser(
        prog="vid2sim",
        description="Simulation-ready assets from posed multi-view videos, and their mesh-free simulation.",
    )
    parser.add_argument("--version", action="version", version=f"vid2sim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    bench = sub.add_parser("bench", help="run benchmarks and print their figures")
    bench_sub = bench.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    speed = bench_sub.add_parser("speed", help="speed figures of the simulator and renderer")
    speed.add_argument("--json", action="store_true", help="print one JSON object")
    speed.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    speed.add_argument(
        "--only", nargs="*", default=None, metavar="SECTION",
        help="run only these sections (physics, render, joint, modes); default: all",
    )
    speed.add_argument("--quick", action="store_true", help="fewer repetitions (for smoke tests)")
    add_threads_option(speed)
    speed.set_defaults(func=_cmd_bench)
    jac = bench_sub.add_parser("jacobian", help="train the Neural Jacobian data-free and report its error")
    jac.add_argument("--iterations", type=int, default=1000, help="training iterations (paper: 10000)")
    jac.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    jac.set_defaults(func=_cmd_bench_jacobian)
    fem = bench_sub.add_parser("fem", help="FEM ground-truth time: exact-Hessian Newton vs projecting every iteration")
    fem.add_argument("--preset", choices=["full", "small"], default="small", help="scene preset (default small)")
    fem.add_argument("--seed", type=int, default=0, help="object and pose seed (default 0)")
    fem.add_argument("--frames", type=int, default=None, help="frames to simulate (default: the preset's 24)")
    fem.add_argument("--quiet", action="store_true", help="no progress bars")
    fem.set_defaults(func=_cmd_bench_fem)

    pred = bench_sub.add_parser("predictability", help="a synthetic scene's truth simulated again from a start "
                                "1 mm higher and scored like an asset: how far its frames can be predicted at all")
    pred.add_argument("scene", help="synthetic scene folder (make-scene / make-benchmark)")
    pred.add_argument("out", help="results folder: twin/ (a scene folder, reused) and predictability.json")
    pred.add_argument("--height-offset", type=float, default=1e-3, metavar="M",
                      help="how much higher the twin starts, in metres (default 0.001)")
    pred.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                      help="processes for the FEM's first pair of time resolutions (default: min(2, CPU count))")
    add_threads_option(pred)
    pred.add_argument("--quiet", action="store_true", help="no progress bars")
    pred.set_defaults(func=_cmd_bench_predictability)

    ident = bench_sub.add_parser("identify", help="identify E, nu and damping from perfect-geometry 3-D motion "
                                 "(the upper bound of the video pipeline)")
    ident.add_argument("--n", type=int, default=None, help="scenes (default 6)")
    ident.add_argument("--only", type=_index_list, default=None, metavar="I,J,...",
                       help="run just these scenes of the suite (0-based, e.g. 4,5) from the same work folder; "
                            "the means are then the subset's")
    ident.add_argument("--seed", type=int, default=None, help="suite seed (default 0)")
    ident.add_argument("--preset", choices=["small", "full"], default=None, help="tet resolution (default small)")
    ident.add_argument("--handles", type=int, default=None, help="learned skinning handles (default 30)")
    ident.add_argument("--skinning-iterations", type=int, default=None, help="data-free skinning iterations (default 2000)")
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
    ident.set_defaults(func=_cmd_bench_identify)

    bsuite = bench_sub.add_parser("suite", help="reconstruct + evaluate every scene of a make-benchmark suite; "
                                  "per-scene table and means, suite.json (resumable)")
    bsuite.add_argument("suite", help="benchmark folder written by make-benchmark (index.json + scenes)")
    bsuite.add_argument("out", help="results folder: NAME/asset, NAME/evaluation.json per scene, suite.json "
                        "(resumed if it holds a suite_config.json)")
    bsuite.add_argument("--preset", choices=["small", "full"], default="small",
                        help="reconstruct preset: small (CPU minutes per scene) or full; default small")
    bsuite.add_argument("--iterations", type=int, default=None,
                        help="joint-optimisation iterations (default: the preset's)")
    _add_suite_run_options(bsuite)
    bsuite.set_defaults(func=_cmd_bench_suite)
    babl = bench_sub.add_parser("ablation", help="the paper's Stage I ablation on a make-benchmark suite: Stage I "
                                "alone, Stage I + II, Stage II from the prior; one table row each, ablation.json "
                                "(resumable)")
    babl.add_argument("suite", help="benchmark folder written by make-benchmark (index.json + scenes)")
    babl.add_argument("out", help="results folder: one bench-suite folder per variant (stage1_only, stage1_stage2, "
                      "stage2_prior) and ablation.json (resumed if it holds them)")
    babl.add_argument("--preset", choices=["small", "full"], default="small",
                      help="reconstruct preset: small (CPU minutes per scene) or full; default small")
    babl.add_argument("--iterations", type=int, default=None,
                      help="joint-optimisation iterations of the Stage II variants (default: the preset's)")
    babl.add_argument("--predictor", metavar="PATH", default=None,
                      help="Stage I checkpoint (default: the one shipped with vid2sim; vid2sim train-predictor)")
    _add_suite_run_options(babl)
    babl.set_defaults(func=_cmd_bench_ablation)

    scene = sub.add_parser("make-scene", help="simulate (FEM) and render one synthetic scene folder")
    scene.add_argument("out", help="scene folder to create")
    scene.add_argument("--mesh", default=None, help="a watertight textured mesh (OBJ/GLB/GLTF/PLY) instead of a "
                       "procedural shape")
    scene.add_argument("--seed", type=int, default=0,
                       help="seed of the procedural shape and texture (unless --mesh) and of the initial pose (default 0)")
    scene.add_argument("--tet-mesh", default=None, help="reuse the tet mesh of an earlier scene (its fem_result.npz) "
                       "instead of fTetWild, which is not reproducible; same settings then give the same scene")
    scene.add_argument("--overwrite", action="store_true", help="replace an existing scene folder")
    _add_scene_options(scene, material_options=True)
    scene.set_defaults(func=_cmd_make_scene)

    suite = sub.add_parser("make-benchmark", help="a deterministic suite of synthetic scenes (E, nu sampled)")
    suite.add_argument("out", help="benchmark folder (resumed if it holds an index.json)")
    suite.add_argument("--n", type=int, required=True, help="number of scenes")
    suite.add_argument("--seed", type=int, default=0, help="suite seed (default 0)")
    suite.add_argument("--ray-address", default=None, metavar="ADDR",
                       help="make each scene as a Ray task: 'local' starts Ray on this machine, or a cluster "
                            "address (auto, HOST:6379); OUT must be a path every node sees (needs "
                            "pip install \"vid2sim[ray]\")")
    _add_scene_options(suite, material_options=False, default_element_order=2)
    suite.set_defaults(func=_cmd_make_benchmark)

    fit = sub.add_parser("fit-gaussians", help="fit 3D Gaussians to one frame of a scene folder (all views, or all but --test-views)")
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
    fit.set_defaults(func=_cmd_fit_gaussians)

    rec = sub.add_parser("reconstruct", help="reconstruct a scene folder into a simulation-ready asset "
                         "(Gaussians, skinning field, material)")
    rec.add_argument("scene", help="scene folder (scene.json + transforms.json)")
    rec.add_argument("out", help="asset folder to create (docs/asset-format.md)")
    rec.add_argument("--preset", choices=["small", "full"], default="small",
                     help="sizes: small (CPU minutes) or full (the paper's iterations); default small")
    rec.add_argument("--iterations", type=int, default=None, help="joint-optimisation iterations (default: the preset's)")
    rec.add_argument("--jacobian", choices=["closed_form", "neural"], default=None,
                     help="dF/dz: exact closed form (default, faster on a CPU) or the paper's Neural Jacobian")
    rec.add_argument("--seed", type=int, default=None, help="seed (default 0)")
    rec.add_argument("--handles", type=int, default=None,
                     help="learned skinning handles (default 10, + 1 rigid); more handles let the subspace squash "
                          "and bend closer to the continuum at a higher cost per step (Stage I's template has 10)")
    rec.add_argument("--skinning-objective", choices=["random_z", "modal"], default=None,
                     help="data-free skinning objective: the subspace's lowest vibration modes (default) or the "
                          "paper's random handle transforms (docs/architecture.md, 'Subspace stiffness')")
    rec.add_argument("--stage1", action=argparse.BooleanOptionalAction, default=None,
                     help="run the Stage I predictor first (its prediction becomes the prior material, the centre of "
                     "the coarse E search and the skinning field's start). Off by default until the shipped "
                     "predictor meets its accuracy targets (docs/predictor.md); --no-stage1 is the paper's "
                     "'w/o Stage I' ablation")
    rec.add_argument("--calibrate-stiffness", action=argparse.BooleanOptionalAction, default=None,
                     help="scale the simulator's elastic energy so that the skinning subspace's lowest mode vibrates "
                     "at the frequency of quadratic tets on a surface of the reconstructed solid: the subspace is "
                     "stiffer than the continuum, and the fitted E is then the material's (on by default; "
                     "--no-calibrate-stiffness turns it off; docs/architecture.md)")
    rec.add_argument("--calibration-nu", choices=["curve", "two_factor", "prior"], default=None,
                     help="with --calibrate-stiffness: two factors (on mu and on lambda) per nu of a grid, matched to "
                          "the six lowest modes and used at the fit's current nu (two_factor, the default), one "
                          "factor s(nu) over that grid (curve), or one factor at the prior nu")
    rec.add_argument("--volumetric", choices=["pointwise", "projected"], default=None,
                     help="the simulator's volumetric term: pointwise, or projected onto the skinning weights' span "
                          "(no volumetric locking; implies --calibration-nu curve unless that is given)")
    rec.add_argument("--mass", choices=["moments", "cubature"], default=None,
                     help="the simulator's lumped masses: the cubature volumes as sampled (cubature, the default) or "
                          "matched to the kept voxels' mass, centre of mass and inertia tensor (moments)")
    rec.add_argument("--frame-rounds", type=int, default=None,
                     help="rounds of carving the frame-0 hull with the masks of the later frames whose rigid pose the "
                     "silhouettes explain (default 2; 0: the frame-0 hull only; docs/architecture.md, 'The hull from "
                     "the later frames')")
    rec.add_argument("--motion-geometry", action=argparse.BooleanOptionalAction, default=None,
                     help="the last stage fits the Gaussians' rest-frame centres, scales and rotations as well as "
                     "their colours and opacities through the simulated motion (on by default; "
                     "--no-motion-geometry: colours and opacities only)")
    rec.add_argument("--sh-degree", type=int, default=None,
                     help="the Gaussians' spherical-harmonic degree, 0-3: view-dependent colour (default: the "
                     "preset's, 0 for small, 3 (3DGS's) for full; with few views or a matte object a lower degree "
                     "has less to overfit)")
    rec.add_argument("--shading", action=argparse.BooleanOptionalAction, default=None,
                     help="the last stage separates the colours' albedo from a light fixed in the world (a "
                     "direction and an ambient share, fitted), so the asset is lit by its pose as it turns (on by "
                     "default; --no-shading: the colours keep the light they were fitted under)")
    rec.add_argument("--motion-loss-power", type=float, default=None, metavar="P",
                     help="the last stage minimises (image loss)^P per step, P in (0, 1] (default 1: 3DGS's loss; "
                     "0.5 weighs the frames the simulated motion explains well more; docs/architecture.md)")
    rec.add_argument("--centre-of-mass-step", type=float, default=None, metavar="S",
                     help="after the coarse E search, search the lumped masses' centre of mass along each axis, "
                     "first in steps of S x the object's diagonal (0.02: about 1 cm on a 50 cm object), then half "
                     "that; the whole observed clip's image loss picks it (default 0: the hull's centre)")
    rec.add_argument("--predictor", metavar="PATH", default=None,
                     help="Stage I checkpoint (default: the one shipped with vid2sim; vid2sim train-predictor)")
    rec.add_argument("--device", default=None, help="torch device of the Gaussian fits, networks and joint "
                     "optimisation (default: cuda if available, else cpu; the asset is the same format either way)")
    rec.add_argument("--restart", action="store_true", help="discard an interrupted run's finished stages")
    rec.add_argument("--overwrite", action="store_true", help="replace an existing asset folder")
    rec.add_argument("--no-report", action="store_true", help="do not write the HTML report (OUT/report/index.html: "
                     "the asset against the scene, docs/report.md)")
    add_threads_option(rec)
    rec.add_argument("--quiet", action="store_true", help="no progress output")
    rec.set_defaults(func=_cmd_reconstruct)

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
    add_threads_option(ev)
    ev.add_argument("--quiet", action="store_true", help="no progress output")
    ev.set_defaults(func=_cmd_evaluate)
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name not in SHARED_MODULES:
            importlib.import_module(f"{__name__}.{info.name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``vid2sim`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        return func(args)
    except (UserError, ValueError, OSError) as exc:
        print(f"vid2sim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vid2sim {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
