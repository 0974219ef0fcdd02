"""Physics fuzz: random simulations through the public scenario API (:mod:`vid2sim.simulate`).

Each case draws an object (a procedural shape or a mesh file loaded as a user's would be), a skinning field of
1–40 learned handles, a material (E log-uniform in [1e3, 1e8] Pa, ν in [0, 0.49], density 100–5 000 kg/m³;
elastic, plasticine or sand), a frame time in [1/240, 1/10] s, a pose, a drop height, an initial velocity up to
10 m/s and a spin, a static, moving or tilted floor and sphere obstacles, each frictionless or with a Coulomb
friction μ in [0.05, 1.5] (half and half; the friction's fixed point of :mod:`vid2sim.physics.solver`). It builds an
:class:`~vid2sim.asset.folder.Asset` in memory, resolves the :class:`~vid2sim.simulate.scenario.Scenario` against
it and simulates it (:func:`~vid2sim.simulate.run.run_scenario`). A share of the cases carries one parameter out
of its range; those must be refused by :func:`~vid2sim.simulate.run.simulate` with an error naming the parameter
before anything is written.

Checked on every frame of a simulated case (:func:`check_run`):

- every state finite (z, ż);
- det F > 0 at every cubature point (the solver's line search must never accept an inverted point);
- the mechanical energy (kinetic + gravity + elastic + barriers) never rises above its start by more than
  :data:`ENERGY_TOLERANCE` of the energy scale, unless something does work on the object (a moving or turning
  floor);
- on a static, level floor, whether the object comes to rest within the case's time (a figure, not a failure: a
  stiff object on the elastic penalty floor keeps bouncing for long, see docs/reliability.md) — the kinetic energy
  left once the motions a frictionless floor cannot stop (horizontal drift and spin about the vertical) are removed
  falls below :data:`REST_TOLERANCE` × M g L.

A case that the simulator stops with a :class:`~vid2sim.physics.solver.SimulationError` (e.g. a very soft
object crushed by a hard impact) is reported as ``stopped`` with its message; it is not a failure of these
checks, but is counted.
"""

from __future__ import annotations

import math
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

#: energy rise allowed without external work, as a fraction of the case's energy scale
ENERGY_TOLERANCE = 0.02
#: kinetic energy (less the motions a frictionless floor cannot stop) at rest, fraction of the energy scale
REST_TOLERANCE = 1e-3  # of M g L
#: seconds after the fall in which an object on a level floor should come to rest
SETTLE_SECONDS = 1.5
#: frames per case at most (keeps a 1/240 s frame time affordable; such a case is too short to judge rest)
MAX_FRAMES = 240
#: the floor height of the fuzz assets (the canonical frame's floor)
FLOOR_HEIGHT = -0.7
#: user-mesh kinds (trimesh primitives written to a file and loaded back)
MESH_KINDS = ("box", "capsule", "cylinder", "icosphere", "hull", "annulus")
#: the parameters an invalid case may break, each with a bad value and the words the error must contain
INVALID = (
    ("material.youngs_modulus", -1e5, "youngs_modulus"),
    ("material.youngs_modulus", 0.0, "youngs_modulus"),
    ("material.youngs_modulus", math.inf, "youngs_modulus"),
    ("material.poisson_ratio", 0.5, "poisson_ratio"),
    ("material.poisson_ratio", math.nan, "poisson_ratio"),
    ("material.density", -1000.0, "density"),
    ("material.density", 0.0, "density"),
    ("material.damping_ratio", -0.1, "damping_ratio"),
    ("material.yield_stress", -5.0, "yield_stress"),
    ("material.friction_angle_deg", 95.0, "friction_angle_deg"),
    ("dt", 0.0, "dt"),
    ("dt", -0.01, "dt"),
    ("dt", math.nan, "dt"),
    ("frames", 0, "frames"),
    ("floor.tilt_deg", 90.0, "tilt_deg"),
    ("floor.frequency", -1.0, "frequency"),
    ("floor.height", 5.0, "floor"),
    ("floor.stiffness", -1.0, "stiffness"),
    ("obstacles[0].radius", -0.2, "radius"),
    ("obstacles[0].center", "the object's centre", "obstacles[0]"),
    ("initial.linear_velocity", (math.nan, 0.0, 0.0), "linear_velocity"),
    ("initial.angular_velocity", (0.0, math.inf, 0.0), "angular_velocity"),
    ("initial.translation", (0.0, 0.0, math.nan), "translation"),
)


