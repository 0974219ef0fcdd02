"""Stage I training samples whose drops are simulated by the FEM ground truth (``make-training-data --truth fem``).

The reduced-model samples of :mod:`vid2sim.predictor.data` teach the predictor our own simulator's motion, which
is not the truth it is judged on (docs/predictor.md: 0.31 decade off on the FEM suite). Here the drop of every
sample is the benchmark's truth, with the suite's settings (:func:`vid2sim.synthetic.scenes.make_benchmark`):

- the posed object's surface tetrahedralized by fTetWild at the suite's size (edge 0.08 of the diagonal,
  envelope 5e-3) and simulated with quadratic tets (:class:`~vid2sim.synthetic.fem.FEMConfig`
  ``element_order=2``);
- Neo-Hookean, Kelvin–Voigt damping, gravity, the floor as a contact pressure (the reduced model's law);
- BDF2 with substeps doubled until the trajectory moves by at most 1 % of the size under 2× refinement
  (:func:`~vid2sim.synthetic.fem.simulate_fem_converged`, the suite's ``time_tolerance``);
- the textured surface carried by the tets (:mod:`vid2sim.synthetic.embedding`) and rendered on white from the
  front camera and ``views − 1`` more cameras of its ring.

The object, its pose, its label (the skinning field's last layer) and the random draws are those of the reduced
truth (:func:`vid2sim.predictor.data.prepare_object`, :func:`vid2sim.predictor.data.draw_sample`).

Determinism and resuming. fTetWild draws from ``std::random_device`` (two runs on one surface give different
meshes, even with one thread), so the tet mesh is the one thing a seed does not fix. It is made once per object
and written to the object's work folder before any FEM runs; every draw after it is deterministic. Each finished
draw is written there too (``draw_000.npz`` …), so an interrupted object resumes at its next draw with the same
tet mesh: a run killed at any moment and run again gives the samples an uninterrupted run with that mesh gives,
byte for byte. The shard stores the tet mesh (``tet_vertices``, ``tets``), and :func:`make_fem_shard` given it
(``tet_mesh=``) remakes the shard byte for byte.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch

from vid2sim.meshing.tetra import TetMesh, tetrahedralize
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.runtime.errors import ConfigError
from vid2sim.synthetic.embedding import apply_embedding, embed_points
from vid2sim.synthetic.fem import FEMConfig, FEMSolverError, InitialPose, TetFEM, simulate_fem_converged
from vid2sim.synthetic.scenes import BENCHMARK_ELEMENT_ORDER, BENCHMARK_QUADRATIC_TETS, SyntheticSceneConfig

if TYPE_CHECKING:
    from vid2sim.meshing.tetra import TetMesh
    from vid2sim.predictor.data import Draw, ObjectSpec, TrainingDataConfig
    from vid2sim.synthetic.fem import FEMConfig, FEMResult, InitialPose

TET_MESH_FILE = "tets.npz"


def draw_file(d: int) -> str:
    """The work-folder file of draw ``d``."""
    return f"draw_{d:03d}.npz"


@dataclass(frozen=True)
class FEMTruth:
    """FEM settings of ``--truth fem`` samples (defaults: the benchmark suite's, :func:`make_benchmark`).

    Attributes:
        element_order: 2 — quadratic tets, converged in space (< 2 % in the lowest frequencies at this size);
            1 — linear tets (3–20 % too stiff; 10–20× faster).
        tet_edge_length: fTetWild's target edge length relative to the bounding-box diagonal.
        tet_envelope: fTetWild's envelope relative to the bounding-box diagonal.
        time_tolerance: the trajectory's largest change under 2× time refinement, percent of the size (mean
            over frames); the substeps are doubled until it holds.
        max_substeps: substeps per frame beyond which a draw fails rather than refine further.
    """

    element_order: int = BENCHMARK_ELEMENT_ORDER
    tet_edge_length: float = BENCHMARK_QUADRATIC_TETS["tet_edge_length"]
    tet_envelope: float = BENCHMARK_QUADRATIC_TETS["tet_envelope"]
    time_tolerance: float = SyntheticSceneConfig.__dataclass_fields__["time_tolerance"].default
    max_substeps: int = 256

    def __post_init__(self) -> None:
        if self.element_order not in (1, 2) or isinstance(self.element_order, bool):
            raise ConfigError(f"FEMTruth.element_order must be 1 or 2, got {self.element_order!r}")
        for name in ("tet_edge_length", "tet_envelope", "time_tolerance"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"FEMTruth.{name} must be a positive number, got {v!r}")
        if self.tet_edge_length > 1:
            raise ConfigError(
                f"FEMTruth.tet_edge_length must be at most 1 (of the diagonal), got {self.tet_edge_length}"
            )
        if isinstance(self.max_substeps, bool) or not isinstance(self.max_substeps, int) or self.max_substeps < 2:
            raise ConfigError(f"FEMTruth.max_substeps must be an integer >= 2, got {self.max_substeps!r}")


# ---- the tet mesh ---------------------------------------------------------------------------------------

def object_tet_mesh(vertices: torch.Tensor, faces: torch.Tensor, fem: FEMTruth, work_dir: Path | None,
                    name: str, threads: int = 1) -> tuple["TetMesh", bool]:
    """The posed object's tet mesh: read from ``work_dir`` when an earlier run made it, else made by fTetWild
    and written there (atomically) before anything uses it.

    Args:
        vertices: (Nv, 3) the posed surface (canonical frame); faces: (Nf, 3).
        fem: the mesh size; work_dir: the object's work folder (None: not kept).
        name: the object's name for messages; threads: fTetWild's threads.
    Returns:
        (the mesh, whether it was read back).
    Raises:
        vid2sim.meshing.tetra.TetrahedralizationError: fTetWild failed.
    """

    path = None if work_dir is None else work_dir / TET_MESH_FILE
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return TetMesh(torch.from_numpy(z["vertices"]), torch.from_numpy(z["tets"]), name=name), True
    tet = tetrahedralize(vertices, faces, edge_length_fac=fem.tet_edge_length, epsilon=fem.tet_envelope,
                         num_threads=threads, name=name)
    if path is not None:
        from vid2sim.predictor.data import write_npz

        work_dir.mkdir(parents=True, exist_ok=True)
        write_npz(path, {"vertices": tet.vertices.numpy(), "tets": tet.tets.numpy()}, compress=False)
    return tet, False


# ---- one draw -------------------------------------------------------------------------------------------

@dataclass
class FEMDraw:
    """A draw's FEM drop: the surface at every frame and the truth's diagnostics.

    Attributes:
        surface: (T, Nv, 3) float32 surface-mesh vertices, frame 0 the initial pose.
        max_strain: largest Green strain ‖½(FᵀF − I)‖_F over quadrature points and frames.
        substeps: substeps per frame of the kept (finer) run.
        time_change_percent: mean change of the trajectory from the coarser run, percent of the size.
        newton_iterations: Newton iterations of the kept run.
        min_det: smallest det F over quadrature points and frames.
        max_penetration: deepest floor penetration (m).
        seconds: wall time of every FEM run of the convergence check.
    """

    surface: torch.Tensor
    max_strain: float
    substeps: int
    time_change_percent: float
    newton_iterations: int
    min_det: float
    max_penetration: float
    seconds: float


def fem_config_of(draw: "Draw", config: "TrainingDataConfig") -> "FEMConfig":
    """The FEM settings of one draw: its material and damping, the dataset's frame time and floor, the
    reduced model's contact law (:data:`~vid2sim.physics.external.AREA_CONTACT_STIFFNESS`)."""

    return FEMConfig(youngs_modulus=draw.youngs_modulus, poisson_ratio=draw.poisson_ratio, density=config.density,
                     dt=config.dt, damping_ratio=draw.damping_ratio, floor_height=config.floor_height,
                     floor_stiffness=AREA_CONTACT_STIFFNESS, element_order=config.fem.element_order)


