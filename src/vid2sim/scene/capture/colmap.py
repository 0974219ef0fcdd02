"""COLMAP sparse models (text and binary): reading them into capture cameras and points, and writing them.

Facts of the format (COLMAP's documentation, "Output Format"): ``cameras`` hold ``CAMERA_ID MODEL WIDTH HEIGHT
PARAMS[]``; ``images`` hold ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and a line of ``X Y POINT3D_ID``
observations, the pose being world-to-camera (Hamilton quaternion, x right, y down, z forward); ``points3D``
hold ``POINT3D_ID X Y Z R G B ERROR`` and a track of ``IMAGE_ID POINT2D_IDX``. The binary files store the same
fields little-endian: counts as uint64, camera and image ids as uint32, the model as int32, sizes as uint64,
parameters, poses and coordinates as float64, point ids as uint64, colours as uint8, track entries as two
uint32; an image name is a NUL-terminated string.

Camera models read (parameters in COLMAP's order), all equal to OpenCV's model with the missing terms zero:
``SIMPLE_PINHOLE`` (f, cx, cy), ``PINHOLE`` (fx, fy, cx, cy), ``SIMPLE_RADIAL`` (f, cx, cy, k),
``RADIAL`` (f, cx, cy, k1, k2), ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Sequence

import numpy as np

from vid2sim.scene.capture.cameras import CaptureCamera, quaternion_to_rotation, rigid, rotation_to_quaternion
from vid2sim.scene.capture.errors import CaptureError

#: COLMAP's model ids and parameter counts (the models vid2sim reads are the first five)
MODEL_IDS: dict[str, int] = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                             "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8,
                             "RADIAL_FISHEYE": 9, "THIN_PRISM_FISHEYE": 10}
MODEL_PARAMS: dict[str, int] = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
                                "OPENCV_FISHEYE": 8, "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4,
                                "RADIAL_FISHEYE": 5, "THIN_PRISM_FISHEYE": 12}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_MODEL_NAMES = {v: k for k, v in MODEL_IDS.items()}


@dataclass
class ColmapCamera:
    """One entry of ``cameras``: model name, image size and the model's parameters."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """One entry of ``images``: world-to-camera pose, camera id, name and 2D observations.

    Attributes:
        qvec: (4,) Hamilton quaternion (w, x, y, z); tvec: (3,).
        xys: (N, 2) keypoints in pixels; point3d_ids: (N,) int64, −1 where a keypoint has no 3D point.
    """

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


@dataclass
class ColmapPoints:
    """``points3D``: ids (P,) int64, xyz (P, 3) float64, rgb (P, 3) uint8, error (P,) float64 and per point
    the ids of the images that observe it (``tracks``: P arrays of image ids)."""

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    tracks: list[np.ndarray]

    @classmethod
    def empty(cls) -> "ColmapPoints":
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), [])


@dataclass
class ColmapModel:
    """A COLMAP sparse model as read from a folder (``cameras``, ``images``, optional ``points3D``)."""

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: ColmapPoints
    folder: Path
    binary: bool

    def file(self, what: str) -> str:
        """The path of the model's ``what`` file (``"cameras"``, ``"images"``, ``"points3D"``)."""
        return str(self.folder / f"{what}.{'bin' if self.binary else 'txt'}")


# ---- reading -----------------------------------------------------------------------------------------------------


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-comment lines of a text file; empty lines are kept (images.txt needs them)."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise CaptureError("not a text file (a binary COLMAP model is named .bin)", file=path) from None
    return [(i + 1, line.rstrip("\r\n")) for i, line in enumerate(text.split("\n")) if not line.startswith("#")]


