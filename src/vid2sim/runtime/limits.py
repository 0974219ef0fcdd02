"""Limits on what a file from someone else may make vid2sim do, each raisable by an environment variable.

- ``VID2SIM_MAX_IMAGE_PIXELS`` (default 100 000 000): pixels of one image or video frame. A PNG of a few
  kilobytes can declare 100 000 × 100 000 pixels and take 30 GB to decode (a decompression bomb): its size is
  checked from the header before any pixel is decoded.
- ``VID2SIM_MAX_ARRAY_BYTES`` (default 4 GiB): bytes of the arrays of one ``.npz`` file once decompressed
  (checked from the archive's directory before anything is read).
- ``VID2SIM_ALLOW_OUTSIDE_PATHS`` (default unset): a scene's ``transforms.json`` / ``scene.json`` may name only
  files inside the scene folder (after following symlinks); set it to 1 to let a scene use files elsewhere (e.g.
  frames shared between scenes). An asset's files likewise.

docs/reliability.md lists them.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

from vid2sim.runtime.errors import InputError

DEFAULT_MAX_IMAGE_PIXELS = 100_000_000
DEFAULT_MAX_ARRAY_BYTES = 4 << 30


def _env_int(name: str, default: int) -> int:
    text = os.environ.get(name)
    if text is None or not text.strip():
        return default
    try:
        value = int(float(text))
    except ValueError:
        raise InputError(f"environment variable {name}={text!r}: expected a positive number") from None
    if value < 1:
        raise InputError(f"environment variable {name}={text!r}: expected a positive number")
    return value


def max_image_pixels() -> int:
    """Pixels one image (or video frame) may have (``VID2SIM_MAX_IMAGE_PIXELS``)."""
    return _env_int("VID2SIM_MAX_IMAGE_PIXELS", DEFAULT_MAX_IMAGE_PIXELS)


def max_array_bytes() -> int:
    """Decompressed bytes one ``.npz`` file may hold (``VID2SIM_MAX_ARRAY_BYTES``)."""
    return _env_int("VID2SIM_MAX_ARRAY_BYTES", DEFAULT_MAX_ARRAY_BYTES)


def outside_paths_allowed() -> bool:
    """Whether files outside a scene or asset folder may be used (``VID2SIM_ALLOW_OUTSIDE_PATHS=1``)."""
    return os.environ.get("VID2SIM_ALLOW_OUTSIDE_PATHS", "").strip().lower() in ("1", "true", "yes")


def image_size_problem(width: int, height: int) -> str | None:
    """None when an image of ``width`` × ``height`` may be decoded, else why not (for a message)."""
    limit = max_image_pixels()
    if width * height > limit:
        return (f"{width}x{height} pixels is more than the limit of {limit} (a decompression bomb?); "
                "raise it with the environment variable VID2SIM_MAX_IMAGE_PIXELS")
    return None


def npz_size_problem(path: str | Path) -> str | None:
    """None when the ``.npz`` at ``path`` decompresses to at most :func:`max_array_bytes`, else why not. An
    archive that is not a readable zip is left to the reader (which names its own error)."""
    try:
        with zipfile.ZipFile(path) as z:
            total = sum(i.file_size for i in z.infolist())
    except (OSError, zipfile.BadZipFile, ValueError):
        return None
    limit = max_array_bytes()
    if total > limit:
        return (f"its arrays decompress to {total} bytes, more than the limit of {limit} (a decompression bomb?); "
                "raise it with the environment variable VID2SIM_MAX_ARRAY_BYTES")
    return None


def outside(root: str | Path, path: str | Path) -> Path | None:
    """The resolved ``path`` when it lies outside the resolved ``root`` (and outside paths are not allowed),
    else None."""
    if outside_paths_allowed():
        return None
    real = Path(path).resolve()
    base = Path(root).resolve()
    if real == base or base in real.parents:
        return None
    return real
