"""Synthetic scenes: an object dropped on the floor, simulated by FEM and rendered from a camera ring.

The paper's benchmark (docs/architecture.md, "The paper's numbers"): objects dropped onto a floor, FEM ground truth, 12
views at 448 × 448,
24 frames (16 observed + 8 for future prediction). Google Scanned Objects and Blender are not available
here, so vid2sim makes its own:

1. the object — a seeded procedural union of primitives with a procedural texture
   (:func:`vid2sim.synthetic.shapes.make_procedural_object`) or a user mesh
   (:func:`vid2sim.synthetic.meshes.load_user_mesh`), in the canonical frame (half bounding-box diagonal 0.5);
2. its tetrahedralization (fTetWild, :func:`vid2sim.meshing.tetra.tetrahedralize`);
3. the FEM drop (:func:`vid2sim.synthetic.fem.simulate_fem`): random rotation, drop height and rigid velocity
   from the seed, Neo-Hookean with the given E, ν, density, the floor of docs/architecture.md;
4. the textured surface carried by the tets (:mod:`vid2sim.synthetic.embedding`) and rendered at every frame
   from every camera (:func:`vid2sim.synthetic.mesh_render.render_textured_mesh`), RGBA on white;
5. one scene folder, complete or absent (staged next to the target, then renamed): the scene written by
   :func:`vid2sim.scene.writing.write_scene` with the ground truth (E, ν, density, material, seed, initial
   pose, FEM statistics) in ``scene.json``'s metadata and the tet trajectory as the ``tet_trajectory``
   extra, plus ``fem_result.npz`` (:meth:`vid2sim.synthetic.fem.FEMResult.save`: rest mesh, positions and
   velocities at every frame, energies, solver statistics) and ``synthetic.json`` (this module's
   :class:`SyntheticSceneConfig`).

fTetWild draws random numbers from ``std::random_device``, so two runs of it on the same surface give
different tet meshes (and so slightly different FEM trajectories). Everything after meshing is
deterministic: ``SyntheticSceneConfig.tet_mesh`` reuses the tet mesh of an earlier scene (its
``fem_result.npz``) and then reproduces that scene bit for bit (same settings, same machine type).

:func:`make_benchmark` writes a deterministic suite of such scenes with E log-uniform in [1e4, 1e6] and
ν uniform in [0.2, 0.5] (the ranges of the paper's training data), resumable scene by scene; its FEM uses
quadratic tets by default (a single scene's default is linear).
"""

from __future__ import annotations

import json
import math
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from vid2sim.meshing.tetra import TetMesh, TetrahedralizationError, clean_tet_mesh, tetrahedralize
from vid2sim.physics.damping import DEFAULT_DAMPING_RATIO
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.materials import ELASTIC_MODELS, lame_parameters
from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.files import (
    check_output_folder,
    jsonable,
    remove_temp_files,
    write_folder_atomic,
    write_json_atomic,
)
from vid2sim.runtime.ray_runner import check_ray, ray_map
from vid2sim.scene.folder import Scene, SceneConfig
from vid2sim.scene.writing import write_scene
from vid2sim.splats.cameras import camera_ring
from vid2sim.synthetic.embedding import apply_embedding, embed_points
from vid2sim.synthetic.fem import FEMConfig, FEMResult, InitialPose, simulate_fem_converged
from vid2sim.synthetic.independent import (
    NewtonConfig,
    NewtonResult,
    import_newton,
    newton_metadata,
    simulate_newton_converged,
)
from vid2sim.synthetic.mesh_render import render_textured_mesh
from vid2sim.synthetic.meshes import TexturedMesh, load_user_mesh
from vid2sim.synthetic.shapes import make_procedural_object

if TYPE_CHECKING:
    from vid2sim.meshing.tetra import TetMesh
    from vid2sim.synthetic.fem import FEMConfig, InitialPose
    from vid2sim.synthetic.independent import NewtonConfig

#: the engines a scene's ground truth can come from (:attr:`SyntheticSceneConfig.truth`)
TRUTHS = ("fem", "newton")
MAX_RESOLUTION = 4096  # the largest image side a synthetic scene renders
MAX_IMAGE_BYTES = 8 * 2**30  # rendered images of one scene in memory (checked before the FEM runs)

PRESETS: dict[str, dict[str, Any]] = {
    # 12 observed views (the paper's benchmark) + 2 held-out novel views
    "full": {"views": 14, "held_out_views": 2, "resolution": 448, "frames": 24, "observed_frames": 16},
    # a coarser tet mesh (about 3 000 tets instead of about 13 000 for a 3 000-face surface) for CPUs
    "small": {
        "views": 6,
        "held_out_views": 2,
        "resolution": 128,
        "frames": 24,
        "observed_frames": 16,
        "tet_edge_length": 0.08,
        "tet_envelope": 5e-3,
    },
}

BENCHMARK_E_RANGE = (1e4, 1e6)
BENCHMARK_NU_RANGE = (0.2, 0.5)
#: a suite's default FEM tets: quadratic, converged in space (see :func:`make_benchmark`)
BENCHMARK_ELEMENT_ORDER = 2
#: the size of a suite's quadratic tets at every preset (the small preset's). Their lowest frequencies lie
#: 0.8–1.7 % above those of quadratic tets twice as fine, against 2.2–5.3 % for the full preset's finer linear
#: tets (docs/benchmarks.md, "The truth's mesh"); quadratic tets of the full preset's size would take hours a scene.
BENCHMARK_QUADRATIC_TETS: dict[str, float] = {"tet_edge_length": 0.08, "tet_envelope": 5e-3}


