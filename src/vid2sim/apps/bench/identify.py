"""``vid2sim bench identify``: how well the reduced simulator identifies E, ν and the damping from 3-D motion.

This is the upper bound of the video pipeline: the same question with perfect geometry and no rendering.
For every scene of a suite (procedural objects, E log-uniform in [1e4, 1e6], ν uniform in [0.2, 0.49],
:func:`vid2sim.synthetic.scenes.benchmark_parameters`):

1. the ground truth — the object tetrahedralized (fTetWild, the preset's resolution) and dropped by the FEM
   with the scene's material and the default damping, quadratic tets (converged in space) and converged in
   time (:func:`vid2sim.synthetic.fem.simulate_fem_converged`);
2. perfect geometry — points sampled uniformly in the FEM's rest tets (their true trajectories by
   barycentric interpolation), a skinning field trained data-free (modal objective) on a separate, larger
   sample of the tets, farthest-point cubature with
   the mesh volume, the FEM's surface vertices with their areas as contact points, the FEM's density,
   length scale and floor, and the exact rigid initial state fitted to the FEM's frame 0;
3. the model error — the reduced simulation at the true parameters against the FEM (frames 1–15 and
   16–23), and the reduced simulation's own time convergence (its default substeps against 4× as many);
4. the fit — log10 E, ν and the damping ratio ζ, as the video pipeline fits them: a coarse search over
   log10 E ∈ [4, 6] at the prior ν = 0.3, ζ = 0.05, then L-BFGS from its minimum on the adjoint gradients
   of a 3-D loss over the observed frames 1–15: by default the centre of mass plus the shape after a rigid
   alignment per frame (``IdentifyConfig.loss``; the plain point distance is the alternative);
5. the E valley — the same loss swept over log10 E around the fitted value (ν, ζ fitted), and its depth
   at ±0.5 decade;
6. the stiffness of the models — the six lowest elastic frequencies of linear tets and of the reduced
   model's subspace, as ratios to quadratic tets on the same mesh (spatially converged to < 1 %). At a
   fixed ν, a ratio r acts on the motion like an E that is r² too large. The ground truth itself uses
   quadratic tets by default (``fem_element_order``).

Trajectory errors are :func:`vid2sim.metrics.trajectory_distance` (mean point distance, percent of the
object's size). Everything expensive is cached in a work folder, so a rerun only fits.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from vid2sim.meshing.tetra import sample_points_in_tets, tet_volumes, tetrahedralize
from vid2sim.metrics import (
    deformation,
    motion_around_contacts,
    nonrigid_distance,
    rigidly_aligned,
    trajectory_distance,
)
from vid2sim.metrics.images import image_metrics
from vid2sim.physics import Floor, Gravity, Material, SimState, Simulator, SkinningField
from vid2sim.physics.contact_compliance import TetCompliance, contact_layer_from_simulation
from vid2sim.physics.cubature import CUBATURE_WEIGHTS, sample_cubature
from vid2sim.physics.mass import moment_matched_volumes, tet_moments
from vid2sim.physics.modes import CURVE_NUS, stiffness_calibration, stiffness_calibration_curve, subspace_frequencies
from vid2sim.physics.reduced import lbs_rows
from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
from vid2sim.physics.tet_modes import tet_frequencies
from vid2sim.reconstruct.config import CalibrationConfig, NetworksConfig, PriorConfig, SimulatorConfig
from vid2sim.reconstruct.stages.joint import coarse_minimum
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.workers import process_pool
from vid2sim.splats.cameras import camera_ring
from vid2sim.synthetic.embedding import apply_embedding, embed_points
from vid2sim.synthetic.fem import FEMResult, simulate_fem, simulate_fem_converged
from vid2sim.synthetic.mesh_render import render_textured_mesh
from vid2sim.synthetic.scenes import SyntheticSceneConfig, benchmark_parameters
from vid2sim.synthetic.shapes import make_procedural_object

LOSSES = ("shape_and_centre", "positions")

#: The flat settings of IdentifyConfig before it took reconstruct's sections (#49) → their dotted paths now.
#: :meth:`IdentifyConfig.from_dict` moves them, so the configuration of an older report still loads.
MOVED = {
    "handles": "networks.handles", "skinning_iterations": "networks.skinning_iterations",
    "skinning_objective": "networks.skinning_objective",
    "cubature": "simulator.cubature", "volumetric": "simulator.volumetric", "mass": "simulator.mass",
    "prior_E": "prior.E", "prior_nu": "prior.nu", "prior_damping": "prior.damping",
    "calibrate_stiffness": "calibration.enabled", "calibration_nu": "calibration.nu",
}

#: The fields of reconstruct's sections that ``bench identify`` does not use (no flag; documented in
#: :class:`IdentifyConfig`).
UNUSED = ("networks.jacobian_iterations", "prior.density", "calibration.cells", "calibration.points")


@dataclass
class IdentifyConfig:
    """Settings of ``vid2sim bench identify``.

    The settings the experiment shares with the reconstruction are :class:`~vid2sim.reconstruct.config.
    ReconstructConfig`'s own sections (``networks``, ``simulator``, ``prior``, ``calibration``), so a flag means
    the same in both (``--networks.handles``); the rest are the experiment's. The defaults are the configuration
    whose figures the README reports for #10 (30 handles, the stiffness calibrated with one factor per ν, the
    projected volumetric term, moment-matched masses, ζ held at the prior); they differ from reconstruct's in
    ``networks.handles``, ``simulator.volumetric``, ``simulator.mass`` and ``calibration.nu``. Earlier rows of
    docs/architecture.md name the flags they were measured with (their old spellings still work). Saved in the
    report as ``config`` (:meth:`to_dict`) and loaded back by :meth:`from_dict`.

    Attributes:
        scenes: number of scenes (≥ 1; the reported figures use 6).
        only: run just these scene indices of the suite (each in [0, scenes)); empty: all of them. A subset's
            means are not the suite's: use it to rerun or study single scenes from the same cache.
        seed: suite seed (scene i: object/pose seed and material of :func:`benchmark_parameters`).
        preset: tet resolution and drop of the synthetic preset ("small" or "full"; the scenes', not
            reconstruct's preset of the same names).
        frames, observed_frames: frames simulated and observed (the rest are the future).
        points: sample points for the loss, the errors and the cubature.
        skinning_points: a separate, larger sample of the tets the skinning field is trained on (reconstruct's
            field trains on its interior points, ``points.num_points``; here those are the loss's). With the modal
            objective a 3 000-point training set is overfitted: the subspace grows soft modes on those points
            that independent quadrature does not see (0.45 × the converged frequency on object 4).
        networks: the skinning field, trained data-free on ``skinning_points`` (reconstruct's stage ``networks``):
            ``handles`` (default 30), ``skinning_iterations``, ``skinning_objective`` ("modal", the default: its
            subspace is 1.11 × the converged lowest frequency on average, random z's 1.48 ×). dF/dz is always the
            closed form (``jacobian`` "neural" is refused; ``jacobian_iterations`` is not used).
        simulator: the reduced model (reconstruct's ``simulator``): ``cubature`` points, the ``volumetric`` term
            ("projected" by default here, which removes the subspace's volumetric locking; calibrate it with one
            factor, ``calibration.nu`` "curve"), the lumped ``mass`` ("moments" by default here: the cubature
            volumes corrected so that the mass, centre of mass and inertia tensor are the tet mesh's exactly,
            :func:`vid2sim.physics.mass.moment_matched_volumes`; "cubature": ρ times the cubature weights, whose
            500 random points put the inertia tensor 6–7 % off, and the bounce with it) and its time
            ``integration``.
        cubature_weights: "equal" or "voronoi" (:func:`~vid2sim.physics.cubature.sample_cubature`); reconstruct has
            no such setting (its cubature weights are equal).
        prior: the fit's start (``E``, ``nu``, ``damping``; ``nu`` and ``damping`` must be > 0, the fit works on
            their logit and inverse softplus). ``density`` is not used: the scene (the FEM) gives one.
        fit_damping: also fit ζ; False (the default) keeps it at ``prior.damping``, as ``reconstruct`` does by
            default (``joint.fit_damping``). ζ and ν trade off: a fitted ζ lets ν drift. Flat, with
            ``coarse_log10_E``, rather than reconstruct's ``joint`` section: the rest of that section (Adam,
            windows of frames, learning rates, views) belongs to the image fit and means nothing to this L-BFGS
            fit of 3-D motion.
        coarse_log10_E: the grid searched over log10 E (at the prior ν and ζ) before L-BFGS, as the video
            pipeline does (``joint.coarse_log10_E``); empty: start at ``prior.E``. The loss is not convex in E:
            with a subspace close to the truth's stiffness, two of the six scenes stopped in a side valley
            0.5–0.8 decade below the truth when the descent started at the prior.
        fit_iterations: L-BFGS iterations (each takes a few loss evaluations).
        sweep_decades, sweep_points: the log10 E sweep around the fit.
        fem_tolerance: the ground truth's time-convergence tolerance (percent of the size).
        fem_element_order: the ground truth's tets: 2 (quadratic, converged in space to < 1 % in the lowest
            frequencies; the default) or 1 (linear, 3–20 % too stiff on these shapes, but 10–20× faster).
        truth: "fem" — fit the FEM's motion (model error included); "reduced" — fit the reduced model's
            own motion at the true parameters (pure identifiability: the loss landscape and the optimiser,
            without model error).
        loss: the fit's loss (:func:`trajectory_loss`): "shape_and_centre" (the default) — the centre of
            mass and the shape after a rigid alignment per frame, blind to the orientation — or "positions"
            (the plain point distance). The orientation of a stiff object rocking on the frictionless floor
            drifts chaotically from the truth's after its first bounce; the plain distance is dominated by
            that drift and pulls E to whatever value matches the rocking phase.
        calibration: the subspace's stiffness matched to quadratic tets (reconstruct's ``calibration``):
            ``enabled`` (the default) scales the reduced model's elastic energy so that its subspace's lowest
            frequencies on its cubature equal those of quadratic tets on the truth's own rest mesh
            (:func:`vid2sim.physics.modes.stiffness_calibration`; ``Simulator.stiffness_scale``), so the fitted
            E is the material's, not the stiffer subspace's; ``nu``: "curve" (the default here, for the
            projected term) one factor on E at each ν of ``calibration_nus``, "two_factor" (for the pointwise
            term, whose locking grows with ν and sits in λ) a factor on μ and one on λ at each ν matched to the
            six lowest modes, used at the simulator's current ν, "prior" one factor at the prior ν. ``cells`` and
            ``points`` are not used: they make reconstruct's reference mesh from the kept voxels, and here the
            reference is the truth's mesh.
        calibration_nus: the ν grid of that curve (reconstruct's is fixed, :data:`vid2sim.physics.modes.CURVE_NUS`,
            the default here).
        contact_layer: the reduced model's contact layer h as a fraction of the object's size
            (``Simulator(contact_layer=)``; 0: none). An experiment: no single value suits every object
            (docs/architecture.md, "The calibration as a function of ν").
        fit_contact_layer: also fit the contact layer h (a fraction of the size, as softplus of a free
            parameter, from ``contact_layer`` or 0.005 when that is 0), so that the fit can soften the
            subspace's too-stiff contact without lowering ν. Experimental and measured negative: h and ν
            trade off (mean |Δν| 0.133 against 0.085 without it; docs/architecture.md).
        calibrate_contact: set the contact layer from the object's continuum instead: after the coarse search,
            the layer that gives the subspace the quadratic tets' compliance under the floor loads of its own
            simulation at the coarse minimum and the prior ν, iterated ``contact_iterations`` times so that the
            patches are those of the layer (:func:`vid2sim.physics.contact_compliance.contact_layer_from_simulation`).
            Overrides ``contact_layer``. Experimental: on two scenes it made the contact too soft and
            the fit worse (docs/architecture.md, "The layer measured per object does not work").
        contact_iterations: the fixed-point iterations of that calibration.
        nu_sensitivity: Δν > 0 measures how much ν moves the ground truth (0: off). A second FEM run at
            ν_true − Δν (ν_true + Δν when that would go below 0), with the same mesh, pose, element order and
            time steps as the truth, is compared with the truth on the loss's sample points
            (:func:`nu_sensitivity`). Its ratio to the model error at the true material says how finely the
            observed frames can pin ν down with this reduced model. The run is cached in the work folder.
        nu_scan: ν values at which to evaluate the observed-frame loss at the true E and ζ (empty: off). Its
            minimum (``nu_scan.argmin_nu``, refined by a parabola through the lowest three) is where the observed
            frames put ν with this model when E is right: a fit can do no better, so it separates the model's
            error from the optimiser's (:func:`scan_nu`).
        render_psnr: also render the object's textured surface carried by the truth and by the reduced model
            (at the true material and at the fitted one) in the preset's observed cameras, and score the
            model's images against the truth's by PSNR and SSIM as ``vid2sim evaluate`` does
            (:func:`render_psnr`): the images a video pipeline using this reduced model could reach with perfect
            geometry, appearance and initial state.
    """

    scenes: int = 6
    only: tuple[int, ...] = ()
    seed: int = 0
    preset: Literal["small", "full"] = "small"
    frames: int = 24
    observed_frames: int = 16
    points: int = 3000
    skinning_points: int = 30000
    networks: NetworksConfig = field(
        default_factory=lambda: NetworksConfig(handles=30, skinning_iterations=2000, skinning_objective="modal")
    )
    simulator: SimulatorConfig = field(
        default_factory=lambda: SimulatorConfig(cubature=500, volumetric="projected", mass="moments")
    )
    cubature_weights: Literal["equal", "voronoi"] = "equal"
    prior: PriorConfig = field(default_factory=lambda: PriorConfig(E=1e5, nu=0.3, damping=0.05))
    fit_damping: bool = False
    coarse_log10_E: tuple[float, ...] = (4.0, 4.25, 4.5, 4.75, 5.0, 5.25, 5.5, 5.75, 6.0)
    fit_iterations: int = 12
    sweep_decades: float = 0.5
    sweep_points: int = 5
    fem_tolerance: float = 1.0
    fem_element_order: int = 2
    truth: Literal["fem", "reduced"] = "fem"
    loss: Literal["shape_and_centre", "positions"] = "shape_and_centre"
    calibration: CalibrationConfig = field(default_factory=lambda: CalibrationConfig(enabled=True, nu="curve"))
    calibration_nus: tuple[float, ...] = CURVE_NUS
    contact_layer: float = 0.0
    fit_contact_layer: bool = False
    calibrate_contact: bool = False
    contact_iterations: int = 3
    nu_sensitivity: float = 0.0
    nu_scan: tuple[float, ...] = ()
    render_psnr: bool = False

    def __post_init__(self) -> None:
        for name in ("scenes", "frames", "observed_frames", "points", "skinning_points", "fit_iterations",
                     "sweep_points", "contact_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"IdentifyConfig.{name} must be an integer >= 1, got {value!r}")
        for name, cls in (("networks", NetworksConfig), ("simulator", SimulatorConfig), ("prior", PriorConfig),
                          ("calibration", CalibrationConfig)):
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(f"IdentifyConfig.{name} must be a {cls.__name__}, got {getattr(self, name)!r}")
        only = tuple(self.only)
        if any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < self.scenes for i in only) \
                or len(set(only)) != len(only):
            raise ConfigError(
                f"IdentifyConfig.only must be distinct scene indices in [0, {self.scenes}), got {self.only!r}"
            )
        self.only = tuple(sorted(only))
        if self.observed_frames >= self.frames:
            raise ConfigError(
                f"IdentifyConfig.observed_frames ({self.observed_frames}) must be < frames ({self.frames})"
            )
        if self.truth not in ("fem", "reduced"):
            raise ConfigError(f"IdentifyConfig.truth must be 'fem' or 'reduced', got {self.truth!r}")
        if self.loss not in LOSSES:
            raise ConfigError(f"IdentifyConfig.loss must be one of {LOSSES}, got {self.loss!r}")

        if self.cubature_weights not in CUBATURE_WEIGHTS:
            raise ConfigError(
                f"IdentifyConfig.cubature_weights must be one of {CUBATURE_WEIGHTS}, got {self.cubature_weights!r}"
            )
        if self.fem_element_order not in (1, 2) or isinstance(self.fem_element_order, bool):
            raise ConfigError(f"IdentifyConfig.fem_element_order must be 1 or 2, got {self.fem_element_order!r}")
        if self.networks.jacobian != "closed_form":
            raise ConfigError("NetworksConfig.jacobian must be 'closed_form' in bench identify (it computes dF/dz "
                              f"from the skinning field), got {self.networks.jacobian!r}")
        if not (self.prior.nu > 0 and self.prior.damping > 0):
            raise ConfigError("PriorConfig.nu and PriorConfig.damping must be > 0 in bench identify (the fit works on "
                              f"their logit and inverse softplus), got {self.prior.nu}, {self.prior.damping}")
        if self.simulator.volumetric == "projected" and self.calibration.enabled and \
                self.calibration.nu == "two_factor":
            raise ConfigError("IdentifyConfig: the projected volumetric term does not lock, so it takes one factor "
                              "(calibration.nu 'curve' or 'prior'), not 'two_factor'")
        self.calibration_nus = tuple(float(v) for v in self.calibration_nus)
        nus = self.calibration_nus
        if len(nus) < 2 or not all(0 <= v < 0.5 for v in nus) or any(b <= a for a, b in zip(nus, nus[1:])):
            raise ConfigError(f"IdentifyConfig.calibration_nus must be >= 2 increasing values in [0, 0.5), got {nus!r}")
        if isinstance(self.contact_layer, bool) or not isinstance(self.contact_layer, (int, float)) \
                or not 0 <= self.contact_layer < math.inf:
            raise ConfigError(f"IdentifyConfig.contact_layer must be a finite number >= 0, got {self.contact_layer!r}")
        if isinstance(self.nu_sensitivity, bool) or not isinstance(self.nu_sensitivity, (int, float)) \
                or not 0 <= self.nu_sensitivity < 0.5:
            raise ConfigError(
                f"IdentifyConfig.nu_sensitivity must be a number in [0, 0.5), got {self.nu_sensitivity!r}"
            )
        self.nu_scan = tuple(float(v) for v in self.nu_scan)
        if any(not 0 < v < 0.5 for v in self.nu_scan) or any(b <= a for a, b in zip(self.nu_scan, self.nu_scan[1:])):
            raise ConfigError(f"IdentifyConfig.nu_scan must be increasing values in (0, 0.5), got {self.nu_scan!r}")
        if self.preset not in ("small", "full"):
            raise ConfigError(f"IdentifyConfig.preset must be 'small' or 'full', got {self.preset!r}")
        self.coarse_log10_E = tuple(sorted(float(v) for v in self.coarse_log10_E))
        if not all(math.isfinite(v) for v in self.coarse_log10_E):
            raise ConfigError(f"IdentifyConfig.coarse_log10_E must be finite numbers, got {self.coarse_log10_E!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "IdentifyConfig":
        """The configuration of a report's ``config`` (:meth:`to_dict`); missing fields take their defaults. The
        flat names of reports before #49 (``handles``, ``prior_nu``, …, :data:`MOVED`) are moved to their
        sections.

        Raises:
            ConfigError: a setting that does not exist, a value of the wrong type or out of range, naming the
                dotted path (``unknown setting networks.handels``).
        """
        if not isinstance(data, dict):
            raise ConfigError(f"an identify configuration must be an object, got {type(data).__name__}")
        data = json.loads(json.dumps(data))  # a deep copy (the moves below edit it)
        for old, new in MOVED.items():
            if old in data:
                section, name = new.split(".")
                if not isinstance(data.get(section, {}), dict) or name in data.get(section, {}):
                    raise ConfigError(f"{old} (now {new}) is given twice: as {old} and in {section}")
                data.setdefault(section, {})[name] = data.pop(old)
        return configs.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready nested dict (a report's ``config``)."""
        return configs.to_dict(self)


@dataclass
class PerfectGeometry:
    """One scene's ground truth and the reduced simulator built on its exact geometry.

    Attributes:
        simulator: the reduced simulator at the prior material (float64).
        start: the exact initial state (rigid pose and velocity of the FEM's frame 0).
        rest_points: (P, 3) sample points in the rest tets; lbs: (P, 4H) their LBS rows.
        truth: (T, P, 3) their FEM trajectory.
        size: the object's rest bounding-box diagonal (m).
        material: {"E", "nu", "damping_ratio"} of the ground truth.
        info: facts about the scene (tets, substeps, time convergence, wall times).
        tet_vertices: (Nv, 3) and tets: (Nt, 4) the rest mesh; contact_nodes: (Nc,) the quadratic-tet node of
            each of the simulator's contact points.
    """

    simulator: Any
    start: Any
    rest_points: torch.Tensor
    lbs: torch.Tensor
    truth: torch.Tensor
    size: float
    material: dict
    info: dict
    tet_vertices: torch.Tensor | None = None
    tets: torch.Tensor | None = None
    contact_nodes: np.ndarray | None = None

    def positions(self, z: torch.Tensor) -> torch.Tensor:
        """(P, 3) sample-point positions for the reduced state z: (12H,)."""
        return self.rest_points + self.lbs @ z.reshape(-1, 3, 4).transpose(0, 1).reshape(3, -1).T

    def trajectory(self, frames: int, grad: bool = False) -> torch.Tensor:
        """(frames, P, 3) reduced trajectory from the exact start (frame 0 included)."""
        context = torch.enable_grad() if grad else torch.no_grad()
        with context:
            states = self.simulator.rollout(self.start, frames - 1)
            return torch.stack([self.positions(self.start.z)] + [self.positions(s.z) for s in states])


def _fem_key(params: dict, config: IdentifyConfig) -> dict:
    """What the cached ground truth of a scene depends on."""
    key = {"params": params, "preset": config.preset, "frames": config.frames, "fem_tolerance": config.fem_tolerance}
    if config.fem_element_order != 1:
        key["element_order"] = config.fem_element_order
    return key


def _fem_paths(folder: Path, config: IdentifyConfig, tag: str = "") -> tuple[Path, Path]:
    """The cached FEM result and its key file in a scene's folder (``tag`` names a variant run)."""
    suffix = ("" if config.fem_element_order == 1 else f"_p{config.fem_element_order}") + tag
    return folder / f"fem_result{suffix}.npz", folder / f"fem_key{suffix}.json"


def _rigid_affine(rest: np.ndarray, posed: np.ndarray) -> np.ndarray:
    """(3, 4) affine A with posed ≈ A [rest; 1] (least squares; exact for a rigid pose or velocity field)."""
    Xh = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    A, *_ = np.linalg.lstsq(Xh, posed, rcond=None)
    return A.T


def prepare_scene(index: int, params: dict, config: IdentifyConfig, workdir: Path, progress: bool = False
                  ) -> PerfectGeometry:
    """Build (or load from ``workdir``) scene ``index`` of the suite: FEM ground truth and perfect geometry."""

    folder = workdir / f"scene_{index:03d}"
    folder.mkdir(parents=True, exist_ok=True)
    scene_cfg = SyntheticSceneConfig.preset(config.preset, frames=config.frames,
                                            observed_frames=config.observed_frames, **params)
    key = _fem_key(params, config)
    fem_path, key_path = _fem_paths(folder, config)
    if fem_path.is_file() and key_path.is_file() and json.loads(key_path.read_text()) == key:
        fem = FEMResult.load(fem_path)
    else:
        mesh = make_procedural_object(scene_cfg.seed)
        tet = tetrahedralize(mesh.vertices, mesh.faces, edge_length_fac=scene_cfg.tet_edge_length,
                             epsilon=scene_cfg.tet_envelope, name=mesh.name)
        fem = simulate_fem_converged(
            tet.vertices,
            tet.tets,
            scene_cfg.fem_config(element_order=config.fem_element_order),
            scene_cfg.initial_pose(),
            frames=config.frames,
            tolerance=config.fem_tolerance,
            progress=progress,
        )
        fem.save(fem_path)
        key_path.write_text(json.dumps(key))
    T = fem.tets
    X = fem.rest_vertices[: int(T.max()) + 1]  # the mesh's vertices (quadratic tets add edge midpoints after them)
    size = float((X.max(0).values - X.min(0).values).norm())
    volume = float(tet_volumes(X, T).abs().sum())
    points, tet_index, bary = sample_points_in_tets(X, T, config.points, seed=index)
    truth = apply_embedding(fem.trajectory, tet_index, bary, fem.embedding_elements)  # (T, P, 3)

    field = SkinningField(num_handles=config.networks.handles, seed=0).double()
    networks = config.networks
    suffix = "_v2" if networks.skinning_objective == "random_z" else f"_{networks.skinning_objective}"
    field_path = (
        folder / f"skinning_{networks.handles}h_{networks.skinning_iterations}it_{config.skinning_points}p{suffix}.pt"
    )
    if field_path.is_file():
        field.load_state_dict(torch.load(field_path, weights_only=True))
    else:
        pool, _, _ = sample_points_in_tets(X, T, config.skinning_points, seed=100_000 + index)
        train_skinning(field, pool, SkinningTrainingConfig(iterations=networks.skinning_iterations, seed=index,
                                                             objective=networks.skinning_objective),
                       progress=progress, volume=volume)
        torch.save(field.state_dict(), field_path)
    for p in field.parameters():
        p.requires_grad_(False)
    idx, weights = sample_cubature(points, config.simulator.cubature, volume=volume, seed=0,
                                   weights=config.cubature_weights)
    nodes = fem.rest_vertices
    areas = fem.contact_areas()  # the FEM's own floor weights, per node
    surface = areas > 0
    fc = fem.config
    if not math.isclose(config.simulator.integration.dt, fc.dt):
        raise ConfigError(f"SimConfig.dt must be the ground truth's frame time here, {fc.dt} s, got "
                          f"{config.simulator.integration.dt} (the reduced model's frames are compared with its)")
    material = Material(config.prior.E, config.prior.nu, fc.density, damping_ratio=config.prior.damping)
    mass_volumes = None
    if config.simulator.mass == "moments":

        mass_volumes = moment_matched_volumes(points[idx], weights, tet_moments(X.to(points.dtype), T))
    scale = 1.0
    if config.calibration.enabled:
        if config.calibration.nu == "prior":
            scale = stiffness_calibration(field, points[idx], weights, X, T, config.prior.nu,
                                          config.simulator.volumetric, mass_volumes=mass_volumes)
        else:
            scale = stiffness_calibration_curve(field, points[idx], weights, X, T, config.calibration_nus,
                                                factors=2 if config.calibration.nu == "two_factor" else 1,
                                                volumetric=config.simulator.volumetric, mass_volumes=mass_volumes)
    sim = Simulator(field, points[idx], weights, material,
                    [Gravity(fc.gravity), Floor(height=fc.floor_height, stiffness=fc.floor_stiffness)],
                    config.simulator.integration, length_scale=fem_length(fem, size), contact_points=nodes[surface],
                    contact_weights=areas[surface], stiffness_scale=scale, contact_layer=config.contact_layer * size,
                    volumetric=config.simulator.volumetric, mass_volumes=mass_volumes)
    H = field.num_handles_total
    Z0 = np.zeros((H, 3, 4))
    Z0[-1] = _rigid_affine(nodes.numpy(), fem.trajectory[0].numpy()) - np.hstack([np.eye(3), np.zeros((3, 1))])
    Zd = np.zeros((H, 3, 4))
    Zd[-1] = _rigid_affine(nodes.numpy(), fem.velocities[0].numpy())
    start = SimState(torch.from_numpy(Z0.reshape(-1)), torch.from_numpy(Zd.reshape(-1)))
    with torch.no_grad():
        w = field(points)

    lbs = lbs_rows(points, w)
    info = {"object": f"procedural-{scene_cfg.seed}", "tets": int(len(T)), "fem_element_order": fc.element_order,
            "fem_substeps": fc.substeps,
            "fem_time_convergence_percent": (fem.time_convergence or {}).get("mean_percent"),
            "fem_seconds": (fem.time_convergence or {}).get("wall_time_all_runs", fem.wall_time),
            "frequencies": lowest_frequencies(X, T, field, points[idx], weights, fc, config.simulator.volumetric,
                                              mass_volumes),
            "stiffness_scale": scale if isinstance(scale, float) else scale.at(config.prior.nu),
            "stiffness_curve": None if isinstance(scale, float) else scale.to_dict()}
    truth_material = {"E": fc.youngs_modulus, "nu": fc.poisson_ratio, "damping_ratio": fc.damping_ratio}
    return PerfectGeometry(sim, start, points, lbs, truth, size, truth_material, info, X, T,
                           np.flatnonzero(surface.numpy()))


def lowest_frequencies(X: torch.Tensor, T: torch.Tensor, field, cubature: torch.Tensor, volumes: torch.Tensor,
                       fc, volumetric: str = "pointwise", mass_volumes: torch.Tensor | None = None) -> dict:
    """The six lowest elastic frequencies at the true material: quadratic tets on the FEM's mesh (the converged
    reference, :mod:`vid2sim.physics.tet_modes`), and as ratios to them, linear tets with lumped mass on that
    mesh (the FEM truth when ``fem_element_order`` is 1) and the reduced model's subspace on its cubature
    (:mod:`vid2sim.physics.modes`)."""

    E, nu, rho = fc.youngs_modulus, fc.poisson_ratio, fc.density
    reference = tet_frequencies(X, T, E, nu, rho, k=6, order=2)
    fem = tet_frequencies(X, T, E, nu, rho, k=6, order=1, lumped=True)
    reduced = subspace_frequencies(field, cubature, volumes, E, nu, rho, k=6, volumetric=volumetric,
                                   mass_volumes=mass_volumes)
    return {"quadratic_tets_hz": (reference / (2 * math.pi)).tolist(),
            "linear_tets_over_quadratic": (fem / reference).tolist(),
            "reduced_over_quadratic": (reduced / reference).tolist(),
            "reduced_over_linear_tets": (reduced / fem).tolist()}


def fem_length(fem, size: float) -> float:
    """The FEM's damping length scale (its config's, else the rest bounding-box diagonal)."""
    return float(fem.config.damping_length) if fem.config.damping_length is not None else size


def set_material(sim, log10_E: float, nu: float, damping: float) -> None:
    with torch.no_grad():
        sim.log10_E.fill_(log10_E)
        sim.nu.fill_(nu)
        sim.damping_ratio.fill_(damping)


def trajectory_loss(scene: PerfectGeometry, frames: int, grad: bool = False, kind: str = "positions") -> torch.Tensor:
    """The fit's loss over frames 1 … frames−1, in units of size².

    ``kind`` "positions": the mean squared point distance to the truth. "shape_and_centre": the squared
    distance of the centres of mass (the mean of the uniformly sampled points) plus the mean squared point
    distance after moving each frame rigidly onto the truth (:func:`vid2sim.metrics.rigidly_aligned`,
    differentiable): the motion of the centre and the deformation, without the orientation.
    """

    if kind not in LOSSES:
        raise InputError(f"trajectory_loss: kind must be one of {LOSSES}, got {kind!r}")
    traj, truth = scene.trajectory(frames, grad=grad)[1:], scene.truth[1:frames]
    if kind == "positions":
        diff = traj - truth
        return (diff * diff).sum(-1).mean() / scene.size**2
    centre = ((traj.mean(1) - truth.mean(1)) ** 2).sum(-1).mean()
    shape = ((rigidly_aligned(traj, truth) - truth) ** 2).sum(-1).mean()
    return (centre + shape) / scene.size**2


def model_errors(scene: PerfectGeometry, config: IdentifyConfig) -> dict:
    """Trajectory errors (percent of the size) on the observed frames 1–15 and the future 16–23; the same
    after aligning each frame rigidly onto the truth (``*_nonrigid_percent``: the shape error, without the
    pose error); and the largest deformation over the frames (distance from the best rigid motion of the
    rest shape) of the truth and of the reduced model; the rotation off the truth's and the errors around each
    contact with the floor (:func:`vid2sim.metrics.motion_around_contacts`, the sample points weighted equally:
    they are uniform in the tets)."""

    traj = scene.trajectory(config.frames)
    observed, future = slice(1, config.observed_frames), slice(config.observed_frames, config.frames)
    truth = scene.truth[: config.frames]
    gravity = next(e.acceleration for e in scene.simulator.externals if isinstance(e, Gravity))
    weights = torch.ones(traj.shape[1], dtype=torch.float64)
    offset = (traj.double().mean(1) - truth.double().mean(1)).norm(dim=1).tolist()
    return {
        "observed_percent": trajectory_distance(traj, scene.truth, scene.size, frames=observed).mean,
        "future_percent": trajectory_distance(traj, scene.truth, scene.size, frames=future).mean,
        "all_percent": trajectory_distance(traj, scene.truth, scene.size).mean,
        "observed_nonrigid_percent": nonrigid_distance(traj, scene.truth, scene.size, frames=observed).mean,
        "future_nonrigid_percent": nonrigid_distance(traj, scene.truth, scene.size, frames=future).mean,
        "peak_deformation_percent": {"truth": max(deformation(scene.truth[: config.frames], scene.rest_points,
                                                               scene.size)),
                                     "reduced": max(deformation(traj, scene.rest_points, scene.size))},
        **motion_around_contacts(traj, weights, truth, weights, offset, float(scene.simulator.config.dt), gravity,
                                 list(range(1, config.observed_frames)),
                                 list(range(config.observed_frames, config.frames))),
    }


def calibrate_contact(scene: PerfectGeometry, config: IdentifyConfig, log10_E: float, nu: float) -> list[dict]:
    """Set the simulator's contact layer from the continuum at (log10 E, ν) and the prior ζ (see
    ``IdentifyConfig.calibrate_contact``); returns each iteration's :class:`ContactCalibration` as a dict."""

    sim = scene.simulator
    set_material(sim, log10_E, nu, config.prior.damping)
    tet = TetCompliance(scene.tet_vertices, scene.tets, nu)
    scale = sim.stiffness_scale
    s = float(scale.at(nu)) if not isinstance(scale, float) else scale
    sim.contact_layer = 0.0
    rounds = []
    for _ in range(config.contact_iterations):
        with torch.no_grad():
            states = sim.rollout(scene.start, config.observed_frames - 1)
        calibration = contact_layer_from_simulation(sim, states, tet, scene.contact_nodes, nu, s)
        sim.contact_layer = calibration.layer
        rounds.append({**calibration.to_dict(), "layer_over_size": calibration.layer / scene.size})
    return rounds


def fit(scene: PerfectGeometry, config: IdentifyConfig, progress: bool = False) -> dict:
    """Fit log10 E, ν and ζ: a coarse search over log10 E at the prior ν and ζ, then L-BFGS from its minimum
    on the adjoint gradients of the observed-frame loss.

    ν is optimised as ν = 0.5·sigmoid(u) (inside (0, 0.5)) and ζ as softplus(v) (≥ 0), so the search is
    unconstrained; the substep count follows the current E (:meth:`Simulator.substeps`)."""
    from tqdm.auto import tqdm


    sim = scene.simulator
    start = time.perf_counter()
    start_log10_E = math.log10(config.prior.E)
    if config.fit_contact_layer:  # the coarse search runs with the layer the fit starts from
        sim.contact_layer = max(config.contact_layer, 0.005) * scene.size
    coarse = []
    for value in tqdm(config.coarse_log10_E, desc="coarse log10 E", leave=False, disable=not progress):
        set_material(sim, value, config.prior.nu, config.prior.damping)
        coarse.append(
            {"log10_E": value, "loss": float(trajectory_loss(scene, config.observed_frames, kind=config.loss))}
        )
    if coarse:
        start_log10_E = coarse_minimum([c["log10_E"] for c in coarse], [c["loss"] for c in coarse])
    contact = calibrate_contact(scene, config, start_log10_E, config.prior.nu) if config.calibrate_contact else None
    fit_h = config.fit_contact_layer
    wh = torch.tensor(math.log(math.expm1(max(config.contact_layer, 0.005))), dtype=torch.float64, requires_grad=fit_h)
    logE = torch.tensor(start_log10_E, dtype=torch.float64, requires_grad=True)
    u = torch.tensor(math.log(config.prior.nu / (0.5 - config.prior.nu)), dtype=torch.float64, requires_grad=True)
    v = torch.tensor(math.log(math.expm1(config.prior.damping)), dtype=torch.float64, requires_grad=config.fit_damping)
    history = []

    def assign():
        sim.log10_E = logE
        sim.nu = 0.5 * torch.sigmoid(u)
        sim.damping_ratio = torch.nn.functional.softplus(v)
        if fit_h:
            sim.contact_layer = torch.nn.functional.softplus(wh) * scene.size

    params = [logE, u] + ([v] if config.fit_damping else []) + ([wh] if fit_h else [])
    optimizer = torch.optim.LBFGS(params, lr=1.0, max_iter=4, history_size=10,
                                  line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-12)

    def closure():
        optimizer.zero_grad()
        assign()
        loss = trajectory_loss(scene, config.observed_frames, grad=True, kind=config.loss)
        loss.backward()
        with torch.no_grad():
            history.append({"log10_E": float(logE), "nu": float(0.5 * torch.sigmoid(u)),
                            "damping_ratio": float(torch.nn.functional.softplus(v)), "loss": float(loss),
                            **({"contact_layer": float(torch.nn.functional.softplus(wh))} if fit_h else {})})
        return loss

    bar = tqdm(range(config.fit_iterations), desc="fit", leave=False, disable=not progress)
    for _ in bar:
        try:
            optimizer.step(closure)
        except Exception as exc:  # a line search that pushed E or ν to where the simulation fails
            history.append({"error": str(exc).splitlines()[0][:200]})
            break
        bar.set_postfix(
            log10_E=f"{history[-1].get('log10_E', float('nan')):.3f}", loss=f"{history[-1].get('loss', 0):.2e}"
        )
    seconds = time.perf_counter() - start
    best = min((h for h in history if "loss" in h), key=lambda h: h["loss"])
    # restore plain tensors at the best point
    sim.log10_E = torch.tensor(best["log10_E"], dtype=torch.float64)
    sim.nu = torch.tensor(best["nu"], dtype=torch.float64)
    sim.damping_ratio = torch.tensor(best["damping_ratio"], dtype=torch.float64)
    if fit_h:
        sim.contact_layer = best["contact_layer"] * scene.size
    return {"log10_E": best["log10_E"], "nu": best["nu"], "damping_ratio": best["damping_ratio"],
            "contact_layer": best.get("contact_layer"),
            "loss": best["loss"], "evaluations": len([h for h in history if "loss" in h]), "seconds": seconds,
            # a line search that pushed E or ν where the simulation fails ends the fit early: counted, not hidden
            "line_search_failures": sum(1 for h in history if "error" in h),
            "line_search_error": next((h["error"] for h in history if "error" in h), None),
            "coarse": coarse, "history": history, "contact_calibration": contact}


def sweep(scene: PerfectGeometry, config: IdentifyConfig, centre: float) -> dict:
    """The observed-frame loss over log10 E ∈ centre ± sweep_decades (ν, ζ as set), and the valley depth:
    loss(±0.5 decade) / loss(centre)."""
    sim = scene.simulator
    nu, zeta = float(sim.nu), float(sim.damping_ratio)
    offsets = np.linspace(-config.sweep_decades, config.sweep_decades, config.sweep_points)
    losses = []
    for off in offsets:
        set_material(sim, centre + off, nu, zeta)
        losses.append(float(trajectory_loss(scene, config.observed_frames, kind=config.loss)))
    set_material(sim, centre, nu, zeta)
    mid = losses[len(losses) // 2]
    return {"log10_E": [centre + float(o) for o in offsets], "loss": losses,
            "depth_at_minus": losses[0] / mid, "depth_at_plus": losses[-1] / mid}


def time_convergence(scene: PerfectGeometry, config: IdentifyConfig) -> dict:
    """The reduced simulation's default substeps against 4× as many, at the current material (percent)."""
    from dataclasses import replace


    sim = scene.simulator
    n = sim.substeps()
    base = scene.trajectory(config.frames)
    saved = sim.config
    sim.config = replace(saved, substeps=4 * n)
    fine = scene.trajectory(config.frames)
    sim.config = saved
    d = trajectory_distance(base, fine, scene.size)
    return {"substeps": n, "refined_substeps": 4 * n, "mean_percent": d.mean, "max_percent": d.max}


def scan_nu(scene: PerfectGeometry, config: IdentifyConfig) -> dict:
    """The observed-frame loss (``config.loss``) at the true E and ζ over ``config.nu_scan``; the simulator is left
    at the true material. ``argmin_nu`` is the grid minimum refined by a parabola through it and its neighbours
    (the grid value itself at an end of the grid)."""
    truth = scene.material
    losses = []
    for nu in config.nu_scan:
        set_material(scene.simulator, math.log10(truth["E"]), nu, truth["damping_ratio"])
        losses.append(float(trajectory_loss(scene, config.observed_frames, kind=config.loss)))
    set_material(scene.simulator, math.log10(truth["E"]), truth["nu"], truth["damping_ratio"])
    nus = list(config.nu_scan)
    k = int(np.argmin(losses))
    best = nus[k]
    if 0 < k < len(nus) - 1:
        a, b, c = np.polyfit(nus[k - 1:k + 2], losses[k - 1:k + 2], 2)
        if a > 0:
            best = float(min(max(-b / (2 * a), nus[k - 1]), nus[k + 1]))
    return {"nu": nus, "loss": losses, "argmin_nu": best, "argmin_error": best - truth["nu"]}


def nu_sensitivity(index: int, params: dict, scene: PerfectGeometry, config: IdentifyConfig, workdir: Path,
                   model_error_observed_percent: float) -> dict:
    """How much the ground truth moves when ν changes by ``config.nu_sensitivity``, against the model error.

    Runs the FEM again at ν_true − Δν (+ Δν if that is below 0) with everything else the truth's (mesh, pose,
    element order, substeps: no time-convergence search, the truth's converged step is kept), cached in the
    scene's folder, and embeds the loss's sample points in it.

    Returns:
        {"dnu": the signed change, "observed_percent", "future_percent": the distance between the two FEM
        trajectories (percent of the size, frames 1 … observed − 1 and observed … frames − 1),
        "observed_percent_per_0_05": the observed distance scaled to |Δν| = 0.05 (the target's size),
        "nu_equivalent_of_model_error": |Δν| · model error / observed distance — the change of ν that moves the
        truth as far as the reduced model at the true material is from it; where this exceeds the target,
        the observed frames cannot pin ν down to the target with this model unless its error happens to be
        orthogonal to ν's effect, "seconds": the extra FEM run (0 when cached)}.
    """
    from dataclasses import replace


    folder = workdir / f"scene_{index:03d}"
    dnu = float(config.nu_sensitivity)
    nu = scene.material["nu"]
    signed = -dnu if nu - dnu >= 0 else dnu
    base_path, _ = _fem_paths(folder, config)
    path, key_path = _fem_paths(folder, config, tag=f"_nu{signed:+.4f}")
    key = {**_fem_key(params, config), "dnu": signed}
    seconds = 0.0
    if path.is_file() and key_path.is_file() and json.loads(key_path.read_text()) == key:
        other = FEMResult.load(path)
    else:
        base = FEMResult.load(base_path)
        fc = replace(base.config, poisson_ratio=nu + signed)
        t0 = time.perf_counter()
        other = simulate_fem(scene.tet_vertices, scene.tets, fc, base.pose, frames=int(base.trajectory.shape[0]),
                             progress=False)
        seconds = time.perf_counter() - t0
        other.save(path)
        key_path.write_text(json.dumps(key))
    _, tet_index, bary = sample_points_in_tets(scene.tet_vertices, scene.tets, config.points, seed=index)
    moved = apply_embedding(other.trajectory, tet_index, bary, other.embedding_elements).to(scene.truth.dtype)
    if config.truth == "reduced":  # the truth is the model's own motion: compare FEM with FEM
        base = FEMResult.load(base_path)
        reference = apply_embedding(base.trajectory, tet_index, bary, base.embedding_elements).to(moved.dtype)
    else:
        reference = scene.truth
    frames = min(config.frames, len(moved), len(reference))
    observed = trajectory_distance(moved[:frames], reference[:frames], scene.size,
                                   frames=slice(1, config.observed_frames)).mean
    future = trajectory_distance(moved[:frames], reference[:frames], scene.size,
                                 frames=slice(config.observed_frames, frames)).mean
    return {"dnu": signed, "observed_percent": observed, "future_percent": future,
            "observed_percent_per_0_05": observed * 0.05 / dnu,
            "nu_equivalent_of_model_error": dnu * model_error_observed_percent / observed if observed > 0 else math.inf,
            "seconds": seconds}


def render_psnr(index: int, params: dict, scene: PerfectGeometry, config: IdentifyConfig, workdir: Path) -> dict:
    """The reduced model's motion against the truth's in images, at the simulator's current material.

    The object's textured surface mesh (the one ``make-scene`` renders) is embedded in the FEM's rest tets. The
    truth carries it with the FEM's motion; the model carries it with its skinning (LBS of the vertices) from
    the exact initial state. Both are rendered in the observed cameras of the preset's camera ring at its
    resolution and scored like ``vid2sim evaluate``'s ``dynamic`` (frames 1 … observed − 1) and ``future``
    groups: means of per-image PSNR (dB) and SSIM. Perfect geometry, appearance and initial state: what is
    lost is the dynamics model's alone.

    Returns:
        {"views", "resolution", "dynamic": {"psnr", "ssim", "psnr_per_frame"}, "future": {...}}.
    """

    sc = SyntheticSceneConfig.preset(config.preset, frames=config.frames, observed_frames=config.observed_frames,
                                     **params)
    mesh = make_procedural_object(sc.seed)
    fem = FEMResult.load(_fem_paths(workdir / f"scene_{index:03d}", config)[0])
    tet_index, bary = embed_points(mesh.vertices.double(), scene.tet_vertices, scene.tets)
    truth = apply_embedding(fem.trajectory[: config.frames], tet_index, bary, fem.embedding_elements)
    rest = apply_embedding(fem.rest_vertices[None], tet_index, bary, fem.embedding_elements)[0].to(torch.float64)
    with torch.no_grad():
        rows = lbs_rows(rest, scene.simulator.field(rest))
        states = scene.simulator.rollout(scene.start, config.frames - 1)
        model = torch.stack([rest + rows @ z.reshape(-1, 3, 4).transpose(0, 1).reshape(3, -1).T
                             for z in [scene.start.z] + [st.z for st in states]])
    cameras = camera_ring(sc.views, sc.camera_radius, sc.camera_elevation_deg, sc.resolution, sc.resolution,
                          fov_x_deg=sc.camera_fov_deg, target=sc.camera_target)
    observed = [v for v in range(sc.views) if v not in set(sc.held_out_indices)]
    cameras = [cameras[v] for v in observed]
    target, _ = render_textured_mesh(mesh, cameras, vertices=truth.float(), supersample=sc.supersample,
                                     progress=False)
    image, _ = render_textured_mesh(mesh, cameras, vertices=model.float(), supersample=sc.supersample,
                                    progress=False)

    def group(frames: range) -> dict:
        m = image_metrics(image[:, list(frames)], target[:, list(frames)], layout="VT")
        return {"psnr": m["psnr"], "ssim": m["ssim"], "psnr_per_frame": m["psnr_per_frame"]}

    return {"views": observed, "resolution": sc.resolution, "dynamic": group(range(1, config.observed_frames)),
            "future": group(range(config.observed_frames, config.frames))}


def run_scene(index: int, params: dict, config: IdentifyConfig, workdir: Path, progress: bool = False) -> dict:
    """Prepare (or load) scene ``index`` of the suite, measure its model error and fit it; its JSON row."""
    t0 = time.perf_counter()
    scene = prepare_scene(index, params, config, workdir, progress=False)
    truth = scene.material
    set_material(scene.simulator, math.log10(truth["E"]), truth["nu"], truth["damping_ratio"])
    if config.truth == "reduced":
        scene.truth = scene.trajectory(config.frames)
    at_truth = model_errors(scene, config)
    sensitivity = (nu_sensitivity(index, params, scene, config, workdir, at_truth["observed_percent"])
                   if config.nu_sensitivity > 0 else None)
    images_at_truth = render_psnr(index, params, scene, config, workdir) if config.render_psnr else None
    scan = scan_nu(scene, config) if config.nu_scan else None
    converged = time_convergence(scene, config)
    result = fit(scene, config, progress=progress)
    fitted_errors = model_errors(scene, config)
    images_fitted = render_psnr(index, params, scene, config, workdir) if config.render_psnr else None
    valley = sweep(scene, config, result["log10_E"])
    return {
        "scene": index, **scene.info,
        "true": {"log10_E": math.log10(truth["E"]), "nu": truth["nu"], "damping_ratio": truth["damping_ratio"]},
        "fitted": {k: result[k] for k in ("log10_E", "nu", "damping_ratio")},
        "fitted_contact_layer": result["contact_layer"],
        "abs_error": {"log10_E": abs(result["log10_E"] - math.log10(truth["E"])),
                      "nu": abs(result["nu"] - truth["nu"]),
                      "damping_ratio": abs(result["damping_ratio"] - truth["damping_ratio"])},
        "model_error_at_truth_percent": at_truth,
        "nu_sensitivity": sensitivity,
        "nu_scan": scan,
        "images_at_truth": images_at_truth,
        "images_fitted": images_fitted,
        "trajectory_error_fitted_percent": fitted_errors,
        "reduced_time_convergence_at_truth": converged,
        "fit": {k: result[k] for k in ("loss", "evaluations", "seconds", "line_search_failures", "line_search_error")},
        "fit_coarse": result["coarse"],
        "contact_calibration": result["contact_calibration"],
        "fit_history": result["history"],
        "e_valley": valley,
        "seconds": time.perf_counter() - t0,
    }


def _scene_in_worker(index: int, params: dict, config: IdentifyConfig, workdir: Path, threads: int) -> dict:
    """:func:`run_scene` in a worker process with ``threads`` torch threads."""
    torch.set_num_threads(threads)
    return run_scene(index, params, config, workdir)


def run(config: IdentifyConfig, workdir: str | Path, progress: bool = True, workers: int = 1,
        threads_per_worker: int = 1) -> dict:
    """Run the benchmark; returns the JSON-ready report (per scene and means).

    ``workers`` > 1 runs that many scenes at once in spawned processes (each with ``threads_per_worker``
    torch threads; :func:`vid2sim.runtime.workers.process_pool`). The ground truth of a scene runs in one process, so
    on a 2-core machine two workers halve the wall time of a fresh work folder. The rows are the same as
    with one worker: every scene is computed from its own seed and cache.
    """
    from tqdm.auto import tqdm


    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"workers must be an integer >= 1, got {workers!r}")
    if isinstance(threads_per_worker, bool) or not isinstance(threads_per_worker, int) or threads_per_worker < 1:
        raise InputError(f"threads_per_worker must be an integer >= 1, got {threads_per_worker!r}")
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    suite = list(enumerate(benchmark_parameters(config.scenes, config.seed)))
    if config.only:
        suite = [suite[i] for i in config.only]
    workers = min(workers, len(suite))
    if workers == 1:
        rows = [run_scene(i, params, config, workdir, progress=progress)
                for i, params in tqdm(suite, desc="identify scenes", unit="scene", disable=not progress)]
    else:
        from concurrent.futures import as_completed


        with process_pool(workers) as pool, \
                tqdm(total=len(suite), desc=f"identify scenes ({workers} workers)", unit="scene",
                     disable=not progress) as bar:
            futures = {pool.submit(_scene_in_worker, i, params, config, workdir, threads_per_worker): i
                       for i, params in suite}
            done = {}
            try:
                for future in as_completed(futures):
                    done[futures[future]] = future.result()
                    bar.update()
            except BaseException:
                # report a failed scene now: drop the queued scenes (the running ones finish into the cache)
                pool.shutdown(wait=False, cancel_futures=True)
                raise
        rows = [done[i] for i, _ in suite]
    return {"config": config.to_dict(), **summarise(rows),
            "threads": torch.get_num_threads() if workers == 1 else threads_per_worker, "workers": workers}


def summarise(rows: list[dict]) -> dict:
    """The report of per-scene rows (:func:`run_scene`): {"summary": means, "scenes": rows}."""

    def mean(get):
        return float(np.mean([get(r) for r in rows]))

    summary = {
        "mean_abs_error_log10_E": mean(lambda r: r["abs_error"]["log10_E"]),
        "mean_abs_error_nu": mean(lambda r: r["abs_error"]["nu"]),
        "mean_abs_error_damping_ratio": mean(lambda r: r["abs_error"]["damping_ratio"]),
        # one outlier (a shape the subspace cannot squash enough) can carry the mean: the medians beside it
        "median_abs_error_log10_E": float(np.median([r["abs_error"]["log10_E"] for r in rows])),
        "median_abs_error_nu": float(np.median([r["abs_error"]["nu"] for r in rows])),
        "mean_model_error_observed_percent": mean(lambda r: r["model_error_at_truth_percent"]["observed_percent"]),
        "mean_model_error_future_percent": mean(lambda r: r["model_error_at_truth_percent"]["future_percent"]),
        "mean_model_error_observed_nonrigid_percent": mean(
            lambda r: r["model_error_at_truth_percent"]["observed_nonrigid_percent"]
        ),
        "mean_model_error_future_nonrigid_percent": mean(
            lambda r: r["model_error_at_truth_percent"]["future_nonrigid_percent"]
        ),
        # the rotation off the truth's and what the reduced model's first bounce adds to it at the true material (a
        # scene without a contact adds 0); absent when a row predates these measures
        **(
            {
                "mean_model_error_rotation_observed_deg": mean(lambda r: r["model_error_at_truth_percent"][
                    "orientation"]["observed_mean_deg"]),
                "mean_model_error_rotation_future_deg": mean(lambda r: r["model_error_at_truth_percent"][
                    "orientation"]["future_mean_deg"]),
                "mean_model_error_first_contact_added_rotation_deg": mean(lambda r: r["model_error_at_truth_percent"][
                    "contacts"]["first_added_rotation_deg"] or 0.0),
                "mean_model_error_first_contact_added_centre_of_mass_m": mean(lambda r: r[
                    "model_error_at_truth_percent"]["contacts"]["first_added_centre_of_mass_m"] or 0.0),
            }
            if rows and all("orientation" in r["model_error_at_truth_percent"] for r in rows)
            else {}
        ),
        "mean_fitted_error_observed_percent": mean(lambda r: r["trajectory_error_fitted_percent"]["observed_percent"]),
        "mean_fitted_error_future_percent": mean(lambda r: r["trajectory_error_fitted_percent"]["future_percent"]),
        "mean_valley_depth_at_half_decade": mean(
            lambda r: min(r["e_valley"]["depth_at_minus"], r["e_valley"]["depth_at_plus"])
        ),
        "max_reduced_time_convergence_percent": max(
            r["reduced_time_convergence_at_truth"]["mean_percent"] for r in rows
        ),
        "mean_fit_seconds": mean(lambda r: r["fit"]["seconds"]),
        # fits that a failed line search ended early (their scenes' rows say where)
        "fit_line_search_failures": sum(int(r["fit"].get("line_search_failures", 0)) for r in rows),
        "mean_stiffness_scale": mean(lambda r: r["stiffness_scale"]),
        # how much ν moves the truth on the observed frames, and the ν change worth the model error
        **(
            {
                "mean_nu_sensitivity_observed_percent_per_0_05": mean(
                    lambda r: r["nu_sensitivity"]["observed_percent_per_0_05"]
                ),
                "median_nu_equivalent_of_model_error": float(
                    np.median([r["nu_sensitivity"]["nu_equivalent_of_model_error"] for r in rows])
                ),
            }
            if rows and all(r.get("nu_sensitivity") for r in rows)
            else {}
        ),
        # where the observed frames put ν at the true E: the fit's floor set by the model error
        **(
            {"mean_abs_nu_scan_argmin_error": mean(lambda r: abs(r["nu_scan"]["argmin_error"]))}
            if rows and all(r.get("nu_scan") for r in rows)
            else {}
        ),
        # images with perfect geometry, appearance and initial state: the reduced model's own ceiling
        **(
            {
                f"mean_{which}_{group}_{metric}": mean(lambda r, w=which, g=group, m=metric: r[f"images_{w}"][g][m])
                for which in ("at_truth", "fitted")
                for group in ("dynamic", "future")
                for metric in ("psnr", "ssim")
            }
            if rows and all(r.get("images_at_truth") for r in rows)
            else {}
        ),
        # lowest elastic frequency as a ratio to quadratic tets: the FEM truth's and the reduced model's stiffening
        **{
            f"mean_lowest_frequency_{key}": mean(lambda r, key=key: r["frequencies"][key][0])
            for key in ("linear_tets_over_quadratic", "reduced_over_quadratic", "reduced_over_linear_tets")
        },
    }
    return {"summary": summary, "scenes": rows}
