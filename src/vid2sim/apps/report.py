"""An asset's HTML report with everything it shows computed: the evaluation, the renders in the scene's cameras
or in a ring of cameras (:mod:`vid2sim.report` renders what it is handed and computes nothing)."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from vid2sim.asset.folder import load_asset
from vid2sim.asset.motion import render_frames, simulate_gaussians
from vid2sim.evaluate.scores import evaluate
from vid2sim.report import ReportConfig, write_report
from vid2sim.report.inputs import read_evaluation
from vid2sim.report.scene_report import RingRenders, check_out
from vid2sim.runtime.device import resolve_device
from vid2sim.scene.folder import Scene
from vid2sim.scene.reading import load_scene
from vid2sim.splats.cameras import camera_ring


def ring_cameras(frames: Sequence[Any], config: ReportConfig) -> tuple[list[Any], list[float]]:
    """Cameras on a ring around the whole trajectory (the 2nd–98th percentile box of the Gaussian centres over
    all frames), far enough that it fits the 40° field of view; returns (cameras, azimuths in degrees)."""
    means = torch.cat([f.means.detach().reshape(-1, 3) for f in frames]).double()
    if means.shape[0] > 200_000:
        means = means[torch.randperm(means.shape[0], generator=torch.Generator().manual_seed(0))[:200_000]]
    lo, hi = torch.quantile(means, 0.02, dim=0), torch.quantile(means, 0.98, dim=0)
    centre, radius = (lo + hi) / 2, float((hi - lo).norm()) / 2
    radius = max(radius, 1e-3)
    fov = 40.0
    distance = 1.15 * radius / math.sin(math.radians(fov / 2))
    cams = camera_ring(config.ring_views, distance, config.ring_elevation_deg, config.ring_resolution,
                       config.ring_resolution, fov_x_deg=fov, target=tuple(float(c) for c in centre))
    return cams, [360.0 * i / config.ring_views for i in range(config.ring_views)]


def _same_folder(a: Any, b: Any) -> bool:
    try:
        return a is not None and b is not None and Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def ring_renders(asset_dir: Path, config: ReportConfig, progress: bool,
                 device: torch.device | str = "cpu") -> RingRenders:
    """The asset's own drop, ``config.ring_frames`` frames, simulated and rendered on ``device`` in a ring of
    ``config.ring_views`` cameras around its whole trajectory (the renders on the CPU)."""
    asset = load_asset(asset_dir, device)
    frames = simulate_gaussians(asset, config.ring_frames, progress=progress)
    cams, azimuths = ring_cameras(frames, config)
    cams = [c.to(device) for c in cams]
    observed = asset.extra.get("observed_frames")
    return RingRenders(render_frames(frames, cams, progress=progress).cpu(), azimuths, float(asset.dt),
                       int(observed) if isinstance(observed, int) else config.ring_frames)


def asset_report(out_dir: str | Path, asset: str | Path, scene: str | Path | Scene | None = None,
                 evaluation: Mapping[str, Any] | None = None, renders: Tensor | None = None, progress: bool = True,
                 config: ReportConfig | None = None, simulations: Sequence[str | Path] = (),
                 device: str | torch.device | None = None) -> Path:
    """:func:`vid2sim.report.write_report` of an asset with what is missing computed first.

    ``device`` (None: CUDA when available, else the CPU) runs the simulation and rendering of what is missing.

    With a scene and no ``evaluation``: the asset's ``evaluation.json`` when it was computed on that scene folder,
    else :func:`~vid2sim.evaluate.scores.evaluate` runs (and provides the renders); renders still missing are made
    by one simulation. Without a scene, the asset's drop is rendered in a ring of cameras.

    Returns:
        ``out_dir`` as a Path.
    """
    config = config or ReportConfig()
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    asset_dir = Path(asset)
    check_out(Path(out_dir))  # before any work
    timings: dict[str, float] = {}
    if scene is None:
        t0 = time.perf_counter()
        ring = ring_renders(asset_dir, config, progress, dev) if asset_dir.is_dir() else None
        timings["simulate and render (ring)"] = time.perf_counter() - t0
        return write_report(out_dir, asset_dir, evaluation=evaluation, ring=ring, progress=progress, config=config,
                            simulations=simulations, timings=timings)
    scene_obj = scene if isinstance(scene, Scene) else load_scene(scene, progress=progress) \
        if Path(scene).is_dir() else None
    scene_path = scene_obj.root if scene_obj is not None else Path(scene)
    stored = asset_dir / "evaluation.json"
    if evaluation is None and stored.is_file():
        candidate = read_evaluation(stored)
        if _same_folder(candidate.get("scene"), scene_path):
            evaluation = candidate
    if scene_obj is not None and asset_dir.is_dir():
        if renders is None and evaluation is None:
            t0 = time.perf_counter()
            evaluation, renders = evaluate(asset_dir, scene_path, progress=progress, return_renders=True,
                                           device=dev)
            timings["evaluate (simulate, render, score)"] = time.perf_counter() - t0
        elif renders is None:
            t0 = time.perf_counter()
            frames = simulate_gaussians(load_asset(asset_dir, dev), scene_obj.images.shape[1], progress=progress)
            renders = render_frames(frames, [c.to(dev) for c in scene_obj.cameras], progress=progress).cpu()
            timings["simulate and render"] = time.perf_counter() - t0
    return write_report(out_dir, asset_dir, scene=scene_obj if scene_obj is not None else scene, evaluation=evaluation,
                        renders=renders, progress=progress, config=config, simulations=simulations, timings=timings)
