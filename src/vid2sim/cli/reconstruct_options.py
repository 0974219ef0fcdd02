"""The reconstruction's settings on the command line, shared by ``reconstruct``, ``bench suite`` and
``bench ablation``: ``--preset``, ``--config FILE`` and one flag per field of
:class:`~vid2sim.reconstruct.config.ReconstructConfig` (``--joint.iterations``, ``--networks.handles``, …, generated
by :mod:`vid2sim.runtime.config`), with short aliases for the common ones."""

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
    "--iterations": "joint.iterations", "--jacobian": "networks.jacobian", "--seed": "seed",
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

    configs.add_flags(p, ReconstructConfig, ALIASES, defaults=defaults,
                      group_title="reconstruction settings (each --section.field; docs/architecture.md)")


def reconstruct_config(args: argparse.Namespace) -> ReconstructConfig:
    """The configuration the options describe: the preset (or ``--config``'s file) with the flags on top. A
    checkpoint given with ``--predictor`` switches Stage I on unless ``--no-stage1`` says otherwise; the projected
    volumetric term takes one calibration factor ("curve") unless ``--calibration-nu`` says otherwise.

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
    try:
        if args.config is not None:
            base = ReconstructConfig.from_dict(read_json(args.config, "a reconstruction's config.json"))
            return configs.merge(base, overrides)
        return ReconstructConfig.preset(args.preset, overrides)
    except ConfigError as exc:
        raise UserError(configs.name_flags(str(exc), ReconstructConfig, ALIASES)) from exc
