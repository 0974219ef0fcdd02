"""Per-camera colour: an affine map from each camera's colours to a reference camera's, measured on the clean
plates where the cameras see the same surfaces, applied to the frames before anything is fitted.

Two cameras film the same floor and walls with different gains and white balances. Points of the static scene —
a grid on the floor plane around the object (once the floor is known) and COLMAP's 3D points where the model has
them — are projected into every plate; where a point is inside both the reference camera's plate and camera v's,
the two colours (after a light blur, so a small misregistration matters little) form one correspondence.
``c_ref ≈ A c_v + b`` is then fitted by iteratively reweighted least squares (Huber), with ridges pulling the
off-diagonal entries of A and the offset b to zero: gains and white balance are diagonal and multiplicative,
cross-talk and offsets are small, and the narrow range of colours a floor shows cannot pin down a free offset. A
camera with too few correspondences keeps the identity (and says so).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import cv2
import numpy as np

from vid2sim.scene.capture.cameras import CaptureCamera


@dataclass
class ColourConfig:
    """Settings of the colour correction.

    Attributes:
        enabled: correct colours at all.
        blur_sigma: blur (px at 128 px height) of the plates before sampling.
        min_points: fewest correspondences a camera needs for a fit.
        ridge: pull of the 3 × 3 part's off-diagonal entries towards zero (relative to the data's weight).
        offset_ridge: pull of the offset towards zero (relative to the data's weight).
        huber: the Huber loss's threshold (colour units).
    """

    enabled: bool = True
    blur_sigma: float = 1.0
    min_points: int = 50
    ridge: float = 1.0
    offset_ridge: float = 0.1
    huber: float = 0.03

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class ColourMap:
    """``colour_ref = clip(A @ colour + b, 0, 1)``: A (3, 3), b (3,); ``points`` correspondences; ``rms`` residual."""

    A: np.ndarray
    b: np.ndarray
    points: int
    rms: float

    @classmethod
    def identity(cls) -> "ColourMap":
        return cls(np.eye(3), np.zeros(3), 0, float("nan"))

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Apply to float images (…, 3) in [0, 1]."""
        return np.clip(images @ self.A.T.astype(np.float32) + self.b.astype(np.float32), 0.0, 1.0)

    def to_json(self) -> dict:
        return {"A": self.A.tolist(), "b": self.b.tolist(), "points": self.points, "rms": self.rms}


def sample(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 3) of an (H, W, 3) image at pixels (N, 2) (centres at +0.5)."""
    mx = (pixels[:, 0] - 0.5).astype(np.float32)[None]
    my = (pixels[:, 1] - 0.5).astype(np.float32)[None]
    return cv2.remap(image.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]


def _inside(cam: CaptureCamera, points: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    uv, z = cam.project(points)
    ok = (z > 0) & (uv[:, 0] > margin) & (uv[:, 1] > margin) & (uv[:, 0] < cam.width - margin) & (
        uv[:, 1] < cam.height - margin)
    return uv, ok


def fit_affine(src: np.ndarray, dst: np.ndarray, config: ColourConfig) -> ColourMap:
    """Huber-IRLS fit of dst (N, 3) ≈ A src (N, 3) + b with ridges pulling A's off-diagonal entries and b to zero.

    The static scene seen by two cameras spans a narrow range of colours, and both cameras' samples are noisy (the
    texture is sampled at slightly different places): a free offset would trade off against the gain and soak up
    the regression's attenuation. Gains and white balance are diagonal and multiplicative, so the fit leans on
    them: the off-diagonal entries and the offset move only when the data ask for it clearly (``ridge``,
    ``offset_ridge`` relative to the data's weight)."""
    n = len(src)
    X = np.concatenate([src, np.ones((n, 1))], 1)
    w = np.ones(n)
    sol = np.zeros((4, 3))
    for _ in range(8):
        Xw = X * w[:, None]
        G = X.T @ Xw
        total = w.sum()
        sol = np.zeros((4, 3))
        for c in range(3):
            R = np.zeros((4, 4))
            for k in range(3):
                if k != c:
                    R[k, k] = config.ridge * total
            R[3, 3] = config.offset_ridge * total
            sol[:, c] = np.linalg.solve(G + R + 1e-9 * np.eye(4), Xw.T @ dst[:, c])
        r = np.linalg.norm(X @ sol - dst, axis=1)
        w = np.where(r <= config.huber, 1.0, config.huber / np.maximum(r, 1e-12))
    res = X @ sol - dst
    return ColourMap(sol[:3].T.copy(), sol[3].copy(), n, float(np.sqrt((res ** 2).sum(1).mean())))


def colour_maps(cameras: Sequence[CaptureCamera], plates: Sequence[np.ndarray], reference: int, points: np.ndarray,
                visible: Sequence[set[int]] | None, config: ColourConfig) -> list[ColourMap]:
    """Per camera the :class:`ColourMap` to the reference camera's colours.

    Args:
        cameras: V undistorted cameras; plates: V plates (H, W, 3) float32 in [0, 1].
        reference: index of the reference camera (its map is the identity).
        points: (P, 3) static scene points (calibration frame); visible: per point the camera indices that see
            it (None: every camera whose image holds it).
    """
    if not config.enabled:
        return [ColourMap.identity() for _ in cameras]
    H = cameras[0].height
    s = config.blur_sigma * H / 128.0
    blurred = [cv2.GaussianBlur(p.astype(np.float32), (0, 0), s) if s > 0 else p for p in plates]
    margin = 3.0 * max(s, 1.0)
    ref_uv, ref_ok = _inside(cameras[reference], points, margin)
    if visible is not None:
        ref_ok &= np.array([reference in v for v in visible], bool)
    out = []
    for v, cam in enumerate(cameras):
        if v == reference:
            out.append(ColourMap.identity())
            continue
        uv, ok = _inside(cam, points, margin)
        ok &= ref_ok
        if visible is not None:
            ok &= np.array([v in vis for vis in visible], bool)
        if ok.sum() < config.min_points:
            out.append(ColourMap.identity())
            continue
        src = sample(blurred[v], uv[ok])
        dst = sample(blurred[reference], ref_uv[ok])
        out.append(fit_affine(src, dst, config))
    return out


def floor_grid(up: np.ndarray, floor_offset: float, centre: np.ndarray, radius: float, n: int = 60) -> np.ndarray:
    """(n², 3) points of the floor plane {x: up·x = floor_offset} on a square grid of half-size ``radius`` around the
    foot of ``centre`` (3,)."""
    up = up / np.linalg.norm(up)
    foot = centre - (centre @ up - floor_offset) * up
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.1:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    s = np.linspace(-radius, radius, n)
    u, v = np.meshgrid(s, s)
    return foot + u.reshape(-1, 1) * a + v.reshape(-1, 1) * b
