"""``import_capture``: a capture folder in (:mod:`vid2sim.scene.capture.layout`), a scene folder out.

Stages, each in its own module:

1. the folder's cameras, plates, masks and calibration (:mod:`~.layout`); frame counts, sizes and the frame rate
   checked across cameras (:mod:`~.frames`);
2. the calibration (COLMAP text or binary, :mod:`~.colmap`; nerfstudio, :mod:`~.nerfstudio`), matched to the
   cameras by name;
3. frames, plates and the user's masks undistorted to pinhole cameras (:mod:`~.undistort`);
4. masks: the user's, else from the clean plate, else from a plate estimated from the video
   (:mod:`~.masks`, :mod:`~.plate`), with per-view, per-frame area, confidence and flags; a plate that
   disagrees with the frames (a moving camera) is refused;
5. the metric frame: scale, gravity and floor from the object's free flight and contact (:mod:`~.metric`);
6. per-camera colour to a reference camera (:mod:`~.colour`);
7. the scene: images composited on white (the plate's share removed at soft edges), cameras in the metric frame,
   ``scene.json`` with every estimate, its uncertainty and the checks in ``metadata.capture``; written beside the
   target and renamed, so the folder appears complete or not at all.

Every problem with the input raises :class:`~.errors.CaptureError` naming the camera and the file.
"""

from __future__ import annotations

import json
import math
import shutil
import time
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch
from scipy import ndimage

from vid2sim.runtime.errors import ConfigError
from vid2sim.runtime.files import remove_leftovers
from vid2sim.scene.capture.cameras import CaptureCamera
from vid2sim.scene.capture.colmap import colmap_cameras, points_by_camera, read_colmap
from vid2sim.scene.capture.colour import ColourConfig, ColourMap, colour_maps, floor_grid
from vid2sim.scene.capture.errors import CaptureError
from vid2sim.scene.capture.frames import frame_count, read_frames, read_masks, read_rgb
from vid2sim.scene.capture.jsonify import jsonable
from vid2sim.scene.capture.layout import CALIBRATIONS, CaptureLayout, discover_capture
from vid2sim.scene.capture.masks import MaskConfig, MaskResult, holes_filled, masks_from_plate, summarise
from vid2sim.scene.capture.metric import (
    MetricConfig,
    MetricFrame,
    NoFreeFlight,
    Track,
    solve_metric_frame,
    track_object,
)
from vid2sim.scene.capture.nerfstudio import read_transforms
from vid2sim.scene.capture.plate import estimate_plate, image_shift
from vid2sim.scene.capture.undistort import make_undistortion, reduce
from vid2sim.scene.folder import Scene, SceneConfig
from vid2sim.scene.writing import move_into_place, write_scene
from vid2sim.splats.cameras import Camera

IMPORT_CONFIG_JSON = "capture_import.json"
IMPORT_REPORT_JSON = "capture_report.json"


