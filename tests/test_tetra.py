"""Tetrahedralization: the structured box mesher, mesh cleaning, and fTetWild run in a child process."""

from __future__ import annotations

import math
import stat
import sys

import numpy as np
import pytest
import torch
import trimesh

from vid2sim.meshing.tetra import (
    TetMesh,
    TetrahedralizationError,
    _surface_volume_and_closed,
    boundary_faces,
    box_tet_mesh,
    clean_tet_mesh,
    largest_connected_part,
    tet_volumes,
    tetrahedralize,
)


def _closed_surface_volume(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[float, bool]:
    return _surface_volume_and_closed(vertices.numpy(), faces.numpy())


def test_box_mesh_counts_volumes_and_boundary():
    mesh = box_tet_mesh((1.0, 0.3, 0.2), (5, 3, 2), origin=(0.5, -1.0, 2.0))
    assert mesh.vertices.shape == (6 * 4 * 3, 3)
    assert mesh.tets.shape == (6 * 5 * 3 * 2, 4)
    vol = tet_volumes(mesh.vertices, mesh.tets)
    assert bool((vol > 0).all())
    # every tet of a Kuhn split of a cell has 1/6 of the cell volume
    np.testing.assert_allclose(vol.numpy(), (0.2 * 0.1 * 0.1) / 6, rtol=1e-12)
    assert mesh.volume == pytest.approx(0.06, rel=1e-12)
    np.testing.assert_allclose(mesh.vertices.min(0).values.numpy(), [0.5, -1.0, 2.0])
    np.testing.assert_allclose(mesh.vertices.max(0).values.numpy(), [1.5, -0.7, 2.2])
    faces = mesh.boundary_faces()
    # 2 triangles per boundary quad: 2 (5·3 + 5·2 + 3·2) quads
    assert faces.shape == (2 * 2 * (15 + 10 + 6), 3)
    volume, closed = _closed_surface_volume(mesh.vertices, faces)
    assert closed
    assert volume == pytest.approx(0.06, rel=1e-12)  # positive → outward winding
    tri = mesh.vertices[faces]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1).sum()
    assert float(area) == pytest.approx(2 * (0.3 + 0.2 + 0.06), rel=1e-12)