@dataclass
class PhysicsCase:
    """One random simulation (all drawn by :func:`draw_case` from ``seed``)."""

    seed: int
    shape: str  # "procedural:<seed>" or a MESH_KINDS entry
    handles: int
    cubature: int
    material: str  # elastic, plasticine, sand
    model: str
    youngs_modulus: float
    poisson_ratio: float
    density: float
    damping_ratio: float
    yield_stress: float | None
    friction_angle_deg: float | None
    dt: float
    duration: float
    drop_height: float
    axis_angle: tuple[float, float, float, float]
    linear_velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]
    floor: dict[str, Any]
    obstacles: list[dict[str, Any]] = field(default_factory=list)
    invalid: tuple[str, Any, str] | None = None  # (parameter path, bad value, word the error must name)

    @property
    def frames(self) -> int:
        return max(2, int(math.ceil(self.duration / self.dt)) + 1)

    @property
    def static_floor(self) -> bool:
        f = self.floor
        return f["kind"] == "static" or (f["kind"] == "tilted" and f.get("tilt_rate_deg", 0.0) == 0.0)

    @property
    def level_floor(self) -> bool:
        return self.floor["kind"] == "static"


def draw_case(seed: int, invalid_share: float = 0.1, quick: bool = False) -> PhysicsCase:
    """A random case from ``seed`` (deterministic). ``quick`` keeps the object small and the run short."""
    rng = np.random.default_rng([seed, 53])
    shape = (f"procedural:{int(rng.integers(0, 10_000))}" if rng.random() < 0.5
             else MESH_KINDS[int(rng.integers(len(MESH_KINDS)))])
    handles = int(rng.choice([1, 2, 3, 5, 8, 10, 16, 24, 32, 40]))
    material = str(rng.choice(["elastic", "elastic", "plasticine", "sand"]))
    E = float(10 ** rng.uniform(3, 8))
    dt = float(1.0 / rng.uniform(10, 240))
    kind = str(rng.choice(["static", "static", "static", "moving", "tilted", "none"]))
    floor: dict[str, Any] = {"kind": kind}
    if kind == "moving":
        floor.update(velocity=float(rng.uniform(-0.3, 0.3)), amplitude=float(rng.uniform(0, 0.1)),
                     frequency=float(rng.uniform(0, 3)))
    elif kind == "tilted":
        floor.update(tilt_deg=float(rng.uniform(-40, 40)),
                     tilt_rate_deg=float(rng.choice([0.0, rng.uniform(-20, 20)])),
                     tilt_axis=(float(np.cos(a := rng.uniform(0, np.pi))), float(np.sin(a))))
    drop = float(rng.uniform(0.05, 1.5))
    speed = float(rng.uniform(0, 10)) * (rng.random() < 0.6)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    spin = rng.normal(size=3) * float(rng.uniform(0, 8)) * (rng.random() < 0.6)
    axis = rng.normal(size=3)
    axis_angle = (*(axis / np.linalg.norm(axis)).tolist(), float(rng.uniform(0, 180)))
    obstacles = []
    for _ in range(int(rng.choice([0, 0, 1, 2]))):
        r = float(rng.uniform(0.1, 0.4))
        obstacles.append({"center": (float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)),
                                     FLOOR_HEIGHT + float(rng.uniform(-r, r))), "radius": r})
    # the floor's and the obstacles' friction come from a stream of their own: every other draw of a seed is the
    # one the campaigns before friction made
    fr = np.random.default_rng([seed, 59])
    if kind != "none":
        floor["friction"] = float(fr.choice([0.0, fr.uniform(0.05, 1.5)]))
    for o in obstacles:
        o["friction"] = float(fr.choice([0.0, fr.uniform(0.05, 1.5)]))
    case = PhysicsCase(
        seed=seed, shape=shape, handles=handles, cubature=int(rng.integers(40, 160)), material=material,
        model="neo_hookean" if material == "elastic" and rng.random() < 0.7 else "stvk",
        youngs_modulus=E, poisson_ratio=float(rng.uniform(0, 0.49)), density=float(rng.uniform(100, 5000)),
        damping_ratio=float(rng.choice([0.05, 0.05, rng.uniform(0, 0.3)])),
        yield_stress=float(E * 10 ** rng.uniform(-3, -1)) if material == "plasticine" else None,
        friction_angle_deg=float(rng.uniform(15, 45)) if material == "sand" else None,
        dt=dt, duration=0.0, drop_height=drop, axis_angle=axis_angle,
        linear_velocity=tuple(float(v) for v in direction * speed),
        angular_velocity=tuple(float(v) for v in spin), floor=floor, obstacles=obstacles)
    if quick:
        case.handles, case.cubature = min(case.handles, 8), min(case.cubature, 60)
    case.duration = rest_time(case) if not quick else min(rest_time(case), 0.3)
    if rng.random() < invalid_share:
        path, value, word = INVALID[int(rng.integers(len(INVALID)))]
        if path.startswith("obstacles") and not case.obstacles:
            case.obstacles.append({"center": (3.0, 3.0, FLOOR_HEIGHT), "radius": 0.2})
        if path.startswith("floor") and kind == "none":
            case.floor = {"kind": "static"}
        case.invalid = (path, value, word)
    return case


