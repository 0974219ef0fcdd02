"""The front view: the one camera whose video Stage I sees.

The paper's predictor takes "a single front-view video". vid2sim's front camera is camera 0 of the
synthetic scenes' ring (:class:`vid2sim.synthetic.scenes.SyntheticSceneConfig` defaults): on a benchmark
scene, the front view is an actual scene camera, and Stage I is trained on exactly the framing it will see.

Geometry (canonical frame, metres, z up, floor z = −0.7):

- It looks at the target (0, 0, −0.4) from 2.4 m away, from azimuth 0° (the +x side) and 20° above the
  horizontal. Its centre is at (2.255, 0, 0.421), with the world z axis up in the image.
- Its field of view is 40° horizontally and vertically (square images): 1.75 m across at the target's
  distance.
- The object starts centred above the origin (half bounding-box diagonal 0.5) with 0.05–0.3 m between
  its lowest point and the floor, and drifts at most 0.2 m/s × 0.75 s = 0.15 m sideways over 16 frames.
  Projected, the image spans the floor line over the whole footprint (x from −0.5 to 0.5; 12.6° below the
  optical axis at the near edge, against 20°), y = ±0.65 m below z = 0.3 m, and heights up to z ≈ 0.42 m
  over the footprint.
- So an object leaves the frame only at its top: when it is taller than 0.82 m and dropped from 0.3 m
  (taller than 1.07 m from 0.05 m). Most objects are 0.5–0.7 m tall. ``TrainingData`` records, per sample,
  the fraction of frames whose silhouette touches the image border (``border_frames``), and ``index.json``
  the dataset mean.

Stage II picks, among a scene's cameras, the one closest to this view (:func:`closest_view`). The angle is
taken between the directions from the target, so a scene camera at another distance still matches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from vid2sim.runtime.errors import ConfigError
from vid2sim.splats.cameras import Camera, camera_ring


@dataclass(frozen=True)
class FrontCamera:
    """The front camera's placement (defaults: camera 0 of the synthetic scenes' ring).

    Attributes:
        radius: distance from the target (m).
        elevation_deg: angle above the horizontal plane.
        azimuth_deg: angle about z from the +x axis.
        fov_deg: field of view, horizontal = vertical (square images).
        target: the point it looks at (m, canonical frame).
    """

    radius: float = 2.4
    elevation_deg: float = 20.0
    azimuth_deg: float = 0.0
    fov_deg: float = 40.0
    target: tuple[float, float, float] = (0.0, 0.0, -0.4)

    def __post_init__(self) -> None:
        for name in ("radius", "elevation_deg", "azimuth_deg", "fov_deg"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"FrontCamera.{name} must be a finite number, got {v!r}")
        if not self.radius > 0:
            raise ConfigError(f"FrontCamera.radius must be positive, got {self.radius}")
        if not 0 < self.fov_deg < 180:
            raise ConfigError(f"FrontCamera.fov_deg must be in (0, 180), got {self.fov_deg}")
        if not -89 <= self.elevation_deg <= 89:
            raise ConfigError(f"FrontCamera.elevation_deg must be in [-89, 89], got {self.elevation_deg}")
        target = tuple(float(c) for c in self.target)
        if len(target) != 3 or not all(math.isfinite(c) for c in target):
            raise ConfigError(f"FrontCamera.target must be three finite numbers, got {self.target!r}")
        object.__setattr__(self, "target", target)

    def camera(self, resolution: int) -> Camera:
        """The :class:`~vid2sim.splats.cameras.Camera` rendering ``resolution`` × ``resolution`` images."""
        return self.ring(1, resolution)[0]

    def ring(self, views: int, resolution: int) -> list[Camera]:
        """``views`` cameras on this camera's ring (same distance, elevation, field of view and target), at
        azimuths ``azimuth_deg + 360° k / views``; camera 0 is :meth:`camera`. The training data's other views."""
        if isinstance(views, bool) or not isinstance(views, int) or views < 1:
            raise ValueError(f"views must be a positive integer, got {views!r}")
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 1:
            raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
        return camera_ring(views, self.radius, self.elevation_deg, resolution, resolution, fov_x_deg=self.fov_deg,
                           target=self.target, azimuth_offset_deg=self.azimuth_deg)

    def direction(self) -> torch.Tensor:
        """(3,) unit vector from the target towards the camera."""
        el, az = math.radians(self.elevation_deg), math.radians(self.azimuth_deg)
        return torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)],
                            dtype=torch.float64)


def closest_view(cameras: Sequence[Camera], front: FrontCamera | None = None,
                 target: Sequence[float] | None = None) -> int:
    """Index of the camera whose direction from ``target`` is closest in angle to the front camera's.

    Args:
        cameras: a scene's cameras (world frame).
        front: the front camera (default :class:`FrontCamera`).
        target: the point the angles are measured from, e.g. the object's centre at frame 0 in the scene's
            frame (default: ``front.target``).
    """
    front = front or FrontCamera()
    if len(cameras) == 0:
        raise ValueError("closest_view needs at least one camera")
    t = torch.tensor(front.target if target is None else tuple(target), dtype=torch.float64)
    d = front.direction()
    best, best_cos = 0, -math.inf
    for i, cam in enumerate(cameras):
        v = cam.center.detach().to(torch.float64).cpu() - t
        c = float(v @ d) / max(float(v.norm()), 1e-12)
        if c > best_cos:
            best, best_cos = i, c
    return best
