"""``vid2sim bench speed``: one JSON object of timings for the simulator, the renderer and the Stage I predictor."""

from __future__ import annotations

import platform
from typing import Any, Callable

import torch

from vid2sim.apps.bench import (
    joint_speed,
    modes_speed,
    physics_speed,
    predictor_speed,
    render_speed,
    training_speed,
)
from vid2sim.runtime.device import resolve_device
from vid2sim.runtime.errors import ConfigError


def _sections() -> dict[str, Callable[..., dict[str, Any]]]:

    return {"physics": physics_speed.run, "training": training_speed.run, "render": render_speed.run,
            "joint": joint_speed.run, "modes": modes_speed.run, "predictor": predictor_speed.run}


def run_speed_benchmark(
    device: str | None = None, sections: list[str] | None = None, quick: bool = False
) -> dict[str, Any]:
    """Run the named benchmark sections (all by default) and return their figures in one dict."""
    dev = resolve_device(device)
    available = _sections()
    names = list(available) if not sections else sections
    unknown = [n for n in names if n not in available]
    if unknown:
        raise ConfigError(f"unknown benchmark section(s) {unknown}; expected some of {sorted(available)}")
    result: dict[str, Any] = {
        "device": str(dev),
        "device_name": torch.cuda.get_device_name(dev)
        if dev.type == "cuda"
        else platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    for name in names:
        result.update(available[name](dev, quick=quick))
    return result
