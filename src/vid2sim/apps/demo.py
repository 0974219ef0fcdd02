"""``vid2sim demo``: the whole product once, on a laptop CPU — a synthetic drop in, a simulation-ready asset,
its scores, a simulation of it in a new situation and an HTML report out.

Steps (each kept in the output folder, so running the same command again resumes after the last finished
one):

1. ``scene/`` — a procedural object dropped on the floor, simulated by the FEM (converged in time) with a known
   material and rendered in a ring of cameras (:func:`vid2sim.synthetic.scenes.make_scene`);
2. ``asset/`` — reconstructed from the observed views and frames (:func:`vid2sim.reconstruct.pipeline.reconstruct`);
3. ``asset/evaluation.json`` — PSNR / SSIM on observed, future and novel views, material and Chamfer errors
   (:func:`vid2sim.evaluate.scores.evaluate`);
4. ``simulation/`` — the asset in a situation it was never seen in (:mod:`vid2sim.simulate.run`);
5. ``report/index.html`` — everything above, to open in a browser (:mod:`vid2sim.report`).

``DemoConfig.size = "small"`` is the README's demo (about 6 minutes on two CPU cores); ``"tiny"`` runs the same
steps at toy sizes in about a minute to check an installation (its numbers mean nothing).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vid2sim.apps.report import asset_report
from vid2sim.asset.folder import load_asset
from vid2sim.evaluate.scores import evaluate, write_evaluation
from vid2sim.reconstruct.pipeline import ReconstructConfig, reconstruct
from vid2sim.reconstruct.rollouts import spare_threads
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import ConfigError
from vid2sim.simulate.run import simulate
from vid2sim.simulate.scenario import ObstacleSpec, Scenario
from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene

if TYPE_CHECKING:
    import torch

    from vid2sim.reconstruct.pipeline import ReconstructConfig
    from vid2sim.simulate.scenario import Scenario
    from vid2sim.synthetic.scenes import SyntheticSceneConfig

SIZES = ("small", "tiny")
#: the reconstruction at toy sizes (``--size tiny``: checks an installation in about a minute; the tests' shared
#: asset too), on top of the defaults. The Gaussians stay at the visual hull's 5 000 (no densification): more than
#: the pixels of the toy views (4 × 40²), and half the joint stage's rendering time of the 11 000 it would grow to
TINY = {"gaussians": {"iterations": 30, "densify": {"max_gaussians": 5000}},
        "points": {"resolution": 24, "num_points": 1000},
        "appearance": {"iterations": 5}, "motion_appearance": {"iterations": 5},
        "networks": {"handles": 3, "skinning_iterations": 10}, "simulator": {"cubature": 60},
        "calibration": {"enabled": False},
        "joint": {"iterations": 2, "gauss_newton_iterations": 1, "coarse_log10_E": [4.5, 5.0], "validate_every": 1,
                  "window": 2}}


@dataclass
class DemoConfig:
    """Settings of :func:`run_demo` (saved as ``demo_config.json`` in the output folder).

    Attributes:
        size: "small" (the README's demo: 6-view 128² scene, the small reconstruction preset) or "tiny"
            (toy sizes, to check an installation).
        seed: seed of the procedural object, its texture and its drop.
        youngs_modulus: the true E of the scene (Pa); the reconstruction starts from 1e5 Pa.
        poisson_ratio: the true ν; the reconstruction starts from 0.3.
        scenario: the new situation to simulate, as :class:`vid2sim.simulate.scenario.Scenario` fields
            (a YAML-like dict): by default the object dropped from higher onto a ball lying on the floor,
            seen by a camera orbiting it.
    """

    size: str = "small"
    seed: int = 0
    youngs_modulus: float = 2e5
    poisson_ratio: float = 0.4
    scenario: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.size not in SIZES:
            raise ConfigError(f"DemoConfig.size must be one of {SIZES}, got {self.size!r}")

    def scene_config(self) -> "SyntheticSceneConfig":
        """The synthetic scene: the small preset (6 views, 128², 24 frames) or a toy version of it."""

        toy = {"frames": 6, "observed_frames": 5, "resolution": 40, "views": 4, "held_out_views": 1,
               "substeps": 4} if self.size == "tiny" else {}
        return SyntheticSceneConfig.preset("small", seed=self.seed, youngs_modulus=self.youngs_modulus,
                                           poisson_ratio=self.poisson_ratio, **toy)

    def reconstruct_config(self) -> "ReconstructConfig":
        """The reconstruction: the small preset, or toy sizes."""

        if self.size == "small":
            return ReconstructConfig.preset("small", {"seed": self.seed})
        return configs.merge(ReconstructConfig(), {**TINY, "seed": self.seed})

    def new_scenario(self) -> "Scenario":
        """The new situation: the object lifted 30 cm and dropped onto a ball lying on the floor, filmed by a
        camera orbiting it (``scenario`` fields override)."""

        frames = 8 if self.size == "tiny" else 36
        resolution = 32 if self.size == "tiny" else 160
        base: dict[str, Any] = {"frames": frames, "resolution": resolution,
                                "initial": {"translation": [0.0, 0.0, 0.3], "euler_deg": [0.0, 25.0, 0.0]},
                                "cameras": {"type": "orbit"}}
        return Scenario.from_dict({**base, **self.scenario}, source="DemoConfig.scenario")


@dataclass
class DemoResult:
    """What :func:`run_demo` made: the folders and the material recovered against the truth."""

    out: Path
    scene: Path
    asset: Path
    simulation: Path
    report: Path
    true_E: float
    true_nu: float
    found_E: float
    found_nu: float
    evaluation: dict[str, Any]
    seconds: dict[str, float]


STEPS = ("scene", "asset", "evaluation", "simulation", "report")


def _ball_under(asset_path: Path, drop: float) -> dict[str, Any]:
    """A ball on the floor under the asset's frame-0 centre (radius a third of the object's size), clear of
    the object lifted by ``drop`` metres."""

    asset = load_asset(asset_path)
    pts = asset.points
    lo, hi = pts.min(0).values, pts.max(0).values
    centre = 0.5 * (lo + hi)
    size = float((hi - lo).max())
    floor = asset.floor_height if asset.floor_height is not None else float(lo[2]) - 0.05
    radius = size / 3.0
    top = float(lo[2]) + drop  # the lifted object's lowest point
    z = min(floor + 0.6 * radius, top - 1.2 * radius)  # partly sunk into the floor, below the object
    return {"center": [float(centre[0]), float(centre[1]), z], "radius": radius}


def run_demo(out: str | Path, config: DemoConfig | None = None, progress: bool = True,
             workers: int = 1, device: "str | torch.device | None" = None) -> DemoResult:
    """Run the demo into ``out`` (created, or resumed after its last finished step; module docstring).

    ``device`` (None: CUDA when available, else the CPU) runs the reconstruction's optimisations, the
    evaluation, the simulation and the report's renders; the synthetic scene is made on the CPU.

    Returns:
        a :class:`DemoResult`; ``out/demo.json`` holds the same figures.
    Raises:
        FileExistsError: ``out`` holds something other than an earlier demo with the same settings.
    """

    cfg = config or DemoConfig()
    out = Path(out)
    settings = out / "demo_config.json"
    if out.exists() and any(out.iterdir()):
        if not settings.is_file():
            raise FileExistsError(f"{out} is a non-empty folder that is not a vid2sim demo; choose another OUT")
        earlier = json.loads(settings.read_text())
        if earlier != asdict(cfg):
            raise FileExistsError(f"{out} holds a demo made with other settings ({earlier}); choose another OUT "
                                  "or delete it")
    out.mkdir(parents=True, exist_ok=True)
    settings.write_text(json.dumps(asdict(cfg), indent=2))
    scene, asset, sim, report = out / "scene", out / "asset", out / "simulation", out / "report"
    timing_file = out / "timings.json"
    seconds: dict[str, float] = json.loads(timing_file.read_text()) if timing_file.is_file() else {}

    def step(name: str, n: int, message: str) -> float:
        if progress:
            print(f"[demo {n}/{len(STEPS)}] {message}", flush=True)
        return time.perf_counter()

    def done(name: str, t0: float) -> None:
        seconds[name] = time.perf_counter() - t0
        timing_file.write_text(json.dumps(seconds, indent=2))

    if not (scene / "scene.json").is_file():
        t0 = step("scene", 1, f"making a synthetic drop (FEM ground truth, E = {cfg.youngs_modulus:g} Pa, "
                              f"nu = {cfg.poisson_ratio:g}) in {scene}")
        make_scene(cfg.scene_config(), scene, overwrite=True, progress=progress, workers=workers)
        done("scene", t0)
    if not (asset / "asset.json").is_file():
        t0 = step("asset", 2, f"reconstructing it from its observed views and frames into {asset}")
        reconstruct(scene, asset, cfg.reconstruct_config(), progress=progress, device=device,
                    rollout_processes=spare_threads())
        done("asset", t0)
    evaluation_path = asset / "evaluation.json"
    renders = None
    if not evaluation_path.is_file():
        t0 = step("evaluation", 3, "scoring it on observed, future and held-out views")
        evaluation, renders = evaluate(asset, scene, progress=progress, return_renders=True, device=device)
        write_evaluation(evaluation, evaluation_path)
        done("evaluation", t0)
    evaluation = json.loads(evaluation_path.read_text())
    if not (sim / "summary.json").is_file():
        t0 = step("simulation", 4, f"simulating it in a new situation (dropped onto a ball) into {sim}")
        scenario = cfg.new_scenario()
        if "obstacles" not in cfg.scenario:

            ball = _ball_under(asset, drop=0.3)
            scenario.obstacles.append(ObstacleSpec(center=tuple(ball["center"]), radius=ball["radius"]))
        simulate(asset, scenario, sim, progress=progress, overwrite=True, device=device)
        done("simulation", t0)
    t0 = step("report", 5, f"writing the report {report / 'index.html'}")
    asset_report(report, asset, scene=scene, evaluation=evaluation, renders=renders, progress=progress,
                 simulations=[sim], device=device)
    done("report", t0)
    material = evaluation["material"]
    result = DemoResult(out=out, scene=scene, asset=asset, simulation=sim, report=report,
                        true_E=float(material["truth"]["E"]), true_nu=float(material["truth"]["nu"]),
                        found_E=float(material["fitted"]["E"]), found_nu=float(material["fitted"]["nu"]),
                        evaluation=evaluation, seconds=seconds)
    summary = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(result).items() if k != "evaluation"}
    (out / "demo.json").write_text(json.dumps(summary, indent=2))
    return result