def fall_time(case: PhysicsCase) -> float:
    """Seconds until the object's centre reaches the floor, roughly (its fall of drop height + 1 m)."""
    vz = case.linear_velocity[2]
    return (vz + math.sqrt(vz * vz + 2 * 9.8 * (case.drop_height + 1.0))) / 9.8


def rest_time(case: PhysicsCase) -> float:
    """Seconds the case runs. On a level floor: the fall of its centre (about drop height + 1 m), then
    :data:`SETTLE_SECONDS` to come to rest; otherwise (no rest is expected) at most 1 s, no floor 0.5 s. At most
    :data:`MAX_FRAMES` frames either way (a short frame time shortens the run)."""
    fall = fall_time(case)
    if case.floor["kind"] == "none":
        seconds = 0.5
    elif case.level_floor:
        seconds = fall + SETTLE_SECONDS
    else:
        seconds = min(fall + 0.3, 1.0)
    return min(seconds, MAX_FRAMES * case.dt)


# ---- building the asset and the scenario ----------------------------------------------------------

def _mesh(shape: str, workdir: Path):
    """(vertices (V, 3), faces (F, 3)) of ``shape`` in the canonical frame."""
    from vid2sim.synthetic.meshes import load_user_mesh

    if shape.startswith("procedural:"):
        from vid2sim.synthetic.shapes import (
            ProceduralShapeConfig,
            make_procedural_object,
        )

        mesh = make_procedural_object(int(shape.split(":")[1]), ProceduralShapeConfig(target_faces=800,
                                                                                      texture_size=8))
        return mesh.vertices, mesh.faces
    import trimesh

    rng = np.random.default_rng(abs(hash(shape)) % 2**32)
    if shape == "box":
        m = trimesh.creation.box(extents=(1.0, 0.5, 0.25))
    elif shape == "capsule":
        m = trimesh.creation.capsule(height=1.0, radius=0.2)
    elif shape == "cylinder":
        m = trimesh.creation.cylinder(radius=0.5, height=0.15, sections=32)
    elif shape == "icosphere":
        m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    elif shape == "annulus":
        m = trimesh.creation.annulus(r_min=0.25, r_max=0.5, height=0.2, sections=32)
    else:  # a random convex hull
        m = trimesh.convex.convex_hull(rng.normal(size=(40, 3)) * (1.0, 0.6, 0.3))
    path = workdir / f"{shape}.obj"  # through the file, as a user's mesh comes
    m.export(str(path))
    mesh = load_user_mesh(path)
    return mesh.vertices, mesh.faces


