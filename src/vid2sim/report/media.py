"""The report's pictures and videos: side-by-side panels, error heat maps, labels, encoding.

Every picture is a uint8 array (…, H, W, 3). A *panel* is one image column (ground truth, reconstruction,
|error|, or one camera); :func:`compose_video` puts panels side by side under a strip of column headings
and over a strip that labels every frame (frame number, time, PSNR, and whether the frame was observed or is
a future frame predicted by the simulator, with a timeline whose colours mark the boundary).

Videos are VP9 in WebM (:func:`encode_video`, through the ffmpeg of ``imageio-ffmpeg``): Chromium, Chrome,
Edge and Firefox play it from ``file://`` without proprietary codecs. Animated WebP is the fallback that always
plays (shown as an image).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

from vid2sim.report.config import FUTURE_COLOUR, OBSERVED_COLOUR
from vid2sim.runtime.errors import InputError
from vid2sim.scene.video import ffmpeg_rate, probe_video

HEADER_HEIGHT = 50
"""Pixels of the strip of column headings above the panels of a video or strip."""
FOOTER_HEIGHT = 40
"""Pixels of the strip below a video's panels: frame label, PSNR, observed/future tag, timeline."""
STRIP_BG = (31, 35, 40)
STRIP_FG = (240, 242, 245)
STRIP_DIM = (160, 168, 178)


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    h = hex_colour.lstrip("#")
    return tuple(int(h[i:i + 2], 16) for i in (0, 2, 4))  # type: ignore[return-value]


@lru_cache(maxsize=16)
def font(size: int, bold: bool = False) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    """DejaVu Sans (bold or regular) at ``size`` px when the system has it, else Pillow's built-in scalable
    font (the bitmap font when Pillow has no FreeType)."""
    try:
        return ImageFont.truetype("DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf", size)
    except OSError:
        pass
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # pragma: no cover - Pillow < 10.1
        return ImageFont.load_default()