@dataclass
class SyntheticSceneConfig:
    """Settings of one synthetic scene (defaults: the paper's benchmark, :data:`PRESETS` ``"full"``).

    Attributes:
        seed: seeds the procedural shape and texture, and the initial pose.
        mesh: a user mesh file (OBJ/GLB/GLTF/PLY) instead of a procedural shape, or None.
        youngs_modulus, poisson_ratio, density: the material (Pa, −, kg/m³).
        material: elastic model of the FEM ground truth ('neo_hookean', the paper's, or 'stvk').
        drop_height: clearance (m) between the object's lowest point and the floor at frame 0, or None
            for a random height in [0.05, 0.3] m from the seed.
        max_horizontal_speed, max_downward_speed, max_angular_speed: bounds of the random initial rigid
            velocity (m/s, m/s, rad/s).
        views, resolution: a ring of ``views`` cameras rendering ``resolution`` × ``resolution`` images.
        held_out_views: how many ring cameras are held out of the reconstruction (novel views for
            evaluation), spread evenly: indices ⌊(i + ½)·views / n⌋ (:attr:`held_out_indices`).
        frames, observed_frames: T frames, the first ``observed_frames`` observed, the rest held out.
        dt: seconds between frames.
        damping_ratio: ζ of the Kelvin–Voigt material damping (:mod:`vid2sim.physics.damping`).
        substeps: the FEM's first substep count per frame, or None for half the automatic count of the
            material (:func:`vid2sim.physics.integrators.auto_substeps`); the FEM then doubles it until the
            trajectory is converged in time (:func:`vid2sim.synthetic.fem.simulate_fem_converged`).
        time_tolerance: the FEM's convergence tolerance: largest change of the trajectory under 2× time
            refinement, percent of the object's size (mean over frames).
        floor_height, floor_stiffness: the floor plane z = h and its penalty stiffness κ per unit surface
            area (Pa per metre of penetration; :class:`vid2sim.synthetic.fem.FEMConfig`).
        element_order: the FEM's tets: 1 linear (default; 3–20 % too stiff in the lowest frequencies at the
            small preset's mesh) or 2 quadratic (converged in space to < 1 %, the FEM 19–26× slower on small scenes;
            :class:`vid2sim.synthetic.fem.FEMConfig`). With ``truth="newton"`` (linear tets only): 1 simulates the
            tets as they are, 2 the eight linear tets per tet on the quadratic tets' nodes (twice as fine).
        truth: the engine of the ground truth: 'fem' (ours, :mod:`vid2sim.synthetic.fem`) or 'newton' (NVIDIA
            Newton's VBD solver, another energy, contact and damping: :mod:`vid2sim.synthetic.independent`).
        friction: the floor's Coulomb friction coefficient in the 'newton' truth (ours is frictionless; the 'fem'
            truth ignores it).
        tet_edge_length: fTetWild's target edge length relative to the bounding-box diagonal.
        tet_envelope: fTetWild's envelope (largest distance of the tet boundary from the surface) relative
            to the bounding-box diagonal; a wider envelope lets it coarsen the surface (fewer tets).
        tet_mesh: an earlier scene's ``fem_result.npz`` (or any ``.npz`` with ``rest_vertices`` or
            ``vertices`` (Nv, 3) and ``tets`` (Nt, 4)) whose rest tet mesh is used instead of running
            fTetWild; the object's surface must lie in it (same seed / mesh file).
        camera_radius, camera_elevation_deg, camera_fov_deg, camera_target: the camera ring.
        supersample: anti-aliasing samples per pixel side of the mesh renderer.
        layout: scene-folder layout ('rgba', 'rgb+mask' or 'video').
    """

    seed: int = 0
    mesh: str | None = None
    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    material: str = "neo_hookean"
    drop_height: float | None = None
    max_horizontal_speed: float = 0.2
    max_downward_speed: float = 1.0
    max_angular_speed: float = 2.0
    views: int = 12
    held_out_views: int = 0
    resolution: int = 448
    frames: int = 24
    observed_frames: int = 16
    dt: float = 0.05
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    substeps: int | None = None
    time_tolerance: float = 1.0
    element_order: int = 1
    truth: str = "fem"
    friction: float = 0.5
    floor_height: float = -0.7
    floor_stiffness: float = AREA_CONTACT_STIFFNESS
    tet_edge_length: float = 0.06
    tet_envelope: float = 1e-3
    tet_mesh: str | None = None
    camera_radius: float = 2.4
    camera_elevation_deg: float = 20.0
    camera_fov_deg: float = 40.0
    camera_target: tuple[float, float, float] = (0.0, 0.0, -0.4)
    supersample: int = 2
    layout: str = "rgba"

    def __post_init__(self) -> None:

        def bad(name: str, expected: str) -> ConfigError:
            return ConfigError(f"SyntheticSceneConfig.{name} must be {expected}, got {getattr(self, name)!r}")

        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise bad("seed", "an integer >= 0")
        if self.element_order not in (1, 2) or isinstance(self.element_order, bool):
            raise bad("element_order", "1 (linear tets) or 2 (quadratic tets)")
        for name in ("mesh", "tet_mesh"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, (str, Path)):
                raise bad(name, "a file path or None")
            setattr(self, name, None if value is None else str(value))
        for name in ("youngs_modulus", "poisson_ratio", "density", "max_horizontal_speed", "max_downward_speed",
                     "max_angular_speed", "dt", "floor_height", "floor_stiffness", "tet_edge_length",
                     "tet_envelope", "camera_radius", "camera_elevation_deg", "camera_fov_deg", "damping_ratio",
                     "time_tolerance", "friction"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise bad(name, "a finite number")
        try:
            lame_parameters(self.youngs_modulus, self.poisson_ratio)
        except ValueError as exc:
            raise ConfigError(f"SyntheticSceneConfig: {exc}") from None
        for name in ("density", "dt", "floor_stiffness", "tet_edge_length", "tet_envelope", "camera_radius",
                     "time_tolerance"):
            if not getattr(self, name) > 0:
                raise bad(name, "positive")
        if self.truth not in TRUTHS:
            raise bad("truth", f"one of {list(TRUTHS)}")
        for name in ("max_horizontal_speed", "max_downward_speed", "max_angular_speed", "damping_ratio", "friction"):
            if getattr(self, name) < 0:
                raise bad(name, ">= 0")
        if not 0 < self.camera_fov_deg < 180:
            raise bad("camera_fov_deg", "in (0, 180) degrees")
        if self.material not in ELASTIC_MODELS:
            raise ConfigError(
                f"SyntheticSceneConfig.material must be one of {sorted(ELASTIC_MODELS)} (the FEM ground truth is "
                f"elastic; plasticine and sand are not simulated by it), got {self.material!r}")
        if self.drop_height is not None and not (isinstance(self.drop_height, (int, float))
                                                 and math.isfinite(self.drop_height) and self.drop_height >= 0):
            raise bad("drop_height", "a finite number >= 0 or None")
        for name, lo in (("views", 1), ("resolution", 8), ("frames", 2), ("observed_frames", 1), ("substeps", 1),
                         ("supersample", 1)):
            value = getattr(self, name)
            if name == "substeps" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < lo:
                raise bad(name, f"an integer >= {lo}")
        if isinstance(self.held_out_views, bool) or not isinstance(self.held_out_views, int) or not (
                0 <= self.held_out_views < self.views):
            raise bad("held_out_views", f"an integer in [0, views={self.views}) (at least one view stays observed)")
        if self.resolution > MAX_RESOLUTION:
            raise bad("resolution", f"at most {MAX_RESOLUTION} pixels (the image side)")
        need = self.image_bytes()
        if need > MAX_IMAGE_BYTES:
            raise ConfigError(f"SyntheticSceneConfig.resolution {self.resolution} with {self.views} views x "
                             f"{self.frames} frames needs {need / 2**30:.1f} GiB of images; at most "
                             f"{MAX_IMAGE_BYTES / 2**30:.0f} GiB (lower the resolution, views or frames)")
        if self.observed_frames > self.frames:
            raise ConfigError(f"SyntheticSceneConfig.observed_frames ({self.observed_frames}) must not exceed "
                             f"frames ({self.frames})")
        target = tuple(float(c) for c in self.camera_target)
        if len(target) != 3 or not all(math.isfinite(c) for c in target):
            raise bad("camera_target", "three finite numbers")
        self.camera_target = target  # type: ignore[assignment]
        if self.layout not in ("rgba", "rgb+mask", "video"):
            raise bad("layout", "'rgba', 'rgb+mask' or 'video'")

    def image_bytes(self) -> int:
        """Bytes of the rendered scene in memory (float32 RGB + alpha, views x frames x resolution²)."""
        return self.views * self.frames * self.resolution ** 2 * 4 * 4

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> "SyntheticSceneConfig":
        """The named preset (``"full"``: 12 + 2 held-out views, 448², 24 frames; ``"small"``: 4 + 2 held-out
        views, 128², 24 frames)
        with ``overrides`` applied (None values are ignored)."""
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
        return cls._from_fields({**PRESETS[name], **{k: v for k, v in overrides.items() if v is not None}},
                                "SyntheticSceneConfig")

    @property
    def held_out_indices(self) -> list[int]:
        """The held-out ring cameras: ⌊(i + ½)·views / n⌋ for i < n = ``held_out_views``."""
        n = self.held_out_views
        return [int((i + 0.5) * self.views / n) for i in range(n)]

    def fem_config(self, **overrides: Any) -> "FEMConfig":
        """The FEM settings of this scene (material, damping, frame time, floor), with ``overrides``; the
        substeps are those of :attr:`substeps` when set (the converged run chooses its own)."""

        fields_ = {"youngs_modulus": self.youngs_modulus, "poisson_ratio": self.poisson_ratio,
                   "density": self.density, "material": self.material, "dt": self.dt,
                   "damping_ratio": self.damping_ratio, "floor_height": self.floor_height,
                   "floor_stiffness": self.floor_stiffness, "element_order": self.element_order}
        if self.substeps is not None:
            fields_["substeps"] = self.substeps
        return FEMConfig(**{**fields_, **overrides})

    def newton_config(self) -> "NewtonConfig":
        """The independent engine's settings for this scene (material, damping, frame time, floor and its stiffness,
        friction; ``element_order`` 2 → ``subdivide``); its substeps are those of :attr:`substeps` when set."""

        fields_ = {"youngs_modulus": self.youngs_modulus, "poisson_ratio": self.poisson_ratio,
                   "density": self.density, "damping_ratio": self.damping_ratio, "dt": self.dt,
                   "floor_height": self.floor_height, "floor_stiffness": self.floor_stiffness,
                   "friction": self.friction, "subdivide": self.element_order == 2}
        if self.substeps is not None:
            fields_["substeps"] = self.substeps
        return NewtonConfig(**fields_)

    def initial_pose(self) -> "InitialPose":
        """The seeded random drop pose (orientation, height above the floor, rigid velocity)."""

        height = (0.05, 0.3) if self.drop_height is None else (self.drop_height, self.drop_height)
        return InitialPose.random(self.seed, drop_height=height, max_horizontal_speed=self.max_horizontal_speed,
                                  max_downward_speed=self.max_downward_speed,
                                  max_angular_speed=self.max_angular_speed)

    @classmethod
    def from_json(cls, path: str | Path) -> "SyntheticSceneConfig":
        """Read a ``synthetic.json`` written by :func:`make_scene`."""
        path = Path(path)
        try:
            values = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(values, dict):
            raise ValueError(f"{path}: expected a JSON object of SyntheticSceneConfig fields")
        return cls._from_fields(values, str(path))

    @classmethod
    def _from_fields(cls, values: dict[str, Any], where: str) -> "SyntheticSceneConfig":
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"{where}: unknown SyntheticSceneConfig fields {unknown}")
        return cls(**values)


