"""``vid2sim simulate ASSET OUT``: simulate a reconstructed asset in a :class:`~vid2sim.simulate.scenario.Scenario`
and write what it looks like.

The scenario is checked against the asset first (:func:`~vid2sim.simulate.resolve.resolve_scenario`), so a
scenario that makes no sense fails before any simulation. Then the asset is simulated (``frames − 1`` video
frames after the initial state), its Gaussians are moved with the simulated state and rendered in every
camera, and the output folder is written (docs/scenarios.md)::

    OUT/
      scenario.yaml                 the scenario with every default filled in (re-runnable)
      summary.json                  what ran: material, externals, cameras, timings, contact and motion stats
      states.npz                    z (T, 12H), zdot (T, 12H), times (T,) [, Fp_inv (T, K, 3, 3) if plastic]
      frames/<camera>/<t:04d>.png   every camera, every frame
      videos/<camera>.mp4, .gif     one video per camera (unless video=False)
      ply/<t:04d>.ply               the deformed Gaussians per frame, standard 3DGS PLY (unless ply=False)

The folder is written next to its final name and renamed when complete, so a folder named like an output is
whole (or absent).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from vid2sim import __version__
from vid2sim.asset.folder import load_asset
from vid2sim.asset.motion import GaussianRig
from vid2sim.physics.external import Floor, MovingFloor, SphereObstacle
from vid2sim.runtime.device import resolve_device
from vid2sim.scene.video import write_video
from vid2sim.scene.writing import move_into_place
from vid2sim.simulate.cameras import CameraTrack
from vid2sim.simulate.resolve import ResolvedScenario, reframe, resolve_scenario
from vid2sim.simulate.scenario import Scenario
from vid2sim.simulate.scenery import concatenate, scenery_gaussians
from vid2sim.splats.deform import DeformedGaussians
from vid2sim.splats.ply import save_ply
from vid2sim.splats.render import render_gaussians

if TYPE_CHECKING:
    from vid2sim.asset.folder import Asset
    from vid2sim.physics.solver import SimState, Simulator
    from vid2sim.splats.cameras import Camera

__all__ = ["ScenarioRun", "run_scenario", "trajectory_stats", "simulate", "OUTPUT_MARKERS"]

#: files whose presence marks a folder as a ``vid2sim simulate`` output (so ``overwrite`` may replace it)
OUTPUT_MARKERS = ("scenario.yaml", "summary.json")
PNG_COMPRESS_LEVEL = 3
#: interior points (at most) behind the centre-of-mass and deformation figures of the summary
STATS_POINTS = 4000
#: the renderer's near plane (m)
NEAR_PLANE = 0.01


@dataclass
class ScenarioRun:
    """A simulated scenario.

    Attributes:
        resolved: the checked, concrete scenario.
        sim: the simulator that ran (the asset with the scenario's material and externals).
        states: ``frames`` states, the initial one first (times 0, dt, 2 dt, …).
        seconds: wall time of the rollout.
    """

    resolved: ResolvedScenario
    sim: "Simulator"
    states: list["SimState"]
    seconds: float


def _simulator(asset: "Asset", resolved: ResolvedScenario) -> "Simulator":
    cfg = replace(asset.sim_config, dt=resolved.dt)
    return replace(asset, sim_config=cfg).simulator(externals=list(resolved.externals), **resolved.material)


def run_scenario(asset: "Asset", resolved: ResolvedScenario, progress: bool = False) -> ScenarioRun:
    """Simulate ``resolved`` (from :func:`resolve_scenario`) on ``asset``: ``frames − 1`` frames after the
    initial state, without gradients, in the asset's ``SimConfig.dtype`` (float64 by default, whatever the precision
    the asset is stored in: in float32 Newton stalled on ordinary drops, docs/reliability.md)."""
    sim = _simulator(asset, resolved)
    with torch.no_grad():
        start = resolved.initial_state(sim)
        t0 = time.perf_counter()
        states = [start] + sim.rollout(start, resolved.frames - 1, progress=progress)
    return ScenarioRun(resolved, sim, states, time.perf_counter() - t0)


def _motion_cloud(asset: "Asset", run: ScenarioRun, points: int = 400) -> Tensor:
    """(T · ≤points, 3) positions of contact points (evenly strided) over every frame of the run."""
    contact = asset.contact_points.detach().to(run.sim.X.dtype)
    contact = contact[:: max(1, contact.shape[0] // points)]
    with torch.no_grad():
        return torch.cat([run.sim.positions(contact, s.z) for s in run.states]).double()


def _rigid_residual(reference: Tensor, x: Tensor) -> float:
    """RMS distance (m) of points x: (N, 3) from the best rigid motion of ``reference`` (N, 3) (Kabsch):
    how much the shape itself has changed."""
    a = reference - reference.mean(0)
    b = x - x.mean(0)
    U, _, Vh = torch.linalg.svd(b.T @ a)
    D = torch.ones(3, dtype=x.dtype, device=x.device)
    D[2] = torch.sign(torch.linalg.det(U @ Vh))
    R = (U * D) @ Vh
    return float(((a @ R.T - b) ** 2).sum(1).mean().sqrt())


def trajectory_stats(asset: "Asset", run: ScenarioRun) -> dict[str, Any]:
    """Per-frame and summary physics of a run (JSON-ready).

    Per frame: ``time`` (s), ``lowest_z`` (m, the lowest contact point), ``centre_of_mass`` (m, mean of the
    interior points; at most :data:`STATS_POINTS` of them, evenly strided), ``deformation_rms`` (m, RMS
    distance of the interior points from the best rigid motion of the initial shape: the shape change),
    ``floor_distance`` (m, the contact points' smallest signed distance to the floor, negative = penetration;
    None without a floor), ``obstacle_distance`` (the same per obstacle), ``newton_iterations``.
    """

    sim, states = run.sim, run.states
    floor = next((e for e in run.resolved.externals if isinstance(e, (Floor, MovingFloor))), None)
    spheres = [e for e in run.resolved.externals if isinstance(e, SphereObstacle)]
    interior = asset.points.detach().to(sim.X.dtype)
    interior = interior[:: max(1, interior.shape[0] // STATS_POINTS)]
    contact = asset.contact_points.detach().to(sim.X.dtype)
    per: dict[str, list] = {"time": [], "lowest_z": [], "centre_of_mass": [], "deformation_rms": [],
                            "floor_distance": [], "obstacle_distance": [], "newton_iterations": []}
    reference = None
    with torch.no_grad():
        for s in states:
            xi = sim.positions(interior, s.z).double()
            xc = sim.positions(contact, s.z).double()
            reference = xi if reference is None else reference
            per["time"].append(float(s.t))
            per["lowest_z"].append(float(xc[:, 2].min()))
            per["centre_of_mass"].append(xi.mean(0).tolist())
            per["deformation_rms"].append(_rigid_residual(reference, xi))
            per["floor_distance"].append(None if floor is None else float(floor.signed_distance(xc, float(s.t)).min()))
            per["obstacle_distance"].append([float(o.signed_distance(xc).min()) for o in spheres])
            per["newton_iterations"].append(int(s.newton_iterations))

    def contact_summary(distances: list[float]) -> dict[str, Any]:
        touching = [t for t, d in enumerate(distances) if d < 0]
        return {"min_distance_m": min(distances), "max_penetration_m": max(0.0, -min(distances)),
                "frames_in_contact": len(touching), "first_contact_frame": touching[0] if touching else None}

    com = per["centre_of_mass"]
    summary: dict[str, Any] = {
        "lowest_point_m": min(per["lowest_z"]),
        "floor": None if floor is None else {**floor.to_dict(), **contact_summary(per["floor_distance"])},
        "obstacles": [{**o.to_dict(), **contact_summary([d[i] for d in per["obstacle_distance"]])}
                      for i, o in enumerate(spheres)],
        "centre_of_mass_start_m": com[0], "centre_of_mass_end_m": com[-1],
        "displacement_m": [b - a for a, b in zip(com[0], com[-1])],
        "deformation_rms_end_m": per["deformation_rms"][-1], "deformation_rms_max_m": max(per["deformation_rms"]),
        "newton_iterations_total": sum(per["newton_iterations"]),
        "all_converged": all(bool(s.converged) for s in states),
    }
    return {"summary": summary, "per_frame": per}


def _to_uint8(rgb: Tensor) -> np.ndarray:
    return (rgb.detach().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def _in_view(means: Tensor, camera: "Camera") -> bool:
    """Whether any Gaussian centre (N, 3) lies in front of ``camera`` (beyond its near plane), inside its image."""
    pix, depth = camera.project(means)
    ok = ((depth > NEAR_PLANE) & (pix[:, 0] >= 0) & (pix[:, 0] < camera.width) & (pix[:, 1] >= 0)
          & (pix[:, 1] < camera.height))
    return bool(ok.any())


def _render(d: Any, cameras: list["Camera"], background: Any) -> list[np.ndarray]:
    """uint8 images (H, W, 3) of the deformed Gaussians ``d`` in ``cameras`` (one size); a camera the object
    has left shows the background."""

    return list(_to_uint8(render_gaussians(d, cameras, background=background, near_plane=NEAR_PLANE).rgb))


def _write_gif(path: Path, frames: list[np.ndarray], dt: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=max(20, round(1000.0 * dt)), loop=0)


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists():
        if not overwrite:
            raise FileExistsError(f"{out} exists; pass --overwrite (overwrite=True) to replace it")
        if not out.is_dir() or (any(out.iterdir()) and not any((out / m).exists() for m in OUTPUT_MARKERS)):
            raise FileExistsError(f"{out} is not an earlier `vid2sim simulate` output (no scenario.yaml); "
                                  "refusing to replace it")


def simulate(asset: "Asset | str | Path", scenario: Scenario | None, out: str | Path, progress: bool = True, *,
             video: bool = True, ply: bool = True, overwrite: bool = False, scenery: bool = True,
             device: str | torch.device | None = None) -> Path:
    """Simulate ``asset`` (an :class:`~vid2sim.asset.folder.Asset` or its folder) in ``scenario`` (None: the
    captured drop) and write the output folder ``out`` (module docstring); returns ``out``.

    ``device`` (None: CUDA when available, else the CPU) is where an asset given as a folder is loaded, and so
    where it is simulated and rendered; a loaded asset runs on its own device.

    ``scenery`` draws the floor and the sphere obstacles in the frames and videos
    (:mod:`vid2sim.simulate.scenery`); the PLY files hold the object alone.

    Everything about the scenario is checked before any simulation (:class:`ScenarioError`); an existing
    ``out`` is replaced only with ``overwrite`` and only if it is an earlier output.
    """
    t_start = time.perf_counter()
    out = Path(out)
    asset_path = None
    if not hasattr(asset, "simulator"):
        asset_path = str(asset)
        asset = load_asset(asset, device if isinstance(device, torch.device) else resolve_device(device))
    _check_out(out, overwrite)
    resolved = resolve_scenario(asset, scenario if scenario is not None else Scenario())
    timings: dict[str, float] = {"load_and_check": time.perf_counter() - t_start}

    run = run_scenario(asset, resolved, progress=progress)
    timings["simulate"] = run.seconds
    patch = _frame_the_motion(asset, run, timings)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        frames, out_of_view = _write_frames(tmp, asset, run, patch if scenery else None, progress, video, ply,
                                            timings)
        _note_out_of_view(resolved, out_of_view, len(run.states))
        t0 = time.perf_counter()
        if video:
            _write_videos(tmp, resolved.tracks, frames, resolved.dt)
        timings["write_videos"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        _write_states(tmp / "states.npz", run.states)
        resolved.scenario.to_yaml(tmp / "scenario.yaml")
        stats = trajectory_stats(asset, run)
        timings["write_states_and_stats"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start
        summary = _summary(asset, asset_path, resolved, run, stats, timings, video, ply)
        for cam in summary["cameras"]:
            cam["frames_out_of_view"] = out_of_view[cam["name"]]
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        move_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _frame_the_motion(asset: "Asset", run: ScenarioRun, timings: dict[str, float]) -> tuple[list[float], float]:
    """Re-place automatic ring/orbit cameras to follow the whole motion, not only t = 0 (timed in ``timings``),
    and return where the floor is drawn: the patch's centre (x, y) and half side (m) around the motion."""
    cloud = _motion_cloud(asset, run)
    if run.resolved.auto_framing:  # automatic ring/orbit cameras follow the whole motion, not only t = 0
        t0 = time.perf_counter()
        reframe(run.resolved, cloud)
        timings["frame_cameras"] = time.perf_counter() - t0
    lo, hi = cloud.min(0).values, cloud.max(0).values
    patch_centre = (0.5 * (lo + hi))[:2].tolist()
    patch_half = 1.5 * float((hi - lo)[:2].max()) + 0.5 * float((hi - lo).norm())  # the floor drawn around the motion
    return patch_centre, patch_half


