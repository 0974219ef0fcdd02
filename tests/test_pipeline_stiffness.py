"""The reconstruction's stiffness calibration: a closed surface of the sampled solid, its tets, and the factor."""

import numpy as np
import pytest
import torch

from vid2sim.meshing.tetra import box_tet_mesh
from vid2sim.physics import SkinningField, SkinningTrainingConfig, train_skinning
from vid2sim.physics.modes import stiffness_calibration
from vid2sim.reconstruct.stages.calibration import calibrate_stiffness, solid_surface

BAR = (1.2, 0.4, 0.4)


def _bar(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(BAR, dtype=torch.float64)


def test_solid_surface_is_closed_outward_and_encloses_the_solid():
    verts, faces = solid_surface(_bar(100000, 0).numpy(), cells=48)
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6
    assert volume == pytest.approx(np.prod(BAR), rel=0.05)  # positive: the normals point outward
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert set(counts) == {2}  # closed: every edge shared by two triangles
    assert np.allclose(verts.min(0), -np.array(BAR) / 2, atol=0.03) and np.allclose(
        verts.max(0), np.array(BAR) / 2, atol=0.03
    )
    assert solid_surface(np.zeros((3, 3))) is None


def test_calibration_from_samples_matches_the_one_from_a_mesh_of_the_solid():
    """The factor from 200 000 samples of a bar (surface, fTetWild, quadratic tets) agrees with the one from
    a structured tet mesh of the same bar to a few percent (the smoothed edges and corners are the difference).
    Both sides calibrate the same subspace, so it needs only a short training (60 iterations: the factor 0.91,
    against 0.92 after 150; the two agree to 0.8 % either way)."""
    field = SkinningField(num_handles=4, seed=0).double()
    train_skinning(
        field,
        _bar(20000, 1),
        SkinningTrainingConfig(iterations=60, points_per_step=500, objective="modal"),
        progress=False,
        volume=float(np.prod(BAR)),
    )
    cubature = _bar(2000, 2)
    weights = torch.full((2000,), float(np.prod(BAR)) / 2000, dtype=torch.float64)
    mesh = box_tet_mesh(BAR, (12, 4, 4))
    exact = stiffness_calibration(field, cubature, weights, mesh.vertices, mesh.tets, 0.3)  # frequencies: any origin
    out = calibrate_stiffness(field, cubature, weights, _bar(200000, 3), 0.3, cells=96)
    assert 0.3 < exact < 1.0
    assert out["stiffness_scale"] == pytest.approx(exact, rel=0.05)
    assert out["points_volume_ratio"] == pytest.approx(1.0, abs=0.03)
    # the solid's own lowest mode (what evaluate compares with a truth's mesh): the bar's, corners smoothed
    from vid2sim.physics.tet_modes import tet_frequencies

    assert out["solid_frequencies"]["nu"] == [0.3]
    bar = tet_frequencies(mesh.vertices, mesh.tets, 1.0, 0.3, 1.0, k=1, order=2)[0]
    assert out["solid_frequencies"]["omega"][0][0] == pytest.approx(bar, rel=0.05)
    # two factors over a grid of ν (ReconstructConfig.calibration_nu = "two_factor"): the curve keeps λ's own factor
    # (its form only: a coarse surface and mesh, 1 000 tets against 2 600 from 200 000 samples at 48 cells and 0.08)
    two = calibrate_stiffness(field, cubature, weights, _bar(20000, 3), 0.3, cells=16, edge_length=0.12,
                              nus=(0.3, 0.45), factors=2)
    curve = two["stiffness_curve"]
    assert curve["nu"] == [0.3, 0.45] and len(curve["lam_scale"]) == 2 and all(v > 0 for v in curve["lam_scale"])
    assert two["stiffness_scale"] == pytest.approx(curve["scale"][0], rel=1e-9)
    with pytest.raises(ValueError, match="no closed surface"):
        calibrate_stiffness(field, cubature, weights, _bar(3, 4), 0.3)


def test_the_tet_reference_runs_in_a_child_process_and_feeds_the_calibration(tmp_path):
    """TetReferenceJob: the same reference as in this process (fTetWild's meshes differ run to run in their last
    tets, so to 1 %), written to its file; calibrate_stiffness takes it instead of the points and checks its grid
    and its rule for local modes; the child's bad-input error comes back as the same ValueError. A coarse mesh
    (20 000 samples, 16 cells, edge length 0.12: 1 000 quadratic tets) keeps it short: run to run its frequencies
    moved by 0.12 %, as at 100 000 samples, 32 cells and 0.08."""
    from vid2sim.physics.tet_modes import LOCAL_MODE_PARTICIPATION
    from vid2sim.reconstruct.stages.calibration import TetReferenceJob, stored_reference, tet_reference

    points = _bar(20000, 3).numpy()
    job = TetReferenceJob(points, tmp_path / "ref.json", nus=(0.3, 0.45), k=6, cells=16, edge_length=0.12)
    here = tet_reference(points, (0.3, 0.45), 6, cells=16, edge_length=0.12)
    there = job.result()
    assert not job.running()
    assert (tmp_path / "ref.json").is_file() and there["nus"] == [0.3, 0.45] and there["k"] == 6
    assert np.allclose(there["frequencies"], here["frequencies"], rtol=0.01)
    field = SkinningField(num_handles=4, seed=0).double()
    cubature = _bar(800, 2)
    weights = torch.full((800,), float(np.prod(BAR)) / 800, dtype=torch.float64)
    out = calibrate_stiffness(field, cubature, weights, None, 0.3, nus=(0.3, 0.45), factors=2, reference=there)
    assert out["tets"] == there["tets"] and out["stiffness_curve"]["nu"] == [0.3, 0.45]
    with pytest.raises(ValueError, match="computed for nu"):
        calibrate_stiffness(field, cubature, weights, None, 0.3, nus=(0.3, 0.4), factors=2, reference=there)
    # the local modes' rule is part of the reference: another rule's calibration refuses it, a resumed run ignores it
    assert there["min_participation"] == LOCAL_MODE_PARTICIPATION and there["left_out_modes"] is None  # a bar: none
    assert out["left_out_modes"] is None and out["min_participation"] == LOCAL_MODE_PARTICIPATION
    with pytest.raises(ValueError, match="min_participation"):
        calibrate_stiffness(field, cubature, weights, None, 0.3, nus=(0.3, 0.45), factors=2, reference=there,
                            min_participation=0.0)
    # stored with a digest of its inputs: reused for the same points and arguments only
    arguments = {"nus": (0.3, 0.45), "k": 6, "cells": 16, "edge_length": 0.12}
    assert stored_reference(tmp_path / "ref.json", points, arguments) == there
    assert stored_reference(tmp_path / "ref.json", points, {**arguments, "cells": 48}) is None
    assert stored_reference(tmp_path / "ref.json", points, {**arguments, "min_participation": 0.0}) is None
    assert stored_reference(tmp_path / "ref.json", points[1:], arguments) is None
    with pytest.raises(ValueError, match="no closed surface"):
        TetReferenceJob(np.zeros((3, 3)), tmp_path / "bad.json", nus=(0.3,), k=1).result()
