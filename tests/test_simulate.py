"""``vid2sim simulate``: scenarios (YAML, options, validation before any work) and their physics and outputs,
on the tiny reconstructed asset of conftest.py."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from vid2sim.asset.folder import load_asset
from vid2sim.cli import main
from vid2sim.simulate.cameras import scene_cameras
from vid2sim.simulate.resolve import resolve_scenario
from vid2sim.simulate.rotations import axis_angle_to_matrix, euler_to_matrix
from vid2sim.simulate.run import run_scenario, simulate, trajectory_stats
from vid2sim.simulate.scenario import InitialSpec, ObstacleSpec, Scenario, ScenarioError


@pytest.fixture(scope="module")
def asset(tiny_asset):
    return load_asset(tiny_asset)


def _physics(asset, scenario: Scenario):
    """Resolve and simulate without rendering (tiny ring cameras keep the checks cheap)."""
    scenario.cameras.type = scenario.cameras.type or "ring"
    scenario.resolution = scenario.resolution or 16
    run = run_scenario(asset, resolve_scenario(asset, scenario))
    return run, trajectory_stats(asset, run)


def _no_leftovers(parent: Path, name: str) -> bool:
    return not any(p.name.startswith(f".{name}.") for p in parent.iterdir())


# ---- physics ------------------------------------------------------------------------------------

def test_captured_scenario_reproduces_the_assets_own_rollout(asset, tiny_scene):
    resolved = resolve_scenario(asset, Scenario())
    assert resolved.frames == 6  # the source scene's clip
    assert [t.name for t in resolved.tracks] == [f"scene_{v:02d}" for v in range(4)]
    run = run_scenario(asset, resolved)
    sim = asset.simulator()
    with torch.no_grad():
        start = asset.initial_state(sim)
        ref = [start] + sim.rollout(start, 5)
    assert len(run.states) == 6
    assert run.states[0].z.dtype == torch.float64  # simulations are float64 (SimConfig.dtype, docs/reliability.md)
    torch.testing.assert_close(run.states[0].z, ref[0].z, rtol=0, atol=0)
    torch.testing.assert_close(run.states[0].zdot, ref[0].zdot, rtol=0, atol=1e-6)  # about the centre of mass
    contact = asset.contact_points
    for a, b in zip(run.states, ref):
        assert a.t == pytest.approx(b.t)
        with torch.no_grad():  # the same simulation: the same motion to round-off amplified by the contact
            torch.testing.assert_close(sim.positions(contact, a.z), sim.positions(contact, b.z), rtol=0, atol=1e-5)
    # the scene's cameras, read without decoding its frames, are the loader's cameras
    from vid2sim.scene.reading import load_scene

    cams, frames = scene_cameras(tiny_scene)
    scene = load_scene(tiny_scene, dtype=torch.uint8)
    assert frames == scene.num_frames == 6
    for c, d in zip(cams, scene.cameras):
        torch.testing.assert_close(c.world_to_camera, d.world_to_camera)
        torch.testing.assert_close(c.K, d.K)


def test_new_pose_and_velocity_are_a_rigid_unstressed_start(asset):
    s = Scenario(frames=4)
    s.floor.enabled = False
    s.initial.axis_angle = (0.0, 1.0, 1.0, 70.0)
    s.initial.translation = (0.1, -0.2, 0.5)
    s.initial.linear_velocity = (1.0, 0.0, 0.5)
    s.initial.angular_velocity = (0.0, 0.0, 2.0)
    resolved = resolve_scenario(asset, s)
    run, stats = _physics(asset, s)
    sim = run.sim
    R = axis_angle_to_matrix((0.0, 1.0, 1.0, 70.0))
    c = asset.points.double().mean(0)
    X = asset.points.to(sim.X.dtype)
    with torch.no_grad():
        x0 = sim.positions(X, run.states[0].z).double()
        v0 = (sim.positions(X, run.states[0].zdot) - X).double()  # x is affine in z: velocity = B zdot
    expected = (asset.points.double() - c) @ R.T + c + torch.tensor([0.1, -0.2, 0.5], dtype=torch.float64)
    torch.testing.assert_close(x0, expected, rtol=0, atol=1e-5)
    com = expected.mean(0)
    w = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(v0, torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64) + torch.cross(
        w.expand_as(expected), expected - com, dim=1), rtol=0, atol=1e-5)
    # no floor: a rotated rest shape without spin is unstressed, so it flies ballistically without deforming
    # (the rigid handle carries translation exactly: ~1e-7 m of Newton tolerance); spinning at 2 rad/s adds a
    # stretch below the centrifugal scale ρ ω² L³ / E, so the bound follows the asset's fitted E. The spin must be
    # set to zero: a scenario's default spin is the asset's fitted one
    g = torch.tensor(asset.gravity, dtype=torch.float64)
    still = Scenario(frames=4)
    still.floor.enabled = False
    still.initial.axis_angle, still.initial.translation = s.initial.axis_angle, s.initial.translation
    still.initial.linear_velocity = s.initial.linear_velocity
    still.initial.angular_velocity = (0.0, 0.0, 0.0)
    _, still_stats = _physics(asset, still)
    m = asset.material
    centrifugal = m["density"] * 2.0**2 * asset.length_scale**3 / m["E"]
    assert stats["per_frame"]["deformation_rms"][0] < 1e-6
    for k, t in enumerate(stats["per_frame"]["time"]):
        assert still_stats["per_frame"]["deformation_rms"][k] < 1e-5 * asset.length_scale
        assert (
            stats["per_frame"]["deformation_rms"][k]
            < still_stats["per_frame"]["deformation_rms"][k] + 0.05 * centrifugal
        )
        ballistic = com + torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64) * t + 0.5 * g * t * t
        assert torch.allclose(torch.tensor(stats["per_frame"]["centre_of_mass"][k], dtype=torch.float64), ballistic,
                              atol=5e-3)
    assert resolved.scenario.floor.enabled is False
    # Euler angles: R = Rz Ry Rx about the world axes
    Rz = euler_to_matrix((0, 0, 90))
    torch.testing.assert_close(Rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1, 0], dtype=torch.float64), rtol=0, atol=1e-12)
    Rxz = euler_to_matrix((90, 0, 90))
    torch.testing.assert_close(Rxz, Rz @ euler_to_matrix((90, 0, 0)), rtol=0, atol=1e-12)


def test_tilted_floor_makes_the_object_slide_downhill(asset):
    _, flat = _physics(asset, Scenario(frames=10))
    tilted_scenario = Scenario(frames=10)
    tilted_scenario.floor.tilt_deg = 20.0  # about +x: the plane descends towards -y
    run, tilted = _physics(asset, tilted_scenario)
    dy_flat = flat["summary"]["displacement_m"][1]
    dy_tilted = tilted["summary"]["displacement_m"][1]
    assert dy_tilted < dy_flat - 0.2, (dy_flat, dy_tilted)
    assert abs(tilted["summary"]["displacement_m"][0]) < 0.05  # no drift along the tilt axis
    # the object rests on the tilted plane (not through it), and sinks lower than the flat floor allows
    floor = tilted["summary"]["floor"]
    assert floor["type"] == "moving_floor" and floor["frames_in_contact"] >= 3
    assert floor["max_penetration_m"] < 0.01 * asset.length_scale
    assert tilted["summary"]["lowest_point_m"] < -0.7 - 0.02 < flat["summary"]["lowest_point_m"]


def test_the_floor_and_obstacles_take_the_scenarios_friction_or_the_assets(asset):
    """``floor.friction`` / ``obstacles[i].friction`` reach the simulator's barriers (static and moving floors);
    unset, they are the asset's floor friction (the one its reconstruction fitted); a negative one is refused naming
    the field."""
    from dataclasses import replace

    sphere = ObstacleSpec(center=(0.0, 0.0, 3.0), radius=0.2)
    plain = resolve_scenario(asset, Scenario(frames=2, obstacles=[sphere])).externals
    assert [e.friction for e in plain[1:]] == [asset.floor_friction] * 2
    rough = replace(asset, floor_friction=0.3)
    resolved = resolve_scenario(rough, Scenario(frames=2, obstacles=[ObstacleSpec(center=(0.0, 0.0, 3.0), radius=0.2)]))
    assert [e.friction for e in resolved.externals[1:]] == [0.3, 0.3]
    tilted = resolve_scenario(rough, Scenario(frames=2, floor=_floor(tilt_deg=10.0, friction=0.8))).externals[1]
    assert type(tilted).__name__ == "MovingFloor" and tilted.friction == 0.8
    bad = Scenario(frames=2)
    bad.set("floor.friction", -0.2, "--floor-friction")
    with pytest.raises(ScenarioError, match=r"--floor-friction -0.2: expected a Coulomb coefficient >= 0"):
        resolve_scenario(asset, bad)


def test_rising_floor_carries_the_object(asset):
    _, static = _physics(asset, Scenario(frames=12))
    _, rising = _physics(asset, Scenario(frames=12, floor=_floor(velocity=0.5)))
    t_end = rising["per_frame"]["time"][-1]
    lift = rising["per_frame"]["centre_of_mass"][-1][2] - static["per_frame"]["centre_of_mass"][-1][2]
    assert lift == pytest.approx(0.5 * t_end, abs=0.03), lift  # resting on it, so raised with it
    d = rising["per_frame"]["floor_distance"]
    assert all(abs(x) < 0.03 for x in d[4:]) and all(abs(x) < 0.01 for x in d[-3:]), d  # on it (a small
    # bounce at most), never through it


def test_sphere_obstacle_stops_the_object_above_the_floor(asset):
    c = asset.points.mean(0).tolist()
    _, free = _physics(asset, Scenario(frames=10, initial=_lift(0.3)))
    s = Scenario(frames=10, initial=_lift(0.3), obstacles=[ObstacleSpec((c[0], c[1], -0.6), 0.2)])
    _, blocked = _physics(asset, s)
    assert free["summary"]["floor"]["frames_in_contact"] > 0  # without it, the object lands on the floor
    ball = blocked["summary"]["obstacles"][0]
    assert ball["frames_in_contact"] >= 3 and ball["first_contact_frame"] <= 4
    assert ball["max_penetration_m"] < 0.015 * asset.length_scale  # no deep penetration of the ball
    assert blocked["summary"]["floor"]["frames_in_contact"] == 0
    assert min(blocked["per_frame"]["lowest_z"]) > -0.7 + 0.1  # held well above the floor by the ball (top -0.4)


def _lift(dz: float):
    return InitialSpec(translation=(0.0, 0.0, dz))


def test_plasticine_keeps_its_deformation_where_elastic_recovers(asset):
    # without spin (a scenario's default is the asset's fitted spin, whose centrifugal stretch would blur the
    # in-air check), so the body is exactly rigid until it lands
    still = InitialSpec(angular_velocity=(0.0, 0.0, 0.0))
    _, elastic = _physics(asset, Scenario(frames=16, initial=still))
    run, plastic = _physics(asset, Scenario(frames=16, material=_material("plasticine"), initial=still))
    e = elastic["per_frame"]["deformation_rms"]
    p = plastic["per_frame"]["deformation_rms"]
    contact = plastic["summary"]["floor"]["first_contact_frame"]
    assert contact is not None and contact <= 4
    assert max(e[:contact]) < 1e-5 and max(p[:contact]) < 1e-5  # both rigid in the air
    assert min(e[contact + 2:]) < 0.3 * max(e)  # elastic: springs back towards its rest shape
    assert min(p[-4:]) > 3 * max(e[-4:])  # plasticine: the impact's deformation stays (and grows: 500 Pa yield)
    assert all(b >= a - 1e-4 for a, b in zip(p[contact + 1:], p[contact + 2:]))
    Fp = run.states[-1].Fp_inv
    assert Fp is not None and float((Fp - torch.eye(3)).abs().max()) > 0.01  # the points yielded
    assert run.sim.material.model == "stvk" and run.sim.material.plasticity.yield_stress == 500.0


def _material(preset: str, **kw):
    from vid2sim.simulate.scenario import MaterialSpec

    return MaterialSpec(preset=preset, **kw)


# ---- outputs ------------------------------------------------------------------------------------

def test_output_folder_ply_sequence_and_rerun_of_the_saved_scenario(asset, tiny_asset, tmp_path):
    from PIL import Image

    from vid2sim.scene.video import read_video
    from vid2sim.splats.ply import load_ply

    s = Scenario(frames=4, resolution=24)
    s.cameras.type = "ring"
    s.cameras.views = 2
    s.background = 0.0
    out = simulate(tiny_asset, s, tmp_path / "out", progress=False)
    names = ["ring_00", "ring_01"]
    for name in names:
        pngs = sorted((out / "frames" / name).iterdir())
        assert [p.name for p in pngs] == [f"{t:04d}.png" for t in range(4)]
        first = np.asarray(Image.open(pngs[0]))
        assert first.shape == (24, 24, 3) and first.min() == 0 and first.max() > 50  # black background, object
        video = read_video(out / "videos" / f"{name}.mp4")
        assert tuple(video.shape) == (4, 24, 24, 3)
        with Image.open(out / "videos" / f"{name}.gif") as gif:
            assert gif.n_frames == 4
    states = np.load(out / "states.npz")
    assert states["z"].shape == (4, asset.field.num_handles_total * 12)
    np.testing.assert_allclose(states["times"], [0.0, 0.05, 0.1, 0.15], atol=1e-9)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4 and [c["name"] for c in summary["cameras"]] == names
    assert summary["material"]["E"] == pytest.approx(asset.material["E"])
    assert set(summary["timings_seconds"]) >= {"simulate", "render", "write_frames", "write_ply", "write_videos"}
    from vid2sim.splats.cameras import Camera

    resolved = resolve_scenario(asset, Scenario.from_yaml(out / "scenario.yaml"))
    for cam, track in zip(summary["cameras"], resolved.tracks):  # the cameras are recorded (NeRF convention)
        K = Camera.intrinsics(cam["fl_x"], cam["fl_y"], cam["cx"], cam["cy"])
        again = Camera.from_nerf(torch.tensor(cam["transform_matrix"]), K, cam["width"], cam["height"])
        torch.testing.assert_close(again.world_to_camera, track.cameras[0].world_to_camera, rtol=0, atol=1e-5)
    # the PLY sequence: standard 3DGS files whose centres are the simulated positions of the Gaussians
    sim = asset.simulator()
    plys = sorted((out / "ply").iterdir())
    assert len(plys) == 4
    for t in (0, 3):
        g = load_ply(plys[t])
        assert g.num == asset.gaussians.num
        with torch.no_grad():
            x = sim.positions(asset.gaussians.means, torch.from_numpy(states["z"][t]).float())
        torch.testing.assert_close(g.means, x, rtol=0, atol=1e-5)
    assert float((load_ply(plys[3]).means - load_ply(plys[0]).means).norm(dim=1).mean()) > 0.05  # it moved
    # the saved scenario is complete: running it again simulates the same thing
    saved = Scenario.from_yaml(out / "scenario.yaml")
    assert saved.frames == 4 and saved.cameras.radius is not None and saved.material.youngs_modulus is not None
    again = run_scenario(asset, resolve_scenario(asset, saved))
    np.testing.assert_allclose(torch.stack([s.z for s in again.states]).numpy(), states["z"], atol=1e-6)


def test_output_is_complete_or_absent(asset, tiny_asset, tmp_path, monkeypatch):
    import vid2sim.simulate.run as ply  # where simulate looks save_ply up

    s = Scenario(frames=3, resolution=16, cameras=_cams("orbit"))
    calls = {"n": 0}
    real = ply.save_ply

    def failing(g, path):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full")
        return real(g, path)

    monkeypatch.setattr(ply, "save_ply", failing)
    with pytest.raises(OSError, match="disk full"):
        simulate(asset, s, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists() and _no_leftovers(tmp_path, "out")
    monkeypatch.setattr(ply, "save_ply", real)
    out = simulate(asset, s, tmp_path / "out", progress=False, video=False)
    assert sorted(p.name for p in out.iterdir()) == ["frames", "ply", "scenario.yaml", "states.npz", "summary.json"]
    assert len(list((out / "frames" / "orbit").iterdir())) == 3
    with pytest.raises(FileExistsError, match="overwrite"):
        simulate(asset, s, out, progress=False)
    out = simulate(asset, s, out, progress=False, video=False, ply=False, overwrite=True)
    assert not (out / "ply").exists() and _no_leftovers(tmp_path, "out")
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "precious.txt").write_text("x")
    with pytest.raises(FileExistsError, match="refusing"):
        simulate(asset, s, tmp_path / "keep", progress=False, overwrite=True)


def test_automatic_cameras_follow_the_whole_motion(asset, tmp_path):
    from PIL import Image

    # released at rest (not with the reconstruction's velocity), so that where it goes is the slope's doing
    s = Scenario(frames=10, resolution=16, cameras=_cams("ring", views=1), floor=_floor(tilt_deg=20.0),
                 initial=InitialSpec(linear_velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0)))
    at_start = resolve_scenario(asset, s).scenario.cameras  # framed on the object at t = 0
    out = simulate(asset, s, tmp_path / "slide", progress=False, video=False, ply=False)
    saved = Scenario.from_yaml(out / "scenario.yaml").cameras
    # measured on the tiny assets of either joint method: radius × 1.265 and 1.263, target 0.14 m down the slope
    assert saved.radius > 1.2 * at_start.radius and saved.target[1] < at_start.target[1] - 0.1  # down the slope
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cameras"][0]["frames_out_of_view"] == [] and summary["notes"] == []
    last = np.asarray(Image.open(out / "frames" / "ring_00" / "0009.png"))
    assert (last < 200).any(axis=2).sum() >= 4  # the object is still in the picture
    # cameras set by hand that lose the object show the background, and the summary says so: a narrow view of
    # the start of a fall without a floor
    fixed = Scenario(frames=10, resolution=16, cameras=_cams("ring", views=1, fov_deg=10.0),
                     floor=_floor(enabled=False))
    c = resolve_scenario(asset, fixed).scenario.cameras
    fixed.cameras.target, fixed.cameras.radius, fixed.cameras.height = c.target, c.radius, c.height
    out = simulate(asset, fixed, tmp_path / "fixed", progress=False, video=False, ply=False)
    summary = json.loads((out / "summary.json").read_text())
    lost = summary["cameras"][0]["frames_out_of_view"]
    assert lost and lost[-1] == 9 and "ring_00" in summary["notes"][0]
    assert (np.asarray(Image.open(out / "frames" / "ring_00" / "0009.png")) == 255).all()


def test_an_asset_without_a_floor(asset):
    from dataclasses import replace

    from vid2sim.physics.external import Floor, Gravity, MovingFloor

    bare = replace(asset, floor_height=None)
    resolved = resolve_scenario(bare, Scenario(frames=2))
    assert [type(e) for e in resolved.externals] == [Gravity] and resolved.scenario.floor.enabled is False
    tilted = Scenario(frames=2)
    tilted.set("floor.tilt_deg", 10.0, "--floor-tilt")
    with pytest.raises(ScenarioError, match=r"^--floor-tilt 10: the asset has no floor; give the floor's height"):
        resolve_scenario(bare, tilted)
    tilted.set("floor.height", -1.0, "--floor-height")
    floor = resolve_scenario(bare, tilted).externals[1]
    assert isinstance(floor, MovingFloor) and floor.height == -1.0 and floor.stiffness == asset.floor_stiffness
    assert isinstance(resolve_scenario(bare, Scenario(frames=2, floor=_floor(height=-1.0))).externals[1], Floor)


def _floor(**kw):
    from vid2sim.simulate.scenario import FloorSpec

    return FloorSpec(**kw)


def _cams(kind: str, **kw):
    from vid2sim.simulate.scenario import CameraSpec

    return CameraSpec(type=kind, **kw)


def test_cameras_ring_and_orbit_look_at_the_object(asset):
    ring = resolve_scenario(asset, Scenario(frames=5, resolution=32, cameras=_cams("ring", views=3)))
    assert [t.name for t in ring.tracks] == ["ring_00", "ring_01", "ring_02"]
    centres = torch.stack([t.cameras[0].center for t in ring.tracks]).double()
    target = torch.tensor(ring.scenario.cameras.target, dtype=torch.float64)
    radius, height = ring.scenario.cameras.radius, ring.scenario.cameras.height
    torch.testing.assert_close((centres[:, :2] - target[:2]).norm(dim=1), torch.full((3,), radius, dtype=torch.float64),
                               rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(centres[:, 2] - target[2], torch.full((3,), height, dtype=torch.float64),
                               rtol=1e-5, atol=1e-5)
    # the whole object projects inside every image (automatic framing)
    pix, depth = ring.tracks[1].cameras[0].project(ring.posed(asset.points))
    assert bool((depth > 0).all()) and bool(((pix >= 0) & (pix < 32)).all())
    orbit = resolve_scenario(asset, Scenario(frames=5, resolution=32, cameras=_cams("orbit", turns=0.5)))
    (track,) = orbit.tracks
    assert track.name == "orbit" and len(track.cameras) == 5
    first, last = track.cameras[0].center.double(), track.cameras[-1].center.double()
    torch.testing.assert_close(first[:2] - target[:2], -(last[:2] - target[:2]), rtol=1e-4, atol=1e-4)  # half a turn


# ---- scenario files and validation -------------------------------------------------------------

FULL_YAML = """
frames: 12
dt: 0.025
floor:
  height: -0.8
  stiffness: 2.0e+7
  velocity: 0.1
  amplitude: 0.02
  frequency: 2
  tilt_deg: 5
  tilt_rate_deg: 10
  tilt_axis: [0, 1]
  pivot_xy: [0.1, 0.2]
