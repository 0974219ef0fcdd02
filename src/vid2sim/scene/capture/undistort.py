"""Lens undistortion of frames, plates and masks to pinhole cameras (OpenCV's model, ``opencv-python-headless``).

A calibrated camera with distortion ``(k1, k2, p1, p2, k3)`` maps a normalised point (x, y) to
``x' = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)`` (and symmetrically for y), then to pixels by
K. Undistortion resamples each image onto a pinhole camera of the same size whose intrinsics ``K_new`` come
from ``cv2.getOptimalNewCameraMatrix`` with ``alpha = 0``: every output pixel sees the scene (no empty borders,
which masks and plates would otherwise have to explain). Pixel centres: vid2sim, COLMAP and nerfstudio put
them at +0.5, OpenCV at 0, so K is shifted by half a pixel on the way into and out of OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from vid2sim.scene.capture.cameras import CaptureCamera


def to_opencv_K(K: np.ndarray) -> np.ndarray:
    """K with pixel centres at 0 (OpenCV) from K with pixel centres at +0.5 (vid2sim, COLMAP)."""
    out = np.array(K, dtype=np.float64)
    out[0, 2] -= 0.5
    out[1, 2] -= 0.5
    return out


def from_opencv_K(K: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_opencv_K`."""
    out = np.array(K, dtype=np.float64)
    out[0, 2] += 0.5
    out[1, 2] += 0.5
    return out


@dataclass
class Undistortion:
    """Resampling of one camera's images onto its pinhole twin, optionally reduced by an integer factor.

    Attributes:
        camera: the pinhole camera the images are resampled to (same pose, ``K_new``, no distortion; its size is
            the source's divided by ``downscale``).
        map_x, map_y: (H, W) float32 source pixel (OpenCV convention) of every full-size output pixel, or None for
            a camera without distortion (then images are only reduced).
        downscale: the reduction factor (1: none); reductions average whole blocks of pixels (:func:`reduce`, the
            result is float32), so a mask reduced this way holds each pixel's coverage.
    """

    camera: CaptureCamera
    map_x: np.ndarray | None
    map_y: np.ndarray | None
    downscale: int = 1

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Undistort one image (H, W), (H, W, C) of uint8 or float32 (bilinear, borders replicated), then reduce it."""
        if self.map_x is not None:
            image = cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
        if self.downscale > 1:
            image = reduce(image.astype(np.float32), self.downscale, image.ndim == 3)
        return image

    def stack(self, images: np.ndarray) -> np.ndarray:
        """Undistort a stack (T, H, W[, C]) image by image."""
        if self.map_x is None and self.downscale == 1:
            return images
        return np.stack([self(im) for im in images])


def make_undistortion(camera: CaptureCamera, alpha: float = 0.0, downscale: int = 1) -> Undistortion:
    """The :class:`Undistortion` of ``camera`` (``alpha`` as in ``cv2.getOptimalNewCameraMatrix``: 0 keeps only
    pixels that see the scene, 1 keeps every source pixel), reduced ``downscale`` times (the size must divide)."""
    if camera.width % downscale or camera.height % downscale:
        raise ValueError(f"camera {camera.name}: {camera.width}x{camera.height} is not divisible by {downscale}")
    reduce = np.diag([1.0 / downscale, 1.0 / downscale, 1.0])
    size = (camera.width // downscale, camera.height // downscale)
    if camera.is_pinhole:
        return Undistortion(replace(camera, K=reduce @ camera.K, width=size[0], height=size[1]), None, None, downscale)
    full = (camera.width, camera.height)
    K_cv = to_opencv_K(camera.K)
    new_K, _ = cv2.getOptimalNewCameraMatrix(K_cv, camera.distortion, full, alpha, full)
    map_x, map_y = cv2.initUndistortRectifyMap(K_cv, camera.distortion, None, new_K, full, cv2.CV_32FC1)
    # with pixel centres at +0.5, reducing the image scales K (a reduced pixel covers ``downscale`` full ones)
    pinhole = replace(camera, K=reduce @ from_opencv_K(new_K), distortion=np.zeros(5), model="PINHOLE",
                      width=size[0], height=size[1])
    return Undistortion(pinhole, map_x, map_y, downscale)


def reduce(images: np.ndarray, factor: int, channels: bool) -> np.ndarray:
    """Float images (…, H, W, C) (``channels``) or (…, H, W) reduced ``factor`` times by averaging
    ``factor`` × ``factor`` blocks (H and W must be multiples of it), float32 (OpenCV's area resampling, which
    is that block mean at an integer factor)."""
    if factor == 1:
        return images
    shape = images.shape[-3:] if channels else images.shape[-2:]
    H, W = shape[:2]
    flat = np.asarray(images, dtype=np.float32).reshape((-1,) + shape)
    out = np.empty((len(flat), H // factor, W // factor) + shape[2:], np.float32)
    for i, image in enumerate(flat):
        out[i] = cv2.resize(image, (W // factor, H // factor), interpolation=cv2.INTER_AREA)
    return out.reshape(images.shape[:-len(shape)] + out.shape[1:])


def distort_normalised(xy: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """OpenCV's distortion of normalised image points (N, 2) (before K) → distorted normalised points (N, 2)."""
    k1, k2, p1, p2, k3 = np.asarray(distortion, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def distortion_maps(K_pinhole: np.ndarray, camera: CaptureCamera) -> tuple[np.ndarray, np.ndarray]:
    """Maps that *apply* the lens distortion of ``camera``: for every pixel of the distorted image (``camera``'s K
    and distortion), the pixel (OpenCV convention, float32 (H, W) each) of a pinhole image with intrinsics
    ``K_pinhole`` (+0.5 convention) that it sees. Used by the synthetic capture generator."""
    w, h = camera.width, camera.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    und = cv2.undistortPoints(pix, to_opencv_K(camera.K), camera.distortion,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))[:, 0, :]
    Kp = to_opencv_K(K_pinhole)
    mx = (Kp[0, 0] * und[:, 0] + Kp[0, 2]).reshape(h, w).astype(np.float32)
    my = (Kp[1, 1] * und[:, 1] + Kp[1, 2]).reshape(h, w).astype(np.float32)
    return mx, my
