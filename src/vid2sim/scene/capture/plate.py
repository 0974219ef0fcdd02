"""Clean plates: checking a given one against the video (did the camera move?), or estimating one from the video
when none was filmed.

**Moving camera.** The plate and the first frames must show the same static background: the image shift between
them (phase correlation of the grey images, which the object, a small part of the view, barely moves) must be
under a pixel, and most of the frame outside the object must match the plate.

**No plate.** The background of a pixel is what it shows while the object is elsewhere. Start from the temporal
median of every pixel, which is right wherever the object stays less than half of the time; where it rests
longer (its final position) the median shows the object itself. Masks against that median then find, in the
frames before the object arrives, a "ghost" there: a region that differs from the median though nothing is in
it. A real object has its own outline in the frame, a ghost has it in the median instead, so each region is
judged by where the edges along its border are stronger; a ghost's pixels take their plate from the frames in
which it shows. Then plate and masks are refined twice: the plate of a pixel is its median over the frames whose
(dilated) masks leave it free; pixels never free keep the median and are reported as unknown.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from vid2sim.scene.capture.masks import MaskConfig, blur, clean, hysteresis, noise_level, object_score


def image_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The translation (dx, dy) in pixels of image ``b`` (H, W, 3) relative to ``a`` (phase correlation of grey
    images under a Hann window), and the correlation peak's strength in [0, 1]."""
    ga = a.astype(np.float32).mean(-1)
    gb = b.astype(np.float32).mean(-1)
    window = cv2.createHanningWindow((ga.shape[1], ga.shape[0]), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(ga, gb, window)
    return float(np.hypot(dx, dy)), float(response)


@dataclass
class PlateEstimate:
    """A plate estimated from a video.

    Attributes:
        plate: (H, W, 3) float32 in [0, 1].
        unknown: (H, W) bool, pixels the object never left (their plate is a guess).
        ghosts: how many regions were found to hold the object in the temporal median.
    """

    plate: np.ndarray
    unknown: np.ndarray
    ghosts: int


def _edge_strength(image: np.ndarray, ring: np.ndarray) -> float:
    gx = ndimage.sobel(image.mean(-1), axis=1)
    gy = ndimage.sobel(image.mean(-1), axis=0)
    return float(np.hypot(gx, gy)[ring].mean()) if ring.any() else 0.0


def estimate_plate(frames: np.ndarray, config: MaskConfig | None = None, rounds: int = 2) -> PlateEstimate:
    """The background (H, W, 3) of frames (T, H, W, 3) float32 in [0, 1] (module docstring)."""
    config = MaskConfig() if config is None else config
    T, H, W, _ = frames.shape
    scale = H / 128.0
    F = blur(frames.astype(np.float32), config.blur_sigma)
    plate = np.median(frames, axis=0).astype(np.float32)
    ghosts = 0
    # regions where the median holds the object: they differ from the median in the frames before it arrives
    B = blur(plate, config.blur_sigma)
    sigma = noise_level(F, B, config.noise_floor)
    score = object_score(F, B, sigma, config)
    detected = hysteresis(score, config.high, config.low)
    fixed = np.zeros((H, W), bool)
    for t in range(T):
        labels, n = ndimage.label(ndimage.binary_closing(detected[t], iterations=2))
        for k in range(1, n + 1):
            region = labels == k
            if region.sum() < 16 * scale * scale or (fixed & region).mean() > 0.5:
                continue
            ring = ndimage.binary_dilation(region, iterations=2) & ~ndimage.binary_erosion(region, iterations=2)
            if _edge_strength(B, ring) > 1.2 * _edge_strength(F[t], ring):
                # the median has the outline: a ghost; its plate comes from the frames where it shows the background
                showing = [s for s in range(T) if detected[s][region].mean() > 0.5]
                plate[region] = np.median(frames[showing][:, region], axis=0)
                fixed |= region
                ghosts += 1
    unknown = np.zeros((H, W), bool)
    for _ in range(rounds):
        B = blur(plate, config.blur_sigma)
        sigma = noise_level(F, B, config.noise_floor)
        detected = hysteresis(object_score(F, B, sigma, config), config.high, config.low)
        occupied = np.stack([ndimage.binary_dilation(clean(detected[t], config, scale),
                                                     iterations=max(1, int(round(2 * scale)))) for t in range(T)])
        free = ~occupied
        count = free.sum(0)
        unknown = count == 0
        masked = np.where(free[..., None], frames, np.nan)
        with warnings.catch_warnings():  # pixels never free give an all-NaN median; they keep the old plate
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(masked, axis=0)
        plate = np.where(unknown[..., None], plate, med).astype(np.float32)
    return PlateEstimate(plate, unknown, ghosts)