def _write_frames(tmp: Path, asset: "Asset", run: ScenarioRun, patch: tuple[list[float], float] | None,
                  progress: bool, video: bool, ply: bool, timings: dict[str, float]
                  ) -> tuple[list[list[np.ndarray]], dict[str, list[int]]]:
    """Render every state of ``run`` in every camera track and write ``tmp``/frames/<camera>/<t:04d>.png (and,
    with ``ply``, ``tmp``/ply/<t:04d>.ply of the object alone).

    ``patch`` (the floor's centre (x, y) and half side, :func:`_frame_the_motion`) draws the floor and obstacles
    too; None draws the object alone. Adds the render / write_frames / write_ply times to ``timings``.

    Returns:
        the uint8 images (H, W, 3) of each track, frame by frame (kept only with ``video``), and per camera name
        the frames where no Gaussian centre of the object is in view.
    """
    from PIL import Image
    from tqdm.auto import tqdm

    resolved = run.resolved
    tracks = resolved.tracks
    for tr in tracks:
        (tmp / "frames" / tr.name).mkdir(parents=True)
    if ply:
        (tmp / "ply").mkdir()
    frames: list[list[np.ndarray]] = [[] for _ in tracks]
    out_of_view: dict[str, list[int]] = {tr.name: [] for tr in tracks}
    t_render = t_png = t_ply = 0.0
    with torch.no_grad():
        rig = GaussianRig(run.sim, asset.gaussians, asset.shading)
        basis = rig.basis()
        bg = resolved.background if isinstance(resolved.background, float) else list(resolved.background)
        for t, state in enumerate(tqdm(run.states, desc="render", unit="frame", disable=not progress,
                                       leave=False)):
            t0 = time.perf_counter()
            d = rig.deformed(state.z, basis)
            shown = d if patch is None else _with_scenery(d, resolved.externals, float(state.t), patch)
            images = _render_tracks(shown, tracks, t, bg)
            for tr in tracks:
                if not _in_view(d.means, tr.at(t)):
                    out_of_view[tr.name].append(t)
            t1 = time.perf_counter()
            for k, tr in enumerate(tracks):
                Image.fromarray(images[k]).save(tmp / "frames" / tr.name / f"{t:04d}.png",
                                                compress_level=PNG_COMPRESS_LEVEL)
                if video:
                    frames[k].append(images[k])
            t2 = time.perf_counter()
            if ply:
                save_ply(d.to_gaussians(), tmp / "ply" / f"{t:04d}.ply")
            t3 = time.perf_counter()
            t_render += t1 - t0
            t_png += t2 - t1
            t_ply += t3 - t2
    timings["render"] = t_render
    timings["write_frames"] = t_png
    timings["write_ply"] = t_ply
    return frames, out_of_view


