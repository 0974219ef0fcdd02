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
filled — except those through which the plate is seen, at its own brightness or its texture in shadow
(:func:`see_through`) — and its largest component kept (and the fringe of found pixels the opening took,
:func:`clean`). At the boundary the mask is made soft: a pixel's coverage is its colour's position between the
background just outside (the plate, darkened by the shadow measured there) and the nearby object colour
(:func:`soft_edges`).

Each mask comes with its area, a confidence (the share of its pixels that the colour test supports directly, not
through filling) and flags: ``border`` (the object touches the image border), ``empty`` (no object) and
``jump`` (the area changes by more than half between neighbouring frames).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import cv2
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
            typical shadow (the mode of the brightness ratio over the shadow-like pixels, each weighted by its
            darkening) is measured per camera; a band of ``max(shadow_band, 3 MAD)`` below it and everything up to
            the background's brightness pass (``shadow_min_brightness`` bounds it from below; a negative band
            disables the measurement).
        shadow_min_correlation: the least agreement in that window between the frame and the plate darkened as a
            shadow would (:meth:`PlateTexture.correlation`, a normalised correlation where one darkening covers the
            window) for a darkening to pass as a shadow, where the texture it would keep stands out of the noise (the
            plate's local std times the darkening above ``shadow_texture_min`` σ).
        noise_floor: the smallest noise level σ assumed (a perfectly clean synthetic frame would give 0).
        open_radius, close_radius: radii (px at 128 px image height; scaled with the image) of the opening that
            removes specks and the closing that bridges gaps.
        fill_holes: fill holes inside the object (a colour the test missed inside it), except holes through which the
            background is seen (:func:`see_through`).
        hole_min_pixels: the least area (px at 128 px image height) of a hole that may stay open; smaller ones are
            filled.
        hole_min_brightness: the least median brightness ratio (frame over plate) across a hole for it to be the
            plate seen at its own brightness (:func:`see_through`).
        hole_texture_min: how far (in σ) the plate's brightness must vary within a hole (its local std) for its
            texture to be told from the noise (the second test of :func:`see_through`).
        hole_min_correlation: the least median, over a hole's pixels, of the local correlation between the frame's
            brightness and the plate's, darkened as a shadow would (:meth:`PlateTexture.correlation`), for the hole
            to be the background seen through the object.
        soft_edges: estimate fractional coverage in a band at the boundary (:func:`soft_edges`).
        edge_chroma_weight: the weight of the colour differences (Cb, Cr) against the luma there: below 1 for
            video and JPEG frames, whose colour differences have half the resolution (:func:`soft_edges`).
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
    hole_min_pixels: float = 6.0
    hole_min_brightness: float = 0.9
    hole_texture_min: float = 6.0
    hole_min_correlation: float = 0.8
    soft_edges: bool = True
    edge_width: float = 2.0
    edge_depth: float = 3.0
    edge_chroma_weight: float = 0.3
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
    """Gaussian blur over the two image axes of (..., H, W, C) float images (edges replicated; the kernel cut at
    2.5 σ, as ``scipy.ndimage.gaussian_filter(mode="nearest", truncate=2.5)``), float32."""
    if sigma <= 0:
        return images
    size = 2 * int(2.5 * sigma + 0.5) + 1
    flat = np.asarray(images, dtype=np.float32).reshape((-1,) + images.shape[-3:])
    out = np.empty(flat.shape, np.float32)
    for i, image in enumerate(flat):
        out[i] = cv2.GaussianBlur(image, (size, size), sigma, borderType=cv2.BORDER_REPLICATE)
    return out.reshape(images.shape)


def distance_to_background(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance (H, W) float64 of every pixel of a bool mask to the nearest pixel outside it (0 outside),
    exactly as ``scipy.ndimage.distance_transform_edt`` (OpenCV's exact transform, squared and rounded back to
    the integer it is the root of)."""
    d = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)
    return np.sqrt(np.round(d * d))


def noise_level(frames: np.ndarray, plate: np.ndarray, floor: float) -> float:
    """Robust noise level σ of (T, H, W, 3) frames against their (H, W, 3) plate: 1.4826 × the median absolute
    per-channel difference (most pixels are background), at least ``floor``."""
    flat = frames.reshape(-1)
    step = max(1, flat.size // 2_000_000) if flat.size > 2_000_000 else 1
    idx = np.arange(0, flat.size, step)
    diff = np.abs(flat[idx] - plate.reshape(-1)[idx % plate.size])  # = |frames − plate| at every step-th value
    return max(float(1.4826 * np.median(diff)), floor)


def box_mean(image: np.ndarray, window: int) -> np.ndarray:
    """The mean of a (H, W) float32 image over ``window``² windows (odd; edges replicated, as
    ``scipy.ndimage.uniform_filter(mode="nearest")``)."""
    return cv2.boxFilter(np.ascontiguousarray(image, dtype=np.float32), -1, (window, window), normalize=True,
                         borderType=cv2.BORDER_REPLICATE)


@dataclass
class PlateTexture:
    """The grey plate (H, W) and its local statistics in ``window``² windows, for :meth:`correlation`; ``std``
    (H, W) is its local standard deviation."""

    grey: np.ndarray
    window: int

    def __post_init__(self) -> None:
        self.grey = np.asarray(self.grey, dtype=np.float32)
        square = self.grey * self.grey
        mean = box_mean(self.grey, self.window)
        self.var = np.maximum(box_mean(square, self.window) - mean * mean, 0.0)
        self.std = np.sqrt(self.var)
        self.gain_window = max(3, (self.window // 2) | 1)
        self.power = box_mean(square, self.gain_window)

    def correlation(self, grey: np.ndarray) -> np.ndarray:
        """How well a shadow explains one grey frame (H, W) in the windows, on the scale of a normalised correlation:
        (H, W) in [0, 1], ``sqrt(1 − R)``, with ``R`` the energy of the residual ``I − g·B`` over the window against
        the texture energy ``g²·var(B)`` a shadow would keep there. ``g = box(I·B) / box(B·B)`` is the frame's local
        darkening, its least-squares ratio to the plate over a window of half the side, so that it follows a
        shadow's edge across the window (correlated with the plate alone, that edge read as object on a textured
        floor) but not the plate's texture. An object's own colours leave that texture in the residual (R ≈ 1)."""
        gain = box_mean(grey * self.grey, self.gain_window) / np.maximum(self.power, 1e-6)
        residual = box_mean(np.square(grey - gain * self.grey), self.window)
        return np.sqrt(np.clip(1.0 - residual / np.maximum(np.square(gain) * self.var, 1e-12), 0.0, 1.0))


def texture_window(config: MaskConfig, scale: float) -> int:
    """The side (odd, at least 3 px) of the windows the texture tests compare frame and plate in:
    ``shadow_texture_window`` scaled by ``scale`` = the image height / 128."""
    return max(3, int(round(config.shadow_texture_window * scale)) | 1)


def _shadow_floor(a: np.ndarray, shadow_like: np.ndarray, config: MaskConfig) -> float | None:
    """The darkest brightness ratio that still passes as this camera's shadow (``MaskConfig.shadow_band``), from
    the ratios ``a`` of the shadow-like pixels; None when fewer than 50 are."""
    if config.shadow_band < 0 or shadow_like.sum() < 50:
        return None
    ratios = a[shadow_like]
    # each pixel counts by its darkening: the penumbrae and the faint darkenings just past the noise pile up close
    # to 1 and, counted alone, can outnumber the shadow itself (a camera that sees little of it)
    counts, edges = np.histogram(ratios, bins=50, range=(config.shadow_min_brightness, 1.0), weights=1.0 - ratios)
    k = int(np.argmax(counts))
    mode = 0.5 * (edges[k] + edges[k + 1])
    near = ratios[np.abs(ratios - mode) < 0.1]
    mad = 1.4826 * float(np.median(np.abs(near - mode))) if len(near) else 0.0
    return max(config.shadow_min_brightness, mode - max(config.shadow_band, 3.0 * mad))


def object_score(frames: np.ndarray, plate: np.ndarray, sigma: float, config: MaskConfig) -> np.ndarray:
    """The object score s (T, H, W) of blurred frames (T, H, W, 3) against a blurred plate (H, W, 3).

    Besides the module docstring's three terms, a darkening that does not keep the plate's texture (normalised
    correlation with the darkened plate, :meth:`PlateTexture.correlation`, below ``shadow_min_correlation`` where
    the plate is textured) is no shadow: it scores its depth ``(1 − a)·|B| / σ``. Works frame by frame on colour
    planes (each frame's images stay in the cache; the shadow's brightness band needs every frame's ratios first)."""
    frames = np.asarray(frames, dtype=np.float32)
    B = np.ascontiguousarray(np.moveaxis(np.asarray(plate, dtype=np.float32), -1, 0))
    bb = np.maximum(B[0] * B[0] + B[1] * B[1] + B[2] * B[2], 1e-6)
    nb = np.sqrt(bb)
    nb_s = nb / sigma
    T = len(frames)
    a = np.empty(frames.shape[:3], np.float32)
    score = np.empty(frames.shape[:3], np.float32)
    shadow_like = np.empty(frames.shape[:3], bool)
    for t in range(T):
        F = np.moveaxis(frames[t], -1, 0)
        at = a[t]
        np.divide(F[0] * B[0] + F[1] * B[1] + F[2] * B[2], bb, out=at)
        c2 = np.square(F[0] - at * B[0])
        c2 += np.square(F[1] - at * B[1])
        c2 += np.square(F[2] - at * B[2])
        chroma = np.sqrt(c2, out=c2)
        chroma /= sigma + config.shadow_chroma_tolerance * np.maximum(at, 0) * nb
        st = score[t]
        np.maximum(chroma, (at - 1.0) * nb_s, out=st)
        np.maximum(st, (config.shadow_min_brightness - at) * nb_s, out=st)
        shadow_like[t] = (chroma < 2.0) & (at > config.shadow_min_brightness) & ((1.0 - at) * nb > 4.0 * sigma)
    floor_ratio = _shadow_floor(a, shadow_like, config)
    del shadow_like
    if config.shadow_min_correlation > -1:
        texture = PlateTexture((B[0] + B[1] + B[2]) / 3.0, texture_window(config, frames.shape[1] / 128.0))
    for t in range(T):
        at, st = a[t], score[t]
        if floor_ratio is not None:
            np.maximum(st, (floor_ratio - at) * nb_s, out=st)
        if config.shadow_min_correlation > -1:
            F = np.moveaxis(frames[t], -1, 0)
            ncc = texture.correlation((F[0] + F[1] + F[2]) / np.float32(3.0))
            # the texture a shadow would keep is the plate's, scaled by the darkening: it must stand out of the noise
            unexplained = (np.clip(at, 0.0, 1.0) * texture.std > config.shadow_texture_min * sigma) & \
                (ncc < config.shadow_min_correlation)
            st[unexplained] = np.maximum(st[unexplained], ((1.0 - at) * nb_s)[unexplained])
    return score


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


def erode(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """Binary erosion of a (H, W) bool mask by a symmetric structure, the outside of the image counting as
    background (``scipy.ndimage.binary_erosion``'s default; OpenCV's morphology is several times faster)."""
    out = cv2.erode(mask.astype(np.uint8), structure.astype(np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool)


def dilate(mask: np.ndarray, structure: np.ndarray, iterations: int = 1) -> np.ndarray:
    """Binary dilation of a (H, W) bool mask by a symmetric structure, ``iterations`` times (as
    ``scipy.ndimage.binary_dilation``)."""
    out = cv2.dilate(mask.astype(np.uint8), structure.astype(np.uint8), iterations=iterations,
                     borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool)


CROSS = ndimage.generate_binary_structure(2, 1)


def see_through(frame: np.ndarray, plate: np.ndarray, sigma: float, config: MaskConfig,
                scale: float) -> Callable[[np.ndarray], bool]:
    """The test that a hole (a (H, W) bool component the object encloses, which the colour test did not find) shows
    the background. A hole of at least ``hole_min_pixels`` (scaled) pixels does when either

    * the plate shows through it at its own brightness: the median brightness ratio ``a = <I, B> / <B, B>`` over its
      pixels is at least ``hole_min_brightness``. What else the clean-up encloses is darker: parts of the object
      dark enough to pass for shadow (a ≈ 0.4–0.65 on the capture twins, where keeping every large hole open lost
      IoU); or
    * the plate's own texture shows through it, even in shadow: over its pixels the median normalised correlation
      between the frame's brightness and the plate's, darkened as a shadow would, in small windows (the shadow
      test's ``shadow_texture_window``) is at least ``hole_min_correlation``, where that texture stands out of the noise
      (the median of the plate's local std above ``hole_texture_min`` σ). A patch of the object keeps its own
      colours as it moves over the room; the hole shows whatever lies behind it.

    What stays filled: a hole in the object's shadow over a plain background (nothing tells it from a dark patch of
    the object), and a patch coloured and lit like the background behind it (nothing tells it from a hole).

    Args:
        frame: (H, W, 3) float32 in [0, 1] as filmed (blurred here by ``blur_sigma``, as the plate was).
        plate: (H, W, 3) float32, the plate blurred by ``blur_sigma``.
        sigma: the camera's noise level; scale: the image height / 128.
    """
    least = config.hole_min_pixels * scale * scale
    maps: dict[str, np.ndarray] = {}  # made on the first hole large enough to test: most frames have none

    def test(hole: np.ndarray) -> bool:
        if hole.sum() < least:
            return False
        if not maps:
            f = blur(frame, config.blur_sigma)
            maps["ratio"] = (f * plate).sum(-1) / np.maximum((plate * plate).sum(-1), 1e-6)
            texture = PlateTexture(plate.mean(-1), texture_window(config, scale))
            maps["std"], maps["ncc"] = texture.std, texture.correlation(f.mean(-1))
        if np.median(maps["ratio"][hole]) >= config.hole_min_brightness:
            return True
        return bool(np.median(maps["std"][hole]) >= config.hole_texture_min * sigma
                    and np.median(maps["ncc"][hole]) >= config.hole_min_correlation)

    return test


def fill_holes(mask: np.ndarray, keep_open: Callable[[np.ndarray], bool] | None = None) -> np.ndarray:
    """Fill the holes of a (H, W) bool mask, leaving open each hole (4-connected component of the filled pixels)
    for which ``keep_open(component)`` is true."""
    filled = ndimage.binary_fill_holes(mask)
    if keep_open is None:
        return filled
    labels, n = ndimage.label(filled & ~mask)
    for k in range(1, n + 1):
        hole = labels == k
        if keep_open(hole):
            filled &= ~hole
    return filled


def holes_filled(masks: np.ndarray) -> np.ndarray:
    """(T, H, W) coverage with every hole of each frame's mask (coverage above ½) filled: the silhouette whose
    outline alone counts. The object's track uses it: whether a hole opens depends on its light (a hole in the
    object's own shadow is filled, :func:`see_through`), and the shadow follows the object's height, so the masks'
    own holes would move the tracked centre with the height (the metric scale 1.0–2.4 % lower on three of four
    capture twins with holes)."""
    out = np.array(masks, dtype=np.float32, copy=True)
    for t, m in enumerate(out):
        inside = m > 0.5
        hole = ndimage.binary_fill_holes(inside) & ~inside
        m[hole] = 1.0
    return out


def clean(mask: np.ndarray, config: MaskConfig, scale: float,
          keep_open: Callable[[np.ndarray], bool] | None = None) -> np.ndarray:
    """Opening, closing, hole filling and the largest component of one (H, W) bool mask; then the pixels of ``mask``
    within the opening's radius of the result come back (and holes they close are filled). Holes for which
    ``keep_open`` (e.g. :func:`see_through`) is true stay open.

    The opening is there to drop specks and cut thin bridges to them; on an object whose colours come close to the
    background's in places (a stripe the colour of the floor) what the test finds of its outline is a comb, and the
    opening took the teeth with the specks — 100–180 of the 400 px a view missed per frame on such capture twins.
    Put back within its radius of the cleaned object, they return without the specks or the far ends of any bridge
    (mean soft IoU on twenty capture twins 0.949 → 0.951)."""
    found = mask
    if config.open_radius > 0:
        disk = _disk(config.open_radius * scale)
        mask = dilate(erode(mask, disk), disk)
    if config.close_radius > 0:
        disk = _disk(config.close_radius * scale)
        pad = int(np.ceil(config.close_radius * scale)) + 1
        mask = erode(dilate(np.pad(mask, pad), disk), disk)[pad:-pad, pad:-pad]
    if config.fill_holes:
        mask = fill_holes(mask, keep_open)
    mask = largest_component(mask)
    if config.open_radius > 0:
        mask = mask | (found & dilate(mask, _disk(config.open_radius * scale)))
        if config.fill_holes:
            mask = fill_holes(mask, keep_open)
    return mask


#: RGB → Y'CbCr (BT.601): the luma and the two colour differences that video and JPEG codecs store
YCBCR = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])


def soft_edges(mask: np.ndarray, frame: np.ndarray, plate: np.ndarray, sigma: float, width: float = 2.0,
               depth: float = 3.0, chroma_weight: float = 0.3) -> np.ndarray:
    """Fractional coverage (H, W) float32 in a band of ``width`` px on both sides of a (H, W) bool mask's boundary.

    A band pixel's colour I is explained as ``α·F + (1 − α)·s·B``: F the colour of the nearest object pixel at least
    ``depth`` px inside the boundary (the object's own colour, unmixed), B the plate and s the background's shadow
    factor just outside the band — the brightness ratio ``<I, B> / <B, B>`` (3 × 3 mean) at the nearest pixel 1–2 px
    beyond it, clipped to [0.25, 1]: the object's own shadow often borders its bottom, and what lies behind an
    outline there is the darkened floor, not the plate. The projection ``α = <I − s·B, F − s·B> / |F − s·B|²``
    solves it; where F and the background are too alike (``|F − s·B| < 6σ``) the binary value is kept.

    Why s is measured and not solved for per pixel: with s free (``I = α·F + β·B`` by least squares) a pixel of
    shadow beside a dark object reads as part object, so the masks grow at the bottom by a rim that thickens as the
    object nears its shadow — on the capture twins that read as extra gravity, the metric scale 3–6 % low on five
    of twelve; measured outside, the rim goes and the mean |scale error| falls from 2.5 % to 1.0 % (and the mean
    soft IoU rises from 0.940 to 0.950).

    The colours are compared in Y'CbCr with the two colour differences weighted by ``chroma_weight``: video codecs
    (H.264's usual 4:2:0) and JPEG store them at half the resolution, so at an outline they are smeared over twice
    the pixels the luma is, and weighted fully they pull α towards the wrong side (0.3 was chosen on six capture
    twins of a small suite; 1 weighs them like the luma, for frames stored at full chroma resolution, e.g. PNG)."""
    out = mask.astype(np.float32)
    if not mask.any():
        return out
    inside = distance_to_background(mask)
    outside = distance_to_background(~mask)
    band = (mask & (inside <= width)) | (~mask & (outside <= width))
    ring = ~mask & (outside > width) & (outside <= width + 2.0)
    core = inside >= depth
    if not core.any():
        core = inside >= max(1.0, float(inside.max()) - 1.0)
    if not band.any() or not ring.any():
        return out
    _, (iy, ix) = ndimage.distance_transform_edt(~core, return_indices=True)
    _, (ry, rx) = ndimage.distance_transform_edt(~ring, return_indices=True)
    ratio = box_mean((frame * plate).sum(-1), 3) / np.maximum(box_mean((plate * plate).sum(-1), 3), 1e-6)
    ys, xs = np.nonzero(band)
    s = np.clip(ratio[ry[ys, xs], rx[ys, xs]], 0.25, 1.0)[:, None].astype(np.float64)
    M = np.diag([1.0, chroma_weight, chroma_weight]) @ YCBCR
    F = frame[iy[ys, xs], ix[ys, xs]].astype(np.float64) @ M.T
    I = frame[ys, xs].astype(np.float64) @ M.T
    B = s * (plate[ys, xs].astype(np.float64) @ M.T)
    d = F - B
    dd = (d * d).sum(-1)
    alpha = np.clip(((I - B) * d).sum(-1) / np.maximum(dd, 1e-12), 0.0, 1.0)
    sure = dd > (6.0 * sigma) ** 2 * float(np.trace(M @ M.T)) / 3.0  # σ² per RGB channel, carried through M
    vals = out[ys, xs]
    vals[sure] = alpha[sure]
    out[ys, xs] = vals
    return out


def object_box(detected: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """The rows and columns (slices) of a (H, W) bool mask's bounding box grown by ``margin`` px (clipped to the
    image), or None for an empty mask."""
    rows = np.flatnonzero(detected.any(1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(detected.any(0))
    H, W = detected.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, H)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, W)))


def masks_from_plate(frames: np.ndarray, plate: np.ndarray, config: MaskConfig | None = None) -> MaskResult:
    """Masks of one camera from its frames and clean plate.

    The clean-up, the soft edges and the stray count of each frame work on the box around what the test found,
    grown by more than any of their operations reaches (the result is the same as on the whole frame: every
    pixel outside the box is background to all of them).

    Args:
        frames: (T, H, W, 3) float32 in [0, 1] (undistorted).
        plate: (H, W, 3) float32 in [0, 1], the same view without the object.
        config: the test's settings.
    """
    config = MaskConfig() if config is None else config
    frames = np.asarray(frames, dtype=np.float32)
    plate = np.asarray(plate, dtype=np.float32)
    T, H, W, _ = frames.shape
    scale = H / 128.0
    F = blur(frames, config.blur_sigma)
    B = blur(plate, config.blur_sigma)
    sigma = noise_level(F, B, config.noise_floor)
    score = object_score(F, B, sigma, config)
    del F
    detected = hysteresis(score, config.high, config.low)
    grow = max(1, int(round(2 * scale)))
    margin = int(np.ceil(2 * config.close_radius * scale + config.open_radius * scale + config.edge_width)) + grow + 3
    masks = np.zeros((T, H, W), np.float32)
    confidence = np.zeros(T)
    stray = np.zeros(T)
    for t in range(T):
        hits = score[t] > config.low
        box = object_box(detected[t], margin)
        if box is None:
            stray[t] = hits.mean()
            continue
        d = detected[t][box]
        holes = see_through(frames[t][box], B[box], sigma, config, scale) if config.fill_holes else None
        m = clean(d, config, scale, holes)
        confidence[t] = (d & m).sum() / max(m.sum(), 1)
        near = dilate(m, CROSS, grow)
        outside = H * W - int(near.sum())
        stray[t] = (int(hits.sum()) - int(hits[box][near].sum())) / outside if outside > 0 else 0.0
        masks[t][box] = soft_edges(m, frames[t][box], plate[box], sigma, width=config.edge_width,
                                   depth=config.edge_depth, chroma_weight=config.edge_chroma_weight) \
            if config.soft_edges else m
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
