"""The observed clip simulated as a function of the physical parameters θ, and worker processes that simulate it
at several θ beside the caller.

The Gauss–Newton fit's Jacobian (:func:`vid2sim.reconstruct.gauss_newton.linearise`) needs p rollouts of the
whole clip besides θ's own, one per parameter, all independent. A rollout is thousands of small tensor operations
(an implicit step of a 132-number state per substep) that torch's intra-op threads barely speed up: on two cores
a second thread took a small-preset rollout from 1.59 to 1.47 s, while a second process simulates another one in
the same time. :class:`RolloutPool` holds such processes (spawned, one torch thread each); :func:`simulate_many`
gives them a fixed share of the θ — the caller simulates the first share itself, on its threads less one per
worker (a thread of its own spinning on a worker's core slowed both) — so the results never depend on which
worker was free. A worker simulates a copy of the simulator (pickled, about 0.2 MB), so results differ from the
caller's by rounding only where the thread counts differ (1e-13 of the state after 16 frames, measured).
"""

from __future__ import annotations

import pickle
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from typing import Any, Sequence

import torch

from vid2sim.physics.external import Floor
from vid2sim.physics.solver import SimState, SimulationError, Simulator
from vid2sim.runtime.workers import process_pool


def floor_friction(sim: Simulator) -> float:
    """The Coulomb coefficient of the simulator's floor (0 without one)."""
    return next((float(e.friction) for e in sim.externals if isinstance(e, Floor)), 0.0)


def set_floor_friction(sim: Simulator, value: float) -> None:
    """Give the simulator's floor(s) the Coulomb coefficient ``value``."""
    sim.externals = [replace(e, friction=value) if isinstance(e, Floor) else e for e in sim.externals]


def rollout_from(sim: Simulator, start: SimState, frames: int, substeps: int | None = None) -> list[SimState]:
    """``start`` and the ``frames`` frames after it, without gradients, at ``substeps`` per frame (None: the
    simulator's automatic count; its configuration is restored). Raises
    :class:`~vid2sim.physics.solver.SimulationError` where the simulation fails."""
    config = sim.config
    if substeps is not None:
        sim.config = replace(config, substeps=substeps)
    try:
        with torch.no_grad():
            return [start] + sim.rollout(start, frames)
    finally:
        sim.config = config


class Attempting:
    """A clip as a function of θ whose ``simulate(θ, substeps)`` may fail: :meth:`attempt` gives None instead. What
    :func:`simulate_many` simulates, pickled for the workers (:class:`ClipSimulation`, or the continuation's window,
    :class:`vid2sim.reconstruct.stages.continuation.WindowSimulation`)."""

    def simulate(self, theta: Sequence[float], substeps: int | None = None) -> Any:
        raise NotImplementedError

    def attempt(self, theta: Sequence[float], substeps: int | None = None) -> Any:
        """:meth:`simulate`, or None where the simulation fails."""
        try:
            return self.simulate(theta, substeps)
        except SimulationError:
            return None


@dataclass
class ClipSimulation(Attempting):
    """Frames 0 … ``frames`` of the clip as a function of θ.

    Attributes:
        sim: the simulator; θ sets its material (and floor friction), the rest of it is fixed.
        names: θ's parameter names (:func:`vid2sim.reconstruct.stages.joint.physical_parameters`): ``log10_E``,
            ``nu``, optionally ``damping_ratio`` and ``floor_friction``, then the initial rigid velocity
            ``linear_velocity_{x,y,z}`` (m/s) and ``angular_velocity_{x,y,z}`` (rad/s).
        centre: (3,) the point the initial angular velocity turns about (m).
        frames: the frames simulated after frame 0.
    """

    sim: Simulator
    names: list[str]
    centre: list[float]
    frames: int

    def apply(self, theta: Sequence[float]) -> SimState:
        """Set the simulator's material from θ; returns the initial state θ's velocity gives."""
        values = dict(zip(self.names, (float(x) for x in theta)))
        with torch.no_grad():
            self.sim.log10_E.fill_(values["log10_E"])
            self.sim.nu.fill_(values["nu"])
            if "damping_ratio" in values:
                self.sim.damping_ratio.fill_(values["damping_ratio"])
        if "floor_friction" in values:
            set_floor_friction(self.sim, values["floor_friction"])
        v = [values[f"linear_velocity_{a}"] for a in "xyz"]
        w = [values[f"angular_velocity_{a}"] for a in "xyz"]
        return self.sim.rigid_velocity_state(v, w, self.centre)

    def substeps(self, theta: Sequence[float]) -> int:
        """The automatic substep count at θ."""
        self.apply(theta)
        return self.sim.substeps()

    def simulate(self, theta: Sequence[float], substeps: int | None = None) -> list[SimState]:
        """Frames 0 … ``frames`` at θ (frame 0 the initial state), ``substeps`` per frame (None: the automatic
        count). Raises :class:`~vid2sim.physics.solver.SimulationError` where the simulation fails."""
        return rollout_from(self.sim, self.apply(theta), self.frames, substeps)


