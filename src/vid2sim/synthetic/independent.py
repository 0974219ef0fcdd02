"""A second, independent ground truth: the same drop simulated by NVIDIA Newton's Vertex Block Descent solver.

The benchmark's own truth (:mod:`vid2sim.synthetic.fem`) shares its energy, contact and damping with the reduced
simulator it judges. This module makes the same drop (same tet mesh, pose, velocity, E, ν, density and damping ratio)
with an engine that is not ours, `Newton <https://pypi.org/project/newton/>`_ (NVIDIA's physics engine on Warp,
optional: ``pip install "vid2sim[newton]"``), whose model differs in every part that is not the material's two
constants (docs/benchmarks.md, "A second, independent truth"):

* **Energy.** Newton's ``SolverVBD`` gives a tet the *stable* Neo-Hookean energy of Smith et al. (2018) without the
  log barrier, Ψ = μ/2 (I_C − 3) + λ'/2 (J − α)², λ' = λ + μ, α = 1 + μ/λ', where (μ, λ) are the Lamé parameters
  that Newton takes (:class:`NewtonConfig.newton_material`). It linearises to the same Lamé parameters as ours,
  μ/2 (I_C − 3) − μ ln J + λ/2 (ln J)², and differs at large strain: it stays finite as J → 0 (no barrier against
  inversion) and its volumetric term is quadratic in J, not in ln J.
* **Elements.** Linear tets (Newton has no quadratic ones): the scene's tets, or with ``subdivide`` the quadratic
  tets' ten nodes split into eight linear tets each (:func:`subdivide_quadratic`).
* **Contact.** A penalty per vertex, ke · depth with one ``ke`` for all vertices (ours is a pressure per unit area
  at each vertex's own area), switched on a ``contact_radius`` above the plane, with Newton's regularised Coulomb
  friction (coefficient ``friction``; ours is frictionless) and optional damping while approaching.
* **Dissipation.** Newton's viscosity on the rate of C = FᵀF, force −V d Σ Ċ_ij ∂C_ij/∂x: a shear viscosity
  only (ours has the bulk term τλ tr Ė too), with d = τμ/2 so that its shear part equals our Kelvin–Voigt
  2τμĖ; implicit Euler's own damping (ours: BDF2); friction.
* **Solver.** Implicit Euler steps, each minimised approximately by a fixed number of VBD sweeps (Gauss–Seidel
  over colours of vertices, a 3×3 Newton step per vertex) in float32 on Warp's CPU (or CUDA) device; ours runs
  Newton's method on the whole system to a tolerance in float64.

:func:`simulate_newton_converged` halves the time step until two runs' trajectories differ by at most a tolerance
(as :func:`vid2sim.synthetic.fem.simulate_fem_converged` does), and :class:`NewtonResult` keeps the comparison.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.meshing.tetra import surface_vertex_areas
from vid2sim.metrics.trajectory import trajectory_distance
from vid2sim.physics.damping import DEFAULT_DAMPING_RATIO, check_damping_ratio, retardation_time
from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
from vid2sim.physics.integrators import auto_substeps
from vid2sim.physics.materials import lame_parameters
from vid2sim.physics.tet_modes import quadratic_tet_nodes
from vid2sim.runtime.errors import ConfigError
from vid2sim.synthetic.fem import InitialPose

#: the engine version vid2sim is tested with (pyproject's ``newton`` extra pins it: SolverVBD is experimental)
NEWTON_VERSION = "1.8.0"
INSTALL_HINT = 'pip install "vid2sim[newton]"'


class NewtonSolverError(RuntimeError):
    """The Newton drop did not converge in time, or its state stopped being finite."""


def import_newton() -> tuple[Any, Any]:
    """``(newton, warp)``, imported quietly.

    Raises:
        ConfigError: Newton is not installed (the message gives the install command).
    """
    try:
        import warp as wp

        wp.config.quiet = True
        import newton
    except ImportError as exc:
        raise ConfigError(f"the independent truth needs NVIDIA Newton ({INSTALL_HINT}): {exc}") from None
    return newton, wp


@dataclass
class NewtonConfig:
    """The independent engine's drop (SI units); the material and scene fields mean what they mean in
    :class:`vid2sim.synthetic.fem.FEMConfig`.

    Attributes:
        youngs_modulus: E in Pa.
        poisson_ratio: ν in (−1, 0.5).
        density: ρ in kg/m³ (lumped masses ρV/4 per tet vertex, Newton's own).
        damping_ratio: ζ at ω_ref = √(E/ρ)/L: the shear viscosity d = τμ/2 with τ = 2ζL√(ρ/E)
            (:func:`vid2sim.physics.damping.retardation_time`); 0 = undamped.
        damping_length: L in metres; None = the rest bounding-box diagonal.
        dt: time between video frames (s).
        substeps: implicit-Euler steps per frame (h = dt / substeps); :func:`simulate_newton_converged` doubles it.
        iterations: VBD sweeps per step (Newton's default is 10).
        floor_height: z of the floor plane, or None for no floor.
        floor_stiffness: κ (Pa/m): each vertex's penalty stiffness is ke = κ · ā, ā the mean lumped rest area of the
            boundary vertices, so that a flat contact has our pressure on average.
        contact_damping: Newton's contact damping kd (N·s/m per vertex), applied while a vertex approaches the floor.
        friction: Coulomb friction coefficient of the floor.
        friction_velocity: slip speed (m/s) below which Newton's friction is a linear ramp (its ``friction_epsilon``).
        contact_radius: the vertices' contact radius (m); the plane sits this far below ``floor_height``, so a vertex
            touches it at z = floor_height.
        contact_gap: extra detection distance (m) of Newton's collision pipeline.
        gravity: (3,) acceleration (m/s²).
        subdivide: the tets are quadratic elements' corners: simulate the eight linear tets per tet spanned by the
            corners and edge midpoints (:func:`subdivide_quadratic`), twice as fine, 8× the tets.
        device: Warp device, ``"cpu"`` or ``"cuda:0"``.
    """

    youngs_modulus: float = 1e5
    poisson_ratio: float = 0.3
    density: float = 1000.0
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    damping_length: float | None = None
    dt: float = 0.05
    substeps: int = 64
    iterations: int = 10
    floor_height: float | None = -0.7
    floor_stiffness: float = AREA_CONTACT_STIFFNESS
    contact_damping: float = 0.0
    friction: float = 0.5
    friction_velocity: float = 1e-2
    contact_radius: float = 1e-3
    contact_gap: float = 1e-2
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    subdivide: bool = False
    device: str = "cpu"

    def __post_init__(self) -> None:
        try:
            lame_parameters(self.youngs_modulus, self.poisson_ratio)
        except ValueError as exc:
            raise ConfigError(f"NewtonConfig: {exc}") from None
        self.damping_ratio = check_damping_ratio(self.damping_ratio, "NewtonConfig.damping_ratio")
        def number(value: Any) -> bool:
            return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)

        for name in ("density", "dt", "floor_stiffness", "friction_velocity", "contact_radius", "contact_gap"):
            value = getattr(self, name)
            if not (number(value) and value > 0):
                raise ConfigError(f"NewtonConfig.{name} must be a positive finite number, got {value!r}")
        for name in ("contact_damping", "friction"):
            value = getattr(self, name)
            if not (number(value) and value >= 0):
                raise ConfigError(f"NewtonConfig.{name} must be a finite number >= 0, got {value!r}")
        for name in ("substeps", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"NewtonConfig.{name} must be an integer >= 1, got {value!r}")
        if self.damping_length is not None and not (math.isfinite(self.damping_length) and self.damping_length > 0):
            raise ConfigError(
                f"NewtonConfig.damping_length must be a positive number or None, got {self.damping_length!r}")
        if self.floor_height is not None and not math.isfinite(self.floor_height):
            raise ConfigError(f"NewtonConfig.floor_height must be finite or None, got {self.floor_height!r}")
        g = tuple(float(c) for c in self.gravity)
        if len(g) != 3 or not all(math.isfinite(c) for c in g):
            raise ConfigError(f"NewtonConfig.gravity must be three finite numbers, got {self.gravity!r}")
        self.gravity = g  # type: ignore[assignment]

    def newton_material(self, size: float) -> dict[str, float]:
        """Newton's tet material for an object of rest bounding-box diagonal ``size`` (m), and how it maps.

        Returns:
            ``k_mu`` = μ and ``k_lambda`` = λ (the Lamé parameters Newton's ``add_soft_mesh`` takes), ``k_damp`` = d =
            τμ/2 (Pa·s), and the energy's own constants ``mu_nh`` = μ, ``lambda_nh`` = λ + μ, ``alpha`` = 1 + μ/λ_nh,
            ``tau`` (s).
        """
        mu, lam = lame_parameters(self.youngs_modulus, self.poisson_ratio)
        length = self.damping_length if self.damping_length is not None else size
        tau = float(retardation_time(self.damping_ratio, self.youngs_modulus, self.density, length))
        return {"k_mu": mu, "k_lambda": lam, "k_damp": 0.5 * tau * mu, "mu_nh": mu, "lambda_nh": lam + mu,
                "alpha": 1.0 + mu / (lam + mu), "tau": tau}


def subdivide_quadratic(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split every tet into eight linear tets on its corners and edge midpoints (the nodes of quadratic tets).

    Args:
        vertices: (Nv, 3) positions. tets: (Nt, 4) positively oriented tets.

    Returns:
        ``(nodes (Nv + Ne, 3), tets (8 Nt, 4))``: the nodes of :func:`vid2sim.physics.tet_modes.quadratic_tet_nodes`
        (vertices first, then one per edge) and positively oriented linear tets (the inner octahedron cut along the
        diagonal between the midpoints of edges 0–2 and 1–3).
    """

    nodes, elements = quadratic_tet_nodes(vertices, tets)
    a, b, c, d, ab, bc, ac, ad, bd, cd = elements.T  # corners, then the midpoints in TET_EDGES order
    sub = np.concatenate([np.stack(t, 1) for t in (
        (a, ab, ac, ad), (ab, b, bc, bd), (ac, bc, c, cd), (ad, bd, cd, d),
        (ab, ac, ad, bd), (ab, bc, ac, bd), (ac, ad, bd, cd), (ac, bd, bc, cd))], 0)
    sub = _positively_oriented(nodes, sub)
    return nodes, sub


def _positively_oriented(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = nodes[tets]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    if not (np.abs(volume) > 0).all():
        raise ValueError("degenerate tets (zero volume)")
    out = tets.copy()
    out[volume < 0] = out[volume < 0][:, [0, 2, 1, 3]]
    return out


@dataclass
class NewtonResult:
    """A drop simulated by Newton.

    Attributes:
        rest_vertices: (N, 3) rest positions of the simulated nodes.
        tets: (Nt, 4) the simulated linear tets (node indices).
        trajectory: (T, N, 3) node positions at the video frames (float64 copies of Newton's float32).
        velocities: (T, N, 3) node velocities at the frames.
        times: (T,) seconds.
        energies: name → (T,) 'kinetic', 'elastic' (Newton's energy, zero at rest), 'gravity' (−Σ m g·x), 'floor'
            (½ ke Σ depth²), 'total'.
        min_det: (T,) smallest det F over the tets per frame.
        masses: (N,) Newton's lumped masses.
        contact_stiffness: ke, the penalty stiffness of each vertex (N/m).
        config: the NewtonConfig used. pose: the InitialPose used.
        engine: name, version, Warp version, solver and device.
        wall_time: seconds spent simulating.
        time_convergence: the step halvings of :func:`simulate_newton_converged`, or None for a single run.
    """

    rest_vertices: Tensor
    tets: Tensor
    trajectory: Tensor
    velocities: Tensor
    times: Tensor
    energies: dict[str, Tensor]
    min_det: Tensor
    masses: Tensor
    contact_stiffness: float
    config: NewtonConfig
    pose: InitialPose
    engine: dict[str, str]
    wall_time: float = 0.0
    time_convergence: dict | None = None

    @property
    def embedding_elements(self) -> Tensor:
        """(Nt, 4) the elements that carry points inside the mesh
        (:func:`vid2sim.synthetic.embedding.apply_embedding`)."""
        return self.tets

    def save(self, path: str | Path) -> Path:
        """Write everything to one ``.npz`` (config, pose, engine and convergence as JSON strings); returns the path."""
        path = Path(path)
        arrays = {k: getattr(self, k).numpy() for k in
                  ("rest_vertices", "tets", "trajectory", "velocities", "times", "min_det", "masses")}
        arrays.update({f"energy_{k}": v.numpy() for k, v in self.energies.items()})
        np.savez_compressed(path, config=json.dumps(asdict(self.config)), pose=json.dumps(asdict(self.pose)),
                            engine=json.dumps(self.engine), time_convergence=json.dumps(self.time_convergence),
                            wall_time=self.wall_time, contact_stiffness=self.contact_stiffness, **arrays)
        return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")

    @classmethod
    def load(cls, path: str | Path) -> "NewtonResult":
        """Read a file written by :meth:`save`."""
        with np.load(Path(path), allow_pickle=False) as z:
            t = lambda k: torch.from_numpy(z[k].copy())  # noqa: E731
            cfg = json.loads(str(z["config"]))
            cfg["gravity"] = tuple(cfg["gravity"])
            return cls(rest_vertices=t("rest_vertices"), tets=t("tets"), trajectory=t("trajectory"),
                       velocities=t("velocities"), times=t("times"),
                       energies={k[len("energy_"):]: t(k) for k in z.files if k.startswith("energy_")},
                       min_det=t("min_det"), masses=t("masses"), contact_stiffness=float(z["contact_stiffness"]),
                       config=NewtonConfig(**cfg), pose=InitialPose(**json.loads(str(z["pose"]))),
                       engine=json.loads(str(z["engine"])), wall_time=float(z["wall_time"]),
                       time_convergence=json.loads(str(z["time_convergence"])))


def _as_numpy(a: Tensor | np.ndarray, dtype: Any) -> np.ndarray:
    return np.asarray(a.detach().cpu() if isinstance(a, Tensor) else a, dtype=dtype)


def _elastic_energy(x: np.ndarray, tets: np.ndarray, dm_inv: np.ndarray, volume: np.ndarray,
                    material: dict[str, float]) -> tuple[float, float]:
    """(Σ V Ψ(F) with Newton's energy less its value at rest, smallest det F) at positions x (N, 3)."""
    p = x[tets]
    F = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2) @ dm_inv
    J = np.linalg.det(F)
    mu, lam, alpha = material["mu_nh"], material["lambda_nh"], material["alpha"]
    psi = 0.5 * mu * ((F * F).sum((1, 2)) - 3.0) + 0.5 * lam * (J - alpha) ** 2 - 0.5 * lam * (1.0 - alpha) ** 2
    return float(volume @ psi), float(J.min())


def simulate_newton(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: NewtonConfig | None = None,
                    pose: InitialPose | None = None, frames: int = 24,
                    initial_velocity: Tensor | np.ndarray | None = None, progress: bool = True,
                    on_frame: Callable[[], None] | None = None) -> NewtonResult:
    """Simulate a tet mesh dropped onto the floor with Newton's VBD solver.

    Args:
        vertices: (Nv, 3) rest positions (canonical frame). tets: (Nt, 4) tets.
        config: NewtonConfig (defaults if None); with ``subdivide`` the tets are split eight ways first.
        pose: initial pose (rotation about the centre of mass, drop height, rigid velocity), or None to start
            at rest where the vertices are.
        frames: video frames T >= 1 (frame 0 is the initial state).
        initial_velocity: (N, 3) node velocities overriding the pose's (e.g. a mode shape).
        progress: show a progress bar over frames. on_frame: called after every frame.

    Returns:
        NewtonResult with (T, N, 3) trajectory and velocities.

    Raises:
        ConfigError: Newton is not installed.
    """

    config = config or NewtonConfig()
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    newton, wp = import_newton()
    X, T = _simulated_tets(vertices, tets, config)
    size = float(np.linalg.norm(X.max(0) - X.min(0)))
    material = config.newton_material(size)
    areas = surface_vertex_areas(torch.from_numpy(X), torch.from_numpy(T)).numpy()
    ke = config.floor_stiffness * float(areas[areas > 0].mean())
    model = _newton_model(newton, wp, X, T, config, material, ke)
    masses = model.particle_mass.numpy().astype(np.float64)
    dm_inv = model.tet_poses.numpy().astype(np.float64)
    volume = 1.0 / (6.0 * np.linalg.det(dm_inv))
    rest = torch.from_numpy(X)
    x0, v0, pose = _initial_state(rest, masses, pose, initial_velocity, config)
    stepper = _VBDStepper(newton, model, config, x0, v0)
    frames_ = _NewtonFrames(T, dm_inv, volume, material, masses, ke, config)
    frames_.record(stepper.positions(), stepper.velocities())
    start = time.perf_counter()
    for _ in tqdm(range(frames - 1), desc="Newton frames", disable=not progress):
        stepper.advance()
        x = stepper.positions()
        if not np.isfinite(x).all():
            raise NewtonSolverError(f"Newton's state is not finite after frame {len(frames_.traj)}")
        frames_.record(x, stepper.velocities())
        if on_frame is not None:
            on_frame()
    wall = time.perf_counter() - start
    engine = {"name": "newton", "version": newton.__version__, "warp": wp.__version__,
              "solver": f"SolverVBD, {config.iterations} iterations per step, implicit Euler",
              "device": str(config.device)}
    return frames_.result(rest, pose, engine, wall)


def _simulated_tets(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: NewtonConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The nodes (N, 3) float64 and linear tets (Nt, 4) int64 Newton simulates: the tets split eight ways with
    ``subdivide``, else the vertices the tets use, renumbered, with every tet positively oriented."""
    X = _as_numpy(vertices, np.float64)
    T = _as_numpy(tets, np.int64)
    if config.subdivide:
        return subdivide_quadratic(X, T)
    used = np.unique(T)
    remap = np.full(len(X), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return X[used], _positively_oriented(X[used], remap[T])


def _newton_model(newton: Any, wp: Any, X: np.ndarray, T: np.ndarray, config: NewtonConfig,
                  material: dict[str, float], ke: float) -> Any:
    """Newton's model of the soft mesh (nodes X (N, 3), tets T (Nt, 4)) with ``material``'s moduli and damping,
    the ground plane (friction μ) when there is a floor, and the soft-contact stiffness ``ke`` (N/m)."""
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=config.gravity)
    builder.add_soft_mesh(pos=(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=(0.0, 0.0, 0.0),
                          vertices=X.tolist(), indices=T.reshape(-1).tolist(), density=config.density,
                          k_mu=material["k_mu"], k_lambda=material["k_lambda"], k_damp=material["k_damp"],
                          particle_radius=config.contact_radius, add_surface_mesh_edges=False)
    if config.floor_height is not None:
        shape_cfg = newton.ModelBuilder.ShapeConfig(mu=config.friction, margin=0.0)
        builder.add_ground_plane(height=config.floor_height - config.contact_radius, cfg=shape_cfg)
    builder.color()
    model = builder.finalize(device=config.device)
    model.soft_contact_ke = ke
    model.soft_contact_kd = config.contact_damping
    model.soft_contact_mu = config.friction  # mixed with the plane's μ as √(μ·μ) = μ
    return model


def _initial_state(rest: Tensor, masses: np.ndarray, pose: InitialPose | None,
                   initial_velocity: Tensor | np.ndarray | None, config: NewtonConfig
                   ) -> tuple[Tensor, Tensor, InitialPose]:
    """The start positions and velocities (N, 3) float64 (``pose`` applied to ``rest``, at rest where the nodes
    are without one; ``initial_velocity`` (N, 3) replacing the velocities), and the pose recorded."""
    if pose is None:
        x0, v0 = rest.clone(), torch.zeros_like(rest)
        pose = InitialPose(drop_height=0.0)
    else:
        x0, v0 = pose.apply(rest, torch.from_numpy(masses), config.floor_height)
    if initial_velocity is not None:
        v0 = torch.from_numpy(_as_numpy(initial_velocity, np.float64))
        if v0.shape != x0.shape or not torch.isfinite(v0).all():
            raise ValueError(f"initial_velocity must be a finite {tuple(x0.shape)} array, got shape {tuple(v0.shape)}")
    return x0, v0, pose


class _VBDStepper:
    """Newton's VBD solver on ``model`` from the start state x0, v0 (N, 3), with the floor's collision pipeline when
    there is a floor; it advances a video frame at a time (``substeps`` implicit Euler steps)."""

    def __init__(self, newton: Any, model: Any, config: NewtonConfig, x0: Tensor, v0: Tensor) -> None:
        self.solver = newton.solvers.SolverVBD(model, iterations=config.iterations,
                                               friction_epsilon=config.friction_velocity,
                                               particle_enable_self_contact=False, particle_enable_tile_solve=False)
        self.state, self.state_next, self.control = model.state(), model.state(), model.control()
        self.state.particle_q.assign(x0.numpy().astype(np.float32))
        self.state.particle_qd.assign(v0.numpy().astype(np.float32))
        self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=config.contact_gap) \
            if config.floor_height is not None else None
        self.contacts = self.pipeline.contacts() if self.pipeline is not None else None
        self.substeps = config.substeps
        self.h = config.dt / config.substeps

    def advance(self) -> None:
        """One video frame: ``substeps`` solver steps of h seconds (contacts found before each)."""
        for _ in range(self.substeps):
            self.state.clear_forces()
            if self.pipeline is not None:
                self.pipeline.collide(self.state, self.contacts)
            self.solver.step(self.state, self.state_next, self.control, self.contacts, self.h)
            self.state, self.state_next = self.state_next, self.state

    def positions(self) -> np.ndarray:
        """(N, 3) float64 positions now."""
        return self.state.particle_q.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """(N, 3) float64 velocities now."""
        return self.state.particle_qd.numpy().astype(np.float64)


class _NewtonFrames:
    """The frames of a Newton run as they come: positions, velocities (N, 3), smallest det F and energies."""

    def __init__(self, tets: np.ndarray, dm_inv: np.ndarray, volume: np.ndarray, material: dict[str, float],
                 masses: np.ndarray, ke: float, config: NewtonConfig) -> None:
        self.tets, self.dm_inv, self.volume, self.material = tets, dm_inv, volume, material
        self.masses, self.ke, self.config = masses, ke, config
        self.g = np.asarray(config.gravity)
        self.traj: list[np.ndarray] = []
        self.vels: list[np.ndarray] = []
        self.dets: list[float] = []
        self.energies: dict[str, list[float]] = {}

    def record(self, x: np.ndarray, v: np.ndarray) -> None:
        """Add a frame: positions x and velocities v (N, 3) float64."""
        config, masses = self.config, self.masses
        elastic, det = _elastic_energy(x, self.tets, self.dm_inv, self.volume, self.material)
        floor = 0.0
        if config.floor_height is not None:
            floor = 0.5 * self.ke * float((np.maximum(0.0, config.floor_height - x[:, 2]) ** 2).sum())
        parts = {"kinetic": 0.5 * float(masses @ (v * v).sum(1)), "elastic": elastic,
                 "gravity": -float(masses @ (x @ self.g)), "floor": floor}
        parts["total"] = sum(parts.values())
        for k, val in parts.items():
            self.energies.setdefault(k, []).append(val)
        self.traj.append(x)
        self.vels.append(v)
        self.dets.append(det)

    def result(self, rest: Tensor, pose: InitialPose, engine: dict[str, str], wall: float) -> NewtonResult:
        """The run's :class:`NewtonResult` from the frames recorded."""
        frames = len(self.traj)
        return NewtonResult(
            rest_vertices=rest, tets=torch.from_numpy(self.tets), trajectory=torch.from_numpy(np.stack(self.traj)),
            velocities=torch.from_numpy(np.stack(self.vels)),
            times=torch.arange(frames, dtype=torch.float64) * self.config.dt,
            energies={k: torch.tensor(v, dtype=torch.float64) for k, v in self.energies.items()},
            min_det=torch.tensor(self.dets, dtype=torch.float64), masses=torch.from_numpy(self.masses),
            contact_stiffness=self.ke, config=self.config, pose=pose, engine=engine, wall_time=wall)


def default_start_substeps(config: NewtonConfig, size: float) -> int:
    """The first substep count of :func:`simulate_newton_converged`: 4 × the automatic count of our BDF2 FEM for the
    material (:func:`vid2sim.physics.integrators.auto_substeps`), at least 16: implicit Euler damps a mode of angular
    frequency ω by a ratio ≈ ωh/2, which must stay well below the material's damping."""

    length = config.damping_length if config.damping_length is not None else size
    return max(16, 4 * auto_substeps(config.dt, config.youngs_modulus, config.density, length))


def simulate_newton_converged(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray,
                              config: NewtonConfig | None = None, pose: InitialPose | None = None, frames: int = 24,
                              tolerance: float = 1.0, start_substeps: int | None = None, max_substeps: int = 4096,
                              progress: bool = True) -> NewtonResult:
    """A Newton trajectory converged in time: run with n and 2n substeps per frame (the same VBD sweeps per step),
    doubling n until the two differ by at most ``tolerance`` percent of the object's size (mean over frames 1 … T−1
    of the mean node distance, :func:`vid2sim.metrics.trajectory_distance`); return the finer run with
    :attr:`NewtonResult.time_convergence` filled in.

    Args:
        vertices, tets, config, pose, frames: as :func:`simulate_newton`.
        tolerance: the largest change allowed under 2× refinement, percent of the rest bounding-box diagonal.
        start_substeps: the first n; default :func:`default_start_substeps`.
        max_substeps: give up (:class:`NewtonSolverError`) rather than go beyond this.
        progress: show a progress bar.
    """

    config = config or NewtonConfig()
    X = _as_numpy(vertices, np.float64)
    size = float(np.linalg.norm(np.ptp(X[np.unique(_as_numpy(tets, np.int64))], axis=0)))
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive percentage, got {tolerance!r}")
    n = int(start_substeps) if start_substeps is not None else default_start_substeps(config, size)
    if n < 1 or 2 * n > max_substeps:
        raise ValueError(f"start_substeps must be in [1, {max_substeps // 2}], got {n!r}")

    def run(substeps: int) -> NewtonResult:
        with tqdm(total=frames - 1, desc=f"Newton frames ({substeps} substeps)", disable=not progress) as bar:
            return simulate_newton(vertices, tets, replace(config, substeps=substeps), pose, frames, progress=False,
                                   on_frame=bar.update)

    coarse, fine = run(n), run(2 * n)
    history: list[dict[str, Any]] = []
    total = coarse.wall_time + fine.wall_time
    while True:
        d = trajectory_distance(coarse.trajectory, fine.trajectory, size)
        history.append({"substeps": [n, 2 * n], "mean_percent": round(d.mean, 4), "max_percent": round(d.max, 4)})
        if d.mean <= tolerance:
            fine.time_convergence = {
                "substeps": [n, 2 * n], "kept": 2 * n, "tolerance_percent": tolerance, "mean_percent": d.mean,
                "max_percent": d.max, "per_frame_percent": d.per_frame,
                "measure": "mean over frames 1..T-1 of the mean node distance, percent of the rest bounding-box "
                           "diagonal, between the runs with n and 2n substeps (the same VBD iterations per step)",
                "comparisons": history, "wall_time_all_runs": total}
            return fine
        if 4 * n > max_substeps:
            raise NewtonSolverError(
                f"the Newton trajectory is not converged in time: {n} and {2 * n} substeps per frame differ by "
                f"{d.mean:.2f} % of the size (tolerance {tolerance} %) and {4 * n} would exceed "
                f"max_substeps={max_substeps}")
        n, coarse = 2 * n, fine
        fine = run(2 * n)
        total += fine.wall_time


def newton_metadata(result: NewtonResult) -> dict[str, Any]:
    """scene.json's ``metadata.newton``: the engine and its version, its energy and how its parameters map to (E, ν,
    ζ), its contact and solver settings, the mesh and the time convergence."""
    cfg = result.config
    size = float(np.linalg.norm(np.ptp(result.rest_vertices.numpy(), axis=0)))
    tc = result.time_convergence or {}
    return {
        "engine": result.engine,
        "material_model": "stable Neo-Hookean without the log term (Smith et al. 2018, as Newton's SolverVBD has it): "
                          "psi = mu_nh/2 (I_C - 3) + lambda_nh/2 (J - alpha)^2",
        "parameters": cfg.newton_material(size),
        "mapping": "k_mu = mu, k_lambda = lambda (the Lame parameters of E, nu); Newton uses mu_nh = mu, "
                   "lambda_nh = lambda + mu, alpha = 1 + mu/lambda_nh (the same small-strain Lame parameters); "
                   "k_damp = tau mu / 2, its viscosity on dC/dt equal to our Kelvin-Voigt shear term 2 tau mu dE/dt "
                   "(no bulk viscosity)",
        "contact": {"model": "penalty ke * depth per vertex, regularised Coulomb friction, damping while approaching",
                    "ke_per_vertex": result.contact_stiffness, "floor_stiffness_per_area": cfg.floor_stiffness,
                    "damping_kd": cfg.contact_damping, "friction": cfg.friction,
                    "friction_velocity": cfg.friction_velocity, "contact_radius": cfg.contact_radius},
        "integrator": "implicit Euler, VBD",
        "iterations": cfg.iterations,
        "substeps": cfg.substeps,
        "tets": int(len(result.tets)),
        "vertices": int(len(result.rest_vertices)),
        "subdivided": cfg.subdivide,
        "time_convergence": {k: tc.get(k) for k in
                             ("substeps", "kept", "tolerance_percent", "mean_percent", "max_percent")},
        "max_penetration_m": float((cfg.floor_height - result.trajectory[..., 2]).clamp_min(0).max())
        if cfg.floor_height is not None else 0.0,
        "min_det_F": float(result.min_det.min()),
        "wall_time_s": result.wall_time,
    }
