"""The options shared by ``make-scene`` and ``make-benchmark`` (the synthetic scene's settings)."""

from __future__ import annotations

import argparse
import os

from vid2sim.cli.common import UserError, add_threads_option
from vid2sim.meshing.tetra import TetrahedralizationError
from vid2sim.synthetic.fem import FEMSolverError
from vid2sim.synthetic.independent import NewtonSolverError

_SCENE_OPTIONS = {  # CLI option → SyntheticSceneConfig field
    "E": "youngs_modulus", "nu": "poisson_ratio", "density": "density", "material": "material",
    "drop_height": "drop_height", "views": "views", "resolution": "resolution", "frames": "frames",
    "observed_frames": "observed_frames", "substeps": "substeps", "layout": "layout",
    "damping_ratio": "damping_ratio", "held_out_views": "held_out_views", "element_order": "element_order",
    "truth": "truth", "friction": "friction",
}


def scene_overrides(args: argparse.Namespace) -> dict:
    """The SyntheticSceneConfig fields given on the command line (make-benchmark has no --E / --nu)."""
    values = {field: getattr(args, opt, None) for opt, field in _SCENE_OPTIONS.items()}
    return {field: value for field, value in values.items() if value is not None}


def scene_config_error(exc: ValueError) -> UserError:
    """A SyntheticSceneConfig error with the command-line flag the user typed instead of the field's name."""
    message = str(exc)
    for opt, field in _SCENE_OPTIONS.items():
        flag = "--" + opt.replace("_", "-") if opt != "damping_ratio" else "--damping"
        message = message.replace(f"SyntheticSceneConfig.{field} ", f"{flag} ")
    return UserError(message)


def generation_errors() -> tuple[type[Exception], ...]:

    return (FEMSolverError, TetrahedralizationError, NewtonSolverError)


def add_scene_options(p: argparse.ArgumentParser, material_options: bool, default_element_order: int = 1) -> None:
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
    p.add_argument(
        "--element-order",
        type=int,
        choices=[1, 2],
        default=None,
        help="the FEM's tets: 1 linear or 2 quadratic (converged in space, the FEM about 20x slower); default "
        f"{default_element_order}"
        + (
            "; a suite's quadratic tets have the small preset's size at every preset"
            if default_element_order == 2
            else ""
        ),
    )
    p.add_argument("--truth", choices=["fem", "newton"], default=None,
                   help="the engine of the ground truth: fem (ours, the default) or newton (NVIDIA Newton's VBD "
                        "solver: another energy, contact and damping; needs pip install \"vid2sim[newton]\"; with "
                        "newton, --element-order 2 splits each tet into 8 linear ones)")
    p.add_argument("--friction", type=float, default=None,
                   help="the floor's Coulomb friction in the newton truth (default 0.5; the fem truth is frictionless)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="processes for the FEM's side-by-side time resolutions (default: 2, or 1 on a 1-CPU machine)")
    p.add_argument("--layout", choices=["rgba", "rgb+mask", "video"], default=None, help="scene folder layout")
    add_threads_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress output")