@dataclass
class CaptureImportConfig:
    """What ``import-capture`` does, with what a user knows (defaults: measure everything).

    Attributes:
        calibration: ``"colmap"`` (default) or ``"transforms"``; when the chosen one is missing the other is used.
        fps: frames per second, overriding ``capture.json`` and the videos.
        frames: (A, B): the scene keeps frames A … B − 1 (all by default); scale and gravity are measured on every
            frame of the videos.
        every: the scene keeps every ``every``-th of those frames (film at 60 fps, keep 20 fps: the free fall is
            measured on all 60).
        gravity_axis: the direction gravity points in the calibration frame (3,), instead of measuring it.
        scale: metres per calibration unit, instead of measuring it.
        floor: the floor's height in calibration units along up (−``gravity_axis``): the plane up·x = floor.
        observed_views, held_out_views: camera names or indices (in camera-name order) for fitting / novel views.
        observed_frames, held_out_frames: scene frame indices (after ``frames``).
        colour_reference: the camera whose colours the others are mapped to (default the first observed).
        undistort_alpha: ``cv2.getOptimalNewCameraMatrix``'s alpha (0: every output pixel sees the scene).
        downscale: the scene keeps the frames reduced this many times (block averages); masks are found at the full
            resolution first, so their reduced values are each pixel's coverage.
        max_plate_shift: largest image shift (px) between a clean plate and the first frames.
        max_stray: largest share of the pixels outside the object that may differ from the plate in the first
            frames (more: the camera moved or the light changed).
        masks, metric, colour: the stages' settings.
        layout: the scene folder's layout (``"rgba"``, ``"rgb+mask"`` or ``"video"``).
        threads: torch and OpenCV threads (None: their defaults).
    """

    calibration: str = "colmap"
    fps: float | None = None
    frames: tuple[int, int] | None = None
    every: int = 1
    gravity_axis: tuple[float, float, float] | None = None
    scale: float | None = None
    floor: float | None = None
    observed_views: list[str | int] | None = None
    held_out_views: list[str | int] | None = None
    observed_frames: list[int] | None = None
    held_out_frames: list[int] | None = None
    colour_reference: str | None = None
    undistort_alpha: float = 0.0
    downscale: int = 1
    max_plate_shift: float = 2.0
    max_stray: float = 0.2
    masks: MaskConfig = field(default_factory=MaskConfig)
    metric: MetricConfig = field(default_factory=MetricConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)
    layout: str = "rgba"
    threads: int | None = None

    def __post_init__(self) -> None:

        if self.calibration not in CALIBRATIONS:
            raise ConfigError(f"calibration must be one of {', '.join(CALIBRATIONS)}, got {self.calibration!r}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError(f"fps must be a positive number, got {self.fps}")
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise ConfigError(f"scale must be a positive number (metres per calibration unit), got {self.scale}")
        if self.gravity_axis is not None:
            g = np.asarray(self.gravity_axis, dtype=np.float64)
            if g.shape != (3,) or not np.isfinite(g).all() or np.linalg.norm(g) == 0:
                raise ConfigError(f"gravity_axis must be a non-zero 3-vector, got {self.gravity_axis}")
        frames = self.frames
        if frames is not None and (len(frames) != 2 or frames[0] < 0 or frames[1] <= frames[0]):
            raise ConfigError(f"frames must be A:B with 0 <= A < B, got {self.frames}")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ConfigError(f"every must be an integer >= 1, got {self.every!r}")
        if isinstance(self.downscale, bool) or not isinstance(self.downscale, int) or self.downscale < 1:
            raise ConfigError(f"downscale must be an integer >= 1, got {self.downscale!r}")
        if self.layout not in ("rgba", "rgb+mask", "video"):
            raise ConfigError(f"layout must be 'rgba', 'rgb+mask' or 'video', got {self.layout!r}")

    def to_json(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self), default=list))


def parse_axis(text: str) -> tuple[float, float, float]:
    """A gravity axis from the command line: ``x``, ``-y``, ``+z`` or ``gx,gy,gz``."""

    t = text.strip().lower()
    axes = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    if t.lstrip("+-") in axes:
        sign = -1.0 if t.startswith("-") else 1.0
        return tuple(sign * c for c in axes[t.lstrip("+-")])  # type: ignore[return-value]
    try:
        vals = tuple(float(v) for v in t.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals) or not any(vals):
        raise ConfigError(f"--gravity-axis must be x, -y, +z, ... or three numbers gx,gy,gz; got {text!r}")
    return vals  # type: ignore[return-value]


@dataclass
class ViewData:
    """One camera after stages 1–4: its pinhole camera (reduced), frames (T, H, W, 3) float32, plate (or None),
    masks and their report (all reduced), and where each came from; for the object's track, the masks before the
    reduction (T, k·H, k·W) as uint8 coverage, their holes filled (:func:`~.masks.holes_filled`), and their camera."""

    name: str
    camera: CaptureCamera
    frames: np.ndarray
    plate: np.ndarray | None
    plate_source: str
    masks: MaskResult
    mask_source: str
    source: str
    track_camera: CaptureCamera
    track_masks: np.ndarray


def _stage_times() -> tuple[dict[str, float], Any]:
    times: dict[str, float] = {}
    t0 = [time.perf_counter()]

    def lap(name: str) -> None:
        now = time.perf_counter()
        times[name] = round(now - t0[0], 3)
        t0[0] = now

    return times, lap


