"""User-mesh loading: seams merged into watertight surfaces, winding repair, clear errors, colours."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from vid2sim.synthetic.mesh_render import sample_texture
from vid2sim.synthetic.meshes import (
    TexturedMesh,
    bake_corner_colors,
    load_user_mesh,
    merge_vertices,
    normalize_to_canonical,
    save_obj,
    surface_report,
)
from vid2sim.synthetic.shapes import ProceduralShapeConfig, make_procedural_object

# six face colours of the test cube, one per signed axis +x, +y, +z, -x, -y, -z
FACE_COLORS = np.array(
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [0, 255, 255], [255, 0, 255]], dtype=np.uint8
)


def _cube_quads(size: float = 2.0):
    """Per face: (signed-axis slot, 4 corners counter-clockwise seen from outside) of [0, size]³."""
    quads = []
    for slot in range(6):
        axis, sign = slot % 3, (1.0 if slot < 3 else -1.0)
        n = np.zeros(3)
        n[axis] = sign
        t1 = np.zeros(3)
        t1[(axis + 1) % 3] = 1.0
        t2 = np.cross(n, t1)
        c = np.full(3, size / 2) + n * size / 2
        corners = [c + size / 2 * (a * t1 + b * t2) for a, b in [(-1, -1), (1, -1), (1, 1), (-1, 1)]]
        quads.append((slot, corners))
    return quads


def _write_cube_obj(path, drop_faces=(), flip_faces=(), size=2.0):
    """A cube with 24 vertices (4 per face: UV seams everywhere) and a 6×4 texel atlas texture."""
    tex = np.zeros((4, 6, 3), dtype=np.uint8)
    for slot in range(6):
        col, row = slot % 3, slot // 3
        tex[2 * row : 2 * row + 2, 2 * col : 2 * col + 2] = FACE_COLORS[slot]
    Image.fromarray(tex).save(path.with_suffix(".png"))
    path.with_suffix(".mtl").write_text(f"newmtl m\nKd 0.8 0.8 0.8\nmap_Kd {path.stem}.png\n")
    lines = [f"mtllib {path.stem}.mtl", "usemtl m"]
    faces, vts = [], []
    for slot, corners in _cube_quads(size):
        if slot in drop_faces:
            continue
        col, row_top = slot % 3, slot // 3
        base = len(vts)
        # UVs inside the texel-centre square of the face's 2×2 cell (v up: image row r ↔ v from the top)
        u0, u1 = (2 * col + 0.5) / 6, (2 * col + 1.5) / 6
        v1, v0 = 1 - (2 * row_top + 0.5) / 4, 1 - (2 * row_top + 1.5) / 4
        for (x, y, z), (u, v) in zip(corners, [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]):
            lines.append(f"v {x} {y} {z}")
            vts.append(f"vt {u} {v}")
        tris = [(0, 1, 2), (0, 2, 3)]
        if slot in flip_faces:
            tris = [(0, 2, 1), (0, 3, 2)]
        for t in tris:
            faces.append("f " + " ".join(f"{base + i + 1}/{base + i + 1}" for i in t))
    path.write_text("\n".join(lines + vts + faces) + "\n")
    return path


def _expected_slot(normal: np.ndarray) -> int:
    axis = int(np.abs(normal).argmax())
    return axis if normal[axis] > 0 else axis + 3


def test_textured_cube_obj_with_seams_becomes_watertight(tmp_path):
    path = _write_cube_obj(tmp_path / "cube.obj")
    mesh = load_user_mesh(path, normalize=False)
    assert mesh.num_vertices == 8 and mesh.num_faces == 12
    rep = surface_report(mesh.vertices.double().numpy(), mesh.faces.numpy())
    assert rep.watertight and rep.consistently_wound and rep.num_components == 1
    assert mesh.volume() == pytest.approx(8.0, rel=1e-6)  # outward: positive, side 2
    # every face's corners look up its own colour, so UVs survived the merge attached to the right faces
    normals = mesh.face_normals().numpy()
    colours = sample_texture(mesh.texture, mesh.uvs.reshape(-1, 2), wrap="clamp").reshape(12, 3, 3).numpy()
    for f in range(12):
        slot = _expected_slot(normals[f])
        np.testing.assert_allclose(colours[f], np.repeat(FACE_COLORS[slot][None] / 255.0, 3, 0), atol=1e-6)
    # texture is the PNG: map_Kd used on its own, Kd 0.8 not multiplied in
    assert mesh.texture.shape == (4, 6, 3) and float(mesh.texture.max()) == pytest.approx(1.0)


def test_normalize_records_similarity(tmp_path):
    path = _write_cube_obj(tmp_path / "cube.obj")
    mesh = load_user_mesh(path)
    v = mesh.vertices.double()
    assert torch.allclose(v.max(0).values + v.min(0).values, torch.zeros(3, dtype=torch.float64), atol=1e-6)
    assert float((v.max(0).values - v.min(0).values).norm()) / 2 == pytest.approx(0.5, abs=1e-6)
    # the recorded transform maps the file's corner (2, 2, 2) to the canonical (+c, +c, +c)
    m = mesh.to_canonical
    corner = m[:3, :3] @ torch.tensor([2.0, 2.0, 2.0], dtype=torch.float64) + m[:3, 3]
    c = 0.5 / np.sqrt(3)
    assert torch.allclose(corner, torch.full((3,), c, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(m[:3, :3], m[0, 0] * torch.eye(3, dtype=torch.float64))


def test_open_mesh_raises_clear_error(tmp_path):
    path = _write_cube_obj(tmp_path / "open_cube.obj", drop_faces=(2,))
    with pytest.raises(ValueError) as err:
        load_user_mesh(path)
    msg = str(err.value)
    assert "open_cube.obj" in msg and "4 boundary edges" in msg and "not watertight" in msg


def test_nonmanifold_mesh_raises(tmp_path):
    import trimesh

    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation((1.0, 1.0, 0.0))  # touches the first box along one edge only
    path = tmp_path / "two_boxes.ply"
    trimesh.util.concatenate([a, b]).export(path)
    with pytest.raises(ValueError, match=r"two_boxes\.ply.*0 boundary edges.*1 non-manifold edges"):
        load_user_mesh(path)


@pytest.mark.parametrize("flip", [(0, 1, 2, 3, 4, 5), (1, 4)])
def test_winding_is_repaired(tmp_path, flip):
    path = _write_cube_obj(tmp_path / "flipped.obj", flip_faces=flip)
    mesh = load_user_mesh(path, normalize=False)
    rep = surface_report(mesh.vertices.double().numpy(), mesh.faces.numpy())
    assert rep.consistently_wound
    assert mesh.volume() == pytest.approx(8.0, rel=1e-6)
    # UV corners were permuted with the faces: colours still match the face normals
    normals = mesh.face_normals().numpy()
    colours = sample_texture(mesh.texture, mesh.uvs.reshape(-1, 2), wrap="clamp").reshape(12, 3, 3).numpy()
    for f in range(12):
        np.testing.assert_allclose(colours[f, 0], FACE_COLORS[_expected_slot(normals[f])] / 255.0, atol=1e-6)


@pytest.mark.parametrize("factor", [(255, 255, 255), (255, 102, 51)])
def test_glb_with_texture_roundtrip(tmp_path, factor):
    """GLB (glTF v-down UVs, flipped by trimesh) keeps UVs on the right faces; baseColorFactor multiplies."""
    import trimesh

    # build the seam-split cube in memory and export it as GLB
    verts, faces, uvs = [], [], []
    for slot, corners in _cube_quads(1.0):
        col, row = slot % 3, slot // 3
        u0, u1 = (2 * col + 0.5) / 6, (2 * col + 1.5) / 6
        v1, v0 = 1 - (2 * row + 0.5) / 4, 1 - (2 * row + 1.5) / 4
        base = len(verts)
        verts += corners
        uvs += [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    tex = np.zeros((4, 6, 3), dtype=np.uint8)
    for slot in range(6):
        tex[2 * (slot // 3) : 2 * (slot // 3) + 2, 2 * (slot % 3) : 2 * (slot % 3) + 2] = FACE_COLORS[slot]
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(tex), baseColorFactor=np.array([*factor, 255], dtype=np.uint8)
    )
    visual = trimesh.visual.TextureVisuals(uv=np.array(uvs), material=material)
    tm = trimesh.Trimesh(np.array(verts), np.array(faces), visual=visual, process=False)
    path = tmp_path / "cube.glb"
    tm.export(path)
    mesh = load_user_mesh(path, normalize=False)
    assert mesh.num_vertices == 8 and mesh.num_faces == 12
    assert mesh.volume() == pytest.approx(1.0, rel=1e-6)
    normals = mesh.face_normals().numpy()
    colours = sample_texture(mesh.texture, mesh.uvs.reshape(-1, 2), wrap="clamp").reshape(12, 3, 3).numpy()
    for f in range(12):
        want = FACE_COLORS[_expected_slot(normals[f])] / 255.0 * np.array(factor) / 255.0
        np.testing.assert_allclose(colours[f, 1], want, atol=1e-6)


def test_ply_vertex_colours_are_baked_exactly(tmp_path):
    import trimesh

    rng = np.random.default_rng(0)
    box = trimesh.creation.box(extents=(1, 2, 3))
    colours = rng.integers(0, 256, (8, 3)).astype(np.uint8)
    box.visual = trimesh.visual.ColorVisuals(box, vertex_colors=np.c_[colours, np.full(8, 255, np.uint8)])
    path = tmp_path / "coloured.ply"
    box.export(path)
    mesh = load_user_mesh(path, normalize=False)
    assert mesh.volume() == pytest.approx(6.0, rel=1e-6)
    # map loaded vertices back to the original ones by position
    orig = np.asarray(box.vertices)
    idx = np.argmin(np.linalg.norm(mesh.vertices.double().numpy()[:, None] - orig[None], axis=2), axis=1)
    want = colours[idx][mesh.faces.numpy()] / 255.0  # (12, 3, 3)
    got = sample_texture(mesh.texture, mesh.uvs.reshape(-1, 2)).reshape(12, 3, 3).numpy()
    np.testing.assert_allclose(got, want, atol=1e-6)
    # inside a face, bilinear lookup reproduces linear interpolation unless the 4th texel was clamped
    w = np.array([0.2, 0.3, 0.5])
    mid_uv = (mesh.uvs * torch.tensor(w, dtype=torch.float32)[None, :, None]).sum(1)
    mid = sample_texture(mesh.texture, mid_uv).numpy()
    fourth = want[:, 1] + want[:, 2] - want[:, 0]
    ok = ((fourth >= 0) & (fourth <= 1)).all(axis=1)
    assert ok.any()
    np.testing.assert_allclose(mid[ok], (w[None, :, None] * want[ok]).sum(1), atol=1e-5)


def test_bake_corner_colors_layout():
    c = np.random.default_rng(1).uniform(0.2, 0.4, (5, 3, 3))  # c1 + c2 - c0 stays inside [0, 1]
    uvs, tex = bake_corner_colors(c)
    assert tex.shape == (4, 6, 3) and uvs.shape == (5, 3, 2)  # 3 columns × 2 rows of 2×2 blocks
    got = sample_texture(torch.from_numpy(tex).double(), torch.from_numpy(uvs).reshape(-1, 2)).reshape(5, 3, 3)
    np.testing.assert_allclose(got.numpy(), c, atol=1e-6)


def test_save_obj_roundtrip(tmp_path):
    mesh = make_procedural_object(3, ProceduralShapeConfig(target_faces=400, texture_size=32))
    path = save_obj(mesh, tmp_path / "obj" / "shape.obj")
    back = load_user_mesh(path, normalize=False)
    assert back.num_faces == mesh.num_faces and back.num_vertices == mesh.num_vertices
    # compare faces through their centroids (the loader may reorder vertices and faces)
    def keyed(m):
        tri = m.vertices.double()[m.faces]
        cen = tri.mean(1).numpy()
        order = np.lexsort(cen.T)
        return cen[order], m.uvs.double().numpy()[order], tri.numpy()[order]

    c0, uv0, t0 = keyed(mesh)
    c1, uv1, t1 = keyed(back)
    np.testing.assert_allclose(c1, c0, atol=1e-6)
    np.testing.assert_allclose(t1, t0, atol=1e-6)  # same corner order: same winding
    np.testing.assert_allclose(uv1, uv0, atol=1e-6)
    np.testing.assert_allclose(back.texture.numpy(), mesh.texture.numpy(), atol=0.5 / 255 + 1e-6)


def test_merge_vertices_tolerance():
    v = np.array([[0, 0, 0], [1e-7, 0, 0], [1, 0, 0], [1, 2e-7, 0], [0, 1, 0]], dtype=np.float64)
    f = np.array([[0, 2, 4], [1, 3, 4]])
    mv, mf = merge_vertices(v, f, 1e-6)
    assert len(mv) == 3
    assert (mf[0] == mf[1]).all()
    mv2, _ = merge_vertices(v, f, 1e-9)
    assert len(mv2) == 5


def test_normalize_to_canonical_maps_points():
    pts = torch.randn(50, 3, dtype=torch.float64) * torch.tensor([3.0, 1.0, 0.5]) + 7.0
    out, m = normalize_to_canonical(pts)
    assert torch.allclose(out, pts @ m[:3, :3].T + m[:3, 3])
    assert 0.5 * float((out.max(0).values - out.min(0).values).norm()) == pytest.approx(0.5)
    assert torch.allclose(out.max(0).values, -out.min(0).values)


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        load_user_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "mesh.stl"
    bad.write_text("solid x\nendsolid x\n")
    with pytest.raises(ValueError, match=r"unsupported mesh format '\.stl'"):
        load_user_mesh(bad)


def test_textured_mesh_validation():
    v = torch.rand(4, 3)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv = torch.rand(2, 3, 2)
    tex = torch.rand(4, 4, 3)
    TexturedMesh(v, f, uv, tex)
    with pytest.raises(ValueError, match=r"uvs must have shape \(Nf, 3, 2\)"):
        TexturedMesh(v, f, torch.rand(2, 2), tex)
    with pytest.raises(ValueError, match=r"faces index vertices in \[0, 4\]"):
        TexturedMesh(v, torch.tensor([[0, 1, 4]]), torch.rand(1, 3, 2), tex)
    with pytest.raises(ValueError, match=r"texture values must lie in \[0, 1\]"):
        TexturedMesh(v, f, uv, tex * 3)


def test_multi_material_obj_is_packed_into_one_texture(tmp_path):
    """Two materials with different texture images: trimesh packs them into one atlas; each face keeps
    its own material's colour."""
    Image.fromarray(np.full((4, 4, 3), [255, 0, 0], np.uint8)).save(tmp_path / "a.png")
    Image.fromarray(np.full((8, 8, 3), [0, 0, 255], np.uint8)).save(tmp_path / "b.png")
    (tmp_path / "two.mtl").write_text("newmtl A\nKd 1 1 1\nmap_Kd a.png\nnewmtl B\nKd 1 1 1\nmap_Kd b.png\n")
    lines, vts, faces, n = ["mtllib two.mtl"], [], [], 0
    for slot, corners in _cube_quads(1.0):
        faces.append(f"usemtl {'A' if slot < 3 else 'B'}")
        for c, (u, v) in zip(corners, [(0.1, 0.1), (0.9, 0.1), (0.9, 0.9), (0.1, 0.9)]):
            lines.append("v {} {} {}".format(*c))
            vts.append(f"vt {u} {v}")
        for tri in [(1, 2, 3), (1, 3, 4)]:
            faces.append("f " + " ".join(f"{n + i}/{n + i}" for i in tri))
        n += 4
    (tmp_path / "two.obj").write_text("\n".join(lines + vts + faces) + "\n")
    mesh = load_user_mesh(tmp_path / "two.obj")
    assert mesh.num_vertices == 8 and mesh.num_faces == 12
    normals = mesh.face_normals().numpy()
    centre_uv = mesh.uvs.mean(dim=1)
    colours = sample_texture(mesh.texture, centre_uv).numpy()
    for f in range(12):
        positive = normals[f].max() > 0.5  # slots 0-2 (+x, +y, +z) use material A
        np.testing.assert_allclose(colours[f], [1, 0, 0] if positive else [0, 0, 1], atol=1e-6)
