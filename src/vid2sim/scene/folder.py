"""Scene folders: the input of every vid2sim command.

A scene folder holds posed multi-view video of one object: V fixed, synchronised cameras, each
seeing the same T time steps. On disk it is (full description in ``docs/scene-format.md``)::

    scene/
      scene.json          dt, gravity, floor, observed/held-out views and frames, metadata, extras
      transforms.json     cameras (NeRF/Blender convention) and the frame or video files
      images/c00_t000.png ...   RGBA (alpha = object mask), or RGB/JPG + masks/c00_t000.png
      videos/c00.mp4 ...        or one video per camera + a mask video / mask images
      extras/<name>.npz         optional named arrays (e.g. a ground-truth tet trajectory)

In memory it is a :class:`Scene`: cameras as :class:`vid2sim.splats.cameras.Camera` (OpenCV
convention), images (V, T, H, W, 3) composited on a white background, masks (V, T, H, W), times
(T,), a :class:`SceneConfig` and named extra arrays.

:func:`load_scene` validates everything and raises :class:`SceneFormatError` listing every
problem (file, frame, camera and field named). :func:`write_scene` writes into a temporary folder
next to the target and renames it into place, so a failed write never leaves a partial scene.

Memory: images are loaded eagerly. The full benchmark preset (12 views × 24 frames × 448²) takes
925 MB as float32 (images 694 MB + masks 231 MB) and 231 MB as uint8; pass
``load_scene(path, dtype=torch.uint8)`` to keep the 4× smaller form and convert per frame with
:meth:`Scene.image` / :meth:`Scene.mask`, or a sub-range with :meth:`Scene.subset`.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import threading
import uuid
import warnings
import zipfile
import zlib
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor
from tqdm import tqdm

from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.limits import (
    image_size_problem,
    max_image_pixels,
    npz_size_problem,
    outside,
)
from vid2sim.scene.validation import (
    SCENE_FORMAT_NAME,
    SCENE_FORMAT_VERSION,
    TIME_RTOL,
    Problems,
    SceneFormatError,
    TransformsPlan,
    VideoEntry,
    config_problems,
    index_problems,
    is_valid_extra_name,
    parse_scene_json,
    parse_transforms,
    read_json,
    resolve_intrinsics,
)
from vid2sim.scene.video import VideoError, load_video, write_video
from vid2sim.splats.cameras import Camera

__all__ = [
    "SceneConfig",
    "Scene",
    "SceneFormatError",
    "load_scene",
    "write_scene",
    "SCENE_JSON",
    "TRANSFORMS_JSON",
    "LAYOUTS",
]

SCENE_JSON = "scene.json"
TRANSFORMS_JSON = "transforms.json"
#: ``write_scene`` layouts: RGBA PNGs, RGB PNGs + grey mask PNGs, or one mp4 (+ mask mp4) per camera
LAYOUTS = ("rgba", "rgb+mask", "video")
#: frames observed by default (the paper: 16 observed + 8 future frames out of 24)
DEFAULT_OBSERVED_FRAMES = 16
#: zlib level of written PNGs (1 fast .. 9 small); 3 is ~3x faster than 9 and ~10% larger
PNG_COMPRESS_LEVEL = 3

_FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


# =============================================================================================
# SceneConfig
# =============================================================================================


@dataclass
class SceneConfig:
    """Physical and experimental settings of a scene (``scene.json``).

    Attributes:
        dt: seconds between consecutive frames; vid2sim takes one implicit-Euler step per frame.
        gravity: (3,) gravity vector in the world frame, m/s² (direction and magnitude); the world
            is z-up by convention, so the default is (0, 0, -9.8).
        floor_height: height of the floor plane along the up axis ``-gravity/|gravity|`` (for the
            default gravity: the plane z = floor_height), metres; None for no floor.
        observed_frames, held_out_frames: time indices used for fitting and for future-state
            evaluation. None picks a default when the scene's size is known (:meth:`resolved`):
            the first min(16, T) frames observed, the rest held out; if only one list is given the
            other is its complement.
        observed_views, held_out_views: camera indices used for fitting and for novel-view
            evaluation; default all views observed, none held out (complement rule as above).
        metadata: free-form JSON-serialisable dict passed through unchanged (e.g. ground-truth
            ``E``, ``nu``, ``density``, ``material``, generator ``seed``).
    """

    dt: float = 0.05
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    floor_height: float | None = None
    observed_frames: list[int] | None = None
    held_out_frames: list[int] | None = None
    observed_views: list[int] | None = None
    held_out_views: list[int] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        problems = config_problems(
            self.dt,
            self.gravity,
            self.floor_height,
            self.observed_frames,
            self.held_out_frames,
            self.observed_views,
            self.held_out_views,
            self.metadata,
        )
        if problems:
            raise ConfigError("SceneConfig: " + "; ".join(problems))
        self.dt = float(self.dt)
        self.gravity = tuple(float(g) for g in self.gravity)  # type: ignore[assignment]
        self.floor_height = None if self.floor_height is None else float(self.floor_height)
        for name in ("observed_frames", "held_out_frames", "observed_views", "held_out_views"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, [int(v) for v in value])

    @property
    def fps(self) -> float:
        """Frames per second, ``1 / dt``."""
        return 1.0 / self.dt

    @property
    def up(self) -> tuple[float, float, float]:
        """(3,) unit up vector, ``-gravity / |gravity|`` (raises for zero gravity)."""
        norm = math.sqrt(sum(g * g for g in self.gravity))
        if norm == 0.0:
            raise InputError("SceneConfig.up: gravity is zero, so there is no up direction")
        return tuple(-g / norm for g in self.gravity)  # type: ignore[return-value]

    def resolved(self, num_views: int, num_frames: int) -> "SceneConfig":
        """A copy with every view/frame list explicit (sorted) for a scene of V views and T frames.

        Raises:
            ValueError: an index is out of range for this scene size.
        """
        problems = index_problems(
            num_views, num_frames, self.observed_frames, self.held_out_frames, self.observed_views, self.held_out_views
        )
        if problems:
            raise InputError("SceneConfig: " + "; ".join(problems))

        def split(observed, held, n, default_observed):
            if observed is None and held is None:
                observed = list(range(default_observed))
            if observed is None:
                observed = [i for i in range(n) if i not in set(held)]
            if held is None:
                held = [i for i in range(n) if i not in set(observed)]
            return sorted(observed), sorted(held)

        obs_f, held_f = split(
            self.observed_frames, self.held_out_frames, num_frames, min(DEFAULT_OBSERVED_FRAMES, num_frames)
        )
        obs_v, held_v = split(self.observed_views, self.held_out_views, num_views, num_views)
        return replace(
            self,
            observed_frames=obs_f,
            held_out_frames=held_f,
            observed_views=obs_v,
            held_out_views=held_v,
            metadata=dict(self.metadata),
        )

    def to_json(self) -> dict[str, Any]:
        """The ``scene.json`` fields of this config (without ``extras``)."""
        return {
            "format": SCENE_FORMAT_NAME,
            "version": SCENE_FORMAT_VERSION,
            "dt": self.dt,
            "fps": self.fps,
            "gravity": list(self.gravity),
            "floor_height": self.floor_height,
            "observed_frames": self.observed_frames,
            "held_out_frames": self.held_out_frames,
            "observed_views": self.observed_views,
            "held_out_views": self.held_out_views,
            "metadata": self.metadata,
        }


# =============================================================================================
# Scene
# =============================================================================================


@dataclass
class Scene:
    """Posed multi-view video of one object, with its settings.

    Attributes:
        cameras: V fixed cameras (OpenCV convention), all of size W×H.
        images: (V, T, H, W, 3) RGB composited on a white background; float in [0, 1] (float32
            by default) or uint8 in [0, 255] (the compact form, see ``load_scene(dtype=...)``).
        masks: (V, T, H, W) object masks (1 = object), same dtype family as ``images``.
        times: (T,) seconds of each frame, float32; None → ``arange(T) * config.dt``. Steps must
            equal ``config.dt`` (relative tolerance 1e-3).
        config: the scene's :class:`SceneConfig`; replaced by its :meth:`~SceneConfig.resolved`
            copy, so view/frame lists are always explicit.
        root: the folder it was loaded from (None for a scene built in memory).
        extras: named groups of arrays, e.g. ``{"tet_trajectory": {"vertices": (T, Nv, 3),
            "tets": (Nt, 4)}}``; stored as ``extras/<name>.npz`` and listed in ``scene.json``.
    """

    cameras: list[Camera]
    images: Tensor
    masks: Tensor
    times: Tensor | None = None
    config: SceneConfig = field(default_factory=SceneConfig)
    root: Path | None = None
    extras: dict[str, dict[str, Tensor]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.cameras, (list, tuple)) or not self.cameras:
            raise ConfigError(f"Scene: cameras must be a non-empty list of Camera, got {type(self.cameras).__name__}")
        for i, cam in enumerate(self.cameras):
            if not isinstance(cam, Camera):
                raise ConfigError(
                    f"Scene: cameras[{i}] must be a vid2sim.splats.cameras.Camera, got {type(cam).__name__}"
                )
        self.cameras = list(self.cameras)
        num_views = len(self.cameras)
        if not isinstance(self.images, Tensor):
            raise ConfigError(f"Scene: images must be a torch.Tensor, got {type(self.images).__name__}")
        if self.images.ndim != 5 or self.images.shape[0] != num_views or self.images.shape[-1] != 3:
            raise ConfigError(
                f"Scene: images must have shape (V, T, H, W, 3) with V = {num_views} cameras, "
                f"got {tuple(self.images.shape)}"
            )
        _, num_frames, height, width, _ = self.images.shape
        if num_frames == 0 or height == 0 or width == 0:
            raise ConfigError(f"Scene: images must be non-empty, got shape {tuple(self.images.shape)}")
        if not isinstance(self.masks, Tensor) or tuple(self.masks.shape) != (num_views, num_frames, height, width):
            got = tuple(self.masks.shape) if isinstance(self.masks, Tensor) else type(self.masks).__name__
            raise ConfigError(
                f"Scene: masks must have shape (V, T, H, W) = {(num_views, num_frames, height, width)}, got {got}"
            )
        for name in ("images", "masks"):
            _check_pixel_range(getattr(self, name), f"Scene: {name}")
        for i, cam in enumerate(self.cameras):
            if (cam.width, cam.height) != (width, height):
                raise ConfigError(
                    f"Scene: cameras[{i}] is {cam.width}x{cam.height} but the images are {width}x{height} (W x H)"
                )
        if not isinstance(self.config, SceneConfig):
            raise ConfigError(f"Scene: config must be a SceneConfig, got {type(self.config).__name__}")
        self.config = self.config.resolved(num_views, num_frames)
        self.times = _check_times(self.times, num_frames, self.config.dt, "Scene: times")
        self.root = None if self.root is None else Path(self.root)
        self.extras = _check_extras(self.extras)

    # ---- sizes ----------------------------------------------------------------------------------
    @property
    def num_views(self) -> int:
        """V, the number of cameras."""
        return len(self.cameras)

    @property
    def num_frames(self) -> int:
        """T, the number of time steps."""
        return int(self.images.shape[1])

    @property
    def height(self) -> int:
        """H, image height in pixels."""
        return int(self.images.shape[2])

    @property
    def width(self) -> int:
        """W, image width in pixels."""
        return int(self.images.shape[3])

    # ---- pixel access ---------------------------------------------------------------------------
    def image(self, view: int, frame: int, dtype: torch.dtype = torch.float32) -> Tensor:
        """(H, W, 3) image of camera ``view`` at time index ``frame``, float in [0, 1]."""
        return _to_float(self.images[view, frame], dtype)

    def mask(self, view: int, frame: int, dtype: torch.dtype = torch.float32) -> Tensor:
        """(H, W) mask of camera ``view`` at time index ``frame``, float in [0, 1]."""
        return _to_float(self.masks[view, frame], dtype)

    def float_images(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """All images (V, T, H, W, 3) as floats in [0, 1] (no copy if already of ``dtype``)."""
        return _to_float(self.images, dtype)

    def float_masks(self, dtype: torch.dtype = torch.float32) -> Tensor:
        """All masks (V, T, H, W) as floats in [0, 1] (no copy if already of ``dtype``)."""
        return _to_float(self.masks, dtype)

    # ---- derived scenes -------------------------------------------------------------------------
    def to(self, device: torch.device | str) -> "Scene":
        """The same scene with cameras, images, masks, times and extras on ``device``."""
        return Scene(
            [c.to(device) for c in self.cameras],
            self.images.to(device),
            self.masks.to(device),
            self.times.to(device),
            replace(self.config, metadata=dict(self.config.metadata)),
            self.root,
            {k: {n: a.to(device) for n, a in group.items()} for k, group in self.extras.items()},
        )

    def subset(self, views: Sequence[int] | None = None, frames: range | None = None) -> "Scene":
        """A scene with only some cameras and/or a contiguous range of time indices.

        Args:
            views: camera indices to keep, in the order given (None: all).
            frames: a ``range`` of time indices with step 1 (None: all); frame times stay as they were.

        The config's view/frame lists are renumbered to the new indices (entries that were dropped
        disappear). Extras are kept unchanged (they may describe all frames).
        """
        views = list(range(self.num_views)) if views is None else [int(v) for v in views]
        if not views or any(not 0 <= v < self.num_views for v in views) or len(set(views)) != len(views):
            raise InputError(f"Scene.subset: views must be distinct indices in 0..{self.num_views - 1}, got {views}")
        frames = range(self.num_frames) if frames is None else frames
        contiguous = isinstance(frames, range) and frames.step == 1 and len(frames) > 0
        if not contiguous or frames.start < 0 or frames.stop > self.num_frames:
            raise InputError(
                f"Scene.subset: frames must be a non-empty range(start, stop) within 0..{self.num_frames}, got "
                f"{frames!r}"
            )
        view_map = {old: new for new, old in enumerate(views)}
        frame_map = {old: new for new, old in enumerate(frames)}
        cfg = self.config

        def remap(values, mapping):
            return [mapping[v] for v in values if v in mapping]

        config = replace(
            cfg,
            observed_frames=remap(cfg.observed_frames, frame_map),
            held_out_frames=remap(cfg.held_out_frames, frame_map),
            observed_views=remap(cfg.observed_views, view_map),
            held_out_views=remap(cfg.held_out_views, view_map),
            metadata=dict(cfg.metadata),
        )
        index = torch.tensor(views, dtype=torch.long, device=self.images.device)
        sl = slice(frames.start, frames.stop)
        return Scene(
            [self.cameras[v] for v in views],
            self.images.index_select(0, index)[:, sl].contiguous(),
            self.masks.index_select(0, index.to(self.masks.device))[:, sl].contiguous(),
            self.times[sl].clone(),
            config,
            self.root,
            self.extras,
        )


def _to_float(x: Tensor, dtype: torch.dtype) -> Tensor:
    if dtype not in _FLOAT_DTYPES:
        raise InputError(f"dtype must be a floating-point torch dtype, got {dtype}")
    if x.dtype == torch.uint8:
        return x.to(dtype) / 255.0
    return x.to(dtype)


def _check_pixel_range(x: Tensor, name: str) -> None:
    if x.dtype == torch.uint8:
        return
    if x.dtype not in _FLOAT_DTYPES:
        raise InputError(f"{name} must be uint8 or floating point, got dtype {x.dtype}")
    lo, hi = torch.aminmax(x.detach())
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"{name} contains NaN or infinite values")
    if lo < 0.0 or hi > 1.0:
        raise InputError(f"{name} must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")


def _check_times(times: Tensor | None, num_frames: int, dt: float, name: str) -> Tensor:
    if times is None:
        return torch.arange(num_frames, dtype=torch.float64).mul(dt).to(torch.float32)
    times = torch.as_tensor(times)
    if tuple(times.shape) != (num_frames,):
        raise InputError(f"{name} must have shape (T,) = ({num_frames},), got {tuple(times.shape)}")
    t64 = times.detach().to("cpu", torch.float64)
    if not torch.isfinite(t64).all():
        raise InputError(f"{name} contains NaN or infinite values")
    steps = t64[1:] - t64[:-1]
    bad = ((steps - dt).abs() > TIME_RTOL * dt).nonzero()
    if len(bad):
        k = int(bad[0])
        raise InputError(
            f"{name} must step by config.dt = {dt:g} s (one simulation step per frame), but time index "
            f"{k} → {k + 1} steps by {float(steps[k]):.6g} s"
        )
    return times.to(torch.float32)


def _check_extras(extras: Mapping[str, Mapping[str, Any]] | None) -> dict[str, dict[str, Tensor]]:
    if extras is None:
        return {}
    if not isinstance(extras, Mapping):
        raise InputError(f"Scene: extras must be a dict of name -> dict of arrays, got {type(extras).__name__}")
    out: dict[str, dict[str, Tensor]] = {}
    for name, group in extras.items():
        if not is_valid_extra_name(name):
            raise InputError(f"Scene: extras name {name!r} is not allowed (use ASCII letters, digits, '_' and '-')")
        if not isinstance(group, Mapping) or not group:
            raise InputError(f"Scene: extras['{name}'] must be a non-empty dict of array name -> array")
        arrays: dict[str, Tensor] = {}
        for key, value in group.items():
            if not isinstance(key, str) or not key.isidentifier():
                raise InputError(f"Scene: extras['{name}'] has array name {key!r}; use a Python identifier")
            try:
                arr = value if isinstance(value, Tensor) else torch.as_tensor(np.asarray(value))
            except (TypeError, ValueError, RuntimeError) as exc:
                raise InputError(f"Scene: extras['{name}']['{key}'] is not a numeric array: {exc}") from exc
            if not (arr.is_floating_point() or arr.dtype in _INT_DTYPES or arr.dtype == torch.bool):
                raise InputError(
                    f"Scene: extras['{name}']['{key}'] has dtype {arr.dtype}; use a float, integer or bool array"
                )
            arrays[key] = arr
        out[name] = arrays
    return out


_INT_DTYPES = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)


# =============================================================================================
# pixels on disk
# =============================================================================================


def _open_image(path: Path) -> Image.Image:
    """``Image.open`` with vid2sim's pixel limit (``VID2SIM_MAX_IMAGE_PIXELS``) in place of Pillow's warning and
    error: raises ValueError naming the limit, before any pixel is decoded."""
    Image.MAX_IMAGE_PIXELS = max_image_pixels()  # Pillow's error then comes at twice vid2sim's own limit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            img = Image.open(path)
        except Image.DecompressionBombError as exc:
            raise ValueError(f"{exc}; raise vid2sim's limit with the environment variable "
                             "VID2SIM_MAX_IMAGE_PIXELS") from None
    problem = image_size_problem(int(img.width), int(img.height))
    if problem is not None:
        img.close()
        raise ValueError(problem)
    return img


def _read_raster(path: Path) -> np.ndarray:
    """Decode an image file into an (H, W, C) array, C in {1, 2, 3, 4}; uint8, uint16 or float32.

    Palette images are expanded, 1-bit images become uint8 0/255, 16-bit grey stays uint16.
    Raises OSError/ValueError (with the reason) for unreadable or unsupported files.
    """
    with _open_image(path) as img, warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        img.load()
        mode = img.mode
        if mode == "P" or mode == "PA":
            img = img.convert("RGBA" if (mode == "PA" or "transparency" in img.info) else "RGB")
        elif mode == "1":
            img = img.convert("L")
        elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
            img = img.convert("RGB")
        mode = img.mode
        if mode in ("L", "LA", "RGB", "RGBA"):
            arr = np.asarray(img, dtype=np.uint8)
        elif mode.startswith("I;16"):
            arr = np.asarray(img).astype(np.uint16)
        elif mode == "I":
            arr = np.asarray(img)
            if arr.min() < 0 or arr.max() > 65535:
                raise InputError(f"32-bit integer image with values outside 0..65535 (mode {mode})")
            arr = arr.astype(np.uint16)
        elif mode == "F":
            arr = np.asarray(img, dtype=np.float32)
            if not np.isfinite(arr).all() or arr.min() < 0 or arr.max() > 1:
                raise InputError("float image with values outside [0, 1]")
        else:
            raise InputError(f"unsupported image mode {mode!r}")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return arr


def _unit(arr: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Integer/float raster → floats in [0, 1] of ``dtype`` (uint8 / 255, uint16 / 65535)."""
    if arr.dtype == np.uint8:
        return arr.astype(dtype) / dtype.type(255.0)
    if arr.dtype == np.uint16:
        return arr.astype(dtype) / dtype.type(65535.0)
    return arr.astype(dtype)


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels.

    Raises:
        ValueError: more pixels than ``VID2SIM_MAX_IMAGE_PIXELS`` (:mod:`vid2sim.runtime.limits`).
    """
    with _open_image(path) as img:
        return int(img.width), int(img.height)


def _write_png(path: Path, array: np.ndarray) -> None:
    """Write a uint8 (H, W), (H, W, 3) or (H, W, 4) array as an 8-bit PNG."""
    Image.fromarray(array).save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def _resolve_file(root: Path, rel: str) -> Path | None:
    """The file ``rel`` names (relative to ``root``); NeRF-style paths without suffix get ``.png``.

    Raises:
        SceneFormatError: the file (after following symlinks) lies outside the scene folder, unless
            ``VID2SIM_ALLOW_OUTSIDE_PATHS=1`` (:mod:`vid2sim.runtime.limits`): a scene from someone else must not
            make vid2sim read the user's other files.
    """
    path = Path(rel) if Path(rel).is_absolute() else root / rel
    found = None
    if path.is_file():
        found = path
    elif not path.suffix:
        with_png = path.with_name(path.name + ".png")
        if with_png.is_file():
            found = with_png
    if found is not None:
        real = outside(root, found)
        if real is not None:
            raise SceneFormatError([f"file '{rel}' resolves to {real}, outside the scene folder (set "
                                    "VID2SIM_ALLOW_OUTSIDE_PATHS=1 to allow files elsewhere)"], root)
    return found


def _composite(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Object colour (H, W, 3) and mask (H, W), floats in [0, 1] → image on white, rgb·m + (1 − m)."""
    m = mask[..., None]
    return rgb * m + (1.0 - m)