SYNTHETIC_JSON = "synthetic.json"
FEM_RESULT_NPZ = "fem_result.npz"
NEWTON_RESULT_NPZ = "newton_result.npz"


def _stage(progress: bool, message: str) -> None:
    if progress:
        from tqdm.auto import tqdm

        tqdm.write(f"[make-scene] {message}")


def _check_target(out: Path, overwrite: bool) -> None:
    """Refuse a target that exists (unless an empty folder, or a scene folder with ``overwrite``)."""
    if not (out.exists() or out.is_symlink()):
        return
    if not out.is_dir() or out.is_symlink():
        raise FileExistsError(f"{out} exists and is not a folder")
    if not any(out.iterdir()):
        return
    if not overwrite:
        raise FileExistsError(f"{out} already exists and is not empty (pass overwrite=True / --overwrite to "
                              "replace a scene folder)")
    if not (out / "scene.json").is_file():
        raise FileExistsError(f"{out} is not a scene folder (no scene.json): refusing to replace it")


def load_tet_mesh(path: str | Path) -> "TetMesh":
    """The rest tet mesh stored in an ``.npz``: an earlier scene's ``fem_result.npz`` (``rest_vertices``,
    ``tets``) or a file with ``vertices`` (Nv, 3) and ``tets`` (Nt, 4).

    Raises:
        FileNotFoundError: no such file. ValueError: not an npz with those arrays, or degenerate tets.
    """

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"tet mesh file {path} does not exist")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"tet mesh file {path} is not a readable .npz (numpy.savez) file")
    with np.load(path, allow_pickle=False) as z:
        key = "rest_vertices" if "rest_vertices" in z.files else "vertices"
        if key not in z.files or "tets" not in z.files:
            raise ValueError(f"tet mesh file {path} holds {sorted(z.files)}; expected 'rest_vertices' (or "
                             "'vertices') and 'tets'")
        vertices, tets = z[key], z["tets"]
    if not np.issubdtype(tets.dtype, np.integer):
        raise ValueError(f"tet mesh file {path}: 'tets' must hold integers, got dtype {tets.dtype}")
    try:
        v, t, _ = clean_tet_mesh(vertices, tets, name=f"tet mesh file {path}")
    except TetrahedralizationError as exc:
        raise ValueError(str(exc)) from None
    return TetMesh(v, t, name=str(path))


