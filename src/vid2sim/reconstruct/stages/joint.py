"""Stage II joint optimisation (paper Eq. 6): material, initial velocity and networks from the images.

The simulator starts from the object's frame-0 configuration (its rest shape) with a rigid initial velocity;
each frame's state z moves the Gaussians fitted at frame 0 (centres by LBS, covariances by F Σ Fᵀ), they are
rendered in the observed views and compared with the video.

First, for either method, a coarse search over log10 E (the loss is not convex in E: the wrong bounce phase is a
local minimum): whole observed rollouts at a grid of E, compared at ``coarse_scale`` (renders and images
area-averaged, :meth:`Observations.at_scale`); its parabola vertex is the start. The whole-clip losses weight
frame t by exp(−(t − 1)/4) (``frame_decay``): the first contact, where E acts most directly, counts more than the
late frames, where a stiff object's rocking on the floor drifts chaotically from any model's.
Then ``JointConfig.method``:

* "gauss_newton" (the default, beyond the paper; on the 8-scene quadratic-tet small suite it beat the coarse start
  on 7 scenes, the windows on 4, docs/results.md): Levenberg–Marquardt on the few physical parameters — log10 E,
  ν, the damping ratio ζ, the initial linear and angular velocity — over the whole observed clip at
  ``coarse_scale``, with a Gaussian prior on the material (:mod:`vid2sim.reconstruct.gauss_newton`). The
  Jacobian comes from forward differences of whole rollouts, so every frame's error informs every parameter;
  every step is accepted only if it lowers the posterior objective; the kept state is the best by the
  full-resolution validation loss, the start included, and the fit stops when that has not improved for
  ``gauss_newton_patience`` steps. The networks stay as trained data-free.
* "windows" (the paper's): Adam on random windows of 4 frames, the networks too (:mod:`vid2sim.reconstruct.windows`).

The observations, renders of simulated states and the image losses are :mod:`vid2sim.reconstruct.clip`'s.

At the kept state the Gauss–Newton curvature of the whole clip gives the material's Laplace intervals and says
whether each parameter is identifiable from the video at all, and which frames inform it
(:mod:`vid2sim.reconstruct.uncertainty`).
"""

from __future__ import annotations

import copy
import math
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from vid2sim.asset.folder import Asset
from vid2sim.asset.motion import GaussianRig, simulated_centre_of_mass
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS, Floor, Gravity
from vid2sim.physics.mass import centre_shifted_volumes
from vid2sim.physics.solver import Material, SimState, SimulationError, Simulator
from vid2sim.physics.stiffness_curve import StiffnessCurve
from vid2sim.reconstruct.clip import (
    Observations,
    clip_loss,
    detached_state,
    frame_losses,
    frame_weights,
    render_states,
    trajectory_clip_loss,
)
from vid2sim.reconstruct.config import JointConfig
from vid2sim.reconstruct.gauss_newton import (
    FitResult,
    Parameter,
    effective_images,
    levenberg_marquardt,
)
from vid2sim.reconstruct.hull_track import HullTrack, hull_track
from vid2sim.reconstruct.rollouts import (
    ClipSimulation,
    RolloutPool,
    floor_friction,
    set_floor_friction,
    simulate_many,
)
from vid2sim.reconstruct.runner import Context, State
from vid2sim.reconstruct.stages.networks import cpu_state
from vid2sim.reconstruct.stages.points import floor_carved_contact, rigid_frames, track_poses
from vid2sim.reconstruct.stages.stage1 import prior_material
from vid2sim.reconstruct.uncertainty import (
    coarse_best,
    information_by_frame,
    laplace_intervals,
    mark_coarse_edge,
    mark_unmoved,
)
from vid2sim.reconstruct.windows import windowed_adam
from vid2sim.runtime.files import read_json, save_torch_atomic, write_json_atomic
from vid2sim.splats.gaussians import Gaussians


@dataclass
class JointResult:
    """What :func:`joint_optimisation` found (the best state by validation loss).

    Attributes:
        log10_E, nu, damping_ratio: the material.
        floor_friction: the floor's Coulomb coefficient (fitted with ``fit_friction``, else the simulator's).
        linear_velocity, angular_velocity: (3,) the initial rigid velocity about ``centre``.
        validation_loss: the best validation loss (mean squared image error, all observed frames and views).
        coarse: the coarse search, one ``{"log10_E", "loss"}`` per grid value (and ``"floor_friction"``,
            ``"contact_surface"`` when those are searched too).
        contact_surface: the name of the contact surface the fit used ("hull": the solid's own;
            ``JointConfig.contact_search``).
        centre_of_mass_offset: (3,) m, how far the search moved the lumped masses' centre (zeros: no search, or
            none of its candidates did better); the simulator's ``mass_volumes`` carry it.
        centre_of_mass_search: the search, one ``{"offset", "loss"}`` per candidate.
        log: one dict per iteration: "windows": ``iteration``, ``loss`` (the window's), ``log10_E``, ``nu``,
            ``damping_ratio``, ``window_start``, ``scale``, ``ms``, and ``validation_loss`` where validated;
            "gauss_newton": ``iteration``, ``loss`` (the whole clip's at ``coarse_scale``), ``objective``, the
            parameters by name, ``damping`` (Marquardt's), ``accepted``, ``rollouts``, ``ms``, ``validation_loss``.
        seconds: wall time.
        method: ``JointConfig.method``.
        start_validation_loss: the validation loss of the start (the coarse search's material, the velocity
            estimate); the kept state's is at most this.
        uncertainty: the material's Laplace intervals (:func:`~vid2sim.reconstruct.uncertainty.laplace_intervals`).
        information_by_frame: per parameter, the share of its information each observed frame 1 … T−1 gives
            (:func:`~vid2sim.reconstruct.uncertainty.information_by_frame`).
        stop: why the fit stopped.
        track: with a hull track (``JointConfig.track_sd``): ``{"sd" (m), "frame_sd" (T−1 standard deviations, m,
            :meth:`~vid2sim.reconstruct.hull_track.HullTrack.frame_sd`), "hull_centroids" (T × 3, m), "hull_volumes"
            (T, m³), "displacement_error" (T−1 distances, m, between the kept fit's centre-of-mass displacement from
            frame 0 and the track's)}``; empty without one.
    """

    log10_E: float
    nu: float
    damping_ratio: float
    linear_velocity: list[float]
    angular_velocity: list[float]
    validation_loss: float
    floor_friction: float = 0.0
    coarse: list[dict[str, float]] = field(default_factory=list)
    centre_of_mass_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    centre_of_mass_search: list[dict[str, Any]] = field(default_factory=list)
    log: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0
    method: str = "gauss_newton"
    start_validation_loss: float | None = None
    uncertainty: dict[str, Any] = field(default_factory=dict)
    information_by_frame: dict[str, list[float]] = field(default_factory=dict)
    stop: str = ""
    contact_surface: str = "hull"
    track: dict[str, Any] = field(default_factory=dict)


