"""Object masks from a clean plate: a per-pixel colour/brightness test with shadow suppression, hysteresis in
space and time, morphological clean-up, the largest component, soft edges — no learned model.

Per pixel, with the frame's colour ``I`` and the plate's ``B`` (both RGB in [0, 1], lightly blurred), the
*brightness ratio* ``a = <I, B> / <B, B>`` and the *chromatic residual* ``c = |I − a·B|`` separate what an object
does from what a shadow does (Horprasert et al.'s colour model): a shadow darkens the background (``a < 1``)
and keeps its chromaticity (``c`` small), an object changes the chromaticity, or is brighter than the
background, or darker than any shadow. The object score is

    s = max( c / (σ + τ·a·|B|),  (a − 1)·|B| / σ,  (a_min − a)·|B| / σ )

with σ the camera's noise level (measured on the frames), τ the chromatic change a shadow may still cause
(coloured ambient light) and ``a_min`` the darkest shadow. Pixels with s above ``high`` seed the object; pixels
above ``low`` join it when connected to a seed in space *or time* (6-connected in (t, y, x)), so a weak edge
that was strong a frame earlier survives and isolated noise does not. Each frame is then opened, closed, its holes
filled and its largest component kept. At the boundary the mask is made soft: a pixel's coverage is its colour's
position between the plate and the nearby object colour, ``α = <I − B, F − B> / |F − B|²``.

Each mask comes with its area, a confidence (the share of its pixels that the colour test supports directly, not
through filling) and flags: ``border`` (the object touches the image border), ``empty`` (no object) and
``jump`` (the area changes by more than half between neighbouring frames).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage


@dataclass
class MaskConfig:
    """Settings of the background test (defaults suit 8-bit video with mild compression).

    Attributes:
        blur_sigma: Gaussian blur (px) of frames and plate before the test (noise and compression blocks).
        high, low: hysteresis thresholds of the object score (seeds, and pixels joining a seed).
        shadow_min_brightness: a_min, the darkest a shadow can make the background (share of its brightness).
        shadow_chroma_tolerance: τ, the chromatic change a shadow may cause, relative to the brightness.
        shadow_texture_window: side (px at 128 px image height) of the window in which a shadow must keep the
            background's texture.
        shadow_band: how much darker than the camera's typical shadow a pixel may be and still pass as shadow: the
            typical shadow (the mode of the brightness ratio over the shadow-like pixels) is measured per camera; a
            band of ``max(shadow_band, 3 MAD)`` below it and everything up to the background's brightness pass
            (``shadow_min_brightness`` bounds it from below; a negative band disables the measurement).
        shadow_min_correlation: the smallest normalised correlation between frame and plate in that window for a
            darkening to pass as a shadow, where the texture it would keep stands out of the noise (the plate's local
            std times the darkening above ``shadow_texture_min`` σ).
        noise_floor: the smallest noise level σ assumed (a perfectly clean synthetic frame would give 0).
        open_radius, close_radius: radii (px at 128 px image height; scaled with the image) of the opening that
            removes specks and the closing that bridges gaps.
        fill_holes: fill holes inside the object (an object that truly has holes should give its own masks).
        soft_edges: estimate fractional coverage in a band at the boundary (:func:`soft_edges`).
        edge_width, edge_depth: that band's half-width and how deep inside the object its colour is taken, in pixels
            of the frames (an outline's blur is a few pixels whatever the image's size).
        jump_ratio: an area ratio between neighbouring frames beyond this (or its inverse) flags ``jump``.
    """

    blur_sigma: float = 0.7
    high: float = 6.0
    low: float = 3.0
    shadow_min_brightness: float = 0.25
    shadow_chroma_tolerance: float = 0.02
    shadow_texture_window: int = 5
    shadow_min_correlation: float = 0.5
    shadow_texture_min: float = 6.0
    shadow_band: float = 0.08
    noise_floor: float = 1.0 / 255.0
    open_radius: float = 1.0
    close_radius: float = 2.0
    fill_holes: bool = True
    soft_edges: bool = True
    edge_width: float = 2.0
    edge_depth: float = 3.0
    jump_ratio: float = 1.5

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class MaskResult:
    """Masks of one camera.

    Attributes:
        masks: (T, H, W) float32 in [0, 1], soft at the boundary.
        area: (T,) mask area in pixels.
        confidence: (T,) share of the mask's pixels the colour test supports directly.
        border: (T,) bool, the mask touches the image border.
        empty: (T,) bool, no object found.
        jump: (T,) bool, the area changed by more than the config's ratio from a neighbouring frame.
        noise: the camera's noise level σ used (colour units in [0, 1]).
        stray: (T,) share of the pixels outside the mask that the test still finds different from the plate (a
            moving camera or a changed light shows here).
    """

    masks: np.ndarray
    area: np.ndarray
    confidence: np.ndarray
    border: np.ndarray
    empty: np.ndarray
    jump: np.ndarray
    noise: float
    stray: np.ndarray


def _disk(radius: float) -> np.ndarray:
    r = max(int(round(radius)), 0)
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return x * x + y * y <= radius * radius + 1e-9


def blur(images: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur over the two image axes of (..., H, W, C) float images."""
    if sigma <= 0:
        return images
    axes_sigma = [0.0] * images.ndim
    axes_sigma[-3] = axes_sigma[-2] = sigma
    return ndimage.gaussian_filter(images, axes_sigma, mode="nearest", truncate=2.5)


