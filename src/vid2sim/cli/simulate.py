"""``vid2sim simulate ASSET OUT``: simulate a reconstructed asset in a new situation (docs/scenarios.md).

The scenario comes from ``--scenario FILE.yaml`` and/or the options below (an option overrides the file's
field); with neither it is the captured drop. Every error names the flag, or the file and key, it came from.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vid2sim.cli.common import UserError, add_device_option, add_threads_option, set_threads
from vid2sim.physics.solver import SimulationError
from vid2sim.runtime.device import resolve_device
from vid2sim.simulate.run import OUTPUT_MARKERS, simulate
from vid2sim.simulate.scenario import Scenario

#: flag dest → (scenario field path, the flag as typed)
_SCALARS = {
    "frames": ("frames", "--frames"), "dt": ("dt", "--dt"), "resolution": ("resolution", "--resolution"),
    "material": ("material.preset", "--material"), "E": ("material.youngs_modulus", "--E"),
    "nu": ("material.poisson_ratio", "--nu"), "density": ("material.density", "--density"),
    "damping": ("material.damping_ratio", "--damping"), "model": ("material.model", "--model"),
    "yield_stress": ("material.yield_stress", "--yield-stress"),
    "friction_angle": ("material.friction_angle_deg", "--friction-angle"),
    "floor_height": ("floor.height", "--floor-height"), "floor_stiffness": ("floor.stiffness", "--floor-stiffness"),
    "floor_friction": ("floor.friction", "--floor-friction"),
    "floor_velocity": ("floor.velocity", "--floor-velocity"),
    "floor_amplitude": ("floor.amplitude", "--floor-amplitude"),
    "floor_frequency": ("floor.frequency", "--floor-frequency"), "floor_tilt": ("floor.tilt_deg", "--floor-tilt"),
    "floor_tilt_rate": ("floor.tilt_rate_deg", "--floor-tilt-rate"),
    "cameras": ("cameras.type", "--cameras"), "scene": ("cameras.scene", "--scene"),
    "views": ("cameras.views", "--views"), "camera_radius": ("cameras.radius", "--camera-radius"),
    "camera_height": ("cameras.height", "--camera-height"), "fov": ("cameras.fov_deg", "--fov"),
    "azimuth": ("cameras.azimuth_deg", "--azimuth"), "turns": ("cameras.turns", "--turns"),
}
#: flag dest → (scenario field path, the flag, accepted lengths, an example)
_VECTORS = {
    "floor_tilt_axis": ("floor.tilt_axis", "--floor-tilt-axis", (2, 3), "1,0"),
    "floor_pivot": ("floor.pivot_xy", "--floor-pivot", (2,), "0,0"),
    "rotation": ("initial.euler_deg", "--rotation", (3,), "0,0,90"),
    "axis_angle": ("initial.axis_angle", "--axis-angle", (4,), "0,0,1,45"),
    "translation": ("initial.translation", "--translation", (3,), "0,0,0.2"),
    "velocity": ("initial.linear_velocity", "--velocity", (3,), "0,0,-1"),
    "angular_velocity": ("initial.angular_velocity", "--angular-velocity", (3,), "0,0,3.14"),
    "camera_target": ("cameras.target", "--camera-target", (3,), "0,0,-0.4"),
}


def _numbers(text: str, flag: str, lengths: tuple[int, ...], example: str) -> tuple[float, ...]:
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) not in lengths or not all(v == v and abs(v) != float("inf") for v in values):
        counts = " or ".join(str(n) for n in lengths)
        raise UserError(f"{flag} {text!r}: expected {counts} comma-separated numbers, e.g. {flag} {example}")
    return values


def scenario_from_args(args: argparse.Namespace):
    """The :class:`~vid2sim.simulate.scenario.Scenario` of ``--scenario`` (or the captured drop) with the
    command-line options applied on top (each remembered as set by its flag)."""

    scenario = Scenario.from_yaml(args.scenario) if args.scenario else Scenario()
    for dest, (path, flag) in _SCALARS.items():
        value = getattr(args, dest, None)
        if value is not None:
            scenario.set(path, value, flag)
    for dest, (path, flag, lengths, example) in _VECTORS.items():
        text = getattr(args, dest, None)
        if text is not None:
            scenario.set(path, _numbers(text, flag, lengths, example), flag)
            if dest == "rotation":
                scenario.set("initial.axis_angle", None, flag)
            elif dest == "axis_angle":
                scenario.set("initial.euler_deg", None, flag)
    if args.no_floor:
        scenario.set("floor.enabled", False, "--no-floor")
    if args.obstacle:
        spheres = []
        for text in args.obstacle:
            x, y, z, r = _numbers(text, "--obstacle", (4,), "0,0,-0.5,0.1")
            spheres.append({"center": (x, y, z), "radius": r})
        scenario.set("obstacles", spheres, "--obstacle")
    if args.background is not None:
        bg = _numbers(args.background, "--background", (1, 3), "1 (white) or 0.2,0.2,0.2")
        scenario.set("background", bg[0] if len(bg) == 1 else bg, "--background")
    return scenario


def run(args: argparse.Namespace) -> int:


    set_threads(args.threads)
    device = resolve_device(args.device)  # a bad --device fails before any work
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise UserError(f"{out} exists; pass --overwrite to replace it")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and
                                               not any((out / m).exists() for m in OUTPUT_MARKERS))):
        raise UserError(f"{out} is not an earlier `vid2sim simulate` output (no scenario.yaml); refusing to replace it")
    scenario = scenario_from_args(args)
    scenario.validate()  # field errors before the asset is even loaded
    try:
        path = simulate(args.asset, scenario, out, progress=not args.quiet, video=not args.no_video,
                        ply=not args.no_ply, overwrite=args.overwrite,
                        scenery=not args.no_scenery, device=device)
    except SimulationError as exc:
        raise UserError(f"the simulation failed ({exc}); nothing was written to {out}") from exc

    summary = json.loads((path / "summary.json").read_text())
    phys, times = summary["physics"], summary["timings_seconds"]
    lines = [f"wrote {path}: {summary['frames']} frames x {len(summary['cameras'])} cameras "
             f"({summary['cameras'][0]['width']}x{summary['cameras'][0]['height']}), "
             f"material {summary['material']['preset']} (E = {summary['material']['E']:.4g} Pa, "
             f"nu = {summary['material']['nu']:.3f})",
             f"lowest point {phys['lowest_point_m']:.3f} m"
             + (f", floor penetration {phys['floor']['max_penetration_m'] * 1000:.1f} mm" if phys["floor"] else "")
             + "".join(f", obstacle {i} {'touched' if o['frames_in_contact'] else 'not touched'}"
                       f" (penetration {o['max_penetration_m'] * 1000:.1f} mm)"
                       for i, o in enumerate(phys["obstacles"])),
             f"time {times['total']:.1f} s: simulate {times['simulate']:.1f} s, render {times['render']:.1f} s, "
             f"write {times['write_frames'] + times['write_ply'] + times['write_videos']:.1f} s"]
    for note in summary["notes"]:
        lines.append(f"note: {note}")
    print("\n".join(lines))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` subcommand."""
    p = sub.add_parser(
        "simulate", help="simulate a reconstructed asset in a new situation (floor, obstacles, pose, material, "
        "cameras) and write frames, videos and a 3DGS PLY per frame",
        description="Simulate an asset (from `vid2sim reconstruct`) in a scenario: by default its captured drop; "
        "a YAML file (--scenario) and/or the options below change it (options override the file). Writes "
        "OUT/frames/<camera>/<t>.png, OUT/videos/<camera>.mp4 and .gif, OUT/ply/<t>.ply, states.npz, "
        "summary.json and the resolved scenario.yaml (docs/scenarios.md). Units: m, s, kg, Pa, degrees.")
    p.add_argument("asset", help="asset folder written by `vid2sim reconstruct`")
    p.add_argument("out", help="output folder to create")
    p.add_argument("--scenario", default=None, metavar="FILE.yaml", help="scenario file (docs/scenarios.md)")
    g = p.add_argument_group("time")
    g.add_argument("--frames", type=int, default=None,
                   help="frames written, the initial one included (default: the captured clip's)")
    g.add_argument("--dt", type=float, default=None, help="seconds per frame (default: the asset's)")
    g = p.add_argument_group("material")
    g.add_argument("--material", default=None, metavar="NAME",
                   help="elastic (the recovered material, default), plasticine (StVK + von Mises, yield 500 Pa), "
                        "sand (StVK + Drucker-Prager, 10 deg), soft (E 8000, nu 0.4), stiff (E 1e7, nu 0.49)")
    g.add_argument("--E", type=float, default=None, help="Young's modulus in Pa")
    g.add_argument("--nu", type=float, default=None, help="Poisson's ratio, -1 < nu < 0.5")
    g.add_argument("--density", type=float, default=None, help="kg/m^3")
    g.add_argument("--damping", type=float, default=None, help="damping ratio zeta >= 0")
    g.add_argument("--model", default=None, metavar="NAME", help="elastic energy: neo_hookean or stvk")
    g.add_argument("--yield-stress", type=float, default=None, help="plasticine's yield stress in Pa (default 500)")
    g.add_argument("--friction-angle", type=float, default=None, help="sand's friction angle in degrees (default 10)")
    g = p.add_argument_group("floor (default: the captured floor)")
    g.add_argument("--no-floor", action="store_true", help="no floor")
    g.add_argument("--floor-height", type=float, default=None, help="m, under the object at t = 0")
    g.add_argument("--floor-stiffness", type=float, default=None, help="Pa per metre of penetration")
    g.add_argument("--floor-friction", type=float, default=None,
                   help="Coulomb coefficient >= 0 (default: the asset's; 0: frictionless)")
    g.add_argument("--floor-velocity", type=float, default=None, help="vertical velocity, m/s")
    g.add_argument("--floor-amplitude", type=float, default=None, help="vertical oscillation amplitude, m")
    g.add_argument("--floor-frequency", type=float, default=None, help="vertical oscillation frequency, Hz")
    g.add_argument("--floor-tilt", type=float, default=None, help="tilt at t = 0, degrees")
    g.add_argument("--floor-tilt-rate", type=float, default=None, help="tilt rate, degrees/s")
    g.add_argument("--floor-tilt-axis", default=None, metavar="X,Y", help="horizontal tilt axis (default 1,0)")
    g.add_argument("--floor-pivot", default=None, metavar="X,Y",
                   help="the point the floor tilts about (default: under the object)")
    g = p.add_argument_group("obstacles")
    g.add_argument("--obstacle", action="append", default=None, metavar="X,Y,Z,R",
                   help="a fixed sphere (centre and radius in m); repeatable; replaces the file's obstacles")
    g = p.add_argument_group("initial state (default: the captured pose and velocity)")
    g.add_argument("--rotation", default=None, metavar="RX,RY,RZ",
                   help="rotate the object about its centre of mass: degrees about world x, then y, then z")
    g.add_argument("--axis-angle", default=None, metavar="AX,AY,AZ,DEG",
                   help="rotate the object about an axis through its centre of mass")
    g.add_argument("--translation", default=None, metavar="DX,DY,DZ", help="move the object, m")
    g.add_argument("--velocity", default=None, metavar="VX,VY,VZ", help="linear velocity, m/s")
    g.add_argument("--angular-velocity", default=None, metavar="WX,WY,WZ", help="angular velocity, rad/s")
    g = p.add_argument_group("cameras (default: the source scene's)")
    g.add_argument("--cameras", default=None, metavar="KIND",
                   help="scene (the source scene's cameras), ring (--views cameras around the object) or orbit "
                        "(one camera circling over the frames)")
    g.add_argument("--scene", default=None, metavar="FOLDER", help="use this scene folder's cameras")
    g.add_argument("--views", type=int, default=None, help="ring cameras (default 4)")
    auto = " (default: automatic, framing the whole motion)"
    g.add_argument("--camera-radius", type=float, default=None, help="ring/orbit horizontal distance, m" + auto)
    g.add_argument("--camera-height", type=float, default=None, help="ring/orbit height above the target, m" + auto)
    g.add_argument("--camera-target", default=None, metavar="X,Y,Z", help="point the ring/orbit looks at" + auto)
    g.add_argument("--fov", type=float, default=None, help="ring/orbit horizontal field of view, degrees (default 40)")
    g.add_argument("--azimuth", type=float, default=None, help="azimuth of the first ring/orbit camera, degrees")
    g.add_argument("--turns", type=float, default=None, help="orbit revolutions over the frames (default 1)")
    g.add_argument("--resolution", type=int, default=None,
                   help="image width in pixels (default: the source scene's, else 256)")
    g.add_argument("--background", default=None, metavar="G|R,G,B", help="background colour in [0, 1] (default 1)")
    g = p.add_argument_group("output")
    g.add_argument("--no-video", action="store_true", help="skip the mp4 and gif videos")
    g.add_argument("--no-ply", action="store_true", help="skip the per-frame PLY files")
    g.add_argument("--no-scenery", action="store_true", help="draw the object alone (by default the floor and the "
                   "sphere obstacles are drawn in the frames and videos)")
    g.add_argument("--overwrite", action="store_true", help="replace an earlier output folder")
    add_device_option(g, "the simulation and rendering")
    add_threads_option(g)
    g.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run, lock_output="out")  # one writer per OUT (runtime.locks)
