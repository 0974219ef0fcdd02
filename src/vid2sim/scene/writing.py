"""Writing scene folders: :func:`write_scene`, :func:`move_into_place` and their helpers.

:func:`write_scene` writes a :class:`~vid2sim.scene.folder.Scene` into a temporary folder next to the
target (PNG frames or per-camera videos, ``transforms.json``, ``scene.json`` last, extras) and renames it into
place with :func:`move_into_place` (:func:`vid2sim.runtime.files.move_folder_into_place`, re-exported here), so a
failed write never leaves a partial scene. Other folder writers (assets, exports, reports) use it for the same
guarantee.
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import move_folder_into_place as move_into_place
from vid2sim.runtime.files import remove_leftovers
from vid2sim.scene.folder import SCENE_JSON, TRANSFORMS_JSON, Scene
from vid2sim.scene.reading import run_parallel
from vid2sim.scene.video import write_video
from vid2sim.splats.cameras import Camera

__all__ = ["write_scene", "move_into_place", "LAYOUTS"]

#: ``write_scene`` layouts: RGBA PNGs, RGB PNGs + grey mask PNGs, or one mp4 (+ mask mp4) per camera
LAYOUTS = ("rgba", "rgb+mask", "video")
#: zlib level of written PNGs (1 fast .. 9 small); 3 is ~3x faster than 9 and ~10% larger
PNG_COMPRESS_LEVEL = 3


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
    remove_leftovers(target)  # what a killed writer of the same scene left
    tmp = target.parent / f".{target.name}.writing-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    try:
        _write_contents(scene, tmp, layout, float(video_quality), progress, workers)
        move_into_place(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


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
        run_parallel(jobs, workers, progress, "writing scene")
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
        run_parallel([lambda v=v: encode(v) for v in range(V)], workers, progress, "writing videos")
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


def _write_png(path: Path, array: np.ndarray) -> None:
    """Write a uint8 (H, W), (H, W, 3) or (H, W, 4) array as an 8-bit PNG."""
    Image.fromarray(array).save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


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