def initial_pose_of(draw: "Draw") -> "InitialPose":
    """The draw's drop as an FEM :class:`~vid2sim.synthetic.fem.InitialPose`. No rotation: the rest mesh is
    already the posed object, as Stage II sees it at frame 0."""

    return InitialPose(drop_height=draw.drop_height, linear_velocity=draw.linear_velocity,
                       angular_velocity=draw.angular_velocity)


def max_green_strain(result: "FEMResult") -> float:
    """Largest ‖½(FᵀF − I)‖_F over the FEM's quadrature points and frames of ``result``."""

    model = TetFEM(result.rest_vertices[: int(result.tets.max()) + 1], result.tets, result.config)
    worst = 0.0
    for x in result.trajectory.numpy():
        F = model.deformation_gradients(x)  # (Nq, 3, 3)
        green = 0.5 * (np.swapaxes(F, 1, 2) @ F - np.eye(3))
        worst = max(worst, float(np.linalg.norm(green.reshape(-1, 9), axis=1).max()))
    return worst


def simulate_fem_draw(tet: "TetMesh", tet_index: torch.Tensor, bary: torch.Tensor, draw: "Draw",
                      config: "TrainingDataConfig") -> FEMDraw:
    """Drop the posed object's tet mesh as ``draw`` says and carry its surface along.

    Args:
        tet: the posed object's tet mesh (rest = frame 0's shape before the lift).
        tet_index: (Nv,) and bary: (Nv, 4), the surface vertices' embedding in ``tet``
            (:func:`vid2sim.synthetic.embedding.embed_points`).
        draw: material, damping and drop; config: frames, frame time, floor, :attr:`FEMTruth`.
    Raises:
        vid2sim.synthetic.fem.FEMSolverError: a step failed or the tolerance needs more than ``max_substeps``.
    """

    t0 = time.perf_counter()
    result = simulate_fem_converged(tet.vertices, tet.tets, fem_config_of(draw, config), initial_pose_of(draw),
                                    frames=config.frames, tolerance=config.fem.time_tolerance,
                                    max_substeps=config.fem.max_substeps, progress=False, workers=1)
    seconds = time.perf_counter() - t0
    surface = apply_embedding(result.trajectory, tet_index, bary, result.embedding_elements).float()
    conv = result.time_convergence
    return FEMDraw(surface=surface, max_strain=max_green_strain(result), substeps=int(result.config.substeps),
                   time_change_percent=float(conv["mean_percent"]),
                   newton_iterations=int(result.newton_iterations.sum()), min_det=float(result.min_det.min()),
                   max_penetration=float(result.max_penetration), seconds=seconds)


