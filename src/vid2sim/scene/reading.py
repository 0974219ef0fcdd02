"""Reading scene folders: :func:`load_scene` and its helpers.

:func:`load_scene` validates everything (the JSON files through :mod:`vid2sim.scene.validation`, then the
images, masks, videos and extras) and raises :class:`~vid2sim.scene.validation.SceneFormatError` listing every
problem (file, frame, camera and field named). Images and masks are decoded on a thread pool
(:func:`run_parallel`, which :mod:`vid2sim.scene.writing` uses too); the result is a
:class:`~vid2sim.scene.folder.Scene`.

Memory: images are loaded eagerly. The full benchmark preset (12 views × 24 frames × 448²) takes
925 MB as float32 (images 694 MB + masks 231 MB) and 231 MB as uint8; pass
``load_scene(path, dtype=torch.uint8)`` to keep the 4× smaller form and convert per frame with
:meth:`Scene.image <vid2sim.scene.folder.Scene.image>` / :meth:`~vid2sim.scene.folder.Scene.mask`, or a
sub-range with :meth:`~vid2sim.scene.folder.Scene.subset`.
"""

from __future__ import annotations

import os
import threading
import warnings
import zipfile
import zlib
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor
from tqdm import tqdm

from vid2sim.runtime.errors import InputError
from vid2sim.runtime.limits import (
    image_size_problem,
    max_image_pixels,
    npz_size_problem,
    outside,
)
from vid2sim.scene.folder import SCENE_JSON, TRANSFORMS_JSON, Scene, SceneConfig
from vid2sim.scene.validation import (
    TIME_RTOL,
    Problems,
    SceneFormatError,
    TransformsPlan,
    VideoEntry,
    index_problems,
    parse_scene_json,
    parse_transforms,
    read_json,
    resolve_intrinsics,
)
from vid2sim.scene.video import VideoError, load_video
from vid2sim.splats.cameras import Camera

__all__ = ["load_scene", "run_parallel"]


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


