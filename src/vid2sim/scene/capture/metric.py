"""The capture's metric, gravity-aligned frame: metres per calibration unit, the gravity direction and the floor,
measured on the object's motion (and on COLMAP's points, where the model has them), then the similarity that
takes the calibration frame to the scene format's SI, z-up frame.

1. **Track.** Per frame, the object's centre from the views where it is whole (not empty, not touching the
   border): silhouette centroids triangulated, then the centroid of the soft visual hull around it
   (:mod:`vid2sim.scene.capture.hull`).
2. **Gravity and scale.** The free-flight frames' parabola (:mod:`vid2sim.scene.capture.ballistic`): a is gravity
   in calibration units; direction ``â``, metres per unit ``|g| / |a|``.
3. **Floor.** The plane normal to gravity that the object rests on: with COLMAP points, the dense layer of points
   near the object's lowest contact height (a plane fit; its normal also sharpens the gravity direction when it
   agrees with the parabola's within ``floor_normal_agreement_deg``); without, the object's lowest point over the
   contact frames (the hull's, the median over those frames).
4. **Transform.** ``x_scene = s·R·x_cal + t``: R the smallest rotation taking â to −z, s the metres per unit, t
   putting the floor at z = 0 and the object's mean position over the scene's frames above the origin.

``--scale``, ``--gravity-axis`` and ``--floor`` replace the matching estimate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np

from vid2sim.scene.capture.ballistic import BallisticFit, BallisticSearch, find_ballistic, fit_segments, jackknife_sigma
from vid2sim.scene.capture.cameras import CaptureCamera
from vid2sim.scene.capture.floor import floor_from_plates
from vid2sim.scene.capture.hull import HullFrame, lowest_point, mask_centroids, soft_hull, triangulate


@dataclass
class MetricConfig:
    """Settings of the metric-frame estimate.

    Attributes:
        gravity: |g| in m/s² (9.81 at sea level; a synthetic world may use another value).
        hull_resolution: voxels per side of each frame's hull grid.
        hull_margin: the grid's half-size relative to the object's largest silhouette radius.
        ballistic: the free-flight search (:class:`~vid2sim.scene.capture.ballistic.BallisticSearch`).
        use_points: use COLMAP's 3D points for the floor.
        use_plates: without points, find the floor on the clean plates (:mod:`vid2sim.scene.capture.floor`).
        upright_cameras: the cameras stand roughly upright (image down within 60° of gravity on average): free fall
            is then told from a bounce's steady upward deceleration (``--gravity-axis`` for rigs that are not).
        floor_normal_agreement_deg: adopt the point floor's normal as the gravity direction when it is within this
            angle of the parabola's, or within 3 of the parabola's standard deviations (a short free flight's
            direction is uncertain; the floor's plane, from hundreds of points, is not).
        robust_hull_views: track the robust hull's centroid (one view's mask may disagree,
            :mod:`~vid2sim.scene.capture.hull`) in frames with at least this many whole views; 0: the strict hull's.
    """

    gravity: float = 9.81
    hull_resolution: int = 32
    hull_margin: float = 1.6
    ballistic: BallisticSearch = field(default_factory=BallisticSearch)
    use_points: bool = True
    use_plates: bool = True
    upright_cameras: bool = True
    floor_normal_agreement_deg: float = 10.0
    robust_hull_views: int = 4

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class Track:
    """The object's track in the calibration frame.

    Attributes:
        centres: (T, 3) the robust hull's centroids (NaN where fewer than two views see the whole object): what the
            free flight is fitted to.
        hulls: per frame its :class:`HullFrame` (None where not tracked).
        size: the object's diameter (calibration units; the median hull extent).
        strict_centres: (T, 3) the strict hull's centroids (the same as ``centres`` where the robust hull is off);
            the difference of the two fits measures how much the masks' errors move the scale.
    """

    centres: np.ndarray
    hulls: list[HullFrame | None]
    size: float
    strict_centres: np.ndarray | None = None

    def lowest_along(self, up: np.ndarray) -> np.ndarray:
        """(T,) the object's lowest height along ``up`` (NaN where not tracked)."""
        return np.array([lowest_point(h, up) if h is not None else np.nan for h in self.hulls])


