"""Reconstruct a benchmark scene from its true frame-0 geometry instead of the 4-view hull: a diagnostic that
separates what the geometry costs from what the physics does (docs/results.md, "The 4-view hull's cost").

    vid2sim reconstruct SCENE hull --preset small --share-stages STAGES     # the defaults, keeping snapshots
    python3 scripts/true_geometry.py SCENE STAGES OUT [--threads N]
    vid2sim evaluate OUT SCENE                                               # then compare with hull's

The scene must be a ``make-benchmark`` / ``make-scene`` folder with its FEM truth (``fem_result.npz``). The script
takes the hull run's snapshot after the appearance stage, replaces its object points with the FEM mesh at frame 0
voxelised on the same grid (the same voxel size, so only the shape changes), and runs the remaining stages with
the small preset's defaults from there (``reconstruct(..., snapshots=...)``).
"""

from __future__ import annotations

import argparse
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from vid2sim.reconstruct.config import ReconstructConfig
from vid2sim.reconstruct.pipeline import reconstruct
from vid2sim.reconstruct.runner import StageSnapshots
from vid2sim.reconstruct.stages.points import ObjectPoints, points_from_occupancy


def voxels_inside(vertices: torch.Tensor, tets: torch.Tensor, origin: torch.Tensor, voxel: float,
                  shape: tuple[int, int, int]) -> torch.Tensor:
    """(A, B, C) bool: the voxels of the grid (``origin``, ``voxel``, ``shape``) whose centre lies in a tet
    (``vertices`` (N, 3), ``tets`` (M, 4) corner indices)."""
    A, B, C = shape
    idx = torch.stack(torch.meshgrid(torch.arange(A), torch.arange(B), torch.arange(C), indexing="ij"), -1)
    centres = origin.double() + (idx.reshape(-1, 3).double() + 0.5) * voxel
    inside = torch.zeros(len(centres), dtype=torch.bool)
    for tet in tets:
        P = vertices[tet].double()
        near = ((centres >= P.min(0).values) & (centres <= P.max(0).values)).all(1)
        if not near.any():
            continue
        M = torch.stack([P[1] - P[0], P[2] - P[0], P[3] - P[0]], 1)
        b = torch.linalg.solve(M, (centres[near] - P[0]).T).T  # barycentric coordinates 1-3
        hit = (b >= -1e-9).all(1) & (b.sum(1) <= 1 + 1e-9)
        inside[torch.nonzero(near)[:, 0][hit]] = True
    return inside.reshape(A, B, C)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene"), parser.add_argument("stages"), parser.add_argument("out")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene, out = Path(args.scene), Path(args.out)
    cfg = ReconstructConfig.preset("small")
    found = [p for p in Path(args.stages).iterdir() if p.name.startswith("appearance-")]
    if len(found) != 1:
        raise SystemExit(f"{args.stages}: expected one snapshot of the appearance stage, found {len(found)}")
    snapshots = out.parent / f"{out.name}.snapshots"
    shutil.rmtree(snapshots, ignore_errors=True)
    copy = snapshots / found[0].name
    shutil.copytree(found[0], copy)
    hull = ObjectPoints(**torch.load(copy / "points.pt", weights_only=True))
    fem = np.load(scene / "fem_result.npz")
    occ = voxels_inside(torch.tensor(fem["trajectory"][0]), torch.tensor(fem["tets"]), hull.origin, hull.voxel,
                        tuple(hull.occupancy.shape))
    print(f"hull voxels {int(hull.occupancy.sum())}, true {int(occ.sum())}, true inside the hull "
          f"{int((occ & hull.occupancy).sum())}")
    true = points_from_occupancy(occ, hull.origin, hull.voxel, cfg.points, hull_voxels=int(hull.occupancy.sum()))
    torch.save(asdict(true), copy / "points.pt")
    reconstruct(scene, out, cfg, progress=True, snapshots=StageSnapshots(snapshots, ("appearance",)))
    shutil.rmtree(snapshots, ignore_errors=True)


if __name__ == "__main__":
    main()