def coarse_minimum(values: Sequence[float], losses: Sequence[float]) -> float:
    """The minimum of a loss sampled on an ascending grid: the vertex of the parabola through the best sample
    and its two neighbours (kept between them), or the best sample itself at an end of the grid or where the
    parabola is not convex."""
    i = min(range(len(losses)), key=lambda j: losses[j])
    value = float(values[i])
    if 0 < i < len(values) - 1:
        (x0, y0), (x1, y1), (x2, y2) = [(values[j], losses[j]) for j in (i - 1, i, i + 1)]
        denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
        a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
        b = (x2 ** 2 * (y0 - y1) + x1 ** 2 * (y2 - y0) + x0 ** 2 * (y1 - y2)) / denom
        if a > 0:
            value = min(max(-b / (2 * a), x0), x2)
    return value


def centre_of_mass_search(sim: Simulator, rig: GaussianRig, start: Callable[[], SimState], obs: Observations,
                          step: float, rounds: int, decay: float | None = None,
                          progress: bool = False) -> tuple[list[float], list[dict[str, Any]]]:
    """Move the lumped masses' centre of mass to where the whole observed clip is rendered best (beyond the paper).

    The hull's centre of mass is off wherever the hull is carved unevenly (sides no view sees in profile stay
    too wide), and where the centre lies sets how the floor's impulse at the bounce splits between spin and
    translation (docs/architecture.md, "Where the motion goes wrong"). Each round tries the current best
    centre moved by ± ``step`` along each world axis (masses on the same cubature points, re-matched by
    :func:`~vid2sim.physics.mass.centre_shifted_volumes`: the same total and inertia about the centre), then the
    offset made of each axis's parabola vertex; the best of all tried is kept, and the next round halves the step.
    Losses are :func:`clip_loss` at ``obs``'s resolution from ``start()``; an offset no positive masses on the
    points carry counts as infinitely bad.

    Args:
        sim: the simulator; its ``mass_volumes`` are set to the best candidate's (the start's when none does better).
        step: the first round's step (m).
        rounds: rounds, each with half the step of the one before.
    Returns:
        (the best offset (3,) in m, one ``{"offset", "loss"}`` per candidate, the start first).
    """
    from tqdm.auto import tqdm

    base = sim.mass_volumes
    tried: dict[tuple[float, float, float], float] = {}
    records: list[dict[str, Any]] = []
    bar = tqdm(total=1 + 7 * rounds, desc="search over the centre of mass", disable=not progress, leave=False)

    def loss_at(offset: Sequence[float]) -> float:
        key = tuple(round(float(o), 9) for o in offset)
        if key not in tried:
            try:
                sim.mass_volumes = centre_shifted_volumes(sim.X, base, torch.tensor(key, dtype=torch.float64)).to(base)
                tried[key] = clip_loss(sim, rig, detached_state(start()), obs, decay)[0]
            except ValueError:  # no positive masses on these points have that centre
                tried[key] = math.inf
            finally:
                sim.mass_volumes = base
            records.append({"offset": list(key), "loss": tried[key]})
            bar.update(1)
            bar.set_postfix(loss=f"{tried[key]:.3e}")
        return tried[key]

    best = [0.0, 0.0, 0.0]
    loss_at(best)
    for r in range(rounds):
        d = step / 2 ** r
        vertex = list(best)
        for axis in range(3):
            ends = []
            for sign in (-1.0, 1.0):
                moved = list(best)
                moved[axis] += sign * d
                ends.append(loss_at(moved))
            if all(math.isfinite(v) for v in ends):
                vertex[axis] = best[axis] + coarse_minimum([-d, 0.0, d], [ends[0], loss_at(best), ends[1]])
        loss_at(vertex)
        best = list(min(tried, key=tried.get))
    bar.close()
    sim.mass_volumes = centre_shifted_volumes(sim.X, base, torch.tensor(best, dtype=torch.float64)).to(base)
    return best, records


#: forward-difference steps of the Gauss–Newton Jacobian: log10 E (decades), ν, ζ, and the initial velocity as a
#: fraction of the object's size per frame (linear, m/s per m/frame) and radians per frame (angular). Each moves
#: the observed frames by a fraction of a pixel to a few pixels at the small preset: large enough that the
#: rasteriser's cutoffs and Newton's tolerance are noise, small enough for a secant of a smooth loss. At the full
#: preset the velocity's steps move the last frame by about 4 pixels and their forward and backward differences
#: disagree; steps of one pixel made a truer Jacobian and fits that matched the observed clip better but predicted
#: the future frames worse (0.05–6.2 dB on four scenes, docs/results.md), so these stay.
DIFFERENCE_STEPS = {"log10_E": 0.01, "nu": 0.01, "damping_ratio": 0.005, "floor_friction": 0.02, "linear": 0.002,
                    "angular": 0.002}


