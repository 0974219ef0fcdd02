"""Stage I training data: dropped objects, simulated by the FEM ground truth (``truth="fem"``, the default;
:mod:`vid2sim.predictor.fem_truth`) or by the reduced simulator (``truth="reduced"``), seen from the front camera
and ``views − 1`` more cameras of its ring.

One **object** (procedural, or a user mesh) gives one **shard** of ``draws_per_object`` **samples**
(:func:`make_object_shard`). The reduced truth's steps (the FEM's differ in 6: see its module):

1. The object. A procedural object comes from ``make_procedural_object(object_seed)``; a user mesh from
   :func:`~vid2sim.synthetic.meshes.load_user_mesh`.
2. Its pose. It is turned by a uniformly random rotation and re-normalised to the canonical frame (centred
   bounding box, half-diagonal 0.5). The rest shape IS this posed object, as in the synthetic scenes: the
   shape Stage II sees at frame 0.
3. Its samples (:mod:`vid2sim.predictor.solid`): interior points, volume, and surface contact points with
   their areas.
4. Its label. The skinning field's last layer is fitted with the template's hidden layers frozen
   (:func:`vid2sim.predictor.template.fit_last_layer`; 650 numbers in the canonical gauge).
5. Its cubature points: 500, farthest-point sampled, weights volume / 500.
6. Per draw:

   - The material: E log-uniform in ``E_range``, ν uniform in ``nu_range``, the damping ratio log-uniform in
     ``damping_ratio`` (its own random stream, so a fixed ratio leaves the other draws as they were).
   - The drop: a clearance above the floor, a linear and an angular velocity
     (:meth:`vid2sim.synthetic.fem.InitialPose.random`, the synthetic scenes' ranges). The object is
     lifted so that its lowest vertex has that clearance.
   - The simulation: the reduced :class:`~vid2sim.physics.Simulator` (BDF2, automatic substeps,
     converged in time) with gravity and the floor as a contact pressure on the surface points
     (``AREA_CONTACT_STIFFNESS``, as ``reconstruct`` does), for ``frames − 1`` frames of ``dt``.
   - The video: the mesh vertices skinned at every frame (frame 0 is the initial pose), rendered with
     the textured-mesh renderer from the front camera (:mod:`vid2sim.predictor.front_view`) and the other
     ``views − 1`` cameras of its ring, on white.

Seeds. Procedural object i of a dataset with seed s is ``make_procedural_object(10**9 * (s + 1) + i)``.
These seeds are disjoint from the synthetic benchmark's scenes (small seeds) and from the template's shapes
(10⁶ + k), so no test object is in the training data. The rotation, materials and drops come from numpy
generators keyed by (s, kind, index).

Storage (:func:`make_training_data`): one ``.npz`` per object, written atomically with fixed zip
timestamps, so equal inputs give byte-identical files. An ``index.json`` holds the config, the shards, the
counts, the dataset statistics and the timings. docs/training-data.md gives the format.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import shutil
import sys
import time
import zipfile
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from vid2sim.meshing.tetra import TetrahedralizationError
from vid2sim.physics import Floor, Gravity, Material, SimConfig, SimulationError, Simulator
from vid2sim.physics.cubature import sample_cubature
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.skinning import deform, deformation_gradient, gradient_basis
from vid2sim.predictor.fem_truth import FEMTruth, make_fem_shard
from vid2sim.predictor.front_view import FrontCamera
from vid2sim.predictor.solid import sample_solid
from vid2sim.predictor.template import TEMPLATE_PATH, field_from_last_layer, fit_last_layer, load_template
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.files import check_output_folder, remove_temp_files, write_file_atomic, write_json_atomic
from vid2sim.runtime.ray_runner import import_ray, ray_map
from vid2sim.runtime.workers import process_pool
from vid2sim.synthetic.fem import FEMSolverError, InitialPose
from vid2sim.synthetic.mesh_render import render_textured_mesh
from vid2sim.synthetic.meshes import load_user_mesh, normalize_to_canonical
from vid2sim.synthetic.shapes import make_procedural_object, random_rotation

FORMAT = "vid2sim-training-data/1"
TRUTHS = ("fem", "reduced")
#: the settings whose default depends on the truth (None in :class:`TrainingDataConfig` until resolved). The
#: reduced truth's are the generator's before the FEM truth existed, so its datasets resume and reproduce.
TRUTH_DEFAULTS: dict[str, dict[str, Any]] = {
    # E a quarter decade beyond the benchmark's [1e4, 1e6] at both ends, so that the benchmark's range is not
    # the prior's edge (above 1e6 a 1 m drop's contact already lasts under a frame; the FEM's substeps grow as
    # √E); ζ log-uniform around the simulators' default 0.05; four views, 90° apart, for multi-view predictors;
    # two draws per object (an FEM draw costs minutes, the object seconds: more shapes for the same cost)
    "fem": {"E_range": (10**3.75, 10**6.25), "damping_ratio": (0.025, 0.1), "views": 4, "draws_per_object": 2},
    "reduced": {"E_range": (1e4, 1e6), "damping_ratio": (0.05, 0.05), "views": 1, "draws_per_object": 4},
}
INDEX = "index.json"
#: procedural object i of a dataset with seed s is make_procedural_object(OBJECT_SEED_STRIDE * (s + 1) + i)
OBJECT_SEED_STRIDE = 10**9
_KIND_KEY = {"procedural": 0, "mesh": 1}
#: index.json is rewritten at most this often while shards are being made (and always at the end)
INDEX_EVERY_SECONDS = 10.0
#: the FEM truth's work folders (tet meshes and finished draws of unfinished objects), inside the dataset
WORK = "work"


@dataclass
class TrainingDataConfig:
    """Settings of a Stage I training dataset (written into ``index.json``; the defaults are the issue's).

    Attributes:
        truth: what simulates the drops: "fem" (the benchmark's ground truth, :mod:`vid2sim.predictor.fem_truth`)
            or "reduced" (the reduced simulator, the generator's only truth before issue #52).
        seed: the dataset's seed (objects, poses, materials, drops, fits).
        objects: procedural objects (one shard each).
        meshes: user mesh files (OBJ/GLB/GLTF/PLY), one more object (shard) each.
        draws_per_object: samples per object (material and drop draws); None: the truth's.
        frames: video frames (frame 0 is the initial pose; the simulator runs ``frames − 1``).
        resolution: video side in pixels (224 for VideoMAE; 64 on a CPU).
        dt: seconds between frames (the synthetic scenes' 0.05).
        E_range: Young's modulus range (Pa), drawn log-uniformly; None: the truth's (:data:`TRUTH_DEFAULTS`).
        nu_range: Poisson's ratio range, drawn uniformly (0.49: ν → 0.5 is incompressible).
        density: kg/m³.
        damping_ratio: range of the Kelvin–Voigt damping ratio ζ, drawn log-uniformly (one number: that ratio for
            every draw); None: the truth's.
        views: cameras rendered per draw: the front camera and ``views − 1`` more on its ring, evenly spaced in
            azimuth (``ring_video``); None: the truth's.
        drop_height: range of the clearance (m) between the lowest vertex and the floor at frame 0.
        max_horizontal_speed, max_downward_speed, max_angular_speed: bounds of the random rigid velocity
            (m/s, m/s, rad/s; the synthetic scenes').
        floor_height: the floor plane z (m).
        camera: the front camera (:class:`~vid2sim.predictor.front_view.FrontCamera`).
        supersample: anti-aliasing samples per pixel side of the mesh renderer.
        points: interior points per object (skinning fit and cubature choose among them).
        cubature_points: cubature points of the simulator (the paper's 500).
        contact_points: at most this many surface contact points.
        fit_iterations, fit_lr: Adam iterations (and rate) of the last-layer fit after its closed-form start.
        template: the template skinning network file, or None for the shipped one.
        max_retries: a draw whose simulation fails (inverted state) is replaced by a fresh draw at most this
            many times (recorded per sample).
        fem: the FEM truth's settings (:class:`~vid2sim.predictor.fem_truth.FEMTruth`, the benchmark suite's);
            None for the reduced truth.
    """

    truth: str = "fem"
    seed: int = 0
    objects: int = 100
    meshes: tuple[str, ...] = ()
    draws_per_object: int | None = None
    frames: int = 16
    resolution: int = 224
    dt: float = 0.05
    E_range: tuple[float, float] | None = None
    nu_range: tuple[float, float] = (0.2, 0.49)
    density: float = 1000.0
    damping_ratio: tuple[float, float] | float | None = None
    views: int | None = None
    drop_height: tuple[float, float] = (0.05, 0.3)
    max_horizontal_speed: float = 0.2
    max_downward_speed: float = 1.0
    max_angular_speed: float = 2.0
    floor_height: float = -0.7
    camera: FrontCamera = field(default_factory=FrontCamera)
    supersample: int = 2
    points: int = 20000
    cubature_points: int = 500
    contact_points: int = 1000
    fit_iterations: int = 0
    fit_lr: float = 3e-5
    template: str | None = None
    max_retries: int = 3
    fem: FEMTruth | None = None

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> ConfigError:
            return ConfigError(f"TrainingDataConfig.{name} must be {expected}, got {getattr(self, name)!r}")

        if self.truth not in TRUTHS:
            raise bad("truth", f"one of {TRUTHS}")
        for name, value in TRUTH_DEFAULTS[self.truth].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if isinstance(self.damping_ratio, (int, float)) and not isinstance(self.damping_ratio, bool):
            self.damping_ratio = (self.damping_ratio, self.damping_ratio)
        if isinstance(self.fem, dict):
            self.fem = FEMTruth(**self.fem)
        if self.truth == "fem" and self.fem is None:
            self.fem = FEMTruth()
        if self.truth == "reduced" and self.fem is not None:
            raise bad("fem", "None for the reduced truth")
        if self.fem is not None and not isinstance(self.fem, FEMTruth):
            raise bad("fem", "a FEMTruth")

        if isinstance(self.camera, dict):
            self.camera = FrontCamera(**self.camera)
        if not isinstance(self.camera, FrontCamera):
            raise bad("camera", "a FrontCamera")
        self.meshes = tuple(str(m) for m in self.meshes)
        for name, lo in (("seed", 0), ("objects", 0), ("draws_per_object", 1), ("frames", 2), ("resolution", 8),
                         ("views", 1),
                         ("supersample", 1), ("points", 100), ("cubature_points", 10), ("contact_points", 1),
                         ("fit_iterations", 0), ("max_retries", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise bad(name, f"an integer >= {lo}")
        if self.objects >= OBJECT_SEED_STRIDE:
            raise bad("objects", f"below {OBJECT_SEED_STRIDE}")
        if self.objects + len(self.meshes) == 0:
            raise ConfigError("TrainingDataConfig.objects must be >= 1 when no meshes are given, got 0")
        if self.cubature_points > self.points:
            raise bad("cubature_points", f"at most points ({self.points})")
        for name in ("dt", "density", "max_horizontal_speed", "max_downward_speed", "max_angular_speed",
                     "floor_height", "fit_lr"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(name, "a finite number")
        for name in ("dt", "density", "fit_lr"):
            if not getattr(self, name) > 0:
                raise bad(name, "positive")
        for name in ("max_horizontal_speed", "max_downward_speed", "max_angular_speed"):
            if getattr(self, name) < 0:
                raise bad(name, ">= 0")
        for name, lo, hi in (("E_range", 0.0, math.inf), ("nu_range", -1.0, 0.5), ("drop_height", 0.0, math.inf),
                             ("damping_ratio", 0.0, math.inf)):
            v = tuple(float(x) for x in getattr(self, name))
            ok = len(v) == 2 and all(math.isfinite(x) for x in v) and v[0] <= v[1]
            ok = ok and (v[0] > lo if name != "drop_height" else v[0] >= lo) and v[1] < hi
            if not ok:
                raise bad(name, f"a range (low, high) with {lo} {'<' if name != 'drop_height' else '<='} low <= high"
                                f" < {hi}")
            setattr(self, name, v)
        if self.template is not None:
            self.template = str(self.template)

    @property
    def total_objects(self) -> int:
        """Procedural objects + user meshes."""
        return self.objects + len(self.meshes)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (tuples as lists) that :meth:`from_dict` reads back."""
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "TrainingDataConfig":
        """The config of an ``index.json``. One without ``truth`` was written before the FEM truth existed: it
        is the reduced truth's (its damping ratio then one number, the same config)."""
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise ConfigError(f"unknown TrainingDataConfig fields {unknown}")
        return cls(**{"truth": "reduced", **values})


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a dataset: ``kind`` "procedural" (``source`` = its shape seed) or "mesh" (``source`` = the
    file); ``index`` among objects of its kind; ``name`` the shard's file name."""

    kind: str
    index: int
    source: int | str
    name: str


def object_specs(config: TrainingDataConfig) -> list[ObjectSpec]:
    """The dataset's objects in shard order: procedural ``object_000000`` …, then ``mesh_000`` … ."""
    specs = [ObjectSpec("procedural", i, OBJECT_SEED_STRIDE * (config.seed + 1) + i, f"object_{i:06d}.npz")
             for i in range(config.objects)]
    specs += [ObjectSpec("mesh", k, path, f"mesh_{k:03d}.npz") for k, path in enumerate(config.meshes)]
    return specs


def object_rng(config: TrainingDataConfig, spec: ObjectSpec, stream: int) -> np.random.Generator:
    """The random stream ``stream`` of one object (0: its pose, 1: its draws, 2: their damping), fixed by the seed."""
    return np.random.default_rng([config.seed, _KIND_KEY[spec.kind], spec.index, stream])


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def template_path(config: TrainingDataConfig) -> Path:

    return Path(config.template) if config.template is not None else TEMPLATE_PATH


# ---- one object -----------------------------------------------------------------------------------------

@dataclass
class Draw:
    """One sample's random parameters (E in Pa, ν, clearance in m, velocities in m/s and rad/s, damping ratio)."""

    youngs_modulus: float
    poisson_ratio: float
    drop_height: float
    linear_velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]
    damping_ratio: float = 0.05


def draw_sample(config: TrainingDataConfig, rng: np.random.Generator, damping_rng: np.random.Generator) -> Draw:
    """The next draw of an object's streams: E, ν and the drop from ``rng`` (stream 1), ζ from ``damping_rng``
    (stream 2; a fixed ratio draws nothing, so ``rng``'s draws are those of datasets made before ζ varied)."""

    lo, hi = (math.log10(x) for x in config.E_range)
    log_e = rng.uniform(lo, hi)
    nu = rng.uniform(*config.nu_range)
    pose = InitialPose.random(int(rng.integers(2**62)), drop_height=config.drop_height,
                              max_horizontal_speed=config.max_horizontal_speed,
                              max_downward_speed=config.max_downward_speed,
                              max_angular_speed=config.max_angular_speed)
    z_lo, z_hi = config.damping_ratio
    zeta = z_lo if z_lo == z_hi else float(10.0 ** damping_rng.uniform(math.log10(z_lo), math.log10(z_hi)))
    return Draw(float(10.0**log_e), float(nu), pose.drop_height, tuple(pose.linear_velocity),
                tuple(pose.angular_velocity), zeta)


def _load_object(spec: ObjectSpec):

    return make_procedural_object(int(spec.source)) if spec.kind == "procedural" else load_user_mesh(spec.source)


@dataclass
class SimulatedDraw:
    """A draw's simulation: the mesh vertices at every frame and per-frame diagnostics."""

    vertices: torch.Tensor  # (T, Nv, 3)
    max_strain: float
    converged: bool
    substeps: int


def simulate_draw(field_, vertices: torch.Tensor, cubature: torch.Tensor, cubature_weights: torch.Tensor,
                  contact: torch.Tensor, contact_areas: torch.Tensor, centre_of_mass: torch.Tensor, draw: Draw,
                  config: TrainingDataConfig) -> SimulatedDraw:
    """Drop the posed object (canonical-frame rest shape ``vertices: (Nv, 3)``) as ``draw`` says.

    The rest shape is lifted by t = (0, 0, floor + clearance − min z); the field is evaluated at X − t (its
    input frame, scale 1: the canonical frame has diagonal 1). Returns the skinned vertices at frames
    0 … frames − 1 and the largest Green strain ‖½(FᵀF − I)‖_F over cubature points and frames.
    """

    dtype = torch.float64  # in float32 Newton cannot meet the simulator's tolerance (and is no faster)
    field_ = field_.to(dtype)
    vertices, cubature, cubature_weights = vertices.to(dtype), cubature.to(dtype), cubature_weights.to(dtype)
    contact, contact_areas, centre_of_mass = contact.to(dtype), contact_areas.to(dtype), centre_of_mass.to(dtype)
    lift = config.floor_height + draw.drop_height - float(vertices[:, 2].min())
    t = torch.tensor([0.0, 0.0, lift], dtype=dtype)
    field_.set_input_frame(t, 1.0)
    material = Material(draw.youngs_modulus, draw.poisson_ratio, config.density, damping_ratio=draw.damping_ratio)
    sim = Simulator(field_, cubature + t, cubature_weights, material,
                    [Gravity(), Floor(height=config.floor_height, stiffness=AREA_CONTACT_STIFFNESS)],
                    SimConfig(dt=config.dt), length_scale=1.0, contact_points=contact + t,
                    contact_weights=contact_areas)
    state = sim.rigid_velocity_state(draw.linear_velocity, draw.angular_velocity, about=centre_of_mass + t)
    with torch.no_grad():
        states = sim.rollout(state, config.frames - 1)
        X = vertices + t
        w = field_(X)
        frames = [X] + [deform(X, w, s.z) for s in states]
        wc, dwc = field_.weights_and_gradients(sim.X)
        F = deformation_gradient(gradient_basis(sim.X, wc, dwc), torch.stack([s.z for s in states]))  # (T-1, K, 3, 3)
        green = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(3, dtype=dtype))
        strain = float(green.flatten(-2).norm(dim=-1).max())
    return SimulatedDraw(torch.stack(frames).float(), strain, all(s.converged for s in states), sim.substeps())


@dataclass
class PreparedObject:
    """An object ready to drop, shared by its draws (either truth).

    Attributes:
        mesh: the textured surface (its vertices unposed; render with ``vertices=``).
        rotation: (3, 3) the pose: posed = normalize_to_canonical(mesh.vertices @ rotationᵀ).
        posed: (Nv, 3) float32, the posed surface in the canonical frame: the rest shape.
        solid: its interior and contact samples (:func:`vid2sim.predictor.solid.sample_solid`).
        last_layer: (650,) the label, fitted with the template's hidden layers frozen.
        field: the template with that last layer (float64).
        seconds: {"object", "fit"}.
    """

    spec: ObjectSpec
    mesh: Any
    rotation: np.ndarray
    posed: torch.Tensor
    solid: Any
    last_layer: torch.Tensor
    field: Any
    seconds: dict[str, float]

    def shared_arrays(self) -> dict[str, np.ndarray]:
        """The shard's per-object arrays: the label, the seed, the pose and the volume."""
        return {"last_layer": self.last_layer.numpy().astype(np.float32),
                "object_seed": np.asarray(self.spec.source if self.spec.kind == "procedural" else -1, dtype=np.int64),
                "rotation": self.rotation.astype(np.float32),
                "volume": np.asarray(self.solid.volume, dtype=np.float32)}


def prepare_object(config: TrainingDataConfig, spec: ObjectSpec, template=None) -> PreparedObject:
    """Steps 1–4 of the module docstring: the object, its pose, its solid samples and its label.

    Args:
        template: the template :class:`~vid2sim.physics.SkinningField` (default: loaded from ``config.template``
            or the shipped file).
    """

    t0 = time.perf_counter()
    if template is None:
        template = load_template(template_path(config))
    mesh = _load_object(spec)
    rotation = random_rotation(object_rng(config, spec, 0))
    posed, _ = normalize_to_canonical(mesh.vertices.double() @ torch.from_numpy(rotation).T)
    posed = posed.float()
    solid = sample_solid(posed, mesh.faces, num_points=config.points, max_contact_points=config.contact_points,
                         seed=spec.index, name=mesh.name)
    t1 = time.perf_counter()
    last_layer = fit_last_layer(template, solid.points, config.fit_iterations, lr=config.fit_lr, seed=spec.index,
                                volume=solid.volume)
    field_ = field_from_last_layer(template, last_layer).to(torch.float64)
    return PreparedObject(spec, mesh, rotation, posed, solid, last_layer, field_,
                          {"object": t1 - t0, "fit": time.perf_counter() - t1})


def render_draw(mesh, vertices: torch.Tensor, cameras: list, supersample: int
                ) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Render a draw's surface from the front camera and the other ring cameras, on white.

    Args:
        mesh: the textured surface; vertices: (T, Nv, 3) its vertices at every frame.
        cameras: V cameras, the front one first (:meth:`FrontCamera.ring`).
    Returns:
        (front video (T, R, R, 3) uint8, the other views (V − 1, T, R, R, 3) uint8 or None when V = 1, the
        fraction of frames whose front silhouette touches the image border).
    """

    rgb, alpha = render_textured_mesh(mesh, cameras, vertices=vertices, supersample=supersample)
    video = (rgb.clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()  # (V, T, R, R, 3)
    a = alpha[0]
    border = torch.cat([a[:, 0, :], a[:, -1, :], a[:, :, 0], a[:, :, -1]], dim=1)  # (T, 4R)
    return video[0], (video[1:] if len(cameras) > 1 else None), float((border.amax(dim=1) > 0).float().mean())


def make_object_shard(config: TrainingDataConfig, spec: ObjectSpec, template=None, work_dir: Path | None = None,
                      threads: int = 1) -> tuple[dict[str, np.ndarray], dict]:
    """All samples of one object (module docstring) as the shard's arrays, and its timings.

    Args:
        config: the dataset's settings; spec: the object (:func:`object_specs`).
        template: the template :class:`~vid2sim.physics.SkinningField` (default: loaded from
            ``config.template`` or the shipped file).
        work_dir: the FEM truth's work folder of this object (:func:`vid2sim.predictor.fem_truth.make_fem_shard`).
        threads: fTetWild's threads (FEM truth).
    Returns:
        (arrays of the shard (docs/training-data.md), seconds {"object", "fit", "simulate", "render", "total", …};
        "simulate" and "render" summed over draws).
    Raises:
        vid2sim.physics.SimulationError: every retry of a draw failed (reduced truth); the FEM truth's errors
        (:func:`~vid2sim.predictor.fem_truth.make_fem_shard`).
    """
    if config.truth == "fem":

        return make_fem_shard(config, spec, template, work_dir=work_dir, threads=threads)
    return make_reduced_shard(config, spec, template)


def make_reduced_shard(config: TrainingDataConfig, spec: ObjectSpec,
                       template=None) -> tuple[dict[str, np.ndarray], dict]:
    """:func:`make_object_shard` with the reduced simulator's drops (module docstring)."""

    t_all, cpu_all = time.perf_counter(), time.process_time()
    prepared = prepare_object(config, spec, template)
    solid = prepared.solid
    t0 = time.perf_counter()
    com = solid.points.mean(0)
    idx, cub_w = sample_cubature(solid.points, config.cubature_points, volume=solid.volume, seed=spec.index)
    cubature = solid.points[idx]
    timings = {"object": prepared.seconds["object"] + time.perf_counter() - t0, "fit": prepared.seconds["fit"],
               "simulate": 0.0, "render": 0.0}

    cameras = config.camera.ring(config.views, config.resolution)
    rng, damping_rng = object_rng(config, spec, 1), object_rng(config, spec, 2)
    D, T, R = config.draws_per_object, config.frames, config.resolution
    video = np.empty((D, T, R, R, 3), dtype=np.uint8)
    ring = np.empty((D, config.views - 1, T, R, R, 3), dtype=np.uint8)
    rows: dict[str, list] = {k: [] for k in ("log10_E", "nu", "drop_height", "linear_velocity", "angular_velocity",
                                             "max_strain", "converged", "substeps", "retries", "border_frames",
                                             "damping_ratio")}
    for d in range(D):
        t0 = time.perf_counter()
        for attempt in range(config.max_retries + 1):
            draw = draw_sample(config, rng, damping_rng)
            try:
                sim = simulate_draw(prepared.field, prepared.posed, cubature, cub_w, solid.contact_points,
                                    solid.contact_areas, com, draw, config)
                break
            except SimulationError:
                if attempt == config.max_retries:
                    raise
        timings["simulate"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        video[d], others, border = render_draw(prepared.mesh, sim.vertices, cameras, config.supersample)
        if others is not None:
            ring[d] = others
        timings["render"] += time.perf_counter() - t0
        rows["log10_E"].append(math.log10(draw.youngs_modulus))
        rows["nu"].append(draw.poisson_ratio)
        rows["drop_height"].append(draw.drop_height)
        rows["linear_velocity"].append(draw.linear_velocity)
        rows["angular_velocity"].append(draw.angular_velocity)
        rows["max_strain"].append(sim.max_strain)
        rows["converged"].append(sim.converged)
        rows["substeps"].append(sim.substeps)
        rows["retries"].append(attempt)
        rows["border_frames"].append(border)
        rows["damping_ratio"].append(draw.damping_ratio)
    shared = prepared.shared_arrays()
    arrays = {
        "video": video,
        "log10_E": np.asarray(rows["log10_E"], dtype=np.float32),
        "nu": np.asarray(rows["nu"], dtype=np.float32),
        **shared,
        "drop_height": np.asarray(rows["drop_height"], dtype=np.float32),
        "linear_velocity": np.asarray(rows["linear_velocity"], dtype=np.float32),
        "angular_velocity": np.asarray(rows["angular_velocity"], dtype=np.float32),
        "max_strain": np.asarray(rows["max_strain"], dtype=np.float32),
        "converged": np.asarray(rows["converged"], dtype=bool),
        "substeps": np.asarray(rows["substeps"], dtype=np.int32),
        "retries": np.asarray(rows["retries"], dtype=np.int32),
        "border_frames": np.asarray(rows["border_frames"], dtype=np.float32),
        "damping_ratio": np.asarray(rows["damping_ratio"], dtype=np.float32),
    }
    if config.views > 1:
        arrays["ring_video"] = ring
    timings["total"] = time.perf_counter() - t_all
    timings["cpu"] = time.process_time() - cpu_all
    return arrays, timings


# ---- files ----------------------------------------------------------------------------------------------

def write_npz(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> Path:
    """Write ``arrays`` as an ``.npz`` that ``numpy.load`` reads, atomically (temp file + rename) and
    byte-reproducibly (fixed member order, timestamps and compression level)."""

    def write(tmp: str) -> None:
        with zipfile.ZipFile(tmp, "w") as zf:
            for key in arrays:
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
                info.external_attr = 0o644 << 16
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(arrays[key]), allow_pickle=False)  # 0-d stays 0-d
                zf.writestr(info, buf.getvalue(), compresslevel=6 if compress else None)

    return write_file_atomic(path, write)


def work_dir_of(out_dir: str | Path, spec: ObjectSpec) -> Path:
    """The FEM truth's work folder of one object: its tet mesh and finished draws until its shard is written."""
    return Path(out_dir) / WORK / Path(spec.name).stem


def shard_task(config_dict: dict, spec_fields: tuple, out_dir: str, threads: int | None,
               verbose: bool = False) -> dict:
    """Make and write one shard (a module-level function: the unit of work of process pools and Ray tasks).

    Args:
        verbose: print a line per finished FEM draw to stderr (a long run's log).
    Returns:
        {"name", "timings", "summary"} for ``index.json``.
    """
    if threads is not None:
        torch.set_num_threads(threads)
    config = TrainingDataConfig.from_dict(config_dict)
    spec = ObjectSpec(*spec_fields)
    work_dir = work_dir_of(out_dir, spec) if config.truth == "fem" else None
    if config.truth == "fem":

        on_draw = _print_draw if verbose else None
        arrays, timings = make_fem_shard(config, spec, work_dir=work_dir, threads=torch.get_num_threads(),
                                         on_draw=on_draw)
    else:
        arrays, timings = make_reduced_shard(config, spec)
    write_npz(Path(out_dir) / spec.name, arrays)
    if work_dir is not None:
        shutil.rmtree(work_dir, ignore_errors=True)
    return {"name": spec.name, "timings": timings, "summary": shard_summary(arrays)}


def _print_draw(name: str, d: int, row: dict[str, np.ndarray], seconds: float) -> None:
    print(f"[make-training-data] {name} draw {d}: log10 E {float(row['log10_E']):.2f}, nu {float(row['nu']):.3f}, "
          f"zeta {float(row['damping_ratio']):.3f}, {int(row['substeps'])} substeps, {seconds:.0f} s",
          file=sys.stderr, flush=True)


#: the per-sample figures ``index.json`` keeps per shard (those a shard has: the FEM's are the last three)
SUMMARY_KEYS = ("log10_E", "nu", "max_strain", "border_frames", "converged", "substeps", "retries", "damping_ratio",
                "time_change_percent", "newton_iterations")


def shard_summary(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """The small per-shard figures ``index.json`` keeps (labels and diagnostics, no video)."""
    return {k: np.asarray(arrays[k]).tolist() for k in SUMMARY_KEYS if k in arrays}


def _read_summary(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as z:
        return shard_summary({k: z[k] for k in SUMMARY_KEYS if k in z.files})


def _stats(shards: list[dict]) -> dict[str, Any]:
    if not shards:
        return {}
    present = [k for k in SUMMARY_KEYS if all(k in s["summary"] for s in shards)]
    cat = {k: np.concatenate([np.asarray(s["summary"][k], dtype=np.float64) for s in shards]) for k in present}

    def summary(x: np.ndarray) -> dict[str, float]:
        return {"min": float(x.min()), "max": float(x.max()), "mean": float(x.mean()), "std": float(x.std())}

    stats = {k: summary(cat[k]) for k in ("log10_E", "nu", "max_strain", "substeps", "damping_ratio",
                                          "time_change_percent", "newton_iterations") if k in cat}
    return {**stats, "border_frames_mean": float(cat["border_frames"].mean()),
            "samples_touching_border": float((cat["border_frames"] > 0).mean()),
            "converged_fraction": float(cat["converged"].mean()), "retries_total": int(cat["retries"].sum())}


def _run_seconds(made: list[dict], draws_per_object: int) -> dict[str, Any]:
    """This run's seconds: summed per stage over the shards it made (wall), per sample made, and the medians of
    the samples' own wall and CPU seconds (an FEM draw's simulation + rendering, without the object's share; a
    reduced shard's total / its draws)."""
    samples = sum(int(m["seconds"].get("draws_made", draws_per_object)) for m in made)
    keys = sorted({k for m in made for k, v in m["seconds"].items() if isinstance(v, float) and k != "cpu"})
    split = {k: float(sum(m["seconds"].get(k, 0.0) for m in made)) for k in keys}

    def per_sample(per_draw: str, per_shard: str) -> float | None:
        values = [t for m in made for t in m["seconds"].get(per_draw, [])]
        values += [m["seconds"][per_shard] / draws_per_object for m in made
                   if per_draw not in m["seconds"] and per_shard in m["seconds"]]
        return float(np.median(values)) if values else None

    return {"samples_made": samples, "seconds_split": split,
            "seconds_per_sample": {k: v / samples for k, v in split.items()} if samples else None,
            "median_sample_seconds": per_sample("per_draw", "total"),
            "median_sample_cpu_seconds": per_sample("per_draw_cpu", "cpu")}


# ---- the dataset ----------------------------------------------------------------------------------------

def make_training_data(config: TrainingDataConfig, out_dir: str | Path, workers: int | None = None,
                       threads: int | None = 1, ray_address: str | None = None, progress: bool = True,
                       on_shard: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write (or resume) a training dataset: one shard per object and ``index.json``.

    Resumable: shards are written atomically, so every ``.npz`` present is complete and is kept (after
    checking that ``index.json``'s config, if any, equals ``config``); only missing shards are made.
    ``index.json`` is rewritten every ``INDEX_EVERY_SECONDS`` while shards are made and at the end
    (``complete`` once all are there); shards it does not list yet are read back on resume. Deterministic: a shard
    depends only on ``config`` and its object (and the thread count of the process making it), not on how
    many workers run or in which order.

    Args:
        config: the dataset's settings.
        out_dir: the folder (created).
        workers: processes side by side (default: all local cores; 1 = in this process). With
            ``ray_address``: Ray tasks run side by side as the cluster has room, each reserving ``threads``
            CPUs.
        threads: torch threads per worker (None: torch's default).
        ray_address: ``"local"`` or a Ray cluster address (:mod:`vid2sim.runtime.ray_runner`); every node must
            see ``out_dir`` at the same path.
        progress: a tqdm bar.
        on_shard: called with each shard's name when it is written (tests, logs).
    Returns:
        the ``index.json`` content.
    Raises:
        FileExistsError: ``out_dir`` is a file or a non-empty folder that is not such a dataset.
        ValueError: ``index.json`` was written with another config.
        FileNotFoundError: a user mesh or the template file is missing.
        vid2sim.runtime.ray_runner.RayUnavailable: ``ray_address`` given but Ray is missing or unreachable.
    """
    from tqdm.auto import tqdm

    out = Path(out_dir)
    index_path = out / INDEX
    check_output_folder(out, index_path.is_file(), INDEX, "a training dataset")
    remove_temp_files(out)  # what a run killed while writing a shard or index.json left
    header = _dataset_header(config, ray_address)
    previous = _previous_index(index_path, config, header) if index_path.is_file() else {}
    out.mkdir(parents=True, exist_ok=True)
    specs = object_specs(config)
    entries, todo = _shards_present(out, specs, previous)
    workers = _worker_count(workers)
    run = _DatasetRun(config, specs, header, index_path, entries, workers, threads, ray_address, on_shard)
    cfg_dict = config.to_dict()
    calls = [(cfg_dict, (s.kind, s.index, s.source, s.name), str(out), threads, progress) for s in todo]
    run.bar = tqdm(total=len(specs), initial=len(specs) - len(todo), desc="training data", unit="object",
                   disable=not progress)
    index = run.write_index()
    try:
        if ray_address is not None:
            _make_shards_on_ray(run, todo, calls, ray_address, threads)
        elif workers == 1 or len(calls) <= 1:
            _make_shards_here(run, todo, calls, threads, progress)
        else:
            _make_shards_in_pool(run, todo, calls, workers)
        index = run.write_index()
    finally:
        run.bar.close()
    if run.errors:
        raise run.errors[0]
    return index


def _dataset_header(config: TrainingDataConfig, ray_address: str | None) -> dict[str, Any]:
    """``index.json``'s format, config and template hash, once the user meshes, Ray (when asked for) and the
    template file are checked (FileNotFoundError, RayUnavailable) before anything is written."""
    for m in config.meshes:
        if not Path(m).is_file():
            raise FileNotFoundError(f"mesh file {m} does not exist")
    if ray_address is not None:
        import_ray()  # RayUnavailable before anything is written
    tpath = template_path(config)
    if not tpath.is_file():
        raise FileNotFoundError(f"template skinning network {tpath} does not exist")
    return {"format": FORMAT, "config": config.to_dict(), "template_sha256": file_sha256(tpath)}


def _previous_index(index_path: Path, config: TrainingDataConfig, header: dict[str, Any]) -> dict[str, Any]:
    """The ``index.json`` already in the folder, checked to be the same dataset as ``header`` (or a smaller
    one of it, which grows); ValueError naming the settings that differ otherwise."""
    previous = json.loads(index_path.read_text())
    # A dataset grows: every object's shape and draws depend on (seed, its index) only, so a rerun with a
    # larger ``objects`` keeps the shards already made and adds the new ones. Shrinking is refused.
    prev_config = _normalised_config(previous.get("config", {}))
    grown = (isinstance(prev_config.get("objects"), int) and config.objects >= prev_config["objects"])
    if grown:
        prev_config["objects"] = config.objects
    differ = sorted(k for k in ("format", "config", "template_sha256")
                    if (prev_config if k == "config" else previous.get(k)) != header[k])
    if differ:
        diff = _config_diff(previous.get("config", {}), header["config"])
        raise ValueError(f"{index_path} was written with other settings ({', '.join(differ)}"
                         + (f": {diff}" if diff else "") + "); resume with the same settings or use another folder")
    return previous


def _shards_present(out: Path, specs: list[ObjectSpec], previous: dict[str, Any]
                    ) -> tuple[dict[str, dict], list[ObjectSpec]]:
    """The ``index.json`` entries of the shards already written (by file name; read back from the shard when the
    previous index does not list it yet) and the objects still to make, in order."""
    old = {s["file"]: s for s in previous.get("shards", [])}
    entries: dict[str, dict] = {}
    todo = []
    for spec in specs:
        path = out / spec.name
        if path.is_file():
            entry = old.get(spec.name) or {"file": spec.name, "kind": spec.kind, "source": spec.source,
                                            "seconds": None, "summary": _read_summary(path)}
            entries[spec.name] = entry
            shutil.rmtree(work_dir_of(out, spec), ignore_errors=True)  # left by a kill between write and clean-up
        else:
            todo.append(spec)
    return entries, todo


def _worker_count(workers: int | None) -> int:
    """``workers``, or all the cores this process may use when None; ValueError below 1."""
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    return workers


class _DatasetRun:
    """One run of :func:`make_training_data`: the shards listed so far, those this run made or failed, the
    progress bar, and ``index.json`` written from them."""

    def __init__(self, config: TrainingDataConfig, specs: list[ObjectSpec], header: dict[str, Any],
                 index_path: Path, entries: dict[str, dict], workers: int, threads: int | None,
                 ray_address: str | None, on_shard: Callable[[str], None] | None) -> None:
        self.config, self.specs, self.header, self.index_path = config, specs, header, index_path
        self.entries = entries
        self.workers, self.threads, self.ray_address, self.on_shard = workers, threads, ray_address, on_shard
        self.by_name = {s.name: s for s in specs}
        self.t_start = time.perf_counter()
        self.made: list[dict] = []
        self.failed: list[dict[str, str]] = []
        self.errors: list[BaseException] = []
        self.bar: Any = None  # the tqdm bar, set before any shard is made
        self.last_write = time.perf_counter()

    def write_index(self) -> dict[str, Any]:
        """Write ``index.json`` (atomically) from the shards listed so far; its content."""
        config, specs, made = self.config, self.specs, self.made
        shards = [self.entries[s.name] for s in specs if s.name in self.entries]
        wall = time.perf_counter() - self.t_start
        seconds = _run_seconds(made, config.draws_per_object)
        made_samples = seconds["samples_made"]
        index = {**self.header, "complete": len(shards) == len(specs), "objects": len(specs),
                 "shards_written": len(shards), "samples": len(shards) * config.draws_per_object,
                 "label_layout": {"log10_E": "()", "nu": "()", "last_layer": "(650,): skinning last layer, weights "
                                  "row-major (10, 64) then 10 biases, canonical gauge"},
                 "video_layout": f"(draws, {config.frames}, {config.resolution}, {config.resolution}, 3) uint8 RGB "
                                 "on white, the front view" + ("" if config.views == 1 else
                                 f"; ring_video (draws, {config.views - 1}, {config.frames}, {config.resolution}, "
                                 f"{config.resolution}, 3), the ring's other views at azimuth + 360°·k/{config.views}"),
                 "stats": _stats(shards),
                 "last_run": {"workers": self.workers if self.ray_address is None else None, "threads": self.threads,
                              "ray_address": self.ray_address, "shards_made": len(made), "wall_seconds": wall,
                              "samples_per_second": made_samples / wall if made_samples and wall > 0 else None,
                              **seconds, "failed": self.failed},
                 "shards": shards}
        write_json_atomic(self.index_path, index)
        return index

    def finished(self, result: dict) -> None:
        """Record a shard :func:`shard_task` wrote (``index.json`` at most every ``INDEX_EVERY_SECONDS``)."""
        spec = self.by_name[result["name"]]
        entry = {"file": spec.name, "kind": spec.kind, "source": spec.source, "seconds": result["timings"],
                 "summary": result["summary"]}
        self.entries[spec.name] = entry
        self.made.append(entry)
        if time.perf_counter() - self.last_write >= INDEX_EVERY_SECONDS:  # O(N) each: not after every shard at scale
            self.write_index()
            self.last_write = time.perf_counter()
        self.bar.update(1)
        rate = len(self.made) * self.config.draws_per_object / (time.perf_counter() - self.t_start)
        self.bar.set_postfix(samples_per_s=f"{rate:.3g}")
        if self.on_shard is not None:
            self.on_shard(spec.name)

    def failure(self, name: str, exc: BaseException) -> None:
        """Record a shard that failed (raised once all have run) and rewrite ``index.json``."""
        self.errors.append(exc)
        self.failed.append({"file": name, "error": f"{type(exc).__name__}: {exc}"})
        self.bar.write(f"[make-training-data] {name} failed: {type(exc).__name__}: {exc}")
        self.write_index()


def _make_shards_on_ray(run: _DatasetRun, todo: list[ObjectSpec], calls: list[tuple], ray_address: str,
                        threads: int | None) -> None:
    """Make the ``todo`` shards as Ray tasks of ``threads`` CPUs each (``calls``: :func:`shard_task`'s arguments)."""

    def gathered(i: int, result: Any) -> None:
        if isinstance(result, BaseException):
            run.failure(todo[i].name, result)
        else:
            run.finished(result)

    ray_map(shard_task, [(c, {}) for c in calls], ray_address, num_cpus=max(1, threads or 1), on_done=gathered)


def _make_shards_here(run: _DatasetRun, todo: list[ObjectSpec], calls: list[tuple], threads: int | None,
                      progress: bool) -> None:
    """Make the ``todo`` shards one after the other in this process, with ``threads`` torch threads (restored
    after); an object that fails does not stop the next ones."""
    if threads is not None:
        old_threads = torch.get_num_threads()
        torch.set_num_threads(threads)
    try:
        for spec, c in zip(todo, calls):
            try:
                result = shard_task(*c[:3], None, progress)
            except _shard_failures() as exc:  # the next objects still run; raised at the end
                run.failure(spec.name, exc)
            else:
                run.finished(result)
    finally:
        if threads is not None:
            torch.set_num_threads(old_threads)


def _make_shards_in_pool(run: _DatasetRun, todo: list[ObjectSpec], calls: list[tuple], workers: int) -> None:
    """Make the ``todo`` shards in a pool of ``workers`` processes, recording each as it finishes (an interrupt
    cancels those not started)."""
    with process_pool(min(workers, len(calls))) as pool:
        names = {pool.submit(shard_task, *c): spec.name for spec, c in zip(todo, calls)}
        pending = set(names)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    exc = fut.exception()
                    if exc is not None:
                        run.failure(names[fut], exc)
                    else:
                        run.finished(fut.result())
        except KeyboardInterrupt:
            for fut in pending:
                fut.cancel()
            raise


def _shard_failures() -> tuple[type[BaseException], ...]:
    """What makes one object fail without stopping the others: a simulation that failed every retry, fTetWild,
    a surface that is not watertight or does not fit its tets (ValueError)."""

    return (SimulationError, FEMSolverError, TetrahedralizationError, ValueError)


def _normalised_config(values: dict[str, Any]) -> dict[str, Any]:
    """An ``index.json`` config as this version writes it (:meth:`TrainingDataConfig.from_dict`: older ones are the
    reduced truth's), or the dict as it is when it is no valid config (then it differs, and is named)."""
    try:
        return TrainingDataConfig.from_dict(dict(values)).to_dict()
    except (ValueError, TypeError):
        return dict(values)


def _config_diff(old: dict, new: dict) -> dict[str, Any]:
    return {k: (old.get(k), new.get(k)) for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)}
