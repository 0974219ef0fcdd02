"""``vid2sim reconstruct``: a scene folder in, a simulation-ready asset out (paper §4.2).

Stages (each saved in a work folder beside the output, so an interrupted run resumes after its last finished
stage; the asset folder itself appears only when everything is done):

1. ``gaussians`` — 3D Gaussians fitted to frame 0 of the observed views (:func:`vid2sim.splats.fit_gaussians`).
2. ``points`` — the object's interior at frame 0 (:func:`vid2sim.reconstruct.stages.points.object_points`): simulation
   points, volume, contact points, canonical frame. The frame-0 hull is then carved again with the masks of
   the later frames that a tracked rigid pose explains (:mod:`vid2sim.reconstruct.stages.carving`): the sides that no
   camera saw in profile at frame 0, where the object meets the floor as it rolls, would otherwise give the
   bounce the wrong spin.
3. ``velocity`` — the initial rigid velocity from the ballistic pre-contact frames
   (:func:`vid2sim.reconstruct.stages.velocity.estimate_initial_velocity`).
4. ``appearance`` — the Gaussians refined on all those ballistic frames at once: the object's fitted rigid pose
   in frame t turns each camera into a virtual camera looking at the frame-0 object, so K frames of V views
   become K·V views of one rigid object (a few views of frame 0 alone leave the Gaussians overfitted to
   those viewpoints; as the object turns and moves, that shows).
5. ``networks`` — the skinning field trained data-free on the canonical points (and the Neural Jacobian when
   ``jacobian="neural"``), then moved to the metric frame by its input frame.
6. ``joint`` — the joint optimisation (:func:`vid2sim.reconstruct.stages.joint.joint_optimisation`) from the prior
   material.
7. ``motion_appearance`` — the Gaussians (colours, opacities and, by default, rest-frame geometry) refitted on
   every observed frame through the finished asset's simulated motion
   (:mod:`vid2sim.reconstruct.stages.motion_appearance`): after the bounce the views see sides of the object and a
   lighting that frame 0 never showed.

**Stage I** (``ReconstructConfig.stage1``, ``--stage1``; off by default while the shipped predictor misses its
accuracy targets — docs/predictor.md; before ``networks``): the feed-forward predictor
(:mod:`vid2sim.predictor.predict`; the shipped ``predictor_small.pt`` unless ``predictor`` names another
checkpoint) sees 16 frames of the observed view closest to the front camera and predicts log10 E, ν and the
skinning field's last layer. They become the prior material, the centre of the joint stage's coarse search
over log10 E (its grid shifted, spacing kept), and the skinning field's starting point (the template's hidden
layers with the predicted last layer) for the data-free skinning training. It is skipped — and the reason is
written to ``log.json`` ``stage1`` — when switched off (``--no-stage1``, the paper's "w/o Stage I"), when the
checkpoint is missing or transformers is not installed: the prior then is ``prior_E``/``prior_nu`` and the field a
seeded initialisation. With ``handles`` other than the template's (10) it gives the material only (the predicted last
layer is for 10 handles), and ``log.json`` says so (``skinning_start`` false).

Physics runs in the scene's metric frame: E in Pa is the real material if the scene's scale is metric and the
density right. A drop only identifies E/ρ; the density comes from ``scene.json`` ``metadata.density`` when
present, else ``ReconstructConfig.density`` (1000 kg/m³).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from vid2sim.physics.solver import SimConfig
from vid2sim.reconstruct.stages.joint import JointConfig
from vid2sim.reconstruct.stages.points import PointsConfig
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.splats.densify import DensifyConfig
from vid2sim.splats.fitting import FitConfig
from vid2sim.splats.shading import Shading

STAGES = ("gaussians", "points", "velocity", "appearance", "networks", "joint", "motion_appearance")


@dataclass
class ReconstructConfig:
    """Settings of :func:`reconstruct` (saved as the asset's ``config.json``).

    Attributes:
        gaussians: Gaussian fitting of frame 0.
        points: interior points.
        handles: learned skinning handles (+1 rigid).
        skinning_iterations: data-free skinning iterations (paper: 10 000; 17 ms each on 2 CPU cores).
        skinning_objective: "modal" (the subspace's lowest vibration modes; the default) or "random_z" (the
            paper's), :class:`~vid2sim.physics.SkinningTrainingConfig`; trained on the ``points.num_points``
            samples. The modal subspace's lowest frequency is 1.11 × the converged one on the ``bench identify``
            shapes (random z: 1.48 ×), and on the small suite it fits E closer (docs/architecture.md).
        num_cubature: cubature points (paper: 500).
        jacobian: "closed_form" (exact dF/dz from the field; faster on a CPU) or "neural" (paper's Neural Jacobian).
        jacobian_iterations: data-free Neural Jacobian iterations when ``jacobian="neural"``.
        velocity_frames: at most this many pre-contact frames estimate the initial velocity.
        appearance_iterations: Gaussian refinement steps on the ballistic frames (0: skip).
        motion_appearance_iterations: steps of the last stage, the Gaussians fitted to all observed frames
            through the simulated motion (0: skip; the Gaussians of the ballistic frames are kept).
        motion_appearance_geometry: the last stage also fits the Gaussians' rest-frame centres, scales and
            rotations (default, beyond the paper); False: colours and opacities only.
        motion_appearance_shading: the last stage separates albedo from a light fixed in the world
            (:mod:`vid2sim.splats.shading`: Lambert's law with an ambient share; the normals, the light's
            direction and the ambient share are fitted along with the colours), so the asset is lit by its pose
            as it turns (beyond the paper); False: the colours keep the light of the frames they were fitted to.
        motion_appearance_loss_power: p in (0, 1]: each step of the last stage minimises (its image loss)^p.
            1 is 3DGS's loss; below 1 a frame's gradient is scaled by its loss^(p − 1), so the frames the
            simulated motion explains well count more against those it does not (p = 0.5: the square root).
        prior_E, prior_nu, prior_damping: the starting material when Stage I does not run (Stage I replaces the
            first two).
        stage1: run the Stage I predictor (module docstring); False (the default until the shipped predictor
            meets its targets) is the paper's "w/o Stage I" ablation.
        predictor: its checkpoint (None: the one shipped with vid2sim).
        density: kg/m³ when the scene does not give one.
        calibrate_stiffness: scale the simulator's elastic energy by s = (ω_tets / ω_subspace)² of the lowest
            mode, so that the fitted E is the material's rather than the stiffer subspace's
            (:mod:`vid2sim.reconstruct.stages.calibration`: quadratic tets on a surface of the kept voxels; see
            ``calibration_nu``). On by default: on the eight-scene small suite it takes the E error from
            0.27 to 0.20 decade and ν's from 0.10 to 0.07 (docs/results.md). Its tet reference runs in a child process
            beside the velocity, appearance and network stages. fTetWild is not deterministic, so a
            calibrated reconstruction is not bit-reproducible: s depends on the mesh it makes.
        calibration_nu: with ``calibrate_stiffness``, "two_factor" (the default) a factor on μ and one on λ
            over a grid of ν, matched to the six lowest modes
            (:func:`vid2sim.physics.modes.stiffness_calibration_curve` with ``factors=2``), used at the
            simulator's current ν; "curve" one factor s(ν) over that grid (the subspace's locking grows with ν);
            "prior" one factor at the prior ν.
        calibration_cells: the surface grid's cells along the longest side for that reference mesh.
        calibration_points: samples of the kept voxels that grid is made from.
        volumetric: the simulator's volumetric term, "pointwise" or "projected" onto the skinning weights'
            span (``Simulator(volumetric=)``, :mod:`vid2sim.physics.volumetric`: no volumetric locking, so λ
            needs no factor of its own; calibrate with ``calibration_nu`` "curve").
        mass: the simulator's lumped masses: "cubature" (the default: the cubature volumes as sampled, whose
            inertia tensor is a few percent off) or "moments" — those volumes corrected so that the mass, centre
            of mass and inertia tensor are the kept voxels' (:mod:`vid2sim.physics.mass`; the default of
            ``bench identify``, where it took |Δν| from 0.121 to 0.043; not yet measured on the video suite, and
            the hull's own moments are off where the hull is too large).
        sim: the simulator's settings (time-converged BDF2 substeps by default).
        joint: the joint optimisation.
        seed: seeds every stage.
    """

    gaussians: FitConfig = field(default_factory=lambda: FitConfig(iterations=1000))
    points: PointsConfig = field(default_factory=PointsConfig)
    handles: int = 10
    skinning_iterations: int = 2000
    skinning_objective: str = "modal"
    num_cubature: int = 500
    jacobian: str = "closed_form"
    jacobian_iterations: int = 2000
    velocity_frames: int = 8
    appearance_iterations: int = 300
    motion_appearance_iterations: int = 300
    motion_appearance_geometry: bool = True
    motion_appearance_shading: bool = True
    motion_appearance_loss_power: float = 1.0
    prior_E: float = 1e5
    prior_nu: float = 0.3
    prior_damping: float = 0.05
    density: float = 1000.0
    calibrate_stiffness: bool = True
    calibration_nu: str = "two_factor"
    calibration_cells: int = 96
    calibration_points: int = 200_000
    volumetric: str = "pointwise"
    mass: str = "cubature"
    sim: SimConfig = field(default_factory=SimConfig)
    joint: JointConfig = field(default_factory=JointConfig)
    seed: int = 0
    stage1: bool = False
    predictor: str | None = None

    def __post_init__(self) -> None:
        if self.jacobian not in ("closed_form", "neural"):
            raise ConfigError(f"ReconstructConfig.jacobian must be 'closed_form' or 'neural', got {self.jacobian!r}")
        from vid2sim.physics.skinning_training import OBJECTIVES

        if self.skinning_objective not in OBJECTIVES:
            raise ConfigError(f"ReconstructConfig.skinning_objective must be one of {OBJECTIVES}, "
                             f"got {self.skinning_objective!r}")
        if self.calibration_nu not in ("curve", "two_factor", "prior"):
            raise ConfigError("ReconstructConfig.calibration_nu must be 'curve', 'two_factor' or 'prior', "
                             f"got {self.calibration_nu!r}")
        if self.volumetric not in ("pointwise", "projected"):
            raise ConfigError(f"ReconstructConfig.volumetric must be 'pointwise' or 'projected', got {self.volumetric!r}")
        if self.mass not in ("moments", "cubature"):
            raise ConfigError(f"ReconstructConfig.mass must be 'moments' or 'cubature', got {self.mass!r}")
        if self.volumetric == "projected" and self.calibrate_stiffness and self.calibration_nu == "two_factor":
            raise ConfigError("ReconstructConfig: the projected volumetric term does not lock, so its calibration "
                             "takes one factor (calibration_nu 'curve' or 'prior'), not 'two_factor'")
        for name in ("handles", "skinning_iterations", "num_cubature", "velocity_frames", "calibration_cells",
                     "calibration_points"):
            if getattr(self, name) < 1:
                raise ConfigError(f"ReconstructConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("appearance_iterations", "motion_appearance_iterations"):
            if getattr(self, name) < 0:
                raise ConfigError(f"ReconstructConfig.{name} must be >= 0, got {getattr(self, name)}")
        p = self.motion_appearance_loss_power
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 < p <= 1:
            raise ConfigError(f"ReconstructConfig.motion_appearance_loss_power must be in (0, 1], got {p!r}")
        if not (self.prior_E > 0 and 0 <= self.prior_nu < 0.5 and self.density > 0):
            raise ConfigError("ReconstructConfig needs prior_E > 0, 0 <= prior_nu < 0.5 and density > 0")

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> "ReconstructConfig":
        """``"small"`` (CPU minutes, the CI-sized suite) or ``"full"`` (the paper's sizes)."""
        if name == "small":
            # CPU minutes: at most 6 000 Gaussians (4 views of 128² need no more; rendering cost grows with
            # them), and the networks fixed during the joint optimisation (the paper's learning rate of 5e-7
            # moves them imperceptibly in 100 iterations, and their gradient costs a third of an iteration).
            # View-independent colours (SH degree 0): with 4 views, higher bands fit the views, not the object,
            # and as the object moves they change its colour in the joint optimisation's images (8-scene small
            # suite: |Δlog10 E| 0.155 against 0.243 at degree 3, images equal, 8 % faster; docs/results.md)
            base = cls(gaussians=FitConfig(iterations=500, sh_degree=0, densify=DensifyConfig(max_gaussians=6000)),
                       skinning_iterations=1000,
                       joint=JointConfig(iterations=100, validate_every=25, lr_skinning=0.0, lr_jacobian=0.0))
        elif name == "full":
            base = cls(gaussians=FitConfig(iterations=1000, views_per_step=2), skinning_iterations=2000,
                       joint=JointConfig(iterations=400, views_per_iteration=4))
        else:
            raise ConfigError(f"unknown reconstruct preset {name!r} (expected 'small' or 'full')")
        for key, value in overrides.items():
            if not hasattr(base, key):
                raise ConfigError(f"ReconstructConfig has no field {key!r}")
            setattr(base, key, value)
        base.__post_init__()
        return base

    def to_dict(self) -> dict[str, Any]:
        return _jsonable(asdict(self))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (int, float, str, bool)) or x is None:
        return x
    return repr(x)


class _Given:
    """An initializer that returns Gaussians already fitted (to refine them)."""

    def __init__(self, gaussians) -> None:
        self.gaussians = gaussians

    def __call__(self, images, masks, cameras, sh_degree, generator):
        return self.gaussians


def virtual_views(images: torch.Tensor, masks: torch.Tensor, cameras: list, rotations, translations
                  ) -> tuple[torch.Tensor, torch.Tensor, list]:
    """K frames of V views of a rigidly moving object as K·V views of the object at frame 0.

    Args:
        images: (V, K, H, W, 3); masks: (V, K, H, W); cameras: V cameras.
        rotations: (K, 3, 3), translations: (K, 3): frame t maps a frame-0 point X to R_t X + T_t.
    Returns:
        (K·V, H, W, 3) images, (K·V, H, W) masks, K·V cameras with world-to-camera = camera ∘ (R_t, T_t).
    """
    from vid2sim.splats.cameras import Camera

    V, K = images.shape[:2]
    dev = cameras[0].world_to_camera.device
    R = torch.as_tensor(rotations, dtype=torch.float32, device=dev)
    T = torch.as_tensor(translations, dtype=torch.float32, device=dev)
    cams = []
    for t in range(K):
        M = torch.eye(4, device=dev)
        M[:3, :3], M[:3, 3] = R[t], T[t]
        cams += [Camera(c.world_to_camera @ M, c.K, c.width, c.height) for c in cameras]
    return (images.transpose(0, 1).reshape(K * V, *images.shape[2:]),
            masks.transpose(0, 1).reshape(K * V, *masks.shape[2:]), cams)


class ReconstructionError(InputError):
    """The scene cannot be reconstructed as given (the message names the view, frame or field)."""


def check_scene(scene) -> None:
    """Raise :class:`ReconstructionError` for what would make the reconstruction meaningless: fewer than
    window + 1 observed frames, a view whose frame-0 mask is empty (named), an object touching the image
    border at frame 0 in a view (named)."""
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


class _Work:
    """The stage cache beside the output folder."""

    def __init__(self, out: Path, config: ReconstructConfig, scene_root: Path | None, restart: bool) -> None:
        self.dir = out.parent / f".{out.name}.work"
        key = {"config": config.to_dict(), "scene": str(scene_root.resolve()) if scene_root else None}
        key_path = self.dir / "key.json"
        if restart and self.dir.exists():
            shutil.rmtree(self.dir)
        if key_path.is_file() and json.loads(key_path.read_text()) != key:
            raise ReconstructionError(
                f"{self.dir} holds an interrupted reconstruction with other settings or another scene; run with "
                "the same settings to resume it, or with --restart to start over")
        self.dir.mkdir(parents=True, exist_ok=True)
        key_path.write_text(json.dumps(key))
        self.timings_path = self.dir / "timings.json"
        self.timings = json.loads(self.timings_path.read_text()) if self.timings_path.is_file() else {}

    def done(self, stage: str) -> bool:
        return (self.dir / f"{stage}.done").is_file()

    def finish(self, stage: str, seconds: float) -> None:
        self.timings[stage] = seconds
        self.timings_path.write_text(json.dumps(self.timings))
        (self.dir / f"{stage}.done").write_text("")


def _calibrated(path: Path, want_curve: bool, want_two: bool, volumetric: str, mass: str | None = None) -> bool:
    """Whether the work folder's stiffness calibration exists and is of the kind asked for (``mass``: also with
    that lumping of the mass; None: any)."""
    if not path.is_file():
        return False
    stored = json.loads(path.read_text())
    curve = stored.get("stiffness_curve")
    if mass is not None and stored.get("mass", "cubature") != mass:
        return False
    return (bool(curve), bool(curve and curve.get("lam_scale")), stored.get("volumetric", "pointwise")) == \
        (want_curve, want_two, volumetric)


def _stored_reference(path: Path, nus: tuple[float, ...], k: int) -> dict | None:
    """The tet reference a finished :class:`~vid2sim.reconstruct.stages.calibration.TetReferenceJob` left at ``path`` for this
    grid and k, or None."""
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
    except json.JSONDecodeError:
        return None
    reference = stored.get("reference") if stored.get("ok") else None
    if reference is None or reference.get("nus") != [float(v) for v in nus] or reference.get("k") != k:
        return None
    return reference


def _calibration_points(obj, cfg: ReconstructConfig) -> torch.Tensor:
    """(N, 3) samples of the kept voxels of ``obj`` (:class:`~vid2sim.reconstruct.stages.points.ObjectPoints`) that the
    calibration's reference mesh is made from."""
    from vid2sim.reconstruct.stages.points import sample_in_voxels

    return sample_in_voxels(obj.occupancy, obj.origin.double(), obj.voxel, cfg.calibration_points,
                            torch.Generator().manual_seed(cfg.seed))


def _cpu_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The module's state dict with CPU tensors (work files and assets load on any device)."""
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}


