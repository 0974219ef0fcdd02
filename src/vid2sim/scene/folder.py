"""Scene folders: the input of every vid2sim command, and the in-memory scene they hold.

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

This module holds that data model (:class:`SceneConfig`, :class:`Scene` and the checks they run on
construction) and the names of the two JSON files. :mod:`vid2sim.scene.reading` loads a folder
(:func:`~vid2sim.scene.reading.load_scene`), :mod:`vid2sim.scene.writing` writes one atomically
(:func:`~vid2sim.scene.writing.write_scene`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.scene.validation import (
    SCENE_FORMAT_NAME,
    SCENE_FORMAT_VERSION,
    TIME_RTOL,
    config_problems,
    index_problems,
    is_valid_extra_name,
)
from vid2sim.splats.cameras import Camera

__all__ = [
    "SceneConfig",
    "Scene",
    "SCENE_JSON",
    "TRANSFORMS_JSON",
]

SCENE_JSON = "scene.json"
TRANSFORMS_JSON = "transforms.json"
#: frames observed by default (the paper: 16 observed + 8 future frames out of 24)
DEFAULT_OBSERVED_FRAMES = 16

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
