"""The floor plane from the clean plates: the plane on which every camera sees the same floor texture.

A candidate plane {x : n·x = h} (n near the up direction) puts a grid of points on the floor around the object's
foot; each point is projected into every plate (undistorted pinhole cameras) and its colours compared across the
cameras after each camera's colours are normalised by their mean over the grid (so different gains and white
balances do not count). On the true plane a textured floor looks the same from everywhere and the spread is the
noise; off it, each camera sees a different patch of texture. The plane's height is swept first, then height and
tilt are refined together (Nelder–Mead). Used where the calibration has no 3D points; it needs a floor with some
texture (a plain floor gives no minimum, and the importer falls back on the object's lowest contact point).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import optimize

from vid2sim.scene.capture.cameras import CaptureCamera
from vid2sim.scene.capture.colour import sample


@dataclass
class PlateFloor:
    """A floor plane {x : normal·x = offset} found on the plates: the std of its offset (calibration units) and of its
    normal's direction (degrees), both from the curvature of the cost at its minimum, and the cost curve's contrast
    (median over the sweep / minimum)."""

    normal: np.ndarray
    offset: float
    sigma: float
    normal_sigma_deg: float
    contrast: float


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.1:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(up, a)


def _cost(cameras: Sequence[CaptureCamera], plates: Sequence[np.ndarray], points: np.ndarray) -> float:
    """Mean over points seen by at least three cameras of the colour variance across cameras (each camera's colours
    divided by their mean over the points it sees)."""
    cols, seen = [], []
    for cam, plate in zip(cameras, plates):
        uv, z = cam.project(points)
        ok = (z > 0) & (uv[:, 0] > 1) & (uv[:, 1] > 1) & (uv[:, 0] < cam.width - 1) & (uv[:, 1] < cam.height - 1)
        c = np.zeros((len(points), 3), np.float32)
        if ok.any():
            c[ok] = sample(plate, uv[ok])
            c[ok] /= np.maximum(c[ok].mean(0), 1e-3)
        cols.append(c)
        seen.append(ok)
    C = np.stack(cols)
    S = np.stack(seen).astype(np.float32)
    n = S.sum(0)
    keep = n >= 3
    if keep.sum() < 50:
        return float("inf")
    mean = (C * S[..., None]).sum(0) / np.maximum(n, 1)[:, None]
    var = (((C - mean) ** 2) * S[..., None]).sum(0) / np.maximum(n - 1, 1)[:, None]
    return float(var[keep].sum(1).mean())


def floor_from_plates(cameras: Sequence[CaptureCamera], plates: Sequence[np.ndarray], up: np.ndarray,
                      start: float, centre: np.ndarray, radius: float, search: float,
                      grid: int = 48, max_tilt: float = 0.12) -> PlateFloor | None:
    """The floor plane near height ``start`` (along the unit ``up``, calibration units), within ±``search``,
    tilted from ``up`` by up to about ``max_tilt`` radians (the coarse search's tilts; the refinement is free), on
    a ``grid``² square of half-size ``radius`` around the foot of ``centre`` (3,). None when the plates show no
    clear minimum (an untextured floor)."""
    up = up / np.linalg.norm(up)
    a, b = _basis(up)
    s = np.linspace(-radius, radius, grid)
    u, v = np.meshgrid(s, s)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    foot = centre - (centre @ up) * up

    def plane_points(h: float, tx: float, ty: float) -> tuple[np.ndarray, np.ndarray]:
        n = up + tx * a + ty * b
        n /= np.linalg.norm(n)
        # points of the plane n·x = h above the grid's (u, v) along up
        base = foot + uv[:, :1] * a + uv[:, 1:] * b
        lift = (h - base @ n) / (up @ n)
        return base + lift[:, None] * up, n

    # coarse: heights × a few tilts (the up direction given may be a few degrees off), then Nelder–Mead from the best
    hs = np.linspace(start - search, start + search, 31)
    steps = np.linspace(-max_tilt, max_tilt, 5)
    tilts = [(tx, ty) for tx in steps for ty in steps]
    table = np.array([[_cost(cameras, plates, plane_points(h, tx, ty)[0]) for h in hs] for tx, ty in tilts])
    if not np.isfinite(table).any():
        return None
    i, k = np.unravel_index(int(np.nanargmin(table)), table.shape)
    row = table[i]
    finite = row[np.isfinite(row)]
    contrast = float(np.median(finite) / max(row[k], 1e-12))
    if contrast < 1.5 or k in (0, len(hs) - 1):
        return None
    step = hs[1] - hs[0]
    h0, tx0, ty0 = hs[k], tilts[i][0], tilts[i][1]
    res = optimize.minimize(lambda p: _cost(cameras, plates, plane_points(p[0], p[1], p[2])[0]),
                            np.array([h0, tx0, ty0]), method="Nelder-Mead",
                            options={"initial_simplex": np.array([[h0, tx0, ty0], [h0 + step, tx0, ty0],
                                                                  [h0, tx0 + 0.3 * max_tilt, ty0],
                                                                  [h0, tx0, ty0 + 0.3 * max_tilt]]),
                                     "xatol": 1e-4 * step, "fatol": 1e-9, "maxiter": 400})
    h, tx, ty = res.x
    _, n = plane_points(h, tx, ty)
    # standard deviations from the cost's curvature along each parameter (a parabola through three samples): for a
    # mean of N squared residuals c, var(p) ≈ c / (N · ∂²c/∂p²)
    def sigma_along(i: int, d: float) -> float:
        p = np.array([h, tx, ty])
        e = np.zeros(3)
        e[i] = d
        c0, c1, c2 = (_cost(cameras, plates, plane_points(*(p + k * e))[0]) for k in (-1, 0, 1))
        curv = (c0 - 2 * c1 + c2) / d ** 2
        return float(np.sqrt(max(c1, 1e-12) / max(curv, 1e-12) / len(uv)))

    sigma = sigma_along(0, 0.25 * step)
    tilt = np.hypot(sigma_along(1, 0.002), sigma_along(2, 0.002))
    pts, _ = plane_points(h, tx, ty)
    return PlateFloor(n, float(np.mean(pts @ n)), sigma, float(np.degrees(tilt)), contrast)
