"""Capture twins: what a real multi-camera capture of a synthetic drop would hand to ``vid2sim import-capture``.

:func:`make_capture_twin` turns a ``make-scene`` folder into a capture folder (the layout of
:mod:`vid2sim.scene.capture.layout`): the same FEM motion and cameras, but

* a textured room behind the object and its shadow on the floor (:mod:`vid2sim.synthetic.capture_render`);
* per-camera exposure, white balance and black level, sensor noise, 8-bit H.264 video (or PNG frames);
* real lens distortion (OpenCV model; COLMAP models OPENCV, RADIAL and SIMPLE_RADIAL);
* calibrations as structure from motion gives them: in a random similarity frame (rotation, origin, scale:
  calibration units are not metres, the up axis is anything), with camera poses perturbed by SfM-sized noise,
  as COLMAP text and/or binary (with 3D points on the floor and walls) and nerfstudio's ``transforms.json``;
* a clean plate per camera;
* ``lead_in_frames`` frames before the scene's first one: the object's rigid free flight extrapolated back in time
  (its centre of mass on the parabola of the scene's initial velocity, the body turning at its initial angular
  velocity), as a recording that starts before the drop. ``import-capture --frames L:L+T`` keeps the scene's
  frames while the importer measures gravity on all of them.

The truth the importer must recover — the similarity from the scene's world to the calibration frame, metres per
unit, gravity, the floor, the true object coverage of every pixel — goes to ``ground_truth/`` (``truth.json``,
``alpha.npz``), which the importer never reads.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from vid2sim.runtime.files import jsonable, write_folder_atomic
from vid2sim.scene.capture.cameras import CaptureCamera, rigid
from vid2sim.scene.capture.colmap import write_colmap
from vid2sim.scene.capture.layout import PHOTOS_DIR
from vid2sim.scene.capture.nerfstudio import write_transforms
from vid2sim.scene.reading import load_scene
from vid2sim.scene.video import write_video
from vid2sim.splats.cameras import Camera, look_at
from vid2sim.synthetic.capture_render import Room, Sensor, ShadowMaps, make_room, render_room, render_view
from vid2sim.synthetic.embedding import apply_embedding, embed_points
from vid2sim.synthetic.fem import FEMResult
from vid2sim.synthetic.mesh_render import DEFAULT_LIGHT_DIR
from vid2sim.synthetic.meshes import load_user_mesh
from vid2sim.synthetic.scenes import FEM_RESULT_NPZ, SYNTHETIC_JSON, SyntheticSceneConfig
from vid2sim.synthetic.shapes import make_procedural_object

TRUTH_DIR = "ground_truth"
TRUTH_JSON = "truth.json"
ALPHA_NPZ = "alpha.npz"


@dataclass
class CaptureTwinConfig:
    """How a capture twin departs from its clean scene (defaults: a careful amateur capture).

    Attributes:
        seed: draws every random choice below (distortion, gains, noise, similarity, pose noise, points).
        resolution_scale: the cameras film at this many times the scene's resolution (a real camera films far more
            pixels than the scene keeps; ``import-capture --downscale`` brings them back, averaging away most of the
            compression's damage at the object's outline).
        frame_rate_scale: the cameras film this many frames per scene frame (60 fps for a 20 fps scene; ``import-capture
            --every`` keeps the scene's): the free flight is measured on them all. Between the FEM's frames the motion
            is
            the cubic Hermite interpolation of its positions and velocities (exact for the centre of mass in flight).
        lead_in_frames: scene frames of free flight recorded before the scene's first frame (fewer when the object would
            otherwise reach the floor, come within ``lead_in_clearance`` m of it, or leave a camera's view).
        lead_in_clearance: metres the object's lowest point stays above the floor in the lead-in.
        frames_format: ``"video"`` (``videos/<cam>.mp4``, H.264 4:2:0) or ``"frames"`` (``frames/<cam>/*.png``
            and ``capture.json`` with the frame rate).
        video_quality: 1..10, the H.264 quality of :func:`vid2sim.scene.video.write_video` (7 ≈ CRF 15).
        colmap_format: ``"text"``, ``"binary"``, ``"both"`` or ``"none"``.
        write_transforms: also write nerfstudio's ``transforms.json``.
        camera_models: COLMAP models drawn per camera (the lens follows the model's terms).
        k1_range, k2_range, tangential: radial terms drawn uniformly; tangential terms uniform in ±``tangential``.
        exposure_range, white_balance_range, black_level_range: the sensor: gain = exposure × per-channel
            white balance, plus a black level (all uniform draws).
        noise_std: sensor noise std (colour units in [0, 1]) before 8-bit quantisation.
        world_scale_range: calibration units per metre, log-uniform.
        rotation_noise_deg, position_noise_m, focal_noise: SfM-sized calibration errors: a random rotation of
            each camera of this std (degrees), a shift of its centre (metres), a relative focal-length error.
        floor_points, wall_points, point_noise_m: COLMAP 3D points on the floor (within 3 m of the centre) and
            walls, seen by every camera whose view holds them, with this position noise.
        shadow_light: the share of light left in the object's shadow on the floor.
        shadow_softness_m: the penumbra's width (Gaussian std, metres on the floor).
        room_half_size, wall_height: the room around the cameras (metres).
        supersample: anti-aliasing of the renders.
        photos: walkaround photos of the empty room written to ``photos/`` (what a user adds so that structure
            from motion links cameras too far apart to match each other's plates: ``vid2sim calibrate-capture``),
            taken on a ring through the cameras at 0.8–1.2 × their distance from the point they look at and
            ±``photo_height_m`` around their height, with the first camera's intrinsics and no distortion. 0: none.
        photo_height_m: see ``photos``.
    """

    seed: int = 0
    resolution_scale: int = 2
    frame_rate_scale: int = 3
    lead_in_frames: int = 8
    lead_in_clearance: float = 0.03
    frames_format: str = "video"
    video_quality: float = 7.0
    colmap_format: str = "text"
    write_transforms: bool = True
    camera_models: tuple[str, ...] = ("OPENCV", "RADIAL", "SIMPLE_RADIAL")
    k1_range: tuple[float, float] = (-0.20, -0.04)
    k2_range: tuple[float, float] = (-0.02, 0.06)
    tangential: float = 5e-4
    exposure_range: tuple[float, float] = (0.8, 1.15)
    white_balance_range: tuple[float, float] = (0.9, 1.1)
    black_level_range: tuple[float, float] = (0.0, 0.015)
    noise_std: float = 1.2 / 255.0
    world_scale_range: tuple[float, float] = (0.25, 4.0)
    rotation_noise_deg: float = 0.03
    position_noise_m: float = 0.001
    focal_noise: float = 0.001
    floor_points: int = 1500
    wall_points: int = 500
    point_noise_m: float = 0.002
    shadow_light: float = 0.45
    shadow_softness_m: float = 0.01
    room_half_size: float = 4.0
    wall_height: float = 3.0
    supersample: int = 2
    photos: int = 0
    photo_height_m: float = 0.3

    def __post_init__(self) -> None:
        if self.frames_format not in ("video", "frames"):
            raise ValueError(f"CaptureTwinConfig.frames_format must be 'video' or 'frames', got {self.frames_format!r}")
        if self.colmap_format not in ("text", "binary", "both", "none"):
            raise ValueError("CaptureTwinConfig.colmap_format must be 'text', 'binary', 'both' or 'none', got "
                             f"{self.colmap_format!r}")
        if isinstance(self.photos, bool) or not isinstance(self.photos, int) or self.photos < 0:
            raise ValueError(f"CaptureTwinConfig.photos must be an integer >= 0, got {self.photos!r}")
        if self.colmap_format == "none" and not self.write_transforms:
            raise ValueError("CaptureTwinConfig: write at least one calibration (colmap_format or write_transforms)")
        if isinstance(self.resolution_scale, bool) or not isinstance(self.resolution_scale, int) or \
                self.resolution_scale < 1:
            raise ValueError(
                f"CaptureTwinConfig.resolution_scale must be an integer >= 1, got {self.resolution_scale!r}"
            )
        if isinstance(self.frame_rate_scale, bool) or not isinstance(self.frame_rate_scale, int) or \
                self.frame_rate_scale < 1:
            raise ValueError(
                f"CaptureTwinConfig.frame_rate_scale must be an integer >= 1, got {self.frame_rate_scale!r}"
            )
        if self.lead_in_frames < 0:
            raise ValueError(f"CaptureTwinConfig.lead_in_frames must be >= 0, got {self.lead_in_frames}")
        for name in ("camera_models",):
            bad = set(getattr(self, name)) - {"OPENCV", "RADIAL", "SIMPLE_RADIAL", "PINHOLE", "SIMPLE_PINHOLE"}
            if bad:
                raise ValueError(f"CaptureTwinConfig.camera_models: unknown {sorted(bad)}")


# ---- motion ----------------------------------------------------------------------------------------------------


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(axis_angle))
    if theta < 1e-15:
        return np.eye(3)
    k = axis_angle / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K


def rigid_velocity(points: np.ndarray, velocities: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid velocity (v (3,), ω (3,)) of point velocities (N, 3) at points (N, 3):
    velocities ≈ v + ω × (points − centre)."""
    r = points - centre
    A = np.zeros((3 * len(r), 6))
    A[:, :3] = np.tile(np.eye(3), (len(r), 1))
    # ω × r = −[r]× ω
    A[0::3, 3:] = np.stack([np.zeros(len(r)), r[:, 2], -r[:, 1]], 1)
    A[1::3, 3:] = np.stack([-r[:, 2], np.zeros(len(r)), r[:, 0]], 1)
    A[2::3, 3:] = np.stack([r[:, 1], -r[:, 0], np.zeros(len(r))], 1)
    sol = np.linalg.lstsq(A, velocities.reshape(-1), rcond=None)[0]
    return sol[:3], sol[3:]


def free_flight(points: np.ndarray, centre: np.ndarray, velocity: np.ndarray, omega: np.ndarray,
                gravity: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Rigid free flight of points (N, 3) at times (K,) (seconds from now, negative for the past): the centre on its
    parabola, the body turning at the constant angular velocity ω about it. Returns (K, N, 3)."""
    out = []
    for t in times:
        c = centre + velocity * t + 0.5 * gravity * t * t
        out.append(c + (points - centre) @ _rotation(omega * t).T)
    return np.stack(out)


def tet_centroid(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Volume centroid (3,) of a tet mesh (the centre of mass at uniform density)."""
    p = vertices[tets[:, :4]]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])) / 6
    return (vol[:, None] * p.mean(1)).sum(0) / vol.sum()


def _in_view(points: np.ndarray, cameras: Sequence[CaptureCamera], margin: float) -> bool:
    for cam in cameras:
        uv, z = cam.project(points)
        if (z <= 0).any():
            return False
        m = margin * max(cam.width, cam.height)
        if (uv < m).any() or (uv[:, 0] > cam.width - m).any() or (uv[:, 1] > cam.height - m).any():
            return False
    return True


def lead_in(surface0: np.ndarray, centre: np.ndarray, velocity: np.ndarray, omega: np.ndarray, gravity: np.ndarray,
            dt: float, max_frames: int, floor_height: float | None, clearance: float,
            cameras: Sequence[CaptureCamera], margin: float = 0.03) -> np.ndarray:
    """The free-flight frames before a scene's first frame, earliest first: (L, Nv, 3) with L ≤ ``max_frames``
    the most frames back for which the object stays ``clearance`` above the floor and inside every view."""
    frames = []
    for k in range(1, max_frames + 1):
        x = free_flight(surface0, centre, velocity, omega, gravity, np.array([-k * dt]))[0]
        if floor_height is not None and x[:, 2].min() < floor_height + clearance:
            break
        if not _in_view(x, cameras, margin):
            break
        frames.append(x)
    return np.stack(frames[::-1]) if frames else np.zeros((0,) + surface0.shape)


def rigid_drop(vertices: np.ndarray, frames: int, dt: float, floor_height: float, drop_height: float,
               velocity: Sequence[float] = (0.0, 0.0, 0.0), omega: Sequence[float] = (0.0, 0.0, 0.0),
               gravity: float = 9.8) -> np.ndarray:
    """A rigid object (vertices (Nv, 3)) in free flight from ``drop_height`` m above the floor that stops dead
    where it first touches it — a quick stand-in for an FEM drop (tests, demos). Returns (T, Nv, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    v = v + np.array([0.0, 0.0, floor_height + drop_height - v[:, 2].min()])
    centre = v.mean(0)
    g = np.array([0.0, 0.0, -gravity])
    out = []
    for t in range(frames):
        x = free_flight(v, centre, np.asarray(velocity, float), np.asarray(omega, float), g, np.array([t * dt]))[0]
        if x[:, 2].min() < floor_height:
            x = out[-1] if out else x
            x = x + np.array([0.0, 0.0, floor_height - x[:, 2].min()])
        out.append(x)
    return np.stack(out)


# ---- calibration ---------------------------------------------------------------------------------------------


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclass
class Similarity:
    """x_calibration = scale · R · x_world + t (calibration units per metre = ``scale``)."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def points(self, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.R.T + self.t

    def world_to_camera(self, w2c: np.ndarray) -> np.ndarray:
        """A camera's world-to-camera (4, 4) in metres → the same camera in the calibration frame."""
        Rc, tc = w2c[:3, :3], w2c[:3, 3]
        R = Rc @ self.R.T
        return rigid(R, self.scale * tc - R @ self.t)

    def to_json(self) -> dict:
        return {"scale": self.scale, "rotation": self.R.tolist(), "translation": self.t.tolist()}


def _lens(model: str, rng: np.random.Generator, config: CaptureTwinConfig) -> np.ndarray:
    k1 = rng.uniform(*config.k1_range)
    k2 = rng.uniform(*config.k2_range)
    p = rng.uniform(-config.tangential, config.tangential, 2)
    return {"OPENCV": np.array([k1, k2, p[0], p[1], 0.0]), "RADIAL": np.array([k1, k2, 0, 0, 0.0]),
            "SIMPLE_RADIAL": np.array([k1, 0, 0, 0, 0.0]), "PINHOLE": np.zeros(5),
            "SIMPLE_PINHOLE": np.zeros(5)}[model]


def _perturbed(cam: CaptureCamera, rng: np.random.Generator, config: CaptureTwinConfig, scale: float) -> CaptureCamera:
    """``cam`` as a structure-from-motion calibration would give it: rotated, shifted, focal length off a little."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    dR = _rotation(axis * math.radians(rng.normal(0.0, config.rotation_noise_deg)))
    R = dR @ cam.rotation
    centre = cam.center + rng.normal(0.0, config.position_noise_m, 3) * scale
    K = cam.K.copy()
    f = 1.0 + rng.normal(0.0, config.focal_noise)
    K[0, 0] *= f
    K[1, 1] *= f
    out = CaptureCamera(cam.name, cam.width, cam.height, K, cam.distortion, rigid(R, -R @ centre), model=cam.model)
    return out


def _room_points(config: CaptureTwinConfig, floor_height: float, rng: np.random.Generator) -> np.ndarray:
    r = 3.0 * np.sqrt(rng.uniform(0, 1, config.floor_points))
    a = rng.uniform(0, 2 * np.pi, config.floor_points)
    floor = np.stack([r * np.cos(a), r * np.sin(a), np.full_like(r, floor_height)], 1)
    h = config.room_half_size
    side = rng.integers(0, 4, config.wall_points)
    s = rng.uniform(-h, h, config.wall_points)
    z = floor_height + rng.uniform(0.05, config.wall_height, config.wall_points)
    xy = np.where(side[:, None] == 0, np.stack([s, -h * np.ones_like(s)], 1),
                  np.where(side[:, None] == 1, np.stack([h * np.ones_like(s), s], 1),
                           np.where(side[:, None] == 2, np.stack([s, h * np.ones_like(s)], 1),
                                    np.stack([-h * np.ones_like(s), s], 1))))
    walls = np.concatenate([xy, z[:, None]], 1)
    return np.concatenate([floor, walls])


# ---- the capture -----------------------------------------------------------------------------------------------


@dataclass
class CaptureMotion:
    """What a capture twin shows: the textured surface moving (all frames, lead-in included) before the cameras.

    Attributes:
        vertices: (T, Nv, 3) surface positions in the world frame (metres, z up).
        faces: (Nf, 3); uvs: (Nf, 3, 2); texture: (Ht, Wt, 3).
        cameras: the V clean cameras (pinhole, world frame).
        dt: seconds per video frame; floor_height: the floor's z; gravity: (3,) m/s².
        lead_in: video frames before the clean scene's first frame.
        step: video frames per scene frame (the scene's frame i is video frame ``lead_in + step·i``).
        info: extra facts for ``truth.json``.
    """

    vertices: Tensor
    faces: Tensor
    uvs: Tensor
    texture: Tensor
    cameras: list[Camera]
    dt: float
    floor_height: float
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    lead_in: int = 0
    step: int = 1
    info: dict[str, Any] = field(default_factory=dict)


def write_capture(motion: CaptureMotion, out: str | Path, config: CaptureTwinConfig | None = None,
                  overwrite: bool = False, progress: bool = False) -> Path:
    """Render ``motion`` as a capture folder at ``out`` (complete or absent: assembled beside it, then renamed).

    Returns:
        ``out``. Its ``ground_truth/truth.json`` holds the similarity, scale, gravity, floor, the true cameras
        and sensors, and ``ground_truth/alpha.npz`` the true coverage ``alpha`` (V, T, H, W) uint8 of the
        distorted frames.
    """

    config = CaptureTwinConfig() if config is None else config
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out} exists and is not empty (pass overwrite=True to replace a capture)")
        if not (out / TRUTH_DIR / TRUTH_JSON).is_file():
            raise FileExistsError(f"{out} is not a capture twin (no {TRUTH_DIR}/{TRUTH_JSON}); refusing to replace it")
    rng = np.random.default_rng([int(config.seed), 48])
    rig = _capture_rig(motion, config, rng)
    room = make_room(motion.floor_height, config.room_half_size, config.wall_height, seed=config.seed)
    shadows = ShadowMaps(motion.vertices, motion.faces, motion.floor_height, DEFAULT_LIGHT_DIR,
                         softness=config.shadow_softness_m)

    def write(staging: Path) -> None:
        alphas = _film(staging, motion, rig, room, shadows, config, rng, progress)
        if config.photos:
            _photograph(staging / PHOTOS_DIR, rig, room, config, progress)
        true_cal = _write_calibrations(staging, motion, rig, config, rng)
        _write_truth(staging / TRUTH_DIR, motion, rig, config, true_cal, alphas)

    return write_folder_atomic(out, write, create=True)


@dataclass
class _CaptureRig:
    """The capture's cameras as drawn: names, COLMAP models, the cameras filming in the world frame (scaled by
    ``resolution_scale``, with their true lenses), their sensors, and the similarity to the calibration frame."""

    names: list[str]
    models: list[str]
    true_world: list[CaptureCamera]
    sensors: list[Sensor]
    sim: Similarity


def _capture_rig(motion: CaptureMotion, config: CaptureTwinConfig, rng: np.random.Generator) -> _CaptureRig:
    """Draw the rig from ``rng`` (in this order: every camera's model, then every lens, every sensor, and the
    similarity)."""
    names = [f"c{v:02d}" for v in range(len(motion.cameras))]
    models = [str(rng.choice(config.camera_models)) for _ in names]
    k = config.resolution_scale
    filming = [c.resized(c.width * k, c.height * k) for c in motion.cameras]
    true_world = [CaptureCamera(n, c.width, c.height, c.K.double().numpy(), _lens(m, rng, config),
                                c.world_to_camera.double().numpy(), model=m)
                  for n, c, m in zip(names, filming, models)]
    sensors = [Sensor(rng.uniform(*config.exposure_range) * rng.uniform(*config.white_balance_range, 3),
                      float(rng.uniform(*config.black_level_range)), config.noise_std) for _ in names]
    lo, hi = np.log(config.world_scale_range[0]), np.log(config.world_scale_range[1])
    sim = Similarity(float(np.exp(rng.uniform(lo, hi))), _random_rotation(rng), rng.normal(0.0, 3.0, 3))
    return _CaptureRig(names, models, true_world, sensors, sim)


def _film(staging: Path, motion: CaptureMotion, rig: _CaptureRig, room: Room, shadows: ShadowMaps,
          config: CaptureTwinConfig, rng: np.random.Generator, progress: bool) -> list[np.ndarray]:
    """Render every camera's frames (through its sensor: noise from ``rng``) as a video or PNG frames, and its clean
    plate; the cameras' true coverage, each (T, H, W) uint8."""
    T = motion.vertices.shape[0]
    alphas = []
    for v, cam in enumerate(rig.true_world):
        if progress:
            print(f"[capture twin] camera {cam.name}: rendering {T} frames", flush=True)
        frames, plate, alpha = render_view(cam, room, motion.vertices, motion.faces, motion.uvs, motion.texture,
                                           shadows, config.shadow_light, config.supersample)
        noisy = rig.sensors[v](frames, rng)
        if config.frames_format == "video":
            (staging / "videos").mkdir(exist_ok=True)
            write_video(staging / "videos" / f"{cam.name}.mp4", noisy, 1.0 / motion.dt,
                        quality=config.video_quality)
        else:
            folder = staging / "frames" / cam.name
            folder.mkdir(parents=True)
            for t, f in enumerate(noisy):
                Image.fromarray(f).save(folder / f"{t:05d}.png", compress_level=1)
        (staging / "background").mkdir(exist_ok=True)
        Image.fromarray(rig.sensors[v](plate, rng)).save(staging / "background" / f"{cam.name}.png")
        alphas.append(np.round(alpha * 255).astype(np.uint8))
    if config.frames_format == "frames":
        (staging / "capture.json").write_text(json.dumps({"fps": 1.0 / motion.dt}) + "\n")
    return alphas


def _photograph(folder: Path, rig: _CaptureRig, room: Room, config: CaptureTwinConfig, progress: bool) -> None:
    """Render ``config.photos`` walkaround photos of the empty room into ``folder`` (see
    :class:`CaptureTwinConfig`); their draws come from their own stream, so a twin with photos is otherwise the one
    without."""
    rng = np.random.default_rng([int(config.seed), 49])
    cams = rig.true_world
    centres = np.array([c.center for c in cams])
    axes = np.array([c.rotation[2] for c in cams])
    # the point nearest every camera's optical axis (least squares)
    A = sum(np.eye(3) - np.outer(a, a) for a in axes)
    b = sum((np.eye(3) - np.outer(a, a)) @ c for a, c in zip(axes, centres))
    target = np.linalg.solve(A, b)
    offsets = centres - target
    radius = float(np.linalg.norm(offsets[:, :2], axis=1).mean())
    height = float(offsets[:, 2].mean())
    phase = float(np.arctan2(offsets[0, 1], offsets[0, 0]))
    ref = cams[0]
    sensor = Sensor(np.ones(3), 0.0, config.noise_std)
    folder.mkdir()
    if progress:
        print(f"[capture twin] {config.photos} walkaround photos of the empty room", flush=True)
    for k in range(config.photos):
        a = phase + 2 * np.pi * (k + 0.5) / config.photos
        r = radius * rng.uniform(0.8, 1.2)
        eye = target + np.array([r * np.cos(a), r * np.sin(a), height + rng.uniform(-1, 1) * config.photo_height_m])
        look = target + rng.normal(0.0, 0.05 * radius, 3)
        cam = Camera(look_at(eye, look), torch.as_tensor(ref.K, dtype=torch.float32), ref.width, ref.height)
        rgb, _, _ = render_room(room, cam, config.supersample)
        Image.fromarray(sensor(rgb, rng)).save(folder / f"p{k:03d}.png")


def _write_calibrations(staging: Path, motion: CaptureMotion, rig: _CaptureRig, config: CaptureTwinConfig,
                        rng: np.random.Generator) -> list[CaptureCamera]:
    """Write the calibrations as structure from motion would give them (cameras perturbed, and 3D points on the
    floor and walls seen by two cameras or more, with noise from ``rng``): COLMAP and/or ``transforms.json``.
    Returns the true cameras in the calibration frame."""
    sim, models = rig.sim, rig.models
    true_cal = [CaptureCamera(c.name, c.width, c.height, c.K, c.distortion,
                              sim.world_to_camera(c.world_to_camera), model=c.model) for c in rig.true_world]
    noisy_cal = [_perturbed(c, rng, config, sim.scale) for c in true_cal]
    points_world = _room_points(config, motion.floor_height, rng)
    visible = []
    keep = []
    for p in points_world:
        seen = [v for v, c in enumerate(rig.true_world) if _in_view(p[None], [c], 0.0)]
        if len(seen) >= 2:
            keep.append(p)
            visible.append(seen)
    points_world = np.array(keep).reshape(-1, 3)
    points_cal = sim.points(points_world + rng.normal(0.0, config.point_noise_m, points_world.shape))
    colours = np.full((len(points_cal), 3), 128, np.uint8)
    if config.colmap_format in ("text", "both"):
        write_colmap(noisy_cal, models, staging / "colmap", binary=False, points=points_cal, colours=colours,
                     visible=visible)
    if config.colmap_format in ("binary", "both"):
        write_colmap(noisy_cal, models, staging / "colmap", binary=True, points=points_cal, colours=colours,
                     visible=visible)
    if config.write_transforms:
        write_transforms(noisy_cal, staging / "transforms.json")
    return true_cal


def _write_truth(truth_dir: Path, motion: CaptureMotion, rig: _CaptureRig, config: CaptureTwinConfig,
                 true_cal: list[CaptureCamera], alphas: list[np.ndarray]) -> None:
    """Write ``ground_truth/``: the true coverage ``alpha.npz`` (V, T, H, W) uint8 and ``truth.json`` (the
    similarity, scale, gravity, floor, true cameras and sensors)."""
    truth_dir.mkdir()
    np.savez_compressed(truth_dir / ALPHA_NPZ, alpha=np.stack(alphas))
    sim = rig.sim
    g = np.asarray(motion.gravity, dtype=np.float64)
    up_world = -g / np.linalg.norm(g)
    up_cal = sim.R @ up_world
    floor_point_cal = sim.points(np.array([[0.0, 0.0, motion.floor_height]]))[0]
    truth = {
        "generator": "vid2sim.synthetic.capture",
        "config": jsonable(asdict(config)),
        "cameras": rig.names,
        "frames": motion.vertices.shape[0],
        "fps": 1.0 / motion.dt,
        "dt": motion.dt,
        "lead_in_frames": motion.lead_in,
        "frame_step": motion.step,
        "resolution_scale": config.resolution_scale,
        "scene_frames": [motion.lead_in, motion.vertices.shape[0]],
        "world_to_calibration": sim.to_json(),
        "units_per_metre": sim.scale,
        "metres_per_unit": 1.0 / sim.scale,
        "gravity_world": g.tolist(),
        "gravity_direction_calibration": (-up_cal).tolist(),
        "floor_height_world": motion.floor_height,
        "floor_calibration": {"normal": up_cal.tolist(), "offset": float(up_cal @ floor_point_cal)},
        "true_cameras_calibration": {c.name: {"model": c.model, "K": c.K.tolist(),
                                              "distortion": c.distortion.tolist(),
                                              "world_to_camera": c.world_to_camera.tolist()} for c in true_cal},
        "sensors": {n: {"gain": s.gain.tolist(), "black": s.black, "noise": s.noise}
                    for n, s in zip(rig.names, rig.sensors)},
        "alpha": f"{TRUTH_DIR}/{ALPHA_NPZ}",
        **motion.info,
    }
    (truth_dir / TRUTH_JSON).write_text(json.dumps(jsonable(truth), indent=2) + "\n")


def hermite(p0: np.ndarray, v0: np.ndarray, p1: np.ndarray, v1: np.ndarray, h: float, s: float) -> np.ndarray:
    """Cubic Hermite interpolation at s ∈ [0, 1] between positions p0, p1 (N, 3) with velocities v0, v1 over h
    seconds (exact for a parabola)."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * v0 + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * h * v1


def scene_motion(scene_dir: str | Path, lead_in_frames: int, clearance: float = 0.03, step: int = 1) -> CaptureMotion:
    """The motion of a ``make-scene`` folder (its object's textured surface carried by the FEM tets, its cameras)
    filmed at ``step`` video frames per scene frame (Hermite-interpolated between the FEM's frames), with up to
    ``lead_in_frames`` scene frames of free flight before it (:func:`lead_in`)."""

    scene_dir = Path(scene_dir)
    for name in (SYNTHETIC_JSON, FEM_RESULT_NPZ):
        if not (scene_dir / name).is_file():
            raise FileNotFoundError(f"{scene_dir} is not a make-scene folder: {name} is missing")
    syn = SyntheticSceneConfig.from_json(scene_dir / SYNTHETIC_JSON)
    scene = load_scene(scene_dir, dtype=torch.uint8)
    mesh = load_user_mesh(syn.mesh) if syn.mesh is not None else make_procedural_object(syn.seed)
    result = FEMResult.load(scene_dir / FEM_RESULT_NPZ)
    nv = int(result.tets.max()) + 1
    tet_index, bary = embed_points(mesh.vertices.double(), result.rest_vertices[:nv].double(), result.tets)
    traj = result.trajectory.double().numpy()
    vels = result.velocities.double().numpy()
    dt_s = scene.config.dt
    nodes = []
    for k in range(traj.shape[0]):
        nodes.append(traj[k])
        if k + 1 < traj.shape[0]:
            nodes += [hermite(traj[k], vels[k], traj[k + 1], vels[k + 1], dt_s, j / step) for j in range(1, step)]
    surface = apply_embedding(torch.as_tensor(np.stack(nodes)), tet_index, bary,
                              result.embedding_elements).double().numpy()
    x0 = result.trajectory[0, :nv].double().numpy()
    centre = tet_centroid(x0, result.tets.numpy())
    vel, omega = rigid_velocity(x0, result.velocities[0, :nv].double().numpy(), centre)
    gravity = np.asarray(result.config.gravity, dtype=np.float64)
    floor = scene.config.floor_height
    cams = [CaptureCamera(f"c{v:02d}", c.width, c.height, c.K.double().numpy(), np.zeros(5),
                          c.world_to_camera.double().numpy()) for v, c in enumerate(scene.cameras)]
    lead = lead_in(surface[0], centre, vel, omega, gravity, dt_s / step, lead_in_frames * step, floor, clearance, cams)
    vertices = np.concatenate([lead, surface]) if len(lead) else surface
    info = {"scene": str(scene_dir.resolve()), "scene_seed": syn.seed, "E": scene.config.metadata.get("E"),
            "nu": scene.config.metadata.get("nu"), "initial_velocity": vel.tolist(), "initial_omega": omega.tolist()}
    return CaptureMotion(torch.as_tensor(vertices, dtype=torch.float32), mesh.faces, mesh.uvs, mesh.texture,
                         scene.cameras, dt_s / step, float(floor), tuple(gravity.tolist()), len(lead), step, info)


def make_capture_twin(scene_dir: str | Path, out: str | Path, config: CaptureTwinConfig | None = None,
                      overwrite: bool = False, progress: bool = False) -> Path:
    """Write the capture twin of the ``make-scene`` folder ``scene_dir`` at ``out`` (see the module docstring)."""
    config = CaptureTwinConfig() if config is None else config
    motion = scene_motion(scene_dir, config.lead_in_frames, config.lead_in_clearance, config.frame_rate_scale)
    return write_capture(motion, out, config, overwrite=overwrite, progress=progress)


def read_truth(capture: str | Path) -> tuple[dict, np.ndarray]:
    """A twin's ``truth.json`` and its true coverage (V, T, H, W) float32 in [0, 1]."""
    capture = Path(capture)
    truth = json.loads((capture / TRUTH_DIR / TRUTH_JSON).read_text())
    with np.load(capture / TRUTH_DIR / ALPHA_NPZ, allow_pickle=False) as z:
        alpha = z["alpha"].astype(np.float32) / 255.0
    return truth, alpha

