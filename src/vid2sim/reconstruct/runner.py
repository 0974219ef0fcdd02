"""How the reconstruction's stages run: the Stage protocol, the work folder that caches their outputs, resume.

A stage (:class:`Stage`) reads the shared :class:`Context` (the scene's observed frames, the config, the device)
and the outputs of the stages before it (:class:`State`), writes its own outputs into the work folder
(``run``), and reads them back into the state (``load``). The runner (:func:`run_stages`) calls ``run`` only for a
stage that has not finished, then ``load`` for every stage, so a run interrupted anywhere resumes after its last
finished stage and a finished stage's outputs are the same whether computed now or read back.

Each stage names the config sections it depends on (``sections``) and the version of its method (``revision``).
Its cache key is those sections' values, the revision and the keys of the stages before it (every stage depends
on the ones before), plus the scene; a finished stage whose
key differs from the stored one is an error naming the stage (resume with the same settings, or ``--restart``).
Settings of stages that have not run yet may change between runs. Each stage runs with torch's global generator
seeded from the config's seed and its own name (:func:`stage_seed`), so a resumed run computes what an
uninterrupted one does.

Reconstructions of one scene whose settings agree up to a stage can share that stage's outputs
(:class:`StageSnapshots`): the first saves a copy of its work folder when the stage finishes, the others start
from the copy (``bench ablation``'s variants share the stages up to the appearance).

A stage may also have a ``start`` method: called as soon as the stages before it are loaded, it may start work
in a child process (:class:`BackgroundJob`) that its ``run`` joins later; while one runs, the stages in between
run on one torch thread fewer (the child computes with one thread).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, Sequence

import torch
from tqdm.auto import tqdm

from vid2sim.reconstruct.config import ReconstructConfig
from vid2sim.runtime import config as configs
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import read_json, write_json_atomic
from vid2sim.splats.cameras import Camera

if TYPE_CHECKING:  # annotations only
    from vid2sim.asset import Asset
    from vid2sim.physics import NeuralJacobian, SkinningField
    from vid2sim.reconstruct.stages.points import Cubature, ObjectPoints
    from vid2sim.scene.folder import Scene
    from vid2sim.splats.gaussians import Gaussians


class ReconstructionError(InputError):
    """The scene cannot be reconstructed as given (the message names the view, frame or field)."""


@dataclass
class Observed:
    """The scene's observed views and frames, on the run's device and on the CPU.

    Attributes:
        images, masks: (V, T, H, W, 3) and (V, T, H, W) float32 on the device; ``images_cpu``, ``masks_cpu`` the same
            on the CPU (the geometric stages run there).
        cameras, cameras_cpu: the V observed cameras.
        views: the scene's indices of the observed views; frames: T (observed frames 0 … T−1).
        dt: seconds between frames; gravity: (3,) m/s²; floor_height: m, or None.
    """

    images: torch.Tensor
    masks: torch.Tensor
    cameras: list[Camera]
    images_cpu: torch.Tensor
    masks_cpu: torch.Tensor
    cameras_cpu: list[Camera]
    views: list[int]
    frames: int
    dt: float
    gravity: list[float]
    floor_height: float | None


@dataclass
class State:
    """What the stages hand each other (each field is set by the stage named, on the run's device unless noted).

    Attributes:
        gaussians: ``gaussians`` (refined by ``appearance``).
        obj_cpu, obj: ``points``: the object's interior (:class:`~.stages.points.ObjectPoints`) on the CPU and the
        device.
        carving: ``points``: the record of the carving with the later frames.
        cubature: ``points``: the simulator's cubature points, weights and lumped masses.
        velocity: ``velocity``: the initial-velocity estimate (a JSON dict).
        stage1: ``stage1``: the Stage I record (a JSON dict; "ran" False when it did not run).
        last_layer: ``stage1``: the predicted last layer of the skinning field, or None.
        skinning, jacobian: ``networks``: the skinning field and the Neural Jacobian (or None); ``joint`` updates them.
        calibration: ``calibration``: the stiffness calibration (a JSON dict).
        joint: ``joint``: the joint optimisation's result (a JSON dict).
        asset: ``joint`` (the Gaussians replaced by ``motion_appearance``'s, the continuation set by ``continuation``).
        log: every stage's record for ``log.json``.
    """

    gaussians: "Gaussians | None" = None
    obj_cpu: "ObjectPoints | None" = None
    obj: "ObjectPoints | None" = None
    carving: dict[str, Any] | None = None
    cubature: "Cubature | None" = None
    velocity: dict[str, Any] | None = None
    stage1: dict[str, Any] | None = None
    last_layer: torch.Tensor | None = None
    skinning: "SkinningField | None" = None
    jacobian: "NeuralJacobian | None" = None
    calibration: dict[str, Any] | None = None
    joint: dict[str, Any] | None = None
    asset: "Asset | None" = None
    log: dict[str, Any] = field(default_factory=dict)


class BackgroundJob(Protocol):
    """Work a stage started in a child process (see :class:`~.stages.calibration.TetReferenceJob`)."""

    def check(self) -> None:
        """Raise if the child has ended without its result."""

    def running(self) -> bool:
        """Whether the child still runs."""


@dataclass
class Context:
    """Everything a stage reads besides the outputs of the stages before it.

    Attributes:
        config: the run's settings.
        scene: the loaded scene folder.
        observed: its observed views and frames.
        device: where the fits, the networks and the joint optimisation run.
        work: the work folder (the stages' outputs).
        progress: print stage lines and progress bars.
        threads: the caller's torch thread count.
        rollout_processes: worker processes for the joint optimisation's and the continuation's rollouts on the CPU
            (0: none).
        jobs: background jobs started by stages and not yet joined.
    """

    config: ReconstructConfig
    scene: "Scene"
    observed: Observed
    device: torch.device
    work: "WorkFolder"
    progress: bool
    threads: int
    rollout_processes: int = 0
    jobs: list[BackgroundJob] = field(default_factory=list)

    def say(self, text: str) -> None:
        """A progress line (when progress is on)."""
        if self.progress:
            tqdm.write(text)

    def path(self, name: str) -> Path:
        """The path of the work file ``name``."""
        return self.work.dir / name

    def share_cores(self) -> None:
        """:func:`share_cores` of this run's jobs."""
        share_cores(self.jobs, self.threads)


def share_cores(jobs: Sequence[BackgroundJob], threads: int) -> None:
    """Give running background ``jobs`` one of the caller's ``threads`` (see the module docstring); a job that has
    ended without its result is reported here, at the next stage boundary.

    The child computes with one thread. With it running, a caller on all the cores oversubscribes them, and
    torch's thread pool then slows several-fold (the appearance stage took 3.6× as long with 2 threads as with 1
    on a 2-core machine)."""
    for job in jobs:
        job.check()
    busy = any(job.running() for job in jobs)
    torch.set_num_threads(max(1, threads - 1) if busy else threads)


class Stage(Protocol):
    """One step of the reconstruction (module docstring)."""

    #: the stage's name (its work files' prefix and ``log.json``'s timing key)
    name: str
    #: the config sections (dotted paths) its outputs depend on
    sections: tuple[str, ...]
    #: the version of the stage's method: raised by a release whose change to the stage's code changes its outputs
    #: at the same settings, so that work folders and snapshots of the old method are not resumed as the new one's.
    #: Above 0 it enters the cache key (a stage never revised keeps the key it always had).
    revision: int

    def title(self, ctx: Context, state: State) -> str | None:
        """The progress line when the stage runs, or None when it has nothing to do (it is then skipped)."""

    def run(self, ctx: Context, state: State) -> None:
        """Compute the stage's outputs and write them into the work folder (nothing else)."""

    def load(self, ctx: Context, state: State) -> None:
        """Read the stage's outputs from the work folder into ``state``."""


def _section(config: ReconstructConfig, dotted: str) -> Any:
    value: Any = config
    for part in dotted.split("."):
        value = getattr(value, part)
    return configs.to_dict(value) if hasattr(value, "__dataclass_fields__") else value


def scene_fingerprint(root: Path) -> str:
    """The scene folder ``root`` as a cache key knows it: its resolved path and a digest of its files' names, sizes
    and modification times (not their content: a stat per file), so a scene made again in the same place does not
    resume, or restore snapshots of, the old one's stages."""
    root = Path(root).resolve()
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file() and not p.name.startswith(".")):
        stat = path.stat()
        digest.update(f"{path.relative_to(root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return f"{root}#{digest.hexdigest()[:16]}"


def cache_keys(stages: Sequence[Stage], config: ReconstructConfig, scene: str) -> dict[str, str]:
    """Each stage's cache key: a hash of the scene, the seed, its sections, its revision (when above 0) and the key
    of the stage before it."""
    keys, previous = {}, hashlib.sha256(json.dumps({"scene": scene, "seed": config.seed}).encode()).hexdigest()
    for stage in stages:
        key: dict[str, Any] = {"previous": previous, "sections": {s: _section(config, s) for s in stage.sections}}
        if stage.revision:
            key["revision"] = stage.revision
        text = json.dumps(key, sort_keys=True)
        previous = keys[stage.name] = hashlib.sha256(text.encode()).hexdigest()
    return keys


def stage_seed(seed: int, stage: str) -> int:
    """The seed of torch's global generator while ``stage`` runs: a hash of the config's ``seed`` and the stage's
    name (so it does not depend on which stages ran in this process before it)."""
    return int.from_bytes(hashlib.sha256(f"{seed}:{stage}".encode()).digest()[:7], "little")


@dataclass(frozen=True)
class StageSnapshots:
    """Copies of a work folder taken as named stages finish, shared by reconstructions of the same scene.

    ``dir/STAGE-KEY/`` holds the work folder as it was when ``STAGE`` finished with cache key ``KEY`` (its files,
    ``done`` markers and timings; not ``keys.json``). A reconstruction given the same snapshots and whose key for
    such a stage is the same (same scene, same settings up to that stage) starts from the latest one instead of
    running the stages up to it; its ``timings.json`` then holds the seconds those stages took when they ran, so a
    run's reported time is what it would have cost alone. A snapshot is written whole (a temporary folder renamed
    into place) and never replaced.

    Attributes:
        dir: the snapshots' folder (one per scene: the keys hold the scene's path, but one folder a scene keeps
            them apart for a reader); stages: the stages after which a snapshot is saved.
    """

    dir: Path
    stages: tuple[str, ...]

    def path(self, stage: str, key: str) -> Path:
        """The snapshot of ``stage`` finished with cache ``key``."""
        return Path(self.dir) / f"{stage}-{key[:24]}"

    def restore(self, work: Path, keys: dict[str, str]) -> str | None:
        """Copy into the folder ``work`` the latest snapshot that matches ``keys`` (stage name → cache key, in the
        stages' order), unless ``work`` has already finished that stage; returns the stage restored, or None."""
        for stage in reversed(list(keys)):
            if stage in self.stages and self.path(stage, keys[stage]).is_dir():
                if (work / f"{stage}.done").is_file():
                    return None
                for item in self.path(stage, keys[stage]).iterdir():
                    if item.is_file():
                        shutil.copy2(item, work / item.name)
                return stage
        return None

    def save(self, work: Path, stage: str, key: str) -> None:
        """Copy the folder ``work`` as the snapshot of ``stage`` (cache ``key``), unless there is one."""
        target = self.path(stage, key)
        if target.is_dir():
            return
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.{os.getpid()}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for item in work.iterdir():  # temporary files (".NAME.…") and the keys of the stages to come stay out
            if item.is_file() and not item.name.startswith(".") and item.name != "keys.json":
                shutil.copy2(item, tmp / item.name)
        try:
            tmp.rename(target)
        except OSError:  # another run saved it first
            shutil.rmtree(tmp, ignore_errors=True)


class WorkFolder:
    """The stage cache beside the output folder: ``.OUT.work/`` with ``keys.json`` (each stage's cache key),
    ``STAGE.done`` markers, ``timings.json`` and the stages' files; with ``snapshots``, it starts from the latest
    matching snapshot and saves one as each of their stages finishes (:class:`StageSnapshots`).

    A finished stage whose key differs from ``keys`` (other settings, another scene, or a release that added a
    setting to its sections or revised its method) is refused, so that a slip of the command line does not discard
    hours of work;
    ``restart`` discards the whole folder first, and ``rerun_changed`` keeps the finished stages before the first
    changed one and marks that one and every later one unfinished (``rerun``), as if the run had been interrupted
    there (the keys chain: every stage after a changed one has changed too)."""

    def __init__(self, out: Path, keys: dict[str, str], restart: bool,
                 snapshots: StageSnapshots | None = None, rerun_changed: bool = False) -> None:
        self.dir = out.parent / f".{out.name}.work"
        self.keys, self.snapshots = dict(keys), snapshots
        if restart and self.dir.exists():
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        keys_path = self.dir / "keys.json"
        stored = read_json(keys_path, "a reconstruction's work folder keys", ReconstructionError) \
            if keys_path.is_file() else {}
        #: the finished stages that ``rerun_changed`` marked unfinished because their settings changed
        self.rerun: list[str] = []
        names = list(keys)
        for i, name in enumerate(names):
            if self.done(name) and stored.get(name) != keys[name]:
                if not rerun_changed:
                    raise ReconstructionError(
                        f"{self.dir} holds an interrupted reconstruction whose {name!r} stage ran with other "
                        "settings, on another scene or with an older version of the stage (or the scene's files "
                        "changed since); run with the same settings to "
                        "resume it, with --rerun-changed to keep the stages before it and run it and the later ones "
                        "again, or with --restart to start over")
                self.rerun = [n for n in names[i:] if self.done(n)]
                for n in self.rerun:
                    (self.dir / f"{n}.done").unlink()
                break
        if (self.dir / "key.json").is_file() and not keys_path.is_file():  # a work folder of an older version
            raise ReconstructionError(f"{self.dir} holds an interrupted reconstruction of an older vid2sim; run with "
                                      "--restart to start over")
        write_json_atomic(keys_path, keys)
        #: the stage whose snapshot this folder started from (None: none)
        self.restored = snapshots.restore(self.dir, keys) if snapshots is not None else None
        self.timings_path = self.dir / "timings.json"
        self.timings = read_json(self.timings_path, "stage timings", ReconstructionError) \
            if self.timings_path.is_file() else {}

    def done(self, stage: str) -> bool:
        """Whether ``stage`` has finished (its outputs are complete)."""
        return (self.dir / f"{stage}.done").is_file()

    def finish(self, stage: str, seconds: float | None) -> None:
        """Mark ``stage`` finished after ``seconds`` (None: it had nothing to do, and gets no timing)."""
        if seconds is not None:
            self.timings[stage] = seconds
            write_json_atomic(self.timings_path, self.timings)
        (self.dir / f"{stage}.done").write_text("")
        if self.snapshots is not None and stage in self.snapshots.stages:
            self.snapshots.save(self.dir, stage, self.keys[stage])


def run_stages(stages: Sequence[Stage], ctx: Context, state: State) -> State:
    """Run (or resume) ``stages`` in order (module docstring); returns ``state`` filled by their ``load``."""
    started = set()
    for i, stage in enumerate(stages):
        for later in stages[i:]:  # start the background work whose inputs are ready
            start = getattr(later, "start", None)
            if start is not None and later.name not in started and not ctx.work.done(later.name) \
                    and later.ready(state):
                started.add(later.name)
                start(ctx, state)
        ctx.share_cores()
        if not ctx.work.done(stage.name):
            title = stage.title(ctx, state)
            t0 = time.perf_counter()
            if title is not None:
                ctx.say(f"[{i + 1}/{len(stages)}] {title}")
                torch.manual_seed(stage_seed(ctx.config.seed, stage.name))
                stage.run(ctx, state)
            ctx.work.finish(stage.name, time.perf_counter() - t0 if title is not None else None)
        stage.load(ctx, state)
    ctx.share_cores()
    return state
