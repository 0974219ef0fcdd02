"""Running the FEM ground truth: a drop simulated over frames (:func:`simulate_fem`), refined in time until converged
(:func:`simulate_fem_converged`), static solves, and the results (:class:`FEMResult`)."""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from vid2sim.metrics.trajectory import trajectory_distance
from vid2sim.physics.integrators import auto_substeps
from vid2sim.runtime.workers import process_pool
from vid2sim.synthetic.fem.config import FEMConfig, FEMSolverError, InitialPose
from vid2sim.synthetic.fem.model import FactorCache, NewtonStats, TetFEM, contact_areas

# ---- results and drivers --------------------------------------------------------------------------

@dataclass
class FEMResult:
    """A simulated FEM trajectory.

    Attributes:
        rest_vertices: (N, 3) rest positions of the nodes: the mesh's Nv vertices, then (quadratic tets) one
            node per edge midpoint.
        tets: (Nt, 4) tets (vertex indices).
        trajectory: (T, N, 3) node positions at the video frames; frame 0 is the initial pose.
        velocities: (T, Nv, 3) vertex velocities at the frames.
        times: (T,) seconds.
        energies: name → (T,) total mechanical energy parts: 'kinetic', 'elastic', 'gravity' (−Σ m g·x),
            'floor', 'total'.
        min_det: (T,) smallest det F over the tets per frame.
        newton_iterations: (T − 1, substeps) Newton iterations of every substep.
        line_search_halvings: (T − 1,) backtracking halvings per frame.
        inverted_rejections: (T − 1,) line-search trial states rejected per frame because a tet inverted.
        config: the FEMConfig used.
        pose: the InitialPose used.
        fixed: (Nv,) bool mask of fixed vertices.
        wall_time: seconds spent simulating.
        time_convergence: how the time step was checked (:func:`simulate_fem_converged`): the substeps
            compared, the trajectory difference between them (percent of the size, mean over frames 1 … T−1
            and the largest frame), the tolerance, every comparison made and the wall time of all runs;
            None for a single run.
        elements: (Nt, 10) node indices of the quadratic tets (:func:`vid2sim.physics.tet_modes.quadratic_tet_nodes`
            order), or None for linear tets.
    """

    rest_vertices: Tensor
    tets: Tensor
    trajectory: Tensor
    velocities: Tensor
    times: Tensor
    energies: dict[str, Tensor]
    min_det: Tensor
    newton_iterations: Tensor
    line_search_halvings: Tensor
    inverted_rejections: Tensor
    config: FEMConfig
    pose: InitialPose
    fixed: Tensor
    wall_time: float = 0.0
    time_convergence: dict | None = None
    elements: Tensor | None = None

    @property
    def embedding_elements(self) -> Tensor:
        """The elements that interpolate positions inside the mesh: ``elements`` (Nt, 10) for quadratic
        tets, else ``tets`` (Nt, 4); for :func:`vid2sim.synthetic.embedding.apply_embedding`."""
        return self.tets if self.elements is None else self.elements

    def contact_areas(self) -> Tensor:
        """(N,) the lumped rest boundary area per node that the floor penalty used (0 inside)."""
        X = self.rest_vertices.numpy()[: int(self.tets.max()) + 1]
        T = self.tets.numpy().astype(np.int64)
        elements = T if self.elements is None else self.elements.numpy().astype(np.int64)
        return torch.from_numpy(contact_areas(X, T, elements, self.rest_vertices.shape[0]))

    @property
    def max_penetration(self) -> float:
        """Largest floor penetration max(0, h − z) over all frames and vertices (0 without a floor)."""
        if self.config.floor_height is None:
            return 0.0
        return float((self.config.floor_height - self.trajectory[..., 2]).clamp_min(0).max())

    def save(self, path: str | Path) -> Path:
        """Write everything to one ``.npz`` (config and pose as JSON strings); returns the path."""
        path = Path(path)
        arrays = {k: getattr(self, k).numpy() for k in
                  ("rest_vertices", "tets", "trajectory", "velocities", "times", "min_det", "newton_iterations",
                   "line_search_halvings", "inverted_rejections", "fixed")}
        arrays.update({f"energy_{k}": v.numpy() for k, v in self.energies.items()})
        if self.elements is not None:
            arrays["elements"] = self.elements.numpy()
        np.savez_compressed(path, config=json.dumps(asdict(self.config)), pose=json.dumps(asdict(self.pose)),
                            wall_time=self.wall_time, time_convergence=json.dumps(self.time_convergence), **arrays)
        return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")

    @classmethod
    def load(cls, path: str | Path) -> "FEMResult":
        """Read a file written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"FEM result file {path} does not exist")
        with np.load(path, allow_pickle=False) as z:
            missing = {"config", "pose", "rest_vertices", "tets", "trajectory"} - set(z.files)
            if missing:
                raise ValueError(f"{path} is not an FEM result file: missing {sorted(missing)}")
            cfg = json.loads(str(z["config"]))
            cfg["gravity"] = tuple(cfg["gravity"])
            t = lambda k: torch.from_numpy(z[k].copy())  # noqa: E731
            return cls(
                rest_vertices=t("rest_vertices"),
                tets=t("tets"),
                trajectory=t("trajectory"),
                velocities=t("velocities"),
                times=t("times"),
                energies={k[len("energy_") :]: t(k) for k in z.files if k.startswith("energy_")},
                min_det=t("min_det"),
                newton_iterations=t("newton_iterations"),
                line_search_halvings=t("line_search_halvings"),
                inverted_rejections=t("inverted_rejections"),
                config=FEMConfig(**cfg),
                pose=InitialPose(**json.loads(str(z["pose"]))),
                fixed=t("fixed"),
                wall_time=float(z["wall_time"]),
                time_convergence=json.loads(str(z["time_convergence"])) if "time_convergence" in z.files else None,
                elements=t("elements") if "elements" in z.files else None,
            )


def _fixed_mask(fixed, num_vertices: int) -> np.ndarray:
    if fixed is None:
        return np.zeros(num_vertices, dtype=bool)
    f = np.asarray(fixed.detach().cpu() if isinstance(fixed, Tensor) else fixed)
    if f.shape != (num_vertices,) or f.dtype != bool:
        raise ValueError(
            f"fixed must be a boolean mask of shape ({num_vertices},), got shape {f.shape}, dtype {f.dtype}"
        )
    return f


def _mechanical_energy(model: TetFEM, x: np.ndarray, v: np.ndarray) -> dict[str, float]:
    e = model.energy_terms(x)
    e["kinetic"] = 0.5 * float(model.masses @ (v * v).sum(1))
    e["total"] = e["kinetic"] + e["elastic"] + e["gravity"] + e["floor"]
    return e


def simulate_fem(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig | None = None,
                 pose: InitialPose | None = None, frames: int = 24, fixed: Tensor | np.ndarray | None = None,
                 initial_velocity: Tensor | np.ndarray | None = None, progress: bool = True,
                 on_frame: Callable[[], None] | None = None) -> FEMResult:
    """Simulate an elastic tet mesh dropped onto the floor.

    Args:
        vertices: (Nv, 3) rest positions (canonical frame).
        tets: (Nt, 4) positively oriented tets.
        config: FEMConfig (defaults if None).
        pose: initial pose (rotation about the centre of mass, drop height, rigid velocity); None
            keeps the rest positions where they are with zero velocity.
        frames: number of video frames T >= 1 (frame 0 is the initial state; T − 1 frame steps).
        fixed: (Nv,) bool mask of vertices held at their initial positions (Dirichlet), or None.
        initial_velocity: (Nv, 3) velocity overriding the pose's rigid velocity (e.g. a mode shape).
        progress: show a tqdm bar over frames.
        on_frame: called after every simulated frame (progress reporting from another process).

    Returns:
        FEMResult with (T, Nv, 3) trajectory and velocities, energies, Newton statistics.

    Raises:
        FEMSolverError: a step could not be solved (see :meth:`TetFEM.minimize`).
    """
    config = config or FEMConfig()
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    with single_torch_thread():
        return _simulate(vertices, tets, config, pose, frames, fixed, initial_velocity, progress, on_frame)


@contextlib.contextmanager
def single_torch_thread():
    """Run torch on one intra-op thread inside the block (restored after).

    The FEM alternates small torch kernels (per-tet stresses) with numpy/scipy work; with several torch
    threads their OpenMP workers keep spinning through the numpy parts and slow both down (measured 4.5×
    on a 13 000-tet mesh with 2 threads). Parallelism comes from running independent simulations side by
    side instead (:func:`simulate_fem_converged`).
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _simulate(vertices, tets, config: FEMConfig, pose, frames: int, fixed, initial_velocity, progress: bool,
              on_frame: Callable[[], None] | None) -> FEMResult:
    model = TetFEM(vertices, tets, config)
    fixed_np = _fixed_mask(fixed, model.num_vertices)
    free = None if not fixed_np.any() else ~fixed_np
    rest = torch.from_numpy(model.rest)
    if pose is None:
        x0, v0 = rest.clone(), torch.zeros_like(rest)
        pose_used = InitialPose(drop_height=0.0)
    else:
        x0, v0 = pose.apply(rest, torch.from_numpy(model.masses), config.floor_height)
        pose_used = pose
    x, v = x0.numpy().copy(), v0.numpy().copy()
    if initial_velocity is not None:
        iv = np.asarray(initial_velocity.detach().cpu() if isinstance(initial_velocity, Tensor) else initial_velocity,
                        dtype=np.float64)
        if iv.shape != x.shape or not np.isfinite(iv).all():
            raise ValueError(f"initial_velocity must be a finite ({model.num_vertices}, 3) array, got shape {iv.shape}")
        v = iv.copy()
    v[fixed_np] = 0.0
    if not model.min_det(x) > 0:
        raise ValueError("the initial state has inverted tets")

    h = config.dt / config.substeps
    traj, vels, dets = [x.copy()], [v.copy()], [model.min_det(x)]
    energies = {k: [val] for k, val in _mechanical_energy(model, x, v).items()}
    iters = np.zeros((frames - 1, config.substeps), dtype=np.int64)
    halvings = np.zeros(frames - 1, dtype=np.int64)
    rejections = np.zeros(frames - 1, dtype=np.int64)
    start = time.perf_counter()
    history = None
    factor = FactorCache() if config.reuse_factorization else None
    for f in tqdm(range(frames - 1), desc="FEM frames", disable=not progress):
        for s in range(config.substeps):
            try:
                x_new, v_new, stats = model.step(x, v, h, free, history, factor)
                history, x, v = (x, v), x_new, v_new
            except FEMSolverError as err:
                raise FEMSolverError(f"frame {f + 1}, substep {s + 1}/{config.substeps}: {err}") from None
            iters[f, s] = stats.iterations
            halvings[f] += stats.line_search_halvings
            rejections[f] += stats.inverted_rejections
        traj.append(x.copy())
        vels.append(v.copy())
        dets.append(model.min_det(x))
        for k, val in _mechanical_energy(model, x, v).items():
            energies[k].append(val)
        if on_frame is not None:
            on_frame()
    wall = time.perf_counter() - start
    return FEMResult(
        rest_vertices=rest, tets=torch.from_numpy(model.tets), trajectory=torch.from_numpy(np.stack(traj)),
        velocities=torch.from_numpy(np.stack(vels)), times=torch.arange(frames, dtype=torch.float64) * config.dt,
        energies={k: torch.tensor(val, dtype=torch.float64) for k, val in energies.items()},
        min_det=torch.tensor(dets, dtype=torch.float64), newton_iterations=torch.from_numpy(iters),
        line_search_halvings=torch.from_numpy(halvings), inverted_rejections=torch.from_numpy(rejections),
        config=config, pose=pose_used, fixed=torch.from_numpy(fixed_np), wall_time=wall,
        elements=None if model.order == 1 else torch.from_numpy(model.elements))