def build_asset(shape: str, handles: int, cubature: int, seed: int, workdir: Path,
                skinning_iterations: int = 40):
    """An in-memory :class:`~vid2sim.asset.folder.Asset` of ``shape`` (canonical frame, floor at
    :data:`FLOOR_HEIGHT`), a skinning field of ``handles`` learned handles trained data-free for
    ``skinning_iterations`` steps, ``cubature`` cubature points."""
    from vid2sim.asset.folder import Asset
    from vid2sim.physics.cubature import sample_cubature
    from vid2sim.physics.external import AREA_CONTACT_STIFFNESS
    from vid2sim.physics.skinning import SkinningField
    from vid2sim.physics.skinning_training import SkinningTrainingConfig, train_skinning
    from vid2sim.physics.solver import SimConfig
    from vid2sim.predictor.solid import sample_solid
    from vid2sim.splats.gaussians import Gaussians

    V, Fc = _mesh(shape, workdir)
    solid = sample_solid(torch.as_tensor(V), torch.as_tensor(Fc), num_points=2000, max_contact_points=200, seed=seed)
    points = solid.points.to(torch.float32)
    field = SkinningField(num_handles=handles, seed=seed)
    train_skinning(field, points, SkinningTrainingConfig(iterations=skinning_iterations, points_per_step=400,
                                                         batch_size=4, seed=seed), progress=False)
    for p in field.parameters():
        p.requires_grad_(False)
    idx, w = sample_cubature(points, min(cubature, points.shape[0]), volume=float(solid.volume), seed=seed)
    surface = solid.contact_points.to(torch.float32)
    gaussians = Gaussians.from_values(surface, torch.full((surface.shape[0],), 0.02), torch.full_like(surface, 0.5),
                                      torch.full((surface.shape[0],), 0.9))
    extent = points.amax(0) - points.amin(0)
    material = {"model": "neo_hookean", "E": 1e5, "log10_E": 5.0, "nu": 0.3, "density": 1000.0,
                "damping_ratio": 0.05}
    return Asset(gaussians=gaussians, field=field, jacobian=None, material=material,
                 cubature_points=points[idx].clone(), cubature_weights=w, contact_points=surface,
                 contact_areas=solid.contact_areas.to(torch.float32), points=points, volume=float(solid.volume),
                 sim_config=SimConfig(), gravity=[0.0, 0.0, -9.8], floor_height=FLOOR_HEIGHT,
                 floor_stiffness=AREA_CONTACT_STIFFNESS, length_scale=float(extent.norm()),
                 initial_velocity={"linear": [0.0, 0.0, 0.0], "angular": [0.0, 0.0, 0.0], "centre": [0.0, 0.0, 0.0]},
                 dt=0.05, extra={"fuzz": shape})


def scenario_of(case: PhysicsCase, asset) -> "Any":
    """The :class:`~vid2sim.simulate.scenario.Scenario` of ``case`` on ``asset`` (the object posed, then lifted so
    that its lowest point is ``drop_height`` above the floor's highest point under it)."""
    from vid2sim.simulate.rotations import axis_angle_to_matrix
    from vid2sim.simulate.scenario import (
        CameraSpec,
        FloorSpec,
        InitialSpec,
        MaterialSpec,
        ObstacleSpec,
        Scenario,
    )

    pts = torch.cat([asset.points, asset.contact_points]).double()
    c = asset.points.double().mean(0)
    R = axis_angle_to_matrix(case.axis_angle)
    posed = (pts - c) @ R.T + c
    lowest = float(posed[:, 2].min())
    f = case.floor
    floor_top = FLOOR_HEIGHT
    if f["kind"] == "tilted":  # the plane rises by tan(tilt) × the horizontal reach of the object
        reach = float((posed[:, :2] - c[:2]).norm(dim=1).max())
        floor_top += math.tan(math.radians(abs(f["tilt_deg"]))) * reach
    elif f["kind"] == "moving":
        floor_top += f["amplitude"]
    lift = floor_top + case.drop_height - lowest
    if f["kind"] == "none":
        floor = FloorSpec(enabled=False)
    elif f["kind"] == "static":
        floor = FloorSpec(enabled=True, height=FLOOR_HEIGHT, friction=f.get("friction"))
    elif f["kind"] == "moving":
        floor = FloorSpec(enabled=True, height=FLOOR_HEIGHT, velocity=f["velocity"], amplitude=f["amplitude"],
                          frequency=f["frequency"], friction=f.get("friction"))
    else:
        floor = FloorSpec(enabled=True, height=FLOOR_HEIGHT, tilt_deg=f["tilt_deg"],
                          tilt_rate_deg=f.get("tilt_rate_deg", 0.0), tilt_axis=tuple(f["tilt_axis"]),
                          friction=f.get("friction"))
    obstacles = [ObstacleSpec(center=tuple(o["center"]), radius=o["radius"], friction=o.get("friction"))
                 for o in case.obstacles]
    s = Scenario(frames=case.frames, dt=case.dt, floor=floor, obstacles=obstacles,
                 initial=InitialSpec(axis_angle=tuple(case.axis_angle), translation=(0.0, 0.0, lift),
                                     linear_velocity=tuple(case.linear_velocity),
                                     angular_velocity=tuple(case.angular_velocity)),
                 material=MaterialSpec(preset=case.material, youngs_modulus=case.youngs_modulus,
                                       poisson_ratio=case.poisson_ratio, density=case.density,
                                       damping_ratio=case.damping_ratio, model=case.model,
                                       yield_stress=case.yield_stress, friction_angle_deg=case.friction_angle_deg),
                 cameras=CameraSpec(type="ring", views=1), resolution=8)
    # obstacles the pose overlaps are moved out of the way (an overlap is a refusal, tested on its own)
    for o in s.obstacles:
        moved = (posed + torch.tensor([0.0, 0.0, lift], dtype=torch.float64) - torch.tensor(o.center)).norm(dim=1)
        if float(moved.min()) < o.radius * 1.05:
            o.center = (o.center[0] + 3.0, o.center[1], o.center[2])
    if case.invalid is not None:
        path, value = case.invalid[:2]
        if path == "obstacles[0].center":  # a sphere around the object's centre at t = 0
            value = tuple((c + torch.tensor([0.0, 0.0, lift], dtype=torch.float64)).tolist())
        _break(s, path, value)
    return s


