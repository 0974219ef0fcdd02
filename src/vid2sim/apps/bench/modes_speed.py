"""Speed of the tet meshes' lowest vibration modes (the stiffness calibration's reference), ``bench speed``.

The stiffness calibration (``reconstruct --calibrate-stiffness``) compares the reduced model's lowest
frequencies with those of quadratic tets on a mesh of the reconstructed solid: 14 000–16 000 tets, about
75 000 degrees of freedom, three eigensolves. This section meshes the synthetic scenes' procedural object of
seed 0 with fTetWild at ``edge`` (relative to the bounding-box diagonal), builds
the quadratic-tet stiffness and mass at E = 1, ν = 0.3, ρ = 1 and times

- ``modes_seconds``: :func:`vid2sim.physics.tet_modes.lowest_elastic_modes` for the 6 lowest elastic
  modes (METIS nested dissection, one sparse LU, rigid motions projected out of Lanczos);
- ``modes_seconds_superlu_mmd``: the baseline, measured in the same run: SciPy's ``eigsh`` in
  shift-invert mode with its own sparse LU (SuperLU's minimum-degree order), 18 pairs with the six rigid
  ones, which is what the calibration did before;
- ``modes_speedup`` (their ratio) and ``modes_max_relative_difference`` (of the 6 frequencies).

Both are single runs (each takes seconds to minutes, so noise is small relative to the figure).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse.linalg as spla
import torch

from vid2sim.meshing.tetra import tetrahedralize
from vid2sim.physics.tet_modes import lowest_elastic_modes, tet_stiffness_and_mass
from vid2sim.synthetic.shapes import make_procedural_object


def run(device: torch.device | None = None, quick: bool = False, edge: float | None = None) -> dict[str, Any]:
    """Time the lowest six elastic modes of a quadratic-tet mesh, new solver against the SuperLU baseline.

    Args:
        device: unused (the eigensolve runs on the CPU); kept for the ``bench speed`` section signature.
        quick: a coarse mesh (edge 0.12, envelope 5e-3) instead of the default edge 0.05, envelope 1e-3
            (14 904 tets, 69 615 degrees of freedom: the size of the calibration's meshes).
        edge: fTetWild's target edge length relative to the bounding-box diagonal (overrides ``quick``).
    Returns:
        the figures in the module docstring plus ``modes_tets`` and ``modes_dof``.
    """

    edge = edge if edge is not None else (0.12 if quick else 0.05)
    envelope = 5e-3 if quick else 1e-3
    surface = make_procedural_object(0)
    mesh = tetrahedralize(surface.vertices, surface.faces, edge_length_fac=edge, epsilon=envelope, name=surface.name)
    K, M, nodes = tet_stiffness_and_mass(mesh.vertices, mesh.tets, 1.0, 0.3, 1.0, order=2)
    K, M = K.tocsc(), M.tocsc()
    t = time.perf_counter()
    w2, _ = lowest_elastic_modes(K, M, nodes, 6)
    new = time.perf_counter() - t
    t = time.perf_counter()
    sigma = -1e-3 * float(K.diagonal().mean() / M.diagonal().mean())
    baseline = np.sort(spla.eigsh(K, k=18, M=M, sigma=sigma, which="LM", ncv=40, return_eigenvectors=False))[6:12]
    old = time.perf_counter() - t
    difference = np.abs(np.sqrt(np.clip(w2, 0, None)) / np.sqrt(np.clip(baseline, 1e-300, None)) - 1.0)
    return {
        "modes_tets": int(len(mesh.tets)),
        "modes_dof": int(K.shape[0]),
        "modes_edge": edge,
        "modes_envelope": envelope,
        "modes_seconds": new,
        "modes_seconds_superlu_mmd": old,
        "modes_speedup": old / new,
        "modes_max_relative_difference": float(difference.max()),
    }