def simulator_prior(sim: Simulator) -> dict[str, float]:
    """The values the simulator holds now, as the fit's prior means: ``log10_E``, ``nu``, ``damping_ratio`` and
    ``floor_friction``."""
    return {"log10_E": float(sim.log10_E), "nu": float(sim.nu), "damping_ratio": float(sim.damping_ratio),
            "floor_friction": floor_friction(sim)}


def physical_parameters(sim: Simulator, cfg: JointConfig, prior: dict[str, float], dt: float) -> list[Parameter]:
    """The Gauss–Newton fit's parameters: log10 E, ν, ζ (with ``cfg.fit_damping``), the floor's friction μ (with
    ``cfg.fit_friction``, when there is a floor), each with the prior of ``cfg`` centred on ``prior`` (the start
    material and friction), then the initial linear (m/s) and angular (rad/s) velocity without a prior."""
    L = sim.length_scale
    out = [Parameter("log10_E", *cfg.log10_E_bounds, DIFFERENCE_STEPS["log10_E"], prior["log10_E"],
                     cfg.prior_sd_log10_E),
           Parameter("nu", *cfg.nu_bounds, DIFFERENCE_STEPS["nu"], prior["nu"], cfg.prior_sd_nu)]
    if cfg.fit_damping:
        out.append(Parameter("damping_ratio", 0.0, 1.0, DIFFERENCE_STEPS["damping_ratio"], prior["damping_ratio"],
                             cfg.prior_sd_damping))
    if cfg.fit_friction and cfg.method == "gauss_newton" and any(isinstance(e, Floor) for e in sim.externals):
        out.append(Parameter("floor_friction", *cfg.friction_bounds, DIFFERENCE_STEPS["floor_friction"],
                             prior["floor_friction"], cfg.prior_sd_friction))
    v, w = DIFFERENCE_STEPS["linear"] * L / dt, DIFFERENCE_STEPS["angular"] / dt
    out += [Parameter(f"linear_velocity_{a}", -math.inf, math.inf, v) for a in "xyz"]
    out += [Parameter(f"angular_velocity_{a}", -math.inf, math.inf, w) for a in "xyz"]
    return out


class ClipResiduals:
    """The whole observed clip as a function of the physical parameters θ (a
    :class:`~vid2sim.reconstruct.gauss_newton.ClipModel`): θ sets the simulator's material and the initial rigid
    velocity about ``centre``; block t is frame t + 1 rendered in every view of ``obs``, minus the video, times
    √(w_t / (V·H·W·3)) (``frame_weights``), so that the blocks' squared norms sum to :func:`clip_loss`.

    With a ``track`` (the visual hulls' centroids, :func:`~vid2sim.reconstruct.hull_track.hull_track`), the track
    residuals compare displacements from frame 0: (c(t) − c(0)) − (h(t) − h(0)) for t = 1 … T−1, c the simulated
    centre of mass and h the track, divided by ``track_sd``. A hull's centroid is off the centre of mass by nearly
    the same vector in every frame while the body keeps its shape; the difference cancels it.

    Args:
        names: the parameters' names in θ's order (:func:`physical_parameters`).
        track: (T, 3) the track's positions of frames 0 … T−1 (m), or None: no track term.
        track_sd: its displacements' standard deviation (m): one number, or (T−1,) one per frame 1 … T−1.
    """

    def __init__(self, sim: Simulator, rig: GaussianRig, obs: Observations, centre: Sequence[float],
                 decay: float | None, names: Sequence[str], track: Tensor | None = None,
                 track_sd: float | Tensor | None = None, pool: RolloutPool | None = None) -> None:
        self.sim, self.rig, self.obs, self.centre, self.names = sim, rig, obs, [float(c) for c in centre], list(names)
        V, T = obs.images.shape[:2]
        self.frames = T - 1
        self.simulation, self.pool = ClipSimulation(sim, self.names, self.centre, self.frames), pool
        if track is not None:
            sd = None if track_sd is None else torch.as_tensor(track_sd, dtype=torch.float64).cpu()
            if tuple(track.shape) != (T, 3) or sd is None or sd.numel() not in (1, T - 1) or not bool((sd > 0).all()):
                raise ValueError(f"the track must have shape (T={T}, 3) and standard deviations > 0 (one, or one per "
                                 f"frame 1 … T−1), got {tuple(track.shape)} and {track_sd}")
            track = (track[1:] - track[0]).double().cpu()  # (T−1, 3) displacements from frame 0
            track_sd = sd.reshape(-1, 1).expand(T - 1, 1)
        self.track, self.track_sd = track, track_sd
        pixels = V * obs.images[0, 0].numel()
        self.scales = [math.sqrt(w / pixels) for w in frame_weights(T, decay)]
        with torch.no_grad():
            self.basis = rig.basis()

    def apply(self, theta: Sequence[float]) -> SimState:
        """Set the simulator's material from θ; returns the initial state θ's velocity gives."""
        return self.simulation.apply(theta)

    def substeps(self, theta: Sequence[float]) -> int:
        return self.simulation.substeps(theta)

    def simulate(self, theta: Sequence[float], substeps: int | None = None) -> list[SimState]:
        """Frames 0 … T−1 at θ (frame 0 the initial state), ``substeps`` per frame (None: the automatic count)."""
        return self.simulation.simulate(theta, substeps)

    def simulate_many(self, thetas: Sequence[Sequence[float]], substeps: int | None = None
                      ) -> list[list[SimState] | None]:
        """Each θ's frames 0 … T−1 (None where the simulation fails), on the ``pool``'s workers and here
        (:func:`~vid2sim.reconstruct.rollouts.simulate_many`)."""
        return simulate_many(self.simulation, thetas, substeps, self.pool)

    def residuals(self, trajectories: Sequence[list[SimState]], frame: int) -> Tensor:
        with torch.no_grad():
            renders = render_states(self.rig, [s[frame + 1] for s in trajectories], self.obs,
                                    range(len(self.obs.cameras)), self.basis)  # (K, V, H, W, 3)
            target = self.obs.images[:, frame + 1].to(renders)
            return ((renders - target) * self.scales[frame]).reshape(len(trajectories), -1)

    def track_residuals(self, trajectories: Sequence[list[SimState]]) -> Tensor | None:
        """(len(trajectories), 3(T−1)) float64 track residuals (class docstring), or None without a track."""
        if self.track is None:
            return None
        out = []
        for states in trajectories:
            c = simulated_centre_of_mass(self.sim, states).cpu()  # (T, 3)
            out.append((((c[1:] - c[0]) - self.track) / self.track_sd).reshape(-1))  # track_sd: (T−1, 1)
        return torch.stack(out)


