"""A z-buffer rasterizer for textured triangle meshes in pure PyTorch (CPU or CUDA, no gradients).

What it computes, per camera and frame:

* Samples: with ``supersample = s`` every pixel holds s × s samples on a regular grid; sample
  (a, b) of pixel (i, j) sits at pixel coordinates ``(j + (b + 0.5)/s, i + (a + 0.5)/s)`` (pixel
  centres at +0.5, as in :class:`vid2sim.splats.cameras.Camera`). The output pixel is the box-filter
  mean of its samples, and alpha is the fraction of its samples that a triangle covers.
* Coverage: a sample belongs to a triangle when its three screen-space barycentric coordinates are
  ≥ 0. Of all triangles covering it, the one with the smallest camera depth z wins (depth is
  interpolated as 1/z, which is linear in screen space); exact ties go to the lower face index.
* Culling: triangles with a vertex closer to the camera than ``near`` (or behind it) are dropped
  whole — they are not clipped — so keep objects in front of the cameras. With
  ``cull_backfaces=True`` (the default, right for closed outward-wound surfaces) triangles facing
  away from the camera are dropped too; otherwise they are drawn with their normal flipped
  towards the camera (two-sided lighting).
* Texture: UVs are interpolated perspective-correctly (barycentrics weighted by 1/z and
  renormalised) and looked up bilinearly with OBJ/OpenGL conventions: u right, v up, (0, 0) the
  bottom-left corner of the image, texel centres at ((j + 0.5)/Wt, 1 − (i + 0.5)/Ht). Outside
  [0, 1] the texture repeats (``wrap="repeat"``, the OBJ/glTF default) or its border is
  extended (``wrap="clamp"``).
* Light: one directional light fixed in the world frame (z up), so shading follows the surface as
  it deforms: ``colour = texture · (ambient + (1 − ambient) · max(0, n · l))`` with ``l`` the unit
  direction towards the light (default from above and slightly to the side) and ``n`` the unit
  normal — the interpolated area-weighted vertex normal (``shading="smooth"``) or the face normal
  (``"flat"``). The shaded colour never exceeds the texture colour.
* Background: white; the result is RGB composited on white (``rgb = α·colour + (1 − α)``
  per sample, then box-filtered) plus the separate alpha.

Work is vectorised over triangles: every triangle enumerates the samples of its screen bounding
box (a ragged enumeration, no padding), in chunks of at most ``chunk_size`` candidate samples, and
the z-test is a single ``scatter_reduce(amin)`` on keys packing the float32 depth bits above the
face index.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ..splats.cameras import Camera

_INT64_MAX = torch.iinfo(torch.int64).max
DEFAULT_LIGHT_DIR = (0.35, 0.25, 1.0)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted unit vertex normals (Nv, 3) of ``vertices`` (Nv, 3) and ``faces`` (Nf, 3)."""
    tri = vertices[faces]
    fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 · area
    vn = torch.zeros_like(vertices)
    vn.index_add_(0, faces.reshape(-1), fn.repeat_interleave(3, dim=0))
    return vn / vn.norm(dim=1, keepdim=True).clamp_min(1e-30)


