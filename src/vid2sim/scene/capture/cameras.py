"""Calibrated capture cameras: a pinhole matrix, OpenCV lens distortion and a pose in the calibration's frame.

A calibration (COLMAP, nerfstudio) is read into one :class:`CaptureCamera` per camera name. Its world frame is
whatever the calibration used (structure from motion: arbitrary rotation, origin and units); the importer
measures the metric, gravity-aligned frame later (:mod:`vid2sim.scene.capture.metric`).

Conventions: pixel centres at +0.5 (as COLMAP, nerfstudio and :class:`vid2sim.splats.cameras.Camera`; OpenCV's
own functions put them at 0, see :mod:`vid2sim.scene.capture.undistort`); world-to-camera in the OpenCV axes
(x right, y down, z forward); distortion as OpenCV's ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vid2sim.splats.cameras import Camera

#: OpenCV's distortion vector length used throughout: (k1, k2, p1, p2, k3)
NUM_DISTORTION = 5


@dataclass
class CaptureCamera:
    """One calibrated camera of a capture.

    Attributes:
        name: the camera's name in the capture (``videos/<name>.mp4`` or ``frames/<name>/``).
        width, height: image size in pixels.
        K: (3, 3) float64 pinhole intrinsics, pixel centres at +0.5.
        distortion: (5,) float64 OpenCV coefficients (k1, k2, p1, p2, k3); zeros for a pinhole camera.
        world_to_camera: (4, 4) float64 rigid transform from the calibration's world frame, OpenCV axes.
        model: the calibration's camera model name (e.g. ``"OPENCV"``), for reports.
        source: the calibration file it came from, for messages.
        image_name: the calibration's name for it (COLMAP's image NAME, nerfstudio's ``file_path``).
        image_id: COLMAP's IMAGE_ID (to find the 3D points it observes), or None.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    world_to_camera: np.ndarray
    model: str = "PINHOLE"
    source: str = ""
    image_name: str = ""
    image_id: int | None = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        d = np.zeros(NUM_DISTORTION)
        given = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        d[: len(given)] = given[:NUM_DISTORTION]
        self.distortion = d
        self.world_to_camera = np.asarray(self.world_to_camera, dtype=np.float64).reshape(4, 4)
        self.width, self.height = int(self.width), int(self.height)

    @property
    def is_pinhole(self) -> bool:
        """True when the lens has no distortion."""
        return not np.any(self.distortion != 0.0)

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the calibration's world frame."""
        return -self.rotation.T @ self.world_to_camera[:3, 3]

    def to_camera(self) -> Camera:
        """The :class:`~vid2sim.splats.cameras.Camera` of this camera's pinhole part (distortion dropped)."""
        return Camera(self.world_to_camera.astype(np.float32), self.K.astype(np.float32), self.width, self.height)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole projection (no distortion) of world points (N, 3) → pixels (N, 2) and depths (N,)."""
        cam = points @ self.rotation.T + self.world_to_camera[:3, 3]
        z = cam[:, 2]
        zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
        uv = cam[:, :2] / zs[:, None]
        return uv @ self.K[:2, :2].T + self.K[:2, 2], z


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a Hamilton unit quaternion (w, x, y, z) (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(4,) Hamilton unit quaternion (w, x, y, z) with w ≥ 0 of a (3, 3) rotation."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.zeros(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform [[R, t], [0, 1]]."""
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = t
    return m


#: camera-side axis flip between OpenCV (y down, z forward) and OpenGL (y up, z backward)
FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_c2w_to_w2c(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4) OpenCV transform of a camera-to-world (4, 4) OpenGL (NeRF) matrix."""
    return np.linalg.inv(np.asarray(c2w, dtype=np.float64) @ FLIP_YZ)


def w2c_to_opengl_c2w(w2c: np.ndarray) -> np.ndarray:
    """Camera-to-world (4, 4) OpenGL (NeRF) matrix of a world-to-camera (4, 4) OpenCV transform."""
    return np.linalg.inv(np.asarray(w2c, dtype=np.float64)) @ FLIP_YZ