def joint_optimisation(
    sim: Simulator, gaussians: Gaussians, observations: Observations,
    linear_velocity: Sequence[float], angular_velocity: Sequence[float], centre: Sequence[float],
    config: JointConfig | None = None,
    progress: bool = True,
    on_iteration: Callable[[dict[str, float]], None] | None = None,
    contacts: dict[str, tuple[Tensor, Tensor]] | None = None,
    track: HullTrack | None = None,
    rollout_processes: int = 0,
) -> JointResult:
    """Fit the material, the initial velocity (and, with ``method`` "windows", the networks) of ``sim`` to the
    observed video; report how well the video determines the material.

    A coarse search over log10 E picks the start (and optionally a search over the centre of mass), then
    ``config.method`` fits: Gauss–Newton on the physical parameters over the whole clip (:func:`_gauss_newton`), or
    the paper's Adam on windows (:func:`~vid2sim.reconstruct.windows.windowed_adam`). Either way the kept state is
    the best by the whole-clip validation loss, the coarse search's start included, and the material's uncertainty
    is the Laplace approximation at it, widened by the model's own error (``cfg.model_error_log10_E``,
    ``cfg.model_error_nu``; :func:`vid2sim.reconstruct.uncertainty.laplace_intervals`).

    Args:
        sim: the simulator built on the object's points (its material is the prior, the prior's mean; it is
            updated in place to the kept state, as are its field and Neural Jacobian).
        gaussians: (N Gaussians) fitted to frame 0.
        observations: :class:`Observations` of frames 0 … T−1 (T ≥ window + 1 for "windows", T ≥ 2 otherwise).
        linear_velocity, angular_velocity: (3,) initial rigid velocity estimate about ``centre`` (3,).
        config: :class:`JointConfig`.
        on_iteration: called with each log entry.
        contacts: the contact surfaces the coarse search tries, by name: (S, 3) points and (S,) areas each
            (``JointConfig.contact_search``); None: ``sim``'s own only. ``sim`` is left with the chosen one.
        track: the body's observed positions (the hull track, :mod:`vid2sim.reconstruct.hull_track`) that the fit
            also matches, with standard deviation ``config.track_sd`` × the object's length scale, widened where the
            hull's volume changed by more than ``config.track_volume_tolerance`` (:class:`ClipResiduals`); None: the
            images alone.
        rollout_processes: worker processes that simulate the coarse search's and the Jacobians' rollouts beside
            this one (:class:`~vid2sim.reconstruct.rollouts.RolloutPool`; a CPU simulator's); 0: none.
    Returns:
        :class:`JointResult`.
    """
    cfg = config or JointConfig()
    t_start = time.perf_counter()
    T = observations.images.shape[1]
    needed = cfg.window + 1 if cfg.method == "windows" else 2
    if T < needed:
        raise ValueError(f"the joint optimisation ({cfg.method}) needs at least {needed} observed frames, got {T}")
    prior = simulator_prior(sim)
    rig = GaussianRig(sim, gaussians)
    c = [float(x) for x in centre]
    coarse_obs = observations.at_scale(cfg.coarse_scale)

    def start_state() -> SimState:
        return sim.rigid_velocity_state(linear_velocity, angular_velocity, c)

    processes = rollout_processes if cfg.method == "gauss_newton" else 0
    with RolloutPool(processes) if processes > 0 else nullcontext() as pool:  # workers start during the search
        coarse = coarse_search(sim, rig, start_state, coarse_obs, cfg, progress, contacts, pool,
                               (linear_velocity, angular_velocity, c))
        surface = str(coarse_best(coarse).get("contact_surface", "hull")) if coarse else "hull"
        com_offset, com_records = [0.0, 0.0, 0.0], []
        if cfg.centre_of_mass_step > 0:
            com_offset, com_records = centre_of_mass_search(sim, rig, start_state, coarse_obs,
                                                            cfg.centre_of_mass_step * sim.length_scale,
                                                            cfg.centre_of_mass_rounds, cfg.frame_decay, progress)
        parameters = physical_parameters(sim, cfg, prior, float(sim.config.dt))
        if track is not None and (cfg.track_sd is None or cfg.method != "gauss_newton"):
            raise ValueError("a track needs JointConfig.track_sd, its standard deviation, and the gauss_newton method")
        clip, frame_sd = _fitted_clip(sim, rig, coarse_obs, c, cfg, [q.name for q in parameters], track, pool)
        start = [float(sim.log10_E), float(sim.nu)] + ([float(sim.damping_ratio)] if cfg.fit_damping else []) \
            + ([floor_friction(sim)] if "floor_friction" in clip.names else []) \
            + [float(x) for x in linear_velocity] + [float(x) for x in angular_velocity]
        n = effective_images(frame_weights(clip.frames + 1, cfg.frame_decay), len(observations.cameras))
        if cfg.method == "gauss_newton":
            fit = _gauss_newton(clip, parameters, start, n, rig, observations, cfg, progress, on_iteration)
        else:
            fit = windowed_adam(sim, rig, observations, coarse_obs, start, c, cfg, clip, parameters, progress,
                                 on_iteration)
    theta = dict(zip(clip.names, fit.theta))
    clip.apply(fit.theta)  # the simulator holds the kept material
    uncertainty = laplace_intervals(fit.linearisation, parameters, n, cfg.interval_level,
                                    {"log10_E": cfg.model_error_log10_E, "nu": cfg.model_error_nu})
    mark_unmoved(uncertainty, dict(zip(clip.names, start)), kept_start=list(fit.theta) == list(start))
    mark_coarse_edge(uncertainty, coarse)
    track_record: dict[str, Any] = {}
    if track is not None:
        kept = clip.track_residuals([clip.simulate(fit.theta)])[0].reshape(-1, 3) * clip.track_sd
        track_record = {"sd": cfg.track_sd * sim.length_scale, "frame_sd": frame_sd.tolist(),
                        "hull_centroids": track.centroids.tolist(), "hull_volumes": track.volumes.tolist(),
                        "displacement_error": kept.norm(dim=1).tolist()}
    return JointResult(log10_E=theta["log10_E"], nu=theta["nu"], damping_ratio=float(sim.damping_ratio),
                       floor_friction=floor_friction(sim),
                       linear_velocity=[theta[f"linear_velocity_{a}"] for a in "xyz"],
                       angular_velocity=[theta[f"angular_velocity_{a}"] for a in "xyz"],
                       validation_loss=fit.validation_loss, coarse=coarse, centre_of_mass_offset=com_offset,
                       centre_of_mass_search=com_records, log=fit.log, seconds=time.perf_counter() - t_start,
                       method=cfg.method, start_validation_loss=fit.start_validation_loss, uncertainty=uncertainty,
                       information_by_frame=information_by_frame(fit.linearisation, parameters), stop=fit.stop,
                       contact_surface=surface, track=track_record)