def read_calibration(layout: CaptureLayout, choice: str, sizes: dict[str, tuple[int, int]]
                     ) -> tuple[dict[str, CaptureCamera], np.ndarray | None, list[set[str]] | None, str]:
    """The cameras of the chosen calibration (the other one when it is missing), COLMAP's points (P, 3) with the
    camera names seeing each (or None), and the calibration file's path."""
    use = choice
    if use == "colmap" and layout.colmap is None:
        use = "transforms"
    if use == "transforms" and layout.transforms is None:
        use = "colmap"
    points = visible = None
    if use == "colmap":
        assert layout.colmap is not None
        model = read_colmap(layout.colmap)
        cameras = colmap_cameras(model, layout.camera_of_name)
        source = model.file("images")
        if len(model.points.ids):
            points, _, visible = points_by_camera(model, cameras)
    else:
        assert layout.transforms is not None
        cameras, applied = read_transforms(layout.transforms, layout.camera_of_name, sizes)
        source = str(layout.transforms)
        if layout.colmap is not None:  # COLMAP's points, carried into nerfstudio's frame
            try:
                model = read_colmap(layout.colmap)
            except CaptureError:
                model = None
            if model is not None and len(model.points.ids):
                pts = model.points.xyz
                if applied is not None:
                    pts = pts @ applied[:3, :3].T + applied[:3, 3]
                points, visible = pts, None
    for name in layout.cameras:
        if name not in cameras:
            raise CaptureError(f"not in the calibration (it calibrates {', '.join(sorted(cameras)) or 'nothing'})",
                               camera=name, file=source)
    for name, cam in cameras.items():
        w, h = sizes[name]
        if (cam.width, cam.height) != (w, h):
            raise CaptureError(f"calibrated for {cam.width}x{cam.height} images but its frames are {w}x{h}",
                               camera=name, file=source)
    return cameras, points, visible, source


def _check_frames(layout: CaptureLayout, config: CaptureImportConfig
                  ) -> tuple[int, float, dict[str, tuple[int, int]], str]:
    """Frame count T, frame rate and sizes of every camera, checked to agree."""
    counts, rates, sizes = {}, {}, {}
    for name, src in layout.cameras.items():
        counts[name], rates[name], sizes[name] = frame_count(src)
    first = next(iter(layout.cameras))
    T = counts[first]
    for name, n in counts.items():
        if n != T:
            raise CaptureError(f"{n} frames, but camera '{first}' has {T}: the cameras must be synchronised and "
                               "trimmed to the same frames", camera=name, file=layout.cameras[name].source)
    for name, size in sizes.items():
        if size != sizes[first]:
            raise CaptureError(f"{size[0]}x{size[1]} frames, but camera '{first}' has {sizes[first][0]}x"
                               f"{sizes[first][1]}; vid2sim needs one image size (resize the videos)", camera=name,
                               file=layout.cameras[name].source)
    if config.fps is not None:
        fps, fps_source = float(config.fps), "--fps"
    elif layout.settings.get("fps") is not None:
        fps, fps_source = float(layout.settings["fps"]), "capture.json"
    else:
        known = {n: r for n, r in rates.items() if r}
        if not known:
            raise CaptureError("no frame rate: the frames are images; give --fps or capture.json {\"fps\": ...}",
                               file=layout.root)
        ref = next(iter(known))
        for name, r in known.items():
            if abs(r - known[ref]) > 0.01 * known[ref]:
                raise CaptureError(f"{r:g} fps, but camera '{ref}' has {known[ref]:g} fps; the cameras must film "
                                   "at one frame rate", camera=name, file=layout.cameras[name].source)
        fps, fps_source = float(known[ref]), "videos"
    return T, fps, sizes, fps_source


def _view_indices(names: list[str], values: Sequence[str | int] | None, what: str) -> list[int] | None:
    if values is None:
        return None

    out = []
    for v in values:
        if isinstance(v, int) or (isinstance(v, str) and v.isdigit() and v not in names):
            i = int(v)
            if not 0 <= i < len(names):
                raise ConfigError(f"{what}: view index {i} is out of range (cameras: {', '.join(names)})")
            out.append(i)
        elif v in names:
            out.append(names.index(v))
        else:
            raise ConfigError(f"{what}: no camera {v!r} (cameras: {', '.join(names)})")
    return out