def simulate_fem_converged(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig | None = None,
                           pose: InitialPose | None = None, frames: int = 24, tolerance: float = 1.0,
                           start_substeps: int | None = None, max_substeps: int = 256,
                           progress: bool = True, workers: int = 1) -> FEMResult:
    """An FEM trajectory converged in time: simulate with n and 2n substeps per frame, doubling n until the
    two trajectories differ by at most ``tolerance`` percent of the object's size (mean over frames 1 … T−1
    of the mean vertex distance, :func:`vid2sim.metrics.trajectory_distance`); return the finer run with
    :attr:`FEMResult.time_convergence` filled in.

    Args:
        vertices, tets, pose, frames: as :func:`simulate_fem`.
        config: FEMConfig; its ``substeps`` is replaced.
        tolerance: largest allowed change under 2× refinement, in percent of the rest bounding-box diagonal.
        start_substeps: the first n; default half of :func:`vid2sim.physics.integrators.auto_substeps` for the
            material (at least 4), so that stiff materials start finer.
        max_substeps: give up (:class:`FEMSolverError`) rather than go beyond this.
        progress: show a progress bar.
        workers: processes for the first pair of runs (n and 2n are independent, so 2 workers take about
            the time of the finer run alone); 1 (default) runs everything in this process. Workers are
            spawned, so a script calling this with ``workers > 1`` needs the usual
            ``if __name__ == "__main__":`` guard.

    Raises:
        FEMSolverError: a step failed, or the tolerance was not met with ``max_substeps``.
    """

    config = config or FEMConfig()
    X = np.asarray(vertices.detach().cpu() if isinstance(vertices, Tensor) else vertices, dtype=np.float64)
    T = np.asarray(tets.detach().cpu() if isinstance(tets, Tensor) else tets)
    size = float(np.linalg.norm(X.max(0) - X.min(0)))
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive percentage, got {tolerance!r}")
    if start_substeps is None:
        length = config.damping_length if config.damping_length is not None else size
        start_substeps = max(4, auto_substeps(config.dt, config.youngs_modulus, config.density, length) // 2)
    n = int(start_substeps)
    if n < 1 or 2 * n > max_substeps:
        raise ValueError(f"start_substeps must be in [1, {max_substeps // 2}], got {start_substeps!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")

    coarse, fine = _simulate_each(X, T, [replace(config, substeps=n), replace(config, substeps=2 * n)], pose,
                                  frames, workers, progress)
    history = []
    total = coarse.wall_time + fine.wall_time
    while True:
        d = trajectory_distance(coarse.trajectory, fine.trajectory, size)
        history.append({"substeps": [n, 2 * n], "mean_percent": round(d.mean, 4), "max_percent": round(d.max, 4)})
        if d.mean <= tolerance:
            fine.time_convergence = {
                "substeps": [n, 2 * n], "kept": 2 * n, "tolerance_percent": tolerance,
                "mean_percent": d.mean, "max_percent": d.max, "per_frame_percent": d.per_frame,
                "measure": "mean over frames 1..T-1 of the mean vertex distance, percent of the rest bounding-box "
                           "diagonal, between the runs with n and 2n substeps",
                "comparisons": history, "wall_time_all_runs": total}
            return fine
        if 4 * n > max_substeps:
            raise FEMSolverError(
                f"the trajectory is not converged in time: {n} and {2 * n} substeps per frame differ by {d.mean:.2f} % "
                f"of the size (tolerance {tolerance} %) and {4 * n} would exceed max_substeps={max_substeps}")
        n, coarse = 2 * n, fine
        (fine,) = _simulate_each(X, T, [replace(config, substeps=2 * n)], pose, frames, 1, progress)
        total += fine.wall_time


def _simulate_each(vertices: np.ndarray, tets: np.ndarray, configs: list[FEMConfig], pose, frames: int,
                   workers: int, progress: bool) -> list[FEMResult]:
    """simulate_fem for each config, in up to ``workers`` processes, with one progress bar over all frames."""
    label = "FEM frames (" + ", ".join(f"{c.substeps} substeps" for c in configs) + ")"
    if workers == 1 or len(configs) == 1:
        with tqdm(total=len(configs) * (frames - 1), desc=label, disable=not progress) as bar:
            return [simulate_fem(vertices, tets, c, pose, frames, progress=False, on_frame=lambda: bar.update())
                    for c in configs]
    import multiprocessing as mp
    from concurrent.futures import wait


    with mp.get_context("spawn").Manager() as manager:
        queue = manager.Queue()
        with process_pool(min(workers, len(configs))) as pool, \
                tqdm(total=len(configs) * (frames - 1), desc=label, disable=not progress) as bar:
            futures = [pool.submit(_simulate_in_worker, vertices, tets, c, pose, frames, queue) for c in configs]
            pending = set(futures)
            while pending:
                _, pending = wait(pending, timeout=0.5)
                while not queue.empty():
                    bar.update(queue.get())
            return [f.result() for f in futures]


def _simulate_in_worker(vertices, tets, config, pose, frames, queue) -> FEMResult:
    return simulate_fem(vertices, tets, config, pose, frames, progress=False, on_frame=lambda: queue.put(1))


@dataclass
class StaticResult:
    """A static equilibrium: positions (Nv, 3) and the Newton statistics of each load step."""

    positions: Tensor
    stats: list[NewtonStats] = field(default_factory=list)


def static_solve(vertices: Tensor | np.ndarray, tets: Tensor | np.ndarray, config: FEMConfig,
                 fixed: Tensor | np.ndarray, load_steps: int = 1) -> StaticResult:
    """Static equilibrium under gravity (and the floor, if configured) with fixed vertices at rest.
    Uses the direct solver unless ``config.linear_solver`` is 'cg'.

    Minimises Σ V Ψ(F) + E_floor − Σ m g·x over the free vertices, applying gravity in ``load_steps``
    equal increments (each solved to convergence) for robustness under large loads.

    Args:
        vertices: (Nv, 3) rest positions.
        tets: (Nt, 4) tets.
        config: FEMConfig (its dt and substeps are unused).
        fixed: (Nv,) bool mask of clamped vertices (at least one; the problem is singular otherwise).
        load_steps: number of gravity increments >= 1.

    Returns:
        StaticResult with the equilibrium positions.
    """
    if not (isinstance(load_steps, int) and load_steps >= 1):
        raise ValueError(f"load_steps must be an integer >= 1, got {load_steps!r}")
    model = TetFEM(vertices, tets, config)
    fixed_np = _fixed_mask(fixed, model.num_vertices)
    if not fixed_np.any():
        raise ValueError("static_solve needs at least one fixed vertex: a free body has no unique equilibrium "
                         "(the frictionless floor leaves horizontal motion unconstrained)")
    g_full = model.gravity.copy()
    x = model.rest.copy()
    all_stats = []
    for i in range(1, load_steps + 1):
        model.gravity = g_full * (i / load_steps)
        x, stats = model.minimize(x, free=~fixed_np)
        all_stats.append(stats)
    return StaticResult(positions=torch.from_numpy(x), stats=all_stats)
