"""``vid2sim reconstruct``: a scene folder in, a simulation-ready asset out (paper §4).

The stages (:mod:`vid2sim.reconstruct.stages`, one module each) run in order through
:func:`~vid2sim.reconstruct.runner.run_stages`: each saves its outputs in a work folder beside the output, so an
interrupted run resumes after its last finished stage, and the asset folder itself appears only when everything
is done.

Physics runs in the scene's metric frame: E in Pa is the real material if the scene's scale is metric and the
density right. A drop only identifies E/ρ; the density comes from ``scene.json`` ``metadata.density`` when
present, else ``prior.density`` (1000 kg/m³).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

from vid2sim.asset.folder import save_asset
from vid2sim.reconstruct.config import ReconstructConfig
from vid2sim.reconstruct.runner import (
    Context,
    Observed,
    ReconstructionError,
    StageSnapshots,
    State,
    WorkFolder,
    cache_keys,
    run_stages,
    scene_fingerprint,
)
from vid2sim.reconstruct.stages import STAGES, all_stages
from vid2sim.runtime.device import resolve_device
from vid2sim.scene.folder import Scene
from vid2sim.scene.reading import load_scene

__all__ = ["ReconstructConfig", "ReconstructionError", "STAGES", "check_scene", "reconstruct"]


def check_scene(scene: Scene) -> None:
    """Raise :class:`ReconstructionError` for what would make the reconstruction meaningless: fewer than 2
    observed frames, a view whose frame-0 mask is empty (named), an object touching the image border at frame 0
    in a view (named)."""
    V = scene.config.observed_views
    T = scene.config.observed_frames
    if len(T) < 2:
        raise ReconstructionError(f"{scene.root}: needs at least 2 observed frames, the scene lists {len(T)} "
                                  "(scene.json observed_frames)")
    if len(V) < 1:
        raise ReconstructionError(f"{scene.root}: no observed views (scene.json observed_views)")
    if T[0] != 0 or list(T) != list(range(len(T))):
        raise ReconstructionError(f"{scene.root}: observed_frames must be 0 … T−1 without gaps, got {list(T)}")
    for v in V:
        m = scene.masks[v, 0].float()
        if float(m.max()) <= 0.5:
            raise ReconstructionError(f"{scene.root}: the frame-0 mask of view {v} is empty: the camera does not "
                                      "see the object (fix the mask or drop the view from observed_views)")
        border = torch.cat([m[0], m[-1], m[:, 0], m[:, -1]])
        if float(border.max()) > 0.5:
            raise ReconstructionError(f"{scene.root}: the object touches the border of view {v} at frame 0; the "
                                      "visual hull needs it whole in every observed view")


def observed(scene: Scene, device: torch.device) -> Observed:
    """The scene's observed views and frames (:class:`~vid2sim.reconstruct.runner.Observed`)."""
    V, T = list(scene.config.observed_views), scene.config.observed_frames
    images_cpu, masks_cpu = scene.images[V][:, T].float(), scene.masks[V][:, T].float()
    cameras_cpu = [scene.cameras[v] for v in V]
    return Observed(images=images_cpu.to(device), masks=masks_cpu.to(device),
                    cameras=[c.to(device) for c in cameras_cpu], images_cpu=images_cpu, masks_cpu=masks_cpu,
                    cameras_cpu=cameras_cpu, views=V, frames=len(T), dt=float(scene.config.dt),
                    gravity=list(scene.config.gravity), floor_height=scene.config.floor_height)


def reconstruct(scene_path: str | Path, out: str | Path, config: ReconstructConfig | None = None,
                progress: bool = True, restart: bool = False, device: str | torch.device | None = None,
                snapshots: StageSnapshots | None = None, rerun_changed: bool = False,
                rollout_processes: int = 0) -> Path:
    """Reconstruct the scene folder ``scene_path`` into the asset folder ``out`` (see the module docstring).

    ``device`` (None: CUDA when available, else the CPU) runs the Gaussian fits, the networks' training and
    the joint optimisation; the geometric stages (points, initial velocity), Stage I and the continuation run on the
    CPU. The device is not part of the configuration: a run interrupted on one device resumes on another, and the
    asset is written with CPU tensors. While the stiffness calibration's tet reference runs in its child process (one
    thread), the stages run on one torch thread fewer than the caller's; the count is restored on return.

    ``snapshots`` shares stages with other reconstructions of this scene
    (:class:`~vid2sim.reconstruct.runner.StageSnapshots`): the run starts from the latest snapshot whose settings
    match and saves one when each stage it names finishes. ``log.json`` ``"restored"`` names the stage restored and
    the seconds its stages took where they ran (None when nothing was restored).

    An interrupted run in ``out``'s work folder resumes after its last finished stage when the settings agree up to
    it. ``restart`` discards it; ``rerun_changed`` keeps its finished stages up to the first whose settings differ
    and runs that one and the later ones again (``log.json`` ``"rerun"`` names them); otherwise a difference is
    refused (:class:`~vid2sim.reconstruct.runner.WorkFolder`).

    ``rollout_processes`` worker processes (spawned, one thread each) simulate the Gauss–Newton fit's Jacobian
    rollouts beside this process when the joint optimisation runs on the CPU
    (:class:`~vid2sim.reconstruct.rollouts.RolloutPool`); ``vid2sim reconstruct`` gives it its threads less one.
    0: every rollout in this process. The material differs by rounding only (the workers' thread count).

    Returns:
        the asset folder (readable with :func:`vid2sim.asset.load_asset`).
    Raises:
        vid2sim.scene.validation.SceneFormatError: the scene folder is invalid.
        ReconstructionError: the scene cannot be reconstructed as given, or ``out``'s work folder holds a run
        with other settings.
    """
    threads = torch.get_num_threads()
    cfg = config or ReconstructConfig()
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    out = Path(out)
    scene = load_scene(scene_path)
    check_scene(scene)
    stages = all_stages()
    work = WorkFolder(out, cache_keys(stages, cfg, scene_fingerprint(scene.root)), restart, snapshots, rerun_changed)
    ctx = Context(config=cfg, scene=scene, observed=observed(scene, dev), device=dev, work=work, progress=progress,
                  threads=threads, rollout_processes=rollout_processes)
    torch.manual_seed(cfg.seed)
    try:
        state = run_stages(stages, ctx, State())
    finally:
        torch.set_num_threads(threads)
    restored = None if work.restored is None else {
        "stage": work.restored, "seconds": sum(work.timings.get(s.name, 0.0)
                                                for s in stages[:STAGES.index(work.restored) + 1])}
    log = {"timings_seconds": work.timings, "restored": restored, "rerun": work.rerun, "device": str(dev),
           "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu", **state.log}
    save_asset(state.asset, out, config=cfg.to_dict(), log=log)
    shutil.rmtree(work.dir, ignore_errors=True)
    return out