def make_scene(config: SyntheticSceneConfig, out_dir: str | Path, overwrite: bool = False,
               progress: bool = True, workers: int = 1) -> Path:
    """Generate one synthetic scene folder (see the module docstring) and return its path.

    ``workers`` processes run the FEM's first pair of time resolutions side by side
    (:func:`vid2sim.synthetic.fem.simulate_fem_converged`); the result does not depend on it.

    The folder is assembled next to ``out_dir`` and renamed into place only when complete, so a failure
    or an interrupt leaves nothing behind (and an existing scene replaced with ``overwrite`` untouched).

    Raises:
        FileExistsError: ``out_dir`` exists and is not empty, unless ``overwrite`` and it is a scene folder.
        FileNotFoundError / ValueError: a bad mesh or tet-mesh file (not found, unsupported, not
            watertight, surface outside the tet mesh).
        vid2sim.meshing.tetra.TetrahedralizationError, vid2sim.synthetic.fem.FEMSolverError,
            vid2sim.synthetic.independent.NewtonSolverError: meshing or the FEM (or Newton) failed (nothing is
            written).
        vid2sim.runtime.errors.ConfigError: ``truth="newton"`` without Newton installed.
    """
    if not isinstance(config, SyntheticSceneConfig):
        raise TypeError(f"config must be a SyntheticSceneConfig, got {type(config).__name__}")
    out = Path(out_dir)
    _check_target(out, overwrite)
    _check_scene_inputs(config)
    lap = _Laps()
    mesh = _scene_object(config, progress)
    lap("object")
    tet = _scene_tets(config, mesh, progress)
    tet_index, bary = _embed_surface(mesh, tet)
    lap("tetrahedralize")
    pose = config.initial_pose()
    if config.truth == "fem":
        result, truth_metadata, result_file = _fem_truth(config, tet, pose, progress, workers)
    else:
        result, truth_metadata, result_file = _newton_truth(config, tet, pose, progress)
        # the surface rides on the tets Newton simulated (subdivided with element_order 2, renumbered)
        tet_index, bary = embed_points(mesh.vertices.double(), result.rest_vertices, result.tets)
    lap(config.truth)
    surface = apply_embedding(result.trajectory, tet_index, bary, result.embedding_elements).float()  # (T, Nv, 3)
    cameras, rgb, alpha = _render_scene(config, mesh, surface, progress)
    lap("render")
    metadata = _scene_metadata(config, mesh, pose, truth_metadata, result_file)
    scene = _scene_of(config, cameras, rgb, alpha, metadata, result, tet)
    _stage(progress, f"writing {out}")

    def write(staging: Path) -> None:
        write_scene(scene, staging, layout=config.layout, progress=progress)
        result.save(staging / result_file)
        (staging / SYNTHETIC_JSON).write_text(json.dumps(jsonable(asdict(config), nan_to_null=False), indent=2)
                                              + "\n")

    write_folder_atomic(out, write)
    lap("write")
    _stage(progress, "done in " + ", ".join(f"{k} {v:.1f} s" for k, v in lap.timings.items())
           + f" (total {sum(lap.timings.values()):.1f} s)")
    return out