def _fitted_clip(sim: Simulator, rig: GaussianRig, obs: Observations, centre: Sequence[float], cfg: JointConfig,
                 names: Sequence[str], track: HullTrack | None,
                 pool: RolloutPool | None = None) -> tuple[ClipResiduals, Tensor | None]:
    """The clip the Gauss–Newton fit sees: the observed frames 0 … T−1 of ``obs`` less the last
    ``cfg.held_out_frames`` (which judge the fit instead), with the track's positions of the same frames; and the
    track's (fitted frames − 1,) standard deviations (None without a track)."""
    T = obs.images.shape[1]
    fitted = T - cfg.held_out_frames
    if fitted < 2:
        raise ValueError(f"JointConfig.held_out_frames={cfg.held_out_frames} leaves {fitted} of the {T} observed "
                         "frames to fit: at least 2 are needed (frame 0 and one after it)")
    frame_sd = None if track is None else \
        track.frame_sd(cfg.track_sd * sim.length_scale, cfg.track_volume_tolerance)[:fitted - 1]
    fit_obs = Observations(obs.images[:, :fitted], obs.cameras, obs.background)
    clip = ClipResiduals(sim, rig, fit_obs, centre, cfg.frame_decay, names,
                         None if track is None else track.centroids[:fitted], frame_sd, pool)
    return clip, frame_sd


def coarse_search(sim: Simulator, rig: GaussianRig, start: Callable[[], SimState], obs: Observations,
                  cfg: JointConfig, progress: bool = False,
                  contacts: dict[str, tuple[Tensor, Tensor]] | None = None, pool: RolloutPool | None = None,
                  velocity: tuple[Sequence[float], Sequence[float], Sequence[float]] | None = None
                  ) -> list[dict[str, Any]]:
    """The coarse search over log10 E (``cfg.coarse_log10_E``; none when empty): the whole clip's
    :func:`clip_loss` at each grid value from ``start()``; the simulator is left at :func:`coarse_minimum`.
    With ``cfg.fit_friction`` and a floor, the same over E at each floor friction of ``cfg.coarse_friction``: friction
    changes which E explains the bounce. With ``contacts`` (contact surfaces by name, :func:`joint_optimisation`), the
    same again for each surface. The first (surface, friction) pair runs the whole grid; each further pair walks it
    downhill from the best E found so far (:func:`grid_descent`) and stops at a minimum of its own on the grid, both
    neighbours tried, or at an end of the grid: a frictional rollout costs 2–3 frictionless ones, and on 19 scenes a
    friction of 0.5 moved the grid's best E by at most 5 steps. The simulator is left with the friction and surface
    whose best grid loss is lowest, at that pair's E. Returns one ``{"log10_E", "loss"}`` (and ``"floor_friction"``,
    ``"contact_surface"``) per log10 E tried, each pair's rows in ascending E.

    With a ``pool`` and the ``velocity`` ``start()`` gives (linear, angular, the centre it turns about), the first
    pair's grid and each walk's first three points are simulated on the pool's workers and here at once
    (:func:`~vid2sim.reconstruct.rollouts.simulate_many`)."""
    from tqdm.auto import tqdm

    coarse: list[dict[str, Any]] = []
    if not cfg.coarse_log10_E:
        return coarse
    frictions: list[float | None] = [None]
    if cfg.fit_friction and any(isinstance(e, Floor) for e in sim.externals):
        frictions = sorted({floor_friction(sim), *cfg.coarse_friction})
    surfaces: list[str | None] = list(contacts) if contacts and len(contacts) > 1 else [None]
    values = sorted(float(v) for v in cfg.coarse_log10_E)
    searched = " and the floor's friction" if len(frictions) > 1 else ""
    searched += " and the contact surface" if len(surfaces) > 1 else ""
    bar = tqdm(total=len(surfaces) * len(frictions) * len(values), desc="coarse search over log10 E" + searched,
               disable=not progress, leave=False)
    for k, (surface, mu) in enumerate((surface, mu) for surface in surfaces for mu in frictions):
        if surface is not None:
            sim.set_contact(*contacts[surface])
        if mu is not None:
            set_floor_friction(sim, mu)
        rows: dict[int, dict[str, Any]] = {}

        def loss_at(i: int, loss: float | None = None) -> float:
            if loss is None:
                with torch.no_grad():
                    sim.log10_E.fill_(values[i])
                loss, _ = clip_loss(sim, rig, detached_state(start()), obs, cfg.frame_decay)
            row: dict[str, Any] = {"log10_E": values[i], "loss": loss}
            if mu is not None:
                row["floor_friction"] = mu
            if surface is not None:
                row["contact_surface"] = surface
            rows[i] = row
            bar.update(1)
            bar.set_postfix(log10_E=values[i], loss=f"{loss:.2e}")
            return loss

        if k == 0:
            at_once = list(range(len(values)))
        else:
            first = values.index(coarse_best(coarse)["log10_E"])
            at_once = [i for i in (first - 1, first, first + 1) if 0 <= i < len(values)]
        if pool is not None and velocity is not None:
            for i, loss in zip(at_once, _coarse_losses(sim, rig, obs, cfg, velocity, mu, [values[i] for i in at_once],
                                                       pool)):
                loss_at(i, loss)
        if k == 0:
            for i in range(len(values)):
                if i not in rows:
                    loss_at(i)
        else:
            grid_descent(len(values), first, lambda i: rows[i]["loss"] if i in rows else loss_at(i))
        coarse.extend(rows[i] for i in sorted(rows))
    bar.close()
    best = coarse_best(coarse)
    rows_best = [r for r in coarse if r.get("floor_friction") == best.get("floor_friction")
                 and r.get("contact_surface") == best.get("contact_surface")]
    with torch.no_grad():
        sim.log10_E.fill_(coarse_minimum([r["log10_E"] for r in rows_best], [r["loss"] for r in rows_best]))
    if "floor_friction" in best:
        set_floor_friction(sim, best["floor_friction"])
    if "contact_surface" in best:
        sim.set_contact(*contacts[best["contact_surface"]])
    return coarse


