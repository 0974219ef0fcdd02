"""What a real camera would have seen of a synthetic drop: a textured room behind the object, the object's shadow
on the floor, lens distortion, per-camera gain and white balance, and sensor noise.

Used by :mod:`vid2sim.synthetic.capture` to write capture twins of synthetic scenes. Everything is rendered with
the z-buffer mesh renderer (:func:`vid2sim.synthetic.mesh_render.render_mesh`) on a pinhole camera a little wider
than the real one, then resampled through the lens model (:func:`vid2sim.scene.capture.undistort.distortion_maps`).

* **Room**: a floor (the scene's floor plane) and four walls around the camera ring, finely tessellated (the
  renderer drops triangles that reach behind a camera instead of clipping them), with muted procedural
  textures, lit by the renderer's directional light.
* **Shadow**: the object's surface projected onto the floor along the light direction (a planar projected
  shadow), rasterised once per frame in a camera looking straight down, blurred a little (penumbra) and looked
  up by every camera at the floor point each pixel sees. In the shadow the floor keeps ``shadow_light`` of its
  brightness and all of its chromaticity.
* **Sensor**: ``colour = clip(gain ⊙ linear + black, 0, 1)`` with gain = exposure × white balance per channel,
  plus Gaussian noise, quantised to 8 bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from vid2sim.scene.capture.cameras import CaptureCamera
from vid2sim.scene.capture.undistort import distortion_maps
from vid2sim.splats.cameras import Camera, look_at
from vid2sim.synthetic.mesh_render import DEFAULT_LIGHT_DIR, render_mesh
from vid2sim.synthetic.textures import noise, random_palette, value_noise


@dataclass
class Room:
    """Floor and walls as two textured triangle meshes (world frame, z up).

    Attributes:
        floor, walls: (vertices (N, 3), faces (F, 3), uvs (F, 3, 2), texture (Ht, Wt, 3)) each.
        floor_height: z of the floor plane.
    """

    floor: tuple[Tensor, Tensor, Tensor, Tensor]
    walls: tuple[Tensor, Tensor, Tensor, Tensor]
    floor_height: float


def _grid_mesh(origin: np.ndarray, du: np.ndarray, dv: np.ndarray, nu: int, nv: int, tiles: tuple[float, float]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rectangle origin + [0, 1]·du + [0, 1]·dv split into nu × nv quads (two triangles each, counter-clockwise
    seen from the side du × dv points to); UVs repeat the texture ``tiles`` times along u and v."""
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1), indexing="ij")
    verts = origin + (i[..., None] / nu) * du + (j[..., None] / nv) * dv
    idx = lambda a, b: a * (nv + 1) + b  # noqa: E731
    faces = []
    uvs = []
    for a in range(nu):
        for b in range(nv):
            q = [idx(a, b), idx(a + 1, b), idx(a + 1, b + 1), idx(a, b + 1)]
            uv = [((a + da) / nu * tiles[0], (b + db) / nv * tiles[1]) for da, db in ((0, 0), (1, 0), (1, 1), (0, 1))]
            faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
            uvs += [[uv[0], uv[1], uv[2]], [uv[0], uv[2], uv[3]]]
    return verts.reshape(-1, 3), np.array(faces), np.array(uvs)


