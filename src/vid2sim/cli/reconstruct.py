"""``vid2sim reconstruct SCENE OUT``: a scene folder in, a simulation-ready asset out."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vid2sim.cli.common import UserError, add_threads_option, set_threads
from vid2sim.cli.report import write_asset_report
from vid2sim.reconstruct.pipeline import ReconstructConfig, reconstruct
from vid2sim.runtime.device import resolve_device


def run(args: argparse.Namespace) -> int:


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
        write_asset_report(path / "report", path, args.scene, quiet=args.quiet)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``reconstruct`` subcommand."""
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
    rec.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)