def _coarse_losses(sim: Simulator, rig: GaussianRig, obs: Observations, cfg: JointConfig,
                   velocity: tuple[Sequence[float], Sequence[float], Sequence[float]], friction: float | None,
                   log10_Es: Sequence[float], pool: RolloutPool) -> list[float]:
    """The coarse search's whole-clip losses at each log10 E (the simulator's other values held, the floor at
    ``friction`` unless None), the rollouts shared with the ``pool``'s workers; a rollout that fails there is
    simulated again here, to raise its error."""
    linear, angular, centre = velocity
    names = ["log10_E", "nu", "damping_ratio"] + (["floor_friction"] if friction is not None else []) \
        + [f"{kind}_velocity_{a}" for kind in ("linear", "angular") for a in "xyz"]
    held = [float(sim.nu), float(sim.damping_ratio)] + ([friction] if friction is not None else []) \
        + [float(x) for x in linear] + [float(x) for x in angular]
    simulation = ClipSimulation(sim, names, [float(c) for c in centre], obs.images.shape[1] - 1)
    thetas = [[float(e)] + held for e in log10_Es]
    out = []
    for theta, states in zip(thetas, simulate_many(simulation, thetas, None, pool)):
        states = simulation.simulate(theta) if states is None else states
        out.append(trajectory_clip_loss(rig, states, obs, cfg.frame_decay))
    return out


def grid_descent(n: int, start: int, loss_at: Callable[[int], float]) -> int:
    """Walk a grid of ``n`` points downhill from index ``start``: ``loss_at`` of it and its neighbours, then of the
    lowest one's, until the lowest is the one walked to (both its neighbours tried and higher) or an end of the grid.
    Each index is evaluated once. Returns the index of that local minimum."""
    if not 0 <= start < n:
        raise ValueError(f"the start index {start} lies outside the grid of {n} points")
    seen: dict[int, float] = {}

    def f(i: int) -> float:
        if i not in seen:
            seen[i] = loss_at(i)
        return seen[i]

    i = start
    while True:
        best = min((j for j in (i - 1, i, i + 1) if 0 <= j < n), key=f)
        if best == i:
            return i
        i = best


def _full_resolution_validation(clip: ClipResiduals, rig: GaussianRig, observations: Observations,
                                decay: float | None) -> Callable[[list[float], list[SimState]], float]:
    """θ, its trajectory → the whole clip's loss in every observed view at full resolution (the trajectory's
    states re-rendered; at ``coarse_scale`` 1 the fit's own loss)."""
    def validate(theta: list[float], trajectory: list[SimState]) -> float:
        T = observations.images.shape[1]
        losses = frame_losses(rig, trajectory[1:T], observations, range(1, T), clip.basis)
        return sum(w * v for w, v in zip(frame_weights(T, decay), losses))
    return validate


def _held_out_validation(clip: ClipResiduals, rig: GaussianRig, observations: Observations
                         ) -> Callable[[list[float], list[SimState]], float]:
    """θ, its trajectory of the fitted frames → the mean loss of the observed frames after them (the held-out frames,
    :attr:`JointConfig.held_out_frames`) in every observed view at full resolution, the trajectory continued to them
    at θ (+inf where the simulation fails there: such a θ is not kept)."""
    def validate(theta: list[float], trajectory: list[SimState]) -> float:
        T, fitted = observations.images.shape[1], len(trajectory)
        clip.apply(theta)
        try:
            with torch.no_grad():
                later = clip.sim.rollout(trajectory[-1], T - fitted)
        except SimulationError:
            return math.inf
        return sum(frame_losses(rig, later, observations, range(fitted, T), clip.basis)) / (T - fitted)
    return validate