def _numbers(text: str, path: Path, line: int, what: str) -> list[float]:
    try:
        return [float(v) for v in text.split()]
    except ValueError:
        raise CaptureError(f"line {line}: {what} must be numbers, got {text.strip()[:80]!r}", file=path) from None


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cameras: dict[int, ColmapCamera] = {}
    for line, text in _data_lines(path):
        parts = text.split()
        if not parts:
            continue
        if len(parts) < 4:
            raise CaptureError(f"line {line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {text[:80]!r}",
                               file=path)
        model = parts[1]
        values = _numbers(" ".join([parts[0]] + parts[2:]), path, line, "CAMERA_ID, WIDTH, HEIGHT and PARAMS")
        cam = ColmapCamera(int(values[0]), model, int(values[1]), int(values[2]), np.array(values[3:]))
        _check_camera(cam, path)
        cameras[cam.camera_id] = cam
    return cameras


def read_images_text(path: Path) -> list[ColmapImage]:
    lines = _data_lines(path)
    # drop trailing empty lines, then read pairs: the pose line and the (possibly empty) observations line
    while lines and not lines[-1][1].strip():
        lines.pop()
    images: list[ColmapImage] = []
    i = 0
    while i < len(lines):
        line, text = lines[i]
        if not text.strip():
            i += 1
            continue
        parts = text.split()
        if len(parts) < 10:
            raise CaptureError(f"line {line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got "
                               f"{text[:80]!r}", file=path)
        values = _numbers(" ".join(parts[:9]), path, line, "IMAGE_ID, QW..TZ and CAMERA_ID")
        name = " ".join(parts[9:])
        obs = lines[i + 1][1] if i + 1 < len(lines) else ""
        nums = _numbers(obs, path, line + 1, "POINTS2D") if obs.strip() else []
        if len(nums) % 3:
            raise CaptureError(f"line {line + 1}: POINTS2D must be triples X Y POINT3D_ID", file=path)
        arr = np.array(nums, dtype=np.float64).reshape(-1, 3)
        images.append(ColmapImage(int(values[0]), np.array(values[1:5]), np.array(values[5:8]), int(values[8]), name,
                                  arr[:, :2], arr[:, 2].astype(np.int64)))
        i += 2
    return images


def read_points_text(path: Path) -> ColmapPoints:
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    for line, text in _data_lines(path):
        if not text.strip():
            continue
        values = _numbers(text, path, line, "POINT3D_ID X Y Z R G B ERROR TRACK[]")
        if len(values) < 8 or (len(values) - 8) % 2:
            raise CaptureError(f"line {line}: expected POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID POINT2D_IDX) "
                               "pairs", file=path)
        ids.append(int(values[0]))
        xyz.append(values[1:4])
        rgb.append(values[4:7])
        err.append(values[7])
        tracks.append(np.array(values[8::2], dtype=np.int64))
    if not ids:
        return ColmapPoints.empty()
    return ColmapPoints(np.array(ids, np.int64), np.array(xyz), np.clip(np.array(rgb), 0, 255).astype(np.uint8),
                        np.array(err), tracks)


class _Reader:
    """Little-endian struct reads from a binary file, with the file named in every error."""

    def __init__(self, f: BinaryIO, path: Path) -> None:
        self.f, self.path = f, path

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        data = self.f.read(size)
        if len(data) != size:
            raise CaptureError("truncated COLMAP binary file (it ends in the middle of a record)", file=self.path)
        return struct.unpack("<" + fmt, data)

    def array(self, fmt: str, count: int) -> np.ndarray:
        if count > 1 << 31:
            raise CaptureError(f"implausible record count {count}: not a COLMAP binary file?", file=self.path)
        dtype = np.dtype("<" + fmt)
        data = self.f.read(dtype.itemsize * count)
        if len(data) != dtype.itemsize * count:
            raise CaptureError("truncated COLMAP binary file (it ends in the middle of a record)", file=self.path)
        return np.frombuffer(data, dtype=dtype).copy()

    def string(self) -> str:
        out = bytearray()
        while True:
            c = self.f.read(1)
            if not c:
                raise CaptureError("truncated COLMAP binary file (an image name has no end)", file=self.path)
            if c == b"\0":
                return out.decode("utf-8", errors="replace")
            out += c


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    cameras: dict[int, ColmapCamera] = {}
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            camera_id, model_id, width, height = r.read("IiQQ")
            if model_id not in _MODEL_NAMES:
                raise CaptureError(f"camera {camera_id}: unknown camera model id {model_id}; vid2sim reads "
                                   f"{', '.join(SUPPORTED_MODELS)}", file=path)
            model = _MODEL_NAMES[model_id]
            params = r.array("f8", MODEL_PARAMS[model])
            cam = ColmapCamera(camera_id, model, width, height, params)
            _check_camera(cam, path)
            cameras[camera_id] = cam
    return cameras


