"""Checking the two JSON files of a scene folder (``scene.json`` and ``transforms.json``).

Everything here turns raw JSON into checked plain values and collects *every* problem it finds
instead of stopping at the first one. Each problem is one line of the form
``<file>: <where>: <what is wrong> [, what was expected]``, for example::

    transforms.json: frame 12 (camera 3, time index 7): file 'images/c03_t007.png' not found
    transforms.json: frame 4 (camera 1, time index 0): transform_matrix is not a rigid transform: ...
    scene.json: dt must be > 0, got -1

:mod:`vid2sim.scene.reading` reads the pixels and raises :class:`SceneFormatError` with the list.
The format itself is documented in ``docs/scene-format.md``.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from vid2sim.runtime.errors import InputError
from vid2sim.runtime.jsonvalues import is_finite_number, is_number

__all__ = [
    "SceneFormatError",
    "Problems",
    "SCENE_FORMAT_NAME",
    "SCENE_FORMAT_VERSION",
    "read_json",
    "config_problems",
    "index_problems",
    "parse_scene_json",
    "parse_transforms",
    "rigid_transform_problem",
    "resolve_intrinsics",
    "FrameEntry",
    "VideoEntry",
    "TransformsPlan",
]

SCENE_FORMAT_NAME = "vid2sim-scene"
SCENE_FORMAT_VERSION = 1

#: at most this many problems are spelled out in an error message (all are kept in ``.problems``)
MAX_PROBLEMS_SHOWN = 20

# tolerances
RIGID_ATOL = 1e-4  # |R Rᵀ − I|, |det R − 1|, last row; Blender/COLMAP exports are far better than this
STATIC_CAMERA_ATOL = 1e-5  # a camera's pose may differ between its frames by this much (relative to scale)
INTRINSICS_RTOL = 1e-3  # fl_x vs camera_angle_x, per-frame intrinsics of one camera
TIME_RTOL = 1e-3  # frame times must step by dt within this relative tolerance


class SceneFormatError(InputError):
    """A scene folder (or a :class:`~vid2sim.scene.folder.Scene` about to be written) is invalid.

    Attributes:
        problems: every problem found, one line each (``<file>: <where>: <what>``).
        root: the scene folder, when known.

    The message lists the problems (at most :data:`MAX_PROBLEMS_SHOWN`), so printing the
    exception is enough for a command-line tool.
    """

    def __init__(self, problems: Iterable[str], root: str | Path | None = None) -> None:
        self.problems = [str(p) for p in problems]
        if not self.problems:
            raise ValueError("SceneFormatError needs at least one problem")
        self.root = Path(root) if root is not None else None
        super().__init__(self._message())

    def _message(self) -> str:
        head = f"invalid scene folder '{self.root}'" if self.root is not None else "invalid scene"
        if len(self.problems) == 1:
            return f"{head}: {self.problems[0]}"
        lines = [f"{head}: {len(self.problems)} problems:"]
        lines += [f"  - {p}" for p in self.problems[:MAX_PROBLEMS_SHOWN]]
        if len(self.problems) > MAX_PROBLEMS_SHOWN:
            lines.append(f"  ... and {len(self.problems) - MAX_PROBLEMS_SHOWN} more")
        return "\n".join(lines)


class Problems:
    """Collects problem lines; :meth:`raise_if_any` turns them into a :class:`SceneFormatError`."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def __bool__(self) -> bool:
        return bool(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def raise_if_any(self, root: str | Path | None = None) -> None:
        if self.items:
            raise SceneFormatError(self.items, root)


# ---------------------------------------------------------------------------------------------
# JSON primitives
# ---------------------------------------------------------------------------------------------


def read_json(path: Path, name: str, root: Path | None = None) -> Any:
    """Parse the JSON file ``path`` (called ``name`` in messages); raise a precise error if it fails."""
    if not path.is_file():
        raise SceneFormatError([f"{name} not found (expected the file '{path}')"], root)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFormatError([f"{name}: cannot read the file: {exc}"], root) from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneFormatError(
            [f"{name}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"], root
        ) from exc


def _is_int(value: Any) -> bool:
    """An int, or a float with an integral value (JSON writers sometimes emit 800.0 for 800)."""
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return True
    return isinstance(value, float) and math.isfinite(value) and value.is_integer()


def _show(value: Any, limit: int = 60) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def check_keys(
    obj: dict,
    allowed: Iterable[str],
    where: str,
    problems: Problems,
    ignored: Iterable[str] = (),
) -> None:
    """Report every key of ``obj`` that is neither allowed nor in ``ignored``, suggesting a close match."""
    allowed = sorted(set(allowed))
    known = set(allowed) | set(ignored)
    for key in obj:
        if key in known:
            continue
        close = difflib.get_close_matches(str(key), allowed, n=1, cutoff=0.6)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        problems.add(f"unknown key '{key}' in {where}{hint}; allowed keys: {', '.join(allowed)}")


def _number(obj: dict, key: str, where: str, problems: Problems) -> float | None:
    """The finite number at ``obj[key]`` (None and a problem when it is something else)."""
    value = obj[key]
    if not is_finite_number(value):
        problems.add(f"{where}: {key} must be a finite number, got {_show(value)}")
        return None
    return float(value)


# ---------------------------------------------------------------------------------------------
# scene.json and SceneConfig
# ---------------------------------------------------------------------------------------------

SCENE_JSON_KEYS = (
    "format",
    "version",
    "dt",
    "fps",
    "gravity",
    "floor_height",
    "observed_frames",
    "held_out_frames",
    "observed_views",
    "held_out_views",
    "metadata",
    "extras",
)
_INDEX_LISTS = ("observed_frames", "held_out_frames", "observed_views", "held_out_views")


def config_problems(
    dt: Any,
    gravity: Any,
    floor_height: Any,
    observed_frames: Any,
    held_out_frames: Any,
    observed_views: Any,
    held_out_views: Any,
    metadata: Any,
) -> list[str]:
    """Problems with the fields of a scene configuration that do not depend on the scene's size.

    Shared by ``SceneConfig.__post_init__`` and the ``scene.json`` parser so both say the same thing.
    """
    out: list[str] = []
    if not is_finite_number(dt):
        out.append(f"dt must be a finite number of seconds, got {_show(dt)}")
    elif float(dt) <= 0:
        out.append(f"dt must be > 0, got {dt:g}")
    if (
        not isinstance(gravity, (list, tuple))
        or len(gravity) != 3
        or not all(is_finite_number(g) for g in gravity)
    ):
        out.append(f"gravity must be 3 finite numbers (m/s², world frame), got {_show(gravity)}")
    elif floor_height is not None and all(float(g) == 0.0 for g in gravity):
        out.append("floor_height needs a non-zero gravity (the floor is perpendicular to it), got gravity [0, 0, 0]")
    if floor_height is not None and not is_finite_number(floor_height):
        out.append(f"floor_height must be a finite number (metres) or null, got {_show(floor_height)}")
    lists = {
        "observed_frames": observed_frames,
        "held_out_frames": held_out_frames,
        "observed_views": observed_views,
        "held_out_views": held_out_views,
    }
    for name, value in lists.items():
        if value is None:
            continue
        if not isinstance(value, (list, tuple)) or not all(_is_int(v) for v in value):
            out.append(f"{name} must be a list of integers or None, got {_show(value)}")
            continue
        bad = [int(v) for v in value if int(v) < 0]
        if bad:
            out.append(f"{name} must hold indices >= 0, got {bad[0]}")
        dup = sorted({int(v) for v in value if list(value).count(v) > 1})
        if dup:
            out.append(f"{name} lists index {dup[0]} more than once")
    for kind in ("frames", "views"):
        obs, held = lists[f"observed_{kind}"], lists[f"held_out_{kind}"]
        if isinstance(obs, (list, tuple)) and isinstance(held, (list, tuple)):
            both = sorted(set(obs) & set(held))
            if both:
                out.append(f"observed_{kind} and held_out_{kind} both contain {both[0]}; they must be disjoint")
    if not isinstance(metadata, dict):
        out.append(f"metadata must be a JSON object (dict), got {type(metadata).__name__}")
    else:
        try:
            json.dumps(metadata, allow_nan=False)
        except (TypeError, ValueError) as exc:
            out.append(f"metadata must be JSON-serialisable (plain numbers, strings, lists, dicts): {exc}")
    return out


def index_problems(
    num_views: int,
    num_frames: int,
    observed_frames: Iterable[int] | None,
    held_out_frames: Iterable[int] | None,
    observed_views: Iterable[int] | None,
    held_out_views: Iterable[int] | None,
) -> list[str]:
    """Problems with view/frame index lists given the scene's size (V views, T frames)."""
    out: list[str] = []
    for name, values, n, what in (
        ("observed_frames", observed_frames, num_frames, "frames"),
        ("held_out_frames", held_out_frames, num_frames, "frames"),
        ("observed_views", observed_views, num_views, "views"),
        ("held_out_views", held_out_views, num_views, "views"),
    ):
        if values is None:
            continue
        bad = [int(v) for v in values if not 0 <= int(v) < n]
        if bad:
            out.append(f"{name} contains {bad[0]}, but the scene has {n} {what} (indices 0..{n - 1})")
    return out


def parse_scene_json(obj: Any, problems: Problems, name: str = "scene.json") -> tuple[dict, dict[str, str]]:
    """Check the parsed ``scene.json`` and return ``(config_kwargs, extras)``.

    ``config_kwargs`` holds the ``SceneConfig`` fields found (missing ones keep their defaults);
    ``extras`` maps extra-array names to paths relative to the scene folder.
    """
    if not isinstance(obj, dict):
        problems.add(f"{name}: the top level must be a JSON object, got {type(obj).__name__}")
        return {}, {}
    check_keys(obj, SCENE_JSON_KEYS, f"{name}", problems)
    if "format" in obj and obj["format"] != SCENE_FORMAT_NAME:
        problems.add(f"{name}: format must be '{SCENE_FORMAT_NAME}', got {_show(obj['format'])}")
    if "version" in obj:
        version = obj["version"]
        if not _is_int(version) or int(version) < 1:
            problems.add(f"{name}: version must be a positive integer, got {_show(version)}")
        elif int(version) > SCENE_FORMAT_VERSION:
            problems.add(
                f"{name}: format version {int(version)} is newer than this vid2sim reads "
                f"(up to {SCENE_FORMAT_VERSION}); upgrade vid2sim"
            )
    kwargs: dict[str, Any] = {}
    if "dt" in obj:
        kwargs["dt"] = obj["dt"]
    if "gravity" in obj:
        g = obj["gravity"]
        kwargs["gravity"] = tuple(g) if isinstance(g, list) else g
    if "floor_height" in obj:
        kwargs["floor_height"] = obj["floor_height"]
    for key in _INDEX_LISTS:
        if key in obj:
            kwargs[key] = obj[key]
    if "metadata" in obj:
        kwargs["metadata"] = obj["metadata"]
    defaults = {"dt": 0.05, "gravity": (0.0, 0.0, -9.8), "floor_height": None, "metadata": {}}
    merged = {**defaults, **{k: None for k in _INDEX_LISTS}, **kwargs}
    before = len(problems)
    for message in config_problems(**merged):
        problems.add(f"{name}: {message}")
    if "fps" in obj and len(problems) == before:
        fps = obj["fps"]
        if not is_number(fps) or not float(fps) > 0:
            problems.add(f"{name}: fps must be a positive number, got {_show(fps)}")
        elif abs(float(fps) * float(merged["dt"]) - 1.0) > 1e-6:
            problems.add(
                f"{name}: fps = {float(fps):g} disagrees with dt = {float(merged['dt']):g} s "
                f"(fps must be 1/dt = {1.0 / float(merged['dt']):g}); fps is informational, drop it or fix it"
            )
    extras: dict[str, str] = {}
    if "extras" in obj:
        value = obj["extras"]
        if not isinstance(value, dict):
            problems.add(f"{name}: extras must be an object mapping names to .npz paths, got {_show(value)}")
        else:
            for key, rel in value.items():
                if not is_valid_extra_name(key):
                    problems.add(
                        f"{name}: extras name {key!r} is not allowed (use letters, digits, '_' and '-')"
                    )
                elif not isinstance(rel, str) or not rel.endswith(".npz"):
                    problems.add(f"{name}: extras '{key}' must be a path to an .npz file, got {_show(rel)}")
                else:
                    extras[key] = rel
    return kwargs, extras


def is_valid_extra_name(name: Any) -> bool:
    """Extra-array names are file-name safe: non-empty, letters/digits/'_'/'-' only."""
    return isinstance(name, str) and bool(name) and all(c.isalnum() or c in "_-" for c in name) and name.isascii()


# ---------------------------------------------------------------------------------------------
# camera matrices and intrinsics
# ---------------------------------------------------------------------------------------------


def parse_matrix(value: Any) -> np.ndarray | None:
    """A (4, 4) float64 array from a 4x4 or 3x4 nested list of numbers (None if it is not one)."""
    if not isinstance(value, list) or len(value) not in (3, 4):
        return None
    if not all(isinstance(row, list) and len(row) == 4 and all(is_number(x) for x in row) for row in value):
        return None
    m = np.array(value, dtype=np.float64)
    if m.shape[0] == 3:
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return m


def rigid_transform_problem(matrix: np.ndarray, atol: float = RIGID_ATOL) -> str | None:
    """Why the (4, 4) ``matrix`` is not a rigid transform (rotation + translation), or None if it is."""
    if not np.isfinite(matrix).all():
        return "it contains NaN or infinite values"
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        return f"its last row is {np.round(matrix[3], 6).tolist()}, expected [0, 0, 0, 1]"
    rot = matrix[:3, :3]
    err = float(np.abs(rot @ rot.T - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if err <= atol and abs(det - 1.0) <= atol:
        return None
    sv = np.linalg.svd(rot, compute_uv=False)
    if det < 0 and np.allclose(sv, 1.0, atol=10 * atol):
        return f"its 3x3 block is a reflection (det = {det:.4g}), not a rotation"
    if sv.max() - sv.min() <= 10 * atol * sv.max() and sv.min() > 0:
        return (
            f"its 3x3 block is a rotation scaled by {sv.mean():.6g}; camera poses must be unscaled "
            "(put the scale into the translation instead)"
        )
    return (
        f"its 3x3 block is not a rotation (max |R Rᵀ − I| = {err:.3g}, det = {det:.4g}, "
        f"singular values {np.round(sv, 4).tolist()})"
    )


INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL", "OPENCV_FISHEYE")


def parse_intrinsics(obj: dict, where: str, problems: Problems) -> dict[str, float]:
    """The intrinsics keys present in ``obj``, type- and range-checked (distortion must be zero)."""
    out: dict[str, float] = {}
    for key in INTRINSIC_KEYS:
        if key not in obj:
            continue
        value = _number(obj, key, where, problems)
        if value is None:
            continue
        if key in ("camera_angle_x", "camera_angle_y") and not 0.0 < value < math.pi:
            problems.add(f"{where}: {key} must be a field of view in radians in (0, π), got {value:g}")
        elif key in ("fl_x", "fl_y") and value <= 0:
            problems.add(f"{where}: {key} must be > 0 (pixels), got {value:g}")
        elif key in ("w", "h") and (not _is_int(obj[key]) or value <= 0):
            problems.add(f"{where}: {key} must be a positive integer (pixels), got {_show(obj[key])}")
        else:
            out[key] = value
    for key in DISTORTION_KEYS:
        if key in obj:
            value = _number(obj, key, where, problems)
            if value is not None and value != 0.0:
                problems.add(
                    f"{where}: lens distortion is not supported ({key} = {value:g}); undistort the images "
                    "first (e.g. with OpenCV) and drop the coefficients"
                )
    if "camera_model" in obj:
        model = obj["camera_model"]
        if model not in CAMERA_MODELS:
            problems.add(f"{where}: camera_model must be one of {', '.join(CAMERA_MODELS)}, got {_show(model)}")
        elif model == "OPENCV_FISHEYE":
            problems.add(f"{where}: camera_model OPENCV_FISHEYE is not supported (pinhole cameras only)")
    return out


def resolve_intrinsics(
    values: dict[str, float],
    image_width: int,
    image_height: int,
    image_desc: str,
    where: str,
    problems: Problems,
) -> tuple[np.ndarray, int, int] | None:
    """The (3, 3) K and image size of a camera from its merged intrinsics keys and its image size.

    ``values`` are the checked keys (global ones overridden by per-camera/per-frame ones). Missing
    ``w``/``h`` default to the image size; ``cx``/``cy`` to the image centre; ``fl_y`` to ``fl_x``
    unless ``camera_angle_y`` is given. Returns None (and adds problems) when they do not fit.
    """
    ok = True
    w = int(values.get("w", image_width))
    h = int(values.get("h", image_height))
    if (w, h) != (image_width, image_height):
        problems.add(f"{where}: image size {image_width}x{image_height} of {image_desc} differs from w/h {w}x{h}")
        ok = False
    fx = values.get("fl_x")
    if "camera_angle_x" in values:
        fx_angle = 0.5 * w / math.tan(0.5 * values["camera_angle_x"])
        if fx is None:
            fx = fx_angle
        elif abs(fx - fx_angle) > INTRINSICS_RTOL * fx:
            problems.add(
                f"{where}: fl_x = {fx:g} and camera_angle_x = {values['camera_angle_x']:g} "
                f"(which gives fl_x = {fx_angle:g} for w = {w}) disagree"
            )
            ok = False
    if fx is None:
        problems.add(f"{where}: no focal length; give fl_x or camera_angle_x (top level, per camera or per frame)")
        return None
    fy = values.get("fl_y")
    if "camera_angle_y" in values:
        fy_angle = 0.5 * h / math.tan(0.5 * values["camera_angle_y"])
        if fy is None:
            fy = fy_angle
        elif abs(fy - fy_angle) > INTRINSICS_RTOL * fy:
            problems.add(
                f"{where}: fl_y = {fy:g} and camera_angle_y = {values['camera_angle_y']:g} "
                f"(which gives fl_y = {fy_angle:g} for h = {h}) disagree"
            )
            ok = False
    if fy is None:
        fy = fx
    cx = values.get("cx", 0.5 * w)
    cy = values.get("cy", 0.5 * h)
    if not ok:
        return None
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
    return K, w, h


# ---------------------------------------------------------------------------------------------
# transforms.json
# ---------------------------------------------------------------------------------------------

# keys written by common NeRF tools that carry nothing vid2sim uses; accepted and ignored
IGNORED_TOP_KEYS = ("aabb_scale", "scale", "offset", "applied_transform", "ply_file_path")
IGNORED_FRAME_KEYS = ("rotation", "sharpness", "colmap_im_id")

TOP_KEYS = INTRINSIC_KEYS + DISTORTION_KEYS + ("camera_model", "frames", "videos")
FRAME_KEYS = (
    ("file_path", "mask_path", "transform_matrix", "camera_index", "time_index", "time")
    + INTRINSIC_KEYS
    + DISTORTION_KEYS
)
VIDEO_KEYS = (
    ("camera_index", "video_path", "mask_video_path", "mask_paths", "transform_matrix", "start_time")
    + INTRINSIC_KEYS
    + DISTORTION_KEYS
)


@dataclass
class FrameEntry:
    """One image of the frames layout, checked.

    Attributes:
        index: position in the ``frames`` list. camera, time_index: its place in the (V, T) grid.
        time: seconds, or None when the frame does not say. file_path, mask_path: as written.
        c2w: (4, 4) camera-to-world, OpenGL axes. intrinsics: merged intrinsics keys.
    """

    index: int
    camera: int
    time_index: int
    time: float | None
    file_path: str
    mask_path: str | None
    c2w: np.ndarray
    intrinsics: dict[str, float]

    @property
    def where(self) -> str:
        return f"frame {self.index} (camera {self.camera}, time index {self.time_index})"


@dataclass
class VideoEntry:
    """One camera of the videos layout, checked (fields as in :class:`FrameEntry`)."""

    index: int
    camera: int
    video_path: str
    mask_video_path: str | None
    mask_paths: list[str] | None
    c2w: np.ndarray
    intrinsics: dict[str, float]
    start_time: float

    @property
    def where(self) -> str:
        return f"videos[{self.index}] (camera {self.camera})"


@dataclass
class TransformsPlan:
    """The checked content of ``transforms.json``.

    ``layout`` is ``"frames"`` (one image per camera and time) or ``"videos"`` (one video per
    camera). For frames, ``grid[v][t]`` is the entry of camera v at time index t and
    ``num_frames`` is T; for videos, ``num_frames`` is None until the videos are read.
    """

    layout: str
    num_views: int
    num_frames: int | None
    frames: list[FrameEntry] = field(default_factory=list)
    videos: list[VideoEntry] = field(default_factory=list)
    grid: list[list[FrameEntry]] = field(default_factory=list)

    def camera_entries(self) -> list[FrameEntry | VideoEntry]:
        """The first entry of each camera (its pose and intrinsics), indexed by camera."""
        if self.layout == "frames":
            return [row[0] for row in self.grid]
        return sorted(self.videos, key=lambda e: e.camera)


def _parse_common(
    obj: dict, where: str, problems: Problems, global_intrinsics: dict[str, float]
) -> tuple[int | None, np.ndarray | None, dict[str, float]]:
    """camera_index, transform_matrix and merged intrinsics shared by frame and video entries."""
    camera = None
    if "camera_index" not in obj:
        problems.add(f"{where}: missing camera_index (an integer 0..V-1)")
    elif not _is_int(obj["camera_index"]) or int(obj["camera_index"]) < 0:
        problems.add(f"{where}: camera_index must be an integer >= 0, got {_show(obj['camera_index'])}")
    else:
        camera = int(obj["camera_index"])
    c2w = None
    if "transform_matrix" not in obj:
        problems.add(f"{where}: missing transform_matrix (4x4 camera-to-world, OpenGL axes)")
    else:
        m = parse_matrix(obj["transform_matrix"])
        if m is None:
            problems.add(
                f"{where}: transform_matrix must be a 4x4 (or 3x4) nested list of numbers, "
                f"got {_show(obj['transform_matrix'])}"
            )
        else:
            reason = rigid_transform_problem(m)
            if reason is not None:
                problems.add(f"{where}: transform_matrix is not a rigid transform: {reason}")
            else:
                c2w = m
    merged = {**global_intrinsics, **parse_intrinsics(obj, where, problems)}
    return camera, c2w, merged


def _contiguous(indices: set[int], what: str, problems: Problems, name: str) -> int:
    """Check ``indices`` is 0..n-1 and return n (reports the gaps)."""
    n = max(indices) + 1 if indices else 0
    gaps = [i for i in range(n) if i not in indices]
    if gaps:
        shown = ", ".join(str(g) for g in gaps[:10]) + (" ..." if len(gaps) > 10 else "")
        problems.add(f"{name}: {what} indices must run 0..{n - 1} without gaps; nothing has {what} index {shown}")
    return n


def parse_transforms(obj: Any, problems: Problems, name: str = "transforms.json") -> TransformsPlan | None:
    """Check the parsed ``transforms.json`` and return its plan (None if it is unusable).

    Checks keys, types, rigid camera poses, complete and unique (camera, time) grids, cameras that
    do not move or change intrinsics between frames, and consistent frame times.
    """
    if not isinstance(obj, dict):
        problems.add(f"{name}: the top level must be a JSON object, got {type(obj).__name__}")
        return None
    check_keys(obj, TOP_KEYS, f"{name} (top level)", problems, ignored=IGNORED_TOP_KEYS)
    global_intrinsics = parse_intrinsics(obj, f"{name} (top level)", problems)
    has_frames, has_videos = "frames" in obj, "videos" in obj
    if has_frames == has_videos:
        problems.add(
            f"{name}: give exactly one of 'frames' (one image per camera and time) or 'videos' "
            f"(one video per camera), got {'both' if has_frames else 'neither'}"
        )
        return None
    key = "frames" if has_frames else "videos"
    entries = obj[key]
    if not isinstance(entries, list) or not entries:
        problems.add(f"{name}: '{key}' must be a non-empty list, got {_show(entries)}")
        return None
    if has_frames:
        return _parse_frames(entries, global_intrinsics, problems, name)
    return _parse_videos(entries, global_intrinsics, problems, name)


def _parse_frames(entries: list, global_intrinsics: dict, problems: Problems, name: str) -> TransformsPlan | None:
    start = len(problems)
    frames: list[FrameEntry] = []
    usable = True
    for i, raw in enumerate(entries):
        where = f"{name}: frame {i}"
        if not isinstance(raw, dict):
            problems.add(f"{where}: must be a JSON object, got {_show(raw)}")
            usable = False
            continue
        t_index = None
        if "time_index" not in raw:
            problems.add(f"{where}: missing time_index (an integer 0..T-1)")
        elif not _is_int(raw["time_index"]) or int(raw["time_index"]) < 0:
            problems.add(f"{where}: time_index must be an integer >= 0, got {_show(raw['time_index'])}")
        else:
            t_index = int(raw["time_index"])
        cam_hint = raw.get("camera_index")
        if _is_int(cam_hint) and t_index is not None:
            where = f"{name}: frame {i} (camera {int(cam_hint)}, time index {t_index})"
        check_keys(raw, FRAME_KEYS, where, problems, ignored=IGNORED_FRAME_KEYS)
        camera, c2w, intrinsics = _parse_common(raw, where, problems, global_intrinsics)
        file_path = raw.get("file_path")
        if not isinstance(file_path, str) or not file_path:
            problems.add(f"{where}: file_path must be a non-empty string, got {_show(file_path)}")
            file_path = None
        mask_path = raw.get("mask_path")
        if mask_path is not None and (not isinstance(mask_path, str) or not mask_path):
            problems.add(f"{where}: mask_path must be a non-empty string, got {_show(mask_path)}")
            mask_path = None
        time = None
        if "time" in raw:
            time = _number(raw, "time", where, problems)
        if camera is None or t_index is None or c2w is None or file_path is None:
            usable = False
            continue
        frames.append(FrameEntry(i, camera, t_index, time, file_path, mask_path, c2w, intrinsics))
    if not usable:
        return None
    # the (camera, time) grid: complete, no duplicates
    seen: dict[tuple[int, int], FrameEntry] = {}
    for f in frames:
        other = seen.get((f.camera, f.time_index))
        if other is not None:
            problems.add(
                f"{name}: frames {other.index} and {f.index} both are camera {f.camera}, time index {f.time_index}"
            )
        else:
            seen[(f.camera, f.time_index)] = f
    num_views = _contiguous({f.camera for f in frames}, "camera", problems, name)
    num_frames = _contiguous({f.time_index for f in frames}, "time", problems, name)
    missing = [(v, t) for v in range(num_views) for t in range(num_frames) if (v, t) not in seen]
    for v, t in missing[:MAX_PROBLEMS_SHOWN]:
        problems.add(
            f"{name}: missing frame {t} of camera {v}: no frame has camera_index {v} and time_index {t} "
            f"(every camera needs time indices 0..{num_frames - 1})"
        )
    if len(missing) > MAX_PROBLEMS_SHOWN:
        problems.add(f"{name}: ... and {len(missing) - MAX_PROBLEMS_SHOWN} more missing (camera, time) frames")
    if len(problems) > start:
        return None
    grid = [[seen[(v, t)] for t in range(num_frames)] for v in range(num_views)]
    for v, row in enumerate(grid):
        _check_static_camera(row, f"{name}: camera {v}", problems)
    _check_frame_times(grid, num_frames, problems, name)
    return TransformsPlan("frames", num_views, num_frames, frames=frames, grid=grid)


def _check_static_camera(entries: list, where: str, problems: Problems) -> None:
    """All entries of one camera must share the pose and the intrinsics."""
    first = entries[0]
    scale = max(1.0, float(np.abs(first.c2w[:3, 3]).max()))
    for e in entries[1:]:
        diff = float(np.abs(e.c2w - first.c2w).max())
        if diff > STATIC_CAMERA_ATOL * scale:
            problems.add(
                f"{where} moves: transform_matrix of frame {e.index} (time index {e.time_index}) differs from "
                f"frame {first.index} (time index {first.time_index}) by up to {diff:.3g}; "
                "vid2sim needs fixed cameras"
            )
            break
    for e in entries[1:]:
        keys = set(first.intrinsics) | set(e.intrinsics)
        changed = [
            k
            for k in sorted(keys)
            if k not in first.intrinsics
            or k not in e.intrinsics
            or abs(first.intrinsics[k] - e.intrinsics[k]) > INTRINSICS_RTOL * max(1.0, abs(first.intrinsics[k]))
        ]
        if changed:
            k = changed[0]
            problems.add(
                f"{where}: intrinsics of frame {e.index} ({k} = {e.intrinsics.get(k, 'unset')}) differ from "
                f"frame {first.index} ({k} = {first.intrinsics.get(k, 'unset')}); "
                "a camera's intrinsics must not change over time"
            )
            break


def _check_frame_times(grid: list[list[FrameEntry]], num_frames: int, problems: Problems, name: str) -> None:
    """Frames that give ``time`` must agree per time index, and either all or none give it."""
    flat = [f for row in grid for f in row]
    with_time = [f for f in flat if f.time is not None]
    if with_time and len(with_time) != len(flat):
        without = next(f for f in flat if f.time is None)
        problems.add(
            f"{name}: some frames give 'time' and others do not (e.g. frame {without.index}); "
            "give it for all frames or none"
        )
        return
    if not with_time:
        return
    for t in range(num_frames):
        column = [row[t] for row in grid]
        ref = column[0]
        for f in column[1:]:
            if abs(f.time - ref.time) > 1e-6 * max(1.0, abs(ref.time)):
                problems.add(
                    f"{name}: time index {t} has different times in frame {ref.index} ({ref.time:g} s) and "
                    f"frame {f.index} ({f.time:g} s); cameras must be synchronised"
                )
                break


def _parse_videos(entries: list, global_intrinsics: dict, problems: Problems, name: str) -> TransformsPlan | None:
    start = len(problems)
    videos: list[VideoEntry] = []
    usable = True
    for i, raw in enumerate(entries):
        where = f"{name}: videos[{i}]"
        if not isinstance(raw, dict):
            problems.add(f"{where}: must be a JSON object, got {_show(raw)}")
            usable = False
            continue
        if _is_int(raw.get("camera_index")):
            where = f"{name}: videos[{i}] (camera {int(raw['camera_index'])})"
        check_keys(raw, VIDEO_KEYS, where, problems)
        camera, c2w, intrinsics = _parse_common(raw, where, problems, global_intrinsics)
        video_path = raw.get("video_path")
        if not isinstance(video_path, str) or not video_path:
            problems.add(f"{where}: video_path must be a non-empty string, got {_show(video_path)}")
            video_path = None
        mask_video = raw.get("mask_video_path")
        mask_paths = raw.get("mask_paths")
        if (mask_video is None) == (mask_paths is None):
            problems.add(
                f"{where}: give exactly one mask source: 'mask_video_path' (a mask video) or "
                "'mask_paths' (one mask image per frame)"
            )
            usable = False
        elif mask_video is not None and (not isinstance(mask_video, str) or not mask_video):
            problems.add(f"{where}: mask_video_path must be a non-empty string, got {_show(mask_video)}")
            usable = False
        elif mask_paths is not None and (
            not isinstance(mask_paths, list) or not mask_paths or not all(isinstance(p, str) and p for p in mask_paths)
        ):
            problems.add(f"{where}: mask_paths must be a non-empty list of file paths, got {_show(mask_paths)}")
            usable = False
        start_time = 0.0
        if "start_time" in raw:
            value = _number(raw, "start_time", where, problems)
            start_time = 0.0 if value is None else value
        if camera is None or c2w is None or video_path is None:
            usable = False
            continue
        videos.append(VideoEntry(i, camera, video_path, mask_video, mask_paths, c2w, intrinsics, start_time))
    if not usable:
        return None
    by_camera: dict[int, VideoEntry] = {}
    for v in videos:
        if v.camera in by_camera:
            problems.add(
                f"{name}: videos[{by_camera[v.camera].index}] and videos[{v.index}] are both camera {v.camera}"
            )
        else:
            by_camera[v.camera] = v
    num_views = _contiguous(set(by_camera), "camera", problems, name)
    starts = {v.start_time for v in videos}
    if len(starts) > 1:
        problems.add(f"{name}: videos have different start_time values {sorted(starts)}; cameras must be synchronised")
    if len(problems) > start:
        return None
    return TransformsPlan("videos", num_views, None, videos=videos)
