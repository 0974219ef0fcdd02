"""Pinhole cameras.

Inside vid2sim a camera is OpenCV-style: x right, y down, z forward, a world-to-camera 4×4 rigid
transform and a 3×3 intrinsic matrix K. On disk (scene folders) cameras use the NeRF/Blender
``transforms.json`` convention: camera-to-world 4×4 with OpenGL axes (x right, y up, z backward).
The two differ by the axis flip ``diag(1, -1, -1)`` applied on the camera side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError

# camera-side axis flip between OpenCV (y down, z forward) and OpenGL (y up, z backward)
_FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def _check_rigid(matrix: Tensor, name: str, atol: float = 1e-4) -> None:
    if matrix.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {tuple(matrix.shape)}")
    if not torch.isfinite(matrix).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    # a 4x4 check: done on the CPU in float64 whatever device the matrix lives on (the constants below are CPU
    # tensors; comparing them with a CUDA matrix was the first-use crash of every GPU path)
    m = matrix.detach().to(device="cpu", dtype=torch.float64)
    rot = m[:3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    if not torch.allclose(rot @ rot.T, eye, atol=atol) or abs(float(torch.linalg.det(rot)) - 1.0) > atol:
        raise ValueError(f"{name} is not a rigid transform: its 3x3 block is not a rotation (R Rᵀ ≠ I or det ≠ 1)")
    if not torch.allclose(m[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=atol):
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {m[3].tolist()}")


@dataclass
class Camera:
    """A pinhole camera in the OpenCV convention.

    Attributes:
        world_to_camera: (4, 4) rigid transform taking world points to camera coordinates.
        K: (3, 3) intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels (pixel centres at +0.5).
        width, height: image size in pixels.
    """

    world_to_camera: Tensor
    K: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        self.world_to_camera = torch.as_tensor(self.world_to_camera, dtype=torch.float32)
        self.K = torch.as_tensor(self.K, dtype=torch.float32)
        _check_rigid(self.world_to_camera, "world_to_camera")
        if self.K.shape != (3, 3):
            raise ConfigError(f"K must be a 3x3 matrix, got shape {tuple(self.K.shape)}")
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0):
            raise ConfigError(
                f"K must have positive focal lengths, got fx={float(self.K[0, 0])}, fy={float(self.K[1, 1])}"
            )
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ConfigError(f"image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    # ---- conversions -------------------------------------------------------------------------
    @staticmethod
    def intrinsics(fx: float, fy: float, cx: float, cy: float) -> Tensor:
        """The (3, 3) matrix K from focal lengths and principal point in pixels."""
        return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)

    @classmethod
    def from_nerf(cls, camera_to_world: Tensor, K: Tensor, width: int, height: int) -> "Camera":
        """Build from a NeRF/Blender camera-to-world (4, 4) matrix with OpenGL axes."""
        c2w = torch.as_tensor(camera_to_world, dtype=torch.float64)
        _check_rigid(c2w, "transform_matrix (camera-to-world)")
        w2c = torch.linalg.inv(c2w @ _FLIP_YZ)
        return cls(w2c.to(torch.float32), K, width, height)

    def to_nerf(self) -> Tensor:
        """The NeRF/Blender camera-to-world (4, 4) matrix (OpenGL axes), float64."""
        c2w_cv = torch.linalg.inv(self.world_to_camera.to(torch.float64))
        return c2w_cv @ _FLIP_YZ

    @property
    def camera_angle_x(self) -> float:
        """Horizontal field of view in radians (NeRF's ``camera_angle_x``)."""
        return 2.0 * math.atan(0.5 * self.width / float(self.K[0, 0]))

    @property
    def center(self) -> Tensor:
        """(3,) camera centre in world coordinates."""
        w2c = self.world_to_camera
        return -w2c[:3, :3].T @ w2c[:3, 3]

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.world_to_camera.to(device), self.K.to(device), self.width, self.height)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera rendering ``width`` × ``height`` pixels (intrinsics scaled per axis)."""
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[0] *= sx
        K[1] *= sy
        return Camera(self.world_to_camera.clone(), K, int(width), int(height))

    # ---- projection --------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points (N, 3) → pixel coordinates (N, 2) and camera depth z (N,)."""
        w2c = self.world_to_camera.to(points)
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        uv = cam[:, :2] / z[:, None]
        K = self.K.to(points)
        pix = torch.stack([K[0, 0] * uv[:, 0] + K[0, 2], K[1, 1] * uv[:, 1] + K[1, 2]], dim=-1)
        return pix, z