def _stage(progress: bool, text: str) -> None:
    if progress:
        from tqdm.auto import tqdm

        tqdm.write(text)


def run_stage1(cfg: ReconstructConfig, images: torch.Tensor, cameras: list, dt: float, centre: list[float],
               progress: bool = False) -> dict[str, Any]:
    """Stage I on the observed video (module docstring).

    Args:
        images: (V, T, H, W, 3) observed frames; cameras: the V observed cameras; dt: seconds between frames;
        centre: the object's centre at frame 0 (the front view is chosen by the angle seen from it).
    Returns:
        the record written to ``log.json`` ``stage1``: {"ran": False, "reason"} or {"ran": True, "E", "log10_E",
        "nu", "seconds", "view" (index into the observed views), "padded_frames", "checkpoint",
        "coarse_log10_E", "skinning_start", "skinning_note"} plus "last_layer" (650,) (a tensor, not written to
        the log). With ``cfg.handles`` other than the template's, the predicted last layer does not fit the
        field: the material is used, "skinning_start" is False, "skinning_note" says why and "last_layer" is
        None.
    """
    from vid2sim.predictor.predict import DEFAULT_PREDICTOR

    if not cfg.stage1:
        return {"ran": False, "reason": "disabled (stage1=False / --no-stage1: the 'w/o Stage I' ablation)"}
    path = Path(cfg.predictor) if cfg.predictor is not None else DEFAULT_PREDICTOR
    if not path.is_file():
        reason = f"no predictor checkpoint at {path}"
        _stage(progress, f"      Stage I skipped: {reason}")
        return {"ran": False, "reason": reason, "checkpoint": str(path)}
    from vid2sim.predictor.predict import centred_grid, front_video, predict_video
    from vid2sim.predictor.template import load_template

    template = load_template()
    skinning_note = None
    if cfg.handles != template.num_handles:
        skinning_note = (f"ReconstructConfig.handles is {cfg.handles}, the predicted last layer is for the template's "
                         f"{template.num_handles} handles: the skinning field starts from its own initialisation")
    from vid2sim.predictor.train import load_predictor

    _stage(progress, "[Stage I] predicting the material and skinning field from the front view")
    t0 = time.perf_counter()
    try:
        model = load_predictor(path)
    except ImportError as exc:  # transformers is not installed
        reason = f"the predictor cannot be loaded: {exc}"
        _stage(progress, f"      Stage I skipped: {reason}")
        return {"ran": False, "reason": reason, "checkpoint": str(path)}
    target_dt = float((model.data_config or {}).get("dt", 0.05))
    video, view, padded = front_video(images, cameras, dt, model.image_size, model.num_frames, target_dt, centre,
                                      framing=model.config.framing)
    pred = predict_video(model, video)
    if skinning_note is not None:
        _stage(progress, f"      Stage I gives the material only: {skinning_note}")
    return {"ran": True, "E": pred["E"], "log10_E": pred["log10_E"], "nu": pred["nu"],
            "seconds": time.perf_counter() - t0, "inference_seconds": pred["seconds"], "view": view,
            "padded_frames": padded, "checkpoint": str(path),
            "coarse_log10_E": list(centred_grid(cfg.joint.coarse_log10_E, pred["log10_E"])),
            "skinning_start": skinning_note is None, "skinning_note": skinning_note,
            "last_layer": pred["last_layer"] if skinning_note is None else None}