class _Laps:
    """The seconds of :func:`make_scene`'s stages, in order: each call ends the stage it names."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = now - self.t0
        self.t0 = now


def _check_scene_inputs(config: SyntheticSceneConfig) -> None:
    """Fail before any work: the mesh and tet-mesh files exist (FileNotFoundError), and Newton is installed when
    it makes the truth (ConfigError naming its extra)."""
    for name in ("mesh", "tet_mesh"):
        value = getattr(config, name)
        if value is not None and not Path(value).is_file():
            raise FileNotFoundError(f"SyntheticSceneConfig.{name}: file {value} does not exist")
    if config.truth == "newton":  # the optional engine: a clear error naming its extra, before any work
        import_newton()


def _scene_object(config: SyntheticSceneConfig, progress: bool) -> TexturedMesh:
    """The scene's textured surface: the user mesh, or the seed's procedural object."""
    if config.mesh is not None:
        _stage(progress, f"loading {config.mesh}")
        return load_user_mesh(config.mesh)
    _stage(progress, f"procedural object, seed {config.seed}")
    return make_procedural_object(config.seed)


def _scene_tets(config: SyntheticSceneConfig, mesh: TexturedMesh, progress: bool) -> "TetMesh":
    """The object's tet mesh: an earlier scene's (``config.tet_mesh``), or fTetWild's of ``mesh``."""
    if config.tet_mesh is not None:
        _stage(progress, f"tet mesh from {config.tet_mesh}")
        return load_tet_mesh(config.tet_mesh)
    _stage(progress, f"tetrahedralizing {len(mesh.faces)} faces (fTetWild)")
    return tetrahedralize(mesh.vertices, mesh.faces, edge_length_fac=config.tet_edge_length,
                          epsilon=config.tet_envelope, name=mesh.name)


def _embed_surface(mesh: TexturedMesh, tet: "TetMesh") -> tuple[torch.Tensor, torch.Tensor]:
    """The tet holding each surface vertex (Nv,) and its barycentric coordinates there (Nv, 4); ValueError naming
    the object when the surface does not fit the tet mesh."""
    try:
        return embed_points(mesh.vertices.double(), tet.vertices, tet.tets)
    except ValueError as exc:
        raise ValueError(f"the surface of {mesh.name} does not fit the tet mesh {tet.name or ''}: {exc}") from None


def _fem_truth(config: SyntheticSceneConfig, tet: "TetMesh", pose: "InitialPose", progress: bool, workers: int
               ) -> tuple[FEMResult, dict[str, Any], str]:
    """The FEM drop, converged in time: its result, scene.json's ``metadata.fem`` and the result's file name."""
    fem_config = config.fem_config()
    _stage(progress, f"FEM drop: {len(tet.tets)} tets, {config.frames} frames, substeps refined until the "
                     f"trajectory changes by <= {config.time_tolerance} % of the size")
    result = simulate_fem_converged(tet.vertices, tet.tets, fem_config, pose, frames=config.frames,
                                    tolerance=config.time_tolerance, start_substeps=config.substeps,
                                    progress=progress, workers=workers)
    return result, {"fem": _fem_metadata(config, tet, result)}, FEM_RESULT_NPZ


def _newton_truth(config: SyntheticSceneConfig, tet: "TetMesh", pose: "InitialPose", progress: bool
                  ) -> tuple[NewtonResult, dict[str, Any], str]:
    """Newton's (VBD) drop, converged in time: its result, scene.json's ``metadata.newton`` and the result's file
    name."""
    _stage(progress, f"Newton (VBD) drop: {len(tet.tets)} tets{' x 8' if config.element_order == 2 else ''}, "
                     f"{config.frames} frames, steps halved until the trajectory changes by <= "
                     f"{config.time_tolerance} % of the size")
    result = simulate_newton_converged(tet.vertices, tet.tets, config.newton_config(), pose, frames=config.frames,
                                       tolerance=config.time_tolerance, start_substeps=config.substeps,
                                       progress=progress)
    return result, {"newton": newton_metadata(result)}, NEWTON_RESULT_NPZ


def _render_scene(config: SyntheticSceneConfig, mesh: TexturedMesh, surface: torch.Tensor, progress: bool
                  ) -> tuple[list, torch.Tensor, torch.Tensor]:
    """The camera ring and the textured ``surface`` (T, Nv, 3) rendered from it: cameras (V), RGB (V, T, H, W, 3)
    on white and alpha (V, T, H, W)."""
    cameras = camera_ring(config.views, config.camera_radius, config.camera_elevation_deg, config.resolution,
                          config.resolution, fov_x_deg=config.camera_fov_deg, target=config.camera_target)
    _stage(progress, f"rendering {config.views} views x {config.frames} frames at {config.resolution}x"
                     f"{config.resolution}")
    rgb, alpha = render_textured_mesh(mesh, cameras, vertices=surface, supersample=config.supersample,
                                      progress=progress)
    return cameras, rgb, alpha


def _scene_metadata(config: SyntheticSceneConfig, mesh: TexturedMesh, pose: "InitialPose",
                    truth_metadata: dict[str, Any], result_file: str) -> dict[str, Any]:
    """scene.json's ``metadata``: the ground truth (engine, material, seed, object, initial pose, the truth's own
    figures) and the names of the scene's extra files."""
    return {
        "generator": "vid2sim.synthetic.scenes",
        "truth": config.truth,
        "E": config.youngs_modulus,
        "nu": config.poisson_ratio,
        "density": config.density,
        "material": config.material if config.truth == "fem" else "newton_vbd_stable_neo_hookean",
        "seed": config.seed,
        "object": mesh.name,
        "initial_pose": jsonable(asdict(pose), nan_to_null=False),
        "damping_ratio": config.damping_ratio,
        "floor_friction": 0.0 if config.truth == "fem" else config.friction,
        **truth_metadata,
        "files": {"config": SYNTHETIC_JSON, f"{config.truth}_result": result_file},
    }