def _object_radius(cameras: Sequence[CaptureCamera], area: np.ndarray, rough: np.ndarray,
                   usable: np.ndarray) -> float:
    """The object's largest radius in calibration units: its silhouettes' areas (V, T) at the rough depth of its
    triangulated centres (T, 3)."""
    radius = 0.0
    V, T = usable.shape
    for t in range(T):
        if not np.isfinite(rough[t]).all():
            continue
        for v in range(V):
            if usable[v, t]:
                depth = (cameras[v].world_to_camera[:3, :3] @ rough[t] + cameras[v].world_to_camera[:3, 3])[2]
                f = 0.5 * (cameras[v].K[0, 0] + cameras[v].K[1, 1])
                radius = max(radius, np.sqrt(area[v, t] / np.pi) * depth / f)
    return radius


def track_object(cameras: Sequence[CaptureCamera], masks: Sequence[np.ndarray], usable: np.ndarray,
                 config: MetricConfig) -> Track:
    """The object's :class:`Track` from each view's masks (T, H, W) — float in [0, 1] or uint8 coverage in 0..255 —
    and the usable (V, T) views of every frame: per frame the soft hull around the triangulated silhouette
    centroids, then again around its own centroid."""
    scale = [255.0 if m.dtype == np.uint8 else 1.0 for m in masks]
    V, T = usable.shape
    pix = np.zeros((V, T, 2))
    area = np.zeros((V, T))
    for v, m in enumerate(masks):
        pix[v], area[v] = mask_centroids(m.astype(np.float32) / scale[v])
    rough = triangulate(cameras, pix, usable)
    half = config.hull_margin * _object_radius(cameras, area, rough, usable)
    robust_views = config.robust_hull_views if config.robust_hull_views > 0 else V + 1
    centres = np.full((T, 3), np.nan)
    strict = np.full((T, 3), np.nan)
    hulls: list[HullFrame | None] = [None] * T
    extents = []
    for t in range(T):
        views = np.flatnonzero(usable[:, t])
        if len(views) < 2 or not np.isfinite(rough[t]).all():
            continue
        cams = [cameras[v] for v in views]
        frame = np.stack([masks[v][t].astype(np.float32) / scale[v] for v in views])
        hull = soft_hull(cams, frame, rough[t], half, max(16, config.hull_resolution // 2), robust_views)
        c = hull.centroid(robust=True)
        if not np.isfinite(c).all():
            continue
        hull = soft_hull(cams, frame, c, half, config.hull_resolution, robust_views)  # centred on the object
        c = hull.centroid(robust=True)
        if np.isfinite(c).all():  # (the strict hull may be empty where one view lost the object's middle)
            centres[t], strict[t] = c, hull.centroid()
            hulls[t] = hull
            extents.append(hull.extent())
    size = float(np.median(extents)) if extents else float("nan")
    return Track(centres, hulls, size, strict)


@dataclass
class FloorEstimate:
    """The floor plane {x : up·x = offset} in calibration units: its offset, std and where it came from; for a point
    floor also its own normal, that normal's std (degrees) and the number of points."""

    offset: float
    sigma: float
    source: str
    normal: np.ndarray | None = None
    normal_sigma_deg: float = float("nan")
    points: int = 0


def floor_from_points(points: np.ndarray, up: np.ndarray, near: float, size: float) -> FloorEstimate | None:
    """The dense horizontal layer of points (P, 3) within ±0.5·``size`` of the height ``near`` (along ``up``): its
    plane {x : normal·x = offset} (least squares over the inliers after a histogram mode; the offset is along the
    plane's own normal), or None when fewer than 20 points lie there."""
    if len(points) < 20 or not np.isfinite(near):
        return None
    h = points @ up
    sel = np.abs(h - near) < 0.5 * size
    if sel.sum() < 20:
        return None
    hs = h[sel]
    bins = max(10, int(sel.sum() ** 0.5))
    counts, edges = np.histogram(hs, bins=bins)
    k = int(np.argmax(counts))
    mode = 0.5 * (edges[k] + edges[k + 1])
    width = edges[1] - edges[0]
    inl = sel & (np.abs(h - mode) < 2 * width)
    for _ in range(3):
        P = points[inl]
        c = P.mean(0)
        _, _, vt = np.linalg.svd(P - c)
        n = vt[2] * np.sign(vt[2] @ up)
        d = (points - c) @ n
        mad = 1.4826 * np.median(np.abs(d[inl])) + 1e-12
        inl = sel & (np.abs(d) < 3 * mad)
        if inl.sum() < 20:
            return None
    P = points[inl]
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c)
    n = vt[2] * np.sign(vt[2] @ up)
    resid = (P - c) @ n
    sigma = float(resid.std() / np.sqrt(len(P)))
    # a tilt of the plane by θ moves points at distance r by r·θ: std(θ) ≈ σ / (rms(r) √N)
    spread = float(np.sqrt((np.linalg.norm((P - c) - np.outer(resid, n), axis=1) ** 2).mean()))
    normal_sigma = float(np.degrees(resid.std() / max(spread, 1e-12) / np.sqrt(len(P))))
    return FloorEstimate(float(c @ n), sigma, "colmap points", n, normal_sigma, int(inl.sum()))


def floor_from_contact(track: Track, up: np.ndarray, flight: Sequence[int]) -> FloorEstimate | None:
    """The object's lowest height (along ``up``) over the tracked frames not in free flight, at and after its first
    contact: the median, and its spread as the std."""
    low = track.lowest_along(up)
    tracked = np.flatnonzero(np.isfinite(low))
    if len(tracked) == 0:
        return None
    flight = set(flight)
    contact = [t for t in tracked if t not in flight and t > min(flight, default=-1)] or \
              [t for t in tracked if t not in flight] or list(tracked)
    vals = low[contact]
    # only the frames near the lowest level (the object resting or pressed on the floor)
    level = np.percentile(vals, 25)
    near = vals[vals <= level + 0.05 * track.size]
    return FloorEstimate(float(np.median(near)), float(1.4826 * np.median(np.abs(near - np.median(near))) /
                                                       np.sqrt(max(len(near), 1)) + 1e-12), "object contact")


def rotation_to_down(direction: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking the unit vector ``direction`` to (0, 0, −1)."""
    a = direction / np.linalg.norm(direction)
    b = np.array([0.0, 0.0, -1.0])
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


@dataclass
class MetricFrame:
    """The calibration → scene similarity and the estimates behind it.

    Attributes:
        scale: metres per calibration unit; scale_sigma: its std; scale_source: ``"free flight"`` or ``"user"``;
            scale_sigma_parts: the std's parts relative to the scale (``fit``, ``jackknife``, ``centre``).
        down: (3,) unit gravity direction in the calibration frame; down_sigma_deg: its std (degrees);
            down_source: ``"free flight"``, ``"floor (colmap points)"``, ``"floor (plates)"`` or ``"user"``.
        floor: the :class:`FloorEstimate` (calibration units along up = −down).
        rotation: (3, 3); translation: (3,): x_scene = scale · rotation @ x_cal + translation.
        ballistic: the free-flight fit, if any.
        gravity: |g| used (m/s²).
        notes: what the estimates found worth saying (the import prints them as warnings).
        flight_clearance: the object's lowest point above the floor over the measured free flight, as a share of
            its size (:func:`flight_clearance`; NaN when the scale is the user's).
    """

    scale: float
    scale_sigma: float
    scale_source: str
    down: np.ndarray
    down_sigma_deg: float
    down_source: str
    floor: FloorEstimate
    rotation: np.ndarray
    translation: np.ndarray
    ballistic: BallisticFit | None
    gravity: float
    notes: list[str] = field(default_factory=list)
    scale_sigma_parts: dict[str, float] = field(default_factory=dict)
    flight_clearance: float = float("nan")

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) x_scene = M @ [x_cal, 1]."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def points(self, x: np.ndarray) -> np.ndarray:
        """Calibration points (N, 3) → scene points (N, 3)."""
        return self.scale * x @ self.rotation.T + self.translation

    def camera(self, world_to_camera: np.ndarray) -> np.ndarray:
        """A calibration-frame world-to-camera (4, 4) → the scene frame's (metres)."""
        R = world_to_camera[:3, :3] @ self.rotation.T
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = self.scale * world_to_camera[:3, 3] - R @ self.translation
        return M

    def to_json(self) -> dict[str, Any]:
        b = self.ballistic
        return {
            "calibration_to_scene": self.matrix.tolist(),
            "metres_per_unit": {"value": self.scale, "sigma": self.scale_sigma, "source": self.scale_source,
                                "sigma_parts_relative": self.scale_sigma_parts},
            "gravity_direction_calibration": {"value": self.down.tolist(), "sigma_deg": self.down_sigma_deg,
                                              "source": self.down_source},
            "floor_calibration": {"offset": self.floor.offset, "sigma": self.floor.sigma, "source": self.floor.source,
                                  "normal": None if self.floor.normal is None else self.floor.normal.tolist(),
                                  "points": self.floor.points, "normal_sigma_deg": self.floor.normal_sigma_deg,
                                  "sigma_m": self.floor.sigma * self.scale},
            "gravity_m_s2": self.gravity,
            "free_flight": None if b is None else {
                "segments": b.segments, "frames": len(b.frames), "acceleration_units": b.acceleration.tolist(),
                "residual_units": b.residual, "noise_units": b.noise, "direction_fixed": b.direction_fixed,
                "clearance_over_size": None if not np.isfinite(self.flight_clearance) else self.flight_clearance},
            "notes": self.notes,
        }


def trim_contact(track: Track, fit: BallisticFit, dt: float, up: np.ndarray, floor: float) -> list[list[int]]:
    """The free-flight segments without the frames in which the object would touch the floor: its lowest point,
    carried along the fitted parabola from where the hull puts it relative to the centre (median over the
    segment), at or below the floor plane {x : up·x = floor}. The hull's lowest point lies a little below the
    object's, so this errs on the side of dropping a frame. Segments left with fewer than 4 frames go, unless none
    would be left."""
    low = track.lowest_along(up)
    out = []
    for seg in fit.segments:
        f = np.array(seg)
        offset = np.nanmedian(low[f] - track.centres[f] @ up)
        t0 = np.mean(seg)
        ts = (f - t0) * dt
        y = track.centres[f] - 0.5 * np.outer(ts * ts, fit.acceleration)
        coef, *_ = np.linalg.lstsq(np.stack([np.ones_like(ts), ts], 1), y, rcond=None)
        path = coef[0] + np.outer(ts, coef[1]) + 0.5 * np.outer(ts * ts, fit.acceleration)
        keep = [int(k) for k, p in zip(f, path) if p @ up + offset > floor]
        out.append(keep)
    long_enough = [s for s in out if len(s) >= 4]
    return long_enough or [s for s in out if len(s) >= 3] or fit.segments


def cameras_down(cameras: Sequence[CaptureCamera]) -> np.ndarray:
    """(3,) the cameras' mean image-down axis in the calibration frame (each camera's +y), unit: roughly gravity's
    direction when the cameras stand upright."""
    d = np.sum([c.rotation[1] for c in cameras], axis=0)
    return d / max(np.linalg.norm(d), 1e-12)


class NoFreeFlight(Exception):
    """No free-flight frames to measure gravity on."""


def _fit_free_flight(track: Track, dt: float, config: MetricConfig, down: np.ndarray | None,
                     cameras: Sequence[CaptureCamera] | None) -> BallisticFit:
    """The free-flight fit (:func:`~vid2sim.scene.capture.ballistic.find_ballistic`) along a known ``down``, if any.

    Raises:
        NoFreeFlight: none shows.
    """
    rough = cameras_down(cameras) if cameras is not None and config.upright_cameras else None
    fit = find_ballistic(track.centres, dt, track.lowest_along, track.size, config.ballistic, direction=down,
                         rough_down=rough)
    if fit is None:
        raise NoFreeFlight("no free-flight frames")
    return fit


def _floor_plane(track: Track, up: np.ndarray, contact: FloorEstimate, config: MetricConfig,
                 points: np.ndarray | None, cameras: Sequence[CaptureCamera] | None,
                 plates: Sequence[np.ndarray] | None) -> FloorEstimate | None:
    """The floor's plane with its own normal: from COLMAP's points near the contact height, else from the clean
    plates; None when neither finds one."""
    if config.use_points and points is not None and len(points):
        plane = floor_from_points(points, up, contact.offset, track.size)
        if plane is not None:
            return plane
    if config.use_plates and plates is not None and cameras is not None and all(p is not None for p in plates):
        centre = np.nanmedian(track.centres, axis=0)
        found = floor_from_plates(cameras, plates, up, contact.offset, centre, 1.5 * track.size, 0.15 * track.size)
        if found is not None:
            return FloorEstimate(found.offset, found.sigma, "plates", found.normal, found.normal_sigma_deg, 0)
    return None


@dataclass
class _Gravity:
    """The gravity direction as it stands: unit ``down`` (3,), its std (degrees) and where it came from."""

    down: np.ndarray
    sigma_deg: float
    source: str

    @property
    def up(self) -> np.ndarray:
        return -self.down


def _measure_floor(track: Track, gravity: _Gravity, fit: BallisticFit | None, config: MetricConfig,
                   points: np.ndarray | None, cameras: Sequence[CaptureCamera] | None,
                   plates: Sequence[np.ndarray] | None, notes: list[str]) -> tuple[FloorEstimate, _Gravity]:
    """The floor (calibration units along up), and the gravity direction — the floor plane's normal instead of the
    free flight's where the two agree (``config.floor_normal_agreement_deg``, or 3 of the flight's σ)."""
    up = gravity.up
    contact = floor_from_contact(track, up, fit.frames if fit is not None else [])
    plane = _floor_plane(track, up, contact, config, points, cameras, plates) if contact is not None else None
    if plane is not None and plane.normal is not None:
        angle = float(np.degrees(np.arccos(np.clip(plane.normal @ up, -1, 1))))
        consistent = angle <= config.floor_normal_agreement_deg or angle <= 3.0 * gravity.sigma_deg
        if gravity.source == "free flight" and consistent:
            notes.append(f"gravity direction from the floor's normal ({plane.source}; {angle:.2f} deg from the "
                         "free-flight estimate)")
            return plane, _Gravity(-plane.normal, plane.normal_sigma_deg, f"floor ({plane.source})")
        if gravity.source == "free flight":
            notes.append(f"the floor's normal ({plane.source}) is {angle:.2f} deg from the free-flight gravity "
                         "direction; kept the free-flight direction")
        # the plane's height along the kept up direction, under the object
        foot = np.nanmedian(track.centres, axis=0)
        height = float(foot @ up) + (plane.offset - float(foot @ plane.normal)) / max(float(plane.normal @ up), 1e-6)
        return FloorEstimate(height, plane.sigma, plane.source, plane.normal, plane.normal_sigma_deg,
                             plane.points), gravity
    if contact is not None:
        return contact, gravity
    notes.append("no contact frames: the floor is put at the object's lowest centre")
    return FloorEstimate(float(np.nanmin(track.centres @ up)), float("nan"), "lowest centre"), gravity


def _measure_scale(track: Track, fit: BallisticFit, dt: float, gravity: _Gravity, floor: FloorEstimate,
                   config: MetricConfig, notes: list[str]) -> tuple[float, float, dict[str, float], BallisticFit]:
    """Metres per unit from the free flight, its std and the std's parts (relative), and the final fit.

    Free-flight frames in which the object, on its fitted parabola, would already reach the floor are dropped (a
    soft object's first contact frames bend its path too little to be told from the parabola); the fit is
    repeated along the final direction when that came from the floor. The std combines (in quadrature) the fit's
    own (from its residuals), the block jackknife's over its frames, and the change of |a| between the robust and
    the strict hull's centres (how much one view's mask errors can move it)."""
    segments = trim_contact(track, fit, dt, gravity.up, floor.offset)
    direction = gravity.down if gravity.source.startswith("floor") else None
    if segments != fit.segments:
        notes.append(f"free-flight frames {sorted(set(fit.frames) - {f for s in segments for f in s})} "
                     "dropped: the object reaches the floor there")
    if segments != fit.segments or direction is not None:
        fit = fit_segments(track.centres, dt, segments, direction=direction, noise=fit.noise)
    a = float(np.linalg.norm(fit.acceleration))
    parts = {"fit": fit.magnitude_sigma() / a,
             "jackknife": jackknife_sigma(track.centres, dt, segments, direction, fit.noise) / a}
    if track.strict_centres is not None:
        finite = np.isfinite(track.strict_centres).all(1)
        kept = [[f for f in s if finite[f]] for s in segments]
        kept = [s for s in kept if len(s) >= 3]
        if kept:
            strict = fit_segments(track.strict_centres, dt, kept, direction=direction, noise=fit.noise)
            parts["centre"] = abs(float(np.linalg.norm(strict.acceleration)) - a) / a
    rel = float(np.sqrt(sum(v * v for v in parts.values() if np.isfinite(v))))
    value = config.gravity / a
    return value, value * rel, parts, fit


def flight_clearance(track: Track, frames: Sequence[int], up: np.ndarray, floor: float) -> float:
    """The object's lowest point above the floor {x : up·x = floor} over ``frames``, as a share of its size: the
    median over the tracked frames (NaN when none is tracked)."""
    heights = track.lowest_along(up)[list(frames)] - floor
    heights = heights[np.isfinite(heights)]
    if len(heights) == 0 or not track.size > 0:
        return float("nan")
    return float(np.median(heights)) / track.size


def solve_metric_frame(track: Track, dt: float, config: MetricConfig, scene_frames: range,
                       points: np.ndarray | None = None, scale: float | None = None,
                       down: np.ndarray | None = None, floor: float | None = None,
                       cameras: Sequence[CaptureCamera] | None = None,
                       plates: Sequence[np.ndarray] | None = None) -> MetricFrame:
    """Measure (or take from the user) scale, gravity direction and floor, and build the similarity.

    Args:
        track: the object's track; dt: seconds per frame; scene_frames: the frames the scene keeps (the origin
            goes under the object's mean position over them).
        points: (P, 3) COLMAP points or None.
        cameras, plates: the undistorted cameras and their clean plates (H, W, 3), for the floor where there are no
            points (:func:`vid2sim.scene.capture.floor.floor_from_plates`).
        scale, down, floor: the user's metres per unit, gravity direction (3,) and floor offset along −down.

    Raises:
        NoFreeFlight: the scale or the direction has to be measured and no free flight shows.
    """
    notes: list[str] = []
    if down is not None:
        down = np.asarray(down, dtype=np.float64)
        down = down / np.linalg.norm(down)
    fit = _fit_free_flight(track, dt, config, down, cameras) if scale is None or down is None else None
    if down is None:
        assert fit is not None
        gravity = _Gravity(fit.acceleration / np.linalg.norm(fit.acceleration), fit.direction_sigma_deg(),
                           "free flight")
    else:
        gravity = _Gravity(down, 0.0, "user")
    if floor is not None:
        floor_est = FloorEstimate(float(floor), 0.0, "user")
    else:
        floor_est, gravity = _measure_floor(track, gravity, fit, config, points, cameras, plates, notes)
    parts: dict[str, float] = {}
    if scale is None:
        assert fit is not None
        scale_val, scale_sigma, parts, fit = _measure_scale(track, fit, dt, gravity, floor_est, config, notes)
        scale_source = "free flight"
        clearance = flight_clearance(track, fit.frames, gravity.up, floor_est.offset)
    else:
        scale_val, scale_sigma, scale_source, clearance = float(scale), 0.0, "user", float("nan")
    R = rotation_to_down(gravity.down)
    centres = track.centres[[t for t in scene_frames if np.isfinite(track.centres[t]).all()]]
    centre = centres.mean(0) if len(centres) else np.nanmean(track.centres, axis=0)
    rc = scale_val * R @ centre
    translation = np.array([-rc[0], -rc[1], -scale_val * floor_est.offset])
    return MetricFrame(scale_val, scale_sigma, scale_source, gravity.down, gravity.sigma_deg, gravity.source,
                       floor_est, R, translation, fit, config.gravity, notes, parts, clearance)