def _gauss_newton(clip: ClipResiduals, parameters: list[Parameter], start: list[float], n: float, rig: GaussianRig,
                  observations: Observations, cfg: JointConfig, progress: bool,
                  on_iteration: Callable[[dict[str, Any]], None] | None) -> FitResult:
    """Levenberg–Marquardt from the coarse search's start
    (:func:`~vid2sim.reconstruct.gauss_newton.levenberg_marquardt`), kept by the full-resolution validation loss: of
    the fitted frames, or of the held-out frames after them (:attr:`JointConfig.held_out_frames`)."""
    from tqdm.auto import tqdm

    bar = tqdm(total=cfg.gauss_newton_iterations, desc="Gauss-Newton fit of the material and velocity",
               disable=not progress)

    def report(entry: dict[str, Any]) -> None:
        bar.update(1)
        bar.set_postfix(loss=f"{entry['loss']:.3e}", log10_E=f"{entry['log10_E']:.3f}", nu=f"{entry['nu']:.3f}")
        if on_iteration is not None:
            on_iteration(entry)

    try:
        held_out = cfg.held_out_frames > 0
        validate = _held_out_validation(clip, rig, observations) if held_out else \
            _full_resolution_validation(clip, rig, observations, cfg.frame_decay)
        return levenberg_marquardt(clip, parameters, start, n, cfg.gauss_newton_iterations, cfg.gauss_newton_tolerance,
                                   cfg.gauss_newton_patience, validate, report, validation_with_track=not held_out)
    finally:
        bar.close()


# ---- the stage -------------------------------------------------------------------------------------------------


def scene_density(ctx: Context) -> float:
    """kg/m³: the scene's ``metadata.density`` when it gives a number, else ``prior.density``."""
    value = ctx.scene.config.metadata.get("density")
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else ctx.config.prior.density


def stiffness_of(calibration: dict[str, Any]) -> float | StiffnessCurve:
    """The simulator's stiffness scale from the calibration record: a curve over ν, or one factor."""
    curve = calibration.get("stiffness_curve")
    return StiffnessCurve.from_dict(curve) if curve else calibration["stiffness_scale"]


def build_simulator(ctx: Context, state: State, mass_volumes: Tensor | None) -> Simulator:
    """The reduced simulator at the prior material (Stage I's when it ran), on the run's device."""
    cfg, obj, cub, o = ctx.config, state.obj, state.cubature, ctx.observed
    externals = [Gravity(list(o.gravity))]
    if o.floor_height is not None:
        externals.append(Floor(height=o.floor_height, stiffness=AREA_CONTACT_STIFFNESS,
                               friction=cfg.simulator.floor_friction))
    E, nu = prior_material(cfg, state.stage1)
    return Simulator(state.skinning, obj.points[cub.index], cub.weights,
                     Material(E, nu, scene_density(ctx), damping_ratio=cfg.prior.damping), externals,
                     cfg.simulator.integration, jacobian=state.jacobian,
                     use_neural_jacobian=state.jacobian is not None, length_scale=obj.scale,
                     contact_points=obj.contact_points, contact_weights=obj.contact_areas,
                     stiffness_scale=stiffness_of(state.calibration), volumetric=cfg.simulator.volumetric,
                     mass_volumes=mass_volumes)


class JointStage:
    """The joint optimisation (``config.joint``) from the prior material; writes ``joint.json`` and the networks
    as it left them. Loading it assembles the asset (:class:`~vid2sim.asset.Asset`) in ``state.asset``."""

    name = "joint"
    sections = ("joint", "simulator", "prior")
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        return "joint optimisation of the material, initial velocity and networks"

    def run(self, ctx: Context, state: State) -> None:
        cfg, o, v = ctx.config, ctx.observed, state.velocity
        joint_cfg = cfg.joint
        if state.stage1["ran"]:  # the coarse grid centred on Stage I's E
            joint_cfg = replace(cfg.joint, coarse_log10_E=tuple(state.stage1["coarse_log10_E"]))
        sim = build_simulator(ctx, state, state.cubature.mass_volumes)
        contacts, record = None, None
        if joint_cfg.contact_search and o.floor_height is not None:
            contacts, record = contact_candidates(ctx, state)
        track = None
        if joint_cfg.track_sd is not None and joint_cfg.method == "gauss_newton":
            track = hull_track(o.masks_cpu, o.cameras_cpu, joint_cfg.track_resolution, progress=ctx.progress)
        result = joint_optimisation(sim, state.gaussians, Observations(o.images, o.cameras), v["linear"],
                                    v["angular"], v["centre"], joint_cfg, progress=ctx.progress, contacts=contacts,
                                    track=track,
                                    rollout_processes=ctx.rollout_processes if ctx.device.type == "cpu" else 0)
        if result.contact_surface != "hull":
            points, areas = contacts[result.contact_surface]
            save_torch_atomic({"points": points.cpu(), "areas": areas.cpu()}, ctx.path("contact_joint.pt"))
        save_torch_atomic(cpu_state(state.skinning), ctx.path("skinning_joint.pt"))
        if state.jacobian is not None:
            save_torch_atomic(cpu_state(state.jacobian), ctx.path("jacobian_joint.pt"))
        write_json_atomic(ctx.path("joint.json"), {**asdict(result), "contact_candidates": record})

    def load(self, ctx: Context, state: State) -> None:
        result = state.joint = read_json(ctx.path("joint.json"), "the joint optimisation's result")
        state.skinning.load_state_dict(torch.load(ctx.path("skinning_joint.pt"), weights_only=True))
        if state.jacobian is not None:
            state.jacobian.load_state_dict(torch.load(ctx.path("jacobian_joint.pt"), weights_only=True))
        state.log.update(coarse_search=result["coarse"], centre_of_mass_search=result.get("centre_of_mass_search", []),
                         iterations=result["log"],
                         joint_fit={"method": result.get("method", "windows"), "stop": result.get("stop", ""),
                                    "start_validation_loss": result.get("start_validation_loss"),
                                    "validation_loss": result["validation_loss"],
                                    "information_by_frame": result.get("information_by_frame", {}),
                                    "track": result.get("track", {})})
        if result.get("contact_candidates"):
            state.log["contact_candidates"] = result["contact_candidates"]
        state.asset = assemble_asset(ctx, state)