def _scene_of(config: SyntheticSceneConfig, cameras: list, rgb: torch.Tensor, alpha: torch.Tensor,
              metadata: dict[str, Any], result: FEMResult | NewtonResult, tet: "TetMesh") -> Scene:
    """The scene: the rendered images (V, T, H, W, 3) and masks (V, T, H, W), its config (observed frames and
    views, ``metadata``), and the truth's tet trajectory (T, N, 3) with its tets as the ``tet_trajectory`` extra."""
    return Scene(
        cameras=cameras,
        images=rgb,
        masks=alpha,
        config=SceneConfig(dt=config.dt, gravity=(0.0, 0.0, -9.8), floor_height=config.floor_height,
                           observed_frames=list(range(config.observed_frames)),
                           observed_views=[v for v in range(config.views) if v not in config.held_out_indices],
                           metadata=metadata),
        extras={"tet_trajectory": {"vertices": result.trajectory.float(),
                                   "tets": (tet.tets if config.truth == "fem" else result.tets).to(torch.int32)}},
    )


def _fem_metadata(config: SyntheticSceneConfig, tet: "TetMesh", result: Any) -> dict[str, Any]:
    """scene.json's ``metadata.fem``: the FEM truth's mesh, integrator, time convergence and solver figures."""
    return {
        "tets": int(len(tet.tets)),
        "vertices": int(len(tet.vertices)),
        "element_order": result.config.element_order,
        "integrator": result.config.integrator,
        "substeps": result.config.substeps,
        "time_convergence": {k: result.time_convergence[k] for k in
                             ("substeps", "kept", "tolerance_percent", "mean_percent", "max_percent")},
        "floor_stiffness": config.floor_stiffness,
        "max_penetration_m": float(result.max_penetration),
        "min_det_F": float(result.min_det.min()),
        "newton_iterations_total": int(result.newton_iterations.sum()),
    }