def sample_texture(texture: Tensor, uv: Tensor, wrap: str = "repeat") -> Tensor:
    """Bilinear texture lookup.

    Args:
        texture: (Ht, Wt, C) image, row 0 at the top.
        uv: (N, 2) coordinates, u right and v up, (0, 0) the image's bottom-left corner.
        wrap: ``"repeat"`` or ``"clamp"`` for coordinates outside [0, 1].

    Returns:
        (N, C) interpolated values.
    """
    if wrap not in ("repeat", "clamp"):
        raise ValueError(f"wrap must be 'repeat' or 'clamp', got {wrap!r}")
    ht, wt = texture.shape[0], texture.shape[1]
    x = uv[:, 0] * wt - 0.5
    y = (1.0 - uv[:, 1]) * ht - 0.5
    x0f, y0f = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0f)[:, None], (y - y0f)[:, None]
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = x0 + 1, y0 + 1
    if wrap == "repeat":
        x0, x1, y0, y1 = x0 % wt, x1 % wt, y0 % ht, y1 % ht
    else:
        x0, x1 = x0.clamp(0, wt - 1), x1.clamp(0, wt - 1)
        y0, y1 = y0.clamp(0, ht - 1), y1.clamp(0, ht - 1)
    flat = texture.reshape(ht * wt, -1)
    c00, c01 = flat[y0 * wt + x0], flat[y0 * wt + x1]
    c10, c11 = flat[y1 * wt + x0], flat[y1 * wt + x1]
    return (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy


def _check_inputs(vertices: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor, cameras: Sequence[Camera]) -> None:
    if vertices.ndim not in (2, 3) or vertices.shape[-1] != 3:
        raise ValueError(f"mesh_vertices must have shape (Nv, 3) or (T, Nv, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (Nf, 3), got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[-2]):
        raise ValueError(
            f"faces index vertices in [{int(faces.min())}, {int(faces.max())}] but there are {vertices.shape[-2]} vertices"
        )
    if uvs.shape != (faces.shape[0], 3, 2):
        raise ValueError(f"uvs must have shape (Nf, 3, 2) = ({faces.shape[0]}, 3, 2), got {tuple(uvs.shape)}")
    if texture.ndim != 3 or texture.shape[2] != 3 or min(texture.shape[:2]) < 1:
        raise ValueError(f"texture must have shape (Ht, Wt, 3), got {tuple(texture.shape)}")
    if len(cameras) == 0:
        raise ValueError("cameras must hold at least one Camera")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"all cameras must share one image size, got {sorted(sizes)}")
    if not torch.isfinite(vertices).all():
        raise ValueError("mesh_vertices contain NaN or infinite values")


@torch.no_grad()
def _rasterize(
    cam_xyz: Tensor, faces: Tensor, K: Tensor, width: int, height: int, near: float, cull_backfaces: bool,
    chunk_size: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Z-buffer over the s× sample grid (``K``, ``width``, ``height`` already scaled by s).

    Returns:
        face_id: (height·width,) long, winning face or -1.
        coef: (Nf, 3, 3) screen-space barycentric plane coefficients (a, b, c) per corner.
        inv_z: (Nf, 3) 1/z of the corners.
        front: (Nf,) bool, whether each face faces the camera.
    """
    dev = cam_xyz.device
    nf = faces.shape[0]
    z = cam_xyz[:, 2]
    px = K[0, 0] * cam_xyz[:, 0] / z + K[0, 2]
    py = K[1, 1] * cam_xyz[:, 1] / z + K[1, 2]
    fz = z[faces]  # (Nf, 3)
    valid = (fz > near).all(dim=1)
    tri = cam_xyz[faces]
    n_cam = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = (n_cam * tri[:, 0]).sum(dim=1) < 0
    if cull_backfaces:
        valid &= front
    fx, fy = px[faces], py[faces]  # (Nf, 3)
    # barycentric of corner i is the edge function of the opposite edge (j, k), divided by the area
    j, k = [1, 2, 0], [2, 0, 1]
    ex, ey = fx[:, k] - fx[:, j], fy[:, k] - fy[:, j]  # (Nf, 3)
    area = (fx[:, 1] - fx[:, 0]) * (fy[:, 2] - fy[:, 0]) - (fy[:, 1] - fy[:, 0]) * (fx[:, 2] - fx[:, 0])
    valid &= area.abs() > 1e-9
    safe_area = torch.where(valid, area, torch.ones_like(area))[:, None]
    coef = torch.stack([-ey / safe_area, ex / safe_area, (ey * fx[:, j] - ex * fy[:, j]) / safe_area], dim=2)
    inv_z = 1.0 / torch.where(valid[:, None], fz, torch.ones_like(fz))

    # sample X covers [X, X+1) with its centre at X + 0.5
    x_lo = torch.ceil(fx.min(dim=1).values - 0.5).clamp(min=0)
    x_hi = torch.floor(fx.max(dim=1).values - 0.5).clamp(max=width - 1)
    y_lo = torch.ceil(fy.min(dim=1).values - 0.5).clamp(min=0)
    y_hi = torch.floor(fy.max(dim=1).values - 0.5).clamp(max=height - 1)
    valid &= (x_hi >= x_lo) & (y_hi >= y_lo)
    ids = torch.nonzero(valid).squeeze(1)
    face_id = torch.full((height * width,), -1, dtype=torch.long, device=dev)
    if ids.numel() == 0:
        return face_id, coef, inv_z, front
    bw = (x_hi[ids] - x_lo[ids] + 1).long()
    bh = (y_hi[ids] - y_lo[ids] + 1).long()
    counts = bw * bh
    ends = torch.cumsum(counts, 0)
    zbuf = torch.full((height * width,), _INT64_MAX, dtype=torch.long, device=dev)
    coef_v, inv_z_v = coef[ids], inv_z[ids]
    xlo_v, ylo_v = x_lo[ids].long(), y_lo[ids].long()
    start = 0
    total = int(ends[-1])
    done = 0
    while done < total:
        # next chunk: whole triangles whose candidates fit in chunk_size (at least one triangle)
        stop = int(torch.searchsorted(ends, done + chunk_size, right=True))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        cnt = counts[sl]
        m = stop - start
        local_tri = torch.repeat_interleave(torch.arange(m, device=dev), cnt)
        first = torch.cumsum(cnt, 0) - cnt
        local = torch.arange(int(cnt.sum()), device=dev) - first[local_tri]
        w = bw[sl][local_tri]
        sx = xlo_v[sl][local_tri] + local % w
        sy = ylo_v[sl][local_tri] + torch.div(local, w, rounding_mode="floor")
        cx = sx.to(cam_xyz.dtype) + 0.5
        cy = sy.to(cam_xyz.dtype) + 0.5
        c = coef_v[sl][local_tri]  # (M, 3, 3)
        b = c[:, :, 0] * cx[:, None] + c[:, :, 1] * cy[:, None] + c[:, :, 2]
        inside = (b >= 0).all(dim=1)
        iz = (b * inv_z_v[sl][local_tri]).sum(dim=1)
        inside &= iz > 0
        depth = (1.0 / iz[inside]).to(torch.float32)
        key = (depth.view(torch.int32).to(torch.long) << 32) | ids[sl][local_tri[inside]]
        zbuf.scatter_reduce_(0, (sy * width + sx)[inside], key, reduce="amin", include_self=True)
        done = int(ends[stop - 1])
        start = stop
    hit = zbuf != _INT64_MAX
    face_id[hit] = zbuf[hit] & 0xFFFFFFFF
    return face_id, coef, inv_z, front


@torch.no_grad()
def render_mesh(
    mesh_vertices: Tensor,
    faces: Tensor,
    uvs: Tensor,
    texture: Tensor,
    cameras: Sequence[Camera],
    supersample: int = 2,
    light_dir: Sequence[float] | Tensor = DEFAULT_LIGHT_DIR,
    ambient: float = 0.3,
    shading: str = "smooth",
    near: float = 0.01,
    cull_backfaces: bool = True,
    wrap: str = "repeat",
    chunk_size: int = 1 << 21,
    progress: bool = False,
) -> tuple[Tensor, Tensor]:
    """Render a textured triangle mesh (optionally a sequence of deformed copies) from cameras.

    Args:
        mesh_vertices: (Nv, 3) world positions, or (T, Nv, 3) for T frames of a deforming mesh.
        faces: (Nf, 3) long vertex indices (counter-clockwise seen from outside).
        uvs: (Nf, 3, 2) per-corner texture coordinates (u right, v up).
        texture: (Ht, Wt, 3) RGB in [0, 1], row 0 at the top.
        cameras: V cameras (OpenCV convention) sharing one image size H × W.
        supersample: s, samples per pixel side (s² per pixel) for anti-aliasing.
        light_dir: (3,) world direction towards the light (normalised here).
        ambient: ambient share in [0, 1].
        shading: ``"smooth"`` (interpolated vertex normals) or ``"flat"`` (face normals).
        near: triangles with a vertex at camera depth ≤ ``near`` are dropped.
        cull_backfaces: drop triangles facing away from the camera.
        wrap: texture addressing outside [0, 1], ``"repeat"`` or ``"clamp"``.
        chunk_size: most candidate samples processed at once (bounds memory).
        progress: show a tqdm bar over the V·T images.

    Returns:
        rgb: (V, H, W, 3), or (V, T, H, W, 3) for (T, Nv, 3) input — composited on white.
        alpha: (V, H, W) or (V, T, H, W) — coverage in [0, 1].
        Both float32 (float64 if ``mesh_vertices`` is float64), on the device of ``mesh_vertices``.
    """
    from tqdm.auto import tqdm

    verts = torch.as_tensor(mesh_vertices)
    if not verts.is_floating_point():
        verts = verts.to(torch.float32)
    dev, dtype = verts.device, verts.dtype
    faces = torch.as_tensor(faces, device=dev).long()
    uvs = torch.as_tensor(uvs, device=dev).to(dtype)
    texture = torch.as_tensor(texture, device=dev).to(dtype)
    _check_inputs(verts, faces, uvs, texture, cameras)
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    if shading not in ("smooth", "flat"):
        raise ValueError(f"shading must be 'smooth' or 'flat', got {shading!r}")
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient must lie in [0, 1], got {ambient}")
    if near <= 0:
        raise ValueError(f"near must be positive, got {near}")
    if wrap not in ("repeat", "clamp"):
        raise ValueError(f"wrap must be 'repeat' or 'clamp', got {wrap!r}")
    light = torch.as_tensor(light_dir, dtype=dtype, device=dev).reshape(-1)
    if light.shape != (3,) or float(light.norm()) == 0.0:
        raise ValueError(f"light_dir must be a non-zero 3-vector, got {light_dir!r}")
    light = light / light.norm()
    s = int(supersample)
    single = verts.ndim == 2
    frames = verts[None] if single else verts
    n_t, n_v = frames.shape[0], len(cameras)
    width, height = cameras[0].width, cameras[0].height
    sw, sh = width * s, height * s
    rgb = torch.ones(n_v, n_t, height, width, 3, dtype=dtype, device=dev)
    alpha = torch.zeros(n_v, n_t, height, width, dtype=dtype, device=dev)
    cams = [c.to(dev) for c in cameras]
    scale = torch.tensor([s, s, 1.0], dtype=dtype, device=dev)[:, None]
    bar = tqdm(total=n_t * n_v, desc="render mesh", disable=not progress)
    for t in range(n_t):
        v = frames[t]
        if shading == "smooth":
            vn = vertex_normals(v, faces)
        else:
            tri = v[faces]
            fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-30)
        for vi, cam in enumerate(cams):
            w2c = cam.world_to_camera.to(dtype)
            cam_xyz = v @ w2c[:3, :3].T + w2c[:3, 3]
            K = cam.K.to(dtype) * scale
            face_id, coef, inv_z, front = _rasterize(cam_xyz, faces, K, sw, sh, near, cull_backfaces, chunk_size)
            hit = torch.nonzero(face_id >= 0).squeeze(1)
            colour = torch.ones(sh * sw, 3, dtype=dtype, device=dev)
            if hit.numel():
                f = face_id[hit]
                cx = (hit % sw).to(dtype) + 0.5
                cy = torch.div(hit, sw, rounding_mode="floor").to(dtype) + 0.5
                c = coef[f]
                b = (c[:, :, 0] * cx[:, None] + c[:, :, 1] * cy[:, None] + c[:, :, 2]).clamp_min(0)
                wp = b * inv_z[f]
                wp = wp / wp.sum(dim=1, keepdim=True)  # perspective-correct barycentrics
                uv = (wp[:, :, None] * uvs[f]).sum(dim=1)
                tex = sample_texture(texture, uv, wrap)
                if shading == "smooth":
                    n = (wp[:, :, None] * vn[faces[f]]).sum(dim=1)
                    n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-30)
                else:
                    n = fn[f]
                if not cull_backfaces:
                    n = torch.where(front[f][:, None], n, -n)
                shade = ambient + (1.0 - ambient) * (n @ light).clamp_min(0)
                colour[hit] = tex * shade[:, None]
            cover = (face_id >= 0).to(dtype)
            rgb[vi, t] = colour.reshape(height, s, width, s, 3).mean(dim=(1, 3))
            alpha[vi, t] = cover.reshape(height, s, width, s).mean(dim=(1, 3))
            bar.update(1)
    bar.close()
    if single:
        return rgb[:, 0], alpha[:, 0]
    return rgb, alpha


def render_textured_mesh(mesh, cameras: Sequence[Camera], vertices: Tensor | None = None, **kwargs) -> tuple[Tensor, Tensor]:
    """:func:`render_mesh` for a :class:`vid2sim.data.meshes.TexturedMesh`.

    Args:
        mesh: the mesh (its faces, uvs and texture are used).
        cameras: V cameras sharing one image size.
        vertices: optional (Nv, 3) or (T, Nv, 3) deformed positions replacing ``mesh.vertices``.
        **kwargs: passed to :func:`render_mesh`.
    """
    v = mesh.vertices if vertices is None else vertices
    return render_mesh(v, mesh.faces, mesh.uvs, mesh.texture, cameras, **kwargs)