def _break(s, path: str, value: Any) -> None:
    """Set the scenario's field ``path`` to ``value``, as a user's file or flag would (the origin is the path
    itself, so the error must name it)."""
    if path.startswith("obstacles[0]."):
        o = s.obstacles[0]
        setattr(o, path.split(".")[-1], value)
        s.origins["obstacles[0]"] = "obstacles[0]"
        return
    s.set(path, value, path)


# ---- the checks -----------------------------------------------------------------------------------

def energies(sim, state, t: float) -> dict[str, float]:
    """Kinetic, gravity, elastic and barrier energies (J) of ``state`` (from the simulator's own points and
    weights: the quantities its incremental potential uses)."""
    from vid2sim.physics.materials import energy_and_pk1

    X = sim.X
    with torch.no_grad():
        x = sim.positions(X, state.z)
        v = sim.positions(X, state.zdot) - X
        m = sim.masses()
        kinetic = 0.5 * float((m * (v * v).sum(1)).sum())
        F = sim.deformation_gradients_at_cubature(state.z)
        if state.Fp_inv is not None:
            F = F @ state.Fp_inv
        mu, lam = sim.lame()
        psi = energy_and_pk1(sim.material.model, F, mu, lam)[0]
        elastic = float((sim.vol * psi).sum())
        gravity = barrier = 0.0
        xc = sim.positions(sim.contact_points, state.z) if sim.contact_points is not None else x
        wc = sim.contact_weights if sim.contact_points is not None else torch.ones_like(m)
        for e in sim.externals:
            if e.kind == "body":
                gravity += float(e.energy(x, m, t))
            else:
                barrier += float(e.energy(xc, wc, t))
    return {"kinetic": kinetic, "gravity": gravity, "elastic": elastic, "barrier": barrier}


def free_kinetic(sim, state) -> float:
    """Kinetic energy (J) left after removing the best horizontal translation and spin about the vertical
    through the centre of mass (what a frictionless level floor cannot stop)."""
    with torch.no_grad():
        X = sim.X
        x = sim.positions(X, state.z).double()
        v = (sim.positions(X, state.zdot) - X).double()
        m = sim.masses().double()
        c = (m[:, None] * x).sum(0) / m.sum()
        r = x - c
        # v ≈ (a, b, 0) + ω e_z × r = (a − ω r_y, b + ω r_x, 0): weighted least squares in (a, b, ω)
        A = torch.zeros(x.shape[0], 2, 3, dtype=torch.float64)
        A[:, 0, 0], A[:, 1, 1] = 1.0, 1.0
        A[:, 0, 2], A[:, 1, 2] = -r[:, 1], r[:, 0]
        W = m[:, None, None]
        lhs = (A.transpose(1, 2) @ (W * A)).sum(0)
        rhs = (A.transpose(1, 2) @ (W * v[:, :2, None])).sum(0)
        sol = torch.linalg.lstsq(lhs, rhs).solution[:, 0]
        u = v.clone()
        u[:, :2] -= (A @ sol)
        return 0.5 * float((m * (u * u).sum(1)).sum())


