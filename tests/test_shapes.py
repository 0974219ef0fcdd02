"""Procedural shapes (SDF unions → marching cubes) and procedural textures."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vid2sim.synthetic.meshes import surface_report
from vid2sim.synthetic.shapes import (
    PRIMITIVE_KINDS,
    Primitive,
    ProceduralShapeConfig,
    box_projection_uvs,
    make_procedural_object,
    random_primitives,
    random_rotation,
    union_sdf,
)
from vid2sim.synthetic.textures import (
    TEXTURE_KINDS,
    checkers,
    procedural_texture,
    stripes,
    value_noise,
)

SMALL = ProceduralShapeConfig(target_faces=800, texture_size=32)


@pytest.fixture(scope="module")
def shapes():
    return {seed: make_procedural_object(seed, SMALL) for seed in (0, 1, 2, 3)}


def test_shapes_are_closed_oriented_and_normalised(shapes):
    for seed, mesh in shapes.items():
        v = mesh.vertices.double()
        rep = surface_report(v.numpy(), mesh.faces.numpy())
        assert rep.watertight and rep.consistently_wound and rep.num_components == 1, seed
        assert rep.signed_volume > 0
        lo, hi = v.min(0).values, v.max(0).values
        assert torch.allclose(lo + hi, torch.zeros(3, dtype=torch.float64), atol=1e-6)
        assert 0.5 * float((hi - lo).norm()) == pytest.approx(0.5, abs=1e-6)
        assert 0.7 * SMALL.target_faces <= mesh.num_faces <= 1.3 * SMALL.target_faces
        # Euler characteristic of a closed orientable surface is even: V − E + F = 2 − 2g
        chi = mesh.num_vertices - 3 * mesh.num_faces // 2 + mesh.num_faces
        assert chi % 2 == 0 and chi <= 2
        assert float(mesh.uvs.min()) >= 0 and float(mesh.uvs.max()) <= 1
        assert mesh.name == f"procedural-{seed}"


def test_seeded_determinism_and_variety(shapes):
    again = make_procedural_object(1, SMALL)
    assert torch.equal(again.vertices, shapes[1].vertices) and torch.equal(again.faces, shapes[1].faces)
    assert torch.equal(again.texture, shapes[1].texture) and torch.equal(again.uvs, shapes[1].uvs)
    vols = [m.volume() for m in shapes.values()]
    assert len({round(x, 6) for x in vols}) == len(vols)
    assert not torch.equal(shapes[0].texture, shapes[1].texture)


def _to_generator_frame(mesh):
    m = mesh.to_canonical
    scale = float(m[0, 0])
    assert torch.allclose(m[:3, :3], scale * torch.eye(3, dtype=torch.float64))  # a similarity
    return (mesh.vertices.double() - m[:3, 3]) / scale, scale


def test_surface_lies_on_the_sdf_zero_set(shapes):
    """Canonical vertices mapped back to the generator frame sit within half a grid cell of sdf = 0."""
    for seed in (0, 2):
        mesh = shapes[seed]
        prims = random_primitives(np.random.default_rng(seed), SMALL)
        src, _ = _to_generator_frame(mesh)
        d = union_sdf(prims, src.numpy())
        tri = src[mesh.faces]
        h = float((tri[:, 1] - tri[:, 0]).norm(dim=1).mean())  # mean edge length ≈ grid spacing
        assert np.abs(d).max() < 0.5 * h


def test_volume_converges_to_the_sdf_union_volume():
    """The enclosed volume approaches a Monte-Carlo estimate of the SDF union's volume at second order
    in the grid spacing (error ∝ 1/faces): ~5 % at 800 faces, ~1 % at 3200."""
    seed = 0
    prims = random_primitives(np.random.default_rng(seed), SMALL)
    lo = np.min([p.center - p.bounding_radius for p in prims], axis=0)
    hi = np.max([p.center + p.bounding_radius for p in prims], axis=0)
    pts = np.random.default_rng(123).uniform(lo, hi, (400_000, 3))
    mc_volume = float((union_sdf(prims, pts) < 0).mean() * np.prod(hi - lo))
    errors = []
    for faces in (800, 3200):
        mesh = make_procedural_object(seed, ProceduralShapeConfig(target_faces=faces, texture_size=8))
        _, scale = _to_generator_frame(mesh)
        errors.append(abs(mesh.volume() / scale**3 / mc_volume - 1.0))
    assert errors[0] < 0.08 and errors[1] < 0.02
    assert errors[1] < errors[0] / 2.5


def test_primitive_sdfs_are_distances():
    """Each SDF is 0 on its analytic surface, negative inside, and has unit gradient outside."""
    rng = np.random.default_rng(0)
    rot = random_rotation(rng)
    assert np.allclose(rot @ rot.T, np.eye(3)) and np.linalg.det(rot) == pytest.approx(1.0)
    c = np.array([0.1, -0.2, 0.3])
    cases = {
        "sphere": {"r": 0.3},
        "box": {"hx": 0.2, "hy": 0.3, "hz": 0.1, "rounding": 0.03},
        "cylinder": {"r": 0.2, "h": 0.3},
        "capsule": {"r": 0.15, "h": 0.25},
        "torus": {"R": 0.3, "r": 0.1},
    }
    assert set(cases) == set(PRIMITIVE_KINDS)
    surface_points = {
        "sphere": np.array([0.3, 0, 0]),
        "box": np.array([0.2, 0.05, 0.0]),
        "cylinder": np.array([0.0, 0.2, 0.1]),
        "capsule": np.array([0.0, 0.0, 0.4]),
        "torus": np.array([0.4, 0.0, 0.0]),
    }
    for kind, params in cases.items():
        prim = Primitive(kind, c, rot, params)
        on = c + rot @ surface_points[kind]
        assert abs(prim.sdf(on[None])[0]) < 1e-12, kind
        assert prim.sdf((c + rot @ (0.5 * surface_points[kind]))[None])[0] < 0, kind
        # outside points: finite-difference gradient has unit length
        pts = c + rng.normal(size=(20, 3)) * 0.5
        pts = pts[prim.sdf(pts) > 0.05]
        eps = 1e-6
        grad = np.stack([(prim.sdf(pts + eps * e) - prim.sdf(pts - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
        np.testing.assert_allclose(np.linalg.norm(grad, axis=1), 1.0, atol=1e-5, err_msg=kind)
        # every primitive lies inside its bounding ball
        far = c + rng.normal(size=(200, 3)) * prim.bounding_radius * 3
        outside_ball = np.linalg.norm(far - c, axis=1) > prim.bounding_radius
        assert (prim.sdf(far[outside_ball]) > 0).all(), kind


def test_primitives_form_connected_union():
    cfg = ProceduralShapeConfig(n_primitives=(4, 4))
    prims = random_primitives(np.random.default_rng(7), cfg)
    assert len(prims) == 4
    # each new primitive's anchor lies min_overlap deep in the union of the previous ones
    for k in range(1, 4):
        anchor_local = np.array([prims[k].params["R"], 0, 0]) if prims[k].kind == "torus" else np.zeros(3)
        anchor = prims[k].center + prims[k].rotation @ anchor_local
        assert union_sdf(prims[:k], anchor[None])[0] < -cfg.min_overlap


def test_box_projection_uvs_on_a_cube():
    import trimesh

    box = trimesh.creation.box(extents=(1, 1, 1))
    v = torch.tensor(box.vertices, dtype=torch.float64)
    f = torch.tensor(box.faces)
    uv = box_projection_uvs(v, f, margin=0.0)
    n = torch.tensor(box.face_normals)
    for i in range(len(f)):
        axis = int(n[i].abs().argmax())
        slot = axis + (3 if n[i, axis] < 0 else 0)
        col, row = slot % 3, slot // 3
        # the face fills exactly its cell of the 3 × 2 grid
        assert torch.all(uv[i, :, 0] >= col / 3 - 1e-12) and torch.all(uv[i, :, 0] <= (col + 1) / 3 + 1e-12)
        assert torch.all(uv[i, :, 1] >= row / 2 - 1e-12) and torch.all(uv[i, :, 1] <= (row + 1) / 2 + 1e-12)
    # +z face: u grows with x and v with y (no mirroring seen from outside, from above)
    top = torch.nonzero(n[:, 2] > 0.5).squeeze(1)[0]
    corners = v[f[top]]
    uv_top = uv[top]
    assert torch.allclose(uv_top[:, 0], (2 + corners[:, 0] + 0.5) / 3)
    assert torch.allclose(uv_top[:, 1], (corners[:, 1] + 0.5) / 2)


def test_config_validation():
    with pytest.raises(ValueError, match="n_primitives"):
        make_procedural_object(0, ProceduralShapeConfig(n_primitives=(3, 2)))
    with pytest.raises(ValueError, match="kinds must be a non-empty subset"):
        make_procedural_object(0, ProceduralShapeConfig(kinds=("cone",)))
    with pytest.raises(ValueError, match="texture_kind"):
        make_procedural_object(0, ProceduralShapeConfig(texture_kind="plaid"))


# ---- textures ---------------------------------------------------------------------------------
def test_texture_kinds_are_seeded_and_in_range():
    for kind in TEXTURE_KINDS:
        a = procedural_texture(11, 48, kind)
        b = procedural_texture(11, 48, kind)
        c = procedural_texture(12, 48, kind)
        assert a.shape == (48, 48, 3) and a.dtype == torch.float32
        assert torch.equal(a, b) and not torch.equal(a, c)
        assert float(a.min()) >= 0 and float(a.max()) <= 1
        assert float(a.std()) > 0.02  # not a flat colour
    with pytest.raises(ValueError, match="unknown texture kind"):
        procedural_texture(0, 16, "plaid")


def test_stripes_and_checkers_patterns():
    pal = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    s = stripes(16, pal, frequency=4, angle=0.0)  # vertical stripes 4 texels wide
    for j in range(16):
        assert torch.allclose(s[:, j], torch.tensor(pal[(j // 4) % 2], dtype=torch.float32).expand(16, 3))
    c = checkers(12, pal, cells=3)  # 4-texel squares
    for i in range(12):
        for j in range(12):
            assert torch.equal(c[i, j], torch.tensor(pal[(i // 4 + j // 4) % 2], dtype=torch.float32))


def test_value_noise_range_and_smoothness():
    n = value_noise(64, np.random.default_rng(0), base_cells=4, octaves=1)
    assert n.min() == 0.0 and n.max() == 1.0
    # one octave on a 4-cell lattice, 16 texels per cell: smooth (second differences ≪ first differences);
    # for white noise the ratio would be about 2
    d1 = np.abs(np.diff(n, axis=1)).max()
    d2 = np.abs(np.diff(n, n=2, axis=1)).max()
    assert d1 > 0 and d2 < 0.4 * d1
    white = np.random.default_rng(0).uniform(size=(64, 64))
    assert np.abs(np.diff(white, n=2, axis=1)).max() > 1.5 * np.abs(np.diff(white, axis=1)).max()