def reconstruct(scene_path: str | Path, out: str | Path, config: ReconstructConfig | None = None,
                progress: bool = True, restart: bool = False, device: str | torch.device | None = None) -> Path:
    """Reconstruct the scene folder ``scene_path`` into the asset folder ``out`` (see the module docstring).

    ``device`` (None: CUDA when available, else the CPU) runs the Gaussian fits, the networks' training and
    the joint optimisation; the cheap geometric stages (points, initial velocity) and Stage I run on the CPU.
    The device is not part of the configuration: a run interrupted on one device resumes on another, and the
    asset is written with CPU tensors. While the stiffness calibration's tet reference runs in its child process
    (one thread), the stages run on one torch thread fewer than the caller's; the count is restored on return.

    Returns:
        the asset folder (readable with :func:`vid2sim.asset.folder.load_asset`).
    Raises:
        vid2sim.scene.validation.SceneFormatError: the scene folder is invalid.
        ReconstructionError: the scene cannot be reconstructed as given.
    """
    threads = torch.get_num_threads()
    try:
        return _reconstruct(scene_path, out, config, progress, restart, device, threads)
    finally:
        torch.set_num_threads(threads)


def _share_cores(job, threads: int) -> None:
    """Give the calibration's child process one of the caller's ``threads`` while it runs.

    The child computes with one thread. With it running, a caller on all the cores oversubscribes them, and
    torch's thread pool then slows several-fold (the appearance stage took 3.6× as long with 2 threads as
    with 1 on a 2-core machine). Called at every stage boundary until the child is joined; a child that has
    ended without its result is reported there (:meth:`~vid2sim.reconstruct.stages.calibration.TetReferenceJob.check`)
    rather than after the stages that run beside it.
    """
    if job is not None:
        job.check()
    busy = job is not None and job.running()
    torch.set_num_threads(max(1, threads - 1) if busy else threads)