def noise_level(frames: np.ndarray, plate: np.ndarray, floor: float) -> float:
    """Robust noise level σ of (T, H, W, 3) frames against their (H, W, 3) plate: 1.4826 × the median absolute
    per-channel difference (most pixels are background), at least ``floor``."""
    diff = np.abs(frames - plate[None]).reshape(-1)
    if diff.size > 2_000_000:
        diff = diff[:: diff.size // 2_000_000]
    return max(float(1.4826 * np.median(diff)), floor)


def texture_correlation(frames: np.ndarray, plate: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised correlation (T, H, W) of the grey frames (T, H, W, 3) with the grey plate (H, W, 3) in
    ``window``² windows, and the plate's local std (H, W)."""
    k = (1, window, window)
    g = frames.mean(-1)
    b = np.broadcast_to(plate.mean(-1)[None], g.shape)
    f = lambda x: ndimage.uniform_filter(x, k, mode="nearest")  # noqa: E731
    mg, mb = f(g), f(b)
    cov = f(g * b) - mg * mb
    vg = np.maximum(f(g * g) - mg * mg, 0.0)
    vb = np.maximum(f(b * b) - mb * mb, 0.0)
    return cov / np.sqrt(np.maximum(vg * vb, 1e-12)), np.sqrt(vb[0])


def object_score(frames: np.ndarray, plate: np.ndarray, sigma: float, config: MaskConfig) -> np.ndarray:
    """The object score s (T, H, W) of blurred frames (T, H, W, 3) against a blurred plate (H, W, 3).

    Besides the module docstring's three terms, a darkening that does not keep the plate's texture (normalised
    correlation below ``shadow_min_correlation`` where the plate is textured) is no shadow: it scores its depth
    ``(1 − a)·|B| / σ``."""
    B = plate[None].astype(np.float32)
    bb = np.maximum((B * B).sum(-1), 1e-6)
    a = (frames * B).sum(-1) / bb
    c = np.linalg.norm(frames - a[..., None] * B, axis=-1)
    nb = np.sqrt(bb)
    chroma = c / (sigma + config.shadow_chroma_tolerance * np.clip(a, 0, None) * nb)
    brighter = (a - 1.0) * nb / sigma
    darker = (config.shadow_min_brightness - a) * nb / sigma
    score = np.maximum(chroma, np.maximum(brighter, darker))
    shadow_like = (chroma < 2.0) & (a > config.shadow_min_brightness) & ((1.0 - a) * nb > 4.0 * sigma)
    if config.shadow_band >= 0 and shadow_like.sum() >= 50:
        ratios = a[shadow_like]
        counts, edges = np.histogram(ratios, bins=50, range=(config.shadow_min_brightness, 1.0))
        k = int(np.argmax(counts))
        mode = 0.5 * (edges[k] + edges[k + 1])
        near = ratios[np.abs(ratios - mode) < 0.1]
        mad = 1.4826 * float(np.median(np.abs(near - mode))) if len(near) else 0.0
        floor_ratio = max(config.shadow_min_brightness, mode - max(config.shadow_band, 3.0 * mad))
        score = np.maximum(score, (floor_ratio - a) * nb / sigma)
    if config.shadow_min_correlation > -1:
        window = max(3, int(round(config.shadow_texture_window * frames.shape[1] / 128.0)) | 1)
        ncc, texture = texture_correlation(frames, plate, window)
        # the texture a shadow would keep is the plate's, scaled by the darkening: it must stand out of the noise
        textured = np.clip(a, 0.0, 1.0) * texture[None] > config.shadow_texture_min * sigma
        unexplained = textured & (ncc < config.shadow_min_correlation)
        score = np.where(unexplained, np.maximum(score, (1.0 - a) * nb / sigma), score)
    return score.astype(np.float32)


def hysteresis(score: np.ndarray, high: float, low: float) -> np.ndarray:
    """(T, H, W) bool: pixels above ``low`` 6-connected in (t, y, x) to a pixel above ``high``."""
    weak = score > low
    labels, n = ndimage.label(weak)
    if n == 0:
        return weak
    keep = np.zeros(n + 1, dtype=bool)
    keep[np.unique(labels[score > high])] = True
    keep[0] = False
    return keep[labels]


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of a (H, W) bool mask."""
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n <= 1:
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def clean(mask: np.ndarray, config: MaskConfig, scale: float) -> np.ndarray:
    """Opening, closing, hole filling and the largest component of one (H, W) bool mask."""
    if config.open_radius > 0:
        mask = ndimage.binary_opening(mask, _disk(config.open_radius * scale))
    if config.close_radius > 0:
        r = config.close_radius * scale
        pad = int(np.ceil(r)) + 1
        mask = ndimage.binary_closing(np.pad(mask, pad), _disk(r))[pad:-pad, pad:-pad]
    if config.fill_holes:
        mask = ndimage.binary_fill_holes(mask)
    return largest_component(mask)


def soft_edges(mask: np.ndarray, frame: np.ndarray, plate: np.ndarray, sigma: float, width: float = 2.0,
               depth: float = 3.0) -> np.ndarray:
    """Fractional coverage (H, W) float32 in a band of ``width`` px on both sides of a (H, W) bool mask's boundary.

    A band pixel's colour I is explained as ``α·F + β·B``: F the colour of the nearest object pixel at least
    ``depth`` px inside the boundary (the object's own colour, unmixed), B the plate, and β = (1 − α)·(shadow
    factor) — the background there may lie in the object's shadow, which only scales it. The 2 × 2 least-squares
    solution gives α; where F and B have nearly the same chromaticity the two cannot be told apart and the plain
    projection ``<I − B, F − B> / |F − B|²`` is used, and where F and B are too alike altogether (|F − B| < 6σ) the
    binary value is kept."""
    out = mask.astype(np.float32)
    if not mask.any():
        return out
    inside = ndimage.distance_transform_edt(mask)
    outside = ndimage.distance_transform_edt(~mask)
    band = (mask & (inside <= width)) | (~mask & (outside <= width))
    core = inside >= depth
    if not core.any():
        core = inside >= max(1.0, float(inside.max()) - 1.0)
    if not band.any():
        return out
    _, (iy, ix) = ndimage.distance_transform_edt(~core, return_indices=True)
    ys, xs = np.nonzero(band)
    F = frame[iy[ys, xs], ix[ys, xs]].astype(np.float64)
    I, B = frame[ys, xs].astype(np.float64), plate[ys, xs].astype(np.float64)
    ff, bb, fb = (F * F).sum(-1), (B * B).sum(-1), (F * B).sum(-1)
    fi, bi = (F * I).sum(-1), (B * I).sum(-1)
    det = ff * bb - fb * fb
    a_ls = (fi * bb - bi * fb) / np.maximum(det, 1e-12)
    b_ls = (ff * bi - fb * fi) / np.maximum(det, 1e-12)
    d = F - B
    dd = (d * d).sum(-1)
    a_plain = ((I - B) * d).sum(-1) / np.maximum(dd, 1e-12)
    separable = (det > 0.01 * ff * bb) & (b_ls >= 0)
    alpha = np.clip(np.where(separable, a_ls, a_plain), 0.0, 1.0)
    sure = dd > (6.0 * sigma) ** 2
    vals = out[ys, xs]
    vals[sure] = alpha[sure]
    out[ys, xs] = vals
    return out


def masks_from_plate(frames: np.ndarray, plate: np.ndarray, config: MaskConfig | None = None) -> MaskResult:
    """Masks of one camera from its frames and clean plate.

    Args:
        frames: (T, H, W, 3) float32 in [0, 1] (undistorted).
        plate: (H, W, 3) float32 in [0, 1], the same view without the object.
        config: the test's settings.
    """
    config = MaskConfig() if config is None else config
    T, H, W, _ = frames.shape
    scale = H / 128.0
    F = blur(frames.astype(np.float32), config.blur_sigma)
    B = blur(plate.astype(np.float32), config.blur_sigma)
    sigma = noise_level(F, B, config.noise_floor)
    score = object_score(F, B, sigma, config)
    detected = hysteresis(score, config.high, config.low)
    masks = np.zeros((T, H, W), np.float32)
    confidence = np.zeros(T)
    stray = np.zeros(T)
    for t in range(T):
        m = clean(detected[t], config, scale)
        supported = detected[t] & m
        confidence[t] = supported.sum() / max(m.sum(), 1)
        outside = ~ndimage.binary_dilation(m, iterations=max(1, int(round(2 * scale))))
        stray[t] = (score[t][outside] > config.low).mean() if outside.any() else 0.0
        masks[t] = soft_edges(m, frames[t].astype(np.float32), plate.astype(np.float32), sigma,
                              width=config.edge_width, depth=config.edge_depth) if config.soft_edges \
            else m.astype(np.float32)
    return summarise(masks, confidence, sigma, stray, config)


def summarise(masks: np.ndarray, confidence: np.ndarray, noise: float, stray: np.ndarray,
              config: MaskConfig) -> MaskResult:
    """Area, border, empty and jump flags of (T, H, W) masks."""
    T, H, W = masks.shape
    area = masks.reshape(T, -1).sum(1)
    binary = masks > 0.5
    border = binary[:, 0, :].any(1) | binary[:, -1, :].any(1) | binary[:, :, 0].any(1) | binary[:, :, -1].any(1)
    empty = area < max(4.0, 1e-4 * H * W)
    jump = np.zeros(T, bool)
    ratio = config.jump_ratio
    for t in range(1, T):
        a, b = area[t - 1], area[t]
        if a > 0 and b > 0 and (b / a > ratio or a / b > ratio):
            jump[t] = True
    return MaskResult(masks, area, confidence, border, empty, jump, noise, stray)