def test_box_mesh_conforming_interior_faces_shared_twice():
    mesh = box_tet_mesh((1, 1, 1), (3, 2, 2))
    local = torch.tensor([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = torch.sort(mesh.tets[:, local].reshape(-1, 3), dim=1).values
    _, counts = torch.unique(faces, dim=0, return_counts=True)
    assert int(counts.max()) == 2  # no face is shared by three tets (no overlaps)
    n_boundary = int((counts == 1).sum())
    assert n_boundary == mesh.boundary_faces().shape[0]


def test_box_mesh_bad_arguments():
    with pytest.raises(ValueError, match="size"):
        box_tet_mesh((1.0, -0.2, 0.1), (2, 2, 2))
    with pytest.raises(ValueError, match="resolution"):
        box_tet_mesh((1.0, 1.0, 1.0), (2, 0, 2))


def test_clean_reorients_and_drops_unreferenced():
    v = torch.tensor([[9.0, 9, 9], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=torch.float64)
    tets = torch.tensor([[1, 3, 2, 4], [2, 3, 4, 5]])  # first negative, second positive; vertex 0 unused
    assert float(tet_volumes(v, tets)[0]) < 0
    cv, ct, flipped = clean_tet_mesh(v, tets)
    assert flipped == 1
    assert cv.shape == (5, 3)
    assert bool((tet_volumes(cv, ct) > 0).all())
    np.testing.assert_allclose(tet_volumes(cv, ct).abs().numpy(), tet_volumes(v, tets).abs().numpy())


def test_largest_connected_part_drops_floating_and_hinged_pieces():
    from vid2sim.physics.tet_modes import tet_frequency_curve

    body = box_tet_mesh((1.0, 0.5, 0.5), (4, 2, 2))
    blob = box_tet_mesh((0.1, 0.1, 0.1), (1, 1, 1), origin=(2.0, 0.0, 0.0))  # floating
    hinged = box_tet_mesh((0.1, 0.1, 0.1), (1, 1, 1), origin=(1.0, 0.5, 0.5))  # touches the body at one corner
    parts = [body, blob, hinged]
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    v = torch.cat([p.vertices for p in parts])
    t = torch.cat([p.tets + int(o) for p, o in zip(parts, offsets)])
    # merge the hinge's corner into the body's: one shared vertex, no shared face
    at_corner = ((v - torch.tensor([1.0, 0.5, 0.5], dtype=v.dtype)).norm(dim=1) < 1e-12).nonzero()[:, 0]
    assert len(at_corner) == 2
    t[t == int(at_corner[1])] = int(at_corner[0])
    v, t, _ = clean_tet_mesh(v, t)  # drops the hinge's own copy of the corner
    # the whole mesh has the blob's and the hinge's free motions among its lowest modes
    assert tet_frequency_curve(v, t, (0.3,), k=1, order=1)[0, 0] < 1e-4
    kv, kt, dropped = largest_connected_part(v, t)
    assert kt.shape == body.tets.shape and kv.shape == body.vertices.shape
    np.testing.assert_allclose(float(tet_volumes(kv, kt).sum()), 0.25, rtol=1e-12)
    np.testing.assert_allclose(dropped, 2e-3 / 0.252, rtol=1e-9)
    expected = tet_frequency_curve(body.vertices, body.tets, (0.3,), k=1, order=1)
    np.testing.assert_allclose(tet_frequency_curve(kv, kt, (0.3,), k=1, order=1), expected, rtol=1e-9)
    same_v, same_t, none = largest_connected_part(body.vertices, body.tets)
    assert none == 0.0 and torch.equal(same_t, body.tets) and torch.equal(same_v, body.vertices)


def test_clean_rejects_bad_meshes():
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], dtype=torch.float64)
    with pytest.raises(TetrahedralizationError, match="degenerate"):
        clean_tet_mesh(v, torch.tensor([[0, 1, 2, 4]]))  # four coplanar points
    with pytest.raises(TetrahedralizationError, match="indices"):
        clean_tet_mesh(v, torch.tensor([[0, 1, 2, 7]]))
    bad = v.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(TetrahedralizationError, match="NaN"):
        clean_tet_mesh(bad, torch.tensor([[0, 1, 2, 3]]))
    with pytest.raises(ValueError, match="tets"):
        TetMesh(v, torch.zeros((0, 4), dtype=torch.long))


def test_boundary_faces_of_single_tet_point_outward():
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    faces = boundary_faces(torch.tensor([[0, 1, 2, 3]]))
    assert faces.shape == (4, 3)
    centroid = v.mean(0)
    tri = v[faces]
    normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert bool(((normal * (tri.mean(1) - centroid)).sum(1) > 0).all())


@pytest.fixture(scope="module")
def sphere_tets():
    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    return ico, tetrahedralize(ico.vertices, ico.faces, edge_length_fac=0.1, name="icosphere")


def test_tetrahedralize_sphere(sphere_tets):
    ico, mesh = sphere_tets
    assert 300 < mesh.tets.shape[0] < 6000
    vol = tet_volumes(mesh.vertices, mesh.tets)
    assert bool((vol > 0).all())
    assert mesh.surface_volume == pytest.approx(ico.volume, rel=1e-9)
    assert mesh.volume_error < 0.02
    # close to the analytic sphere too (the icosphere's polyhedral volume is 2.6 % smaller)
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * 0.5 ** 3, rel=0.04)
    # every vertex is used and the boundary is a closed outward surface enclosing the tet volume
    assert torch.unique(mesh.tets).numel() == mesh.vertices.shape[0]
    volume, closed = _closed_surface_volume(mesh.vertices, mesh.boundary_faces())
    assert closed and volume == pytest.approx(mesh.volume, rel=1e-9)


def test_tetrahedralize_box_keeps_volume_and_extent():
    box = trimesh.creation.box((0.8, 0.5, 0.3))
    mesh = tetrahedralize(box.vertices, torch.as_tensor(box.faces), edge_length_fac=0.15, name="box")
    assert mesh.volume_error < 0.01
    assert mesh.volume == pytest.approx(0.12, rel=0.01)
    np.testing.assert_allclose(mesh.vertices.max(0).values.numpy(), [0.4, 0.25, 0.15], atol=2e-3)


