"""``vid2sim evaluate ASSET SCENE``: how well an asset reproduces and predicts a scene (paper Tables 1–4).

The asset is simulated from its captured initial state over all of the scene's frames (after the observed frames
from the state its continuation fitted to their end, when it has one: :func:`~vid2sim.asset.motion.simulate_states`)
and its Gaussians are rendered in every camera. Reported (means, and per frame):

* ``dynamic`` — observed views, observed frames 1 … T_obs−1 (dynamic reconstruction);
* ``future`` — observed views, held-out frames (future state prediction); ``starts_from`` says where their
  simulation starts: ``"frame 0"``, or ``"continuation"`` (the state fitted to the last observed frames).
  ``future_from_start`` scores the same frames simulated in the one rollout from frame 0 (the paper's prediction;
  ``future`` itself where the asset has no continuation), and ``continuation`` is the reconstruction's record of
  its check (whether it was used, and why);
* ``novel_views`` — held-out views, all frames 1 … T−1;
* ``rest`` — observed views, frame 0: the asset at rest, the look every new simulation starts from. The frame-0
  Gaussian fit renders these views at 40–45 dB on the full preset's scenes; the last stage, which refits the
  Gaussians along the simulated motion, trades some of that for the later frames (docs/results.md);
* each as PSNR and SSIM (3DGS-lineage SSIM, window 11, σ = 1.5), and FoVVDP (JOD) when asked and the
  optional ``pyfvvdp`` is installed (its display model is named in the output);
* with ground truth in the scene: the absolute errors of log10 E and ν, the Chamfer distance (m) of the
  simulated Gaussian centres to the ground-truth surface (the ``tet_trajectory`` extra) per frame, and the
  distance (m) between the simulated body's centre of mass and the truth's per frame (``centre_of_mass``: the
  part of the motion error a wrong start or bounce leaves, whatever the shape; ``frame_0`` is the reconstructed
  body's own error, its mass distribution's, before any motion);
* with that truth, the contacts (``orientation``, ``contacts``: :func:`contact_errors`): the angle between the
  simulated body's rotation from frame 0 and the truth's per frame, and for each of the truth's contacts with the
  floor the centre-of-mass and rotation errors on the frames just before and after it — what each bounce adds to
  the motion's error — with the frames of the simulated body's own contacts beside them;
* the material Stage II started from (the documented prior, or Stage I's prediction) with its own errors
  (``material.start``, :func:`start_material`): the baseline that says whether the fit improved on its start;
* the material's intervals and identifiability as ``reconstruct`` reported them (``material.uncertainty``, from
  ``material.json``), with the truth: whether each interval holds it (``material.interval_covers_truth``, 1.0 or
  0.0, so that a suite's mean is the intervals' coverage); and the joint optimisation's validation loss at its
  start and at the kept state (``material.fit``, :func:`joint_fit_record`);
* with the truth's mesh in the scene and the stiffness calibration's record in the asset: the reconstructed
  solid's lowest elastic frequency against the truth's (``geometry_stiffness``, :func:`solid_stiffness`). At a
  fixed ν every frequency scales as √(E/ρ), so a solid whose lowest mode is r times the truth's vibrates like the
  truth with E r² too large, and a fit of a free vibration gives E r² too low: −2 log10 r is the log10 E offset
  its shape implies. A hull that fills the crevices between an object's lobes is stiffer than the object; the
  offset explained such a scene's error, not a soft object's, whose motion is its squash at the contact
  (docs/results.md): it scores the geometry, it is not a correction;
* with the truth's mesh: the simulation solid against the truth's body at frame 0 (``solid``,
  :func:`solid_against_truth`): its volume's ratio, the share of it outside the object, and how far its lowest
  and highest points reach past the object's along gravity. The bottom decides the first contact, and with it
  the bounce that E is fitted to: a hull 2 cm too deep below a stiff object was fitted 0.86 decade soft, and
  0.24 decade stiff with that wedge cut away (docs/results.md).

The simulation and the rendering are two reusable steps, :func:`simulate_gaussians` (the asset's captured
drop as deformed Gaussians per frame) and :func:`render_frames` (those in any cameras); ``evaluate(...,
return_renders=True)`` also hands back the renders it scored, so that ``vid2sim report`` shows exactly them.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from vid2sim.asset.folder import Asset, load_asset
from vid2sim.asset.motion import (
    deform_states,
    render_frames,
    simulate_states,
    simulated_centre_of_mass,
    true_motion_gaussians,
)
from vid2sim.meshing.tetra import tet_volumes
from vid2sim.metrics.contacts import motion_around_contacts
from vid2sim.metrics.fvvdp import fovvdp as fovvdp_score
from vid2sim.metrics.geometry import boundary_faces, material_errors, surface_chamfer
from vid2sim.metrics.images import image_metrics
from vid2sim.metrics.trajectory import tet_centre_of_mass
from vid2sim.physics.solver import SimState, Simulator
from vid2sim.physics.tet_modes import tet_frequency_curve
from vid2sim.runtime.device import resolve_device
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.jsonvalues import is_number
from vid2sim.scene.folder import SceneConfig
from vid2sim.scene.reading import load_scene
from vid2sim.splats.cameras import Camera
from vid2sim.synthetic.embedding import inside_tets


def _group(renders: torch.Tensor, targets: torch.Tensor, views: list[int], frames: list[int]) -> dict[str, Any]:

    if not views or not frames:
        return {}
    r = renders[views][:, frames]
    t = targets[views][:, frames]
    m = image_metrics(r, t, layout="VT")
    return {"views": views, "frames": frames, "psnr": m["psnr"], "ssim": m["ssim"],
            "psnr_per_frame": m["psnr_per_frame"], "ssim_per_frame": m["ssim_per_frame"]}


def scene_groups(renders: torch.Tensor, targets: torch.Tensor, config: Any) -> dict[str, dict[str, Any]]:
    """The three scores of the module docstring for renders of every camera and frame of a scene.

    Args:
        renders, targets: (V, T, H, W, 3) in [0, 1] (the scene folder's order).
        config: the scene's :class:`~vid2sim.scene.folder.SceneConfig` (its observed / held-out views and frames).

    Returns:
        ``{"dynamic": …, "future": …, "novel_views": …, "rest": …}``, each with ``views``, ``frames``, ``psnr``,
        ``ssim`` and their per-frame lists (empty when the scene has no such views or frames).
    """
    T = renders.shape[1]
    obs_v, held_v = list(config.observed_views), list(config.held_out_views)
    obs_f, held_f = list(config.observed_frames), list(config.held_out_frames)
    return {"dynamic": _group(renders, targets, obs_v, [f for f in obs_f if f > 0]),
            "future": _group(renders, targets, obs_v, held_f),
            "novel_views": _group(renders, targets, held_v, list(range(1, T))),
            "rest": _group(renders, targets, obs_v, [0])}


def _future_from_start(asset: Asset, cameras: list[Camera], targets: Tensor, config: SceneConfig,
                       progress: bool) -> dict[str, Any]:
    """The ``future`` group (observed views, held-out frames) of the asset's one rollout from frame 0."""
    T = targets.shape[1]
    sim, states = simulate_states(asset, T, progress=progress, continued=False)
    views, frames = list(config.observed_views), list(config.held_out_frames)
    deformed = deform_states(asset, sim, [states[t] for t in frames], progress=progress)
    renders = render_frames(deformed, [cameras[v] for v in views], background=1.0, progress=progress).cpu()
    m = image_metrics(renders, targets[views][:, frames], layout="VT")
    return {"views": views, "frames": frames, "starts_from": "frame 0", "psnr": m["psnr"], "ssim": m["ssim"],
            "psnr_per_frame": m["psnr_per_frame"], "ssim_per_frame": m["ssim_per_frame"]}


def start_material(asset_path: str | Path) -> dict[str, Any] | None:
    """The material ``reconstruct``'s Stage II started from: Stage I's prediction when it ran (``log.json``
    ``stage1``), else the prior of ``config.json`` (``prior.E``, ``prior.nu``; ``prior_E``, ``prior_nu`` in assets
    written before the configuration was nested).

    Returns:
        {"E", "log10_E", "nu", "source": "stage1" | "prior"}, or None for an asset without those records (one
        not written by ``reconstruct``).

    Raises:
        ValueError naming the file when a record is there but unreadable or lacks E or ν.
    """
    import math

    folder = Path(asset_path)
    log_path, config_path = folder / "log.json", folder / "config.json"
    try:
        stage1 = json.loads(log_path.read_text()).get("stage1") if log_path.is_file() else None
        if isinstance(stage1, dict) and stage1.get("ran"):
            E, nu, source, where = stage1.get("E"), stage1.get("nu"), "stage1", log_path
        elif config_path.is_file():
            config = json.loads(config_path.read_text())
            prior = (
                config.get("prior")
                if isinstance(config.get("prior"), dict)
                else {"E": config.get("prior_E"), "nu": config.get("prior_nu")}
                if "prior_E" in config or "prior_nu" in config
                else None
            )
            if prior is None:
                return None
            E, nu, source, where = prior.get("E"), prior.get("nu"), "prior", config_path
        else:
            return None
    except (OSError, json.JSONDecodeError, AttributeError) as exc:
        raise InputError(f"{folder}: cannot read the start material from log.json / config.json ({exc})") from exc
    numbers = is_number(E) and is_number(nu)
    if not (numbers and E > 0):
        raise InputError(f"{where}: the {source} material needs E > 0 and nu as numbers, got E={E!r}, nu={nu!r}")
    return {"E": float(E), "log10_E": math.log10(float(E)), "nu": float(nu), "source": source}


def interval_coverage(uncertainty: dict[str, Any], truth: dict[str, float]) -> dict[str, float]:
    """1.0 where the material's interval (``material.json`` ``uncertainty``, docs/asset-format.md) holds the true
    value, 0.0 where it does not, for each of ``truth``'s keys the record has an interval for (numbers, so that a
    suite's mean is the coverage)."""
    out = {}
    for name, value in truth.items():
        entry = uncertainty.get(name)
        interval = entry.get("interval") if isinstance(entry, dict) else None
        if isinstance(interval, (list, tuple)) and len(interval) == 2:
            out[name] = float(interval[0] <= value <= interval[1])
    return out


def joint_fit_record(extra: dict[str, Any]) -> dict[str, Any] | None:
    """The joint optimisation's validation losses from an asset's ``extra`` (asset.json): ``start_validation_loss``
    (the coarse search's start), ``validation_loss`` (the kept state's) and ``improved`` (1.0 when the kept state is
    lower than the start, 0.0 otherwise), or None for an asset that does not record both."""
    start, kept = extra.get("start_validation_loss"), extra.get("validation_loss")
    if not (is_number(start) and is_number(kept)):
        return None
    return {"start_validation_loss": float(start), "validation_loss": float(kept), "improved": float(kept < start),
            "method": extra.get("joint_method")}


def evaluate(asset_path: str | Path, scene_path: str | Path, fovvdp: bool = False,
             display: str = "standard_4k", progress: bool = True, return_renders: bool = False,
             true_motion: bool = False, device: str | torch.device | None = None) -> Any:
    """Evaluate the asset at ``asset_path`` on the scene folder ``scene_path`` (see the module docstring).

    ``device`` (None: CUDA when available, else the CPU) runs the simulation and the rendering; the scores are
    computed on the CPU.

    Returns:
        a JSON-ready dict: ``dynamic``, ``future``, ``novel_views`` (each ``psnr``, ``ssim``, per-frame lists,
        optionally ``fovvdp``), ``material`` (fitted, truth, errors when known; ``start``: Stage II's starting
        material and its errors, :func:`start_material`; ``uncertainty``, ``interval_covers_truth`` and ``fit``
        when the asset records them), ``chamfer``, ``centre_of_mass`` and ``orientation`` (per frame and means over
        observed and future frames) and ``contacts``, when the scene has a ``tet_trajectory``; with that
        truth also ``solid`` (:func:`solid_against_truth`) and, for a calibrated asset, ``geometry_stiffness``,
        and ``timing``.
        With ``return_renders=True``: the pair (that dict, the renders (V, T, H, W, 3) in [0, 1] it scored,
        every scene camera and frame).
    """
    t0 = time.perf_counter()
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    asset = load_asset(asset_path, dev)
    scene = load_scene(scene_path)
    cameras = [c.to(dev) for c in scene.cameras]
    if abs(float(scene.config.dt) - asset.dt) > 1e-6 * asset.dt:
        raise InputError(f"{scene_path}: frame time {scene.config.dt} s differs from the asset's {asset.dt} s")
    T = scene.images.shape[1]
    sim, states = simulate_states(asset, T, progress=progress)
    deformed = deform_states(asset, sim, states, progress=progress)
    centres = [d.means.cpu() for d in deformed]
    renders = render_frames(deformed, cameras, background=1.0, progress=progress).cpu()  # (V, T, H, W, 3)
    targets = scene.images.float()
    report: dict[str, Any] = {"asset": str(asset_path), "scene": str(scene_path),
                              **scene_groups(renders, targets, scene.config)}
    continued = asset.continuation is not None and T > asset.continuation["from_frame"]
    if report["future"]:
        report["future"]["starts_from"] = "continuation" if continued else "frame 0"
        report["future_from_start"] = _future_from_start(asset, cameras, targets, scene.config, progress) \
            if continued else report["future"]
    record = asset.extra.get("continuation")
    if record is not None:  # the check's decision and losses (its fit's wall time left out: not a score)
        check = record.get("check")
        report["continuation"] = {"used": record.get("used"), "check": None if check is None else {
            k: check.get(k) for k in ("frame", "predicted_frames", "loss_continued", "loss_single")}}
    if fovvdp:
        _add_fovvdp(report, renders, targets, scene.config, display)
    report["material"] = _material_record(asset, asset_path, scene.config.metadata)
    tet = scene.extras.get("tet_trajectory")
    if tet is not None:
        report.update(_motion_errors(tet, centres, sim, states, scene.config))
        meta_nu = scene.config.metadata.get("nu")
        nu = float(meta_nu) if is_number(meta_nu) else float(asset.material["nu"])
        stiffness = solid_stiffness(asset_path, tet, nu)
        if stiffness is not None:
            report["geometry_stiffness"] = stiffness
        solid = solid_against_truth(asset, tet)
        if solid is not None:
            report["solid"] = solid
    if true_motion:
        report["true_motion"] = _true_motion(asset, tet, targets, cameras, scene.config, scene_path, progress)
    report["timing"] = {"seconds": time.perf_counter() - t0}
    if return_renders:
        return report, renders
    return report


def _add_fovvdp(report: dict[str, Any], renders: Tensor, targets: Tensor, config: SceneConfig, display: str) -> None:
    """Add FoVVDP (``fovvdp_jod``, mean over the group's views, and ``fovvdp_display``) to the ``dynamic``,
    ``future`` and ``novel_views`` groups of ``report``; ``renders`` and ``targets`` (V, T, H, W, 3) in [0, 1]."""
    T = targets.shape[1]
    obs_v, held_v = list(config.observed_views), list(config.held_out_views)
    obs_f, held_f = list(config.observed_frames), list(config.held_out_frames)
    fps = 1.0 / float(config.dt)
    for key, views, frames in (("dynamic", obs_v, obs_f), ("future", obs_v, held_f),
                               ("novel_views", held_v, list(range(T)))):
        if report[key] and frames:
            scores = [fovvdp_score(renders[v, frames], targets[v, frames], fps=fps, display=display)
                      for v in views]
            report[key]["fovvdp_jod"] = sum(s["jod"] for s in scores) / len(scores)
            report[key]["fovvdp_display"] = scores[0]["display"]


def solid_stiffness(asset_path: str | Path, tet: dict[str, Tensor], nu: float) -> dict[str, Any] | None:
    """The reconstructed solid's lowest elastic frequency against the ground truth's (module docstring).

    The asset's side is the stiffness calibration's own tet reference (``log.json`` ``stiffness_calibration``
    ``solid_frequencies``: quadratic tets on a mesh of the reconstructed solid, ω at E = ρ = 1 on a grid of ν,
    interpolated at ``nu``); the truth's is quadratic tets on the truth's mesh at frame 0 (``tet``: the
    ``tet_trajectory`` extra, ``vertices`` (T, N, 3), ``tets`` (Nt, 4); with quadratic truths the first
    max(tets) + 1 vertices are the tets' corners). Both are free–free, linear elasticity at rest, and both leave
    out the local modes the calibration left out (the record's ``min_participation``; 0 in records written
    before it was kept).

    Args:
        nu: the Poisson ratio both are compared at (the truth's).
    Returns:
        {"nu", "omega_asset", "omega_truth" (rad/s at E = ρ = 1), "lowest_frequency_ratio" r,
        "implied_log10_E_offset" −2 log10 r}, or None when the asset has no such record (calibration off, or an
        asset written before it was kept).
    Raises:
        InputError naming log.json when the record is there but malformed.
    """
    log_path = Path(asset_path) / "log.json"
    if not log_path.is_file():
        return None
    try:
        record = json.loads(log_path.read_text()).get("stiffness_calibration") or {}
        solid = record.get("solid_frequencies") if isinstance(record, dict) else None
        if solid is None:
            return None
        nus = np.asarray(solid["nu"], dtype=float)
        omega = np.asarray(solid["omega"], dtype=float)
        share = float(record.get("min_participation", 0.0))
    except (OSError, json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{log_path}: cannot read stiffness_calibration.solid_frequencies ({exc})") from exc
    if nus.ndim != 1 or omega.ndim != 2 or omega.shape[0] != len(nus) or len(nus) == 0 or omega.shape[1] == 0 \
            or not np.all(np.isfinite(omega)) or not np.all(omega > 0) or np.any(np.diff(nus) <= 0):
        raise InputError(f"{log_path}: stiffness_calibration.solid_frequencies needs an increasing 'nu' grid and "
                         f"positive 'omega' of shape (len(nu), k), got nu {nus.tolist()} and omega of shape "
                         f"{list(omega.shape)}")
    asset_omega = float(np.interp(nu, nus, omega[:, 0]))
    tets = tet["tets"].long()
    corners = tet["vertices"][0, : int(tets.max()) + 1].double()
    truth_omega = float(tet_frequency_curve(corners, tets, (nu,), k=1, order=2, min_participation=share)[0, 0])
    ratio = asset_omega / truth_omega
    return {"nu": nu, "omega_asset": asset_omega, "omega_truth": truth_omega, "lowest_frequency_ratio": ratio,
            "implied_log10_E_offset": -2.0 * math.log10(ratio)}


def solid_against_truth(asset: Asset, tet: dict[str, Tensor]) -> dict[str, Any] | None:
    """The reconstructed simulation solid against the truth's body at frame 0 (module docstring).

    ``asset``'s solid is its interior samples ``points`` (N, 3) and ``volume`` (its contact points, on the
    boundary, join them for the extent); the truth's is the corners of ``tet`` (the ``tet_trajectory`` extra,
    ``vertices`` (T, N, 3), ``tets`` (Nt, 4)) at frame 0. Heights are along −gravity.

    Returns:
        {"volume_m3", "truth_volume_m3", "volume_ratio", "outside_truth_fraction" (the share of the asset's
        interior samples outside the truth's tets: the hull's excess), "bottom_offset_m" and "top_offset_m"
        (the solid's lowest and highest point minus the truth's: negative at the bottom, positive at the top,
        where the solid reaches beyond the object)}; None when the truth's tets have no volume at frame 0.
    """
    tets = tet["tets"].long()
    corners = tet["vertices"][0, : int(tets.max()) + 1].double()
    truth_volume = float(tet_volumes(corners, tets).abs().sum())
    if not truth_volume > 0:
        return None
    points = asset.points.detach().cpu().double()
    outside = ~inside_tets(points, corners, tets)
    g = torch.as_tensor(asset.gravity, dtype=torch.float64)
    up = -g / g.norm()
    solid_heights = torch.cat([points, asset.contact_points.detach().cpu().double()]) @ up
    truth_heights = corners @ up
    return {"volume_m3": float(asset.volume), "truth_volume_m3": truth_volume,
            "volume_ratio": float(asset.volume) / truth_volume, "outside_truth_fraction": float(outside.mean()),
            "bottom_offset_m": float(solid_heights.min() - truth_heights.min()),
            "top_offset_m": float(solid_heights.max() - truth_heights.max())}


def true_floor_friction(meta: dict[str, Any]) -> float | None:
    """The floor's Coulomb coefficient in a scene's ``metadata``: ``floor_friction``, else the independent engine's
    contact record (``newton.contact.friction``), else 0 for our FEM truth (its floor is frictionless); None when
    the scene does not say."""
    value = meta.get("floor_friction")
    if value is None:
        value = (meta.get("newton") or {}).get("contact", {}).get("friction")
    if value is None and meta.get("truth") == "fem":
        value = 0.0
    return float(value) if is_number(value) else None


def _material_record(asset: Asset, asset_path: str | Path, meta: dict[str, Any]) -> dict[str, Any]:
    """The report's ``material``: the fitted material, the asset's uncertainty and joint fit record, Stage II's
    start, and with the truth in the scene's ``meta``data the errors and whether the intervals hold it; the floor's
    friction (the asset's, fitted or given) beside it, scored where the scene says its true value."""
    fitted = {"E": asset.material["E"], "nu": asset.material["nu"]}
    material: dict[str, Any] = {"fitted": {**fitted, "log10_E": asset.material.get("log10_E"),
                                           "damping_ratio": asset.material.get("damping_ratio"),
                                           "floor_friction": asset.floor_friction}}
    friction = true_floor_friction(meta)
    if friction is not None:
        material["true_floor_friction"] = friction
        material["abs_error_floor_friction"] = abs(asset.floor_friction - friction)
    uncertainty = asset.material.get("uncertainty")
    if isinstance(uncertainty, dict):
        material["uncertainty"] = uncertainty
    fit = joint_fit_record(asset.extra)
    if fit is not None:
        material["fit"] = fit
    start = start_material(asset_path)
    if start is not None:
        material["start"] = start
    if isinstance(meta.get("E"), (int, float)) and isinstance(meta.get("nu"), (int, float)):
        material["truth"] = {"E": meta["E"], "nu": meta["nu"]}
        material.update(material_errors(fitted, material["truth"]))
        if start is not None:
            start.update(material_errors(start, material["truth"]))
        if isinstance(uncertainty, dict) and meta["E"] > 0:
            material["interval_covers_truth"] = interval_coverage(uncertainty, {"log10_E": math.log10(meta["E"]),
                                                                                 "nu": meta["nu"]})
    return material


def _motion_errors(tet: dict[str, Tensor], centres: list[Tensor], sim: Simulator, states: list[SimState],
                   config: SceneConfig) -> dict[str, Any]:
    """The report's ``chamfer`` (the simulated Gaussian centres, T × (N, 3), against the ground-truth surface of
    ``tet``) and ``centre_of_mass`` (the simulated body's, of ``states``, against the truth's), per frame and as
    means over the observed and held-out frames."""
    T = len(centres)
    obs_f, held_f = list(config.observed_frames), list(config.held_out_frames)
    faces = boundary_faces(tet["tets"])
    per_frame = [surface_chamfer(centres[t].double(), tet["vertices"][t].double(), faces, seed=t)
                 for t in range(T)]
    offset = (simulated_centre_of_mass(sim, states).cpu()
              - tet_centre_of_mass(tet["vertices"][:T], tet["tets"])).norm(dim=1).tolist()
    return {
        "chamfer": {
            "per_frame": per_frame,
            "observed_mean": sum(per_frame[f] for f in obs_f) / len(obs_f),
            "future_mean": sum(per_frame[f] for f in held_f) / len(held_f) if held_f else None,
            "units": "m (mean of both directions, simulated Gaussian centres vs the ground-truth surface)",
        },
        "centre_of_mass": {
            "per_frame": offset,
            "frame_0": offset[0],  # the reconstructed body's own, before any motion
            "observed_mean": sum(offset[f] for f in obs_f) / len(obs_f),
            "future_mean": sum(offset[f] for f in held_f) / len(held_f) if held_f else None,
            "units": "m (distance between the simulated body's centre of mass and the ground truth's)",
        },
        **contact_errors(tet, sim, states, offset, config),
    }


def contact_errors(tet: dict[str, Tensor], sim: Simulator, states: list[SimState], offset: list[float],
                   config: SceneConfig) -> dict[str, Any]:
    """The report's ``orientation`` and ``contacts`` (:func:`vid2sim.metrics.motion_around_contacts`) of the
    simulated body (the simulator's mass points over ``states``) against the truth's tets (their centroids, each
    with its frame-0 volume), with the centre-of-mass distances ``offset`` (T,) of :func:`_motion_errors`."""
    T = len(offset)
    vertices, tets = tet["vertices"][:T].double(), tet["tets"].long()
    with torch.no_grad():
        points = torch.stack([sim.positions(sim.X, s.z).double().cpu() for s in states])
        masses = sim.masses().double().cpu()
    return motion_around_contacts(points, masses, vertices[:, tets].mean(2), tet_volumes(vertices[0], tets).abs(),
                                  offset, float(config.dt), config.gravity, list(config.observed_frames),
                                  list(config.held_out_frames))


def _true_motion(asset: Asset, tet: dict[str, Tensor] | None, targets: Tensor, cameras: list[Camera],
                 config: SceneConfig, scene_path: str | Path, progress: bool) -> dict[str, Any]:
    """The report's ``true_motion``: the asset's Gaussians moved by the ground truth's motion (``tet``), rendered
    and scored against ``targets`` (V, T, H, W, 3) like the simulation: the appearance's ceiling."""
    T = targets.shape[1]
    if tet is None:
        raise InputError(f"{scene_path}: true_motion needs the ground-truth motion (the tet_trajectory extra), "
                         "which this scene does not have")
    carried = true_motion_gaussians(asset, tet)
    if len(carried) < T:
        raise InputError(f"{scene_path}: the tet_trajectory extra has {len(carried)} frames, the images {T}")
    truth_renders = render_frames(carried[:T], cameras, background=1.0, progress=progress).cpu()
    groups = scene_groups(truth_renders, targets, config)
    del groups["rest"]  # frame 0 is the rest pose under either motion: the report's own ``rest``
    return {"what": "the asset's Gaussians moved by the ground truth's motion: the appearance's ceiling", **groups}


def write_evaluation(report: dict[str, Any], path: str | Path) -> Path:
    """Write ``report`` as JSON (atomically)."""
    import os

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, path)
    return path