def _with_scenery(d: DeformedGaussians, externals: list, t: float, patch: tuple[list[float], float]
                  ) -> DeformedGaussians:
    """The object's Gaussians ``d`` with the floor (a patch centred at ``patch[0]`` (x, y), half side ``patch[1]``)
    and the sphere obstacles among ``externals`` at time ``t`` (s) drawn as surface Gaussians."""
    extra = scenery_gaussians(externals, t, patch[0], patch[1], sh_bases=d.sh.shape[1], dtype=d.means.dtype,
                              device=d.means.device)
    return d if extra is None else concatenate([d, extra])


def _render_tracks(shown: DeformedGaussians, tracks: list[CameraTrack], t: int, bg: Any) -> dict[int, np.ndarray]:
    """uint8 images (H, W, 3) of ``shown`` at frame ``t``, by track index: the fixed cameras in one batch, then
    each moving (orbit) camera."""
    fixed = [k for k, tr in enumerate(tracks) if len(tr.cameras) == 1]
    moving = [k for k, tr in enumerate(tracks) if len(tr.cameras) > 1]
    images: dict[int, np.ndarray] = {}
    if fixed:
        images.update(zip(fixed, _render(shown, [tracks[k].at(t) for k in fixed], bg)))
    for k in moving:
        images[k] = _render(shown, [tracks[k].at(t)], bg)[0]
    return images


