"""What a capture folder holds: cameras (a video or a frame sequence each), clean plates, the user's own masks,
the calibration and ``capture.json``.

::

    capture/
      videos/<cam>.mp4|.mov|.avi|.mkv  or  frames/<cam>/<NNNNN>.png|.jpg   one per camera, synchronised
      background/<cam>.png|.jpg          optional clean plate per camera
      masks/<cam>/<NNNNN>.png            optional masks of the user's (they win)
      colmap/cameras.txt + images.txt (+ points3D.txt), or the same .bin     COLMAP model
      transforms.json                    nerfstudio
      capture.json                       optional {"fps": ...}
      photos/*.png|.jpg                  optional photos of the empty scene, for ``vid2sim calibrate-capture`` only

Anything else in the folder is ignored.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from vid2sim.scene.capture.errors import CaptureError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
CALIBRATIONS = ("colmap", "transforms")
#: extra photos of the empty scene that only structure from motion reads (``vid2sim calibrate-capture``)
PHOTOS_DIR = "photos"


@dataclass
class CameraSource:
    """The files of one camera.

    Attributes:
        name: the camera's name (the video's stem or the frame folder's name).
        video: its video file, or None for a frame sequence.
        frames: its frame images in time order (numeric stems sorted by number), or None for a video.
        plate: its clean plate, or None.
        masks: the user's masks in time order, or None.
    """

    name: str
    video: Path | None = None
    frames: list[Path] | None = None
    plate: Path | None = None
    masks: list[Path] | None = None

    @property
    def source(self) -> Path:
        """The video file or the frame folder (for messages)."""
        if self.video is not None:
            return self.video
        assert self.frames
        return self.frames[0].parent


@dataclass
class CaptureLayout:
    """A capture folder's contents (:func:`discover_capture`)."""

    root: Path
    cameras: dict[str, CameraSource]
    colmap: Path | None = None
    transforms: Path | None = None
    settings: dict = field(default_factory=dict)
    photos: list[Path] = field(default_factory=list)

    def camera_of_name(self, name: str) -> str | None:
        """The camera a calibration's image name refers to: its file stem, or else the first path component
        naming a camera (``c00.png``, ``background/c00.jpg``, ``frames/c00/00000.png`` → ``c00``)."""
        path = PurePosixPath(name.replace("\\", "/"))
        if path.stem in self.cameras:
            return path.stem
        for part in path.parts[:-1]:
            if part in self.cameras:
                return part
        return None


def _sorted_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` in time order: by the number in their stem when every stem holds one, else by name."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    numbers = [re.findall(r"\d+", p.stem) for p in files]
    if files and all(numbers):
        return [p for _, p in sorted(zip([int(n[-1]) for n in numbers], files), key=lambda x: (x[0], x[1].name))]
    return sorted(files)


def discover_capture(root: str | Path, require_calibration: bool = True) -> CaptureLayout:
    """Find the cameras, plates, masks and calibration files of the capture folder ``root`` (a capture without
    a calibration only with ``require_calibration=False``: what ``calibrate-capture`` starts from).

    Raises:
        CaptureError: no capture there, no cameras, a camera with both a video and a frame folder, an empty frame
            folder, a plate or mask folder for a camera that has no video, no calibration, a bad ``capture.json``.
    """
    root = Path(root)
    if not root.is_dir():
        raise CaptureError("no such capture folder", file=root)
    cameras: dict[str, CameraSource] = {}
    videos = root / "videos"
    if videos.is_dir():
        for p in sorted(videos.iterdir()):
            if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
                if p.stem in cameras:
                    raise CaptureError(f"two videos ({cameras[p.stem].video.name} and {p.name})", camera=p.stem,
                                       file=videos)
                cameras[p.stem] = CameraSource(p.stem, video=p)
    frames = root / "frames"
    if frames.is_dir():
        for d in sorted(frames.iterdir()):
            if not d.is_dir():
                continue
            if d.name in cameras:
                raise CaptureError(f"both a video ({cameras[d.name].video}) and a frame folder; keep one",
                                   camera=d.name, file=d)
            images = _sorted_images(d)
            if not images:
                raise CaptureError("frame folder without .png/.jpg images", camera=d.name, file=d)
            cameras[d.name] = CameraSource(d.name, frames=images)
    if not cameras:
        raise CaptureError("no cameras: expected videos/<cam>.mp4 (.mov/.avi/.mkv) or frames/<cam>/<NNNNN>.png",
                           file=root)
    plates = root / "background"
    if plates.is_dir():
        for p in sorted(plates.iterdir()):
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
                if p.stem not in cameras:
                    raise CaptureError(f"a clean plate for camera '{p.stem}', which has no video or frame folder "
                                       f"(cameras: {', '.join(cameras)})", file=p)
                if cameras[p.stem].plate is not None:
                    raise CaptureError(f"two clean plates ({cameras[p.stem].plate.name} and {p.name})",
                                       camera=p.stem, file=plates)
                cameras[p.stem].plate = p
    masks = root / "masks"
    if masks.is_dir():
        for d in sorted(masks.iterdir()):
            if not d.is_dir():
                continue
            if d.name not in cameras:
                raise CaptureError(f"masks for camera '{d.name}', which has no video or frame folder (cameras: "
                                   f"{', '.join(cameras)})", file=d)
            cameras[d.name].masks = _sorted_images(d)
    colmap = root / "colmap"
    has_colmap = colmap.is_dir() and any((colmap / f"cameras.{e}").is_file() for e in ("txt", "bin"))
    transforms = root / "transforms.json"
    if require_calibration and not has_colmap and not transforms.is_file():
        raise CaptureError("no calibration: expected colmap/cameras.txt + images.txt (or .bin) or transforms.json",
                           file=root)
    settings: dict = {}
    cj = root / "capture.json"
    if cj.is_file():
        try:
            settings = json.loads(cj.read_text())
        except json.JSONDecodeError as exc:
            raise CaptureError(f"not valid JSON: {exc}", file=cj) from None
        if not isinstance(settings, dict):
            raise CaptureError("expected a JSON object such as {\"fps\": 30}", file=cj)
        fps = settings.get("fps")
        if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0):
            raise CaptureError(f"fps must be a positive number, got {fps!r}", file=cj)
    photos = _sorted_images(root / PHOTOS_DIR) if (root / PHOTOS_DIR).is_dir() else []
    return CaptureLayout(root, dict(sorted(cameras.items())), colmap if has_colmap else None,
                         transforms if transforms.is_file() else None, settings, photos)