def check_run(case: PhysicsCase, run) -> dict[str, Any]:
    """The checks of the module docstring on a finished run; returns a JSON-ready record (``ok``: finite, no
    inverted point, no energy gain; ``rest``: whether a level-floor case came to rest, None otherwise).

    The energy scale is M g L + the largest kinetic energy of the run (M the mass, L the object's size): the
    energy the integrator moves around."""
    from vid2sim.physics.materials import det3

    sim, states = run.sim, run.states
    problems: list[str] = []
    dets, totals, kinetic = [], [], []
    with torch.no_grad():
        for s in states:
            if not (bool(torch.isfinite(s.z).all()) and bool(torch.isfinite(s.zdot).all())):
                problems.append(f"non-finite state at t = {s.t:.4g} s")
                break
            F = sim.deformation_gradients_at_cubature(s.z)
            dets.append(float(det3(F).min()))
            e = energies(sim, s, float(s.t))
            totals.append(sum(e.values()))
            kinetic.append(e["kinetic"])
    if dets and min(dets) <= 0:
        problems.append(f"inverted cubature point accepted (min det F = {min(dets):.3g})")
    M = float(sim.masses().sum())
    scale = M * 9.8 * sim.length_scale + (max(kinetic) if kinetic else 0.0)
    gain = (max(totals) - totals[0]) / scale if totals else 0.0
    if case.static_floor and gain > ENERGY_TOLERANCE:
        k = int(np.argmax(totals))
        problems.append(f"energy gain without external work: {gain:.3g} of the energy scale at t = "
                        f"{float(states[k].t):.4g} s")
    rest = rest_kinetic = None
    if case.level_floor and not problems and case.duration >= fall_time(case) + SETTLE_SECONDS - 1e-9:
        rest_kinetic = free_kinetic(sim, states[-1]) / (M * 9.8 * sim.length_scale)
        rest = rest_kinetic <= REST_TOLERANCE
    return {"ok": not problems, "problems": problems, "min_det_F": min(dets) if dets else None,
            "energy_gain": gain if case.static_floor else None, "rest": rest, "rest_kinetic": rest_kinetic,
            "substeps": sim.substeps(), "frames": len(states),
            "newton_iterations": sum(int(s.newton_iterations) for s in states),
            "converged": all(bool(s.converged) for s in states)}


# ---- running a case ----------------------------------------------------------------------------------

_ASSETS: dict[tuple, Any] = {}