def contact_candidates(ctx: Context, state: State) -> tuple[dict[str, tuple[Tensor, Tensor]], dict[str, Any]]:
    """The contact surfaces the coarse search tries (``JointConfig.contact_search``): the hull's own; when the rigid
    poses tracked from the masks put some of its voxels below the floor, the surface without them ("floor-carved",
    :func:`~vid2sim.reconstruct.stages.points.floor_carved_contact`); and when the poses of the frames whose rigid
    fit is as good as in flight (:func:`~vid2sim.reconstruct.stages.points.rigid_frames`) carve less, that surface
    too ("floor-carved-rigid": a soft object's squash is not carved as keel). Also a record of the carves for
    joint.json (``skipped`` says why there is no carved surface when the poses would sink nearly all of the hull)."""
    o, obj, points_cfg = ctx.observed, state.obj_cpu, ctx.config.points
    poses = track_poses(obj.points, o.masks_cpu, o.cameras_cpu, max_points=points_cfg.track_points,
                        seed=points_cfg.seed)
    contacts = {"hull": (obj.contact_points, obj.contact_areas)}
    record: dict[str, Any] = {"voxels": obj.kept_voxels, "tracked_frames": poses.num_frames,
                              "residuals_px": [round(float(x), 4) for x in poses.residuals_px]}
    try:
        carved, areas, removed = floor_carved_contact(obj, poses.rotations, poses.translations, o.floor_height,
                                                      config=points_cfg)
        record["floor_carved_voxels"] = removed
        if removed:
            contacts["floor-carved"] = (carved, areas)
    except ValueError as exc:  # the poses sink (nearly) all of it: no surface to offer; the record says why
        record.update(floor_carved_voxels=None, skipped=str(exc))
        removed = None
    ratio = ctx.config.joint.contact_search_residual_ratio
    if ratio is None or removed == 0:  # no third surface asked for, or no frame's pose sinks anything
        return contacts, record
    rigid = rigid_frames(poses.residuals_px, ratio)
    if rigid.all():  # every frame fits as in flight: the same carve
        return contacts, record
    # a squash's poses may sink all of the hull; the rigid frames' need not
    record["rigid_frames"] = [int(t) for t in rigid.nonzero()[0]]
    try:
        carved, areas, fewer = floor_carved_contact(obj, poses.rotations[rigid], poses.translations[rigid],
                                                    o.floor_height, config=points_cfg)
    except ValueError as exc:
        record.update(floor_carved_rigid_voxels=None, skipped_rigid=str(exc))
        return contacts, record
    record["floor_carved_rigid_voxels"] = fewer
    if fewer and (removed is None or fewer < removed):
        contacts["floor-carved-rigid"] = (carved, areas)
    return contacts, record


def assemble_asset(ctx: Context, state: State) -> Asset:
    """The asset of the joint stage's result (on the CPU); the centre-of-mass search's offset, if any, moves the
    lumped masses."""
    cfg, obj, obj_cpu, cub, result, o = ctx.config, state.obj, state.obj_cpu, state.cubature, state.joint, ctx.observed
    mass_volumes = cub.mass_volumes
    offset = torch.tensor(result.get("centre_of_mass_offset", [0.0, 0.0, 0.0]), dtype=torch.float64)
    if bool(offset.ne(0).any()):  # the joint stage's search moved the centre of mass: the same masses again
        mass_volumes = centre_shifted_volumes(obj.points[cub.index],
                                              cub.weights if mass_volumes is None else mass_volumes,
                                              offset).to(cub.weights)
    stiffness = stiffness_of(state.calibration)
    material = {"model": "neo-hookean", "E": float(10.0 ** result["log10_E"]), "log10_E": result["log10_E"],
                "nu": result["nu"], "density": scene_density(ctx), "damping_ratio": result["damping_ratio"],
                "stiffness_scale": stiffness.at(result["nu"]) if isinstance(stiffness, StiffnessCurve) else stiffness,
                "volumetric": cfg.simulator.volumetric}
    if isinstance(stiffness, StiffnessCurve):
        material["stiffness_curve"] = stiffness.to_dict()
    if result.get("uncertainty"):
        material["uncertainty"] = result["uncertainty"]
    index = cub.index.cpu()
    contact_points, contact_areas = obj_cpu.contact_points, obj_cpu.contact_areas
    if result.get("contact_surface", "hull") != "hull":  # the coarse search's choice (JointConfig.contact_search)
        chosen = torch.load(ctx.path("contact_joint.pt"), weights_only=True)
        contact_points, contact_areas = chosen["points"], chosen["areas"]
    return Asset(gaussians=state.gaussians.to("cpu"), field=copy.deepcopy(state.skinning).to("cpu"),
                 jacobian=copy.deepcopy(state.jacobian).to("cpu") if state.jacobian is not None else None,
                 material=material, cubature_points=obj_cpu.points[index], cubature_weights=cub.weights.cpu(),
                 contact_points=contact_points, contact_areas=contact_areas, points=obj_cpu.points,
                 volume=obj.volume, sim_config=cfg.simulator.integration,
                 mass_volumes=None if mass_volumes is None else mass_volumes.detach().cpu(),
                 gravity=list(o.gravity), floor_height=o.floor_height, floor_stiffness=AREA_CONTACT_STIFFNESS,
                 floor_friction=float(result.get("floor_friction", cfg.simulator.floor_friction)),
                 length_scale=obj.scale,
                 initial_velocity={"linear": result["linear_velocity"], "angular": result["angular_velocity"],
                                   "centre": state.velocity["centre"]},
                 dt=o.dt,
                 extra={"canonical_frame": {"centre": obj_cpu.centre.tolist(), "scale": obj.scale,
                                            "maps": "X -> (X - centre) / scale"},
                        "scene": str(ctx.scene.root), "observed_views": list(o.views), "observed_frames": o.frames,
                        "scene_frames": int(ctx.scene.images.shape[1]), "volume_m3": obj.volume,
                        "gaussians": state.gaussians.num, "initial_velocity_estimate": state.velocity,
                        "validation_loss": result["validation_loss"],
                        "start_validation_loss": result.get("start_validation_loss"),
                        "joint_method": result.get("method", "windows"), "centre_of_mass_offset": offset.tolist(),
                        "contact_surface": result.get("contact_surface", "hull")})
