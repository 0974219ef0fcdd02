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

Work is vectorised over triangles and over images: views and frames are rasterized together in
batches of about ``batch_samples`` samples; each image only keeps a z-buffer for the crop (whole
pixels) around its visible triangles; every triangle enumerates the samples of its screen bounding
box (a ragged enumeration, no padding), in chunks of at most ``chunk_size`` candidates; and the
z-test is a single ``scatter_reduce(amin)`` on int64 keys packing the float32 depth bits above the
global face index. Measured on the 2-core CPU: about 0.1–0.4 s per 448² image (s = 2, ~3000
faces, the range is machine load) and 0.02–0.05 s per 128² image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import torch
from torch import Tensor

from ..splats.cameras import Camera

if TYPE_CHECKING:
    from .meshes import TexturedMesh

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
    c00, c01 = flat.index_select(0, y0 * wt + x0), flat.index_select(0, y0 * wt + x1)
    c10, c11 = flat.index_select(0, y1 * wt + x0), flat.index_select(0, y1 * wt + x1)
    return (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy


def _check_inputs(vertices: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor, cameras: Sequence[Camera]) -> None:
    if vertices.ndim not in (2, 3) or vertices.shape[-1] != 3:
        raise ValueError(f"mesh_vertices must have shape (Nv, 3) or (T, Nv, 3), got {tuple(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (Nf, 3), got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[-2]):
        raise ValueError(
            f"faces index vertices in [{int(faces.min())}, {int(faces.max())}] "
            f"but there are {vertices.shape[-2]} vertices"
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


@dataclass
class _Raster:
    """Result of rasterizing a batch of B images over their crops (see :func:`_rasterize`)."""

    face: Tensor  # (S,) long: winning global face b·Nf + f per crop sample, or -1
    crop: Tensor  # (B, 4) long: x0, y0, width, height of each image's crop, in samples (multiples of s)
    offset: Tensor  # (B,) long: where each image's crop starts in ``face``
    coef: Tensor  # (B·Nf, 3, 3): screen-space barycentric plane coefficients (a, b, c) per corner
    inv_z: Tensor  # (B·Nf, 3): 1/z of the corners
    front: Tensor  # (B·Nf,) bool: the face looks towards the camera


def _rasterize(
    cam_xyz: Tensor, faces: Tensor, K: Tensor, width: int, height: int, s: int, near: float,
    cull_backfaces: bool, chunk_size: int,
) -> _Raster:
    """Z-buffer B images at once over the s× sample grid.

    Args:
        cam_xyz: (B, Nv, 3) vertices in each image's camera frame.
        faces: (Nf, 3).
        K: (B, 3, 3) intrinsics already scaled to samples (fx·s, cx·s, ...).
        width, height: sample-grid size (pixels × s).
        s: supersampling factor; crops are aligned to whole pixels.
    """
    dev = cam_xyz.device
    n_b, nf = cam_xyz.shape[0], faces.shape[0]
    z = cam_xyz[..., 2]
    px = K[:, 0, 0, None] * cam_xyz[..., 0] / z + K[:, 0, 2, None]
    py = K[:, 1, 1, None] * cam_xyz[..., 1] / z + K[:, 1, 2, None]
    fz = z[:, faces].reshape(-1, 3)  # (B·Nf, 3)
    fx, fy = px[:, faces].reshape(-1, 3), py[:, faces].reshape(-1, 3)
    valid = (fz > near).all(dim=1)
    tri = cam_xyz[:, faces].reshape(-1, 3, 3)
    n_cam = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = (n_cam * tri[:, 0]).sum(dim=1) < 0
    if cull_backfaces:
        valid &= front
    # barycentric of corner i is the edge function of the opposite edge (j, k), divided by the area
    j, k = [1, 2, 0], [2, 0, 1]
    ex, ey = fx[:, k] - fx[:, j], fy[:, k] - fy[:, j]
    area = (fx[:, 1] - fx[:, 0]) * (fy[:, 2] - fy[:, 0]) - (fy[:, 1] - fy[:, 0]) * (fx[:, 2] - fx[:, 0])
    valid &= area.abs() > 1e-9
    safe_area = torch.where(valid, area, torch.ones_like(area))[:, None]
    coef = torch.stack([-ey / safe_area, ex / safe_area, (ey * fx[:, j] - ex * fy[:, j]) / safe_area], dim=2)
    inv_z = 1.0 / torch.where(valid[:, None], fz, torch.ones_like(fz))

    # samples whose centre X + 0.5 lies in the triangle's bounding box
    x_lo = torch.ceil(fx.min(dim=1).values - 0.5).clamp(min=0)
    x_hi = torch.floor(fx.max(dim=1).values - 0.5).clamp(max=width - 1)
    y_lo = torch.ceil(fy.min(dim=1).values - 0.5).clamp(min=0)
    y_hi = torch.floor(fy.max(dim=1).values - 0.5).clamp(max=height - 1)
    valid &= (x_hi >= x_lo) & (y_hi >= y_lo)

    # per image: the crop (whole pixels) holding every visible triangle's bounding box
    big = float(max(width, height) + 1)
    vb = valid.reshape(n_b, nf)
    cx0 = torch.where(vb, x_lo.reshape(n_b, nf), big).min(dim=1).values
    cy0 = torch.where(vb, y_lo.reshape(n_b, nf), big).min(dim=1).values
    cx1 = torch.where(vb, x_hi.reshape(n_b, nf), -1.0).max(dim=1).values
    cy1 = torch.where(vb, y_hi.reshape(n_b, nf), -1.0).max(dim=1).values
    empty = ~vb.any(dim=1)
    x0 = torch.where(empty, 0.0, torch.div(cx0, s, rounding_mode="floor") * s).long()
    y0 = torch.where(empty, 0.0, torch.div(cy0, s, rounding_mode="floor") * s).long()
    cw = torch.where(empty, 0.0, (torch.div(cx1, s, rounding_mode="floor") + 1) * s - x0).long()
    ch = torch.where(empty, 0.0, (torch.div(cy1, s, rounding_mode="floor") + 1) * s - y0).long()
    sizes = cw * ch
    offset = torch.cumsum(sizes, 0) - sizes
    crop = torch.stack([x0, y0, cw, ch], dim=1)
    total_samples = int(sizes.sum())

    ids = torch.nonzero(valid).squeeze(1)
    zbuf = torch.full((total_samples,), _INT64_MAX, dtype=torch.long, device=dev)
    if ids.numel():
        img = torch.div(ids, nf, rounding_mode="floor")
        # per visible triangle: where its bounding box starts in the flat crop buffer, and the crop's row stride
        xlo_v, ylo_v = x_lo[ids].long(), y_lo[ids].long()
        bw = x_hi[ids].long() - xlo_v + 1
        counts = bw * (y_hi[ids].long() - ylo_v + 1)
        base = offset[img] + (ylo_v - y0[img]) * cw[img] + (xlo_v - x0[img])
        stride = cw[img]
        ends = torch.cumsum(counts, 0)
        first = ends - counts
        coef_v, inv_z_v = coef.index_select(0, ids), inv_z.index_select(0, ids)
        total = int(ends[-1])
        start, done = 0, 0
        while done < total:
            # next chunk: whole triangles whose candidates fit in chunk_size (at least one triangle)
            stop = max(int(torch.searchsorted(ends, done + chunk_size, right=True)), start + 1)
            cnt = counts[start:stop]
            local_tri = torch.repeat_interleave(torch.arange(start, stop, device=dev), cnt)
            local = torch.arange(done, int(ends[stop - 1]), device=dev) - first.index_select(0, local_tri)
            w = bw.index_select(0, local_tri)
            dy = torch.div(local, w, rounding_mode="floor")
            dx = local - dy * w
            sx = (xlo_v.index_select(0, local_tri) + dx).to(cam_xyz.dtype) + 0.5
            sy = (ylo_v.index_select(0, local_tri) + dy).to(cam_xyz.dtype) + 0.5
            g = ids.index_select(0, local_tri)
            c = coef_v.index_select(0, local_tri)  # (M, 3, 3)
            b = c[:, :, 0] * sx[:, None] + c[:, :, 1] * sy[:, None] + c[:, :, 2]
            iz = (b * inv_z_v.index_select(0, local_tri)).sum(dim=1)
            inside = torch.nonzero((b >= 0).all(dim=1) & (iz > 0)).squeeze(1)
            depth = (1.0 / iz.index_select(0, inside)).to(torch.float32)
            key = (depth.view(torch.int32).to(torch.long) << 32) | g.index_select(0, inside)
            where = base.index_select(0, local_tri) + dy * stride.index_select(0, local_tri) + dx
            where = where.index_select(0, inside)
            zbuf.scatter_reduce_(0, where, key, reduce="amin", include_self=True)
            done = int(ends[stop - 1])
            start = stop
    face = torch.where(zbuf != _INT64_MAX, zbuf & 0xFFFFFFFF, torch.full_like(zbuf, -1))
    return _Raster(face, crop, offset, coef, inv_z, front)


@torch.no_grad()
def render_mesh(
    mesh_vertices: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor, cameras: Sequence[Camera],
    supersample: int = 2, light_dir: Sequence[float] | Tensor = DEFAULT_LIGHT_DIR, ambient: float = 0.3,
    shading: str = "smooth", near: float = 0.01, cull_backfaces: bool = True, wrap: str = "repeat",
    chunk_size: int = 1 << 21, batch_samples: int = 1 << 23, progress: bool = False,
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
        chunk_size: most candidate (triangle, sample) pairs processed at once (bounds memory).
        batch_samples: images are rasterized together in batches of about this many samples
            (H·W·s² each, at least one image per batch); larger batches amortise per-call overhead.
        progress: show a tqdm bar over the V·T images.

    Returns:
        rgb: (V, H, W, 3), or (V, T, H, W, 3) for (T, Nv, 3) input — composited on white.
        alpha: (V, H, W) or (V, T, H, W) — coverage in [0, 1].
        Both float32 (float64 if ``mesh_vertices`` is float64), on the device of ``mesh_vertices``.
    """
    from tqdm.auto import tqdm

    verts, faces, uvs, texture, light = _checked_inputs(mesh_vertices, faces, uvs, texture, cameras, supersample,
                                                        light_dir, ambient, shading, near, wrap, chunk_size,
                                                        batch_samples)
    dev, dtype = verts.device, verts.dtype
    s = int(supersample)
    single = verts.ndim == 2
    frames = verts[None] if single else verts
    n_t, n_v, nf = frames.shape[0], len(cameras), faces.shape[0]
    width, height = cameras[0].width, cameras[0].height
    sw, sh = width * s, height * s
    _check_face_ids(n_t, n_v, nf)
    normals = _world_normals(frames, faces, shading)
    w2c, ks = _camera_matrices(cameras, s, dtype, dev)
    rgb = torch.ones(n_v, n_t, height, width, 3, dtype=dtype, device=dev)
    alpha = torch.zeros(n_v, n_t, height, width, dtype=dtype, device=dev)
    per_batch = max(1, min(batch_samples // (sw * sh), (1 << 22) // max(nf, 1)))
    image_t = torch.arange(n_t, device=dev).repeat_interleave(n_v)  # images ordered frame-major
    image_v = torch.arange(n_v, device=dev).repeat(n_t)
    bar = tqdm(total=n_t * n_v, desc="render mesh", disable=not progress)
    for b0 in range(0, n_t * n_v, per_batch):
        tb, vb = image_t[b0 : b0 + per_batch], image_v[b0 : b0 + per_batch]
        rot, trans = w2c[vb, :3, :3], w2c[vb, :3, 3]
        cam_xyz = torch.einsum("bij,bnj->bni", rot, frames[tb]) + trans[:, None, :]
        r = _rasterize(cam_xyz, faces, ks[vb], sw, sh, s, near, cull_backfaces, chunk_size)
        colour = _shade_samples(r, tb, faces, uvs, texture, normals, light, ambient, shading, wrap, cull_backfaces)
        _resolve_pixels(rgb, alpha, r, colour, tb, vb, s)
        bar.update(len(tb))
    bar.close()
    if single:
        return rgb[:, 0], alpha[:, 0]
    return rgb, alpha


def _checked_inputs(
    mesh_vertices: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor, cameras: Sequence[Camera],
    supersample: int, light_dir: Sequence[float] | Tensor, ambient: float, shading: str, near: float, wrap: str,
    chunk_size: int, batch_samples: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`render_mesh`'s inputs checked (ValueError) and converted: vertices (Nv, 3) or (T, Nv, 3) floating
    (float32 unless already floating), faces (Nf, 3) long, uvs (Nf, 3, 2) and texture (Ht, Wt, 3) in the vertices'
    dtype on their device, and the unit light direction (3,)."""
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
    if chunk_size < 1 or batch_samples < 1:
        raise ValueError(f"chunk_size and batch_samples must be positive, got {chunk_size} and {batch_samples}")
    light = torch.as_tensor(light_dir, dtype=dtype, device=dev).reshape(-1)
    if light.shape != (3,) or float(light.norm()) == 0.0:
        raise ValueError(f"light_dir must be a non-zero 3-vector, got {light_dir!r}")
    return verts, faces, uvs, texture, light / light.norm()


def _check_face_ids(n_t: int, n_v: int, nf: int) -> None:
    """ValueError unless every face of every image (``n_t`` frames × ``n_v`` views × ``nf`` faces) has a 32-bit
    id (the z-buffer packs it below the depth)."""
    if n_t * n_v * max(nf, 1) >= 2**31:
        raise ValueError(
            f"too many frames × views × faces ({n_t} × {n_v} × {nf}) for 32-bit face ids; render in parts"
        )


def _camera_matrices(cameras: Sequence[Camera], s: int, dtype: torch.dtype, dev: torch.device
                     ) -> tuple[Tensor, Tensor]:
    """The cameras' world-to-camera matrices (V, 4, 4) and intrinsics (V, 3, 3) scaled to the s× sample grid."""
    w2c = torch.stack([c.world_to_camera.to(device=dev, dtype=dtype) for c in cameras])  # (V, 4, 4)
    ks = torch.stack([c.K.to(device=dev, dtype=dtype) for c in cameras])
    return w2c, ks * torch.tensor([s, s, 1.0], dtype=dtype, device=dev)[None, :, None]


def _world_normals(frames: Tensor, faces: Tensor, shading: str) -> Tensor:
    """Per frame, the unit normals in world space (the light is fixed in the world): (T, Nv, 3) vertex normals
    for ``"smooth"`` shading, (T, Nf, 3) face normals for ``"flat"``, of ``frames`` (T, Nv, 3)."""
    if shading == "smooth":
        return torch.stack([vertex_normals(v, faces) for v in frames])  # (T, Nv, 3)
    tri = frames[:, faces]
    fn = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    return fn / fn.norm(dim=-1, keepdim=True).clamp_min(1e-30)  # (T, Nf, 3)


def _shade_samples(
    r: _Raster, tb: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor, normals: Tensor, light: Tensor,
    ambient: float, shading: str, wrap: str, cull_backfaces: bool,
) -> Tensor:
    """The shaded colour (S, 3) of every crop sample of the raster ``r`` of B images (white where no face won):
    perspective-correct UVs, the texture looked up bilinearly, Lambert light on the interpolated (or face) normal.

    Args:
        tb: (B,) long, the frame of each image.
        normals: (T, Nv, 3) or (T, Nf, 3) from :func:`_world_normals`.
        light: (3,) unit direction towards the light.
    """
    dtype, dev = texture.dtype, texture.device
    nf = faces.shape[0]
    colour = torch.ones(r.face.shape[0], 3, dtype=dtype, device=dev)
    hit = torch.nonzero(r.face >= 0).squeeze(1)
    if not hit.numel():
        return colour
    g = r.face.index_select(0, hit)
    img = torch.div(g, nf, rounding_mode="floor")
    f = g - img * nf
    crop = r.crop.index_select(0, img)
    x0, y0, cw = crop[:, 0], crop[:, 1], crop[:, 2]
    li = hit - r.offset.index_select(0, img)
    ly = torch.div(li, cw, rounding_mode="floor")
    sx = (x0 + li - ly * cw).to(dtype) + 0.5
    sy = (y0 + ly).to(dtype) + 0.5
    c = r.coef.index_select(0, g)
    bary = (c[:, :, 0] * sx[:, None] + c[:, :, 1] * sy[:, None] + c[:, :, 2]).clamp_min(0)
    wp = bary * r.inv_z.index_select(0, g)
    wp = wp / wp.sum(dim=1, keepdim=True)  # perspective-correct barycentrics
    uv = (wp[:, :, None] * uvs.index_select(0, f)).sum(dim=1)
    tex = sample_texture(texture, uv, wrap)
    frame = tb.index_select(0, img)
    if shading == "smooth":
        corner = (frame[:, None] * normals.shape[1] + faces.index_select(0, f)).reshape(-1)
        vn = normals.reshape(-1, 3).index_select(0, corner).reshape(-1, 3, 3)
        n = (wp[:, :, None] * vn).sum(dim=1)
        n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-30)
    else:
        n = normals.reshape(-1, 3).index_select(0, frame * nf + f)
    if not cull_backfaces:
        n = torch.where(r.front.index_select(0, g)[:, None], n, -n)
    shade = ambient + (1.0 - ambient) * (n @ light).clamp_min(0)
    colour.index_copy_(0, hit, tex * shade[:, None])
    return colour


def _resolve_pixels(rgb: Tensor, alpha: Tensor, r: _Raster, colour: Tensor, tb: Tensor, vb: Tensor, s: int) -> None:
    """Box-filter the s × s samples of each image's crop into its pixels of ``rgb`` (V, T, H, W, 3) and ``alpha``
    (V, T, H, W), in place; ``colour`` (S, 3) holds the samples' colours, ``tb`` / ``vb`` (B,) each image's frame
    and view."""
    cover = (r.face >= 0).to(rgb.dtype)
    crops = r.crop.tolist()
    offsets = r.offset.tolist()
    for i, ((x0, y0, cw, ch), off) in enumerate(zip(crops, offsets)):
        if cw == 0:
            continue
        t_i, v_i = int(tb[i]), int(vb[i])
        px0, py0, pw, ph = x0 // s, y0 // s, cw // s, ch // s
        block = colour[off : off + cw * ch].reshape(ph, s, pw, s, 3).mean(dim=(1, 3))
        rgb[v_i, t_i, py0 : py0 + ph, px0 : px0 + pw] = block
        cov = cover[off : off + cw * ch].reshape(ph, s, pw, s).mean(dim=(1, 3))
        alpha[v_i, t_i, py0 : py0 + ph, px0 : px0 + pw] = cov


def render_textured_mesh(
    mesh: "TexturedMesh", cameras: Sequence[Camera], vertices: Tensor | None = None, **kwargs
) -> tuple[Tensor, Tensor]:
    """:func:`render_mesh` for a :class:`vid2sim.synthetic.meshes.TexturedMesh`.

    Args:
        mesh: the mesh (its faces, uvs and texture are used).
        cameras: V cameras sharing one image size.
        vertices: optional (Nv, 3) or (T, Nv, 3) deformed positions replacing ``mesh.vertices``.
        **kwargs: passed to :func:`render_mesh`.
    """
    v = mesh.vertices if vertices is None else vertices
    return render_mesh(v, mesh.faces, mesh.uvs, mesh.texture, cameras, **kwargs)
