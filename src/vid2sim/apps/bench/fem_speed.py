"""Cost of the FEM ground truth and of its Newton Hessian strategy (``vid2sim bench fem``).

Meshes the procedural object of a synthetic-scene preset once with fTetWild, then simulates the
preset's drop on that same mesh twice: with ``FEMConfig.hessian_projection = "on_demand"`` (the default:
exact Hessian, projected only when it gives no descent direction) and with ``"always"`` (every element
tangent projected to PSD each Newton iteration — the baseline, measured in the same run). Reports

- ``fem_seconds`` / ``fem_seconds_always_projected`` and their ratio ``fem_speedup_vs_always_projected``;
- the Newton iterations per substep of each (mean and max; the limit is ``FEMConfig.newton_max_iters``);
- ``trajectory_max_difference_m`` — the largest vertex distance between the two trajectories (both solve
  every step to ``newton_tol``, so it should be of that order).
"""

from __future__ import annotations

from typing import Any

from vid2sim.meshing.tetra import tetrahedralize
from vid2sim.synthetic.fem import simulate_fem
from vid2sim.synthetic.scenes import SyntheticSceneConfig
from vid2sim.synthetic.shapes import make_procedural_object


def run(preset: str = "small", seed: int = 0, frames: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Mesh the preset's object for ``seed`` and time its drop with both Hessian strategies.

    Args:
        preset: synthetic-scene preset ("small" or "full"), which sets the mesh resolution and the drop.
        seed: object and pose seed, as in ``vid2sim make-scene --seed``.
        frames: video frames to simulate (default: the preset's 24).
        progress: tqdm bars over the FEM frames.

    Returns:
        A JSON-ready dict of the figures in the module docstring plus the mesh size and settings.
    """

    config = SyntheticSceneConfig.preset(preset, seed=seed)
    if frames is not None:  # the observed/held-out split does not matter to the FEM
        config = SyntheticSceneConfig.preset(preset, seed=seed, frames=frames,
                                             observed_frames=min(frames, config.observed_frames))
    mesh = make_procedural_object(config.seed)
    tet = tetrahedralize(mesh.vertices, mesh.faces, edge_length_fac=config.tet_edge_length,
                         epsilon=config.tet_envelope, name=mesh.name)
    pose = config.initial_pose()
    results = {mode: simulate_fem(tet.vertices, tet.tets, config.fem_config(hessian_projection=mode), pose,
                                  frames=config.frames, progress=progress)
               for mode in ("on_demand", "always")}
    exact, projected = results["on_demand"], results["always"]
    difference = (exact.trajectory - projected.trajectory).norm(dim=-1).max()
    out: dict[str, Any] = {
        "preset": preset, "seed": seed, "object": mesh.name, "tets": int(len(tet.tets)),
        "vertices": int(len(tet.vertices)), "frames": config.frames, "substeps": config.substeps,
        "fem_seconds": exact.wall_time, "fem_seconds_always_projected": projected.wall_time,
        "fem_speedup_vs_always_projected": projected.wall_time / exact.wall_time,
        "trajectory_max_difference_m": float(difference),
        "newton_max_iters": exact.config.newton_max_iters,
    }
    for mode, suffix in (("on_demand", ""), ("always", "_always_projected")):
        iterations = results[mode].newton_iterations.double()
        out[f"newton_iterations_mean{suffix}"] = float(iterations.mean())
        out[f"newton_iterations_max{suffix}"] = int(iterations.max())
    return out
