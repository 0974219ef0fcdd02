"""The settings of ``vid2sim reconstruct``: one nested dataclass per stage, the presets as data.

:class:`ReconstructConfig` is saved as the asset's ``config.json`` and loads back with
:meth:`ReconstructConfig.from_dict` (``vid2sim reconstruct --config ASSET/config.json`` repeats a run). Every
leaf field is a command-line flag ``--section.field`` (:mod:`vid2sim.runtime.config`); its help is the field's
entry in its class docstring, so a new option is one documented field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from vid2sim.physics.cubature import CUBATURE_WEIGHTS
from vid2sim.physics.solver import SimConfig
from vid2sim.physics.tet_modes import LOCAL_MODE_PARTICIPATION
from vid2sim.reconstruct.photo_poses import LOSSES as PHOTOMETRIC_LOSSES
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.fitting import FitConfig


@dataclass
class PointsConfig:
    """Settings of :func:`object_points`.

    Attributes:
        resolution: voxels along the longest side of the hull's box (fine carving pass).
        num_points: interior samples drawn (skinning training and cubature choose among them).
        depth_tolerance: how far (in voxels) a hull voxel may lie in front of the Gaussians' rendered
            surface before it is carved (0.75 since 2026-12-04; 1.5 before: on four seed-3 scenes 0.75 gave better
            images and centres of mass, docs/results.md "A tighter depth carving").
        alpha_threshold: the rendered opacity above which a pixel's depth is trusted.
        depth_planes: depth planes per view on which the Gaussians' surface depth is found
            (:func:`vid2sim.splats.surface_depth.surface_depth`; its resolution is the object's depth / planes).
        surface_opacity: the opacity accumulated along a ray that marks the Gaussians' surface for the depth
            carving (½ is the median depth; lower carves less where the front Gaussians are faint).
        mask_threshold: mask values above it count as object.
        max_contact_points: the surface voxels are reduced to at most this many contact points (farthest-point
            sampling; each keeps the area of the voxels nearest to it) — the contact's cost grows with them.
        seed: seeds the sampling.
        frame_rounds: rounds of carving with the later frames' masks (:mod:`vid2sim.reconstruct.stages.points`; 0: the
            frame-0 hull only).
        frame_residual_ratio: a frame carves only if its rigid pose fits its silhouettes with a residual at most
            this many times frame 0's.
        free_flight_tolerance: a frame carves only if the tracked centroid's acceleration is within this
            fraction of |g| of gravity (no contact).
        coverage_tolerance: a frame carves only if that uncovers at most this fraction of every mask of frame 0
            and of the frames chosen before it.
        track_points: surface samples the tracking fits to the silhouettes.
        carve_margin_px: a later frame carves a voxel only if its centre projects more than this many pixels
            outside a mask, on the mask's sub-pixel signed distance (0: at the mask's 0.5 iso-line; on the small
            suite 0.25 gave the same images and a worse E, README).
    """

    resolution: int = 64
    num_points: int = 20000
    depth_tolerance: float = 0.75
    alpha_threshold: float = 0.5
    depth_planes: int = 32
    surface_opacity: float = 0.2
    mask_threshold: float = 0.5
    max_contact_points: int = 1000
    seed: int = 0
    frame_rounds: int = 2
    frame_residual_ratio: float = 4.0
    free_flight_tolerance: float = 0.5
    coverage_tolerance: float = 0.01
    track_points: int = 5000
    carve_margin_px: float = 0.0

    def __post_init__(self) -> None:
        if self.frame_rounds < 0 or self.track_points < 4:
            raise ConfigError(f"PointsConfig.frame_rounds must be >= 0 and track_points >= 4, got {self.frame_rounds}, "
                             f"{self.track_points}")
        if not (isinstance(self.carve_margin_px, (int, float)) and 0 <= self.carve_margin_px < math.inf):
            raise ConfigError(
                f"PointsConfig.carve_margin_px must be a finite number >= 0, got {self.carve_margin_px!r}"
            )
        for name in ("frame_residual_ratio", "free_flight_tolerance", "coverage_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"PointsConfig.{name} must be a finite number > 0, got {value!r}")
        if isinstance(self.depth_planes, bool) or not isinstance(self.depth_planes, int) or self.depth_planes < 2:
            raise ConfigError(f"PointsConfig.depth_planes must be an integer >= 2, got {self.depth_planes!r}")
        if isinstance(self.surface_opacity, bool) or not isinstance(self.surface_opacity, (int, float)) \
                or not 0 < self.surface_opacity < 1:
            raise ConfigError(f"PointsConfig.surface_opacity must lie in (0, 1), got {self.surface_opacity!r}")
        if self.resolution < 8:
            raise ConfigError(f"PointsConfig.resolution must be >= 8, got {self.resolution}")
        if self.num_points < 100:
            raise ConfigError(f"PointsConfig.num_points must be >= 100, got {self.num_points}")
        if self.max_contact_points < 1:
            raise ConfigError(f"PointsConfig.max_contact_points must be >= 1, got {self.max_contact_points}")
        if self.depth_tolerance < 0:
            raise ConfigError(f"PointsConfig.depth_tolerance must be >= 0, got {self.depth_tolerance}")


@dataclass
class VelocityConfig:
    """Stage ``velocity``: the initial rigid velocity from the ballistic pre-contact frames.

    Attributes:
        frames: at most this many pre-contact frames estimate the initial velocity.
        photometric_iterations: the silhouette poses of the pre-contact frames refined on the images, with the
            frame-0 Gaussians moved rigidly (:mod:`vid2sim.reconstruct.photo_poses`): Adam steps per frame; 0 keeps
            the silhouette poses. The velocity is refitted to the refined poses.
        photometric_size: the refinement's loss images' longer side at most (pixels; the renders, made at the
            cameras' size, and the images area-averaged to it; 0: the images' own size).
        photometric_views: the refinement reads at most this many observed views, spread over them (0: all): its
            renders are made at the cameras' size, so at 448² each view costs as much as twelve at 128².
        photometric_loss: ``"l1"`` (the colours) or ``"gradients"`` (their differences between neighbouring pixels,
            less swayed by the frame-0 shading the Gaussians carry while the light stays put: on six seed-2 runs,
            three scenes clean and as twins, frame 3's turn 0.3–1.2° off against 0.3–2.9° with ``"l1"``; end to end on
            eight runs the images and the material within the noise of ``"l1"``'s, the rotation 5.7 → 4.8° off;
            docs/capture.md, ninth entry).
    """

    frames: int = 8
    photometric_iterations: int = 150
    photometric_size: int = 128
    photometric_views: int = 4
    photometric_loss: str = "l1"

    def __post_init__(self) -> None:
        if self.frames < 2:
            raise ConfigError(f"VelocityConfig.frames must be >= 2, got {self.frames}")
        if self.photometric_loss not in PHOTOMETRIC_LOSSES:
            raise ConfigError(f"VelocityConfig.photometric_loss must be one of {PHOTOMETRIC_LOSSES}, got "
                              f"{self.photometric_loss!r}")
        if min(self.photometric_iterations, self.photometric_size, self.photometric_views) < 0:
            raise ConfigError("VelocityConfig.photometric_iterations, photometric_size and photometric_views must be "
                              f">= 0, got {self.photometric_iterations}, {self.photometric_size} and "
                              f"{self.photometric_views}")


@dataclass
class AppearanceConfig:
    """Stage ``appearance``: the Gaussians refined on all ballistic frames at once.

    Attributes:
        iterations: Gaussian refinement steps on the ballistic frames (0: skip).
    """

    iterations: int = 300

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ConfigError(f"AppearanceConfig.iterations must be >= 0, got {self.iterations}")


@dataclass
class Stage1Config:
    """Stage ``stage1``: the feed-forward predictor (paper §4.1).

    Attributes:
        enabled: run the Stage I predictor; off (the default until the shipped predictor meets its targets,
            docs/predictor.md) is the paper's "w/o Stage I" ablation.
        predictor: its checkpoint (None: the one shipped with vid2sim).
    """

    enabled: bool = False
    predictor: str | None = None


@dataclass
class NetworksConfig:
    """Stage ``networks``: the skinning field (and the Neural Jacobian) trained data-free.

    Attributes:
        handles: learned skinning handles (+1 rigid); more let the subspace squash and bend closer to the
            continuum at a higher cost per step (Stage I's template has 10).
        skinning_iterations: data-free skinning iterations (paper: 10 000).
        skinning_objective: "modal" (the subspace's lowest vibration modes; the default) or "random_z" (the
            paper's random handle transforms); docs/architecture.md, "Subspace stiffness".
        jacobian: dF/dz: "closed_form" (exact, from the field; faster on a CPU) or "neural" (the paper's Neural
            Jacobian).
        jacobian_iterations: data-free Neural Jacobian iterations when ``jacobian`` is "neural".
    """

    handles: int = 10
    skinning_iterations: int = 2000
    skinning_objective: Literal["modal", "random_z"] = "modal"
    jacobian: Literal["closed_form", "neural"] = "closed_form"
    jacobian_iterations: int = 2000

    def __post_init__(self) -> None:
        if self.jacobian not in ("closed_form", "neural"):
            raise ConfigError(f"NetworksConfig.jacobian must be 'closed_form' or 'neural', got {self.jacobian!r}")
        if self.skinning_objective not in ("modal", "random_z"):
            raise ConfigError("NetworksConfig.skinning_objective must be one of ('random_z', 'modal'), "
                              f"got {self.skinning_objective!r}")
        for name in ("handles", "skinning_iterations", "jacobian_iterations"):
            if getattr(self, name) < 1:
                raise ConfigError(f"NetworksConfig.{name} must be >= 1, got {getattr(self, name)}")


@dataclass
class PriorConfig:
    """The material the joint optimisation starts from when Stage I does not run (Stage I replaces E and ν).

    Attributes:
        E: Young's modulus in Pa.
        nu: Poisson's ratio.
        damping: the damping ratio ζ (Kelvin–Voigt; held there unless ``joint.fit_damping``).
        density: kg/m³ when the scene's metadata gives none (a drop identifies E/ρ only).
    """

    E: float = 1e5
    nu: float = 0.3
    damping: float = 0.05
    density: float = 1000.0

    def __post_init__(self) -> None:
        if not (self.E > 0 and 0 <= self.nu < 0.5 and self.density > 0 and self.damping >= 0):
            raise ConfigError("PriorConfig needs E > 0, 0 <= nu < 0.5, damping >= 0 and density > 0, got "
                              f"E={self.E}, nu={self.nu}, damping={self.damping}, density={self.density}")


@dataclass
class SimulatorConfig:
    """The reduced simulator the joint optimisation fits and the asset carries.

    Attributes:
        cubature: cubature points (paper: 500).
        volumetric: the volumetric term, "pointwise" or "projected" onto the skinning weights' span
            (:mod:`vid2sim.physics.volumetric`: no volumetric locking, so λ needs no factor of its own; calibrate
            it with ``calibration.nu`` "curve").
        cubature_weights: the cubature points' integration volumes and lumped masses, "voronoi" (each point's cell,
            :func:`~vid2sim.physics.cubature.voronoi_weights`; the default since it was measured on eight full-preset
            scenes, docs/architecture.md "Voronoi volumes are the default") or "equal" (the paper's: the volume / K
            each, which puts farthest-point sampling's boundary layer at a whole cell's mass).
        mass: lumped masses: "cubature" (the cubature volumes; the default) or "moments" (those volumes
            corrected so that the mass, centre of mass and inertia tensor are the kept voxels',
            :mod:`vid2sim.physics.mass`).
        integration: time integration (time-converged BDF2 substeps by default).
        floor_friction: the Coulomb friction coefficient μ of the floor the object lands on (smoothed below a slip
            speed of 1 cm/s); 0, the paper's frictionless floor, by default. The asset carries it (the fitted one
            with ``joint.fit_friction``).
    """

    cubature: int = 500
    volumetric: Literal["pointwise", "projected"] = "pointwise"
    cubature_weights: Literal["equal", "voronoi"] = "voronoi"
    mass: Literal["cubature", "moments"] = "cubature"
    integration: SimConfig = field(default_factory=SimConfig)
    floor_friction: float = 0.0

    def __post_init__(self) -> None:
        if self.cubature < 1:
            raise ConfigError(f"SimulatorConfig.cubature must be >= 1, got {self.cubature}")
        if self.volumetric not in ("pointwise", "projected"):
            raise ConfigError(f"SimulatorConfig.volumetric must be 'pointwise' or 'projected', got {self.volumetric!r}")
        if self.cubature_weights not in CUBATURE_WEIGHTS:
            raise ConfigError(f"SimulatorConfig.cubature_weights must be one of {CUBATURE_WEIGHTS}, "
                              f"got {self.cubature_weights!r}")
        if self.mass not in ("moments", "cubature"):
            raise ConfigError(f"SimulatorConfig.mass must be 'moments' or 'cubature', got {self.mass!r}")
        if isinstance(self.floor_friction, bool) or not isinstance(self.floor_friction, (int, float)) \
                or not 0 <= self.floor_friction < math.inf:
            raise ConfigError("SimulatorConfig.floor_friction must be a Coulomb coefficient >= 0 (0: frictionless), "
                              f"got {self.floor_friction!r}")


@dataclass
class CalibrationConfig:
    """Stage ``calibration``: the subspace's stiffness matched to quadratic tets (:mod:`~.stages.calibration`).

    Attributes:
        enabled: scale the simulator's elastic energy so that the subspace's lowest modes vibrate at the
            frequencies of quadratic tets on a surface of the kept voxels: the subspace is stiffer than the
            continuum, and the fitted E is then the material's. fTetWild is not deterministic, so a calibrated
            reconstruction is not bit-reproducible.
        nu: "two_factor" (the default): a factor on μ and one on λ over a grid of ν, matched to the six lowest
            modes and used at the simulator's current ν; "curve": one factor s(ν) over that grid; "prior": one
            factor at the prior ν.
        cells: the surface grid's cells along the longest side for the reference mesh.
        points: samples of the kept voxels that grid is made from.
        min_participation: the reference mesh's modes that move less than this share of the mass are left out
            (a sliver of the hull on a hinge of a few tets vibrates alone, below the body's modes; matched, it
            softened a seed-2 scene's subspace 7×; :func:`vid2sim.physics.tet_modes.mode_participation`); 0 keeps
            every mode.
    """

    enabled: bool = True
    nu: Literal["two_factor", "curve", "prior"] = "two_factor"
    cells: int = 96
    points: int = 200_000
    min_participation: float = LOCAL_MODE_PARTICIPATION

    def __post_init__(self) -> None:
        if self.nu not in ("curve", "two_factor", "prior"):
            raise ConfigError(f"CalibrationConfig.nu must be 'curve', 'two_factor' or 'prior', got {self.nu!r}")
        for name in ("cells", "points"):
            if getattr(self, name) < 1:
                raise ConfigError(f"CalibrationConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.min_participation < 1.0:
            raise ConfigError(f"CalibrationConfig.min_participation must be in [0, 1), got {self.min_participation}")


@dataclass
class JointConfig:
    """Settings of :func:`joint_optimisation` (defaults: the paper's, plus the CPU measures above).

    Attributes:
        method: "gauss_newton" (the default, beyond the paper): Levenberg–Marquardt on the physical parameters
            (log10 E, ν, ζ, the initial linear and angular velocity) over the whole observed clip, with a Gaussian
            prior on the material (:mod:`vid2sim.reconstruct.gauss_newton`); the networks stay as trained
            data-free; at most ``gauss_newton_iterations`` steps. On the 8-scene quadratic-tet small suite it
            beat the coarse search's start on 7 scenes (the windows on 4), with images and E as good or better
            (docs/results.md, "The quadratic-tet small suite"). "windows" (the paper's): Adam on random windows of
            ``window`` frames (``iterations``, the learning rates; the networks too where their learning rates
            are > 0). :meth:`method_iterations` and :meth:`with_iterations` read and set the iterations of the
            chosen method (``--iterations``). Either method reports the material's intervals.
        gauss_newton_iterations: at most this many Gauss–Newton Jacobians (each p + 1 rollouts of the clip at
            ``coarse_scale``).
        gauss_newton_tolerance: stop when an accepted step lowers the posterior objective Φ (a negative
            log-likelihood) by less than this, or when the Gauss–Newton model predicts less before any trial step is
            simulated. A step worth 0.05 moves the parameters by √(2 · 0.05) ≈ 0.3 of their noise-only standard
            deviation; on 12 scenes the steps after the first below it moved log10 E by at most 0.004 and ν by at
            most 0.001, and cost up to three Jacobians (p + 1 rollouts each) per scene.
        gauss_newton_patience: stop when the validation loss has not improved for this many accepted steps.
        held_out_frames: the last this many observed frames are left out of the Gauss–Newton fit (its residuals,
            its track and its effective number of images) and judge its steps instead: the kept θ is the best by
            their loss at full resolution (equal weights), the start included, and the patience counts steps that
            did not improve it. 0 (the default): the validation is the fit's own frames at full resolution. On four
            full-preset scenes 3 held-out frames stopped a fit that overfitted the observed frames (future frames
            +2.0 dB) but did not beat the default, and cost ν where late frames disagreed with a step toward the
            truth (docs/results.md, "Held-out frames").
        prior_sd_log10_E, prior_sd_nu, prior_sd_damping: standard deviations of the Gaussian prior on log10 E, ν
            and ζ, centred on the start material (``prior``, or Stage I's prediction): the Gauss–Newton fit's
            regulariser, and the yardstick of identifiability (a parameter the images constrain less tightly than
            this is reported as not identifiable from the video).
        interval_level: probability of the material's reported intervals (``material.json`` ``uncertainty``;
            a Laplace approximation at the fit, :mod:`vid2sim.reconstruct.uncertainty`).
        model_error_log10_E, model_error_nu: the reduced model's own error in log10 E and ν, added to the image
            noise's in the reported intervals (:mod:`vid2sim.reconstruct.uncertainty`): the RMS error of the
            Gauss–Newton fits on the 8-scene quadratic-tet small suite against its FEM truth (0.195 decade and
            0.091; docs/results.md), where the noise alone held the truth on 2 of 8. 0: the image noise alone
            (right for the model's own motion).
        log10_E_bounds: log10 E is kept in this interval by the Gauss–Newton fit.
        iterations: Adam iterations (``method`` "windows"; not used by "gauss_newton").
        window: frames per window (Δs).
        lr_log10_E, lr_nu, lr_skinning, lr_jacobian: the paper's learning rates.
        lr_velocity: learning rate of the initial linear (m/s) and angular (rad/s) velocity.
        fit_damping: also fit the damping ratio ζ (beyond the paper: the damping is a property of the object,
            and held at its prior the bounce's energy loss is absorbed by E); otherwise (the default) it stays at
            its prior. ``windows`` fits it with the learning rate ``lr_damping``.
        fit_friction: also fit the floor's Coulomb friction μ: the coarse search runs over E at each friction of
            ``coarse_friction`` (and ``simulator.floor_friction``; after the first, each walks the E grid downhill
            from the best E so far) and starts from the best pair, then the
            Gauss–Newton fit refines μ in ``friction_bounds`` with a Gaussian prior of standard deviation
            ``prior_sd_friction`` centred on ``simulator.floor_friction`` (the windows' Adam, which has no gradient
            to μ, keeps the coarse search's). After the first bounce friction decides whether the object slides or
            rolls, and where it comes to rest. On by default (beyond the paper, whose floor is frictionless): on a
            drop by an independent engine with μ = 0.5 it found μ = 0.42 and cut the centre of mass's error over
            the observed frames from 11.2 to 1.2 cm; on our frictionless FEM's drop it found 0.004 (docs/results.md,
            "Floor friction"). Off: the floor keeps ``simulator.floor_friction``.
        coarse_log10_E: grid of the coarse search (empty: skip it).
        contact_search: also try, in the coarse search, the contact surface without the voxels that the rigid poses
            tracked from the masks put below the floor (``reconstruct.stages.points.floor_carved_contact``), and
            keep the surface of the best grid point (it needs the coarse search and a floor). On by default since
            a one-code A/B (docs/capture.md, "eighth entry"): on 10 clean scenes (6 of the seed-2 suite, 4 of an
            unseen seed-9 suite) the video kept a carved surface on 6, and the means rose from 28.95 to 29.52 dB
            (observed frames) and 24.47 to 24.93 dB (future frames), |Δlog10 E| fell from 0.133 to 0.084; on the
            6 seed-2 capture twins it kept one on 4 and the means rose by 0.84 / 0.77 dB, |Δlog10 E| from 0.247 to
            0.172. Where the video keeps the hull nothing changes. Four views from above leave the hull reaching
            below the object, and that keel meets the floor first: on a stiff scene of the seed-2 suite the hull
            was fitted 0.86 decade soft, and 0.31 decade stiff with that surface (docs/results.md).
        contact_search_residual_ratio: with ``contact_search``, a third surface is tried when it differs: the hull
            carved with the poses of the frames whose rigid fit is about as good as in flight only
            (:func:`~vid2sim.reconstruct.stages.points.rigid_frames`: silhouette residual at most this many times
            the median of the first three frames). A soft object squashes at the contact, its rigid pose then sinks
            below the floor, and every frame's carve takes the squash for keel (docs/capture.md, "seventh entry").
            None: the two surfaces only.
        coarse_scale: image scale of the coarse search, the Gauss–Newton fit and the first ``coarse_fraction`` of the
            iterations (targets and renders, made at full size, area-averaged to it).
        coarse_fraction: fraction of the iterations rendered at ``coarse_scale`` (then full resolution).
        views_per_iteration: views rendered per iteration (None: all observed views).
        refresh_every: iterations between the whole rollouts that provide the windows' start states.
        validate_every: iterations between validations on all observed frames and views.
        nu_bounds: ν is kept in this interval.
        centre_of_mass_step: the first step of a search over the centre of mass after the coarse search, as a
            fraction of the simulator's length scale (the object's diagonal); 0 (the default): no search. See
            :func:`centre_of_mass_search`.
        centre_of_mass_rounds: rounds of that search, each with half the step of the one before.
        frame_decay: weights exp(−(t − 1)/τ) on the frames t = 1 … T−1 of the coarse search's and the
            validation's whole-clip losses, τ = ``frame_decay`` frames (default 4, beyond the paper); None:
            equal weights (the paper's mean over the clip). See :func:`~vid2sim.reconstruct.clip.clip_loss`. On the
            quadratic-tet small suite (8 scenes) τ = 4 gave |Δlog10 E| 0.30 against 0.37 with equal weights.
        track_sd: the standard deviation of the hull track (the displacement of each observed frame's visual-hull
            centroid from frame 0's, :mod:`vid2sim.reconstruct.hull_track`) as a fraction of the object's diagonal;
            with it, the Gauss–Newton fit also matches the simulated centre of mass's displacement to that track
            (:class:`~vid2sim.reconstruct.stages.joint.ClipResiduals`). None (the default): no track term.
        track_resolution: voxels per side of each frame's hull for the track.
        track_volume_tolerance: a frame whose hull's volume differs from frame 0's by more than this fraction has its
            standard deviation widened by the ratio (the body deformed; :meth:`HullTrack.frame_sd
            <vid2sim.reconstruct.hull_track.HullTrack.frame_sd>`); None: ``track_sd`` in every frame.
        seed: seeds the windows and view subsets.
    """

    method: Literal["gauss_newton", "windows"] = "gauss_newton"
    gauss_newton_iterations: int = 8
    gauss_newton_tolerance: float = 0.05
    gauss_newton_patience: int = 2
    held_out_frames: int = 0
    prior_sd_log10_E: float = 1.0
    prior_sd_nu: float = 0.1
    prior_sd_damping: float = 0.05
    interval_level: float = 0.68
    model_error_log10_E: float = 0.2
    model_error_nu: float = 0.09
    log10_E_bounds: tuple[float, float] = (3.0, 7.0)
    iterations: int = 400
    window: int = 4
    lr_log10_E: float = 5e-3
    lr_nu: float = 1e-3
    lr_skinning: float = 5e-7
    lr_jacobian: float = 5e-7
    lr_velocity: float = 5e-3
    fit_damping: bool = False
    lr_damping: float = 1e-3
    fit_friction: bool = True
    prior_sd_friction: float = 0.5
    friction_bounds: tuple[float, float] = (0.0, 2.0)
    coarse_friction: tuple[float, ...] = (0.0, 0.5)
    coarse_log10_E: tuple[float, ...] = (4.0, 4.25, 4.5, 4.75, 5.0, 5.25, 5.5, 5.75, 6.0)
    contact_search: bool = True
    contact_search_residual_ratio: float | None = 1.25
    coarse_scale: float = 0.5
    coarse_fraction: float = 0.5
    views_per_iteration: int | None = None
    refresh_every: int = 10
    validate_every: int = 50
    nu_bounds: tuple[float, float] = (0.0, 0.49)
    frame_decay: float | None = 4.0
    centre_of_mass_step: float = 0.0
    centre_of_mass_rounds: int = 2
    track_sd: float | None = None
    track_resolution: int = 64
    track_volume_tolerance: float | None = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("gauss_newton", "windows"):
            raise ConfigError(f"JointConfig.method must be 'gauss_newton' or 'windows', got {self.method!r}")
        if self.gauss_newton_iterations < 0 or self.gauss_newton_patience < 1:
            raise ConfigError("JointConfig.gauss_newton_iterations must be >= 0 and gauss_newton_patience >= 1, got "
                              f"{self.gauss_newton_iterations}, {self.gauss_newton_patience}")
        if isinstance(self.held_out_frames, bool) or not isinstance(self.held_out_frames, int) \
                or self.held_out_frames < 0:
            raise ConfigError(f"JointConfig.held_out_frames must be an integer >= 0, got {self.held_out_frames!r}")
        if self.held_out_frames and self.method != "gauss_newton":
            raise ConfigError("JointConfig.held_out_frames needs the gauss_newton method (the windows validate on the "
                              f"whole clip), got method {self.method!r}")
        for name in ("gauss_newton_tolerance", "prior_sd_log10_E", "prior_sd_nu", "prior_sd_damping",
                     "prior_sd_friction"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < float(value) < math.inf:
                raise ConfigError(f"JointConfig.{name} must be a finite number > 0, got {value!r}")
        if not 0 < self.interval_level < 1:
            raise ConfigError(f"JointConfig.interval_level must lie in (0, 1), got {self.interval_level}")
        for name in ("model_error_log10_E", "model_error_nu"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= float(value) < math.inf:
                raise ConfigError(f"JointConfig.{name} must be a finite number >= 0, got {value!r}")
        ratio = self.contact_search_residual_ratio
        if ratio is not None and (isinstance(ratio, bool) or not isinstance(ratio, (int, float))
                                  or not 1.0 <= float(ratio) < math.inf):
            raise ConfigError(f"JointConfig.contact_search_residual_ratio must be a finite number >= 1 or None, got "
                              f"{ratio!r}")
        lo, hi = self.log10_E_bounds
        if not lo < hi:
            raise ConfigError(f"JointConfig.log10_E_bounds must satisfy lo < hi, got {self.log10_E_bounds}")
        if self.iterations < 0:
            raise ConfigError(f"JointConfig.iterations must be >= 0, got {self.iterations}")
        if self.window < 1:
            raise ConfigError(f"JointConfig.window must be >= 1, got {self.window}")
        if not 0 < self.coarse_scale <= 1:
            raise ConfigError(f"JointConfig.coarse_scale must be in (0, 1], got {self.coarse_scale}")
        if not 0 <= self.coarse_fraction <= 1:
            raise ConfigError(f"JointConfig.coarse_fraction must be in [0, 1], got {self.coarse_fraction}")
        if self.views_per_iteration is not None and self.views_per_iteration < 1:
            raise ConfigError(f"JointConfig.views_per_iteration must be >= 1 or None, got {self.views_per_iteration}")
        if self.refresh_every < 1 or self.validate_every < 1:
            raise ConfigError("JointConfig.refresh_every and validate_every must be >= 1")
        for name in ("frame_decay", "track_sd", "track_volume_tolerance"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not 0 < float(value) < math.inf):
                raise ConfigError(f"JointConfig.{name} must be a finite number > 0 or None, got {value!r}")
        if isinstance(self.centre_of_mass_step, bool) or not isinstance(self.centre_of_mass_step, (int, float)) \
                or not 0 <= float(self.centre_of_mass_step) < 0.5:
            raise ConfigError("JointConfig.centre_of_mass_step must be a fraction of the object's size in [0, 0.5), "
                             f"got {self.centre_of_mass_step!r}")
        if isinstance(self.track_resolution, bool) or not isinstance(self.track_resolution, int) \
                or self.track_resolution < 8:
            raise ConfigError(f"JointConfig.track_resolution must be an integer >= 8, got {self.track_resolution!r}")
        if self.centre_of_mass_rounds < 1:
            raise ConfigError(f"JointConfig.centre_of_mass_rounds must be >= 1, got {self.centre_of_mass_rounds}")
        if any(not 0 <= float(mu) < math.inf for mu in self.coarse_friction):
            raise ConfigError("JointConfig.coarse_friction must hold Coulomb coefficients >= 0, got "
                              f"{self.coarse_friction}")
        lo, hi = self.friction_bounds
        if not 0 <= lo < hi < math.inf:
            raise ConfigError("JointConfig.friction_bounds must satisfy 0 <= lo < hi < inf, got "
                              f"{self.friction_bounds}")
        lo, hi = self.nu_bounds
        if not 0 <= lo < hi < 0.5:
            raise ConfigError(f"JointConfig.nu_bounds must satisfy 0 <= lo < hi < 0.5, got {self.nu_bounds}")
        self.coarse_log10_E = tuple(sorted(float(v) for v in self.coarse_log10_E))  # the parabola needs order

    def _iterations_field(self) -> str:
        """The field holding the chosen method's iterations."""
        return "gauss_newton_iterations" if self.method == "gauss_newton" else "iterations"

    def method_iterations(self) -> int:
        """The iterations of the chosen method: Gauss–Newton steps (``gauss_newton_iterations``) or Adam
        iterations (``iterations``)."""
        return getattr(self, self._iterations_field())

    def with_iterations(self, n: int) -> "JointConfig":
        """A copy whose chosen method runs ``n`` iterations (0: Stage II keeps the coarse search's start)."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ConfigError(f"the joint optimisation's iterations must be an integer >= 0, got {n!r}")
        return dataclasses.replace(self, **{self._iterations_field(): n})


@dataclass
class MotionAppearanceConfig:
    """Stage ``motion_appearance``: the Gaussians refitted on every observed frame through the simulated motion.

    Attributes:
        iterations: refitting steps (0: skip; the Gaussians of the ballistic frames are kept).
        geometry: also fit the Gaussians' rest-frame centres, scales and rotations (beyond the paper); off: colours
            and opacities only (the full preset's).
        shading: separate albedo from a light fixed in the world (:mod:`vid2sim.splats.shading`), so the asset is
            lit by its pose as it turns (beyond the paper); off: the colours keep the light they were fitted under.
        loss_power: p in (0, 1]: each step minimises (its image loss)^p; 1 is 3DGS's loss, below 1 the frames the
            simulated motion explains well count more (0.5: the square root).
    """

    iterations: int = 300
    geometry: bool = True
    shading: bool = True
    loss_power: float = 1.0

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ConfigError(f"MotionAppearanceConfig.iterations must be >= 0, got {self.iterations}")
        p = self.loss_power
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 < p <= 1:
            raise ConfigError(f"MotionAppearanceConfig.loss_power must be in (0, 1], got {p!r}")


@dataclass
class ContinuationConfig:
    """Stage ``continuation``: the state at the end of the observed clip fitted to its last frames, from which the
    captured drop goes on after them (the future frames' prediction; beyond the paper, whose prediction is the one
    rollout from frame 0).

    Attributes:
        window: the last observed frames the state is fitted to (≥ 2: a pose and a velocity); the state is that of
            their first frame. 0 skips the stage (the drop is one rollout from frame 0).
        iterations: Levenberg–Marquardt iterations of the fit (each 13 rollouts of the window).
        scale: image scale of the fit's images (the observed size 1; the full preset's 448² views take 0.5).
        check: first fit the window ending ``window`` frames earlier and use a continuation only if it predicts the
            last ``window`` frames better than the one rollout from frame 0 (needs 2·window + 1 observed frames;
            with fewer, or off, the continuation is always used).
    """

    window: int = 2
    iterations: int = 8
    scale: float = 1.0
    check: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window == 1 or self.window < 0:
            raise ConfigError(f"ContinuationConfig.window must be 0 (off) or an integer >= 2, got {self.window!r}")
        if self.iterations < 1:
            raise ConfigError(f"ContinuationConfig.iterations must be >= 1, got {self.iterations}")
        if not 0 < self.scale <= 1:
            raise ConfigError(f"ContinuationConfig.scale must be in (0, 1], got {self.scale}")


@dataclass
class ReconstructConfig:
    """Settings of :func:`vid2sim.reconstruct.reconstruct`, one section per stage (saved as ``config.json``).

    Attributes:
        gaussians: stage ``gaussians``, the Gaussians fitted to frame 0 (and the later fits' settings).
        points: stage ``points``, the interior points of the hull carved with the later frames.
        velocity: stage ``velocity``.
        appearance: stage ``appearance``.
        stage1: stage ``stage1``.
        networks: stage ``networks``.
        prior: the starting material.
        simulator: the reduced simulator.
        calibration: stage ``calibration``.
        joint: stage ``joint``, the joint optimisation.
        motion_appearance: stage ``motion_appearance``.
        continuation: stage ``continuation``.
        seed: seeds every stage.
    """

    gaussians: FitConfig = field(default_factory=lambda: FitConfig(iterations=1000))
    points: PointsConfig = field(default_factory=PointsConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    stage1: Stage1Config = field(default_factory=Stage1Config)
    networks: NetworksConfig = field(default_factory=NetworksConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    joint: JointConfig = field(default_factory=JointConfig)
    motion_appearance: MotionAppearanceConfig = field(default_factory=MotionAppearanceConfig)
    continuation: ContinuationConfig = field(default_factory=ContinuationConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.simulator.volumetric == "projected" and self.calibration.enabled and \
                self.calibration.nu == "two_factor":
            raise ConfigError("ReconstructConfig: the projected volumetric term does not lock, so its calibration "
                              "takes one factor (calibration.nu 'curve' or 'prior'), not 'two_factor'")

    @classmethod
    def preset(cls, name: str, overrides: dict[str, Any] | None = None) -> "ReconstructConfig":
        """The preset ``name`` ("small" or "full", :data:`PRESETS`) with the nested dict ``overrides`` on top."""
        if name not in PRESETS:
            raise ConfigError(f"unknown reconstruct preset {name!r} (expected one of {', '.join(PRESETS)})")
        return configs.merge(configs.merge(cls(), PRESETS[name]), overrides or {})

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "ReconstructConfig":
        """The configuration of a ``config.json`` (:meth:`to_dict`); missing fields take their defaults."""
        return configs.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready nested dict (``config.json``)."""
        return configs.to_dict(self)

    def replace(self, **changes: Any) -> "ReconstructConfig":
        """A copy with top-level fields replaced (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)


#: The presets, as overrides of the defaults (the defaults are the paper's where it gives one).
PRESETS: dict[str, dict[str, Any]] = {
    # CPU minutes: at most 6 000 Gaussians (4 views of 128² need no more; rendering cost grows with them), and the
    # networks fixed during the joint optimisation (the paper's learning rate of 5e-7 moves them imperceptibly in
    # 100 iterations, and their gradient costs a third of an iteration). View-independent colours (SH degree 0):
    # with 4 views, higher bands fit the views, not the object, and as the object moves they change its colour in
    # the joint optimisation's images (8-scene small suite: |Δlog10 E| 0.155 against 0.243 at degree 3, images
    # equal, 8 % faster; docs/results.md).
    # The last stage takes 2 000 steps (the default 300 left the small suite's Gaussians short of their fit: on its
    # 8 scenes +1.32 dB on the observed frames (all 8), +0.19 on the future frames (7 of 8), +0.47 on the held-out
    # views (6 of 8); 1 000 steps +0.93 / +0.09 / +0.39, 600 +0.59 / -0.01 / +0.23; learning rates decayed to a
    # tenth over 600 steps +0.09 / -0.15 / -0.16; docs/results.md).
    "small": {"gaussians": {"iterations": 500, "sh_degree": 0, "densify": {"max_gaussians": 6000}},
              "networks": {"skinning_iterations": 1000},
              "joint": {"iterations": 100, "validate_every": 25, "lr_skinning": 0.0, "lr_jacobian": 0.0},
              "motion_appearance": {"iterations": 2000}},
    # the paper's sizes. The last stage refits colours and opacities only: with 12 views the frame-0 fit is sharp
    # (40-45 dB on its views), and moving the Gaussians along a simulated motion that is off after the bounce blurs
    # it. On four full scenes colours only gave +0.5 dB on the observed frames, +0.3 on the held-out views, -0.5 on
    # the future frames (which the geometry's blur hedges) and +6.5 dB at rest (frame 0) (docs/results.md).
    # The Gauss-Newton fit also follows the 12 views' hull track at 1 % of the object's size (1 cm for a 1 m
    # diagonal): on three full scenes +0.4 dB observed, +0.1 future, +0.4 held-out views, the centre of mass 21 -> 13 mm
    # off over the observed frames, |dlog10 E| 0.18 -> 0.16, |dnu| 0.10 -> 0.14 (docs/results.md). The small
    # preset's 4-view hulls are not that accurate (their track is 7-18 mm off the truth's, as far as its fits are).
    # The solid is carved on 128 voxels a side: at 64 a voxel is 10-13 mm, three pixels of a 448² view, and the
    # depth carving's tolerance of 0.75 voxel left the solid 6.5-13 % larger than the object on five of six full scenes;
    # at 128 it is 1-5 % larger (docs/results.md "128 voxels at full size").
    "full": {"gaussians": {"iterations": 1000, "views_per_step": 2},
             "points": {"resolution": 128},
             "networks": {"skinning_iterations": 2000},
             "joint": {"iterations": 400, "views_per_iteration": 4, "track_sd": 0.01},
             "motion_appearance": {"geometry": False},
             # the continuation's residuals at half size: 13 trajectories' 12 views of 448² are 0.4 GB at full size
             "continuation": {"scale": 0.5}},
}