def test_tetrahedralize_rejects_open_and_garbage_inputs():
    ico = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(TetrahedralizationError, match="open_sphere.*not closed"):
        tetrahedralize(ico.vertices, ico.faces[1:], name="open_sphere")
    with pytest.raises(TetrahedralizationError, match="inside-out.*non-positive volume|non-positive volume"):
        tetrahedralize(ico.vertices, ico.faces[:, ::-1].copy(), name="flipped")
    bad = ico.vertices.copy()
    bad[3] = np.nan
    with pytest.raises(TetrahedralizationError, match="NaN"):
        tetrahedralize(bad, ico.faces)
    with pytest.raises(TetrahedralizationError, match="face indices"):
        tetrahedralize(ico.vertices, ico.faces + 1000)
    with pytest.raises(TetrahedralizationError, match="faces must have shape"):
        tetrahedralize(ico.vertices, ico.faces[:, :2])
    with pytest.raises(TetrahedralizationError, match="integer"):
        tetrahedralize(ico.vertices, ico.faces.astype(np.float64))
    with pytest.raises(ValueError, match="edge_length_fac"):
        tetrahedralize(ico.vertices, ico.faces, edge_length_fac=2.0)


def test_mesher_crash_becomes_clean_error(tmp_path, monkeypatch):
    """A mesher process killed by a signal (as a segfault in fTetWild would be) raises cleanly."""
    fake = tmp_path / "crashing_python"
    fake.write_text("#!/bin/sh\nkill -SEGV $$\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setattr(sys, "executable", str(fake))
    ico = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(TetrahedralizationError, match=r"crashy.*killed by signal 11"):
        tetrahedralize(ico.vertices, ico.faces, name="crashy")


def test_mesher_failure_status_becomes_clean_error(tmp_path, monkeypatch):
    fake = tmp_path / "failing_python"
    fake.write_text("#!/bin/sh\necho 'fTetWild: something went wrong' >&2\nexit 3\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setattr(sys, "executable", str(fake))
    ico = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(TetrahedralizationError, match="status 3.*something went wrong"):
        tetrahedralize(ico.vertices, ico.faces, name="failing")


def test_ctrl_c_in_the_mesher_is_an_interrupt_not_a_meshing_failure(tmp_path, monkeypatch):
    """Ctrl-C reaches the whole process group; a mesher that died of it must not be reported as fTetWild failing."""
    fake = tmp_path / "interrupted_python"
    # SIGINT back to its default first: a test run started in the background inherits it ignored
    fake.write_text(f"#!{sys.executable}\nimport os, signal\nsignal.signal(signal.SIGINT, signal.SIG_DFL)\n"
                    "os.kill(os.getpid(), signal.SIGINT)\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setattr(sys, "executable", str(fake))
    ico = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(KeyboardInterrupt):
        tetrahedralize(ico.vertices, ico.faces, name="interrupted")


def test_a_mesh_with_slivers_is_meshed_again_once(monkeypatch):
    """fTetWild now and then leaves a few zero-volume slivers (4 of 4 732 tets on a reconstructed solid): the surface
    is meshed once more with 3 % shorter target edges and a warning; slivers twice raise."""
    import vid2sim.meshing.tetra as tetra

    box = trimesh.creation.box((1.0, 1.0, 1.0))
    good = box_tet_mesh((1.0, 1.0, 1.0), (2, 2, 2), origin=(-0.5, -0.5, -0.5))
    # a flat tet: three corners of one face and a point on that face
    a, b, c = good.vertices[good.tets[0, 0]], good.vertices[good.tets[0, 1]], good.vertices[good.tets[0, 2]]
    sliver = torch.cat([good.vertices, ((a + b + c) / 3)[None]])
    flat = torch.cat([good.tets, torch.cat([good.tets[0, :3], torch.tensor([sliver.shape[0] - 1])])[None]])
    calls = []

    def fake(v, f, settings, timeout, name):
        calls.append(dict(settings))
        if len(calls) == 1 or always_bad:
            return sliver.numpy(), flat.numpy()
        return good.vertices.numpy(), good.tets.numpy()

    monkeypatch.setattr(tetra, "_run_tetwild", fake)
    always_bad = False
    with pytest.warns(UserWarning, match="1 of 49 tets are degenerate.*meshing it again with 3 % shorter"):
        mesh = tetrahedralize(box.vertices, box.faces, edge_length_fac=0.1)
    assert len(calls) == 2 and calls[1]["edge_length_fac"] == pytest.approx(0.097)
    assert torch.equal(mesh.tets, good.tets) and mesh.volume == pytest.approx(1.0)
    calls.clear()
    always_bad = True
    with pytest.warns(UserWarning), pytest.raises(tetra.DegenerateTetsError, match="degenerate"):
        tetrahedralize(box.vertices, box.faces, edge_length_fac=0.1)
    assert len(calls) == 2