def read_images_binary(path: Path) -> list[ColmapImage]:
    images: list[ColmapImage] = []
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = r.read("IdddddddI")
            name = r.string()
            (num,) = r.read("Q")
            rec = r.array("f8", 3 * num).reshape(num, 3) if num else np.zeros((0, 3))
            # each observation is (double x, double y, uint64 id): re-read the id bits as an integer
            ids = rec[:, 2].copy().view(np.uint64).astype(np.int64) if num else np.zeros(0, np.int64)
            images.append(ColmapImage(image_id, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), camera_id, name,
                                      rec[:, :2], ids))
    return images


def read_points_binary(path: Path) -> ColmapPoints:
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    with open(path, "rb") as f:
        r = _Reader(f, path)
        (n,) = r.read("Q")
        for _ in range(n):
            pid, x, y, z, cr, cg, cb, e, length = r.read("QdddBBBdQ")
            track = r.array("u4", 2 * length).reshape(length, 2)
            ids.append(pid)
            xyz.append((x, y, z))
            rgb.append((cr, cg, cb))
            err.append(e)
            tracks.append(track[:, 0].astype(np.int64))
    if not ids:
        return ColmapPoints.empty()
    return ColmapPoints(np.array(ids, np.int64), np.array(xyz), np.array(rgb, np.uint8), np.array(err), tracks)


def _check_camera(cam: ColmapCamera, path: Path) -> None:
    if cam.model not in SUPPORTED_MODELS:
        raise CaptureError(f"camera {cam.camera_id}: unknown camera model {cam.model!r}; vid2sim reads "
                           f"{', '.join(SUPPORTED_MODELS)} (undistort the images with COLMAP's image_undistorter "
                           "to get PINHOLE cameras)", file=path)
    if len(cam.params) != MODEL_PARAMS[cam.model]:
        raise CaptureError(f"camera {cam.camera_id}: model {cam.model} has {MODEL_PARAMS[cam.model]} parameters, "
                           f"got {len(cam.params)}", file=path)
    if cam.width <= 0 or cam.height <= 0 or not np.isfinite(cam.params).all():
        raise CaptureError(f"camera {cam.camera_id}: bad size {cam.width}x{cam.height} or parameters", file=path)


