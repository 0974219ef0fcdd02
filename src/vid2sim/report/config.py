"""Settings of the HTML report and its error type.

:class:`ReportConfig` holds every knob of :func:`vid2sim.report.write_report` (sizes, the error colour map,
the video encoding); its defaults keep the report of a small-preset scene (6 views, 128², 24 frames) at a
few megabytes. :class:`ReportInputError` is raised for anything wrong with the report's inputs; its message
names the argument, file or field and the value that was expected.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from vid2sim.runtime.errors import InputError

#: colour of observed frames (plots, the videos' timeline and the page); future frames use ``FUTURE_COLOUR``
OBSERVED_COLOUR = "#1f7a4d"
#: colour of held-out (future) frames, predicted by the simulator
FUTURE_COLOUR = "#d9631e"
VIDEO_FORMATS = ("webm", "webp")


class ReportInputError(InputError):
    """Bad input to a report writer (the message names the argument / file / field and what was expected)."""


@dataclass
class ReportConfig:
    """How a report looks and how big it is.

    Attributes:
        panel_size: target side in pixels of one panel of the videos and key-frame strips. Images are scaled
            by an integer factor towards it — nearest-neighbour up (so pixels stay visible), area-averaged
            down — so a 128² scene shows 256² panels and a 448² scene 224² ones. Default 256.
        crop: show each view cropped to the square around everything that appears in it over the whole
            video (ground-truth mask or rendered object), with a 12 % margin, so a small object fills the
            panel (default True; the crop is named under each video).
        error_max: the |error| (mean over RGB of |reconstruction − ground truth|, images in [0, 1]) shown at
            the top of the colour map; larger errors saturate. Default 0.3.
        error_cmap: matplotlib colour map of the error heat map (default ``"magma"``: black = no error).
        video_format: ``"webm"`` (VP9 in WebM: Chromium, Chrome, Edge and Firefox play it without proprietary codecs)
            or ``"webp"`` (animated WebP shown as an image: always plays, no controls, larger). If VP9
            encoding fails (an ffmpeg without libvpx) the writer falls back to ``"webp"`` with a warning.
        video_fps: playback rate of the videos in frames per second (default 5: a 24-frame scene of 0.05 s
            frames plays in 4.8 s, a quarter of real time, slow enough to follow; the page also has 0.5× / 2×).
        video_crf: VP9 constant-quality level, 0 (best) … 63 (default 32).
        filmstrip_frames: frames in each key-frame strip (default 8; the last observed and first future frame
            are always among them).
        thumb_size: side in pixels of a thumbnail panel (default 112).
        ring_views, ring_resolution, ring_frames, ring_elevation_deg: without a scene, the asset's own
            captured drop is rendered in ``ring_views`` cameras (default 4) of ``ring_resolution`` pixels
            (default 128) on a ring ``ring_elevation_deg`` (default 20°) above the object, for
            ``ring_frames`` frames (default 24).
    """

    panel_size: int = 256
    crop: bool = True
    error_max: float = 0.3
    error_cmap: str = "magma"
    video_format: str = "webm"
    video_fps: float = 5.0
    video_crf: int = 32
    filmstrip_frames: int = 8
    thumb_size: int = 112
    ring_views: int = 4
    ring_resolution: int = 128
    ring_frames: int = 24
    ring_elevation_deg: float = 20.0

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ReportInputError(f"ReportConfig.{name} must be {what}, got {getattr(self, name)!r}")

        for name in ("panel_size", "filmstrip_frames", "thumb_size", "ring_views", "ring_resolution", "ring_frames"):
            value = getattr(self, name)
            need(isinstance(value, int) and not isinstance(value, bool) and value >= 1, name, "an integer >= 1")
        need(self.panel_size >= 16, "panel_size", ">= 16 pixels")
        need(isinstance(self.crop, bool), "crop", "True or False")
        need(self.filmstrip_frames >= 2, "filmstrip_frames", ">= 2")
        need(isinstance(self.error_max, (int, float)) and math.isfinite(self.error_max) and 0 < self.error_max <= 1,
             "error_max", "in (0, 1]")
        need(self.video_format in VIDEO_FORMATS, "video_format", f"one of {VIDEO_FORMATS}")
        need(isinstance(self.video_fps, (int, float)) and math.isfinite(self.video_fps) and 0 < self.video_fps <= 120,
             "video_fps", "in (0, 120]")
        need(isinstance(self.video_crf, int) and 0 <= self.video_crf <= 63, "video_crf", "an integer in 0..63")
        need(isinstance(self.ring_elevation_deg, (int, float)) and -89 <= self.ring_elevation_deg <= 89,
             "ring_elevation_deg", "in [-89, 89] degrees")
        try:
            import matplotlib

            matplotlib.colormaps[self.error_cmap]
        except KeyError:
            raise ReportInputError(f"ReportConfig.error_cmap: {self.error_cmap!r} is not a matplotlib colour map "
                                   "(e.g. 'magma', 'inferno', 'viridis')") from None

    def to_dict(self) -> dict[str, Any]:
        """The settings as a JSON-ready dict (recorded in the report's ``report.json``)."""
        return asdict(self)
