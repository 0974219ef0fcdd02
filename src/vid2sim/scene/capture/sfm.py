"""Calibrating a capture by structure from motion: COLMAP (through ``pycolmap``) on the clean plates, and on
photos of the empty scene where the cameras are too far apart to match each other's plates.

The plates of static cameras are one image per camera: COLMAP matches SIFT features between every pair
(exhaustively), builds the model incrementally with one camera (intrinsics and distortion) per plate and one for
all the photos (taken with one camera: its many views pin its intrinsics), and the
plates' cameras, poses and the 3D points they see become ``capture/colmap/`` (COLMAP's own binary files). The
photos only link the cameras; they are removed from the model before it is written, and the points that fewer than
two plates see go with them. The world frame, scale and axes are COLMAP's (arbitrary): ``import-capture``
measures metres, gravity and the floor.

``pycolmap`` is an optional dependency (``pip install "vid2sim[colmap]"``).
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vid2sim.runtime.files import write_folder_atomic
from vid2sim.scene.capture.colmap import SUPPORTED_MODELS
from vid2sim.scene.capture.errors import CaptureError
from vid2sim.scene.capture.layout import PHOTOS_DIR, discover_capture

REPORT_JSON = "sfm_report.json"


@dataclass(frozen=True)
class SfmConfig:
    """How ``calibrate-capture`` runs COLMAP.

    Attributes:
        camera_model: the COLMAP model of every camera (one per image; OPENCV: fx, fy, cx, cy, k1, k2, p1, p2).
        max_features: SIFT features kept per image.
        threads: COLMAP's threads (None: all cores).
    """

    camera_model: str = "OPENCV"
    max_features: int = 8192
    threads: int | None = None

    def __post_init__(self) -> None:
        if self.camera_model not in SUPPORTED_MODELS:  # those import-capture reads
            raise ValueError(f"SfmConfig.camera_model must be one of {', '.join(SUPPORTED_MODELS)}, got "
                             f"{self.camera_model!r}")
        if self.max_features < 64:
            raise ValueError(f"SfmConfig.max_features must be >= 64, got {self.max_features}")


@dataclass
class SfmReport:
    """What ``calibrate-capture`` found (written to ``colmap/sfm_report.json``)."""

    cameras: list[str]
    photos: int
    photos_registered: int
    points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    seconds: float
    config: dict
    mapping: str
    warnings: list[str]


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise CaptureError('calibrate-capture needs pycolmap: pip install "vid2sim[colmap]" (or pip install '
                           'pycolmap), or calibrate with COLMAP or a ChArUco board yourself (docs/capture.md)'
                           ) from None
    return pycolmap


def _inputs(capture: Path) -> tuple[dict[str, str], list[str]]:
    """The plates' names relative to ``capture`` by camera, and the photos'."""
    layout = discover_capture(capture, require_calibration=False)
    missing = [n for n, c in layout.cameras.items() if c.plate is None]
    if missing:
        raise CaptureError(f"no clean plate for camera(s) {', '.join(missing)}: structure from motion runs on "
                           "background/<cam>.png (one still of each camera without the object)", file=capture)
    plates = {n: c.plate.relative_to(capture).as_posix() for n, c in layout.cameras.items()}
    return plates, [p.relative_to(capture).as_posix() for p in layout.photos]


def _best_model(models: dict, plates: dict[str, str]):
    """The reconstruction that registers the most plates (ties: the most images)."""
    def score(rec) -> tuple[int, int]:
        names = {im.name for im in rec.images.values() if im.has_pose}
        return len(names & set(plates.values())), len(names)
    return max(models.values(), key=score) if models else None


def calibrate_capture(capture: str | Path, config: SfmConfig | None = None, *, overwrite: bool = False,
                      progress: bool = True) -> SfmReport:
    """Calibrate the capture folder ``capture`` by structure from motion and write ``capture/colmap/``.

    Args:
        capture: a capture folder (docs/capture.md) with a clean plate per camera, and optionally ``photos/``.
        config: COLMAP's settings.
        overwrite: replace an existing ``colmap/`` folder.
        progress: print COLMAP's stages.

    Returns:
        The report also written to ``colmap/sfm_report.json``.

    Raises:
        CaptureError: pycolmap missing, a camera without a plate, an existing calibration (without
            ``overwrite``), or a camera whose plate COLMAP could not register (then it says to add photos).
    """
    config = SfmConfig() if config is None else config
    capture = Path(capture)
    out = capture / "colmap"
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise CaptureError("a COLMAP calibration is already there (pass --overwrite to replace it)", file=out)
    plates, photos = _inputs(capture)
    pycolmap = _pycolmap()
    start = time.perf_counter()
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # COLMAP's errors only; the stages are printed here (restored below)
    try:
        return _run(pycolmap, capture, out, plates, photos, config, start, progress)
    finally:
        pycolmap.logging.minloglevel = level


def _run(pycolmap, capture: Path, out: Path, plates: dict[str, str], photos: list[str], config: SfmConfig,
         start: float, progress: bool) -> SfmReport:
    """COLMAP's feature extraction, exhaustive matching and incremental mapping; writes ``out``."""
    with tempfile.TemporaryDirectory(prefix="vid2sim-sfm-") as tmp:
        db = Path(tmp) / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = config.camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = config.max_features
        threads = -1 if config.threads is None else config.threads  # COLMAP's -1: all cores
        extraction.num_threads = threads
        names = list(plates.values()) + photos
        if progress:
            print(f"[calibrate] SIFT features of {len(plates)} plates and {len(photos)} photos", flush=True)
        # a camera per plate (each its own lens); the photos are one camera (one phone), so they pin its intrinsics
        pycolmap.extract_features(db, capture, image_names=list(plates.values()),
                                  camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        if photos:
            pycolmap.extract_features(db, capture, image_names=photos, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
        if progress:
            print(f"[calibrate] matching {len(names) * (len(names) - 1) // 2} image pairs", flush=True)
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = threads
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        if progress:
            print("[calibrate] incremental mapping", flush=True)
        rec, how = _mapping(pycolmap, db, capture, Path(tmp), plates, threads, progress)
        report = _keep_plates(rec, plates, photos, config, time.perf_counter() - start, how)

        def write(staging: Path) -> None:
            rec.write_binary(str(staging))
            (staging / REPORT_JSON).write_text(json.dumps(asdict(report), indent=2) + "\n")

        write_folder_atomic(out, write, create=True)
    return report


def _mapping(pycolmap, db: Path, capture: Path, tmp: Path, plates: dict[str, str], threads: int,
             progress: bool) -> tuple[Any, str]:
    """COLMAP's incremental mapping, and how it was run. First COLMAP's own (intrinsics refined as the images
    register), the most accurate where it holds. Refined image by image, though, a plate seen over a small part of
    its field can collapse to a quarter of its focal length with a small reprojection error (measured:
    docs/capture.md); when a plate's focal length is that far from the others' (:func:`_focal_outliers`), the
    mapping runs again with every camera's intrinsics held at COLMAP's first guess (1.2 × the image's size, no
    distortion) while the images register, refined in one bundle adjustment at the end."""
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    rec = _best_model(pycolmap.incremental_mapping(db, capture, tmp / "default", options=mapping), plates)
    outliers = [] if rec is None else _focal_outliers(rec, plates)
    if not outliers:
        return rec, "default"
    why = f"intrinsics held while registering (the default's {'; '.join(outliers)})"
    if progress:
        print(f"[calibrate] incremental mapping again, {why}", flush=True)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.ba_refine_focal_length = False
    mapping.ba_refine_extra_params = False
    rec = _best_model(pycolmap.incremental_mapping(db, capture, tmp / "held", options=mapping), plates)
    if rec is not None:
        final = pycolmap.BundleAdjustmentOptions()
        final.refine_focal_length = True
        final.refine_extra_params = True
        final.print_summary = False
        pycolmap.bundle_adjustment(rec, final)
    return rec, why


def _focal_outliers(rec, plates: dict[str, str]) -> list[str]:
    """The plates whose focal length is more than ``FOCAL_OUTLIER`` from the registered plates' median, as
    "camera C: F px against the median M px"."""
    focal = {}
    for cam, name in plates.items():
        im = rec.find_image_with_name(name)
        if im is not None and im.has_pose:
            focal[cam] = float(rec.cameras[im.camera_id].mean_focal_length())
    if not focal:
        return []
    median = float(np.median(list(focal.values())))
    return [f"camera {cam}: {f:.0f} px against the median {median:.0f} px" for cam, f in focal.items()
            if abs(f / median - 1) > FOCAL_OUTLIER]


def _keep_plates(rec, plates: dict[str, str], photos: list[str], config: SfmConfig, seconds: float,
                 mapping: str) -> SfmReport:
    """Check that every plate is registered in ``rec``, then deregister the photos (in place)."""
    registered = set() if rec is None else {im.name for im in rec.images.values() if im.has_pose}
    lost = [cam for cam, name in plates.items() if name not in registered]
    if lost:
        linked = len(plates) - len(lost)
        raise CaptureError(
            f"COLMAP registered {linked} of {len(plates)} plates; not those of camera(s) {', '.join(lost)}. Cameras "
            f"far apart rarely match each other's plates: add photos of the empty scene taken between them "
            f"({PHOTOS_DIR}/, {len(photos)} now; docs/capture.md), and keep the floor and walls textured")
    photo_names = set(photos)
    photos_registered = 0
    for im in list(rec.images.values()):
        if im.name in photo_names and im.has_pose:
            photos_registered += 1
            rec.deregister_frame(im.frame_id)
    for pid in [pid for pid, p in rec.points3D.items() if len({e.image_id for e in p.track.elements}) < 2]:
        rec.delete_point3D(pid)  # a point fewer than two plates see is not the cameras' to measure
    return SfmReport(cameras=sorted(plates), photos=len(photos), photos_registered=photos_registered,
                     points=int(rec.num_points3D()),
                     mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
                     mean_track_length=float(rec.compute_mean_track_length()), seconds=round(seconds, 1),
                     config=asdict(config), mapping=mapping, warnings=_warnings(rec, plates))


#: below this many pixels on an image's shorter side COLMAP's intrinsics are loosely held (measured: docs/capture.md)
MIN_SIDE_PX = 480
#: a plate's focal length this far from the plates' median is flagged (a camera COLMAP may have mis-registered)
FOCAL_OUTLIER = 0.3


def _warnings(rec, plates: dict[str, str]) -> list[str]:
    """What the model's own numbers say may be wrong: small plates, a focal length far from the others'."""
    out = []
    cams = {cam: rec.cameras[rec.find_image_with_name(name).camera_id] for cam, name in plates.items()}
    small = min(min(c.width, c.height) for c in cams.values())
    if small < MIN_SIDE_PX:
        out.append(f"plates of {small} px on their shorter side: below {MIN_SIDE_PX} px COLMAP's focal lengths and "
                   "poses are loosely held (a camera can register at a wrong focal length with a small reprojection "
                   "error); calibrate on full-resolution plates")
    for outlier in _focal_outliers(rec, plates):
        out.append(f"{outlier}; unless its lens or zoom differs, COLMAP mis-registered it (add photos near it, or "
                   "calibrate it with a board)")
    return out