def read_colmap(folder: str | Path) -> ColmapModel:
    """Read the COLMAP model in ``folder``: binary when ``cameras.bin`` and ``images.bin`` are there (as COLMAP
    itself prefers), else text; ``points3D`` is optional.

    Raises:
        CaptureError: missing files, unreadable records, an unknown camera model, an image naming an unknown
            camera (the message names the file).
    """
    folder = Path(folder)
    binary = (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file()
    ext = "bin" if binary else "txt"
    for what in ("cameras", "images"):
        if not (folder / f"{what}.{ext}").is_file():
            raise CaptureError(f"a COLMAP model needs cameras.txt + images.txt (or cameras.bin + images.bin); "
                               f"{what}.{ext} is missing", file=folder)
    if binary:
        cameras = read_cameras_binary(folder / "cameras.bin")
        images = read_images_binary(folder / "images.bin")
        pts = folder / "points3D.bin"
        points = read_points_binary(pts) if pts.is_file() else ColmapPoints.empty()
    else:
        cameras = read_cameras_text(folder / "cameras.txt")
        images = read_images_text(folder / "images.txt")
        pts = folder / "points3D.txt"
        points = read_points_text(pts) if pts.is_file() else ColmapPoints.empty()
    model = ColmapModel(cameras, images, points, folder, binary)
    for im in images:
        if im.camera_id not in cameras:
            raise CaptureError(f"image {im.image_id} ({im.name}) uses camera {im.camera_id}, which "
                               f"{model.file('cameras')} does not define", file=model.file("images"))
        if not (np.isfinite(im.qvec).all() and np.isfinite(im.tvec).all()) or np.linalg.norm(im.qvec) < 1e-12:
            raise CaptureError(f"image {im.image_id} ({im.name}): bad pose", file=model.file("images"))
    return model


def intrinsics_of(cam: ColmapCamera) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) and OpenCV distortion (5,) (k1, k2, p1, p2, k3) of a COLMAP camera."""
    p = cam.params
    dist = np.zeros(5)
    if cam.model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif cam.model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif cam.model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist[0] = p[3]
    elif cam.model == "RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist[:2] = p[3:5]
    elif cam.model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist[:4] = p[4:8]
    else:  # pragma: no cover - refused when read
        raise ValueError(cam.model)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), dist


def params_of(camera: CaptureCamera, model: str) -> np.ndarray:
    """COLMAP parameters of ``camera`` in ``model`` (the inverse of :func:`intrinsics_of`; terms the model lacks
    must be zero)."""
    K, d = camera.K, camera.distortion
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    allowed = {"SIMPLE_PINHOLE": 0, "PINHOLE": 0, "SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 4}[model]
    if np.any(d[allowed:] != 0) or (model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") and fx != fy):
        raise ValueError(f"camera {camera.name}: {model} cannot hold K={K.tolist()}, distortion={d.tolist()}")
    return {"SIMPLE_PINHOLE": np.array([fx, cx, cy]), "PINHOLE": np.array([fx, fy, cx, cy]),
            "SIMPLE_RADIAL": np.array([fx, cx, cy, d[0]]), "RADIAL": np.array([fx, cx, cy, d[0], d[1]]),
            "OPENCV": np.array([fx, fy, cx, cy, *d[:4]])}[model]


def colmap_cameras(model: ColmapModel, camera_of_name: Callable[[str], str | None]) -> dict[str, CaptureCamera]:
    """One :class:`CaptureCamera` per image of the model, keyed by ``camera_of_name(image.name)`` (the capture's
    camera name, or None for an image that matches no camera: an error naming the image and the file)."""
    out: dict[str, CaptureCamera] = {}
    for im in model.images:
        name = camera_of_name(im.name)
        if name is None:
            raise CaptureError(f"image {im.name!r} matches no camera of the capture (its name's stem must be a "
                               "camera name: videos/<cam>.mp4 or frames/<cam>/)", file=model.file("images"))
        if name in out:
            raise CaptureError(f"two images ({out[name].image_name} and {im.name}) are this camera; a capture "
                               "calibration has one image per camera", camera=name, file=model.file("images"))
        cam = model.cameras[im.camera_id]
        K, dist = intrinsics_of(cam)
        w2c = rigid(quaternion_to_rotation(im.qvec), im.tvec)
        out[name] = CaptureCamera(name, cam.width, cam.height, K, dist, w2c, model=cam.model,
                                  source=model.file("images"), image_name=im.name, image_id=im.image_id)
    return out


def points_by_camera(model: ColmapModel, cameras: dict[str, CaptureCamera]) -> tuple[np.ndarray, np.ndarray,
                                                                                      list[set[str]]]:
    """The model's 3D points (P, 3), colours (P, 3) uint8 and, per point, the names of the cameras that see it."""
    name_of_image = {c.image_id: n for n, c in cameras.items() if c.image_id is not None}
    seen = [{name_of_image[i] for i in track.tolist() if i in name_of_image} for track in model.points.tracks]
    return model.points.xyz, model.points.rgb, seen