def _note_out_of_view(resolved: ResolvedScenario, out_of_view: dict[str, list[int]], frames: int) -> None:
    """Note in ``resolved.notes`` each camera that lost the object (``out_of_view``: its frames without it)."""
    for name, lost in out_of_view.items():
        if lost:
            resolved.notes.append(f"camera {name}: no Gaussian centre in view in {len(lost)} of "
                                  f"{frames} frames (first {lost[0]}); set the cameras' radius / "
                                  "target to follow the object")


def _write_videos(tmp: Path, tracks: list[CameraTrack], frames: list[list[np.ndarray]], dt: float) -> None:
    """``tmp``/videos/<camera>.mp4 and .gif of each track's images (H, W, 3) uint8, ``dt`` s per frame."""
    (tmp / "videos").mkdir()
    for k, tr in enumerate(tracks):
        write_video(tmp / "videos" / f"{tr.name}.mp4", np.stack(frames[k]), fps=1.0 / dt)
        _write_gif(tmp / "videos" / f"{tr.name}.gif", frames[k], dt)


def _write_states(path: Path, states: list["SimState"]) -> None:
    """``states.npz``: z (T, 12H), zdot (T, 12H), times (T,) [, Fp_inv (T, K, 3, 3) when plastic]."""
    arrays = {"z": torch.stack([s.z for s in states]).cpu().numpy(),
              "zdot": torch.stack([s.zdot for s in states]).cpu().numpy(),
              "times": np.array([s.t for s in states], dtype=np.float64)}
    if states[0].Fp_inv is not None:
        arrays["Fp_inv"] = torch.stack([s.Fp_inv for s in states]).cpu().numpy()
    np.savez(path, **arrays)


