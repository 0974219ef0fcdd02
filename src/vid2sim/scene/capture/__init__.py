"""Real captures in: posed static cameras' videos (or frames), clean plates, a COLMAP or nerfstudio calibration →
a scene folder (docs/capture.md).

:func:`import_capture` runs the whole import; the modules hold its stages: :mod:`~.layout` (what the folder holds),
:mod:`~.colmap` and :mod:`~.nerfstudio` (calibrations), :mod:`~.frames`, :mod:`~.undistort`, :mod:`~.masks` and
:mod:`~.plate` (object masks without a learned model), :mod:`~.hull`, :mod:`~.ballistic` and :mod:`~.metric`
(metres, gravity and floor from the object's free flight and contact), :mod:`~.colour` (per-camera colour) and
:mod:`~.importer`.
"""

from vid2sim.scene.capture.errors import CaptureError
from vid2sim.scene.capture.importer import CaptureImportConfig, import_capture, parse_axis

__all__ = ["CaptureError", "CaptureImportConfig", "import_capture", "parse_axis"]
