"""Resolving a :class:`~vid2sim.simulate.scenario.Scenario` against an asset: everything checked, made concrete.

:func:`resolve_scenario` fills every default from the asset (the captured drop), checks what only the asset can
tell (a floor above the object, an obstacle overlapping it, cameras that do not see it) and returns a
:class:`ResolvedScenario`: the externals, material, initial state and cameras of the simulation.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import torch
from torch import Tensor

from vid2sim.physics.external import Floor, Gravity, MovingFloor, SphereObstacle
from vid2sim.physics.plasticity import DruckerPrager, VonMises
from vid2sim.simulate.cameras import (
    CameraTrack,
    check_visible,
    frame_cameras,
    orbital_tracks,
    resolve_cameras,
    scene_cameras,
)
from vid2sim.simulate.rotations import axis_angle_to_matrix, euler_to_matrix
from vid2sim.simulate.scenario import MATERIAL_PRESETS, InitialSpec, MaterialSpec, Scenario, ScenarioError

if TYPE_CHECKING:  # heavy imports only where used
    from vid2sim.asset.folder import Asset
    from vid2sim.physics.solver import SimState, Simulator

__all__ = ["ResolvedScenario", "resolve_scenario", "reframe", "source_scene", "FLOOR_TOLERANCE"]

#: how far (× the object's size) the object may start below the floor: the contact's own resting depth
FLOOR_TOLERANCE = 0.005


@dataclass
class ResolvedScenario:
    """A scenario made concrete for one asset (everything checked).

    Attributes:
        scenario: the scenario with every default filled in (what ``scenario.yaml`` records; running it
            again gives the same simulation).
        externals: gravity, the floor and the obstacles (:mod:`vid2sim.physics.external`).
        material: keyword arguments of :meth:`~vid2sim.asset.folder.Asset.simulator` (E, ν, density,
            damping ratio, model, plasticity).
        rotation: (3, 3) float64 rotation of the rest shape about ``centre``; translation: (3,) m after it.
        centre: (3,) the rest shape's centre of mass (m).
        linear_velocity, angular_velocity: (3,) m/s and rad/s at t = 0, about ``velocity_centre`` (3,).
        tracks: the output cameras.
        frames: frames written (the initial one included); dt: s per frame.
        background: grey level or (r, g, b).
        notes: what was chosen automatically (e.g. "cameras: ring (the source scene ... is not readable)").
        auto_framing: the ring/orbit camera fields placed automatically (``target``, ``radius``, ``height``): they
            frame the object at t = 0 here, and :func:`reframe` widens them to its whole simulated motion.
    """

    scenario: Scenario
    externals: list
    material: dict[str, Any]
    rotation: Tensor
    translation: Tensor
    centre: Tensor
    linear_velocity: list[float]
    angular_velocity: list[float]
    velocity_centre: list[float]
    tracks: list[CameraTrack]
    frames: int
    dt: float
    background: float | tuple[float, float, float]
    notes: list[str] = field(default_factory=list)
    auto_framing: list[str] = field(default_factory=list)

    def posed(self, points: Tensor) -> Tensor:
        """Rest points (N, 3) moved to the initial pose: R (X − c) + c + T."""
        R = self.rotation.to(points)
        c = self.centre.to(points)
        return (points - c) @ R.T + c + self.translation.to(points)

    def initial_state(self, sim: "Simulator") -> "SimState":
        """The state at t = 0: the rest shape in the initial pose (on the rigid handle, Z = [R − I | t] with
        x = R X + t), moving rigidly with v + ω × (x − a)."""
        state = sim.rest_state()
        dtype, device = torch.float64, sim.X.device  # computed in double, stored in the simulator's precision
        H = sim.num_dofs // 12
        R = self.rotation.to(dtype=dtype, device=device)
        c = self.centre.to(dtype=dtype, device=device)
        t = c + self.translation.to(dtype=dtype, device=device) - R @ c
        w = torch.tensor(self.angular_velocity, dtype=dtype, device=device)
        v = torch.tensor(self.linear_velocity, dtype=dtype, device=device)
        a = torch.tensor(self.velocity_centre, dtype=dtype, device=device)
        S = torch.zeros(3, 3, dtype=dtype, device=device)
        S[0, 1], S[0, 2], S[1, 2] = -w[2], w[1], -w[0]
        S = S - S.T
        z = state.z.to(dtype).reshape(H, 3, 4)
        z[H - 1, :, :3] = R - torch.eye(3, dtype=dtype, device=device)
        z[H - 1, :, 3] = t
        zd = state.zdot.to(dtype).reshape(H, 3, 4)
        zd[H - 1, :, :3] = S @ R
        zd[H - 1, :, 3] = v + S @ (t - a)
        state.z = z.reshape(-1).to(sim.X.dtype)
        state.zdot = zd.reshape(-1).to(sim.X.dtype)
        return state



def _asset_frames(asset: "Asset") -> int | None:
    """The captured scene's frame count (``extra.scene_frames``; older assets: the observed frames)."""
    if not isinstance(asset.extra, Mapping):
        return None
    value = asset.extra.get("scene_frames", asset.extra.get("observed_frames"))
    return int(value) if isinstance(value, int) and value >= 1 else None