def stack_cameras(cameras: "Camera | Sequence[Camera]") -> tuple[Tensor, Tensor, int, int]:
    """Batch cameras that share one image size.

    Returns ``(viewmats, Ks, width, height)`` with ``viewmats: (V, 4, 4)`` world-to-camera and
    ``Ks: (V, 3, 3)``, both float32 on the first camera's device.
    """
    if isinstance(cameras, Camera):
        cameras = [cameras]
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras must hold at least one Camera, got an empty sequence")
    for i, c in enumerate(cameras):
        if not isinstance(c, Camera):
            raise ValueError(f"cameras[{i}] must be a Camera, got {type(c).__name__}")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"all cameras of one batch must share an image size, got (width, height) = {sorted(sizes)}")
    (width, height), = sizes
    dev = cameras[0].world_to_camera.device
    viewmats = torch.stack([c.world_to_camera.to(dev) for c in cameras])
    Ks = torch.stack([c.K.to(dev) for c in cameras])
    return viewmats, Ks, width, height


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """World-to-camera (4, 4) OpenCV transform of a camera at ``eye`` (3,) looking at ``target`` (3,).

    ``up`` (3,) is the world up direction (default +z, the vid2sim convention); the image's y axis
    points opposite to it.
    """
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if up is None else torch.as_tensor(up, dtype=torch.float64)
    forward = target - eye
    if float(forward.norm()) < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if float(right.norm()) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c.to(torch.float32)


def camera_ring(
    n: int,
    radius: float,
    elevation_deg: float,
    width: int,
    height: int,
    fov_x_deg: float = 40.0,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
    azimuth_offset_deg: float = 0.0,
) -> list[Camera]:
    """``n`` cameras evenly spaced in azimuth on a ring around ``target``, looking at it.

    ``elevation_deg`` is the angle above the horizontal plane (z up); ``fov_x_deg`` the
    horizontal field of view. Returns cameras with square pixels and centred principal point.
    """
    if n <= 0:
        raise ValueError(f"camera_ring needs n >= 1, got {n}")
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = Camera.intrinsics(fx, fx, width / 2, height / 2)
    tgt = torch.tensor(target, dtype=torch.float64)
    el = math.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = math.radians(azimuth_offset_deg) + 2 * math.pi * i / n
        eye = tgt + radius * torch.tensor(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)], dtype=torch.float64
        )
        cams.append(Camera(look_at(eye, tgt), K, width, height))
    return cams


def camera_sphere(
    n: int,
    radius: float,
    width: int,
    height: int,
    fov_x_deg: float = 40.0,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
    min_elevation_deg: float = -60.0,
    max_elevation_deg: float = 75.0,
) -> list[Camera]:
    """``n`` cameras spread evenly (Fibonacci spiral) over a band of the sphere around ``target``.

    Elevations lie in [``min_elevation_deg``, ``max_elevation_deg``] (the poles are left out because
    a camera straight above or below has no well-defined "up" with world z up). Each camera looks at
    ``target`` with square pixels and a centred principal point.
    """
    if n <= 0:
        raise ValueError(f"camera_sphere needs n >= 1, got {n}")
    if not -89.0 <= min_elevation_deg <= max_elevation_deg <= 89.0:
        raise ValueError(
            f"need -89 <= min_elevation_deg <= max_elevation_deg <= 89, got {min_elevation_deg}, {max_elevation_deg}"
        )
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = Camera.intrinsics(fx, fx, width / 2, height / 2)
    tgt = torch.tensor(target, dtype=torch.float64)
    z_lo, z_hi = math.sin(math.radians(min_elevation_deg)), math.sin(math.radians(max_elevation_deg))
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    for i in range(n):
        z = z_hi - (z_hi - z_lo) * (i + 0.5) / n  # uniform in z ⇒ uniform in area on the band
        r = math.sqrt(max(0.0, 1.0 - z * z))
        az = golden * i
        eye = tgt + radius * torch.tensor([r * math.cos(az), r * math.sin(az), z], dtype=torch.float64)
        cams.append(Camera(look_at(eye, tgt), K, width, height))
    return cams