def load_views(layout: CaptureLayout, cameras: dict[str, CaptureCamera], T: int, config: CaptureImportConfig
               ) -> list[ViewData]:
    """Stages 3–4 for every camera: undistorted frames, plates and masks with their reports."""
    views = []
    first_frames = list(range(min(3, T)))
    for name, src in layout.cameras.items():
        und = make_undistortion(cameras[name], config.undistort_alpha)
        out_camera = make_undistortion(cameras[name], config.undistort_alpha, config.downscale).camera
        size = (cameras[name].width, cameras[name].height)
        frames = und.stack(read_frames(src, 0, T)).astype(np.float32) / 255.0
        plate = None
        plate_source = "none"
        if src.plate is not None:
            raw = read_rgb(src.plate, name)
            if (raw.shape[1], raw.shape[0]) != size:
                raise CaptureError(f"clean plate of {raw.shape[1]}x{raw.shape[0]} pixels, but the frames are "
                                   f"{size[0]}x{size[1]}", camera=name, file=src.plate)
            plate = und(raw).astype(np.float32) / 255.0
            plate_source = str(src.plate)
        if src.masks is not None:
            m = und.stack(read_masks(src, T, 0, T, size))
            result = summarise(np.clip(m, 0, 1).astype(np.float32), np.ones(T), float("nan"), np.zeros(T),
                               config.masks)
            mask_source = str(src.masks[0].parent)
        else:
            if plate is None:
                est = estimate_plate(frames, config.masks)
                plate = est.plate
                plate_source = f"estimated from the video ({int(est.unknown.sum())} pixels never free, " \
                               f"{est.ghosts} ghost regions)"
            result = masks_from_plate(frames, plate, config.masks)
            mask_source = "clean plate" if src.plate is not None else "estimated plate"
            if src.plate is not None:
                _check_static(name, src.plate, frames, plate, result, first_frames, config)
        k = config.downscale
        track_masks = np.round(np.clip(holes_filled(result.masks), 0.0, 1.0) * 255).astype(np.uint8)
        if k > 1:
            frames = reduce(frames, k, True)
            plate = None if plate is None else reduce(plate, k, True)
            result = summarise(reduce(result.masks, k, False), result.confidence, result.noise, result.stray,
                               config.masks)
        views.append(ViewData(name, out_camera, frames, plate, plate_source, result, mask_source, str(src.source),
                              und.camera, track_masks))
    return views


def _check_static(name: str, path: Path, frames: np.ndarray, plate: np.ndarray, masks: MaskResult,
                  first_frames: Sequence[int], config: CaptureImportConfig) -> None:
    """Refuse a clean plate that disagrees with the first frames on the static background: too many pixels outside
    the object differ from it, or the frame (the object's region filled from the plate) is shifted against it."""
    for t in first_frames:
        if masks.stray[t] > config.max_stray:
            raise CaptureError(f"the clean plate and frame {t} disagree on the static background "
                               f"({100 * masks.stray[t]:.0f} % of the pixels outside the object differ): the camera "
                               "moved, or the light changed; re-film the plate or leave it out", camera=name, file=path)
        obj = ndimage.binary_dilation(masks.masks[t] > 0.05, iterations=3)[..., None]
        shift, _ = image_shift(plate, np.where(obj, plate, frames[t]))
        if shift > config.max_plate_shift:
            raise CaptureError(f"the clean plate and frame {t} disagree on the static background (shifted by "
                               f"{shift:.1f} px): the camera moved between them, or the plate belongs to another "
                               "camera; re-film the plate or leave it out", camera=name, file=path)


def _check_scene_frames(views: list[ViewData], scene_frames: range, layout: CaptureLayout) -> None:
    for view in views:
        for flag, what in ((view.masks.empty, "the object disappears (no mask)"),
                           (view.masks.border, "the object touches the image border (it leaves the view)")):
            bad = [t for t in scene_frames if flag[t]]
            if bad:
                frames = f"frame {bad[0]}" if len(bad) == 1 else f"frames {bad[0]}..{bad[-1]} ({len(bad)} frames)"
                raise CaptureError(f"{what} in {frames}: keep the object inside every view (trim the frames with "
                                   "--frames, hold the camera out, or re-film)", camera=view.name,
                                   file=layout.cameras[view.name].source)