def source_scene(asset: "Asset") -> str | None:
    """The scene folder the asset was reconstructed from (``extra.scene``), when it still exists."""
    path = asset.extra.get("scene") if isinstance(asset.extra, Mapping) else None
    if isinstance(path, str) and (Path(path) / "transforms.json").is_file():
        return path
    return None



def resolve_scenario(asset: "Asset", scenario: Scenario) -> ResolvedScenario:
    """Check ``scenario`` against ``asset`` and make it concrete; nothing is simulated or rendered.

    Checks (besides :meth:`Scenario.validate`): a floor must not start above the object's lowest point
    (beyond the contact's resting depth, :data:`FLOOR_TOLERANCE` × the object's size); an obstacle must not
    overlap or contain the object's points at t = 0; a scene camera folder must be readable; every camera
    must see the object at t = 0.

    Raises:
        ScenarioError: the first problem, one line naming the field and where it was set.
    """
    s = _validated_copy(scenario)
    notes: list[str] = []
    pose = _initial_pose(asset, s.initial)
    linear, angular = _initial_velocity(asset, s.initial, pose)
    scene_path, scene_info = _scene_and_timing(asset, s, notes)
    floor = _resolve_floor(asset, s, pose)
    externals: list = [Gravity(list(asset.gravity))] + ([floor] if floor is not None else [])
    externals += _resolve_obstacles(asset, s, pose.posed)
    material = _resolve_material(asset, s.material)
    auto = [k for k in ("target", "radius", "height") if getattr(s.cameras, k) is None]
    tracks = resolve_cameras(s, scene_path, scene_info, pose.posed, floor, notes)
    check_visible(s, tracks, pose.posed)
    return ResolvedScenario(scenario=s, externals=externals, material=material, rotation=pose.rotation,
                            translation=pose.translation, centre=pose.centre, linear_velocity=linear,
                            angular_velocity=angular, velocity_centre=pose.com.tolist(), tracks=tracks,
                            frames=int(s.frames), dt=float(s.dt), background=s.background, notes=notes,
                            auto_framing=auto if s.cameras.type in ("ring", "orbit") else [])


@dataclass
class _Pose:
    """The object at t = 0, float64 on the CPU (checked there whatever the asset's device).

    Attributes:
        rotation: (3, 3) rotation of the rest shape about ``centre``; translation: (3,) m after it.
        centre: (3,) the rest shape's centre of mass (m).
        posed: (M, 3) the interior, contact and cubature points in the initial pose.
        com: (3,) the centre of mass in the initial pose.
    """

    rotation: Tensor
    translation: Tensor
    centre: Tensor
    posed: Tensor
    com: Tensor


def _validated_copy(scenario: Scenario) -> Scenario:
    """A copy of ``scenario`` (sections, obstacles and origins copied too, so filling defaults leaves the caller's
    scenario alone), validated on its own (:meth:`Scenario.validate`)."""
    s = replace(scenario, floor=replace(scenario.floor), obstacles=[replace(o) for o in scenario.obstacles],
                initial=replace(scenario.initial), material=replace(scenario.material),
                cameras=replace(scenario.cameras), origins=dict(scenario.origins))
    s.validate()
    return s


def _initial_pose(asset: "Asset", init: InitialSpec) -> _Pose:
    """The asset's points moved rigidly by ``init``: its rotation about the rest centre of mass, then its
    translation."""
    points = torch.cat([asset.points, asset.contact_points, asset.cubature_points]).detach().to("cpu", torch.float64)
    centre = asset.points.detach().to("cpu", torch.float64).mean(0)
    if init.euler_deg is not None:
        R = euler_to_matrix(init.euler_deg)
    elif init.axis_angle is not None:
        R = axis_angle_to_matrix(init.axis_angle)
    else:
        R = torch.eye(3, dtype=torch.float64)
    T = torch.tensor(init.translation, dtype=torch.float64)
    posed = (points - centre) @ R.T + centre + T
    return _Pose(rotation=R, translation=T, centre=centre, posed=posed, com=centre + T)


