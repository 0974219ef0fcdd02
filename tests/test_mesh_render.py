"""The textured-mesh rasterizer against hand-computed pixels and analytic geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vid2sim.splats.cameras import Camera, camera_ring
from vid2sim.synthetic.mesh_render import (
    render_mesh,
    render_textured_mesh,
    sample_texture,
    vertex_normals,
)
from vid2sim.synthetic.shapes import ProceduralShapeConfig, make_procedural_object

F64 = torch.float64


def axis_camera(size: int, f: float) -> Camera:
    """Camera at the origin looking along +z (OpenCV: x right, y down), principal point at the centre."""
    return Camera(torch.eye(4), Camera.intrinsics(f, f, size / 2, size / 2), size, size)


def square(x_pix, y_pix, depth, f, c, slope=0.0):
    """A quad facing the axis camera covering pixel ranges x_pix × y_pix at ``depth`` (or a plane
    z = depth + slope·x when slope ≠ 0, then x_pix is only a guide). Returns vertices (4, 3), faces,
    uvs with the texture upright in the image: image top-left ↔ uv (0, 1)."""
    xl, xr = [(p - c) * depth / f for p in x_pix]
    yt, yb = [(p - c) * depth / f for p in y_pix]
    pts = [(xl, yt), (xr, yt), (xr, yb), (xl, yb)]  # TL, TR, BR, BL
    v = torch.tensor([[x, y, depth + slope * x] for x, y in pts], dtype=F64)
    faces = torch.tensor([[0, 3, 2], [0, 2, 1]])  # normal towards the camera (−z)
    corner_uv = torch.tensor([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], dtype=F64)
    return v, faces, corner_uv[faces]


TEX2 = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]], dtype=F64)


def test_square_pixels_are_texels_times_lambert():
    f, size = 10.0, 10
    v, faces, uvs = square((1, 9), (1, 9), 2.0, f, 5.0)
    light = (0.0, 1.0, -1.0)  # 45° from the square's normal (0, 0, −1)
    rgb, alpha = render_mesh(v, faces, uvs, TEX2, [axis_camera(size, f)], supersample=1, light_dir=light,
                             ambient=0.3, wrap="clamp")
    assert rgb.shape == (1, 10, 10, 3) and alpha.shape == (1, 10, 10)
    rgb, alpha = rgb[0], alpha[0]
    shade = 0.3 + 0.7 / math.sqrt(2)
    # hand-computed: pixel (1, 1) centre → uv (1/16, 15/16) → texel (0, 0) red; (8, 8) → texel (1, 1) yellow
    assert torch.allclose(rgb[1, 1], torch.tensor([shade, 0, 0], dtype=F64), atol=1e-12)
    assert torch.allclose(rgb[8, 8], torch.tensor([shade, shade, 0], dtype=F64), atol=1e-12)
    assert torch.allclose(rgb[1, 8], torch.tensor([0, shade, 0], dtype=F64), atol=1e-12)
    assert torch.allclose(rgb[8, 1], torch.tensor([0, 0, shade], dtype=F64), atol=1e-12)
    # every inside pixel: bilinear (clamped) lookup at u = (j − 0.5)/8, v = 1 − (i − 0.5)/8
    for i in range(1, 9):
        for j in range(1, 9):
            wx = min(max(2 * (j - 0.5) / 8 - 0.5, 0.0), 1.0)
            wy = min(max(2 * (i - 0.5) / 8 - 0.5, 0.0), 1.0)
            top = TEX2[0, 0] * (1 - wx) + TEX2[0, 1] * wx
            bottom = TEX2[1, 0] * (1 - wx) + TEX2[1, 1] * wx
            assert torch.allclose(rgb[i, j], shade * (top * (1 - wy) + bottom * wy), atol=1e-12), (i, j)
    inside = torch.zeros(10, 10, dtype=torch.bool)
    inside[1:9, 1:9] = True
    assert (alpha[inside] == 1).all() and (alpha[~inside] == 0).all()
    assert (rgb[~inside] == 1).all()  # white background


def test_edge_pixels_alpha_is_coverage():
    f, size, s = 10.0, 10, 4
    colour = torch.tensor([[[0.2, 0.4, 0.6]]], dtype=F64)
    v, faces, uvs = square((1.25, 6.5), (2.6, 5.3), 2.0, f, 5.0)
    rgb, alpha = render_mesh(v, faces, uvs, colour, [axis_camera(size, f)], supersample=s, ambient=1.0)
    rgb, alpha = rgb[0], alpha[0]
    # samples at pixel + (0.125, 0.375, 0.625, 0.875): count those inside each range per pixel
    offs = (np.arange(s) + 0.5) / s

    def cover(lo, hi):
        return torch.tensor([np.mean((p + offs >= lo) & (p + offs <= hi)) for p in range(size)], dtype=F64)

    cx, cy = cover(1.25, 6.5), cover(2.6, 5.3)
    assert cx[1] == 0.75 and cx[6] == 0.5 and cy[2] == 0.5 and cy[5] == 0.25
    want_alpha = cy[:, None] * cx[None, :]
    assert torch.allclose(alpha, want_alpha, atol=1e-12)
    want_rgb = want_alpha[..., None] * colour[0, 0] + (1 - want_alpha[..., None])
    assert torch.allclose(rgb, want_rgb, atol=1e-12)


def test_perspective_correct_uv_on_slanted_quad():
    f, size, c = 32.0, 32, 16.0
    slope, depth = 0.8, 2.0
    half = 0.6
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    v = torch.tensor([[x, y, depth + slope * x] for x, y in corners], dtype=F64)
    faces = torch.tensor([[0, 3, 2], [0, 2, 1]])
    corner_uv = torch.tensor([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], dtype=F64)
    ramp = torch.zeros(1, 64, 3, dtype=F64)
    ramp[0, :, 0] = (torch.arange(64, dtype=F64) + 0.5) / 64  # red = u exactly under bilinear lookup
    rgb, alpha = render_mesh(v, faces, corner_uv[faces], ramp, [axis_camera(size, f)], supersample=1, ambient=1.0,
                             wrap="clamp")
    rgb, alpha = rgb[0], alpha[0]
    # analytic: the ray through pixel centre (px, py) meets z = depth + slope·x at x = t·rx
    px = torch.arange(size, dtype=F64) + 0.5
    rx = (px - c) / f
    t = depth / (1 - slope * rx)
    u_true = ((t * rx + half) / (2 * half))[None, :].expand(size, size)
    ok = (alpha == 1) & (u_true > 1 / 128) & (u_true < 1 - 1 / 128)
    assert int(ok.sum()) > 200
    assert torch.allclose(rgb[..., 0][ok], u_true[ok], atol=1e-9)
    # the test has teeth: screen-space (affine) interpolation along a row differs a lot
    left = c + f * (-half) / (depth - slope * half)
    right = c + f * half / (depth + slope * half)
    u_affine = ((px - left) / (right - left))[None, :].expand(size, size)
    assert float((u_affine[ok] - u_true[ok]).abs().max()) > 0.08


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_triangle_wins(near_first):
    f, size = 16.0, 16
    vn, fn, un = square((2, 10), (2, 10), 2.0, f, 8.0)  # near, red
    vf, ff, uf = square((6, 14), (6, 14), 3.0, f, 8.0)  # far, blue, partly behind the near one
    tex = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], dtype=F64)
    un = un * torch.tensor([0.0, 1.0], dtype=F64) + torch.tensor([0.25, 0.0], dtype=F64)  # red texel
    uf = uf * torch.tensor([0.0, 1.0], dtype=F64) + torch.tensor([0.75, 0.0], dtype=F64)  # blue texel
    parts = [(vn, fn, un), (vf, ff, uf)] if near_first else [(vf, ff, uf), (vn, fn, un)]
    v = torch.cat([parts[0][0], parts[1][0]])
    faces = torch.cat([parts[0][1], parts[1][1] + 4])
    uvs = torch.cat([parts[0][2], parts[1][2]])
    rgb, alpha = render_mesh(v, faces, uvs, tex, [axis_camera(size, f)], supersample=1, ambient=1.0, wrap="clamp")
    rgb = rgb[0]
    red, blue = torch.tensor([1.0, 0, 0], dtype=F64), torch.tensor([0, 0, 1.0], dtype=F64)
    assert torch.allclose(rgb[7, 7], red)  # overlap: the nearer square
    assert torch.allclose(rgb[3, 3], red)
    assert torch.allclose(rgb[12, 12], blue)
    assert torch.allclose(rgb[7, 12], blue)
    assert float(alpha[0, 1, 1]) == 0.0


def test_backface_and_near_plane_culling():
    f, size = 10.0, 10
    v, faces, uvs = square((1, 9), (1, 9), 2.0, f, 5.0)
    back = faces[:, [0, 2, 1]]
    cam = [axis_camera(size, f)]
    _, alpha = render_mesh(v, back, uvs, TEX2, cam)
    assert float(alpha.sum()) == 0.0
    rgb2, alpha2 = render_mesh(v, back, uvs[:, [0, 2, 1]], TEX2, cam, cull_backfaces=False, supersample=1,
                               light_dir=(0, 0, -1), ambient=0.0, wrap="clamp")
    rgb1, _ = render_mesh(v, faces, uvs, TEX2, cam, supersample=1, light_dir=(0, 0, -1), ambient=0.0, wrap="clamp")
    assert float(alpha2.sum()) == 64.0
    assert torch.allclose(rgb2, rgb1)  # two-sided: the flipped normal faces the light like the front side
    # a quad at depth 0.005 lies in front of the near plane (0.01): dropped
    vz = v.clone()
    vz[:, 2] = 0.005
    vz[:, :2] *= 0.005 / 2.0
    _, alpha3 = render_mesh(vz, faces, uvs, TEX2, cam)
    assert float(alpha3.sum()) == 0.0
    # behind the camera: dropped as well
    vb = v.clone()
    vb[:, 2] = -2.0
    _, alpha4 = render_mesh(vb, faces, uvs, TEX2, cam, cull_backfaces=False)
    assert float(alpha4.sum()) == 0.0


def test_sphere_silhouette_and_lambert_shading():
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    d, f, size = 3.0, 64.0, 64
    v = torch.tensor(ico.vertices, dtype=F64) + torch.tensor([0.0, 0.0, d], dtype=F64)
    faces = torch.tensor(ico.faces)
    uvs = torch.full((len(faces), 3, 2), 0.5, dtype=F64)
    white = torch.ones(1, 1, 3, dtype=F64)
    ambient = 0.2
    rgb, alpha = render_mesh(v, faces, uvs, white, [axis_camera(size, f)], supersample=4, ambient=ambient,
                             light_dir=(0.0, 0.0, -1.0))
    # silhouette: a circle of radius f·R / sqrt(d² − R²) pixels (the inscribed polyhedron is ~0.5 % smaller)
    r_img = f / math.sqrt(d * d - 1.0)
    assert float(alpha.sum()) == pytest.approx(math.pi * r_img**2, rel=0.01)
    # Lambert with the light at the camera: shade = ambient + (1 − ambient)·cos θ, θ the angle between the
    # sphere's normal where the pixel's ray hits it and the light direction
    rgb, alpha = rgb[0, :, :, 0], alpha[0]
    for j in [32, 38, 44, 48]:
        px, py = j + 0.5, 32.5
        ray = torch.tensor([(px - 32) / f, (py - 32) / f, 1.0], dtype=F64)
        ray = ray / ray.norm()
        # |t·ray − c|² = 1 with c = (0, 0, d)
        b = float(ray[2]) * d
        t = b - math.sqrt(b * b - (d * d - 1.0))
        n = t * ray - torch.tensor([0.0, 0.0, d], dtype=F64)
        want = ambient + (1 - ambient) * float(-n[2])
        assert float(alpha[32, j]) == 1.0
        assert float(rgb[32, j]) == pytest.approx(want, abs=0.01), j


def test_frames_and_views_batch():
    f, size = 16.0, 16
    v, faces, uvs = square((2, 9), (3, 11), 2.0, f, 8.0)
    shift = torch.tensor([2 * 2.0 / f, 0.0, 0.0], dtype=F64)  # two pixels to the right at depth 2
    frames = torch.stack([v, v + shift])
    cams = [axis_camera(size, f), Camera(torch.eye(4), Camera.intrinsics(f, f, 8.0, 7.0), size, size)]
    rgb, alpha = render_mesh(frames, faces, uvs, TEX2, cams, supersample=2)
    assert rgb.shape == (2, 2, 16, 16, 3) and alpha.shape == (2, 2, 16, 16)
    single, _ = render_mesh(v, faces, uvs, TEX2, cams, supersample=2)
    assert torch.allclose(rgb[:, 0], single)
    assert torch.allclose(rgb[0, 1][:, 2:], rgb[0, 0][:, :-2])  # frame 1 = frame 0 moved 2 px right
    assert torch.allclose(rgb[1, 0][:-1], rgb[0, 0][1:])  # principal point 1 px up


def test_sample_texture_wrap_modes():
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(5, 7, 3, dtype=F64, generator=g)
    uv = torch.rand(100, 2, dtype=F64, generator=g)
    a = sample_texture(tex, uv)
    assert torch.allclose(sample_texture(tex, uv + torch.tensor([1.0, -2.0], dtype=F64)), a)
    # texel centres return texels exactly: texel (i, j) at ((j + .5)/W, 1 − (i + .5)/H)
    i, j = torch.meshgrid(torch.arange(5), torch.arange(7), indexing="ij")
    centres = torch.stack([(j.reshape(-1) + 0.5) / 7, 1 - (i.reshape(-1) + 0.5) / 5], dim=1).to(F64)
    assert torch.allclose(sample_texture(tex, centres, "clamp"), tex.reshape(-1, 3))
    # outside, clamp extends the border texel
    assert torch.allclose(sample_texture(tex, torch.tensor([[-0.3, 1.4]], dtype=F64), "clamp")[0], tex[0, 0])


def test_vertex_normals_of_sphere_are_radial():
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2)
    v = torch.tensor(ico.vertices, dtype=F64)
    n = vertex_normals(v, torch.tensor(ico.faces))
    assert float((n * v).sum(1).min()) > 0.999


def test_procedural_object_render_is_consistent():
    mesh = make_procedural_object(5, ProceduralShapeConfig(target_faces=600, texture_size=64))
    cams = camera_ring(3, 2.0, 20.0, 48, 48, fov_x_deg=45.0)
    rgb, alpha = render_textured_mesh(mesh, cams)
    assert rgb.shape == (3, 48, 48, 3) and rgb.dtype == torch.float32
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1
    assert (rgb[alpha == 0] == 1).all()
    assert float(alpha.mean()) > 0.05
    # every projected vertex lands on a covered pixel (or right next to one on the silhouette)
    for cam, a in zip(cams, alpha):
        pix, _ = cam.project(mesh.vertices)
        ij = pix.floor().long()
        covered = torch.nn.functional.max_pool2d(a[None, None], 3, 1, 1)[0, 0] > 0
        assert covered[ij[:, 1], ij[:, 0]].all()
    # deformed vertices: rendering (T, Nv, 3) with T = 1 equals rendering the mesh itself
    rgb_t, _ = render_textured_mesh(mesh, cams, vertices=mesh.vertices[None])
    assert torch.allclose(rgb_t[:, 0], rgb)


def test_bad_inputs():
    f, size = 10.0, 10
    v, faces, uvs = square((1, 9), (1, 9), 2.0, f, 5.0)
    cam = [axis_camera(size, f)]
    with pytest.raises(ValueError, match=r"uvs must have shape \(Nf, 3, 2\)"):
        render_mesh(v, faces, uvs[:1], TEX2, cam)
    with pytest.raises(ValueError, match="all cameras must share one image size"):
        render_mesh(v, faces, uvs, TEX2, cam + [axis_camera(12, f)])
    with pytest.raises(ValueError, match="supersample must be a positive integer"):
        render_mesh(v, faces, uvs, TEX2, cam, supersample=0)
    with pytest.raises(ValueError, match="shading must be 'smooth' or 'flat'"):
        render_mesh(v, faces, uvs, TEX2, cam, shading="phong")
    with pytest.raises(ValueError, match="cameras must hold at least one Camera"):
        render_mesh(v, faces, uvs, TEX2, [])
    with pytest.raises(ValueError, match=r"faces index vertices in \[4, 7\] but there are 4 vertices"):
        render_mesh(v, faces + 4, uvs, TEX2, cam)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    mesh = make_procedural_object(2, ProceduralShapeConfig(target_faces=600, texture_size=64))
    cams = camera_ring(2, 2.0, 20.0, 64, 64)
    rgb_cpu, a_cpu = render_textured_mesh(mesh, cams)
    rgb_gpu, a_gpu = render_textured_mesh(mesh.to("cuda"), cams)
    assert rgb_gpu.is_cuda
    assert torch.allclose(a_gpu.cpu(), a_cpu, atol=1e-6)
    assert float((rgb_gpu.cpu() - rgb_cpu).abs().mean()) < 1e-4