def _check_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists; pass overwrite=True (--overwrite) to replace a scene folder")
    if out.exists() and not (out / "scene.json").is_file() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not a scene folder (no scene.json): refusing to replace it")


def measure_metric(views: list[ViewData], fps: float, scene_frames: range, points: np.ndarray | None,
                   layout: CaptureLayout, config: CaptureImportConfig) -> tuple[Track, MetricFrame]:
    """Stage 5: the object's track from the masks at the filmed resolution (half the pixel size, half the
    centroid's noise), then scale, gravity and floor (the user's values win)."""
    usable = np.stack([~v.masks.empty & ~v.masks.border for v in views])
    track = track_object([v.track_camera for v in views], [v.track_masks for v in views], usable, config.metric)
    try:
        down = None if config.gravity_axis is None else np.asarray(config.gravity_axis, dtype=np.float64)
        metric = solve_metric_frame(track, 1.0 / fps, config.metric, scene_frames, points=points,
                                    scale=config.scale, down=down, floor=config.floor,
                                    cameras=[v.camera for v in views], plates=[v.plate for v in views])
    except NoFreeFlight:
        missing = " and ".join(n for n, v in (("--scale", config.scale), ("--gravity-axis", config.gravity_axis))
                               if v is None)
        raise CaptureError(f"no free-flight frames to measure gravity on (the object is never seen falling freely "
                           f"in at least 3 frames); pass {missing}", file=layout.root) from None
    return track, metric


@dataclass
class _Colour:
    """Stage 6's result: the colour map of every view, the reference view, the observed and held-out views."""

    maps: list[ColourMap]
    ref: int
    observed: list[int] | None
    held_out: list[int] | None


def match_colours(views: list[ViewData], track: Track, metric: MetricFrame, scene_frames: range,
                  points: np.ndarray | None, visible: list[set[str]] | None, config: CaptureImportConfig) -> _Colour:
    """Stage 6: each view's affine colour map to the reference camera, fitted on the plates over the floor around
    the object (and COLMAP's points); identities without plates."""
    names = [v.name for v in views]
    obs = _view_indices(names, config.observed_views, "observed_views")
    held = _view_indices(names, config.held_out_views, "held_out_views")
    if config.colour_reference is not None:
        if config.colour_reference not in names:
            raise ConfigError(f"colour_reference: no camera {config.colour_reference!r} (cameras: {', '.join(names)})")
        ref = names.index(config.colour_reference)
    else:
        ref = (obs or [i for i in range(len(names)) if i not in (held or [])] or [0])[0]
    plates = [v.plate for v in views]
    if not all(p is not None for p in plates):
        return _Colour([ColourMap.identity() for _ in views], ref, obs, held)
    centre = np.nanmean(track.centres[list(scene_frames)], axis=0)
    pts = floor_grid(-metric.down, metric.floor.offset, centre, 3.0 * track.size)
    vis_idx = None
    if points is not None and len(points):
        if visible is not None:
            vis_idx = [set(range(len(names)))] * len(pts) + [{names.index(n) for n in s} for s in visible]
        pts = np.concatenate([pts, points])
    maps = colour_maps([v.camera for v in views], plates, ref, pts, vis_idx, config.colour)  # type: ignore[arg-type]
    return _Colour(maps, ref, obs, held)


