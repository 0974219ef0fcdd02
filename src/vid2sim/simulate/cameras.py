"""The cameras that render a scenario: a scene folder's, or a ring / an orbit placed around the object.

:func:`scene_cameras` reads a scene folder's cameras without decoding its frames; :func:`resolve_cameras` makes a
scenario's ``cameras`` section concrete (:class:`CameraTrack` per output camera), :func:`frame_cameras` places
automatic ring/orbit cameras so that they see the object and the floor under it, and :func:`check_visible`
refuses a camera that does not see the object at t = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from torch import Tensor

from vid2sim.scene.validation import Problems, SceneFormatError, parse_transforms, read_json, resolve_intrinsics
from vid2sim.scene.video import VideoError, probe_video
from vid2sim.simulate.scenario import CameraSpec, Scenario, ScenarioError
from vid2sim.splats.cameras import Camera, look_at

__all__ = ["CameraTrack", "scene_cameras", "resolve_cameras", "frame_cameras", "orbital_tracks", "check_visible",
           "AUTO_ELEVATION_DEG"]

#: elevation of automatically placed ring / orbit cameras (the synthetic scenes' ring), degrees
AUTO_ELEVATION_DEG = 20.0


@dataclass
class CameraTrack:
    """One named output camera: ``cameras`` holds one Camera (fixed) or one per frame (orbit)."""

    name: str
    cameras: list[Camera]

    def at(self, frame: int) -> Camera:
        """The camera of frame ``frame``."""
        return self.cameras[0] if len(self.cameras) == 1 else self.cameras[frame]


def scene_cameras(path: str | Path) -> tuple[list[Camera], int]:
    """The cameras of a scene folder and its frame count, read from ``transforms.json`` and one image (or
    video header) per camera — without decoding the frames.

    Raises:
        ScenarioError: the folder is not a readable scene.
    """
    from PIL import Image

    root = Path(path)
    problems = Problems()
    try:
        plan = parse_transforms(read_json(root / "transforms.json", "transforms.json", root), problems)
        problems.raise_if_any(root)
    except SceneFormatError as exc:
        raise ScenarioError(f"{root}: not a readable scene folder ({str(exc).splitlines()[0]})") from None
    assert plan is not None
    cameras: list[Camera] = []
    frames = plan.num_frames
    for entry in plan.camera_entries():
        try:
            if plan.layout == "frames":
                rel = Path(entry.file_path)
                file = rel if rel.is_absolute() else root / rel
                if not file.is_file() and not file.suffix:
                    file = file.with_name(file.name + ".png")
                with Image.open(file) as im:
                    width, height = im.size
            else:
                info = probe_video(root / entry.video_path)
                width, height = info.width, info.height
                frames = info.num_frames if frames is None else min(frames, info.num_frames)
        except (OSError, VideoError) as exc:
            raise ScenarioError(f"{root}: cannot read camera {entry.camera}'s image size ({exc})") from None
        resolved = resolve_intrinsics(entry.intrinsics, width, height, f"camera {entry.camera}", "transforms.json",
                                      problems)
        if resolved is None:
            raise ScenarioError(f"{root}: {problems.items[-1]}")
        K, w, h = resolved
        cameras.append(Camera.from_nerf(torch.from_numpy(entry.c2w), torch.from_numpy(K).float(), w, h))
    if len({(c.width, c.height) for c in cameras}) != 1:
        raise ScenarioError(f"{root}: its cameras have different image sizes")
    return cameras, int(frames or 0)


def resolve_cameras(s: Scenario, scene_path: str | None, scene_info: tuple[list, int] | None, posed: Tensor,
                    floor: Any, notes: list[str]) -> list[CameraTrack]:
    """The output cameras of ``s`` (filling ``cameras.type``, ``cameras.scene``, ``resolution`` and the automatic
    ring/orbit fields): the scene folder's ``scene_info`` (cameras, frames) read from ``scene_path``, or ring/orbit
    cameras framing the posed points ``posed`` (M, 3) and the floor (None: no floor); ``notes`` gets the choices
    made automatically."""
    c = s.cameras
    if c.type is None:
        if scene_info is not None:
            c.type = "scene"
        else:
            c.type = "ring"
            notes.append("cameras: ring (the asset's source scene is not readable)")
    if c.type == "scene":
        if scene_info is None:
            where = "cameras.scene" if c.scene is not None else "cameras.type"
            raise s.error(where, c.scene or c.type, "the asset's source scene is not recorded or no longer exists; "
                          "give a scene folder (cameras.scene / --scene) or use ring / orbit cameras")
        c.scene = str(scene_path)
        cams = scene_info[0]
        if s.resolution is None:
            s.resolution = cams[0].width
        width = s.resolution
        height = max(1, round(cams[0].height * width / cams[0].width))
        cams = [cam.resized(width, height) if (cam.width, cam.height) != (width, height) else cam for cam in cams]
        return [CameraTrack(f"scene_{v:02d}", [cam]) for v, cam in enumerate(cams)]

    if s.resolution is None:
        s.resolution = scene_info[0][0].width if scene_info is not None else 256
    auto = [k for k in ("target", "radius", "height") if getattr(c, k) is None]
    frame_cameras(c, posed, s.floor.height if floor is not None else None, auto)
    return orbital_tracks(s)


def frame_cameras(c: CameraSpec, cloud: Tensor, floor_height: float | None, auto: Sequence[str]) -> None:
    """Fill the automatic ``auto`` fields of ring/orbit cameras (``target``, ``radius``, ``height``) so that they
    see the points ``cloud`` (M, 3) and the floor under them: the target is above the centre of the points'
    horizontal bounding box, halfway between the floor (or their bottom) and their top; the distance fits that
    span and their horizontal reach in the field of view with 20 % margin, at a 20° elevation."""
    top = float(cloud[:, 2].max())
    bottom = float(cloud[:, 2].min())
    if floor_height is not None:
        bottom = min(bottom, float(floor_height))
    if "target" in auto:
        lo, hi = cloud[:, :2].amin(0), cloud[:, :2].amax(0)
        c.target = (float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, 0.5 * (top + bottom))
    target = torch.tensor(c.target, dtype=torch.float64, device=cloud.device)
    reach = float((cloud[:, :2].to(torch.float64) - target[:2]).norm(dim=1).max())
    half_span = max(0.5 * (top - bottom), reach, 1e-3)
    distance = 1.2 * half_span / math.tan(math.radians(c.fov_deg) / 2) + reach
    el = math.radians(AUTO_ELEVATION_DEG)
    if "radius" in auto:
        c.radius = distance * math.cos(el)
    if "height" in auto:
        c.height = distance * math.sin(el)


def orbital_tracks(s: Scenario) -> list[CameraTrack]:
    """The ring or orbit cameras of a scenario whose camera fields are all set (target, radius, height)."""
    c = s.cameras
    target = torch.tensor(c.target, dtype=torch.float64)
    W = int(s.resolution)
    fx = 0.5 * W / math.tan(math.radians(c.fov_deg) / 2)
    K = Camera.intrinsics(fx, fx, W / 2, W / 2)

    def camera_at(azimuth_deg: float) -> Camera:
        a = math.radians(azimuth_deg)
        eye = target + torch.tensor([c.radius * math.cos(a), c.radius * math.sin(a), c.height], dtype=torch.float64)
        return Camera(look_at(eye, target), K, W, W)

    if c.type == "ring":
        return [CameraTrack(f"ring_{i:02d}", [camera_at(c.azimuth_deg + 360.0 * i / c.views)])
                for i in range(c.views)]
    n = int(s.frames)
    steps = max(n - 1, 1)
    return [CameraTrack("orbit", [camera_at(c.azimuth_deg + 360.0 * c.turns * t / steps) for t in range(n)])]


def check_visible(s: Scenario, tracks: list[CameraTrack], posed: Tensor) -> None:
    """Every camera must see some of the object at t = 0 (a point in front of it, inside its image)."""
    pts = posed[:: max(1, posed.shape[0] // 4000)].to(torch.float32)
    for track in tracks:
        for k, cam in enumerate(track.cameras):
            pix, depth = cam.project(pts)
            seen = ((depth > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0)
                    & (pix[:, 1] < cam.height))
            if not bool(seen.any()):
                frame = f" at frame {k}" if len(track.cameras) > 1 else ""
                candidates = ("cameras.target", "cameras.radius", "cameras.height", "cameras.fov_deg",
                              "initial.translation", "initial.euler_deg", "initial.axis_angle", "cameras.scene")
                path = next((c for c in candidates if c in s.origins), "cameras.type")
                raise s.error(path, s.get(path), f"camera {track.name}{frame} does not see the object at t = 0 "
                              "(no point of it projects into its image); expected cameras looking at the object "
                              "(check the cameras' target / radius / height and the object's initial translation)")