def run_case(case: PhysicsCase, workdir: str | Path | None = None, skinning_iterations: int = 30) -> dict[str, Any]:
    """Run one case; returns its record: ``outcome`` is ``passed``, ``failed`` (a check above), ``refused``
    (an invalid case refused as it should be), ``refused_badly`` (an invalid case simulated, refused without
    naming the parameter, or leaving output), ``stopped`` (:class:`SimulationError`) or ``crashed`` (any other
    exception: a bug)."""
    from vid2sim.physics.solver import SimulationError
    from vid2sim.runtime.errors import InputError
    from vid2sim.simulate.resolve import resolve_scenario
    from vid2sim.simulate.run import run_scenario, simulate

    t0 = time.perf_counter()
    record: dict[str, Any] = {"seed": case.seed, "case": asdict(case)}
    tmp = tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-") if workdir is None else None
    work = Path(tmp.name if tmp is not None else workdir)
    try:
        key = (case.shape, case.handles, case.cubature)
        if key not in _ASSETS:
            if len(_ASSETS) > 16:
                _ASSETS.clear()
            _ASSETS[key] = build_asset(case.shape, case.handles, case.cubature, case.seed, work,
                                       skinning_iterations)
        asset = _ASSETS[key]
        scenario = scenario_of(case, asset)
        if case.invalid is not None:
            out = work / f"out-{case.seed}"
            try:
                simulate(asset, scenario, out, progress=False, video=False)
            except (InputError, ValueError) as exc:
                named = case.invalid[2] in str(exc)
                left = out.exists() or any(p.name.startswith(f".{out.name}") for p in work.iterdir())
                record.update(outcome="refused" if named and not left else "refused_badly",
                              error=f"{type(exc).__name__}: {exc}", output_left=left)
            else:
                record.update(outcome="refused_badly", error="simulated an invalid case")
            return record
        resolved = resolve_scenario(asset, scenario)
        run = run_scenario(asset, resolved)
        checks = check_run(case, run)
        record.update(checks, outcome="passed" if checks["ok"] else "failed")
    except SimulationError as exc:
        record.update(outcome="stopped", error=str(exc))
    except Exception as exc:  # noqa: BLE001 - any other exception is what the fuzzer looks for
        record.update(outcome="crashed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
    finally:
        record["seconds"] = round(time.perf_counter() - t0, 3)
        if tmp is not None:
            tmp.cleanup()
    return record


# ---- the section ----------------------------------------------------------------------------------------

def _worker(seed: int, quick: bool, threads: int) -> dict[str, Any]:
    """One case in a worker process (module-level: pickled by reference)."""
    torch.set_num_threads(threads)
    case = draw_case(seed, quick=quick)
    return run_case(case, skinning_iterations=10 if quick else 30)


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The section's figures from its case records."""
    from collections import Counter

    outcomes = Counter(r["outcome"] for r in records)
    simulated = [r for r in records if r["outcome"] in ("passed", "failed", "stopped", "crashed")
                 and r.get("case", {}).get("invalid") is None]
    judged = [r for r in records if r.get("rest") is not None]
    gains = [r["energy_gain"] for r in records if r.get("energy_gain") is not None]
    return {
        "cases": len(records),
        "outcomes": dict(sorted(outcomes.items())),
        "valid_cases": len(simulated),
        "clean_runs": outcomes.get("passed", 0) + outcomes.get("stopped", 0),
        "clean_runs_note": "valid cases without NaN, accepted inversion or energy gain (passed, or stopped by a "
                           "SimulationError with its message before any output)",
        "invalid_cases": sum(1 for r in records if r.get("case", {}).get("invalid") is not None),
        "invalid_refused_naming_the_parameter": outcomes.get("refused", 0),
        "largest_energy_gain": max(gains) if gains else None,
        "energy_tolerance": ENERGY_TOLERANCE,
        "rest_judged": len(judged),
        "rest_reached": sum(1 for r in judged if r["rest"]),
        "stopped": [{"seed": r["seed"], "error": r.get("error")} for r in records if r["outcome"] == "stopped"][:20],
        "failures": [{"seed": r["seed"], "outcome": r["outcome"], "problems": r.get("problems"),
                      "error": r.get("error")} for r in records
                     if r["outcome"] in ("failed", "crashed", "refused_badly")][:20],
    }


def run(config, records_path: str | Path | None, progress: bool = False) -> dict[str, Any]:
    """``config.physics`` cases (seeds ``config.seed`` …), resumed from ``records_path``; returns the figures."""
    from vid2sim.apps.bench.fuzz.records import RecordFile, read_records, todo

    done = read_records(records_path) if records_path is not None else {}
    sink = RecordFile(records_path)
    indices = todo(range(config.physics), done)
    results = dict(done)

    def finish(i: int, record: dict[str, Any]) -> None:
        record["index"] = i
        results[i] = record
        sink.add(record)
        if progress:
            print(f"physics {len(results)}/{config.physics}: seed {record['seed']} {record['outcome']} "
                  f"({record['seconds']} s)", flush=True)

    if config.workers == 1:
        torch.set_num_threads(config.threads)
        for i in indices:
            finish(i, _worker(config.seed + i, config.quick, config.threads))
    else:
        from concurrent.futures import as_completed

        from vid2sim.runtime.workers import process_pool

        with process_pool(config.workers) as pool:
            futures = {pool.submit(_worker, config.seed + i, config.quick, config.threads): i for i in indices}
            for fut in as_completed(futures):
                finish(futures[fut], fut.result())
    return summarize([results[i] for i in sorted(results) if i < config.physics])