# ---- writing -------------------------------------------------------------------------------------------------------


def write_colmap(cameras: Sequence[CaptureCamera], models: Sequence[str], folder: str | Path, *, binary: bool = False,
                 points: np.ndarray | None = None, colours: np.ndarray | None = None,
                 visible: Sequence[Sequence[int]] | None = None, image_suffix: str = ".png") -> None:
    """Write a COLMAP sparse model (``cameras``, ``images``, ``points3D``; text or binary) into ``folder``.

    Args:
        cameras: V cameras; camera i is written as CAMERA_ID and IMAGE_ID i + 1, image NAME ``<name><suffix>``.
        models: V COLMAP model names (each must hold its camera's intrinsics, :func:`params_of`).
        points: (P, 3) 3D points, colours (P, 3) uint8, visible: per point the camera indices that observe it;
            each observation's keypoint is the point's pinhole projection (only the tracks matter to vid2sim).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    points = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64)
    colours = np.zeros((len(points), 3), np.uint8) if colours is None else np.asarray(colours, np.uint8)
    visible = [[] for _ in points] if visible is None else visible
    params = [params_of(c, m) for c, m in zip(cameras, models)]
    obs: list[list[tuple[float, float, int]]] = [[] for _ in cameras]
    tracks: list[list[tuple[int, int]]] = []
    for p, cams in enumerate(visible):
        track = []
        for c in cams:
            uv, _ = cameras[c].project(points[p : p + 1])
            track.append((c + 1, len(obs[c])))
            obs[c].append((float(uv[0, 0]), float(uv[0, 1]), p + 1))
        tracks.append(track)
    quats = [rotation_to_quaternion(c.rotation) for c in cameras]
    names = [c.name + image_suffix for c in cameras]
    if binary:
        with open(folder / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cameras)))
            for i, (cam, model) in enumerate(zip(cameras, models)):
                f.write(struct.pack("<IiQQ", i + 1, MODEL_IDS[model], cam.width, cam.height))
                f.write(np.asarray(params[i], "<f8").tobytes())
        with open(folder / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cameras)))
            for i, cam in enumerate(cameras):
                f.write(struct.pack("<IdddddddI", i + 1, *quats[i], *cam.world_to_camera[:3, 3], i + 1))
                f.write(names[i].encode() + b"\0")
                f.write(struct.pack("<Q", len(obs[i])))
                for x, y, pid in obs[i]:
                    f.write(struct.pack("<ddQ", x, y, pid))
        with open(folder / "points3D.bin", "wb") as f:
            f.write(struct.pack("<Q", len(points)))
            for p in range(len(points)):
                f.write(struct.pack("<QdddBBBdQ", p + 1, *points[p], *(int(c) for c in colours[p]), 0.5,
                                    len(tracks[p])))
                for image_id, idx in tracks[p]:
                    f.write(struct.pack("<II", image_id, idx))
        return
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras)}"]
    for i, (cam, model) in enumerate(zip(cameras, models)):
        lines.append(f"{i + 1} {model} {cam.width} {cam.height} " + " ".join(repr(float(v)) for v in params[i]))
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(cameras)}"]
    for i, cam in enumerate(cameras):
        lines.append(" ".join([str(i + 1), *(repr(float(v)) for v in quats[i]),
                               *(repr(float(v)) for v in cam.world_to_camera[:3, 3]), str(i + 1), names[i]]))
        lines.append(" ".join(f"{x!r} {y!r} {pid}" for x, y, pid in obs[i]))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(points)}"]
    for p in range(len(points)):
        lines.append(" ".join([str(p + 1), *(repr(float(v)) for v in points[p]), *(str(int(c)) for c in colours[p]),
                               "0.5", *(f"{a} {b}" for a, b in tracks[p])]))
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
