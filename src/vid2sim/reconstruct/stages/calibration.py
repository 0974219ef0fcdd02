"""The stiffness calibration of a reconstruction: a tet mesh of the reconstructed solid, and the factor that
brings the skinning subspace's lowest vibration mode to the continuum's.

The skinning subspace is a Rayleigh–Ritz approximation, stiffer than the continuum, so a material fitted with
it comes out soft (docs/architecture.md, "Calibrating the subspace's stiffness"). The reference is quadratic
tets on a mesh of the same solid. A reconstruction has no such mesh; it has interior samples. So:

1. :func:`solid_surface` — the samples are binned on a grid (at most ``cells`` a side), blurred (Gaussian,
   σ = 1.5 cells) and the surface is the level set at half the median density at the points (marching cubes;
   a blurred step is at half its height at the step). The grid is padded, so the surface is closed.
2. fTetWild tetrahedralizes it (:func:`vid2sim.meshing.tetra.tetrahedralize`).
3. quadratic tets give the continuum's lowest frequencies at a grid of ν (:func:`tet_reference`; in a child
   process beside the rest of a reconstruction, :class:`TetReferenceJob`);
4. :func:`vid2sim.physics.modes.stiffness_calibration_curve` compares them with the subspace's (or the lowest
   one at a single ν): the subspace's volumetric locking grows with ν, so the factor is a curve s(ν)
   (:mod:`vid2sim.physics.stiffness_curve`).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from vid2sim.meshing.tetra import largest_connected_part, tet_volumes, tetrahedralize
from vid2sim.physics.modes import (
    CURVE_NUS,
    TWO_FACTOR_MODES,
    stiffness_calibration_curve,
    subspace_frequencies,
)
from vid2sim.physics.tet_modes import LOCAL_MODE_PARTICIPATION, tet_frequency_curve
from vid2sim.reconstruct.config import CalibrationConfig
from vid2sim.reconstruct.runner import Context, ReconstructionError, State
from vid2sim.reconstruct.silhouettes import solid_surface
from vid2sim.reconstruct.stages.points import ObjectPoints, sample_in_voxels
from vid2sim.reconstruct.stages.stage1 import prior_material
from vid2sim.runtime.files import read_json, write_json_atomic, write_text_atomic

RESULT, REFERENCE = "stiffness.json", "stiffness_reference.json"


def tet_reference(points: np.ndarray, nus: tuple[float, ...], k: int, edge_length: float = 0.08,
                  cells: int = 64, seed: int = 0, min_participation: float = LOCAL_MODE_PARTICIPATION) -> dict:
    """The continuum's side of the calibration: quadratic tets on a mesh of the solid ``points`` fill.

    It needs only the interior samples, not the skinning field, so a reconstruction computes it in a child
    process while it trains the networks (:class:`TetReferenceJob`).

    Args:
        points: (N, 3) samples filling the solid (m); nus: the ν grid; k: elastic frequencies per ν.
        edge_length, cells, seed, min_participation: as :func:`calibrate_stiffness`.
    Returns:
        {"nus": list, "k": k, "frequencies": (len(nus), k) nested list of ω at E = ρ = 1, "tets",
        "mesh_volume_m3", "dropped_volume_fraction" (the mesh's pieces other than the largest face-connected one,
        left out: :func:`vid2sim.meshing.tetra.largest_connected_part`), "min_participation", "left_out_modes"
        ({"nu", "omega", "participation"} of the local modes left out below the k-th kept one, at the grid's ν
        nearest 0.3; None when there are none), "seconds"}.
    Raises:
        ValueError: no closed surface could be made from the points.
    """

    t0 = time.perf_counter()
    P = np.asarray(points, dtype=np.float64)
    surface = solid_surface(P, cells=cells, rng=np.random.default_rng(seed))
    if surface is None:
        raise ValueError(f"no closed surface could be made from the {len(P)} interior points for the stiffness "
                         "calibration; switch it off with --no-calibrate-stiffness (calibration.enabled false)")
    mesh = tetrahedralize(surface[0], surface[1], edge_length_fac=edge_length, epsilon=5e-3, name="reconstructed solid")
    # the level set also wraps small blobs of stray samples; as separate pieces (or pieces hinged on a vertex)
    # they would add rigid motions that the eigensolve reports as the lowest "elastic" frequencies
    X, T, dropped = largest_connected_part(mesh.vertices, mesh.tets)
    # a sliver of the hull hinged on a few tets vibrates alone below the body's modes: not the body's stiffness
    left_out: list[dict] = []
    frequencies = tet_frequency_curve(X, T, tuple(float(v) for v in nus), k=k, order=2,
                                      min_participation=min_participation, left_out=left_out)
    middle = min(left_out, key=lambda entry: abs(entry["nu"] - 0.3)) if left_out else None
    middle = middle if middle and middle["omega"] else None
    return {"nus": [float(v) for v in nus], "k": int(k), "frequencies": frequencies.tolist(), "tets": int(len(T)),
            "mesh_volume_m3": float(tet_volumes(X, T).abs().sum()), "dropped_volume_fraction": dropped,
            "min_participation": float(min_participation), "left_out_modes": middle,
            "seconds": time.perf_counter() - t0}


def reference_inputs(points: np.ndarray, arguments: dict) -> str:
    """A digest of :func:`tet_reference`'s inputs (the points' bytes and the other arguments): a stored reference
    is reused only for the same inputs (:func:`stored_reference`)."""
    digest = hashlib.sha256(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    digest.update(json.dumps(arguments, sort_keys=True, default=list).encode())
    return digest.hexdigest()


def _reference_worker(points_path: str, arguments: dict, path: str) -> None:
    """Child process of :class:`TetReferenceJob`: :func:`tet_reference` of the points saved at ``points_path``
    (.npy) into the JSON file ``path``, with the digest of its inputs."""
    torch.set_num_threads(1)
    points = np.load(points_path, allow_pickle=False)
    try:
        out = {"ok": True, "reference": tet_reference(points, **arguments),
               "inputs": reference_inputs(points, arguments)}
    except ValueError as exc:  # a bad input (no surface): reported to the parent as the same error
        out = {"ok": False, "error": str(exc)}
    write_text_atomic(path, json.dumps(out))


class TetReferenceJob:
    """:func:`tet_reference` running in a child process (spawned, one thread) while the caller goes on.

    The child writes its result to ``path`` (JSON) when it is done, so an interrupted reconstruction that is
    resumed finds it there. :meth:`result` waits for it; :meth:`check` raises at once if the child has ended
    without one.

    The points reach the child through a file beside ``path``, not the start-up pipe: Python's spawn writes the
    child's arguments into a pipe whose reading end the parent holds until the write ends, so a payload larger
    than the pipe's buffer (64 KiB) blocks the parent for ever if the child dies while starting. It does when
    the caller's main module starts the reconstruction at import (a script without an
    ``if __name__ == "__main__":`` guard): the spawned child imports that module again, and Python stops it.

    Args:
        points: (N, 3) interior samples; path: where the result is written; arguments: :func:`tet_reference`'s
            other arguments (nus, k, edge_length, cells, seed, min_participation).
    """

    def __init__(self, points: np.ndarray, path: str | Path, **arguments) -> None:
        import multiprocessing

        self.path = Path(path)
        self.path.unlink(missing_ok=True)
        # a hidden name: a transient input, which stage snapshots leave out (runner.StageSnapshots)
        self._points_path = points_path = self.path.parent / f".{self.path.stem}.points.npy"
        np.save(points_path, np.asarray(points, dtype=np.float64))
        context = multiprocessing.get_context("spawn")
        self._process = context.Process(target=_reference_worker, daemon=True,
                                        args=(str(points_path), arguments, str(self.path)))
        self._process.start()

    def running(self) -> bool:
        """Whether the child is still computing."""
        return self._process.is_alive()

    def check(self) -> None:
        """Raise the :meth:`result` error now if the child has ended without writing a result."""
        if not self._process.is_alive() and not self.path.is_file():
            self.result()

    def result(self) -> dict:
        """The reference (:func:`tet_reference`'s dict), after waiting for the child.

        Raises:
            ValueError: the child's (no closed surface). RuntimeError: the child died without a result.
        """
        self._process.join()
        if not self.path.is_file():
            raise RuntimeError(
                f"the stiffness calibration's tet reference process ended with code {self._process.exitcode} and "
                f"wrote no result to {self.path}. It is a spawned process: if the reconstruction was started from a "
                "script, the script's top-level code must be under 'if __name__ == \"__main__\":' (the child imports "
                "the main module again); otherwise see the child's error above, or set "
                "--no-calibrate-stiffness (calibration.enabled false)")
        self._points_path.unlink(missing_ok=True)
        out = json.loads(self.path.read_text())
        if not out["ok"]:
            raise ValueError(out["error"])
        return out["reference"]


def calibrate_stiffness(field, cubature: Tensor, weights: Tensor, points: Tensor | None, poisson_ratio: float,
                        edge_length: float = 0.08, cells: int = 64, seed: int = 0,
                        nus: tuple[float, ...] | None = None, factors: int = 1, reference: dict | None = None,
                        volumetric: str = "pointwise", mass_volumes: Tensor | None = None,
                        min_participation: float = LOCAL_MODE_PARTICIPATION) -> dict:
    """The stiffness factor s of a reconstruction (``Simulator(stiffness_scale=s)``).

    Args:
        field: the trained skinning field (its input frame set: it takes world points).
        cubature: (K, 3) the simulator's cubature points; weights: (K,) their volumes.
        points: (N, 3) the interior samples the subspace was trained on (world frame, m); unused with
            ``reference``.
        poisson_ratio: ν at which both frequencies are compared (the prior's).
        nus: a grid of ν: also measure the curve s(ν) there (None: only at ``poisson_ratio``).
        factors: with ``nus``, 1 (one factor on E) or 2 (a factor on μ and one on λ, matched to the six lowest
            modes; :func:`vid2sim.physics.modes.stiffness_calibration_curve`).
        edge_length: fTetWild's target edge length relative to the bounding-box diagonal (the small preset's
            FEM uses 0.08).
        cells: the surface grid's cells along the longest side.
        reference: :func:`tet_reference` of the same points already computed, for the grid ``nus`` (or
            ``(poisson_ratio,)``) and k = :data:`~vid2sim.physics.modes.TWO_FACTOR_MODES` (two factors) or 1.
        volumetric: the simulator's volumetric term ("pointwise" or "projected"), recorded in the result.
        mass_volumes: (K,) the volumes the simulator lumps its mass on (``Simulator(mass_volumes=)``; None:
            ``weights``): the subspace's frequencies use the simulator's own mass.
        min_participation: the tets' modes that move less than this share of the mass are left out
            (:func:`vid2sim.physics.tet_modes.tet_frequency_curve`); 0 keeps them.
    Returns:
        {"stiffness_scale": s at ``poisson_ratio``, "stiffness_curve": the curve's ``to_dict()`` or None,
        "tets": mesh size, "mesh_volume_m3", "points_volume_ratio" (the mesh's volume over the weights' sum),
        "solid_frequencies": {"nu": the grid, "omega": (len(nu), k) nested list} the reconstructed solid's own
        lowest elastic ω at E = ρ = 1 (rad/s; ``vid2sim evaluate`` compares them with the truth's mesh),
        "min_participation", "left_out_modes" (:func:`tet_reference`'s), "seconds" (the reference's and the
        fit's)}.
    Raises:
        ValueError: no closed surface could be made from the points, or ``reference`` is for another grid.
    """

    t0 = time.perf_counter()
    grid = tuple(float(v) for v in nus) if nus is not None else (float(poisson_ratio),)
    k = TWO_FACTOR_MODES if nus is not None and factors == 2 else 1
    if reference is None:
        if points is None:
            raise ValueError("calibrate_stiffness needs the interior points or their tet reference")
        reference = tet_reference(points.detach().double().cpu().numpy(), grid, k, edge_length, cells, seed,
                                  min_participation)
    if reference["nus"] != list(grid) or reference["k"] != k \
            or reference.get("min_participation") != float(min_participation):
        raise ValueError(f"the tet reference was computed for nu {reference['nus']}, k = {reference['k']} and "
                         f"min_participation {reference.get('min_participation')}, the calibration needs nu "
                         f"{list(grid)}, k = {k} and min_participation {float(min_participation)}")
    frequencies = np.asarray(reference["frequencies"], dtype=float)
    if nus is not None:
        curve = stiffness_calibration_curve(field, cubature, weights, None, None, grid, factors=factors,
                                            reference=frequencies, volumetric=volumetric, mass_volumes=mass_volumes)
        s = curve.at(poisson_ratio)
    else:
        curve = None
        reduced = subspace_frequencies(field, cubature, weights, 1.0, float(poisson_ratio), 1.0, k=1,
                                       volumetric=volumetric, mass_volumes=mass_volumes)[0]
        if not (frequencies[0, 0] > 0 and reduced > 0):
            raise ValueError(f"the lowest elastic frequencies must be positive, got tets {frequencies[0, 0]}, "
                             f"subspace {reduced}")
        s = float((frequencies[0, 0] / reduced) ** 2)
    volume = reference["mesh_volume_m3"]
    return {"stiffness_scale": s, "stiffness_curve": curve.to_dict() if curve is not None else None,
            "tets": reference["tets"], "mesh_volume_m3": volume,
            "dropped_volume_fraction": reference.get("dropped_volume_fraction", 0.0),
            "points_volume_ratio": volume / float(weights.sum()), "volumetric": volumetric,
            "mass": "cubature" if mass_volumes is None else "moments",
            "solid_frequencies": {"nu": list(grid), "omega": frequencies.tolist()},
            "min_participation": float(min_participation), "left_out_modes": reference.get("left_out_modes"),
            "seconds": reference["seconds"] + time.perf_counter() - t0}


# ---- the stage -------------------------------------------------------------------------------------------------


def calibration_points(obj: ObjectPoints, config: CalibrationConfig, seed: int) -> Tensor:
    """(N, 3) samples of the kept voxels of ``obj`` that the calibration's reference mesh is made from."""
    return sample_in_voxels(obj.occupancy, obj.origin.double(), obj.voxel, config.points,
                            torch.Generator().manual_seed(seed))


def stored_reference(path: Path, points: np.ndarray, arguments: dict) -> dict | None:
    """The tet reference a finished :class:`TetReferenceJob` left at ``path`` for these ``points`` and
    :func:`tet_reference` ``arguments`` (a dict of nus, k, edge_length, cells, seed, min_participation), or None."""
    if not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    if not (isinstance(stored, dict) and stored.get("ok") and isinstance(stored.get("reference"), dict)
            and stored.get("inputs") == reference_inputs(points, arguments)):
        return None
    return stored["reference"]


class CalibrationStage:
    """Calibrates the subspace's stiffness (``config.calibration``); writes ``stiffness.json``.

    With a curve over ν (``calibration.nu`` "two_factor" or "curve"), the tet reference needs only the interior
    points: it starts in a child process as soon as the ``points`` stage is loaded (:meth:`start`), runs beside the
    velocity, appearance, Stage I and network stages, and is joined here.
    """

    name = "calibration"
    sections = ("calibration", "simulator", "prior.nu")
    #: 1: the two-factor curve is one regularised fit over the ν grid (was a fit per ν)
    revision = 1

    def __init__(self) -> None:
        self.job: TetReferenceJob | None = None

    def _grid(self, ctx: Context) -> tuple[bool, int]:
        """(whether a curve over ν is wanted, the number of modes its reference needs)."""
        nu = ctx.config.calibration.nu
        return nu != "prior", TWO_FACTOR_MODES if nu == "two_factor" else 1

    def ready(self, state: State) -> bool:
        """Whether :meth:`start` can run (the object's points are loaded)."""
        return state.obj_cpu is not None

    def _reference_inputs(self, ctx: Context, state: State) -> tuple[np.ndarray, dict]:
        """The points and the other arguments of :func:`tet_reference` for this run."""
        cfg = ctx.config
        return (calibration_points(state.obj_cpu, cfg.calibration, cfg.seed).numpy(),
                {"nus": CURVE_NUS, "k": self._grid(ctx)[1], "cells": cfg.calibration.cells, "seed": cfg.seed,
                 "min_participation": cfg.calibration.min_participation})

    def start(self, ctx: Context, state: State) -> None:
        """Start the tet reference in a child process, unless it is not needed or already stored for the same
        inputs (a resumed run, or a run that started from another's snapshot)."""
        cfg = ctx.config
        if not (cfg.calibration.enabled and self._grid(ctx)[0]):
            return
        points, arguments = self._reference_inputs(ctx, state)
        if stored_reference(ctx.path(REFERENCE), points, arguments) is None:
            self.job = TetReferenceJob(points, ctx.path(REFERENCE), **arguments)
            ctx.jobs.append(self.job)

    def title(self, ctx: Context, state: State) -> str | None:
        if not ctx.config.calibration.enabled:
            return None
        return "calibrating the subspace's stiffness against quadratic tets"

    def run(self, ctx: Context, state: State) -> None:
        cfg, obj, cub = ctx.config, state.obj, state.cubature
        curve = self._grid(ctx)[0]
        if curve:
            reference = self.job.result() if self.job is not None else stored_reference(
                ctx.path(REFERENCE), *self._reference_inputs(ctx, state))
            if reference is None:  # start() found it stored; something removed or changed it since
                raise ReconstructionError(f"the stiffness calibration's tet reference {ctx.path(REFERENCE)} is gone or "
                                          "was made from other points; rerun with --restart")
            dense = None
        else:  # one factor at the prior's ν (Stage I may have set it): computed here
            reference, dense = None, calibration_points(state.obj_cpu, cfg.calibration, cfg.seed)
        _, prior_nu = prior_material(cfg, state.stage1)
        record = calibrate_stiffness(state.skinning, obj.points[cub.index], cub.weights, dense, prior_nu,
                                     cells=cfg.calibration.cells, seed=cfg.seed, nus=CURVE_NUS if curve else None,
                                     factors=2 if cfg.calibration.nu == "two_factor" else 1, reference=reference,
                                     volumetric=cfg.simulator.volumetric, mass_volumes=cub.mass_volumes,
                                     min_participation=cfg.calibration.min_participation)
        write_json_atomic(ctx.path(RESULT), record)

    def load(self, ctx: Context, state: State) -> None:
        if self.job is not None:
            ctx.jobs.remove(self.job)
            self.job = None
        state.calibration = (read_json(ctx.path(RESULT), "the stiffness calibration") if ctx.config.calibration.enabled
                             else {"stiffness_scale": 1.0, "stiffness_curve": None})
        state.log["stiffness_calibration"] = state.calibration
