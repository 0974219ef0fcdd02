"""Reading and writing per-camera video files (mp4 and anything else ffmpeg reads).

Videos go through the ffmpeg binary bundled with ``imageio-ffmpeg`` (no system ffmpeg, no PyAV
needed). Frames are (T, H, W, 3) tensors: float32 in [0, 1] or uint8 in [0, 255].

Two encodings are written:

* **lossy** (default): H.264 (``libx264``), ``yuv420p`` when width and height are even (plays in
  every browser and player), ``yuv444p`` otherwise (odd sizes cannot be chroma-subsampled) or
  when ``full_chroma=True`` (no colour bleeding across sharp edges; for data, not for browsers). The
  ``quality`` knob (1..10, 10 best) maps to x264's CRF as ``crf = int((1 - quality/10) * 51)``;
  the default 8 gives CRF 10, i.e. a maximum error of a few grey levels on smooth content.
* **lossless** (``lossless=True``): H.264 in RGB (``libx264rgb`` with ``-qp 0``); frames read back
  bit-exactly. Used for mask videos, where compression ringing would blur the object boundary.

Writes are atomic: the video is encoded into a temporary file next to the target, then renamed, so a
failed or interrupted encode never leaves a truncated file under the target name.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from vid2sim.runtime.errors import InputError
from vid2sim.runtime.limits import image_size_problem, max_array_bytes

__all__ = ["VideoInfo", "VideoError", "probe_video", "load_video", "read_video", "write_video"]


# colour conversion between RGB and YUV: accurate rounding and full chroma interpolation. ffmpeg's
# default (fast bilinear) decode alone adds ~3 grey levels of mean error; with these ~1.
_SWS_FLAGS = ("-sws_flags", "accurate_rnd+full_chroma_int")


class VideoError(InputError):
    """A video file could not be read or written (message names the file and the reason)."""


@dataclass(frozen=True)
class VideoInfo:
    """What ffmpeg reports about a video file.

    Attributes:
        width, height: frame size in pixels.
        fps: frames per second (0.0 when the container does not say).
        num_frames: number of decodable frames (counted by decoding, so exact).
        codec: a hint about the codec, e.g. ``"h264"``.
    """

    width: int
    height: int
    fps: float
    num_frames: int
    codec: str


def _ffmpeg():
    try:
        import imageio_ffmpeg
    except ImportError as exc:  # pragma: no cover - imageio-ffmpeg is a hard dependency
        raise VideoError(
            "video I/O needs the 'imageio-ffmpeg' package (pip install imageio-ffmpeg)"
        ) from exc
    return imageio_ffmpeg


def ffmpeg_rate(fps: float | Fraction) -> float:
    """The frame rate to hand ``imageio_ffmpeg.write_frames``: the rate rounded to a fraction with a denominator of
    at most 1001 (so 30000/1001 stays NTSC's rate), as a float. imageio-ffmpeg 0.8 takes a float back to that
    fraction; 0.6 accepts only floats and ints (a ``Fraction`` fails its assertion) and writes two decimals."""
    return float(Fraction(fps).limit_denominator(1001))


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise VideoError(f"video file '{path}' not found")
    if not path.is_file():
        raise VideoError(f"video path '{path}' is not a file")


def probe_video(path: str | Path) -> VideoInfo:
    """Size, frame rate and exact frame count of the video at ``path``.

    Raises:
        VideoError: the file is missing or ffmpeg cannot decode it.
    """
    path = Path(path)
    _check_readable(path)
    ff = _ffmpeg()
    try:
        gen = ff.read_frames(str(path))
        meta = next(gen)
        gen.close()
        num_frames, _ = ff.count_frames_and_secs(str(path))
    except (OSError, RuntimeError, StopIteration) as exc:
        raise VideoError(f"cannot read video '{path}': {_first_line(exc)}") from exc
    width, height = (int(v) for v in meta["size"])
    return VideoInfo(width, height, float(meta.get("fps") or 0.0), int(num_frames), str(meta.get("codec", "")))


def load_video(path: str | Path, dtype: torch.dtype = torch.float32) -> tuple[Tensor, VideoInfo]:
    """Decode every frame of a video and report its size, frame rate and codec.

    Args:
        path: the video file (mp4, mkv, avi, ... anything the bundled ffmpeg decodes).
        dtype: ``torch.float32``/``torch.float64`` for values in [0, 1], or ``torch.uint8``.

    Returns:
        frames: (T, H, W, 3) RGB tensor of ``dtype``; info: its :class:`VideoInfo` (num_frames = T).

    Raises:
        VideoError: the file is missing, cannot be decoded, or holds no frames.
    """
    path = Path(path)
    if dtype not in (torch.uint8, torch.float32, torch.float64):
        raise InputError(f"read_video: dtype must be torch.uint8, torch.float32 or torch.float64, got {dtype}")
    _check_readable(path)
    ff = _ffmpeg()
    frames: list[np.ndarray] = []
    try:
        gen = ff.read_frames(str(path), pix_fmt="rgb24", output_params=list(_SWS_FLAGS))
        meta = next(gen)
        width, height = (int(v) for v in meta["size"])
        too_big = image_size_problem(width, height)
        if too_big is not None:
            gen.close()
            raise VideoError(f"video '{path}': frames of {too_big}")
        budget = max_array_bytes()  # the decoded frames, as for an archive's arrays
        for raw in gen:
            frames.append(np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3))
            if len(frames) * width * height * 3 > budget:
                gen.close()
                raise VideoError(f"video '{path}': more than {budget} bytes of decoded frames (the limit; raise it "
                                 "with the environment variable VID2SIM_MAX_ARRAY_BYTES)")
    except VideoError:
        raise
    except (OSError, RuntimeError, StopIteration, ValueError) as exc:
        raise VideoError(f"cannot read video '{path}': {_first_line(exc)}") from exc
    if not frames:
        raise VideoError(f"video '{path}' contains no frames")
    out = torch.from_numpy(np.stack(frames))
    info = VideoInfo(width, height, float(meta.get("fps") or 0.0), len(frames), str(meta.get("codec", "")))
    if dtype != torch.uint8:
        out = out.to(dtype) / 255.0
    return out, info


def read_video(path: str | Path, dtype: torch.dtype = torch.float32) -> Tensor:
    """Decode every frame of a video: (T, H, W, 3) RGB, float in [0, 1] (or uint8 with ``dtype``).

    Same as ``load_video(path, dtype)[0]``; raises :class:`VideoError` on a missing/undecodable file.
    """
    return load_video(path, dtype)[0]


def _to_uint8_frames(frames: Tensor | np.ndarray) -> np.ndarray:
    """(T, H, W, 3) or (T, H, W) float [0, 1] / uint8 → C-contiguous (T, H, W, 3) uint8 array."""
    arr = frames.detach().cpu().numpy() if isinstance(frames, Tensor) else np.asarray(frames)
    if arr.ndim == 3:
        arr = np.repeat(arr[..., None], 3, axis=-1)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"write_video: frames must have shape (T, H, W, 3) or (T, H, W), got {tuple(arr.shape)}")
    if arr.shape[0] == 0 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise InputError(f"write_video: frames must be non-empty, got shape {tuple(arr.shape)}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"write_video: frames must be uint8 or floating point in [0, 1], got dtype {arr.dtype}")
    if not np.isfinite(arr).all():
        raise InputError("write_video: frames contain NaN or infinite values")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < -1e-6 or hi > 1 + 1e-6:
        raise InputError(f"write_video: float frames must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")
    return np.ascontiguousarray(np.clip(np.rint(arr * 255.0), 0, 255).astype(np.uint8))


def write_video(
    path: str | Path,
    frames: Tensor | np.ndarray,
    fps: float,
    *,
    quality: float = 8.0,
    lossless: bool = False,
    full_chroma: bool = False,
) -> Path:
    """Encode frames into a video file (atomically: temp file, then rename).

    Args:
        path: output file; its suffix picks the container (``.mp4`` recommended, ``.mkv`` works).
        frames: (T, H, W, 3) RGB or (T, H, W) grey frames, float in [0, 1] or uint8.
        fps: frame rate, > 0 (for a scene, ``1 / dt``); non-integer rates are stored as fractions.
        quality: 1..10 (10 best) for the lossy H.264 encoding; ignored when ``lossless``.
        lossless: encode with ``libx264rgb -qp 0`` so frames decode bit-exactly.
        full_chroma: keep colour at full resolution (``yuv444p``) instead of ``yuv420p``; sharper
            colour edges (e.g. an object against white) at the cost of browser playback.

    Returns:
        The path written.

    Raises:
        ValueError: bad frames/fps/quality. VideoError: ffmpeg failed (nothing is left at ``path``).
    """
    path = Path(path)
    data = _to_uint8_frames(frames)
    if not (isinstance(fps, (int, float, Fraction)) and float(fps) > 0 and np.isfinite(float(fps))):
        raise InputError(f"write_video: fps must be a positive number, got {fps!r}")
    if not lossless and not (1.0 <= float(quality) <= 10.0):
        raise InputError(f"write_video: quality must be in [1, 10], got {quality}")
    if not path.parent.is_dir():
        raise VideoError(f"cannot write video '{path}': folder '{path.parent}' does not exist")
    _, height, width, _ = data.shape
    if lossless:
        codec, pix_fmt, q, extra = "libx264rgb", "rgb24", None, ["-qp", "0"]
    else:
        pix_fmt = "yuv420p" if width % 2 == 0 and height % 2 == 0 and not full_chroma else "yuv444p"
        codec, q, extra = "libx264", float(quality), list(_SWS_FLAGS)
    ff = _ffmpeg()
    # a fresh name next to the target (same file system, so the final rename is atomic); ffmpeg
    # creates it with the usual permissions
    tmp = path.parent / f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"
    try:
        writer = ff.write_frames(
            str(tmp),
            (int(width), int(height)),
            pix_fmt_in="rgb24",
            pix_fmt_out=pix_fmt,
            fps=ffmpeg_rate(fps),
            quality=q,
            codec=codec,
            macro_block_size=1,
            ffmpeg_log_level="error",
            output_params=extra,
        )
        writer.send(None)
        for frame in data:
            writer.send(frame)
        writer.close()
        if tmp.stat().st_size == 0:
            raise VideoError(f"ffmpeg wrote an empty file for '{path}'")
        os.replace(tmp, path)
    except (OSError, RuntimeError, BrokenPipeError) as exc:
        tmp.unlink(missing_ok=True)
        raise VideoError(f"cannot write video '{path}': {_first_line(exc)}") from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