def make_room(floor_height: float, half_size: float = 4.0, wall_height: float = 3.0, seed: int = 0,
              cell: float = 0.25, texture_size: int = 2048) -> Room:
    """A square room of side 2·``half_size`` m centred on the z axis, floor at ``floor_height``, walls
    ``wall_height`` m high facing inwards; textures from ``seed``.

    Like a real room, nothing repeats: the floor is one texture (muted colour noise, a grain of detail down to a
    few texels, tile lines every metre), and the four walls are four quarters of another. The detail is what
    structure from motion matches between the plates (``vid2sim calibrate-capture``)."""
    rng = np.random.default_rng([int(seed), 7])
    n = max(2, int(round(2 * half_size / cell)))
    nh = max(2, int(round(wall_height / cell)))
    o = np.array([-half_size, -half_size, floor_height])
    fv, ff, fuv = _grid_mesh(o, np.array([2 * half_size, 0, 0]), np.array([0, 2 * half_size, 0]), n, n, (1.0, 1.0))
    base = rng.uniform(0.35, 0.7)
    floor_pal = np.clip(base * np.array([1.0, 0.9, 0.75]) + rng.uniform(-0.12, 0.12, (4, 3)) * [1, 1, 1], 0.05, 0.95)
    metres = 2 * half_size
    floor_tex = noise(texture_size, floor_pal, rng, base_cells=int(3 * metres), octaves=4).numpy()
    floor_tex = _terrazzo(floor_tex * _grain(texture_size, rng, base_cells=int(8 * metres)), rng,
                          chip_cells=int(40 * metres))
    lines = np.ones((texture_size, texture_size, 1), np.float32)
    period, width = texture_size / metres, max(1, texture_size // 512)
    on_line = (np.arange(texture_size) % period) < width
    lines[on_line] = 0.75
    lines[:, on_line] = 0.75
    floor_tex = floor_tex * lines
    walls_v, walls_f, walls_uv = [], [], []
    corners = [np.array([-half_size, -half_size]), np.array([half_size, -half_size]),
               np.array([half_size, half_size]), np.array([-half_size, half_size])]
    offset = 0
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        origin = np.array([a[0], a[1], floor_height])
        du = np.array([b[0] - a[0], b[1] - a[1], 0.0])
        dv = np.array([0.0, 0.0, wall_height])
        v, f, uv = _grid_mesh(origin, du, dv, n, nh, (0.25, 1.0))
        uv[..., 0] += 0.25 * k  # each wall its own quarter of the texture
        walls_v.append(v)
        walls_f.append(f + offset)
        walls_uv.append(uv)
        offset += len(v)
    wall_pal = random_palette(rng, 3) * 0.3 + 0.55
    wall_size = texture_size // 2  # the walls are farther from the cameras than the floor in view
    wall_tex = noise(wall_size, wall_pal, rng, base_cells=8, octaves=4).numpy()
    wall_tex = _terrazzo(wall_tex * _grain(wall_size, rng, base_cells=32), rng, chip_cells=128)
    # walls face inwards: du × dv points outwards for this winding, so flip the triangles
    wf = np.concatenate(walls_f)[:, ::-1].copy()
    wuv = np.concatenate(walls_uv)[:, ::-1].copy()
    t = lambda x, dt=torch.float32: torch.as_tensor(np.ascontiguousarray(x), dtype=dt)  # noqa: E731
    return Room((t(fv), t(ff, torch.long), t(fuv), t(floor_tex)),
                (t(np.concatenate(walls_v)), t(wf, torch.long), t(wuv), t(wall_tex.astype(np.float32))),
                float(floor_height))


def _terrazzo(texture: np.ndarray, rng: np.random.Generator, chip_cells: int) -> np.ndarray:
    """``texture`` (S, S, 3) strewn with small hard-edged chips, light and dark, of about one cell of
    ``chip_cells`` across: the crisp, non-repeating detail a real floor or wall has."""
    field = value_noise(texture.shape[0], rng, chip_cells, 1)
    shade = value_noise(texture.shape[0], rng, max(1, chip_cells // 8), 1)[..., None]
    light = np.clip(texture * 1.6 + 0.1, 0.0, 0.95)
    dark = texture * 0.35
    out = np.where((field > 0.78)[..., None], light * (0.8 + 0.2 * shade), texture)
    return np.where((field < 0.18)[..., None], dark, out).astype(np.float32)


def _grain(size: int, rng: np.random.Generator, base_cells: int) -> np.ndarray:
    """A brightness factor (size, size, 1) around 1 (0.75–1.25) with detail at every scale from ``base_cells``
    cells across down to a few texels: value noise whose fine octaves keep most of their amplitude."""
    octaves = max(1, int(np.log2(max(size / 4 / base_cells, 1))) + 1)
    return (0.75 + 0.5 * value_noise(size, rng, base_cells, octaves, persistence=0.8))[..., None].astype(np.float32)


def render_camera(camera: CaptureCamera, pad: float = 1.0) -> tuple[Camera, np.ndarray, np.ndarray]:
    """The pinhole camera to render on before the lens distortion of ``camera`` is applied: same pose and focal
    lengths, grown so that every pixel of the distorted image has a source. Returns the camera and the two
    (H, W) float32 maps (OpenCV pixel convention) from distorted pixels to its pixels."""
    mx, my = distortion_maps(camera.K, camera)
    x0 = math.floor(min(float(mx.min()), 0.0) - pad)
    y0 = math.floor(min(float(my.min()), 0.0) - pad)
    x1 = math.ceil(max(float(mx.max()), camera.width - 1.0) + pad)
    y1 = math.ceil(max(float(my.max()), camera.height - 1.0) + pad)
    K = camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    cam = Camera(torch.as_tensor(camera.world_to_camera, dtype=torch.float32), torch.as_tensor(K, dtype=torch.float32),
                 x1 - x0 + 1, y1 - y0 + 1)
    return cam, (mx - x0).astype(np.float32), (my - y0).astype(np.float32)


def render_room(room: Room, camera: Camera, supersample: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The room seen by ``camera``: colour (H, W, 3), floor coverage (H, W) and the world point on the floor
    plane each pixel's ray meets (H, W, 3) (meaningful where the floor covers the pixel)."""
    walls_rgb, walls_a = render_mesh(*room.walls, [camera], supersample=supersample)
    floor_rgb, floor_a = render_mesh(*room.floor, [camera], supersample=supersample)
    fa = floor_a[0].numpy()[..., None]
    wa = walls_a[0].numpy()[..., None]
    walls_col = (walls_rgb[0].numpy() - (1 - wa)) / np.maximum(wa, 1e-6)
    floor_col = (floor_rgb[0].numpy() - (1 - fa)) / np.maximum(fa, 1e-6)
    rgb = fa * floor_col + (1 - fa) * np.where(wa > 0, walls_col, 0.5)
    # the floor point of every pixel's ray
    w2c = camera.world_to_camera.double().numpy()
    K = camera.K.double().numpy()
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    d = d_cam @ R  # world directions (rows of R are camera axes)
    c = -R.T @ t
    s = (room.floor_height - c[2]) / np.where(np.abs(d[..., 2]) > 1e-9, d[..., 2], -1e-9)
    pts = c + s[..., None] * d
    return rgb.astype(np.float32), fa[..., 0].astype(np.float32), pts


class ShadowMaps:
    """Planar projected shadows of a deforming surface on the floor, one map per frame.

    The surface (T, Nv, 3) is projected along the light direction onto z = floor height and rasterised by a
    camera looking straight down; :meth:`lookup` gives each floor point's shadow coverage in [0, 1].
    """

    def __init__(self, surface: Tensor, faces: Tensor, floor_height: float, light_dir=DEFAULT_LIGHT_DIR,
                 extent: float = 2.5, resolution: int = 512, softness: float = 0.01) -> None:
        light = np.asarray(light_dir, dtype=np.float64)
        light = light / np.linalg.norm(light)
        x = surface.double().numpy()
        s = (x[..., 2] - floor_height) / light[2]
        flat = x - s[..., None] * light
        flat[..., 2] = floor_height + 1e-4
        centre = flat.reshape(-1, 3).mean(0)
        height = 20.0
        eye = torch.tensor([centre[0], centre[1], floor_height + height], dtype=torch.float64)
        tgt = torch.tensor([centre[0], centre[1], floor_height], dtype=torch.float64)
        f = resolution * height / (2 * extent)
        self.camera = Camera(look_at(eye, tgt, up=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)),
                             Camera.intrinsics(f, f, resolution / 2, resolution / 2), resolution, resolution)
        uvs = torch.zeros(len(faces), 3, 2)
        tex = torch.zeros(1, 1, 3)
        _, alpha = render_mesh(torch.as_tensor(flat, dtype=torch.float32), faces, uvs, tex, [self.camera],
                               supersample=2, cull_backfaces=False)
        sigma_px = softness * f / height
        self.maps = ndimage.gaussian_filter(alpha[0].numpy(), (0, sigma_px, sigma_px)).astype(np.float32)

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Shadow coverage (T, H, W) of floor points (H, W, 3) in every frame."""
        h, w = points.shape[:2]
        pix, _ = self.camera.project(torch.as_tensor(points.reshape(-1, 3), dtype=torch.float64))
        mx = (pix[:, 0].numpy() - 0.5).reshape(h, w).astype(np.float32)
        my = (pix[:, 1].numpy() - 0.5).reshape(h, w).astype(np.float32)
        return np.stack([cv2.remap(m, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                         for m in self.maps])


@dataclass
class Sensor:
    """A camera's colour response: ``clip(gain ⊙ x + black, 0, 1)`` plus Gaussian noise of ``noise`` (std)."""

    gain: np.ndarray
    black: float
    noise: float

    def __call__(self, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(…, 3) float colours in [0, 1] → the same shape as uint8."""
        out = linear * self.gain + self.black
        out = out + rng.normal(0.0, self.noise, out.shape)
        return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


def render_view(camera: CaptureCamera, room: Room, surface: Tensor, faces: Tensor, uvs: Tensor, texture: Tensor,
                shadows: ShadowMaps, shadow_light: float, supersample: int = 2
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera's linear colour frames (T, H, W, 3), plate (H, W, 3) and true object coverage (T, H, W), all
    distorted by ``camera``'s lens (float32 in [0, 1])."""
    pin, mx, my = render_camera(camera)
    env, floor_a, floor_pts = render_room(room, pin, supersample)
    shade = 1.0 - (1.0 - shadow_light) * shadows.lookup(floor_pts) * floor_a[None]  # (T, Hr, Wr)
    rgb, alpha = render_mesh(surface, faces, uvs, texture, [pin], supersample=supersample)
    rgb, alpha = rgb[0].numpy(), alpha[0].numpy()
    frames = rgb + (1.0 - alpha[..., None]) * (env[None] * shade[..., None] - 1.0)
    warp = lambda im: cv2.remap(im, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)  # noqa: E731
    out = np.stack([warp(f) for f in frames.astype(np.float32)])
    cover = np.stack([warp(a) for a in alpha.astype(np.float32)])
    return np.clip(out, 0, 1), warp(env), np.clip(cover, 0, 1)