# ---- one object -----------------------------------------------------------------------------------------

#: per-draw arrays of an FEM shard, beside the shared ones (docs/training-data.md)
DRAW_KEYS = ("video", "ring_video", "surface", "log10_E", "nu", "damping_ratio", "drop_height", "linear_velocity",
             "angular_velocity", "max_strain", "converged", "substeps", "time_change_percent", "newton_iterations",
             "min_det_F", "max_penetration", "retries", "border_frames")


def _one_draw(config: "TrainingDataConfig", spec: "ObjectSpec", prepared, tet: "TetMesh", embedding, cameras,
              rng: np.random.Generator, damping_rng: np.random.Generator) -> tuple[dict[str, np.ndarray], dict]:
    """Draw, simulate (redrawing after a failed FEM, at most ``max_retries`` times) and render one sample.

    Returns:
        (the draw's arrays, keyed as :data:`DRAW_KEYS`; its seconds {"simulate", "render", "fem_runs", "cpu"}:
        wall time of the stages and of the FEM runs, and this process's CPU time for the whole draw).
    """
    from vid2sim.predictor.data import draw_sample, render_draw

    t0, cpu0 = time.perf_counter(), time.process_time()
    for attempt in range(config.max_retries + 1):
        draw = draw_sample(config, rng, damping_rng)
        try:
            sim = simulate_fem_draw(tet, *embedding, draw, config)
            break
        except FEMSolverError as exc:
            if attempt == config.max_retries:
                raise FEMSolverError(
                    f"{spec.name}: {config.max_retries + 1} draws in a row failed; last: {exc}"
                ) from exc
    t1 = time.perf_counter()
    video, ring, border = render_draw(prepared.mesh, sim.surface, cameras, config.supersample)
    arrays = {
        "video": video,
        "surface": sim.surface.numpy().astype(np.float32),
        "log10_E": np.float32(math.log10(draw.youngs_modulus)),
        "nu": np.float32(draw.poisson_ratio),
        "damping_ratio": np.float32(draw.damping_ratio),
        "drop_height": np.float32(draw.drop_height),
        "linear_velocity": np.asarray(draw.linear_velocity, dtype=np.float32),
        "angular_velocity": np.asarray(draw.angular_velocity, dtype=np.float32),
        "max_strain": np.float32(sim.max_strain),
        "converged": np.bool_(sim.time_change_percent <= config.fem.time_tolerance),
        "substeps": np.int32(sim.substeps),
        "time_change_percent": np.float32(sim.time_change_percent),
        "newton_iterations": np.int32(sim.newton_iterations),
        "min_det_F": np.float32(sim.min_det),
        "max_penetration": np.float32(sim.max_penetration),
        "retries": np.int32(attempt),
        "border_frames": np.float32(border),
    }
    if ring is not None:
        arrays["ring_video"] = ring
    return arrays, {"simulate": t1 - t0, "render": time.perf_counter() - t1, "fem_runs": sim.seconds,
                    "cpu": time.process_time() - cpu0}


def embed_surface(posed: torch.Tensor, tet: "TetMesh",
                  config: "TrainingDataConfig") -> tuple[torch.Tensor, torch.Tensor]:
    """The object's surface vertices (V, 3) in its tet mesh: (V,) tet indices and (V, 4) barycentric weights
    (:func:`~vid2sim.synthetic.embedding.embed_points`).

    fTetWild keeps the tets' boundary within its envelope of the surface, but a surface vertex can lie a hair farther
    from the tets (0.01013 of the diagonal against an envelope of 0.01 once, an irreproducible fTetWild run): the
    embedding allows twice the envelope, and never less than its own default of 1 %."""
    posed = posed.double()
    diagonal = float((posed.max(0).values - posed.min(0).values).norm())
    return embed_points(posed, tet.vertices, tet.tets, max_distance=max(0.01, 2 * config.fem.tet_envelope) * diagonal)