def scene_images(views: list[ViewData], maps: list[ColourMap], keep: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Stage 7's images (V, T, H, W, 3) composited on white — colour-mapped, the plate's share removed at soft
    edges — and masks (V, T, H, W) of the kept frames."""
    H, W = views[0].frames.shape[1:3]
    images = np.empty((len(views), len(keep), H, W, 3), np.float32)
    masks = np.empty((len(views), len(keep), H, W), np.float32)
    for i, v in enumerate(views):
        fr = maps[i](v.frames[keep])
        m = v.masks.masks[keep]
        if v.plate is not None:
            bg = maps[i](v.plate)[None]
            img = fr + (1.0 - m[..., None]) * (1.0 - bg)
        else:
            img = fr * m[..., None] + (1.0 - m[..., None])
        images[i] = np.clip(img, 0.0, 1.0)
        masks[i] = m
    return images, masks


def _report(capture: str | Path, views: list[ViewData], cameras: dict[str, CaptureCamera], calib_source: str,
            fps: float, fps_source: str, T: int, scene_frames: range, colour: _Colour, metric: MetricFrame,
            track: Track, config: CaptureImportConfig) -> dict[str, Any]:
    """``capture_report.json``'s content (without the warnings and the seconds)."""
    names = [v.name for v in views]
    return {
        "capture": str(Path(capture).resolve()),
        "cameras": names,
        "calibration": calib_source,
        "fps": fps, "fps_source": fps_source,
        "video_frames": T,
        "scene_frames": [scene_frames.start, scene_frames.stop],
        "every": config.every,
        "undistortion": {v.name: {"model": cameras[v.name].model, "K": v.camera.K.tolist(),
                                  "distortion": cameras[v.name].distortion.tolist(), "downscale": config.downscale}
                         for v in views},
        "masks": {v.name: {"source": v.mask_source, "plate": v.plate_source,
                           "noise": None if not math.isfinite(v.masks.noise) else v.masks.noise,
                           "area_px": [round(float(a), 1) for a in v.masks.area],
                           "confidence": [round(float(c), 4) for c in v.masks.confidence],
                           "border_frames": np.flatnonzero(v.masks.border).tolist(),
                           "empty_frames": np.flatnonzero(v.masks.empty).tolist(),
                           "jump_frames": np.flatnonzero(v.masks.jump).tolist()} for v in views},
        "colour": {"reference": names[colour.ref], "maps": {v.name: colour.maps[i].to_json()
                                                            for i, v in enumerate(views)}},
        "metric": metric.to_json(),
        "track_units": track.centres.tolist(),
        "object_size_units": track.size,
    }


def build_scene(views: list[ViewData], metric: MetricFrame, colour: _Colour, scene_frames: range, fps: float,
                report: dict[str, Any], config: CaptureImportConfig) -> Scene:
    """Stage 7's scene: images and masks of the kept frames, the cameras in the metric frame, and ``scene.json``'s
    metadata (the report's estimates and warnings)."""
    images, masks = scene_images(views, colour.maps, list(scene_frames))
    cams = []
    for v in views:
        w2c = metric.camera(v.camera.world_to_camera)
        cams.append(Camera(torch.as_tensor(w2c, dtype=torch.float32), torch.as_tensor(v.camera.K, dtype=torch.float32),
                           v.camera.width, v.camera.height))
    metadata = {"capture": {k: report[k] for k in ("capture", "cameras", "calibration", "fps", "scene_frames", "every",
                                                    "colour", "metric", "warnings")}}
    metadata["capture"]["report"] = IMPORT_REPORT_JSON
    scene_config = SceneConfig(dt=config.every / fps, gravity=(0.0, 0.0, -metric.gravity), floor_height=0.0,
                               observed_frames=config.observed_frames, held_out_frames=config.held_out_frames,
                               observed_views=colour.observed, held_out_views=colour.held_out,
                               metadata=jsonable(metadata))
    try:
        return Scene(cams, torch.from_numpy(images), torch.from_numpy(masks), config=scene_config)
    except ValueError as exc:
        raise ConfigError(f"import-capture: {exc}") from None


def _write(scene: Scene, out: Path, report: dict[str, Any], config: CaptureImportConfig, times: dict[str, float],
           lap: Any) -> None:
    """Write the scene beside ``out`` with the config and the report, then rename it into place."""
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(out)  # what a killed import of the same scene left
    staging = out.parent / f".{out.name}.importing-{uuid.uuid4().hex[:12]}"
    try:
        write_scene(scene, staging / "scene", layout=config.layout)
        lap("write")
        report["seconds"] = times
        (staging / "scene" / IMPORT_CONFIG_JSON).write_text(json.dumps(config.to_json(), indent=2) + "\n")
        (staging / "scene" / IMPORT_REPORT_JSON).write_text(json.dumps(jsonable(report), indent=1) + "\n")
        move_into_place(staging / "scene", out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def import_capture(capture: str | Path, out: str | Path, config: CaptureImportConfig | None = None,
                   overwrite: bool = False, progress: bool = False) -> Path:
    """Import the capture folder ``capture`` as the scene folder ``out`` (module docstring).

    Returns:
        ``out``; it also holds ``capture_import.json`` (the config) and ``capture_report.json`` (per view and
        frame: mask area, confidence, flags; the colour maps; the metric frame; stage timings).

    Raises:
        CaptureError: a problem with the capture (the message names the camera and the file).
        FileExistsError: ``out`` exists (without ``overwrite``) or is not a scene folder.
    """
    config = CaptureImportConfig() if config is None else config
    if config.threads is not None:
        torch.set_num_threads(int(config.threads))
        cv2.setNumThreads(int(config.threads))
    out = Path(out)
    _check_output(out, overwrite)
    times, lap = _stage_times()
    say = (lambda m: print(f"[import-capture] {m}", flush=True)) if progress else (lambda m: None)

    layout = discover_capture(capture)
    T, fps, sizes, fps_source = _check_frames(layout, config)
    A, B = config.frames if config.frames is not None else (0, T)
    if B > T:
        raise ConfigError(f"--frames {A}:{B} goes past the videos' {T} frames")
    scene_frames = range(A, B, config.every)
    cameras, points, visible, calib_source = read_calibration(layout, config.calibration, sizes)
    lap("read")
    say(f"{len(layout.cameras)} cameras, {T} frames at {fps:g} fps, calibration {calib_source}")

    views = load_views(layout, cameras, T, config)
    _check_scene_frames(views, scene_frames, layout)
    lap("masks")
    say("masks: " + ", ".join(f"{v.name} {v.mask_source}" for v in views))

    track, metric = measure_metric(views, fps, scene_frames, points, layout, config)
    lap("metric")
    say(f"metres per unit {metric.scale:.6g} ± {metric.scale_sigma:.2g} ({metric.scale_source}); gravity "
        f"± {metric.down_sigma_deg:.2f} deg ({metric.down_source}); floor ({metric.floor.source})")

    colour = match_colours(views, track, metric, scene_frames, points, visible, config)
    lap("colour")

    report = _report(capture, views, cameras, calib_source, fps, fps_source, T, scene_frames, colour, metric, track,
                     config)
    report["warnings"] = _warnings(views, metric, scene_frames, colour.maps, colour.ref)
    scene = build_scene(views, metric, colour, scene_frames, fps, report, config)
    lap("assemble")
    _write(scene, out, report, config, times, lap)
    for w in report["warnings"]:
        say("warning: " + w)
    return out


def _warnings(views: list[ViewData], metric: MetricFrame, scene_frames: range, maps: list[ColourMap],
              ref: int) -> list[str]:
    out = []
    for v in views:
        jumps = [t for t in scene_frames if v.masks.jump[t]]
        if jumps:
            out.append(f"camera '{v.name}': the mask's area jumps by more than half at frames {jumps}; check them "
                       "(a shadow or reflection taken for the object, or part of the object lost)")
        low = [t for t in scene_frames if v.masks.confidence[t] < 0.8]
        if low:
            out.append(f"camera '{v.name}': low mask confidence (< 0.8) at frames {low}: the object's colours are "
                       "close to the background's there; a plainer background or your own masks help")
    if metric.scale_source == "free flight" and metric.scale_sigma > 0.02 * metric.scale:
        out.append(f"the scale is uncertain ({100 * metric.scale_sigma / metric.scale:.1f} %): few free-flight "
                   "frames before the first contact, or masks that disagree between the views; film at a higher "
                   "frame rate, drop from higher, against a plainer background, or give --scale")
    if metric.down_source == "free flight" and metric.down_sigma_deg > 1.0:
        out.append(f"the gravity direction is uncertain ({metric.down_sigma_deg:.1f} deg); give --gravity-axis or "
                   "calibrate with COLMAP points on the floor")
    for i, m in enumerate(maps):
        if i != ref and m.points == 0 and views[i].plate is not None:
            out.append(f"camera '{views[i].name}': too few floor/scene points shared with the reference camera to "
                       "correct its colours; left as filmed")
    out.extend(metric.notes)
    return out

