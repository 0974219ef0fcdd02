"""Rigid rotations of Gaussians between frames (positions, orientations and spherical harmonics), in NumPy.

glTF is y-up; vid2sim scenes are z-up (more generally: up = −gravity). The exporters bake the rotation
from the scene frame into the glTF frame into the data instead of leaving it to a node transform, so a
viewer that ignores node transforms for splats, or does not rotate spherical harmonics with them (the
``KHR_gaussian_splatting`` spec only says it SHOULD), still shows the object upright and correctly lit.

Rotating by a proper rotation R (3×3, det +1) maps

- positions p → R p,
- orientations R_q → R R_q, i.e. quaternions q → q_R ⊗ q (Hamilton product, (w, x, y, z)),
- scales and opacities unchanged,
- SH coefficients of each degree l ≥ 1 → D_l(R) c_l, where D_l is the (2l+1)×(2l+1) matrix with
  Σ_m (D_l c)_m Y_lm(R d) = Σ_m c_m Y_lm(d) for every direction d (the colour seen along R d after the
  rotation is the colour seen along d before it). The DC term (l = 0) is rotation invariant.

D_l is computed by least squares on a fixed set of well-spread directions; because the degree-l real SH
span is closed under rotation the fit is exact (residual at float64 round-off, checked on every call).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from vid2sim.runtime.errors import InputError
from vid2sim.splats.sh import sh_basis

_Y_AXIS = np.array([0.0, 1.0, 0.0])


def rotation_to_y_up(up: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """The minimal rotation R (3×3, float64) taking the unit vector along ``up`` to +Y (glTF's up).

    For up = +Z (vid2sim's default) this is (x, y, z) → (x, z, −y): a −90° turn about X, so the
    scene's −Y becomes glTF's +Z ("front"). Antiparallel ``up`` (−Y) gets a 180° turn about X.

    Raises:
        ValueError: ``up`` is not 3 finite numbers with a non-zero length.
    """
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) == 0:
        raise InputError(f"up must be 3 finite numbers with a non-zero length, got {np.asarray(up).tolist()}")
    u = u / np.linalg.norm(u)
    c = float(u @ _Y_AXIS)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, _Y_AXIS)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + (k @ k) / (1.0 + c)


def check_rotation(rot: np.ndarray, name: str = "rotation") -> np.ndarray:
    """``rot`` as a float64 (3, 3) proper rotation; raises ValueError naming ``name`` otherwise."""
    r = np.asarray(rot, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise InputError(f"{name} must be a finite 3x3 matrix, got shape {r.shape}")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        raise InputError(f"{name} must be a proper rotation (orthonormal, det +1), got {r.tolist()}")
    return r


def rotmat_to_quat_np(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w ≥ 0, of one rotation matrix ``rot: (3, 3)``."""
    m = check_rotation(rot)
    t = np.array([1 + m[0, 0] + m[1, 1] + m[2, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2],
                  1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2]])
    i = int(np.argmax(t))
    s = 0.5 / math.sqrt(t[i])
    if i == 0:
        q = [0.25 / s, (m[2, 1] - m[1, 2]) * s, (m[0, 2] - m[2, 0]) * s, (m[1, 0] - m[0, 1]) * s]
    elif i == 1:
        q = [(m[2, 1] - m[1, 2]) * s, 0.25 / s, (m[0, 1] + m[1, 0]) * s, (m[0, 2] + m[2, 0]) * s]
    elif i == 2:
        q = [(m[0, 2] - m[2, 0]) * s, (m[0, 1] + m[1, 0]) * s, 0.25 / s, (m[1, 2] + m[2, 1]) * s]
    else:
        q = [(m[1, 0] - m[0, 1]) * s, (m[0, 2] + m[2, 0]) * s, (m[1, 2] + m[2, 1]) * s, 0.25 / s]
    q = np.array(q)
    q = q if q[0] >= 0 else -q
    return q / np.linalg.norm(q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of quaternions (w, x, y, z); ``a, b: (..., 4)`` broadcast → ``(..., 4)``."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_to_rotmat_np(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions (w, x, y, z) ``(..., 4)`` (normalised first)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return np.stack(rows, axis=-1).reshape(*q.shape[:-1], 3, 3)


def _fibonacci_directions(n: int = 64) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = i * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sh_rotation_matrices(rot: np.ndarray, degree: int) -> list[np.ndarray]:
    """``[D_1, …, D_degree]``: D_l (2l+1, 2l+1) maps degree-l SH coefficients of a function to those of
    the same function rotated by ``rot`` (see module docstring), in vid2sim's / 3DGS's / the
    ``KHR_gaussian_splatting`` basis and order (m = −l … l).

    Raises:
        ValueError: ``rot`` is not a proper rotation, or the fit is not exact (would mean a basis bug).
    """
    r = check_rotation(rot)
    if degree == 0:
        return []
    d = _fibonacci_directions()
    before = sh_basis(degree, torch.from_numpy(d)).numpy()  # (K, (degree+1)²)
    after = sh_basis(degree, torch.from_numpy(d @ r.T)).numpy()
    out = []
    for lvl in range(1, degree + 1):
        sl = slice(lvl * lvl, (lvl + 1) * (lvl + 1))
        # c'·Y(R d) = c·Y(d) for all d:  after c' = before c  →  c' = D c with D = after⁺ before
        dmat, *_ = np.linalg.lstsq(after[:, sl], before[:, sl], rcond=None)
        resid = np.abs(after[:, sl] @ dmat - before[:, sl]).max()
        if resid > 1e-9:
            raise InputError(f"SH rotation of degree {lvl} is not exact (residual {resid:.2e})")
        out.append(dmat)
    return out


def rotate_sh(sh: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """SH coefficients ``sh: (N, K, 3)`` (K = (degree+1)²) of colours rotated by ``rot`` → (N, K, 3) float64."""
    sh = np.asarray(sh, dtype=np.float64)
    k = sh.shape[1]
    degree = int(round(math.sqrt(k))) - 1
    out = sh.copy()
    for lvl, dmat in enumerate(sh_rotation_matrices(rot, degree), start=1):
        sl = slice(lvl * lvl, (lvl + 1) * (lvl + 1))
        out[:, sl, :] = np.einsum("ab,nbc->nac", dmat, sh[:, sl, :])
    return out


def rotate_gaussian_arrays(means: np.ndarray, quats: np.ndarray, sh: np.ndarray,
                           rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate Gaussians by ``rot`` about the origin (float64 in and out).

    Args:
        means: (N, 3) centres; quats: (N, 4) (w, x, y, z) orientations (their norm and sign are kept);
        sh: (N, K, 3) colour coefficients; rot: (3, 3) proper rotation.
    Returns:
        (R p, q_R ⊗ q, D(R) sh).
    """
    r = check_rotation(rot)
    q_r = rotmat_to_quat_np(r)
    return (np.asarray(means, dtype=np.float64) @ r.T, quat_multiply(q_r, quats), rotate_sh(sh, r))