def _initial_velocity(asset: "Asset", init: InitialSpec, pose: _Pose) -> tuple[list[float], list[float]]:
    """The linear (3,) m/s and angular (3,) rad/s velocity at t = 0 about the posed centre of mass: ``init``'s,
    else the captured ones; both are written back into ``init``."""
    centre, R, T, com = pose.centre, pose.rotation, pose.translation, pose.com
    # velocities about the centre of mass; the captured rigid motion v + ω × (x − a) about the recorded centre a
    # (moved with the pose) is the same motion as (v + ω × (com − a)) + ω × (x − com)
    captured = asset.initial_velocity
    cap_w = torch.tensor([float(v) for v in captured["angular"]], dtype=torch.float64)
    cap_a = (torch.tensor([float(v) for v in captured.get("centre", centre.tolist())], dtype=torch.float64)
             - centre) @ R.T + centre + T
    cap_v = torch.tensor([float(v) for v in captured["linear"]], dtype=torch.float64) + torch.linalg.cross(
        cap_w, com - cap_a)
    linear = [float(v) for v in (init.linear_velocity if init.linear_velocity is not None else cap_v)]
    angular = [float(v) for v in (init.angular_velocity if init.angular_velocity is not None else cap_w)]
    init.linear_velocity, init.angular_velocity = tuple(linear), tuple(angular)
    return linear, angular


def _scene_and_timing(asset: "Asset", s: Scenario, notes: list[str]) -> tuple[str | None, tuple[list, int] | None]:
    """The scene folder whose cameras and frame count ``s`` may use, and what :func:`scene_cameras` read from it
    (None when it is not needed or not readable, noted in ``notes``); fills ``s.frames`` and ``s.dt``."""
    scene_path = s.cameras.scene if s.cameras.scene is not None else source_scene(asset)
    scene_info: tuple[list, int] | None = None
    if scene_path is not None and (s.cameras.type in (None, "scene") or s.frames is None or s.resolution is None):
        try:
            scene_info = scene_cameras(scene_path)
        except ScenarioError as exc:
            if s.cameras.type == "scene" or s.cameras.scene is not None:
                raise s.error("cameras.scene" if s.cameras.scene is not None else "cameras.type",
                              s.cameras.scene if s.cameras.scene is not None else s.cameras.type,
                              str(exc)) from None
            notes.append(f"source scene {scene_path} not readable ({exc})")
    if s.frames is None:
        if scene_info is not None and scene_info[1] >= 1 and s.cameras.scene is None:
            s.frames = scene_info[1]
        else:
            s.frames = _asset_frames(asset) or 24
    if s.dt is None:
        s.dt = float(asset.dt)
    return scene_path, scene_info


def _resolve_floor(asset: "Asset", s: Scenario, pose: _Pose) -> Floor | MovingFloor | None:
    """The floor of ``s`` (None: no floor) with the asset's height and stiffness as defaults, pivoting under the
    posed centre of mass; refused when it starts above the posed object's lowest point (beyond
    :data:`FLOOR_TOLERANCE` × the object's size)."""
    f = s.floor
    posed, com = pose.posed, pose.com
    size = float(asset.length_scale)
    explicit = s._set_explicitly("floor", exclude=("floor.enabled",))
    if f.enabled is None:
        f.enabled = asset.floor_height is not None or explicit is not None
    if not f.enabled:
        return None
    if f.height is None:
        if asset.floor_height is None:
            path = explicit or "floor.enabled"
            raise s.error(path, s.get(path), "the asset has no floor; give the floor's height "
                          "(floor.height / --floor-height)")
        f.height = float(asset.floor_height)
    if f.stiffness is None:
        f.stiffness = float(asset.floor_stiffness)
    if f.friction is None:
        f.friction = float(asset.floor_friction)
    if f.pivot_xy is None:
        f.pivot_xy = (float(com[0]), float(com[1]))
    if f.moving:
        floor = MovingFloor(height=f.height, velocity=f.velocity, amplitude=f.amplitude, frequency=f.frequency,
                            tilt_deg=f.tilt_deg, tilt_rate_deg=f.tilt_rate_deg, tilt_axis=f.tilt_axis,
                            pivot_xy=f.pivot_xy, stiffness=f.stiffness, friction=f.friction)
        depth = -float(floor.signed_distance(posed, 0.0).min())
    else:
        floor = Floor(height=f.height, stiffness=f.stiffness, friction=f.friction)
        depth = -float(floor.signed_distance(posed).min())
    if depth > FLOOR_TOLERANCE * size:
        culprits = [p for p in s.origins if p.startswith("floor.") and p != "floor.enabled"] + [
            p for p in ("initial.translation", "initial.euler_deg", "initial.axis_angle") if p in s.origins]
        path = culprits[0] if culprits else "floor.height"
        raise s.error(path, s.get(path), f"the floor starts {depth * 100:.3g} cm above the object's lowest point "
                      "at t = 0; expected a floor below the object (lower the floor, or lift the object with "
                      "initial.translation / --translation)")
    return floor