def benchmark_parameters(n: int, seed: int = 0) -> list[dict[str, float | int]]:
    """The deterministic (seed, E, ν) of an N-scene suite: E log-uniform in [1e4, 1e6], ν uniform in [0.2, 0.5]
    and capped at 0.49 (ν → 0.5 is incompressible, the Lamé λ → ∞; about 3 % of the scenes get 0.49).

    Scene i uses object/pose seed ``seed * 100003 + i``; its E and ν come from a generator seeded by
    ``(seed, i)``, so scene i is the same whatever N is.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"the number of scenes must be an integer >= 1, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"the suite seed must be an integer >= 0, got {seed!r}")
    out = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        log_e = rng.uniform(math.log10(BENCHMARK_E_RANGE[0]), math.log10(BENCHMARK_E_RANGE[1]))
        nu = rng.uniform(*BENCHMARK_NU_RANGE)
        nu = min(nu, 0.49)  # ν = 0.5 is incompressible: the Lamé λ is infinite
        out.append({"seed": seed * 100003 + i, "youngs_modulus": float(10.0**log_e), "poisson_ratio": float(nu)})
    return out


def benchmark_overrides(preset: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """The :class:`SyntheticSceneConfig` overrides a suite applies to every scene, from the caller's.

    Adds ``element_order`` = :data:`BENCHMARK_ELEMENT_ORDER` unless given and, for quadratic tets, the tet size
    :data:`BENCHMARK_QUADRATIC_TETS` where the preset's differs (so the small preset's suites record none) and
    the caller gave none. These are the overrides a suite's ``index.json`` records.
    """
    out = {"element_order": BENCHMARK_ELEMENT_ORDER, **overrides}
    if out["element_order"] == 2:
        preset_fields = PRESETS.get(preset, {})
        defaults = SyntheticSceneConfig.__dataclass_fields__
        out = {**{k: v for k, v in BENCHMARK_QUADRATIC_TETS.items()
                  if preset_fields.get(k, defaults[k].default) != v}, **out}
    return out


def make_benchmark(n: int, out_dir: str | Path, preset: str = "full", seed: int = 0, progress: bool = True,
                   workers: int = 1, ray_address: str | None = None, tets_from: str | Path | None = None,
                   scenes: Sequence[int] | None = None, **overrides: Any) -> Path:
    """Write a suite of ``n`` synthetic scenes ``scene_000`` … and an ``index.json`` of their ground truth.

    Scene i has the object/pose seed, E and ν of :func:`benchmark_parameters`; ``overrides`` are
    :class:`SyntheticSceneConfig` fields applied to every scene (not ``seed``, ``youngs_modulus``,
    ``poisson_ratio``). Unlike a single scene, a suite's FEM uses quadratic tets unless ``element_order=1``
    is given: a suite judges reconstructions, and two linear-tet truths of one tumbling scene agree only to
    about 23 dB on the future frames (docs/benchmarks.md, "Predictability"), below what the suite is meant
    to measure. Those quadratic tets have the size :data:`BENCHMARK_QUADRATIC_TETS` at every preset (the
    small preset's), unless ``tet_edge_length`` / ``tet_envelope`` are given: at the full preset this takes
    about 6 minutes a scene on 2 cores instead of hours. The cameras still see the preset's textured surface,
    which the tets carry (:mod:`vid2sim.synthetic.embedding`). A suite written before quadratic tets became
    the default, with no ``element_order`` in its ``index.json``, was linear and resumes with
    ``element_order=1``. Resumable: a scene folder that already exists (they are written atomically) is
    kept if its ``synthetic.json`` matches the settings the suite asks for, else this raises (before any
    work); ``index.json`` is rewritten after every scene (listing the finished ones in order, ``complete``
    once all are). A larger ``n`` extends a suite; a smaller one than the scene folders already there is
    refused (it would leave scenes outside ``index.json``).

    With ``ray_address`` (``"local"`` or a Ray cluster address, :mod:`vid2sim.runtime.ray_runner`) every
    missing scene is made by a Ray task reserving ``workers`` CPUs, with the same settings and seeds as here;
    on a cluster of several machines ``out_dir`` must be on a file system all of them see at the same path.
    A scene whose task fails does not stop the others; the first failure is raised once all have finished.
    fTetWild is not reproducible, so scenes made twice (here or there) differ slightly after meshing.
    With ``tets_from`` (another suite's folder) scene i reuses the tet mesh of that suite's scene i (its
    ``fem_result.npz`` or ``newton_result.npz``) instead of running fTetWild: a second truth of the same drops on the
    same tets (``truth="newton"``, docs/benchmarks.md). With ``scenes`` (indices in ``range(n)``) only those
    scenes are made, a shard of the suite (another machine or a later run makes the rest into the same folder):
    ``index.json`` lists every scene made so far and is ``complete`` once all ``n`` are. Returns ``out_dir``.

    Raises:
        FileExistsError: ``out_dir`` is a file, or a non-empty folder that is not a benchmark.
        FileNotFoundError: a scene of ``tets_from`` holds no result file.
        ValueError: bad settings, an existing suite / scene written with other settings, or scene folders
            beyond ``n``.
        vid2sim.runtime.ray_runner.RayUnavailable: ``ray_address`` given but Ray missing or unreachable.
    """
    from tqdm.auto import tqdm

    params = benchmark_parameters(n, seed)
    wanted = _scene_indices(scenes, n)
    overrides = benchmark_overrides(preset, overrides)
    configs = _suite_configs(preset, params, overrides, tets_from, ray_address)
    root = Path(out_dir)
    index_path = root / "index.json"
    check_output_folder(root, index_path.is_file(), "index.json", "a benchmark")
    remove_temp_files(root)  # what a run killed while writing index.json left
    header = _suite_header(preset, seed, overrides, tets_from)
    if index_path.is_file():
        _check_previous_suite(index_path, header)
        _check_no_scenes_beyond(root, n)
    names = [f"scene_{i:03d}" for i in range(n)]
    todo = [i for i in _scenes_to_make(root, names, configs) if i in wanted]
    created = not root.exists()
    root.mkdir(parents=True, exist_ok=True)
    index = _SuiteIndex(index_path, header, configs, names)
    try:
        with tqdm(total=len(wanted), initial=len(wanted) - len(todo), desc="benchmark scenes", unit="scene",
                  disable=not progress) as bar:
            _make_suite_scenes(index, root, todo, workers, ray_address, bar)
    except BaseException:
        if created and not index.entries and not any(root.iterdir()):
            root.rmdir()  # make_scene leaves nothing behind, so the folder is empty
        raise
    return root


def _scene_indices(scenes: Sequence[int] | None, n: int) -> set[int]:
    """The set of scene indices a run makes: ``scenes`` (ValueError for one outside ``range(n)``, or none), or
    all ``n``."""
    if scenes is None:
        return set(range(n))
    wanted = set()
    for i in scenes:
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < n:
            raise ValueError(f"make_benchmark: scene index {i!r} is not one of the suite's {n} (0 to {n - 1})")
        wanted.add(i)
    if not wanted:
        raise ValueError(f"make_benchmark: no scene selected of the suite's {n}")
    return wanted


def _suite_configs(preset: str, params: list[dict[str, float | int]], overrides: dict[str, Any],
                   tets_from: str | Path | None, ray_address: str | None) -> list[SyntheticSceneConfig]:
    """The settings of every scene of a suite, validated up front (ValueError for an override the suite sets
    per scene), each with its tets from ``tets_from``'s scene when given; Newton and Ray are checked when they
    will be needed, before any work."""
    fixed = sorted({"seed", "youngs_modulus", "poisson_ratio", "mesh", "tet_mesh"} & set(overrides))
    if fixed:
        raise ValueError(f"make_benchmark: {fixed} are set per scene by the suite and cannot be overridden")
    configs = [SyntheticSceneConfig.preset(preset, **{**overrides, **p}) for p in params]  # validates up front
    if any(c.truth == "newton" for c in configs):  # the optional engine, before any work
        import_newton()
    if tets_from is not None:
        configs = [replace(c, tet_mesh=str(_suite_tets(Path(tets_from), i, c))) for i, c in enumerate(configs)]
    if ray_address is not None:  # fail before any work
        check_ray(ray_address)
    return configs


def _suite_header(preset: str, seed: int, overrides: dict[str, Any], tets_from: str | Path | None
                  ) -> dict[str, Any]:
    """What a suite's ``index.json`` records of its settings (and a resume must match)."""
    header = {"preset": preset, "seed": seed, "overrides": jsonable(overrides, nan_to_null=False),
              "E_range": list(BENCHMARK_E_RANGE), "nu_range": list(BENCHMARK_NU_RANGE)}
    if tets_from is not None:
        header["tets_from"] = str(Path(tets_from).resolve())
    return header


def _scenes_to_make(root: Path, names: list[str], configs: list[SyntheticSceneConfig]) -> list[int]:
    """The indices of the scenes not yet in ``root``; every existing scene is checked (ValueError if made with
    other settings) before any work."""
    todo = []
    for i, config in enumerate(configs):  # every existing scene is checked before any work
        if (root / names[i]).exists():
            check_existing_scene(root / names[i], config)
        else:
            todo.append(i)
    return todo


def _check_previous_suite(index_path: Path, header: dict[str, Any]) -> None:
    """ValueError unless the suite's ``index.json`` was written with the settings of ``header`` (a suite written
    when a suite's tets were linear by default has no ``element_order`` override: 1)."""
    previous = json.loads(index_path.read_text())
    if isinstance(previous.get("overrides"), dict):  # written when a suite's tets were linear by default
        previous["overrides"].setdefault("element_order", 1)
    differ = {k: (previous.get(k), v) for k, v in header.items() if previous.get(k) != v}
    if differ:
        raise ValueError(f"{index_path} was written with other settings {differ} (found, asked); resume with "
                         "the same settings or use another folder")


class _SuiteIndex:
    """A suite's ``index.json``, rewritten (atomically) after every finished scene: the scenes finished so far, in
    order, and ``complete`` once all are."""

    def __init__(self, path: Path, header: dict[str, Any], configs: list[SyntheticSceneConfig],
                 names: list[str]) -> None:
        self.path, self.header, self.configs, self.names = path, header, configs, names
        self.entries: dict[int, dict[str, Any]] = {}

    def finished(self, i: int) -> None:
        """Add scene ``i`` and rewrite the index."""
        c = self.configs[i]
        self.entries[i] = {"name": self.names[i], "seed": c.seed, "E": c.youngs_modulus, "nu": c.poisson_ratio,
                           "density": c.density, "material": c.material}
        n = len(self.configs)
        write_json_atomic(self.path, {**self.header, "n": n, "complete": len(self.entries) == n,
                                      "scenes": [self.entries[k] for k in sorted(self.entries)]})


def _make_suite_scenes(index: _SuiteIndex, root: Path, todo: list[int], workers: int, ray_address: str | None,
                       bar: Any) -> None:
    """List the scenes already made, then make the scenes ``todo`` (here one after the other, or as Ray tasks),
    updating the index and the bar as each finishes."""
    waiting = set(todo)
    for i in range(len(index.configs)):
        if i not in waiting and (root / index.names[i]).is_dir():  # made earlier (a shard's others may not be)
            index.finished(i)
    if ray_address is None:
        for i in todo:
            make_scene(index.configs[i], root / index.names[i], progress=False, workers=workers)
            index.finished(i)
            bar.update(1)
    else:
        _make_scenes_on_ray(index, root, todo, workers, ray_address, bar)


def _make_scenes_on_ray(index: _SuiteIndex, root: Path, todo: list[int], workers: int, ray_address: str,
                        bar: Any) -> None:
    """Make the scenes ``todo`` as Ray tasks of ``workers`` CPUs each; a scene that fails does not stop the others,
    and the first failure is raised once all have finished."""
    configs, names = index.configs, index.names
    failures: list[BaseException] = []

    def gathered(k: int, result: Any) -> None:
        if isinstance(result, BaseException):
            failures.append(result)
            bar.write(f"[make-benchmark] {names[todo[k]]} failed: {type(result).__name__}: {result}")
        else:
            index.finished(todo[k])
        bar.update(1)

    calls = [((configs[i], str((root / names[i]).resolve())), {"progress": False, "workers": workers})
             for i in todo]
    ray_map(make_scene, calls, ray_address, num_cpus=max(1, workers), on_done=gathered)
    if failures:
        raise failures[0]


def _suite_tets(suite: Path, i: int, config: SyntheticSceneConfig) -> Path:
    """The result file of scene i of another suite (its tets), checked to be the same object and drop."""
    folder = suite / f"scene_{i:03d}"
    for name in (FEM_RESULT_NPZ, NEWTON_RESULT_NPZ):
        if (folder / name).is_file():
            other = SyntheticSceneConfig.from_json(folder / SYNTHETIC_JSON)
            if (other.seed, other.mesh) != (config.seed, config.mesh):
                raise ValueError(f"{folder} is seed {other.seed} (mesh {other.mesh}), not seed {config.seed} (mesh "
                                 f"{config.mesh}): its tets are another object's")
            return folder / name
    raise FileNotFoundError(f"{folder} holds no {FEM_RESULT_NPZ} or {NEWTON_RESULT_NPZ} to take scene {i}'s tets from")


def _check_no_scenes_beyond(root: Path, n: int) -> None:
    """Refuse to shrink a suite: scene folders ``scene_NNN`` with NNN >= ``n`` would be left out of index.json."""
    found = sorted(int(p.name[len("scene_"):]) for p in root.iterdir()
                   if p.is_dir() and p.name.startswith("scene_") and p.name[len("scene_"):].isdigit())
    beyond = [i for i in found if i >= n]
    if beyond:
        have = max(found) + 1
        extra = ", ".join(f"scene_{i:03d}" for i in beyond)
        raise ValueError(
            f"{root} holds a suite of {have} scene{'s' if have != 1 else ''}; asking for {n} would leave "
            f"{extra} outside index.json. Resume or extend it with n = {have} or more (scene i is the same "
            f"whatever n), or write the smaller suite to another folder")


def check_existing_scene(folder: Path, config: SyntheticSceneConfig) -> None:
    """Raise unless ``folder`` is a finished scene made with ``config`` (up to the tet mesh reuse)."""
    path = folder / SYNTHETIC_JSON
    if not path.is_file():
        raise ValueError(f"{folder} exists but holds no {SYNTHETIC_JSON}: not a scene of this benchmark "
                         "(remove it to regenerate)")
    found = asdict(SyntheticSceneConfig.from_json(path))
    wanted = asdict(config)
    differ = sorted(k for k in wanted if k != "tet_mesh" and found[k] != wanted[k])
    if differ:
        changes = ", ".join(f"{k}: {found[k]!r} != {wanted[k]!r}" for k in differ)
        raise ValueError(f"{folder} was made with other settings ({changes}); remove it to regenerate")