def to_uint8(images: Tensor | np.ndarray) -> np.ndarray:
    """Images in [0, 1] (float) or 0..255 (uint8), any leading shape (…, H, W, 3) → uint8 numpy array."""
    if isinstance(images, Tensor):
        images = images.detach().cpu()
        if images.dtype == torch.uint8:
            return images.numpy()
        return (images.float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    arr = np.asarray(images)
    if arr.dtype == np.uint8:
        return arr
    return (np.clip(arr.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)


def scale_factor(size: int, target: int) -> int:
    """The integer factor that brings an image side ``size`` nearest ``target``: > 0 to enlarge (nearest
    neighbour), < 0 to shrink by area averaging (−2 halves), 1 to keep."""
    if size >= target:
        return 1 if size < 1.5 * target else -math.ceil(size / target)
    return max(1, round(target / size))


def rescale(images: np.ndarray, factor: int) -> np.ndarray:
    """Scale uint8 images (…, H, W, 3) by the integer ``factor`` of :func:`scale_factor`."""
    if factor == 1:
        return images
    if factor > 1:
        return images.repeat(factor, axis=-3).repeat(factor, axis=-2)
    f = -factor
    h, w = images.shape[-3] // f * f, images.shape[-2] // f * f
    x = images[..., :h, :w, :].astype(np.float32)
    x = x.reshape(*x.shape[:-3], h // f, f, w // f, f, 3).mean(axis=(-4, -2))
    return (x + 0.5).astype(np.uint8)


def crop_box(masks: Tensor, renders: Tensor, margin: float = 0.12, min_side: int = 16) -> tuple[int, int, int, int]:
    """The square (where the image allows) around everything that appears in one view over a whole video.

    Args:
        masks: (T, H, W) ground-truth object masks in [0, 1].
        renders: (T, H, W, 3) renders on a white background, in [0, 1].
        margin: added on every side, as a fraction of the box's larger side.
        min_side: the smallest side in pixels.
    Returns:
        (y0, y1, x0, x1), half-open pixel ranges; the whole image when nothing is visible.
    """
    H, W = masks.shape[-2:]
    seen = (masks > 0.5).any(0) | (renders < 0.97).any(-1).any(0)
    if not bool(seen.any()):
        return 0, H, 0, W
    ys, xs = torch.nonzero(seen.any(1)).flatten(), torch.nonzero(seen.any(0)).flatten()
    y0, y1, x0, x1 = int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
    side = max(y1 - y0, x1 - x0, min_side)
    side = int(math.ceil(side * (1 + 2 * margin)))
    side += side % 2  # even, so that panels scaled by any factor keep 4:2:0 video sides even

    def span(lo: int, hi: int, n: int) -> tuple[int, int]:
        size = min(side, n)
        start = min(max(0, (lo + hi - size) // 2), n - size)
        return start, start + size

    (y0, y1), (x0, x1) = span(y0, y1, H), span(x0, x1, W)
    return y0, y1, x0, x1


def colormap_lut(name: str) -> np.ndarray:
    """(256, 3) uint8 lookup table of a matplotlib colour map."""
    import matplotlib

    cmap = matplotlib.colormaps[name]
    return (np.asarray(cmap(np.linspace(0, 1, 256)))[:, :3] * 255 + 0.5).astype(np.uint8)


def error_heatmap(renders: Tensor, targets: Tensor, error_max: float, cmap: str = "magma") -> np.ndarray:
    """|renders − targets| averaged over RGB, divided by ``error_max`` (clipped to 1), as colour-mapped images.

    Args:
        renders, targets: (…, H, W, 3) floats in [0, 1], same shape.
    Returns:
        (…, H, W, 3) uint8.
    """
    err = (renders.float() - targets.float()).abs().mean(-1) / error_max
    idx = (err.clamp(0, 1) * 255 + 0.5).to(torch.long).cpu().numpy()
    return colormap_lut(cmap)[idx]


def _text_width(draw: ImageDraw.ImageDraw, text: str, fnt) -> int:
    left, _, right, _ = draw.textbbox((0, 0), text, font=fnt)
    return int(right - left)


def _gradient_bar(draw: ImageDraw.ImageDraw, box: tuple[int, int, int, int], lut: np.ndarray) -> None:
    x0, y0, x1, y1 = box
    for x in range(x0, x1):
        c = lut[int(round(255 * (x - x0) / max(1, x1 - x0 - 1)))]
        draw.line([(x, y0), (x, y1 - 1)], fill=tuple(int(v) for v in c))


def header_strip(width: int, panel_width: int, headings: Sequence[tuple[str, str]],
                 error_panel: int | None = None, error_max: float = 0.3, cmap: str = "magma") -> np.ndarray:
    """The column headings above side-by-side panels.

    Args:
        width: total width in pixels (≥ len(headings) · panel_width).
        headings: one (title, subtitle) per panel.
        error_panel: index of the error heat-map panel, whose subtitle line becomes a colour bar from 0 to
            ``error_max`` (the legend of the heat map), or None.
    Returns:
        (HEADER_HEIGHT, width, 3) uint8.
    """
    strip = Image.new("RGB", (width, HEADER_HEIGHT), STRIP_BG)
    draw = ImageDraw.Draw(strip)
    title_font, sub_font = font(19, bold=True), font(13)
    for i, (title, subtitle) in enumerate(headings):
        x0 = i * panel_width
        tw = _text_width(draw, title, title_font)
        draw.text((x0 + (panel_width - tw) / 2, 4), title, fill=STRIP_FG, font=title_font)
        if i == error_panel:
            lo, hi = "0", f"{error_max:g}"
            bar_w = max(20, min(140, panel_width - 70))
            lw, hw = _text_width(draw, lo, sub_font), _text_width(draw, hi, sub_font)
            total = lw + 6 + bar_w + 6 + hw
            bx = x0 + (panel_width - total) // 2
            draw.text((bx, 29), lo, fill=STRIP_DIM, font=sub_font)
            _gradient_bar(draw, (bx + lw + 6, 32, bx + lw + 6 + bar_w, 44), colormap_lut(cmap))
            draw.text((bx + lw + 6 + bar_w + 6, 29), hi, fill=STRIP_DIM, font=sub_font)
        elif subtitle:
            sw = _text_width(draw, subtitle, sub_font)
            draw.text((x0 + (panel_width - sw) / 2, 29), subtitle, fill=STRIP_DIM, font=sub_font)
        if i > 0:
            draw.line([(x0, 6), (x0, HEADER_HEIGHT - 6)], fill=(70, 76, 84))
    return np.asarray(strip)


def footer_strip(width: int, frame: int, num_frames: int, future: Sequence[bool], dt: float,
                 psnr: float | None = None, tags: tuple[str, str] = ("OBSERVED", "FUTURE · predicted")) -> np.ndarray:
    """The label under a video frame: ``frame t / T−1 · t = … s``, the frame's PSNR, an OBSERVED / FUTURE tag,
    and a timeline of all frames (observed cells green, future cells orange, the current one white).
    ``tags`` are the texts of the observed and the future tag.

    Returns:
        (FOOTER_HEIGHT, width, 3) uint8.
    """
    strip = Image.new("RGB", (width, FOOTER_HEIGHT), STRIP_BG)
    draw = ImageDraw.Draw(strip)
    fnt, bold = font(16), font(14, bold=True)
    draw.text((8, 5), f"frame {frame} / {num_frames - 1}    t = {frame * dt:.2f} s", fill=STRIP_FG, font=fnt)
    if psnr is not None:
        text = f"PSNR {psnr:.1f} dB"
        draw.text(((width - _text_width(draw, text, fnt)) / 2, 5), text, fill=STRIP_FG, font=fnt)
    is_future = bool(future[frame])
    tag = tags[1] if is_future else tags[0]
    colour = _rgb(FUTURE_COLOUR if is_future else OBSERVED_COLOUR)
    tw = _text_width(draw, tag, bold)
    draw.rounded_rectangle([width - tw - 20, 4, width - 6, 25], radius=5, fill=colour)
    draw.text((width - tw - 13, 6), tag, fill=(255, 255, 255), font=bold)
    # timeline: one cell per frame
    y0, y1 = 31, FOOTER_HEIGHT - 2
    for t in range(num_frames):
        x0 = round(t * width / num_frames)
        x1 = round((t + 1) * width / num_frames) - 1
        c = _rgb(FUTURE_COLOUR if future[t] else OBSERVED_COLOUR)
        if t == frame:
            draw.rectangle([x0, y0 - 2, x1, y1], fill=(255, 255, 255))
        else:
            draw.rectangle([x0, y0, x1, y1], fill=tuple(int(v * 0.75) for v in c))
    return np.asarray(strip)


def compose_video(panels: Sequence[np.ndarray], headings: Sequence[tuple[str, str]], future: Sequence[bool],
                  dt: float, psnr: Sequence[float] | None = None, error_panel: int | None = None,
                  error_max: float = 0.3, cmap: str = "magma",
                  tags: tuple[str, str] = ("OBSERVED", "FUTURE · predicted")) -> np.ndarray:
    """Side-by-side panels with column headings and per-frame labels.

    Args:
        panels: P arrays (T, h, w, 3) uint8 of one size (already scaled for display).
        headings: P (title, subtitle) pairs.
        future: T booleans, True for frames held out of the reconstruction (future prediction).
        dt: seconds between frames (for the time label).
        psnr: T PSNR values in dB shown on each frame, or None.
        error_panel: index of the heat-map panel (its heading gets the colour bar), or None.
        tags: the frame tags of observed and future frames.
    Returns:
        (T, HEADER_HEIGHT + h + FOOTER_HEIGHT, P · w, 3) uint8 (even sides, for 4:2:0 video).
    """
    if len(panels) != len(headings):
        raise InputError(f"{len(panels)} panels but {len(headings)} headings")
    T, h, w, _ = panels[0].shape
    for p in panels:
        if p.shape != panels[0].shape:
            raise InputError(f"panels differ in shape: {p.shape} and {panels[0].shape}")
    if len(future) != T or (psnr is not None and len(psnr) != T):
        raise InputError(f"future/psnr must hold {T} values")
    width = len(panels) * w
    body = np.concatenate(list(panels), axis=2)  # (T, h, P·w, 3)
    head = header_strip(width, w, headings, error_panel, error_max, cmap)
    frames = np.stack([np.concatenate([head, body[t], footer_strip(width, t, T, future, dt,
                                                                   None if psnr is None else psnr[t], tags)], axis=0)
                       for t in range(T)])
    return pad_even(frames)


def pad_even(frames: np.ndarray) -> np.ndarray:
    """Pad (…, H, W, 3) with dark pixels to even H and W (4:2:0 chroma subsampling needs them)."""
    ph, pw = frames.shape[-3] % 2, frames.shape[-2] % 2
    if not ph and not pw:
        return frames
    pad = [(0, 0)] * (frames.ndim - 3) + [(0, ph), (0, pw), (0, 0)]
    return np.pad(frames, pad, constant_values=STRIP_BG[0])


def labelled_grid(rows: Sequence[np.ndarray], row_labels: Sequence[str], column_labels: Sequence[str],
                  column_colours: Sequence[str] | None = None, label_width: int = 128) -> np.ndarray:
    """A still picture: R rows of C panels with row labels on the left and column labels on top.

    Args:
        rows: R arrays (C, h, w, 3) uint8.
        row_labels: R strings; column_labels: C strings (optionally on coloured tags, ``column_colours``).
    Returns:
        (28 + R·h, label_width + C·w, 3) uint8.
    """
    C, h, w, _ = rows[0].shape
    top = 28
    canvas = Image.new("RGB", (label_width + C * w, top + len(rows) * h), STRIP_BG)
    for r, row in enumerate(rows):
        canvas.paste(Image.fromarray(np.concatenate(list(row), axis=1)), (label_width, top + r * h))
    draw = ImageDraw.Draw(canvas)
    fnt, bold = font(13), font(14, bold=True)
    for r, label in enumerate(row_labels):
        lines = label.split("\n")
        y = top + r * h + h / 2 - 9 * len(lines)
        for line in lines:
            draw.text((8, y), line, fill=STRIP_FG, font=bold if line is lines[0] else fnt)
            y += 18
    for c, label in enumerate(column_labels):
        x0 = label_width + c * w
        colour = _rgb(column_colours[c]) if column_colours else STRIP_BG
        draw.rectangle([x0 + 1, 3, x0 + w - 2, top - 4], fill=colour)
        tw = _text_width(draw, label, fnt)
        draw.text((x0 + (w - tw) / 2, 6), label, fill=(255, 255, 255), font=fnt)
    return np.asarray(canvas)


def titled_panels(panels: Sequence[np.ndarray], titles: Sequence[str]) -> np.ndarray:
    """A still picture of panels (each (h, w, 3) uint8) side by side with a title above each (thumbnails)."""
    h, w, _ = panels[0].shape
    top = 20
    canvas = Image.new("RGB", (len(panels) * w, top + h), STRIP_BG)
    draw = ImageDraw.Draw(canvas)
    fnt = font(11)
    for i, (panel, title) in enumerate(zip(panels, titles)):
        canvas.paste(Image.fromarray(panel), (i * w, top))
        tw = _text_width(draw, title, fnt)
        draw.text((i * w + (w - tw) / 2, 3), title, fill=STRIP_FG, font=fnt)
    return np.asarray(canvas)


def save_png(path: Path, image: np.ndarray) -> Path:
    """Write a uint8 (H, W, 3) array as an optimised PNG."""
    Image.fromarray(image).save(path, format="PNG", optimize=True)
    return path


def encode_video(path: Path, frames: np.ndarray, fps: float, crf: int = 32, fmt: str = "webm",
                 threads: int = 1) -> Path:
    """Encode uint8 frames (T, H, W, 3) (even H and W) as VP9 WebM, or animated WebP.

    ``path`` is given without its suffix; the returned path has ``.webm`` or ``.webp``. A WebM encode that
    fails (an ffmpeg without libvpx-vp9) falls back to animated WebP with a warning.
    """
    if fmt == "webm":
        try:
            return _encode_webm(path.with_suffix(".webm"), frames, fps, crf, threads)
        except (OSError, RuntimeError, ValueError) as exc:
            warnings.warn(f"VP9 encoding of {path.name}.webm failed ({exc}); writing animated WebP instead")
    return _encode_webp(path.with_suffix(".webp"), frames, fps)


def _encode_webm(path: Path, frames: np.ndarray, fps: float, crf: int, threads: int) -> Path:
    import imageio_ffmpeg

    T, H, W, _ = frames.shape
    if H % 2 or W % 2:
        raise InputError(f"VP9 4:2:0 needs even sides, got {W}x{H}")
    writer = imageio_ffmpeg.write_frames(
        str(path), (W, H), pix_fmt_in="rgb24", pix_fmt_out="yuv420p", fps=ffmpeg_rate(fps),
        codec="libvpx-vp9", macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-crf", str(crf), "-b:v", "0", "-deadline", "realtime", "-cpu-used", "6", "-row-mt", "1",
                       "-threads", str(max(1, threads)), "-g", str(max(1, T)), "-an"])
    try:
        writer.send(None)
        for frame in frames:
            writer.send(np.ascontiguousarray(frame))
    finally:
        writer.close()
    if not path.is_file() or path.stat().st_size == 0:
        raise RuntimeError(f"ffmpeg wrote nothing to {path}")
    return path


def _encode_webp(path: Path, frames: np.ndarray, fps: float) -> Path:
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, format="WEBP", save_all=True, append_images=images[1:], duration=round(1000 / fps),
                   loop=0, quality=80, method=4)
    return path


def video_frame_count(path: Path) -> tuple[int, int, int]:
    """(frames, width, height) of a report video (WebM through ffmpeg, WebP through Pillow) — for checks."""
    if path.suffix == ".webp":
        with Image.open(path) as im:
            return int(getattr(im, "n_frames", 1)), im.width, im.height

    info = probe_video(path)
    return info.num_frames, info.width, info.height