def run_parallel(
    jobs: list[Callable[[], None]], workers: int | None, progress: bool, desc: str
) -> None:
    """Run ``jobs`` on a thread pool (PIL and zlib release the GIL), with a progress bar.

    Used to decode a scene's frames and videos here and to encode them in :mod:`vid2sim.scene.writing`.

    Args:
        jobs: functions of no argument, run once each.
        workers: threads (default min(4, CPU count)); 1 runs the jobs in order on this thread.
        progress: show a progress bar.
        desc: the progress bar's label.

    Raises:
        InputError: ``workers`` < 1.
        Exception: the first exception of a job, re-raised after every started job has finished, so nothing
            keeps writing into a folder that the caller is about to delete.
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
    """A scene in the frames layout: cameras, images (V, T, H, W, 3) composited on white, masks (V, T, H, W) and
    frame times (T,). The files are found, their sizes checked from the headers, the cameras and times made, then
    the pixels decoded on ``workers`` threads; each stage raises SceneFormatError listing all its problems."""
    problems = Problems()
    V, T = plan.num_views, plan.num_frames
    assert T is not None
    files = _frame_files(root, plan, problems)
    problems.raise_if_any(root)
    sizes = _frame_sizes(plan, files, problems)
    problems.raise_if_any(root)
    cam_sizes = _camera_sizes(plan, sizes, problems)
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
    decode = _FrameDecoder(plan, files, images_np, masks_np, np.dtype(work), problems)
    jobs = [lambda v=v, t=t: decode(v, t) for v in range(V) for t in range(T)]
    run_parallel(jobs, workers, progress, "loading scene")
    problems.raise_if_any(root)
    return cameras, torch.from_numpy(images_np), torch.from_numpy(masks_np), times


def _frame_files(root: Path, plan: TransformsPlan, problems: Problems
                 ) -> dict[tuple[int, int], tuple[Path, Path | None]]:
    """The image and mask file (None: the image's alpha) of every (camera, frame) whose files are all found; a
    problem names each file that is not."""
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
    return files


def _frame_sizes(plan: TransformsPlan, files: dict[tuple[int, int], tuple[Path, Path | None]], problems: Problems
                 ) -> dict[tuple[int, int], tuple[int, int]]:
    """The (width, height) of every (camera, frame) image, read from the headers; a problem for each image or mask
    that cannot be read and each mask of another size than its image."""
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
    return sizes


def _camera_sizes(plan: TransformsPlan, sizes: dict[tuple[int, int], tuple[int, int]], problems: Problems
                  ) -> list[tuple[int, int]]:
    """Each camera's image size: the most common of its frames' (so one odd image is named as the odd one instead
    of every good image being blamed for differing from it); a problem for each image of another size."""
    T = plan.num_frames
    cam_sizes = []
    for v in range(plan.num_views):
        usual = Counter(sizes[(v, t)] for t in range(T)).most_common(1)[0][0]
        cam_sizes.append(usual)
        for t in range(T):
            if sizes[(v, t)] != usual:
                e = plan.grid[v][t]
                problems.add(
                    f"{TRANSFORMS_JSON}: {e.where}: image '{e.file_path}' is {sizes[(v, t)][0]}x{sizes[(v, t)][1]} "
                    f"but camera {v}'s other images are {usual[0]}x{usual[1]}"
                )
    return cam_sizes


class _FrameDecoder:
    """Decodes one (camera, frame) of the frames layout into ``images`` (V, T, H, W, 3) composited on white and
    ``masks`` (V, T, H, W), from an RGBA image or an RGB(A) image with a mask file; thread-safe (a problem is added
    under a lock)."""

    def __init__(self, plan: TransformsPlan, files: dict[tuple[int, int], tuple[Path, Path | None]],
                 images: np.ndarray, masks: np.ndarray, work: np.dtype, problems: Problems) -> None:
        self.plan, self.files, self.images, self.masks, self.work = plan, files, images, masks, work
        self.problems = problems
        self.lock = threading.Lock()

    def _problem(self, message: str) -> None:
        with self.lock:
            self.problems.add(message)

    def __call__(self, v: int, t: int) -> None:
        e = self.plan.grid[v][t]
        img_path, msk_path = self.files[(v, t)]
        where = f"{TRANSFORMS_JSON}: {e.where}"
        work = self.work
        try:
            raster = _read_raster(img_path)
        except (OSError, UnidentifiedImageError, ValueError) as exc:
            return self._problem(f"{where}: cannot read image '{e.file_path}': {exc}")
        channels = raster.shape[2]
        alpha = raster[..., -1] if channels in (2, 4) else None
        colour = raster[..., :3] if channels >= 3 else np.repeat(raster[..., :1], 3, axis=2)
        if msk_path is None:
            if alpha is None:
                return self._problem(
                    f"{where}: image '{e.file_path}' has no alpha channel and the frame has no mask_path; "
                    "give an RGBA image (alpha = object mask) or a mask_path"
                )
            mask = _unit(alpha, work)
        else:
            if alpha is not None and alpha.min() < np.iinfo(alpha.dtype).max:
                return self._problem(
                    f"{where}: image '{e.file_path}' has a (non-opaque) alpha channel and the frame also has "
                    f"mask_path '{e.mask_path}'; give the mask one way only"
                )
            try:
                mask = _read_mask(msk_path)
            except (OSError, UnidentifiedImageError, ValueError) as exc:
                return self._problem(f"{where}: cannot use mask '{e.mask_path}': {exc}")
            mask = _unit(mask, work)
        _store(self.images, (v, t), _composite(_unit(colour, work), mask))
        _store(self.masks, (v, t), mask)


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
    run_parallel([lambda v=v: read_camera(v) for v in range(V)], workers, progress, "loading videos")
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