obstacles:
  - {center: [0, 0, -0.9], radius: 0.1}
  - center: [0.5, 0, -0.9]
    radius: 0.2
    stiffness: 1e6
initial:
  euler_deg: [10, 20, 30]
  translation: [0, 0, 0.1]
  linear_velocity: [0, 0, -1]
  angular_velocity: [0, 0, 1]
material:
  preset: sand
  youngs_modulus: 2e5
  poisson_ratio: 0.35
  friction_angle_deg: 25
cameras:
  type: orbit
  turns: 2
  fov_deg: 30
resolution: 64
background: [0.1, 0.2, 0.3]
"""


def test_yaml_round_trip_and_shorthands(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(FULL_YAML)
    s = Scenario.from_yaml(path).validate()
    assert s.frames == 12 and s.dt == 0.025 and s.floor.tilt_axis == (0.0, 1.0, 0.0) and s.floor.moving
    assert s.obstacles[1] == ObstacleSpec((0.5, 0.0, -0.9), 0.2, 1e6)  # "1e6" (a YAML 1.1 string) read as a number
    assert s.material.youngs_modulus == 2e5 and s.material.friction_angle_deg == 25.0
    assert s.background == (0.1, 0.2, 0.3) and s.cameras.type == "orbit"
    assert s.origins["material.poisson_ratio"] == f"{path}: material.poisson_ratio"
    text = s.to_yaml(tmp_path / "again.yaml")
    assert "tilt_axis: [0.0, 1.0, 0.0]" in text
    assert Scenario.from_yaml(tmp_path / "again.yaml") == s
    assert Scenario.from_yaml(tmp_path / "again.yaml").to_dict() == s.to_dict()
    short = tmp_path / "short.yaml"
    short.write_text("material: plasticine\nfloor: null\ncameras: ring\n")
    s = Scenario.from_yaml(short).validate()
    assert s.material.preset == "plasticine" and s.floor.enabled is False and s.cameras.type == "ring"
    assert Scenario.from_yaml(tmp_path / "again.yaml") != Scenario()
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert Scenario.from_yaml(empty) == Scenario()


@pytest.mark.parametrize("text, message", [
    ("frame: 3", "unknown key 'frame'"),
    ("material:\n  poison_ratio: 0.3", "unknown key material.poison_ratio"),
    ("obstacles:\n  - {centre: [0, 0, 0], radius: 1}", "obstacles[0]: unknown key 'centre'"),
    ("obstacles:\n  - {radius: 1}", "obstacles[0]: missing 'center'"),
    ("frames: many", "frames = 'many': expected an integer"),
    ("initial:\n  translation: [0, 0]", "initial.translation = [0, 0]: expected 3 numbers"),
    ("floor: [1, 2]", "floor: expected a mapping"),
    ("- 1\n- 2", "the top level must be a mapping"),
    ("frames: [", "not valid YAML"),
])
def test_yaml_errors_name_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as exc:
        Scenario.from_yaml(path)
    assert str(path) in str(exc.value) and message in str(exc.value)
    assert "\n" not in str(exc.value)


BAD_SCENARIOS = [
    ("material:\n  poisson_ratio: 0.5", "material.poisson_ratio = 0.5: nu >= 0.5 is an incompressible"),
    ("material:\n  poisson_ratio: -1.5", "expected Poisson's ratio -1 < nu < 0.5"),
    ("material:\n  youngs_modulus: 0", "material.youngs_modulus = 0: expected Young's modulus E > 0"),
    ("material: rubber", "material = 'rubber': unknown material; expected one of elastic, plasticine, sand"),
    ("material:\n  yield_stress: 100", "a yield stress applies to the plasticine material"),
    ("material:\n  preset: sand\n  friction_angle_deg: 95", "expected a friction angle in (0, 90)"),
    ("material:\n  model: linear", "material.model = 'linear': expected one of neo_hookean, stvk"),
    ("frames: 0", "frames = 0: expected at least 1 frame"),
    ("dt: -0.1", "dt = -0.1: expected a number > 0"),
    ("resolution: 4", "resolution = 4: expected an image width of 8"),
    ("floor:\n  height: -0.3", "floor.height = -0.3: the floor starts"),
    ("floor:\n  tilt_deg: 95", "floor.tilt_deg = 95: expected a tilt"),
    ("floor:\n  frequency: -1", "floor.frequency = -1: expected a frequency >= 0"),
    ("floor:\n  tilt_axis: [0, 0, 1]", "floor.tilt_axis = [0, 0, 1]: expected a nonzero horizontal axis"),
    ("floor:\n  enabled: false\n  tilt_deg: 10", "the floor is disabled"),
    ("obstacles:\n  - {center: [0, 0, -0.3], radius: 0.1}", "obstacles[0] = {center: [0, 0, -0.3], radius: 0.1}: "
                                                           "the sphere overlaps the object"),
    ("obstacles:\n  - {center: [0, 0, -0.3], radius: 5}", "the sphere contains the whole object"),
    ("obstacles:\n  - {center: [0, 0, -2], radius: -1}", "obstacles[0].radius = -1: expected a sphere radius > 0"),
    ("initial:\n  euler_deg: [0, 0, 10]\n  axis_angle: [0, 0, 1, 10]", "give one rotation"),
    ("initial:\n  axis_angle: [0, 0, 0, 10]", "expected a nonzero axis"),
    ("cameras: fisheye", "cameras = 'fisheye': expected one of scene, ring, orbit"),
    ("cameras:\n  type: ring\n  views: 0", "cameras.views = 0: expected 1 to 256"),
    ("cameras:\n  type: ring\n  fov_deg: 180", "expected a field of view in (0, 180)"),
    ("cameras:\n  type: ring\n  target: [40, 0, 0]\n  radius: 1", "camera ring_00 does not see the object"),
    ("cameras:\n  scene: /nonexistent/scene", "not a readable scene folder"),
    ("initial:\n  translation: [0, 0, 30]", "initial.translation = [0, 0, 30]: camera scene_00 does not see"),
    ("background: 3", "background = 3: expected a grey level"),
]


@pytest.mark.parametrize("text, message", BAD_SCENARIOS)
def test_every_validation_error_comes_before_any_simulation(asset, tmp_path, monkeypatch, text, message):
    from vid2sim.physics.solver import Simulator

    def reached(*args, **kwargs):
        raise AssertionError("the simulation started")

    monkeypatch.setattr(Simulator, "rollout", reached)
    monkeypatch.setattr(Simulator, "step", reached)
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as exc:
        simulate(asset, Scenario.from_yaml(path), tmp_path / "out", progress=False)
    assert message in str(exc.value) and str(path) in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "out").exists() and _no_leftovers(tmp_path, "out")


# ---- the command --------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, message", [
    (["--nu", "0.5"], "--nu 0.5: nu >= 0.5 is an incompressible material"),
    (["--E", "-1"], "--E -1: expected Young's modulus E > 0"),
    (["--obstacle", "0,0,-0.3,0.1"], "--obstacle {center: [0, 0, -0.3], radius: 0.1}: the sphere overlaps"),
    (["--obstacle", "0,0,1"], "--obstacle '0,0,1': expected 4 comma-separated numbers"),
    (["--floor-height", "0"], "--floor-height 0: the floor starts"),
    (["--no-floor", "--floor-tilt", "10"], "--floor-tilt 10: the floor is disabled"),
    (["--frames", "0"], "--frames 0: expected at least 1 frame"),
    (["--material", "clay"], "--material 'clay': unknown material"),
    (["--friction-angle", "30"], "--friction-angle 30: a friction angle applies to the sand material"),
    (["--rotation", "10,20"], "--rotation '10,20': expected 3 comma-separated numbers"),
    (["--cameras", "ring", "--camera-target", "40,0,0", "--camera-radius", "1"],
     "--camera-target [40, 0, 0]: camera ring_00 does not see"),
    (["--scene", "/nonexistent"], "--scene '/nonexistent': /nonexistent: not a readable scene folder"),
    (["--background", "2"], "--background 2: expected a grey level"),
    (["--threads", "0"], "--threads must be >= 1"),
])
def test_cli_errors_name_the_flag(tiny_asset, tmp_path, capsys, argv, message):
    assert main(["simulate", str(tiny_asset), str(tmp_path / "out"), "--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_cli_options_override_the_yaml_file(tiny_asset, tmp_path, capsys):
    path = tmp_path / "s.yaml"
    path.write_text("frames: 3\nmaterial:\n  preset: plasticine\n  poisson_ratio: 0.3\n  yield_stress: 800\n"
                    "cameras:\n  type: ring\n  views: 3\n")
    out = tmp_path / "out"
    argv = ["simulate", str(tiny_asset), str(out), "--scenario", str(path), "--nu", "0.45", "--views", "1",
            "--resolution", "16", "--rotation", "0,0,45", "--no-video", "--no-ply", "--quiet", "--threads", "1"]
    assert main(argv) == 0
    assert "wrote" in capsys.readouterr().out
    saved = Scenario.from_yaml(out / "scenario.yaml")
    assert saved.material.poisson_ratio == 0.45 and saved.material.yield_stress == 800.0  # flag over file, file kept
    assert saved.cameras.views == 1 and saved.initial.euler_deg == (0.0, 0.0, 45.0) and saved.frames == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["material"]["plasticity"] == {"type": "von_mises", "yield_stress": 800.0}
    assert summary["initial_state"]["rotation"][0][1] == pytest.approx(-math.sin(math.pi / 4))
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["ring_00"]
    assert main(argv) == 2 and "exists; pass --overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite", "--frames", "2"]) == 0
    assert len(list((out / "frames" / "ring_00").iterdir())) == 2
