"""Reading a camera's frames (a video or an image sequence), its clean plate and the user's masks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from vid2sim.scene.capture.errors import CaptureError
from vid2sim.scene.capture.layout import CameraSource
from vid2sim.scene.video import VideoError, load_video, probe_video


def read_rgb(path: Path, camera: str) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB (grey and RGBA are converted)."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = (np.asarray(img).astype(np.float64) / 257.0).round().clip(0, 255).astype(np.uint8)
                return np.repeat(arr[:, :, None], 3, axis=2)
            return np.asarray(img.convert("RGB"), dtype=np.uint8).copy()
    except (OSError, UnidentifiedImageError) as exc:
        raise CaptureError(f"cannot read the image: {exc}", camera=camera, file=path) from None


def read_grey(path: Path, camera: str) -> np.ndarray:
    """A mask image as (H, W) float32 in [0, 1] (8- or 16-bit grey, or the mean of RGB)."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode.startswith("I"):
                return (np.asarray(img).astype(np.float32) / 65535.0).clip(0, 1)
            return np.asarray(img.convert("L"), dtype=np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as exc:
        raise CaptureError(f"cannot read the mask: {exc}", camera=camera, file=path) from None


def frame_count(source: CameraSource) -> tuple[int, float | None, tuple[int, int]]:
    """(number of frames, frames per second or None, (width, height)) of a camera, without decoding every frame
    of an image sequence."""
    if source.video is not None:
        try:
            info = probe_video(source.video)
        except VideoError as exc:
            raise CaptureError(str(exc), camera=source.name, file=source.video) from None
        return info.num_frames, (info.fps or None), (info.width, info.height)
    assert source.frames
    first = read_rgb(source.frames[0], source.name)
    return len(source.frames), None, (first.shape[1], first.shape[0])


def read_frames(source: CameraSource, start: int, stop: int) -> np.ndarray:
    """Frames ``start`` … ``stop − 1`` of a camera: (T, H, W, 3) uint8."""
    if source.video is not None:
        try:
            video, _ = load_video(source.video, dtype=torch.uint8)
        except VideoError as exc:
            raise CaptureError(str(exc), camera=source.name, file=source.video) from None
        return video[start:stop].numpy()
    assert source.frames
    frames = [read_rgb(p, source.name) for p in source.frames[start:stop]]
    for p, f in zip(source.frames[start:stop], frames):
        if f.shape != frames[0].shape:
            raise CaptureError(f"frame size {f.shape[1]}x{f.shape[0]} differs from the first frame's "
                               f"{frames[0].shape[1]}x{frames[0].shape[0]}", camera=source.name, file=p)
    return np.stack(frames)


def read_masks(source: CameraSource, num_frames: int, start: int, stop: int, size: tuple[int, int]) -> np.ndarray:
    """The user's masks ``start`` … ``stop − 1`` of a camera: (T, H, W) float32 in [0, 1]; one per video frame."""
    assert source.masks is not None
    if len(source.masks) != num_frames:
        folder = source.masks[0].parent if source.masks else "masks/" + source.name
        raise CaptureError(f"{len(source.masks)} masks for {num_frames} frames; give one mask per frame",
                           camera=source.name, file=folder)
    masks = []
    for p in source.masks[start:stop]:
        m = read_grey(p, source.name)
        if (m.shape[1], m.shape[0]) != size:
            raise CaptureError(f"mask size {m.shape[1]}x{m.shape[0]} differs from the frames' {size[0]}x{size[1]}",
                               camera=source.name, file=p)
        masks.append(m)
    return np.stack(masks)