class RolloutPool:
    """``processes`` ≥ 1 worker processes for :func:`simulate_many` (spawned: fresh interpreters that leave with
    this process, :func:`vid2sim.runtime.workers.process_pool`). They start in the background when the pool is
    made; use it as a context manager, or :meth:`close` it."""

    def __init__(self, processes: int) -> None:
        if processes < 1:
            raise ValueError(f"RolloutPool: processes must be >= 1, got {processes}")
        self.processes = processes
        self._executor = process_pool(processes)
        for _ in range(processes):  # the workers start now and import torch while the caller works
            self._executor.submit(_ready)

    def submit(self, blob: bytes, thetas: list[list[float]], substeps: int | None):
        """A future of :func:`_simulate_share`'s result (pickled trajectories) for ``thetas``."""
        return self._executor.submit(_simulate_share, blob, thetas, substeps)

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "RolloutPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def spare_threads() -> int:
    """The rollout worker processes the commands start: torch's threads beyond the first (``--threads`` less one)."""
    return max(0, torch.get_num_threads() - 1)


def shares(n: int, parts: int) -> list[tuple[int, int]]:
    """``n`` items cut into ``parts`` contiguous (start, end) ranges, the first ones one longer where n does not
    divide; empty ranges left out."""
    base, extra = divmod(n, parts)
    out, start = [], 0
    for k in range(parts):
        end = start + base + (1 if k < extra else 0)
        if end > start:
            out.append((start, end))
        start = end
    return out


def simulate_many(simulation: Attempting, thetas: Sequence[Sequence[float]], substeps: int | None = None,
                  pool: RolloutPool | None = None) -> list[Any]:
    """Each θ's trajectory (``simulation.attempt``, e.g. :meth:`ClipSimulation.attempt`: None where the simulation
    fails), in order.

    With a ``pool`` of k processes the θ are cut into k + 1 contiguous shares (:func:`shares`): this process
    simulates the first, each worker one of the others, all at once. The simulator is left at an arbitrary θ."""
    thetas = [[float(x) for x in theta] for theta in thetas]
    if pool is None or len(thetas) < 2:
        return [simulation.attempt(theta, substeps) for theta in thetas]
    cuts = shares(len(thetas), pool.processes + 1)
    blob = pickle.dumps(simulation)
    try:
        futures = [pool.submit(blob, thetas[a:b], substeps) for a, b in cuts[1:]]
        a, b = cuts[0]
        threads = torch.get_num_threads()
        torch.set_num_threads(max(1, threads - pool.processes))  # the workers' cores: a thread here would spin there
        try:
            out = [simulation.attempt(theta, substeps) for theta in thetas[a:b]]
        finally:
            torch.set_num_threads(threads)
        for future in futures:
            out.extend(pickle.loads(future.result()))
    except BrokenProcessPool as exc:
        raise RuntimeError(
            "the rollout worker processes ended before they answered: a script that starts the reconstruction must "
            "do so under `if __name__ == \"__main__\":` (worker processes are spawned, and import the script "
            "again), or pass rollout_processes=0") from exc
    return out


def _ready() -> bool:
    return True


def _simulate_share(blob: bytes, thetas: list[list[float]], substeps: int | None) -> bytes:
    """In a worker: the pickled simulation ``blob`` (:class:`Attempting`) simulated at each θ with one torch thread;
    the trajectories (or None) pickled (tensors inline, not through shared memory)."""
    torch.set_num_threads(1)
    simulation: Attempting = pickle.loads(blob)
    return pickle.dumps([simulation.attempt(theta, substeps) for theta in thetas])
