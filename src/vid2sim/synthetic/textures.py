"""Seeded procedural texture images: stripes, checkers, value noise, colour patches and blends.

Every function returns an RGB image as a float32 tensor ``(size, size, 3)`` in [0, 1] (row 0 at
the top) and draws all its randomness from a ``numpy.random.Generator``, so a seed fixes the
image on every platform.
"""

from __future__ import annotations

import colorsys

import numpy as np
import torch
from torch import Tensor

TEXTURE_KINDS = ("stripes", "checkers", "noise", "patches", "blend")


def _check_size(size: int) -> int:
    if int(size) != size or size < 2:
        raise ValueError(f"texture size must be an integer >= 2, got {size!r}")
    return int(size)


def _rng(seed_or_rng: int | np.random.Generator) -> np.random.Generator:
    if isinstance(seed_or_rng, np.random.Generator):
        return seed_or_rng
    return np.random.default_rng(int(seed_or_rng))


def random_palette(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` distinct colours (n, 3) in [0, 1]: hues spread around the wheel from a random start,
    with random saturation and value so neighbours contrast in both hue and brightness."""
    if n < 1:
        raise ValueError(f"palette size must be >= 1, got {n}")
    start = rng.uniform(0.0, 1.0)
    hues = (start + np.arange(n) / n + rng.uniform(-0.3, 0.3, n) / n) % 1.0
    rng.shuffle(hues)
    sats = rng.uniform(0.35, 0.95, n)
    vals = np.where(np.arange(n) % 2 == 0, rng.uniform(0.75, 1.0, n), rng.uniform(0.3, 0.6, n))
    return np.array([colorsys.hsv_to_rgb(h, s, v) for h, s, v in zip(hues, sats, vals)])


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates (size, size) in [0, 1): x to the right, y down."""
    c = (np.arange(size) + 0.5) / size
    return np.meshgrid(c, c, indexing="xy")


def stripes(size: int, palette: np.ndarray, frequency: float, angle: float) -> Tensor:
    """Parallel stripes cycling through ``palette`` (k, 3); ``frequency`` stripes per texture width
    along the direction at ``angle`` radians."""
    size = _check_size(size)
    pal = np.asarray(palette, dtype=np.float64)
    x, y = _grid(size)
    s = (x * np.cos(angle) + y * np.sin(angle)) * frequency
    idx = np.floor(s).astype(np.int64) % len(pal)
    return torch.from_numpy(pal[idx].astype(np.float32))


def checkers(size: int, palette: np.ndarray, cells: int) -> Tensor:
    """A ``cells`` × ``cells`` checkerboard alternating the first two colours of ``palette``."""
    size = _check_size(size)
    if cells < 1:
        raise ValueError(f"checkers needs cells >= 1, got {cells}")
    pal = np.asarray(palette, dtype=np.float64)
    if len(pal) < 2:
        raise ValueError(f"checkers needs a palette of at least 2 colours, got {len(pal)}")
    x, y = _grid(size)
    idx = (np.floor(x * cells).astype(np.int64) + np.floor(y * cells).astype(np.int64)) % 2
    return torch.from_numpy(pal[idx].astype(np.float32))


def value_noise(size: int, rng: np.random.Generator, base_cells: int = 4, octaves: int = 4,
                persistence: float = 0.5) -> np.ndarray:
    """Fractal value noise (size, size) in [0, 1]: random lattice values, smoothstep-interpolated,
    summed over ``octaves`` with doubling frequency and the amplitude times ``persistence`` each octave (0.5:
    the classic halving; nearer 1 keeps more fine detail), then rescaled."""
    size = _check_size(size)
    c = (np.arange(size) + 0.5) / size  # the texel centres of _grid, along x (columns) and y (rows)
    total = np.zeros((size, size))
    amp = 1.0
    for k in range(octaves):
        n = base_cells * 2**k
        lattice = rng.uniform(0.0, 1.0, (n + 1, n + 1))
        g = c * n
        i = np.floor(g).astype(np.int64)
        f = g - i
        s = f * f * (3 - 2 * f)
        # bilinear is separable: each lattice row interpolated along x first, (n + 1, size), then the rows along
        # y; the same arithmetic per texel as gathering the four corners on the whole grid, about 6x faster
        along_x = lattice[:, i] * (1 - s) + lattice[:, i + 1] * s
        total += amp * (along_x[i] * (1 - s)[:, None] + along_x[i + 1] * s[:, None])
        amp *= persistence
    lo, hi = total.min(), total.max()
    return (total - lo) / max(hi - lo, 1e-12)


def noise(size: int, palette: np.ndarray, rng: np.random.Generator, base_cells: int = 4, octaves: int = 4) -> Tensor:
    """Value noise mapped through a piecewise-linear colour ramp over ``palette`` (k, 3)."""
    pal = np.asarray(palette, dtype=np.float64)
    t = value_noise(size, rng, base_cells, octaves) * (len(pal) - 1)
    i = np.clip(np.floor(t).astype(np.int64), 0, len(pal) - 2) if len(pal) > 1 else np.zeros_like(t, dtype=np.int64)
    if len(pal) == 1:
        return torch.from_numpy(np.broadcast_to(pal[0], t.shape + (3,)).astype(np.float32).copy())
    f = (t - i)[..., None]
    return torch.from_numpy((pal[i] * (1 - f) + pal[i + 1] * f).astype(np.float32))


def patches(size: int, palette: np.ndarray, rng: np.random.Generator, n_patches: int) -> Tensor:
    """Voronoi colour patches: ``n_patches`` random sites, each cell coloured from ``palette``."""
    size = _check_size(size)
    if n_patches < 1:
        raise ValueError(f"patches needs n_patches >= 1, got {n_patches}")
    pal = np.asarray(palette, dtype=np.float64)
    sites = rng.uniform(0.0, 1.0, (n_patches, 2))
    colours = pal[rng.integers(0, len(pal), n_patches)]
    x, y = _grid(size)
    d2 = (x[..., None] - sites[:, 0]) ** 2 + (y[..., None] - sites[:, 1]) ** 2
    return torch.from_numpy(colours[np.argmin(d2, axis=-1)].astype(np.float32))


def procedural_texture(seed_or_rng: int | np.random.Generator, size: int = 512, kind: str | None = None) -> Tensor:
    """A random texture of the given ``kind`` (one of ``TEXTURE_KINDS``; random when None).

    ``"blend"`` mixes two of the other kinds through a smooth noise mask. Every kind is finally
    modulated by a faint value noise (±8 %) so that no large area is perfectly uniform, which
    helps photometric reconstruction.

    Args:
        seed_or_rng: an integer seed or a numpy Generator.
        size: side length in texels.
        kind: pattern kind or None.

    Returns:
        (size, size, 3) float32 in [0, 1].
    """
    size = _check_size(size)
    rng = _rng(seed_or_rng)
    if kind is None:
        kind = TEXTURE_KINDS[int(rng.integers(0, len(TEXTURE_KINDS)))]
    if kind not in TEXTURE_KINDS:
        raise ValueError(f"unknown texture kind {kind!r}; expected one of {TEXTURE_KINDS} or None")

    def one(k: str) -> Tensor:
        pal = random_palette(rng, int(rng.integers(2, 6)))
        if k == "stripes":
            return stripes(size, pal, float(rng.uniform(12, 40)), float(rng.uniform(0, np.pi)))
        if k == "checkers":
            return checkers(size, pal, int(rng.integers(8, 25)))
        if k == "noise":
            return noise(size, pal, rng, base_cells=int(rng.integers(6, 13)), octaves=4)
        return patches(size, pal, rng, int(rng.integers(40, 121)))

    if kind == "blend":
        a, b = rng.choice(np.array(TEXTURE_KINDS[:4]), size=2, replace=False)
        mask = value_noise(size, rng, base_cells=int(rng.integers(2, 5)), octaves=2)
        mask = np.clip((mask - 0.5) * 4 + 0.5, 0, 1)[..., None]
        img = one(str(a)).numpy() * mask + one(str(b)).numpy() * (1 - mask)
    else:
        img = one(kind).numpy()
    grain = 0.92 + 0.16 * value_noise(size, rng, base_cells=16, octaves=2)
    return torch.from_numpy(np.clip(img * grain[..., None], 0.0, 1.0).astype(np.float32))