def _resolve_obstacles(asset: "Asset", s: Scenario, posed: Tensor) -> list[SphereObstacle]:
    """The sphere obstacles of ``s`` (the asset's floor stiffness by default); each refused when it overlaps or
    contains the posed points ``posed`` (M, 3)."""
    spheres = []
    for i, o in enumerate(s.obstacles):
        if o.stiffness is None:
            o.stiffness = float(asset.floor_stiffness)
        if o.friction is None:
            o.friction = float(asset.floor_friction)
        c = torch.tensor(o.center, dtype=torch.float64)
        d = (posed - c).norm(dim=1)
        inside = int((d < o.radius).sum())
        if inside == d.numel():
            raise s.error(f"obstacles[{i}]", {"center": list(o.center), "radius": o.radius},
                          "the sphere contains the whole object at t = 0; expected a sphere outside the object")
        if inside:
            raise s.error(f"obstacles[{i}]", {"center": list(o.center), "radius": o.radius},
                          f"the sphere overlaps the object at t = 0 ({inside} of its {d.numel()} points inside, the "
                          f"deepest {(o.radius - float(d.min())) * 100:.3g} cm); expected a sphere outside the object")
        spheres.append(SphereObstacle(center=o.center, radius=o.radius, stiffness=o.stiffness, friction=o.friction))
    return spheres


def _resolve_material(asset: "Asset", m: MaterialSpec) -> dict[str, Any]:
    """The keyword arguments of :meth:`~vid2sim.asset.folder.Asset.simulator` for ``m``: its preset's values,
    else the asset's recovered ones (filled into ``m``), and the preset's plasticity (None: elastic)."""
    preset = MATERIAL_PRESETS[m.preset]
    if m.youngs_modulus is None:
        m.youngs_modulus = float(preset.get("youngs_modulus", asset.material["E"]))
    if m.poisson_ratio is None:
        m.poisson_ratio = float(preset.get("poisson_ratio", asset.material["nu"]))
    if m.density is None:
        m.density = float(asset.material["density"])
    if m.damping_ratio is None:
        m.damping_ratio = float(asset.material["damping_ratio"])
    if m.model is None:
        m.model = preset["model"]
    plasticity = None
    if m.preset == "plasticine":
        m.yield_stress = float(preset["yield_stress"]) if m.yield_stress is None else m.yield_stress
        plasticity = VonMises(m.yield_stress)
    elif m.preset == "sand":
        m.friction_angle_deg = (float(preset["friction_angle_deg"]) if m.friction_angle_deg is None
                                else m.friction_angle_deg)
        plasticity = DruckerPrager(m.friction_angle_deg)
    return {"youngs_modulus": m.youngs_modulus, "poisson_ratio": m.poisson_ratio, "density": m.density,
            "damping_ratio": m.damping_ratio, "model": m.model, "plasticity": plasticity}


def reframe(resolved: ResolvedScenario, cloud: Tensor) -> None:
    """Re-place the automatically framed ring/orbit cameras of ``resolved`` (``auto_framing``) so that they see
    ``cloud`` (M, 3): the object's points over the whole simulated motion. Updates ``resolved.scenario`` (what
    ``scenario.yaml`` records) and ``resolved.tracks``."""
    if not resolved.auto_framing:
        return
    c = resolved.scenario.cameras
    for key in resolved.auto_framing:
        setattr(c, key, None)
    floor = resolved.scenario.floor
    frame_cameras(c, cloud, floor.height if floor.enabled else None, resolved.auto_framing)
    resolved.tracks = orbital_tracks(resolved.scenario)