def _reconstruct(scene_path: str | Path, out: str | Path, config: ReconstructConfig | None, progress: bool,
                 restart: bool, device: str | torch.device | None, threads: int) -> Path:
    """:func:`reconstruct`'s body; ``threads``: the caller's torch thread count (restored by the caller)."""
    from vid2sim.asset.folder import Asset, save_asset
    from vid2sim.physics import Floor, Gravity, Material, Simulator, SkinningField
    from vid2sim.physics.cubature import sample_cubature
    from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
    from vid2sim.physics.mass import moment_matched_volumes, voxel_moments
    from vid2sim.physics.modes import CURVE_NUS, TWO_FACTOR_MODES
    from vid2sim.physics.neural_jacobian import (
        NeuralJacobian,
        NeuralJacobianTrainingConfig,
        train_neural_jacobian,
    )
    from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
    from vid2sim.physics.stiffness_curve import StiffnessCurve
    from vid2sim.reconstruct.stages.carving import carve_with_frames
    from vid2sim.reconstruct.stages.joint import Observations, joint_optimisation
    from vid2sim.reconstruct.stages.points import ObjectPoints
    from vid2sim.reconstruct.stages.velocity import (
        TooFewBallisticFrames,
        estimate_initial_velocity,
    )
    from vid2sim.runtime.device import resolve_device
    from vid2sim.scene.folder import load_scene
    from vid2sim.splats.fitting import fit_gaussians
    from vid2sim.splats.ply import load_ply, save_ply

    cfg = config or ReconstructConfig()
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    out = Path(out)
    scene = load_scene(scene_path)
    check_scene(scene)
    work = _Work(out, cfg, scene.root, restart)
    V, T = scene.config.observed_views, scene.config.observed_frames
    images_cpu = scene.images[V][:, T].float()
    masks_cpu = scene.masks[V][:, T].float()
    cameras_cpu = [scene.cameras[v] for v in V]
    images, masks = images_cpu.to(dev), masks_cpu.to(dev)
    cameras = [c.to(dev) for c in cameras_cpu]
    torch.manual_seed(cfg.seed)

    # 1. Gaussians ---------------------------------------------------------------------------------------
    ply = work.dir / "gaussians.ply"
    if not work.done("gaussians"):
        _stage(progress, "[1/7] fitting Gaussians to frame 0")
        t0 = time.perf_counter()
        g = fit_gaussians(images[:, 0], masks[:, 0], cameras, cfg.gaussians, progress=progress)
        save_ply(g, ply)
        work.finish("gaussians", time.perf_counter() - t0)
    gaussians = load_ply(ply, device=dev)

    # 2. points ------------------------------------------------------------------------------------------
    pts_path = work.dir / "points.pt"
    if not work.done("points"):
        _stage(progress, "[2/7] filling the object with simulation points" +
               (f" (the hull carved with the later frames, {cfg.points.frame_rounds} rounds)"
                if cfg.points.frame_rounds else ""))
        t0 = time.perf_counter()
        carved, carving = carve_with_frames(masks_cpu, cameras_cpu, float(scene.config.dt), scene.config.gravity,
                                            gaussians.to("cpu"), cfg.points, progress=progress)
        torch.save(asdict(carved), pts_path)
        (work.dir / "carving.json").write_text(json.dumps(carving))
        work.finish("points", time.perf_counter() - t0)
    obj_cpu = ObjectPoints(**torch.load(pts_path, weights_only=True))
    carving = json.loads((work.dir / "carving.json").read_text())
    obj = dataclasses.replace(obj_cpu, **{k: getattr(obj_cpu, k).to(dev) for k in
                                          ("points", "contact_points", "contact_areas", "centre")})

    # the stiffness calibration's tet reference needs only the interior points: on a ν grid it is computed in a
    # child process while the velocity, appearance and network stages run, and joined before the joint stage
    calibration_path = work.dir / "stiffness.json"
    reference_path = work.dir / "stiffness_reference.json"
    want_curve = cfg.calibration_nu != "prior"
    want_two = cfg.calibration_nu == "two_factor"
    reference_k = TWO_FACTOR_MODES if want_two else 1
    reference_job = None
    if cfg.calibrate_stiffness and want_curve and \
            not _calibrated(calibration_path, want_curve, want_two, cfg.volumetric) and \
            _stored_reference(reference_path, CURVE_NUS, reference_k) is None:
        from vid2sim.reconstruct.stages.calibration import TetReferenceJob

        reference_job = TetReferenceJob(_calibration_points(obj_cpu, cfg).numpy(), reference_path, nus=CURVE_NUS,
                                        k=reference_k, cells=cfg.calibration_cells, seed=cfg.seed)
    _share_cores(reference_job, threads)

    # 3. initial velocity --------------------------------------------------------------------------------
    vel_path = work.dir / "velocity.json"
    if not work.done("velocity"):
        _stage(progress, "[3/7] estimating the initial velocity from the pre-contact frames")
        t0 = time.perf_counter()
        gravity = torch.tensor(scene.config.gravity, dtype=torch.float32)
        contact_before_frame_1 = False
        try:
            est = estimate_initial_velocity(obj_cpu.points, masks_cpu, cameras_cpu, scene.config.dt, gravity,
                                            scene.config.floor_height, max_frames=cfg.velocity_frames)
        except TooFewBallisticFrames as exc:
            # the object meets the floor by frame 1: frames 0 and 1 still give the velocity to first order
            # (the floor test off); the joint optimisation refines it, and the asset records what happened
            _stage(progress, f"      {exc}; estimating from frames 0 and 1 regardless of the floor")
            est = estimate_initial_velocity(obj_cpu.points, masks_cpu, cameras_cpu, scene.config.dt, gravity, None,
                                            max_frames=2)
            contact_before_frame_1 = True
        vel_path.write_text(json.dumps({"contact_before_frame_1": contact_before_frame_1,
                                        "linear": est.linear.tolist(), "angular": est.angular.tolist(),
                                        "centre": est.centre.tolist(), "frames_used": est.frames_used,
                                        "residual_px": est.residual_px, "rotations": est.rotations.tolist(),
                                        "translations": est.translations.tolist()}))
        work.finish("velocity", time.perf_counter() - t0)
    velocity = json.loads(vel_path.read_text())

    # 4. appearance on the ballistic frames ---------------------------------------------------------------
    _share_cores(reference_job, threads)
    app_ply = work.dir / "gaussians_refined.ply"
    if not work.done("appearance"):
        t0 = time.perf_counter()
        K = int(velocity["frames_used"])
        if cfg.appearance_iterations > 0 and K > 1:
            _stage(progress, f"[4/7] refining the Gaussians on {K} ballistic frames x {len(cameras)} views")
            views, vmasks, vcams = virtual_views(images[:, :K], masks[:, :K], cameras, velocity["rotations"],
                                                 velocity["translations"])
            refine = dataclasses.replace(cfg.gaussians, iterations=cfg.appearance_iterations, densify_from=0.0,
                                         densify_until=0.0, views_per_step=cfg.gaussians.views_per_step or len(cameras), sh_band_every=0.0,
                                         seed=cfg.seed)
            g = fit_gaussians(views, vmasks, vcams, refine, initializer=_Given(gaussians), progress=progress)
        else:
            g = gaussians
        save_ply(g, app_ply)
        work.finish("appearance", time.perf_counter() - t0)
    gaussians = load_ply(app_ply, device=dev)

    # Stage I ---------------------------------------------------------------------------------------------
    _share_cores(reference_job, threads)
    s1_path = work.dir / "stage1.json"
    if not s1_path.is_file():
        s1 = run_stage1(cfg, images_cpu, cameras_cpu, float(scene.config.dt), obj_cpu.centre.tolist(), progress)
        if s1["ran"]:
            s1["scene_view"] = int(V[s1["view"]])
        torch.save(s1.pop("last_layer", None), work.dir / "stage1_last_layer.pt")
        s1_path.write_text(json.dumps(s1))
    stage1 = json.loads(s1_path.read_text())
    prior_E, prior_nu, joint_cfg = cfg.prior_E, cfg.prior_nu, cfg.joint
    if stage1["ran"]:
        prior_E, prior_nu = stage1["E"], stage1["nu"]
        joint_cfg = dataclasses.replace(cfg.joint, coarse_log10_E=tuple(stage1["coarse_log10_E"]))

    # 5. networks ----------------------------------------------------------------------------------------
    _share_cores(reference_job, threads)
    field_path, jac_path = work.dir / "skinning.pt", work.dir / "jacobian.pt"
    field = SkinningField(cfg.handles, seed=cfg.seed)
    if stage1["ran"] and stage1.get("skinning_start", True):
        from vid2sim.predictor.template import field_from_last_layer, load_template

        field = field_from_last_layer(load_template(), torch.load(work.dir / "stage1_last_layer.pt",
                                                                  weights_only=True))
    field = field.to(dev)
    jacobian = (NeuralJacobian(num_handles_total=cfg.handles + 1, seed=cfg.seed).to(dev) if cfg.jacobian == "neural"
                else None)
    if not work.done("networks"):
        _stage(progress, "[5/7] training the skinning field data-free" +
               (" and the Neural Jacobian" if jacobian is not None else ""))
        t0 = time.perf_counter()
        canonical = obj.canonical(obj.points)
        train_skinning(field, canonical, SkinningTrainingConfig(iterations=cfg.skinning_iterations, seed=cfg.seed,
                                                                objective=cfg.skinning_objective),
                       progress=progress, volume=obj.volume / obj.scale ** 3)
        field.set_input_frame(obj.centre, obj.scale)
        torch.save(_cpu_state(field), field_path)
        if jacobian is not None:
            jacobian.set_input_frame(obj.centre, obj.scale)
            train_neural_jacobian(jacobian, field, obj.points, NeuralJacobianTrainingConfig(
                iterations=cfg.jacobian_iterations, seed=cfg.seed), progress=progress)
            torch.save(_cpu_state(jacobian), jac_path)
        work.finish("networks", time.perf_counter() - t0)
    field.load_state_dict(torch.load(field_path, weights_only=True))  # copied onto the field's device
    if jacobian is not None:
        jacobian.load_state_dict(torch.load(jac_path, weights_only=True))

    # 6. joint optimisation ------------------------------------------------------------------------------
    density = float(scene.config.metadata.get("density", cfg.density)) if isinstance(
        scene.config.metadata.get("density"), (int, float)) else cfg.density
    idx, weights = sample_cubature(obj.points, cfg.num_cubature, volume=obj.volume, seed=cfg.seed)
    mass_volumes = None
    if cfg.mass == "moments":  # the kept voxels' mass, centre of mass and inertia, exactly
        mass_volumes = moment_matched_volumes(obj.points[idx], weights,
                                              voxel_moments(obj.occupancy, obj.origin, obj.voxel).to(weights))
    if cfg.calibrate_stiffness and not _calibrated(calibration_path, want_curve, want_two, cfg.volumetric, cfg.mass):
        from vid2sim.reconstruct.stages.calibration import calibrate_stiffness

        _stage(progress, "      calibrating the subspace's stiffness against quadratic tets")
        if want_curve:
            reference = reference_job.result() if reference_job is not None else _stored_reference(
                reference_path, CURVE_NUS, reference_k)
            dense = None
        else:  # one factor at the prior's ν (Stage I may have set it): computed here
            reference, dense = None, _calibration_points(obj_cpu, cfg)
        calibration = calibrate_stiffness(field, obj.points[idx], weights, dense, prior_nu,
                                          cells=cfg.calibration_cells, seed=cfg.seed,
                                          nus=CURVE_NUS if want_curve else None, factors=2 if want_two else 1,
                                          reference=reference, volumetric=cfg.volumetric, mass_volumes=mass_volumes)
        calibration_path.write_text(json.dumps(calibration))
    calibration = (json.loads(calibration_path.read_text()) if cfg.calibrate_stiffness
                   else {"stiffness_scale": 1.0, "stiffness_curve": None})
    _share_cores(reference_job, threads)  # joined above, or never started: all the caller's threads
    stiffness = (StiffnessCurve.from_dict(calibration["stiffness_curve"]) if calibration.get("stiffness_curve")
                 else calibration["stiffness_scale"])
    externals = [Gravity(list(scene.config.gravity))]
    if scene.config.floor_height is not None:
        externals.append(Floor(height=scene.config.floor_height, stiffness=AREA_CONTACT_STIFFNESS))
    material = Material(prior_E, prior_nu, density, damping_ratio=cfg.prior_damping)
    sim = Simulator(field, obj.points[idx], weights, material, externals, cfg.sim, jacobian=jacobian,
                    use_neural_jacobian=jacobian is not None, length_scale=obj.scale,
                    contact_points=obj.contact_points, contact_weights=obj.contact_areas,
                    stiffness_scale=stiffness, volumetric=cfg.volumetric, mass_volumes=mass_volumes)
    joint_path = work.dir / "joint.json"
    if not work.done("joint"):
        _stage(progress, "[6/7] joint optimisation of the material, initial velocity and networks")
        t0 = time.perf_counter()
        result = joint_optimisation(sim, gaussians, Observations(images, cameras), velocity["linear"],
                                    velocity["angular"], velocity["centre"], joint_cfg, progress=progress)
        torch.save(_cpu_state(field), work.dir / "skinning_joint.pt")
        if jacobian is not None:
            torch.save(_cpu_state(jacobian), work.dir / "jacobian_joint.pt")
        joint_path.write_text(json.dumps(asdict(result)))
        work.finish("joint", time.perf_counter() - t0)
    result = json.loads(joint_path.read_text())
    offset = torch.tensor(result.get("centre_of_mass_offset", [0.0, 0.0, 0.0]), dtype=torch.float64)
    if bool(offset.ne(0).any()):  # the joint stage's search moved the centre of mass: the same masses again
        from vid2sim.physics.mass import centre_shifted_volumes

        mass_volumes = centre_shifted_volumes(obj.points[idx], weights if mass_volumes is None else mass_volumes,
                                              offset).to(weights)
    field.load_state_dict(torch.load(work.dir / "skinning_joint.pt", weights_only=True))
    if jacobian is not None:
        jacobian.load_state_dict(torch.load(work.dir / "jacobian_joint.pt", weights_only=True))

    material_json = {"model": "neo-hookean", "E": float(10.0 ** result["log10_E"]), "log10_E": result["log10_E"],
                     "nu": result["nu"], "density": density, "damping_ratio": result["damping_ratio"],
                     "stiffness_scale": (stiffness.at(result["nu"]) if isinstance(stiffness, StiffnessCurve)
                                         else stiffness), "volumetric": cfg.volumetric}
    if isinstance(stiffness, StiffnessCurve):
        material_json["stiffness_curve"] = stiffness.to_dict()
    field, jacobian = field.to("cpu"), (jacobian.to("cpu") if jacobian is not None else None)
    asset = Asset(gaussians=gaussians.to("cpu"), field=field, jacobian=jacobian, material=material_json,
                  cubature_points=obj_cpu.points[idx.cpu()], cubature_weights=weights.cpu(),
                  contact_points=obj_cpu.contact_points, contact_areas=obj_cpu.contact_areas, points=obj_cpu.points,
                  volume=obj.volume, sim_config=cfg.sim,
                  mass_volumes=None if mass_volumes is None else mass_volumes.detach().cpu(),
                  gravity=list(scene.config.gravity), floor_height=scene.config.floor_height,
                  floor_stiffness=AREA_CONTACT_STIFFNESS, length_scale=obj.scale,
                  initial_velocity={"linear": result["linear_velocity"], "angular": result["angular_velocity"],
                                    "centre": velocity["centre"]},
                  dt=float(scene.config.dt),
                  extra={"canonical_frame": {"centre": obj_cpu.centre.tolist(), "scale": obj.scale,
                                             "maps": "X -> (X - centre) / scale"},
                         "scene": str(scene.root), "observed_views": list(V), "observed_frames": len(T),
                         "scene_frames": int(scene.images.shape[1]),
                         "volume_m3": obj.volume, "gaussians": gaussians.num,
                         "initial_velocity_estimate": velocity, "validation_loss": result["validation_loss"],
                         "centre_of_mass_offset": offset.tolist()})
    motion_ply = work.dir / "gaussians_motion.ply"
    if cfg.motion_appearance_iterations > 0:
        if not work.done("motion_appearance"):
            from vid2sim.reconstruct.stages.motion_appearance import (
                SkinnedMotion,
                initial_shading,
                refine_on_motion,
            )

            what = "Gaussians" if cfg.motion_appearance_geometry else "colours"
            _stage(progress, f"[7/7] refitting the {what} on {len(T)} observed frames along the simulated motion")
            t0 = time.perf_counter()
            motion = SkinnedMotion.of_asset(asset, max(T) + 1, device=dev)
            start, shading = gaussians, None
            if cfg.motion_appearance_shading:
                shading = initial_shading(gaussians, obj_cpu.points.to(dev), obj.volume, scene.config.gravity)
                start = dataclasses.replace(gaussians, sh=shading.unshade(gaussians.sh))
            refined, shading, record = refine_on_motion(start, motion, images, cameras, list(T), cfg.gaussians,
                                                        cfg.motion_appearance_iterations,
                                                        geometry=cfg.motion_appearance_geometry, seed=cfg.seed,
                                                        progress=progress, shading=shading,
                                                        loss_power=cfg.motion_appearance_loss_power)
            save_ply(refined.to("cpu"), motion_ply)
            if shading is not None:
                torch.save(shading.to("cpu").__dict__, work.dir / "shading_motion.pt")
            (work.dir / "motion_appearance.json").write_text(json.dumps(record))
            work.finish("motion_appearance", time.perf_counter() - t0)
        shading_path = work.dir / "shading_motion.pt"
        shading = Shading(**torch.load(shading_path, weights_only=True)) if shading_path.is_file() else None
        asset = dataclasses.replace(asset, gaussians=load_ply(motion_ply), shading=shading)
        asset.extra["motion_appearance"] = json.loads((work.dir / "motion_appearance.json").read_text())
    log = {"timings_seconds": work.timings, "stage1": stage1, "carving": carving, "stiffness_calibration": calibration, "coarse_search": result["coarse"],
           "centre_of_mass_search": result.get("centre_of_mass_search", []), "iterations": result["log"]}
    save_asset(asset, out, config=cfg.to_dict(), log=log)
    shutil.rmtree(work.dir, ignore_errors=True)
    return out
