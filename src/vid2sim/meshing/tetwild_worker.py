"""Child-process entry point that runs fTetWild (through pytetwild's compiled extension) on one surface.

Run only by :func:`vid2sim.meshing.tetra.tetrahedralize`, as
``python -m vid2sim.meshing.tetwild_worker IN.npz OUT.npz``, so that a crash inside the C++ mesher (a
segfault, an abort, running out of memory) kills this child rather than the caller, and becomes a
clean :class:`~vid2sim.meshing.tetra.TetrahedralizationError` there.

The compiled ``PyfTetWildWrapper`` extension is loaded straight from pytetwild's install folder:
``import pytetwild`` would import PyVista (a large optional dependency, only used for pytetwild's
PyVista accessors) at package import time. This module deliberately imports nothing but numpy.

Input npz: ``vertices (Nv, 3) float64``, ``faces (Nf, 3) uint32`` and the scalar options
``edge_length_fac``, ``edge_length_abs``, ``epsilon``, ``stop_energy``, ``optimize``,
``num_opt_iter``, ``num_threads``. Output npz: ``vertices (Mv, 3) float64``, ``tets (Mt, 4) int64``.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys

import numpy as np


def load_ftetwild_extension():
    """The ``PyfTetWildWrapper`` extension module of the installed pytetwild (without importing pytetwild)."""
    spec = importlib.util.find_spec("pytetwild")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("pytetwild is not installed (pip install pytetwild)")
    folder = list(spec.submodule_search_locations)[0]
    names = [f for f in os.listdir(folder) if f.startswith("PyfTetWildWrapper") and f.endswith((".so", ".pyd"))]
    if not names:
        raise ImportError(f"pytetwild in {folder} has no compiled PyfTetWildWrapper extension")
    loader = importlib.machinery.ExtensionFileLoader("PyfTetWildWrapper", os.path.join(folder, names[0]))
    module_spec = importlib.util.spec_from_loader("PyfTetWildWrapper", loader)
    module = importlib.util.module_from_spec(module_spec)
    loader.exec_module(module)
    return module


def run(in_path: str, out_path: str) -> None:
    """Tetrahedralize the surface stored in ``in_path`` and write the tet mesh to ``out_path``."""
    data = np.load(in_path, allow_pickle=False)
    ext = load_ftetwild_extension()
    vertices, tets = ext.tetrahedralize_mesh(
        np.ascontiguousarray(data["vertices"], dtype=np.float64),
        np.ascontiguousarray(data["faces"], dtype=np.uint32),
        bool(data["optimize"]),
        False,  # skip_simplify
        float(data["edge_length_fac"]),
        float(data["edge_length_abs"]),
        float(data["epsilon"]),
        float(data["stop_energy"]),
        False,  # coarsen
        int(data["num_threads"]),
        int(data["num_opt_iter"]),
        6,  # log level: minimal
        True,  # quiet
        False,  # vtk ordering
        False,  # disable filtering
        np.empty((0, 3), dtype=np.float64),
        np.empty((0, 4), dtype=np.int32),
        np.empty(0, dtype=np.float64),
    )
    np.savez(out_path, vertices=np.asarray(vertices, dtype=np.float64), tets=np.asarray(tets, dtype=np.int64))


if __name__ == "__main__":  # pragma: no cover - exercised through a subprocess
    if len(sys.argv) != 3:
        sys.exit("usage: python -m vid2sim.meshing.tetwild_worker IN.npz OUT.npz")
    run(sys.argv[1], sys.argv[2])