def _straight_colour(image: Tensor, mask: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Invert the white compositing for writing: (H, W, 3) image, (H, W) mask → uint8 colour, uint8 alpha.

    With a = round(255·m)/255 the written colour is c = (image − (1 − a)) / a where a > 0 and white
    where a = 0, so that loading (c·a + 1 − a) gives the image back: exactly where the mask is 0
    or 1, and within half a grey level (0.5/255) where it is fractional.
    """
    # numpy rather than torch arithmetic: single-threaded, so the writer threads do not
    # oversubscribe the cores with OpenMP; float32 is ample for rounding to 8 bits
    img = image.detach().cpu()
    img = (img.float() if img.dtype == torch.bfloat16 else img).numpy()  # numpy has no bfloat16
    img = img.astype(np.float32) / np.float32(255.0) if img.dtype == np.uint8 else img.astype(np.float32, copy=False)
    m = mask.detach().cpu()
    m = (m.float() if m.dtype == torch.bfloat16 else m).numpy()
    a8 = m if m.dtype == np.uint8 else np.rint(m.astype(np.float32, copy=False) * np.float32(255.0)).astype(np.uint8)
    a = a8.astype(np.float32)[..., None] / np.float32(255.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        colour = np.where(a > 0, (img - (1.0 - a)) / np.where(a > 0, a, 1.0), 1.0)
    rgb8 = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
    return rgb8, a8


def _store(out: np.ndarray, index: tuple[int, ...], values: np.ndarray) -> None:
    """Write float values in [0, 1] into ``out[index]`` (rounded to 0..255 for a uint8 ``out``).

    Works on numpy arrays (the loaders wrap them with ``torch.from_numpy`` at the end): numpy
    copies single-threaded, whereas torch's OpenMP copy from several loader threads at once
    oversubscribes the cores.
    """
    if out.dtype == np.uint8:
        out[index] = np.clip(np.rint(values * 255.0), 0, 255)
    else:
        out[index] = values


def _run_parallel(
    jobs: list[Callable[[], None]], workers: int | None, progress: bool, desc: str
) -> None:
    """Run ``jobs`` on a thread pool (PIL and zlib release the GIL), with a progress bar.

    The first exception is re-raised after every started job has finished, so nothing keeps
    writing into a folder that the caller is about to delete.
    """
    workers = workers if workers is not None else min(4, os.cpu_count() or 1)
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    with tqdm(total=len(jobs), desc=desc, disable=not progress, unit="file") as bar:
        if workers == 1:
            for job in jobs:
                job()
                bar.update(1)
            return
        with ThreadPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(job) for job in jobs]
            try:
                for fut in futures:
                    fut.result()
                    bar.update(1)
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise


# =============================================================================================
# loading
# =============================================================================================


def load_scene(
    path: str | Path,
    *,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    workers: int | None = None,
) -> Scene:
    """Load and validate a scene folder.

    Args:
        path: the scene folder (holding ``scene.json`` and ``transforms.json``).
        dtype: ``torch.float32`` (default) / ``torch.float64`` for images and masks in [0, 1], or
            ``torch.uint8`` for the 4× smaller 0..255 form.
        progress: show a progress bar while decoding.
        workers: decoding threads (default min(4, CPU count)).

    Returns:
        The :class:`Scene` (images composited on white: ``rgb·mask + (1 − mask)``).

    Raises:
        SceneFormatError: anything wrong with the folder; the message lists every problem found,
            naming the file, the frame/camera and the field.
    """
    if dtype not in (torch.uint8, torch.float32, torch.float64):
        raise InputError(f"load_scene: dtype must be torch.uint8, torch.float32 or torch.float64, got {dtype}")
    root = Path(path)
    if not root.exists():
        raise SceneFormatError(["the folder does not exist"], root)
    if not root.is_dir():
        raise SceneFormatError(["not a folder (a scene is a folder with scene.json and transforms.json)"], root)
    problems = Problems()
    scene_obj = read_json(root / SCENE_JSON, SCENE_JSON, root)
    transforms_obj = read_json(root / TRANSFORMS_JSON, TRANSFORMS_JSON, root)
    config_kwargs, extras_paths = parse_scene_json(scene_obj, problems, SCENE_JSON)
    plan = parse_transforms(transforms_obj, problems, TRANSFORMS_JSON)
    problems.raise_if_any(root)
    assert plan is not None
    config = SceneConfig(**config_kwargs)

    def check_indices(num_frames: int) -> None:
        lists = (config.observed_frames, config.held_out_frames, config.observed_views, config.held_out_views)
        for message in index_problems(plan.num_views, num_frames, *lists):
            problems.add(f"{SCENE_JSON}: {message}")

    if plan.num_frames is not None:  # frames layout: T is known before any pixel is read
        check_indices(plan.num_frames)
        problems.raise_if_any(root)
    if plan.layout == "frames":
        cameras, images, masks, times = _load_frames(root, plan, config, dtype, progress, workers)
    else:
        cameras, images, masks, times = _load_videos(root, plan, config, dtype, progress, workers)
        check_indices(int(images.shape[1]))
    extras = _load_extras(root, extras_paths, problems)
    problems.raise_if_any(root)
    return Scene(cameras, images, masks, times, config, root, extras)


def _make_cameras(
    plan: TransformsPlan, sizes: list[tuple[int, int]], descs: list[str], problems: Problems
) -> list[Camera]:
    cameras = []
    for v, entry in enumerate(plan.camera_entries()):
        where = f"{TRANSFORMS_JSON}: {entry.where}"
        resolved = resolve_intrinsics(entry.intrinsics, sizes[v][0], sizes[v][1], descs[v], where, problems)
        if resolved is None:
            continue
        K, w, h = resolved
        try:
            cameras.append(Camera.from_nerf(torch.from_numpy(entry.c2w), torch.from_numpy(K).float(), w, h))
        except ValueError as exc:  # K or pose rejected by Camera itself
            problems.add(f"{where}: {exc}")
    return cameras


def _load_frames(
    root: Path, plan: TransformsPlan, config: SceneConfig, dtype: torch.dtype, progress: bool, workers: int | None
) -> tuple[list[Camera], Tensor, Tensor, Tensor]:
    problems = Problems()
    V, T = plan.num_views, plan.num_frames
    assert T is not None
    files: dict[tuple[int, int], tuple[Path, Path | None]] = {}
    for row in plan.grid:
        for e in row:
            where = f"{TRANSFORMS_JSON}: {e.where}"
            img = _resolve_file(root, e.file_path)
            if img is None:
                problems.add(f"{where}: file '{e.file_path}' not found")
            msk = None
            if e.mask_path is not None:
                msk = _resolve_file(root, e.mask_path)
                if msk is None:
                    problems.add(f"{where}: mask file '{e.mask_path}' not found")
            if img is not None and (e.mask_path is None or msk is not None):
                files[(e.camera, e.time_index)] = (img, msk)
    problems.raise_if_any(root)

    # header pass: sizes agree per camera, between cameras, and between image and mask
    sizes: dict[tuple[int, int], tuple[int, int]] = {}
    for (v, t), (img, msk) in files.items():
        e = plan.grid[v][t]
        where = f"{TRANSFORMS_JSON}: {e.where}"
        try:
            sizes[(v, t)] = _image_size(img)
        except (OSError, UnidentifiedImageError, ValueError) as exc:
            problems.add(f"{where}: cannot read image '{e.file_path}': {exc}")
            continue
        if msk is not None:
            try:
                msize = _image_size(msk)
            except (OSError, UnidentifiedImageError, ValueError) as exc:
                problems.add(f"{where}: cannot read mask '{e.mask_path}': {exc}")
                continue
            if msize != sizes[(v, t)]:
                problems.add(
                    f"{where}: mask '{e.mask_path}' is {msize[0]}x{msize[1]} but image '{e.file_path}' is "
                    f"{sizes[(v, t)][0]}x{sizes[(v, t)][1]}"
                )
    problems.raise_if_any(root)
    # the reference size is the most common one (per camera, then between cameras), so one odd image is
    # named as the odd one instead of every good image being blamed for differing from it
    cam_sizes = []
    for v in range(V):
        usual = Counter(sizes[(v, t)] for t in range(T)).most_common(1)[0][0]
        cam_sizes.append(usual)
        for t in range(T):
            if sizes[(v, t)] != usual:
                e = plan.grid[v][t]
                problems.add(
                    f"{TRANSFORMS_JSON}: {e.where}: image '{e.file_path}' is {sizes[(v, t)][0]}x{sizes[(v, t)][1]} "
                    f"but camera {v}'s other images are {usual[0]}x{usual[1]}"
                )
    cameras = _make_cameras(plan, cam_sizes, [f"'{plan.grid[v][0].file_path}'" for v in range(V)], problems)
    usual = Counter(cam_sizes).most_common(1)[0][0]
    for v in range(V):
        if cam_sizes[v] != usual:
            problems.add(
                f"{TRANSFORMS_JSON}: camera {v} has {cam_sizes[v][0]}x{cam_sizes[v][1]} images but the other "
                f"cameras have {usual[0]}x{usual[1]}; all cameras must have the same image size"
            )
    times = _frame_times(plan, config, problems)
    problems.raise_if_any(root)

    W, H = usual
    np_dtype = {torch.uint8: np.uint8, torch.float32: np.float32, torch.float64: np.float64}[dtype]
    images_np = np.empty((V, T, H, W, 3), dtype=np_dtype)
    masks_np = np.empty((V, T, H, W), dtype=np_dtype)
    work = np.float64 if dtype == torch.float64 else np.float32
    lock = threading.Lock()

    def decode(v: int, t: int) -> None:
        e = plan.grid[v][t]
        img_path, msk_path = files[(v, t)]
        where = f"{TRANSFORMS_JSON}: {e.where}"
        try:
            raster = _read_raster(img_path)
        except (OSError, UnidentifiedImageError, ValueError) as exc:
            with lock:
                problems.add(f"{where}: cannot read image '{e.file_path}': {exc}")
            return
        channels = raster.shape[2]
        alpha = raster[..., -1] if channels in (2, 4) else None
        colour = raster[..., :3] if channels >= 3 else np.repeat(raster[..., :1], 3, axis=2)
        if msk_path is None:
            if alpha is None:
                with lock:
                    problems.add(
                        f"{where}: image '{e.file_path}' has no alpha channel and the frame has no mask_path; "
                        "give an RGBA image (alpha = object mask) or a mask_path"
                    )
                return
            mask = _unit(alpha, np.dtype(work))
        else:
            if alpha is not None and alpha.min() < np.iinfo(alpha.dtype).max:
                with lock:
                    problems.add(
                        f"{where}: image '{e.file_path}' has a (non-opaque) alpha channel and the frame also has "
                        f"mask_path '{e.mask_path}'; give the mask one way only"
                    )
                return
            try:
                mask = _read_mask(msk_path)
            except (OSError, UnidentifiedImageError, ValueError) as exc:
                with lock:
                    problems.add(f"{where}: cannot use mask '{e.mask_path}': {exc}")
                return
            mask = _unit(mask, np.dtype(work))
        _store(images_np, (v, t), _composite(_unit(colour, np.dtype(work)), mask))
        _store(masks_np, (v, t), mask)

    jobs = [lambda v=v, t=t: decode(v, t) for v in range(V) for t in range(T)]
    _run_parallel(jobs, workers, progress, "loading scene")
    problems.raise_if_any(root)
    return cameras, torch.from_numpy(images_np), torch.from_numpy(masks_np), times


def _read_mask(path: Path) -> np.ndarray:
    """(H, W) mask values (uint8/uint16/float) from a grey image or an RGB(A) image with equal channels."""
    raster = _read_raster(path)
    channels = raster.shape[2]
    if channels in (1, 2):
        return raster[..., 0]
    rgb = raster[..., :3]
    if not (np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2])):
        raise InputError("it is a colour image; a mask must be grey (0 = background, max = object)")
    if channels == 4 and raster[..., 3].min() < np.iinfo(raster.dtype).max:
        raise InputError("it has transparency; masks are read from the grey value, not from alpha")
    return rgb[..., 0]


def _frame_times(plan: TransformsPlan, config: SceneConfig, problems: Problems) -> Tensor:
    """(T,) frame times: from the frames' ``time`` keys if given, else ``arange(T) * dt``."""
    T = plan.num_frames
    assert T is not None
    if plan.grid[0][0].time is None:
        return torch.arange(T, dtype=torch.float64).mul(config.dt).to(torch.float32)
    times = np.array([plan.grid[0][t].time for t in range(T)], dtype=np.float64)
    _check_time_steps(times, config.dt, TRANSFORMS_JSON + ": frame times", problems)
    return torch.from_numpy(times).to(torch.float32)


def _check_time_steps(times: np.ndarray, dt: float, what: str, problems: Problems) -> None:
    steps = np.diff(times)
    bad = np.nonzero(np.abs(steps - dt) > TIME_RTOL * dt)[0]
    if len(bad):
        k = int(bad[0])
        problems.add(
            f"{what} step by {steps[k]:.6g} s from time index {k} to {k + 1}, but {SCENE_JSON} has dt = {dt:g} s; "
            "make them agree (vid2sim takes one simulation step of dt per frame)"
        )


def _load_videos(
    root: Path, plan: TransformsPlan, config: SceneConfig, dtype: torch.dtype, progress: bool, workers: int | None
) -> tuple[list[Camera], Tensor, Tensor, Tensor]:
    problems = Problems()
    entries = plan.camera_entries()
    V = len(entries)
    colour_frames: list[Tensor | None] = [None] * V
    mask_frames: list[list[np.ndarray] | None] = [None] * V
    camera_problems = [Problems() for _ in range(V)]  # merged in camera order afterwards

    def read_camera(v: int) -> None:
        e, found = entries[v], camera_problems[v]
        assert isinstance(e, VideoEntry)
        where = f"{TRANSFORMS_JSON}: {e.where}"
        video = _resolve_file(root, e.video_path)
        if video is None:
            found.add(f"{where}: video file '{e.video_path}' not found")
            return
        try:
            frames, info = load_video(video, dtype=torch.uint8)
        except VideoError as exc:
            found.add(f"{where}: {exc}")
            return
        if info.fps > 0 and abs(info.fps * config.dt - 1.0) > 1e-2:
            found.add(
                f"{where}: video '{e.video_path}' runs at {info.fps:g} fps but {SCENE_JSON} has dt = {config.dt:g} s "
                f"({1.0 / config.dt:g} fps); re-encode the video or set dt = 1/fps"
            )
        masks_v = _video_masks(root, e, frames.shape[0], frames.shape[2], frames.shape[1], where, found)
        if masks_v is not None:
            colour_frames[v], mask_frames[v] = frames, masks_v

    # ffmpeg decodes in subprocesses, so cameras are read in parallel threads
    _run_parallel([lambda v=v: read_camera(v) for v in range(V)], workers, progress, "loading videos")
    for found in camera_problems:
        for message in found.items:
            problems.add(message)
    problems.raise_if_any(root)
    counts = [f.shape[0] for f in colour_frames]
    shapes = [tuple(f.shape[1:3]) for f in colour_frames]
    usual_count = Counter(counts).most_common(1)[0][0]
    usual_shape = Counter(shapes).most_common(1)[0][0]
    for v in range(len(entries)):
        if counts[v] != usual_count:
            problems.add(
                f"{TRANSFORMS_JSON}: {entries[v].where}: video '{entries[v].video_path}' has {counts[v]} frames but "
                f"the other cameras' have {usual_count}; all videos must cover the same time steps"
            )
        if shapes[v] != usual_shape:
            problems.add(
                f"{TRANSFORMS_JSON}: camera {v} has {shapes[v][1]}x{shapes[v][0]} frames but the other cameras "
                f"have {usual_shape[1]}x{usual_shape[0]}; all cameras must have the same image size"
            )
    sizes = [(s[1], s[0]) for s in shapes]
    cameras = _make_cameras(plan, sizes, [f"video '{e.video_path}'" for e in entries], problems)
    problems.raise_if_any(root)
    T, (H, W) = counts[0], shapes[0]
    work = np.dtype(np.float64 if dtype == torch.float64 else np.float32)
    np_dtype = {torch.uint8: np.uint8, torch.float32: np.float32, torch.float64: np.float64}[dtype]
    images_np = np.empty((V, T, H, W, 3), dtype=np_dtype)
    masks_np = np.empty((V, T, H, W), dtype=np_dtype)
    for v in range(V):
        colour = colour_frames[v].numpy()
        for t in range(T):
            m = _unit(mask_frames[v][t], work)
            _store(images_np, (v, t), _composite(_unit(colour[t], work), m))
            _store(masks_np, (v, t), m)
        colour_frames[v] = mask_frames[v] = None  # free as we go: peak memory ≈ output + one camera
    start = entries[0].start_time
    times = (start + torch.arange(T, dtype=torch.float64) * config.dt).to(torch.float32)
    return cameras, torch.from_numpy(images_np), torch.from_numpy(masks_np), times


def _video_masks(
    root: Path, e: VideoEntry, T: int, W: int, H: int, where: str, problems: Problems
) -> list[np.ndarray] | None:
    """T masks (H, W) (uint8/uint16/float values) of one camera from its mask video or images (None on problems)."""
    if e.mask_video_path is not None:
        path = _resolve_file(root, e.mask_video_path)
        if path is None:
            problems.add(f"{where}: mask video '{e.mask_video_path}' not found")
            return None
        try:
            frames, _ = load_video(path, dtype=torch.uint8)
        except VideoError as exc:
            problems.add(f"{where}: {exc}")
            return None
        if tuple(frames.shape[:3]) != (T, H, W):
            problems.add(
                f"{where}: mask video '{e.mask_video_path}' has {frames.shape[0]} frames of "
                f"{frames.shape[2]}x{frames.shape[1]}, but video '{e.video_path}' has {T} frames of {W}x{H}"
            )
            return None
        # lossy codecs may tint grey slightly: use the mean of the three channels
        total = frames.numpy().sum(axis=3, dtype=np.uint16)
        return list(((total + 1) // 3).astype(np.uint8))  # round(total / 3)
    assert e.mask_paths is not None
    if len(e.mask_paths) != T:
        problems.add(f"{where}: mask_paths lists {len(e.mask_paths)} files but video '{e.video_path}' has {T} frames")
        return None
    out = []
    ok = True
    for t, rel in enumerate(e.mask_paths):
        path = _resolve_file(root, rel)
        if path is None:
            problems.add(f"{where}: mask file '{rel}' (time index {t}) not found")
            ok = False
            continue
        try:
            mask = _read_mask(path)
        except (OSError, UnidentifiedImageError, ValueError) as exc:
            problems.add(f"{where}: cannot use mask '{rel}' (time index {t}): {exc}")
            ok = False
            continue
        if mask.shape != (H, W):
            problems.add(f"{where}: mask '{rel}' is {mask.shape[1]}x{mask.shape[0]} but the video is {W}x{H}")
            ok = False
            continue
        out.append(mask)
    if not ok:
        return None
    return out


def _load_extras(root: Path, paths: dict[str, str], problems: Problems) -> dict[str, dict[str, Tensor]]:
    extras: dict[str, dict[str, Tensor]] = {}
    for name, rel in paths.items():
        path = Path(rel) if Path(rel).is_absolute() else root / rel
        if not path.is_file():
            problems.add(f"{SCENE_JSON}: extras '{name}': file '{rel}' not found")
            continue
        real = outside(root, path)
        if real is not None:
            problems.add(f"{SCENE_JSON}: extras '{name}': file '{rel}' resolves to {real}, outside the scene folder "
                         "(set VID2SIM_ALLOW_OUTSIDE_PATHS=1 to allow files elsewhere)")
            continue
        too_big = npz_size_problem(path)
        if too_big is not None:
            problems.add(f"{SCENE_JSON}: extras '{name}': '{rel}': {too_big}")
            continue
        try:
            with np.load(path, allow_pickle=False) as data:
                raw = {key: np.array(data[key]) for key in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, zlib.error) as exc:
            problems.add(f"{SCENE_JSON}: extras '{name}': cannot read '{rel}' as an .npz file: {exc}")
            continue
        odd = [f"{key} ({a.dtype})" for key, a in raw.items() if a.dtype.kind not in "biuf"]
        if odd:
            problems.add(f"{SCENE_JSON}: extras '{name}': '{rel}': arrays {', '.join(odd)} are not numbers")
            continue
        arrays = {key: torch.from_numpy(a) for key, a in raw.items()}
        if not arrays:
            problems.add(f"{SCENE_JSON}: extras '{name}': '{rel}' holds no arrays")
            continue
        extras[name] = arrays
    return extras


# =============================================================================================
# writing
# =============================================================================================


def write_scene(
    scene: Scene,
    path: str | Path,
    overwrite: bool = False,
    *,
    layout: str = "rgba",
    video_quality: float = 9.0,
    progress: bool = False,
    workers: int | None = None,
) -> Path:
    """Write ``scene`` as a scene folder at ``path``, atomically.

    Everything is written into a temporary folder next to ``path`` (``.<name>.writing-<id>``)
    which is renamed to ``path`` only when complete; on any failure the temporary folder is
    removed and nothing is left at ``path`` (an existing scene replaced with ``overwrite=True``
    stays untouched until the final rename).

    Args:
        scene: the scene to write.
        path: the scene folder to create.
        overwrite: replace an existing scene folder at ``path``. Only folders that hold a
            ``scene.json`` (or are empty) are replaced; anything else is refused.
        layout: ``"rgba"`` (RGBA PNGs, alpha = mask), ``"rgb+mask"`` (RGB PNGs + grey mask PNGs)
            or ``"video"`` (one H.264 mp4 per camera + a lossless mask mp4).
        video_quality: 1..10 (10 best) for the colour videos of the ``"video"`` layout.
        progress: show a progress bar.
        workers: PNG encoding threads (default min(4, CPU count)).

    Returns:
        The path of the written folder.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False (or it is not a scene folder).
        ValueError: bad arguments. OSError/VideoError: writing failed (nothing left behind).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"write_scene: scene must be a Scene, got {type(scene).__name__}")
    if layout not in LAYOUTS:
        raise InputError(f"write_scene: layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    if layout == "video" and not 1.0 <= float(video_quality) <= 10.0:
        raise InputError(f"write_scene: video_quality must be in [1, 10], got {video_quality}")
    target = Path(path)
    if target.exists() or target.is_symlink():
        if not overwrite:
            raise FileExistsError(f"write_scene: '{target}' already exists; pass overwrite=True to replace it")
        if not target.is_dir() or target.is_symlink():
            raise FileExistsError(f"write_scene: '{target}' is not a folder; refusing to replace it")
        if not (target / SCENE_JSON).is_file() and any(target.iterdir()):
            raise FileExistsError(
                f"write_scene: '{target}' is a non-empty folder without {SCENE_JSON}; refusing to replace "
                "something that is not a scene folder"
            )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.writing-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    try:
        _write_contents(scene, tmp, layout, float(video_quality), progress, workers)
        move_into_place(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def move_into_place(tmp: Path, target: Path) -> None:
    """Rename the finished folder ``tmp`` to ``target``, replacing an existing ``target`` only at the
    last moment (it is restored if the rename fails). Both must be on the same file system.

    ``tmp`` usually comes from :func:`tempfile.mkdtemp`, which makes it private (mode 0700); it is given the
    permissions a folder made with ``mkdir`` would have (0777 minus the umask) before it takes its name."""
    _apply_umask(tmp)
    if not target.exists():
        os.replace(tmp, target)
        return
    old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:12]}"
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except BaseException:
        os.replace(old, target)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _apply_umask(folder: Path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(folder, 0o777 & ~umask)


def _f32(x: float | Tensor) -> float:
    """The shortest decimal that reads back as the same float32 (0.05, not 0.05000000074505806)."""
    return float(str(np.float32(float(x))))


def _intrinsics_json(cam: Camera) -> dict[str, float]:
    K = cam.K.detach().to("cpu")
    return {"fl_x": _f32(K[0, 0]), "fl_y": _f32(K[1, 1]), "cx": _f32(K[0, 2]), "cy": _f32(K[1, 2])}


def _json_text(obj: Any, indent: int = 0) -> str:
    """JSON with 2-space indentation, but lists of numbers (and lists of such lists, i.e. matrices
    rows) kept on one line each, so a 4x4 matrix takes 4 lines rather than 20."""
    pad, inner = "  " * indent, "  " * (indent + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_json_text(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, (list, tuple)):
        if all(not isinstance(x, (dict, list, tuple)) for x in obj):
            return json.dumps(list(obj), allow_nan=False)
        items = [f"{inner}{_json_text(x, indent + 1)}" for x in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def _write_json(path: Path, obj: Any) -> None:
    path.write_text(_json_text(obj) + "\n", encoding="utf-8")


def _write_contents(
    scene: Scene, folder: Path, layout: str, video_quality: float, progress: bool, workers: int | None
) -> None:
    V, T = scene.num_views, scene.num_frames
    cw, tw = max(2, len(str(V - 1))), max(3, len(str(T - 1)))
    intrinsics = [_intrinsics_json(c) for c in scene.cameras]
    shared = all(k == intrinsics[0] for k in intrinsics)
    transforms: dict[str, Any] = {"w": scene.width, "h": scene.height}
    if shared:
        transforms["camera_angle_x"] = scene.cameras[0].camera_angle_x
        transforms.update(intrinsics[0])
    c2w = [c.to_nerf().tolist() for c in scene.cameras]
    times = [_f32(t) for t in scene.times.detach().to("cpu")]

    if layout in ("rgba", "rgb+mask"):
        (folder / "images").mkdir()
        if layout == "rgb+mask":
            (folder / "masks").mkdir()
        frames = []
        jobs = []
        for v in range(V):
            for t in range(T):
                name = f"c{v:0{cw}d}_t{t:0{tw}d}.png"
                entry: dict[str, Any] = {"file_path": f"images/{name}"}
                if layout == "rgb+mask":
                    entry["mask_path"] = f"masks/{name}"
                entry.update(
                    {"camera_index": v, "time_index": t, "time": times[t], "transform_matrix": c2w[v]}
                )
                if not shared:
                    entry.update(intrinsics[v])
                frames.append(entry)
                jobs.append(lambda v=v, t=t, name=name: _write_frame(scene, folder, layout, v, t, name))
        _run_parallel(jobs, workers, progress, "writing scene")
        transforms["frames"] = frames
    else:
        (folder / "videos").mkdir()
        videos = []
        for v in range(V):
            entry = {
                "camera_index": v,
                "video_path": f"videos/c{v:0{cw}d}.mp4",
                "mask_video_path": f"videos/c{v:0{cw}d}_mask.mp4",
                "start_time": times[0],
                "transform_matrix": c2w[v],
            }
            if not shared:
                entry.update(intrinsics[v])
            videos.append(entry)

        def encode(v: int) -> None:
            pairs = [_straight_colour(scene.images[v, t], scene.masks[v, t]) for t in range(T)]
            fps = scene.config.fps
            colour = np.stack([p[0] for p in pairs])
            write_video(folder / videos[v]["video_path"], colour, fps, quality=video_quality, full_chroma=True)
            write_video(folder / videos[v]["mask_video_path"], np.stack([p[1] for p in pairs]), fps, lossless=True)

        # ffmpeg encodes in subprocesses, so cameras are encoded in parallel threads
        _run_parallel([lambda v=v: encode(v) for v in range(V)], workers, progress, "writing videos")
        transforms["videos"] = videos

    scene_json = scene.config.to_json()
    if scene.extras:
        (folder / "extras").mkdir()
        scene_json["extras"] = {}
        for name, group in scene.extras.items():
            np.savez_compressed(
                folder / "extras" / f"{name}.npz", **{k: a.detach().cpu().numpy() for k, a in group.items()}
            )
            scene_json["extras"][name] = f"extras/{name}.npz"
    _write_json(folder / TRANSFORMS_JSON, transforms)
    _write_json(folder / SCENE_JSON, scene_json)  # last: a folder with scene.json is complete


def _write_frame(scene: Scene, folder: Path, layout: str, v: int, t: int, name: str) -> None:
    rgb8, a8 = _straight_colour(scene.images[v, t], scene.masks[v, t])
    if layout == "rgba":
        _write_png(folder / "images" / name, np.concatenate([rgb8, a8[..., None]], axis=2))
    else:
        _write_png(folder / "images" / name, rgb8)
        _write_png(folder / "masks" / name, a8)
