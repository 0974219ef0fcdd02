"""Scenarios for ``vid2sim simulate``: what happens to a reconstructed asset, checked before any work.

A :class:`Scenario` is plain data (docs/scenarios.md gives every field, its unit and default). Its defaults
are **the captured drop**: the asset's frame time, floor, initial velocity and recovered material, seen by
the cameras of the scene it was reconstructed from. Any field may be changed:

* ``frames`` (video frames written, the initial one included) and ``dt`` (s per frame);
* ``floor``: none, static, or moving / tilted (:class:`~vid2sim.physics.external.MovingFloor`);
* ``obstacles``: fixed sphere obstacles;
* ``initial``: a new pose (rotation about the object's centre of mass, then a translation) and/or a new
  linear / angular velocity;
* ``material``: the captured one with other E, ν, density or damping, or a named preset — ``plasticine``
  (StVK + von Mises, τ_Y = 500 Pa), ``sand`` (StVK + Drucker–Prager, θ_f = 10°), ``soft`` (E = 8 000 Pa,
  ν = 0.4) and ``stiff`` (E = 1e7 Pa, ν = 0.49), the settings of the paper's supplementary figure;
* ``cameras``: the source scene's (or another scene folder's), a ``ring`` of views, or an ``orbit`` (one
  camera circling over the frames); ``resolution`` and ``background``.

:meth:`Scenario.from_yaml` / :meth:`Scenario.to_yaml` read and write it; :meth:`Scenario.set` overrides one
field and remembers who set it (a command-line flag), so that every error names the flag or the YAML file
and key it came from. :meth:`Scenario.validate` checks the fields alone;
:func:`~vid2sim.simulate.resolve.resolve_scenario` checks them against the asset (a floor above the object, an
obstacle overlapping it, cameras that do not see it) and returns a
:class:`~vid2sim.simulate.resolve.ResolvedScenario` — concrete externals, material, initial state and cameras
(:mod:`vid2sim.simulate.cameras`) — so that nothing is simulated until the whole scenario makes sense. Errors
are :class:`ScenarioError` (a ``ValueError``), one line each.

This module holds the data: the scenario's dataclasses, their reading from YAML and their validation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

from vid2sim.runtime.errors import InputError

__all__ = [
    "ScenarioError",
    "FloorSpec",
    "ObstacleSpec",
    "InitialSpec",
    "MaterialSpec",
    "CameraSpec",
    "Scenario",
    "MATERIAL_PRESETS",
    "CAMERA_TYPES",
]

#: named materials. ``elastic`` is the asset's recovered (neo-Hookean) material; the others follow the paper's
#: supplementary "Generalized to Different Materials" (figure caption: stiff E = 1e7, ν = 0.49; soft E = 8000,
#: ν = 0.4; plasticine τ_Y = 500 Pa; sand θ_f = 10°; plasticine and sand with the StVK energy). The paper gives
#: no E or ν for plasticine and sand, so those keep the asset's recovered E and ν unless overridden.
MATERIAL_PRESETS: dict[str, dict[str, Any]] = {
    "elastic": {"model": "neo_hookean"},
    "plasticine": {"model": "stvk", "yield_stress": 500.0},
    "sand": {"model": "stvk", "friction_angle_deg": 10.0},
    "soft": {"model": "neo_hookean", "youngs_modulus": 8000.0, "poisson_ratio": 0.4},
    "stiff": {"model": "neo_hookean", "youngs_modulus": 1e7, "poisson_ratio": 0.49},
}
CAMERA_TYPES = ("scene", "ring", "orbit")
ELASTIC_MODEL_NAMES = ("neo_hookean", "stvk")
MAX_RESOLUTION = 8192


class ScenarioError(InputError):
    """A scenario that makes no sense; the one-line message names the field (and its file or flag)."""


# =============================================================================================
# the data
# =============================================================================================


@dataclass
class FloorSpec:
    """The floor: a plane below the object, static or moving / tilted (z up, SI units).

    Attributes:
        enabled: None (default) keeps the captured floor (on when the asset has one, or when ``height`` is
            given); False removes it; True needs a height (given, or the asset's).
        height: m, the plane's height under the pivot at t = 0 (default: the asset's floor height).
        stiffness: Pa per metre of penetration on the contact points' areas (default: the asset's).
        friction: the floor's Coulomb coefficient μ ≥ 0 (default: the asset's; 0 is frictionless).
        velocity: m/s, vertical velocity of the plane.
        amplitude: m, amplitude of a vertical oscillation; frequency: its frequency in Hz.
        tilt_deg: degrees, the plane's tilt at t = 0 (|tilt| < 90); tilt_rate_deg: degrees/s.
        tilt_axis: the horizontal axis it tilts about (x, y[, 0]); right-hand rule, so a positive tilt about
            +x lowers the plane towards −y.
        pivot_xy: m, the (x, y) point the plane turns about (default: under the object's centre of mass at
            t = 0, so ``height`` is the floor's height under the object).
    With every motion parameter 0 the floor is the static :class:`~vid2sim.physics.external.Floor`.
    """

    enabled: bool | None = None
    height: float | None = None
    stiffness: float | None = None
    friction: float | None = None
    velocity: float = 0.0
    amplitude: float = 0.0
    frequency: float = 0.0
    tilt_deg: float = 0.0
    tilt_rate_deg: float = 0.0
    tilt_axis: tuple[float, ...] = (1.0, 0.0, 0.0)
    pivot_xy: tuple[float, float] | None = None

    @property
    def moving(self) -> bool:
        """Whether the plane moves or tilts (else it is a static floor)."""
        return any(getattr(self, k) != 0 for k in ("velocity", "amplitude", "tilt_deg", "tilt_rate_deg"))


@dataclass
class ObstacleSpec:
    """A fixed solid sphere.

    Attributes:
        center: (x, y, z) in m.
        radius: m (> 0).
        stiffness: Pa per metre of penetration (default: the asset's floor stiffness).
        friction: Coulomb coefficient μ ≥ 0 (default: the asset's floor friction).
    """

    center: tuple[float, float, float]
    radius: float
    stiffness: float | None = None
    friction: float | None = None


@dataclass
class InitialSpec:
    """The state at t = 0: the object's rest shape moved rigidly, moving rigidly.

    Attributes:
        euler_deg: (rx, ry, rz) degrees, rotations about the world x, then y, then z axes (R = Rz Ry Rx),
            through the object's centre of mass. None: no rotation.
        axis_angle: (ax, ay, az, degrees), a rotation about that axis through the centre of mass
            (instead of ``euler_deg``). None: no rotation.
        translation: (dx, dy, dz) m, added after the rotation.
        linear_velocity: (vx, vy, vz) m/s of the centre of mass; None: the captured one.
        angular_velocity: (wx, wy, wz) rad/s about the centre of mass; None: the captured one.
    """

    euler_deg: tuple[float, float, float] | None = None
    axis_angle: tuple[float, float, float, float] | None = None
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    linear_velocity: tuple[float, float, float] | None = None
    angular_velocity: tuple[float, float, float] | None = None


@dataclass
class MaterialSpec:
    """The material: a named preset, then any overrides.

    Attributes:
        preset: ``elastic`` (the asset's recovered material), ``plasticine``, ``sand``, ``soft``, ``stiff``
            (:data:`MATERIAL_PRESETS`).
        youngs_modulus: E in Pa (default: the preset's, else the asset's).
        poisson_ratio: ν in (−1, 0.5) (default: the preset's, else the asset's).
        density: kg/m³ (default: the asset's).
        damping_ratio: ζ ≥ 0 of the Kelvin–Voigt damping (default: the asset's).
        model: elastic energy ``neo_hookean`` or ``stvk`` (default: the preset's).
        yield_stress: Pa, τ_Y of plasticine's von Mises yield (only with ``plasticine``; default 500).
        friction_angle_deg: θ_f of sand's Drucker–Prager yield, degrees in (0, 90) (only with ``sand``;
            default 10).
    """

    preset: str = "elastic"
    youngs_modulus: float | None = None
    poisson_ratio: float | None = None
    density: float | None = None
    damping_ratio: float | None = None
    model: str | None = None
    yield_stress: float | None = None
    friction_angle_deg: float | None = None


@dataclass
class CameraSpec:
    """Which cameras render the simulation.

    Attributes:
        type: ``scene`` (the cameras of a scene folder), ``ring`` (``views`` cameras evenly spaced on a
            horizontal circle, looking at ``target``) or ``orbit`` (one camera going ``turns`` times round
            that circle over the frames). None (default): ``scene`` when the asset's source scene can be
            read, else ``ring``.
        scene: scene folder whose cameras to use (default: the asset's source scene).
        views: ring cameras (default 4).
        radius: m, horizontal distance from ``target`` (default: far enough to see, with ``fov_deg``, the
            object over its whole simulated motion and the floor under it).
        height: m, camera height above ``target`` (default: a 20° elevation).
        target: (x, y, z) m the cameras look at (default: above the centre of the simulated motion, halfway
            between the floor and the object's highest point).
        fov_deg: horizontal field of view, degrees (default 40).
        azimuth_deg: azimuth of the first ring camera / of the orbit's start, degrees from +x.
        turns: orbit revolutions over the frames (default 1; negative turns clockwise).
    """

    type: str | None = None
    scene: str | None = None
    views: int = 4
    radius: float | None = None
    height: float | None = None
    target: tuple[float, float, float] | None = None
    fov_deg: float = 40.0
    azimuth_deg: float = 0.0
    turns: float = 1.0


# field path → (kind, extra). kinds: float, int, bool, str, path, vec (extra = allowed lengths)
_FLOOR_SCHEMA = {"enabled": ("bool", None), "height": ("float", None), "stiffness": ("float", None),
                 "friction": ("float", None),
                 "velocity": ("float", None), "amplitude": ("float", None), "frequency": ("float", None),
                 "tilt_deg": ("float", None), "tilt_rate_deg": ("float", None), "tilt_axis": ("vec", (2, 3)),
                 "pivot_xy": ("vec", (2,))}
_OBSTACLE_SCHEMA = {"center": ("vec", (3,)), "radius": ("float", None), "stiffness": ("float", None),
                    "friction": ("float", None)}
_INITIAL_SCHEMA = {"euler_deg": ("vec", (3,)), "axis_angle": ("vec", (4,)), "translation": ("vec", (3,)),
                   "linear_velocity": ("vec", (3,)), "angular_velocity": ("vec", (3,))}
_MATERIAL_SCHEMA = {"preset": ("str", None), "youngs_modulus": ("float", None), "poisson_ratio": ("float", None),
                    "density": ("float", None), "damping_ratio": ("float", None), "model": ("str", None),
                    "yield_stress": ("float", None), "friction_angle_deg": ("float", None)}
_CAMERA_SCHEMA = {"type": ("str", None), "scene": ("path", None), "views": ("int", None),
                  "radius": ("float", None), "height": ("float", None), "target": ("vec", (3,)),
                  "fov_deg": ("float", None), "azimuth_deg": ("float", None), "turns": ("float", None)}
_TOP_SCHEMA = {"frames": ("int", None), "dt": ("float", None), "resolution": ("int", None),
               "background": ("background", None)}
_SECTIONS = {"floor": (FloorSpec, _FLOOR_SCHEMA), "initial": (InitialSpec, _INITIAL_SCHEMA),
             "material": (MaterialSpec, _MATERIAL_SCHEMA), "cameras": (CameraSpec, _CAMERA_SCHEMA)}
_EXPECTED = {"float": "a number", "int": "an integer", "bool": "true or false", "str": "a name",
             "path": "a folder path", "background": "a grey level in [0, 1] or [r, g, b] in [0, 1]"}


@dataclass
class Scenario:
    """A simulation of an asset in a new situation (module docstring; docs/scenarios.md).

    Attributes:
        frames: video frames written, the initial state included (default: the frames of the asset's source
            scene when it can be read, else the asset's observed frames, else 24); ``frames − 1`` are simulated.
        dt: seconds per frame (default: the asset's).
        floor, obstacles, initial, material, cameras: see :class:`FloorSpec`, :class:`ObstacleSpec`,
            :class:`InitialSpec`, :class:`MaterialSpec`, :class:`CameraSpec`.
        resolution: image width in pixels (square for ring/orbit; scene cameras keep their aspect ratio;
            default: the source scene's width, else 256).
        background: grey level in [0, 1] or (r, g, b) (default 1: white, as the scenes).
        origins: who set each field — a dotted path (``material.poisson_ratio``, ``obstacles[0].radius``) →
            ``"FILE: key"`` or ``"--flag"`` — for error messages (not part of the scenario's value).
    """

    frames: int | None = None
    dt: float | None = None
    floor: FloorSpec = field(default_factory=FloorSpec)
    obstacles: list[ObstacleSpec] = field(default_factory=list)
    initial: InitialSpec = field(default_factory=InitialSpec)
    material: MaterialSpec = field(default_factory=MaterialSpec)
    cameras: CameraSpec = field(default_factory=CameraSpec)
    resolution: int | None = None
    background: float | tuple[float, float, float] = 1.0
    origins: dict[str, str] = field(default_factory=dict, repr=False, compare=False)

    # ---- provenance ------------------------------------------------------------------------------
    def where(self, path: str) -> str:
        """Who set the field at ``path``: ``"--flag"``, ``"FILE: path"``, or ``"path (default)"``."""
        origin = self.origins.get(path)
        if origin is None and path.startswith("obstacles["):
            origin = self.origins.get(path.split(".")[0])
            if origin is not None and origin.startswith("--"):
                return origin
            if origin is not None:
                return f"{origin}.{path.split('.', 1)[1]}" if "." in path else origin
        return origin if origin is not None else f"{path} (default)"

    def error(self, path: str, value: Any, message: str) -> ScenarioError:
        """A :class:`ScenarioError` ``"<where> <value>: <message>"`` for the field at ``path``."""
        where = self.where(path)
        sep = " " if where.startswith("--") else " = "
        return ScenarioError(f"{where}{sep}{_show(value)}: {message}")

    # ---- access by path --------------------------------------------------------------------------
    def get(self, path: str) -> Any:
        """The value at a dotted path (``"material.poisson_ratio"``, ``"frames"``)."""
        obj: Any = self
        for part in path.split("."):
            obj = getattr(obj, part)
        return obj

    def set(self, path: str, value: Any, origin: str | None = None) -> "Scenario":
        """Set the field at a dotted path (e.g. from a command-line flag ``origin="--nu"``); returns self.

        ``path = "obstacles"`` replaces the whole list (a list of :class:`ObstacleSpec` or mappings)."""
        if path == "obstacles":
            value = [_obstacle_from_mapping(o, f"{origin or 'scenario'}: obstacles[{i}]") for i, o in enumerate(value)]
            for key in [k for k in self.origins if k.startswith("obstacles[")]:
                del self.origins[key]
            for i in range(len(value)):
                if origin is not None:
                    self.origins[f"obstacles[{i}]"] = origin
            self.obstacles = value
            return self
        parts = path.split(".")
        obj: Any = self
        for part in parts[:-1]:
            obj = getattr(obj, part, None)
        if obj is None or not hasattr(obj, parts[-1]) or parts[-1] == "origins":
            raise ScenarioError(f"{origin or 'scenario'}: unknown scenario field {path!r}")
        setattr(obj, parts[-1], value)
        if origin is not None:
            self.origins[path] = origin
        return self

    # ---- (de)serialisation -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain YAML/JSON-ready data (tuples as lists; unset defaults as null)."""

        def plain(x: Any) -> Any:
            if isinstance(x, (tuple, list)):
                return [plain(v) for v in x]
            return x

        out: dict[str, Any] = {}
        for f in fields(self):
            if f.name == "origins":
                continue
            value = getattr(self, f.name)
            if f.name == "obstacles":
                out[f.name] = [{k.name: plain(getattr(o, k.name)) for k in fields(o)} for o in value]
            elif f.name in _SECTIONS:
                out[f.name] = {k.name: plain(getattr(value, k.name)) for k in fields(value)}
            else:
                out[f.name] = plain(value)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, source: str = "scenario") -> "Scenario":
        """Build from plain data (a parsed YAML file called ``source`` in messages). Unknown keys and
        values of the wrong type raise :class:`ScenarioError` naming the key and ``source``.

        Shorthands: ``floor: null`` or ``floor: false`` (no floor), ``material: plasticine`` (a preset),
        ``cameras: ring`` (a type)."""
        scenario = cls()
        if data is None:
            return scenario
        if not isinstance(data, Mapping):
            raise ScenarioError(f"{source}: the top level must be a mapping of scenario fields "
                                f"({', '.join(_top_keys())}), got {_show(data)}")
        for key, value in data.items():
            if key not in _top_keys():
                raise ScenarioError(f"{source}: unknown key {key!r} (expected one of {', '.join(_top_keys())})")
            if key in _TOP_SCHEMA:
                scenario.set(key, _coerce(value, _TOP_SCHEMA[key], f"{source}: {key}"), f"{source}: {key}")
            elif key == "obstacles":
                if value is None:
                    value = []
                if not isinstance(value, list):
                    raise ScenarioError(f"{source}: obstacles: expected a list of spheres "
                                        f"({{center: [x, y, z], radius: r}}), got {_show(value)}")
                scenario.obstacles = [_obstacle_from_mapping(o, f"{source}: obstacles[{i}]")
                                      for i, o in enumerate(value)]
                for i in range(len(value)):
                    scenario.origins[f"obstacles[{i}]"] = f"{source}: obstacles[{i}]"
            else:
                _section_from_data(scenario, key, value, source)
        return scenario

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Scenario":
        """Read a scenario YAML file (docs/scenarios.md); errors name the file and the key."""
        import yaml

        path = Path(path)
        if not path.is_file():
            raise ScenarioError(f"{path}: scenario file not found")
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            first = str(exc).strip().splitlines()
            raise ScenarioError(f"{path}: not valid YAML ({' '.join(s.strip() for s in first[:3])})") from None
        return cls.from_dict(data, str(path))

    def to_yaml(self, path: str | Path | None = None) -> str:
        """The scenario as YAML text (written to ``path`` when given)."""
        import yaml

        class _Dumper(yaml.SafeDumper):
            pass

        def vector(dumper: yaml.SafeDumper, data: list) -> yaml.Node:  # numbers on one line, mappings as blocks
            flow = all(not isinstance(v, (dict, list)) for v in data)
            return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)

        _Dumper.add_representer(list, vector)
        text = yaml.dump(self.to_dict(), Dumper=_Dumper, sort_keys=False, default_flow_style=False)
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text

    # ---- checks ----------------------------------------------------------------------------------
    def validate(self) -> "Scenario":
        """Check every field on its own (types, ranges, combinations); returns self.

        Raises:
            ScenarioError: the first problem, naming the field and where it was set.
        """
        for key, spec in _TOP_SCHEMA.items():
            setattr(self, key, _coerce(getattr(self, key), spec, self.where(key)))
        if self.frames is not None and self.frames < 1:
            raise self.error("frames", self.frames, "expected at least 1 frame (the initial state counts as one)")
        _positive(self, "dt", "seconds per frame")
        if self.resolution is not None and not 8 <= self.resolution <= MAX_RESOLUTION:
            raise self.error("resolution", self.resolution, f"expected an image width of 8 to {MAX_RESOLUTION} pixels")
        for name, (_, schema) in _SECTIONS.items():
            section = getattr(self, name)
            for key, spec in schema.items():
                path = f"{name}.{key}"
                setattr(section, key, _coerce(getattr(section, key), spec, self.where(path)))
        for i, o in enumerate(self.obstacles):
            if not isinstance(o, ObstacleSpec):
                raise self.error(f"obstacles[{i}]", o, "expected a sphere {center: [x, y, z], radius: r}")
            for key, spec in _OBSTACLE_SCHEMA.items():
                setattr(o, key, _coerce(getattr(o, key), spec, self.where(f"obstacles[{i}].{key}")))
        self._validate_floor()
        self._validate_obstacles()
        self._validate_initial()
        self._validate_material()
        self._validate_cameras()
        return self

    def _validate_floor(self) -> None:
        f = self.floor
        _finite(self, "floor.height", "m")
        _positive(self, "floor.stiffness", "Pa per metre of penetration")
        _friction(self, "floor.friction", f.friction)
        for key in ("velocity", "amplitude", "tilt_rate_deg"):
            _finite(self, f"floor.{key}", "")
        if not (math.isfinite(f.frequency) and f.frequency >= 0):
            raise self.error("floor.frequency", f.frequency, "expected a frequency >= 0 Hz")
        if not (math.isfinite(f.tilt_deg) and abs(f.tilt_deg) < 90):
            raise self.error("floor.tilt_deg", f.tilt_deg, "expected a tilt in degrees with |tilt| < 90")
        axis = tuple(f.tilt_axis)
        if len(axis) == 2:
            axis = (axis[0], axis[1], 0.0)
        if axis[2] != 0 or math.hypot(axis[0], axis[1]) == 0:
            raise self.error("floor.tilt_axis", f.tilt_axis, "expected a nonzero horizontal axis (x, y) or (x, y, 0)")
        f.tilt_axis = axis
        path = self._set_explicitly("floor", exclude=("floor.enabled",)) if f.enabled is False else None
        if path is not None:
            raise self.error(path, self.get(path), "the floor is disabled (floor.enabled false / --no-floor); "
                             "remove this setting or enable the floor")

    def _validate_obstacles(self) -> None:
        for i, o in enumerate(self.obstacles):
            if not o.radius > 0:
                raise self.error(f"obstacles[{i}].radius", o.radius, "expected a sphere radius > 0 m")
            if o.stiffness is not None and not o.stiffness > 0:
                raise self.error(f"obstacles[{i}].stiffness", o.stiffness, "expected a stiffness > 0 (Pa/m)")
            _friction(self, f"obstacles[{i}].friction", o.friction)

    def _validate_initial(self) -> None:
        s = self.initial
        if s.euler_deg is not None and s.axis_angle is not None:
            raise self.error("initial.axis_angle", s.axis_angle,
                             "give one rotation: initial.euler_deg or initial.axis_angle, not both")
        if s.axis_angle is not None and math.sqrt(sum(a * a for a in s.axis_angle[:3])) == 0:
            raise self.error("initial.axis_angle", s.axis_angle, "expected a nonzero axis (ax, ay, az, degrees)")

    def _validate_material(self) -> None:
        m = self.material
        if m.preset not in MATERIAL_PRESETS:
            raise self.error("material.preset", m.preset,
                             f"unknown material; expected one of {', '.join(MATERIAL_PRESETS)}")
        if m.youngs_modulus is not None and not (math.isfinite(m.youngs_modulus) and m.youngs_modulus > 0):
            raise self.error("material.youngs_modulus", m.youngs_modulus, "expected Young's modulus E > 0 (Pa)")
        nu = m.poisson_ratio
        if nu is not None:
            if nu >= 0.5:
                raise self.error("material.poisson_ratio", nu, "nu >= 0.5 is an incompressible material, which the "
                                 "simulator does not support; expected -1 < nu < 0.5 (e.g. 0.49)")
            if not nu > -1:
                raise self.error("material.poisson_ratio", nu, "expected Poisson's ratio -1 < nu < 0.5")
        _positive(self, "material.density", "kg/m^3")
        if m.damping_ratio is not None and not (math.isfinite(m.damping_ratio) and m.damping_ratio >= 0):
            raise self.error("material.damping_ratio", m.damping_ratio, "expected a damping ratio >= 0 (0 = undamped)")
        if m.model is not None and m.model not in ELASTIC_MODEL_NAMES:
            raise self.error("material.model", m.model, f"expected one of {', '.join(ELASTIC_MODEL_NAMES)}")
        if m.yield_stress is not None:
            if m.preset != "plasticine":
                raise self.error("material.yield_stress", m.yield_stress,
                                 f"a yield stress applies to the plasticine material, not {m.preset!r} "
                                 "(set material.preset / --material plasticine)")
            if not (math.isfinite(m.yield_stress) and m.yield_stress > 0):
                raise self.error("material.yield_stress", m.yield_stress, "expected a yield stress > 0 Pa")
        if m.friction_angle_deg is not None:
            if m.preset != "sand":
                raise self.error("material.friction_angle_deg", m.friction_angle_deg,
                                 f"a friction angle applies to the sand material, not {m.preset!r} "
                                 "(set material.preset / --material sand)")
            if not 0 < m.friction_angle_deg < 90:
                raise self.error("material.friction_angle_deg", m.friction_angle_deg,
                                 "expected a friction angle in (0, 90) degrees")

    def _validate_cameras(self) -> None:
        c = self.cameras
        if c.type is not None and c.type not in CAMERA_TYPES:
            raise self.error("cameras.type", c.type, f"expected one of {', '.join(CAMERA_TYPES)}")
        if not 1 <= c.views <= 256:
            raise self.error("cameras.views", c.views, "expected 1 to 256 ring cameras")
        if c.radius is not None and not (math.isfinite(c.radius) and c.radius > 0):
            raise self.error("cameras.radius", c.radius, "expected a horizontal camera distance > 0 m")
        _finite(self, "cameras.height", "m")
        if not 0 < c.fov_deg < 180:
            raise self.error("cameras.fov_deg", c.fov_deg, "expected a field of view in (0, 180) degrees")
        _finite(self, "cameras.azimuth_deg", "degrees")
        _finite(self, "cameras.turns", "")
        if c.scene is not None and c.type in ("ring", "orbit"):
            raise self.error("cameras.scene", c.scene, f"a scene folder's cameras are used with cameras.type scene, "
                             f"not {c.type}")

    def _set_explicitly(self, section: str, exclude: Sequence[str] = ()) -> str | None:
        """The first field of ``section`` that differs from its default (for contradictory settings)."""
        default = {"floor": FloorSpec()}[section]
        for f in fields(default):
            path = f"{section}.{f.name}"
            if path not in exclude and getattr(getattr(self, section), f.name) != getattr(default, f.name):
                return path
        return None


def _top_keys() -> list[str]:
    return [f.name for f in fields(Scenario) if f.name != "origins"]


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {_show(v)}" for k, v in value.items()) + "}"
    return repr(value)


def _number(value: Any) -> float | None:
    """A real number from a number or a numeric string (YAML 1.1 reads ``1e5`` as a string), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    try:  # numpy / torch scalars
        return float(value)
    except (TypeError, ValueError):
        return None


def _coerce(value: Any, spec: tuple[str, Any], where: str) -> Any:
    """Convert ``value`` to the field's type (None stays None), or raise naming ``where``."""
    kind, extra = spec
    if value is None:
        return None

    def bad(expected: str) -> ScenarioError:
        sep = " " if where.startswith("--") else " = "
        return ScenarioError(f"{where}{sep}{_show(value)}: expected {expected}")

    if kind == "float":
        x = _number(value)
        if x is None or not math.isfinite(x):
            raise bad("a finite number")
        return x
    if kind == "int":
        x = _number(value)
        if x is None or not math.isfinite(x) or x != int(x):
            raise bad("an integer")
        return int(x)
    if kind == "bool":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if kind in ("str", "path"):
        if not isinstance(value, (str, Path)) or not str(value):
            raise bad(_EXPECTED[kind])
        return str(value)
    if kind == "vec":
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split()]
        if not isinstance(value, (list, tuple)) or len(value) not in extra:
            raise bad(" or ".join(f"{n} numbers" for n in extra) + " (a list)")
        out = [_number(v) for v in value]
        if any(v is None or not math.isfinite(v) for v in out):
            raise bad(" or ".join(f"{n} finite numbers" for n in extra))
        return tuple(out)
    if kind == "background":
        x = _number(value)
        if x is not None:
            if not 0 <= x <= 1:
                raise bad(_EXPECTED["background"])
            return x
        if isinstance(value, (list, tuple)) and len(value) == 3:
            out = [_number(v) for v in value]
            if all(v is not None and 0 <= v <= 1 for v in out):
                return tuple(out)
        raise bad(_EXPECTED["background"])
    raise AssertionError(kind)  # pragma: no cover


def _finite(s: Scenario, path: str, unit: str) -> None:
    value = s.get(path)
    if value is not None and not math.isfinite(value):
        raise s.error(path, value, f"expected a finite number{' (' + unit + ')' if unit else ''}")


def _friction(s: Scenario, path: str, value: float | None) -> None:
    """A contact's Coulomb coefficient at ``path``: None (the asset's) or a finite number >= 0."""
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise s.error(path, value, "expected a Coulomb coefficient >= 0 (0: frictionless)")


def _positive(s: Scenario, path: str, unit: str) -> None:
    value = s.get(path)
    if value is not None and not (math.isfinite(value) and value > 0):
        raise s.error(path, value, f"expected a number > 0 ({unit})")


def _obstacle_from_mapping(o: Any, where: str) -> ObstacleSpec:
    if isinstance(o, ObstacleSpec):
        return o
    if not isinstance(o, Mapping):
        raise ScenarioError(f"{where}: expected a sphere {{center: [x, y, z], radius: r}}, got {_show(o)}")
    unknown = [k for k in o if k not in _OBSTACLE_SCHEMA]
    if unknown:
        raise ScenarioError(f"{where}: unknown key {unknown[0]!r} (expected {', '.join(_OBSTACLE_SCHEMA)})")
    missing = [k for k in ("center", "radius") if o.get(k) is None]
    if missing:
        raise ScenarioError(f"{where}: missing {missing[0]!r} (a sphere needs center: [x, y, z] and radius: r)")
    values = {k: _coerce(v, _OBSTACLE_SCHEMA[k], f"{where}.{k}") for k, v in o.items()}
    return ObstacleSpec(**values)


def _section_from_data(scenario: Scenario, key: str, value: Any, source: str) -> None:
    cls, schema = _SECTIONS[key]
    if key == "floor" and (value is None or isinstance(value, bool)):
        scenario.set("floor.enabled", bool(value), f"{source}: floor")
        return
    if key == "material" and isinstance(value, str):
        scenario.set("material.preset", value, f"{source}: material")
        return
    if key == "cameras" and isinstance(value, str):
        scenario.set("cameras.type", value, f"{source}: cameras")
        return
    if not isinstance(value, Mapping):
        raise ScenarioError(f"{source}: {key}: expected a mapping of {', '.join(schema)}, got {_show(value)}")
    for sub, v in value.items():
        if sub not in schema:
            raise ScenarioError(f"{source}: unknown key {key}.{sub!s} (expected one of {', '.join(schema)})")
        where = f"{source}: {key}.{sub}"
        scenario.set(f"{key}.{sub}", _coerce(v, schema[sub], where), where)

