"""The reconstruction's settings on the command line, shared by ``reconstruct``, ``bench suite`` and
``bench ablation``: ``--preset``, ``--config FILE`` and one flag per field of
:class:`~vid2sim.reconstruct.config.ReconstructConfig` (``--joint.method``, ``--networks.handles``, …, generated
by :mod:`vid2sim.runtime.config`), with short aliases for the common ones, and ``--iterations``: the joint
optimisation's iterations of whichever method it uses."""

from __future__ import annotations

import argparse
from pathlib import Path

from vid2sim.cli.common import UserError
from vid2sim.reconstruct.config import PRESETS, ReconstructConfig
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.files import read_json

#: short flag → the setting it sets
ALIASES = {
    "--jacobian": "networks.jacobian", "--seed": "seed",
    "--handles": "networks.handles", "--skinning-objective": "networks.skinning_objective",
    "--stage1": "stage1.enabled", "--predictor": "stage1.predictor",
    "--calibrate-stiffness": "calibration.enabled", "--calibration-nu": "calibration.nu",
    "--volumetric": "simulator.volumetric", "--mass": "simulator.mass", "--frame-rounds": "points.frame_rounds",
    "--sh-degree": "gaussians.sh_degree", "--motion-geometry": "motion_appearance.geometry",
    "--shading": "motion_appearance.shading", "--motion-loss-power": "motion_appearance.loss_power",
    "--centre-of-mass-step": "joint.centre_of_mass_step",
}


def add_reconstruct_options(p: argparse.ArgumentParser, default_preset: str = "small") -> None:
    """``--preset``, ``--config`` and the generated setting flags."""
    p.add_argument("--preset", choices=list(PRESETS), default=default_preset,
                   help=f"sizes: small (CPU minutes) or full (the paper's iterations); default {default_preset}")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="start from the settings of this config.json (an asset's: repeats its run) instead of the "
                        "preset; the flags below override it")
    presets = {name: configs.to_dict(ReconstructConfig.preset(name)) for name in PRESETS}

    def defaults(path: str) -> str:
        values = {}
        for name, tree in presets.items():
            value = tree
            for part in path.split("."):
                value = value[part]
            values[name] = value
        if len({repr(v) for v in values.values()}) == 1:
            return f"default {next(iter(values.values()))}"
        return ", ".join(f"{name} preset {value}" for name, value in values.items())

    group = p.add_argument_group("reconstruction settings (each --section.field; docs/architecture.md)")
    group.add_argument("--iterations", type=int, default=None, metavar="N",
                       help="the joint optimisation's iterations: Gauss-Newton steps (--joint.gauss_newton_iterations,"
                            " default 8) with the default method, Adam iterations (--joint.iterations; small preset "
                            "100, full 400) with --joint.method windows")
    configs.add_flags(group, ReconstructConfig, ALIASES, defaults=defaults)


def reconstruct_config(args: argparse.Namespace) -> ReconstructConfig:
    """The configuration the options describe: the preset (or ``--config``'s file) with the flags on top. A
    checkpoint given with ``--predictor`` switches Stage I on unless ``--no-stage1`` says otherwise; the projected
    volumetric term takes one calibration factor ("curve") unless ``--calibration-nu`` says otherwise.
    ``--iterations`` sets the iterations of the joint method the rest resolves to
    (:meth:`~vid2sim.reconstruct.config.JointConfig.with_iterations`).

    Raises:
        UserError: a bad value, naming the flag; a ``--config`` file that is not a configuration.
    """
    overrides = configs.flag_overrides(args)
    stage1 = overrides.get("stage1", {})
    if stage1.get("predictor") is not None:
        path = Path(stage1["predictor"])
        if not path.is_file():
            raise UserError(f"--predictor {path}: no such checkpoint file (train one with `vid2sim train-predictor`)")
        stage1["predictor"] = str(path.resolve())
        stage1.setdefault("enabled", True)  # a checkpoint given is a checkpoint to use
    simulator, calibration = overrides.get("simulator", {}), overrides.get("calibration", {})
    if simulator.get("volumetric") == "projected" and "nu" not in calibration:
        overrides.setdefault("calibration", {})["nu"] = "curve"  # the projected term does not lock: one factor
    iterations = getattr(args, "iterations", None)
    if iterations is not None:
        joint = overrides.get("joint", {})
        both = [f"--joint.{name}" for name in ("iterations", "gauss_newton_iterations") if name in joint]
        if both:
            raise UserError(f"--iterations and {both[0]} both set the joint optimisation's iterations: give one")
        if iterations < 0:
            raise UserError(f"--iterations must be >= 0, got {iterations}")
    try:
        if args.config is not None:
            base = ReconstructConfig.from_dict(read_json(args.config, "a reconstruction's config.json"))
            config = configs.merge(base, overrides)
        else:
            config = ReconstructConfig.preset(args.preset, overrides)
    except ConfigError as exc:
        raise UserError(configs.name_flags(str(exc), ReconstructConfig, ALIASES)) from exc
    if iterations is not None:
        config.joint = config.joint.with_iterations(iterations)
    return config