def _summary(asset: "Asset", asset_path: str | None, resolved: ResolvedScenario, run: ScenarioRun,
             stats: dict[str, Any], timings: dict[str, float], video: bool, ply: bool) -> dict[str, Any]:

    m = resolved.material
    plasticity = m["plasticity"]
    return {
        "vid2sim": __version__,
        "asset": asset_path,
        "scenario": resolved.scenario.to_dict(),
        "notes": resolved.notes,
        "frames": resolved.frames,
        "simulated_frames": resolved.frames - 1,
        "dt": resolved.dt,
        "substeps": run.sim.substeps(),
        "material": {"preset": resolved.scenario.material.preset, "model": m["model"], "E": m["youngs_modulus"],
                     "nu": m["poisson_ratio"], "density": m["density"], "damping_ratio": m["damping_ratio"],
                     "plasticity": None if plasticity is None else plasticity.to_dict()},
        "externals": [e.to_dict() for e in resolved.externals],
        "initial_state": {"rotation": resolved.rotation.tolist(), "translation_m": resolved.translation.tolist(),
                          "centre_of_mass_m": resolved.centre.tolist(),
                          "linear_velocity_m_s": resolved.linear_velocity,
                          "angular_velocity_rad_s": resolved.angular_velocity,
                          "velocity_centre_m": resolved.velocity_centre},
        "cameras": [{"name": tr.name, "width": tr.cameras[0].width, "height": tr.cameras[0].height,
                     "moving": len(tr.cameras) > 1, "fl_x": float(tr.cameras[0].K[0, 0]),
                     "fl_y": float(tr.cameras[0].K[1, 1]), "cx": float(tr.cameras[0].K[0, 2]),
                     "cy": float(tr.cameras[0].K[1, 2]),
                     "transform_matrix": [c.to_nerf().tolist() for c in tr.cameras] if len(tr.cameras) > 1
                     else tr.cameras[0].to_nerf().tolist()} for tr in resolved.tracks],
        "gaussians": asset.gaussians.num,
        "timings_seconds": timings,
        "physics": stats["summary"],
        "per_frame": stats["per_frame"],
        "files": {"frames": "frames/<camera>/<t:04d>.png",
                  "videos": [f"videos/{tr.name}.{ext}" for tr in resolved.tracks for ext in ("mp4", "gif")]
                  if video else [],
                  "ply": "ply/<t:04d>.ply" if ply else None, "states": "states.npz", "scenario": "scenario.yaml"},
    }