def make_fem_shard(config: "TrainingDataConfig", spec: "ObjectSpec", template=None, work_dir: Path | None = None,
                   tet_mesh: "TetMesh | None" = None, threads: int = 1,
                   on_draw: Callable[[str, int, dict, float], None] | None = None,
                   ) -> tuple[dict[str, np.ndarray], dict]:
    """All samples of one object with FEM drops (module docstring) as the shard's arrays, and its timings.

    Args:
        config: the dataset's settings (``truth == "fem"``); spec: the object.
        template: the template skinning network (default: the config's).
        work_dir: the object's work folder: its tet mesh and finished draws are kept there and reused (None:
            nothing is kept).
        tet_mesh: the tet mesh to use instead of fTetWild's (e.g. a shard's ``tet_vertices`` / ``tets``): the
            shard is then remade byte for byte.
        threads: fTetWild's threads.
        on_draw: called as (shard name, draw, its arrays, its seconds) after each draw made here.
    Returns:
        (arrays (docs/training-data.md), seconds {"object", "fit", "tetrahedralize", "simulate", "render",
        "total", "draws_made", "draws_resumed", "per_draw", "per_draw_cpu"}: "per_draw" lists the wall seconds
        (simulation + rendering) of the draws made in this call, "per_draw_cpu" their CPU seconds).
    Raises:
        vid2sim.meshing.tetra.TetrahedralizationError, vid2sim.synthetic.fem.FEMSolverError, ValueError (the
        surface does not fit its tet mesh).
    """
    from vid2sim.predictor.data import draw_sample, object_rng, prepare_object, write_npz

    if config.truth != "fem" or config.fem is None:
        raise ValueError(f"make_fem_shard needs a config with truth 'fem', got {config.truth!r}")
    t_all = time.perf_counter()
    prepared = prepare_object(config, spec, template)
    timings: dict[str, Any] = {"object": prepared.seconds["object"], "fit": prepared.seconds["fit"]}
    t0 = time.perf_counter()
    if tet_mesh is not None:
        tet = tet_mesh
    else:
        tet, _ = object_tet_mesh(prepared.posed, prepared.mesh.faces, config.fem, work_dir, prepared.mesh.name,
                                 threads)
    try:
        embedding = embed_surface(prepared.posed, tet, config)
    except ValueError as exc:
        raise ValueError(f"{spec.name}: the surface of {prepared.mesh.name} does not fit its tet mesh: {exc}") from None
    timings["tetrahedralize"] = time.perf_counter() - t0

    cameras = config.camera.ring(config.views, config.resolution)
    rng, damping_rng = object_rng(config, spec, 1), object_rng(config, spec, 2)
    rows: list[dict[str, np.ndarray]] = []
    timings.update(simulate=0.0, render=0.0, draws_made=0, draws_resumed=0, per_draw=[], per_draw_cpu=[])
    for d in range(config.draws_per_object):
        path = None if work_dir is None else work_dir / draw_file(d)
        if path is not None and path.is_file():
            with np.load(path, allow_pickle=False) as z:
                row = {k: z[k] for k in z.files}
            for _ in range(int(row["retries"]) + 1):  # advance the streams past this draw's attempts
                draw_sample(config, rng, damping_rng)
            timings["draws_resumed"] += 1
        else:
            row, seconds = _one_draw(config, spec, prepared, tet, embedding, cameras, rng, damping_rng)
            if path is not None:
                work_dir.mkdir(parents=True, exist_ok=True)
                write_npz(path, row)
            timings["simulate"] += seconds["simulate"]
            timings["render"] += seconds["render"]
            timings["per_draw"].append(seconds["simulate"] + seconds["render"])
            timings["per_draw_cpu"].append(seconds["cpu"])
            timings["draws_made"] += 1
            if on_draw is not None:
                on_draw(spec.name, d, row, seconds["simulate"] + seconds["render"])
        rows.append(row)
    arrays = {k: np.stack([r[k] for r in rows]) for k in DRAW_KEYS if k in rows[0]}
    arrays.update(prepared.shared_arrays())
    arrays["tet_vertices"] = tet.vertices.numpy().astype(np.float64)
    arrays["tets"] = tet.tets.numpy().astype(np.int32)
    timings["total"] = time.perf_counter() - t_all
    return arrays, timings

