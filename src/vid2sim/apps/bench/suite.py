"""``vid2sim bench suite``: reconstruct + evaluate every scene of a ``make-benchmark`` suite, and the table.

For each scene ``NAME`` listed in ``SUITE/index.json`` (:func:`vid2sim.synthetic.scenes.make_benchmark`):

1. ``OUT/NAME/asset`` — :func:`vid2sim.reconstruct.pipeline.reconstruct` with the suite's
   :class:`SuiteConfig` (skipped when a complete asset is already there; a reconstruction interrupted
   half-way resumes after its last finished stage through reconstruct's own work folder);
2. ``OUT/NAME/evaluation.json`` — :func:`vid2sim.evaluate.scores.evaluate` of that asset on the scene
   (written last and atomically: a scene with this file is finished and skipped by the next run);
3. ``OUT/NAME/run.json`` — the scene's wall time; ``OUT/NAME/error.txt`` — the traceback when it failed.

A scene that raises is recorded as failed with its error message and the suite goes on; rerunning the
command retries the failed and unfinished scenes only. The scenes run one after the other in this process,
or as Ray tasks (``ray_address``, :mod:`vid2sim.runtime.ray_runner`) with the same code and seeds, so the
numbers do not depend on where a scene ran. ``OUT/suite.json`` (written atomically at the end) holds
every scene's record and the means over the finished scenes (schema in :func:`run_suite`);
``OUT/suite_config.json`` the settings, checked when a run resumes. :func:`format_table` prints the
paper's Table 1 layout: one row per metric and subset, one column per scene, then the mean.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vid2sim.evaluate.scores import evaluate, write_evaluation
from vid2sim.reconstruct.pipeline import ReconstructConfig, reconstruct
from vid2sim.reconstruct.rollouts import spare_threads
from vid2sim.reconstruct.runner import StageSnapshots
from vid2sim.report import write_report, write_suite_report
from vid2sim.runtime.errors import ConfigError, InputError
from vid2sim.runtime.files import check_output_folder, remove_temp_files, write_json_atomic
from vid2sim.runtime.ray_runner import check_ray, ray_map

if TYPE_CHECKING:
    from vid2sim.reconstruct.pipeline import ReconstructConfig

SUITE_JSON = "suite.json"
SUITE_CONFIG_JSON = "suite_config.json"
EVALUATION_JSON = "evaluation.json"
RUN_JSON = "run.json"
ERROR_TXT = "error.txt"
REPORT_DIR = "report"  # the HTML reports: OUT/report (the suite) and OUT/NAME/report (each scene)

# suite.json "means" key -> path into a scene's evaluation.json (``seconds`` is the scene record's own)
METRICS: dict[str, tuple[str, ...]] = {
    "dynamic_psnr": ("dynamic", "psnr"),
    "dynamic_ssim": ("dynamic", "ssim"),
    "future_psnr": ("future", "psnr"),
    "future_ssim": ("future", "ssim"),
    "future_from_start_psnr": ("future_from_start", "psnr"),
    "novel_psnr": ("novel_views", "psnr"),
    "novel_ssim": ("novel_views", "ssim"),
    "rest_psnr": ("rest", "psnr"),
    "abs_error_log10_E": ("material", "abs_error_log10_E"),
    "abs_error_nu": ("material", "abs_error_nu"),
    "start_abs_error_log10_E": ("material", "start", "abs_error_log10_E"),
    "start_abs_error_nu": ("material", "start", "abs_error_nu"),
    "chamfer_observed": ("chamfer", "observed_mean"),
    "chamfer_future": ("chamfer", "future_mean"),
    "centre_of_mass_frame_0": ("centre_of_mass", "frame_0"),
    "centre_of_mass_observed": ("centre_of_mass", "observed_mean"),
    "centre_of_mass_future": ("centre_of_mass", "future_mean"),
    "rotation_observed": ("orientation", "observed_mean_deg"),
    "rotation_future": ("orientation", "future_mean_deg"),
    "first_contact_added_centre_of_mass": ("contacts", "first_added_centre_of_mass_m"),
    "first_contact_added_rotation": ("contacts", "first_added_rotation_deg"),
    "solid_frequency_ratio": ("geometry_stiffness", "lowest_frequency_ratio"),
    "solid_volume_ratio": ("solid", "volume_ratio"),
    "solid_bottom_offset": ("solid", "bottom_offset_m"),
    "interval_covers_log10_E": ("material", "interval_covers_truth", "log10_E"),
    "interval_covers_nu": ("material", "interval_covers_truth", "nu"),
    "joint_improved": ("material", "fit", "improved"),
    "seconds": (),
}


@dataclass
class SuiteConfig:
    """Settings of :func:`run_suite` (saved as ``OUT/suite_config.json``).

    Attributes:
        preset: the reconstruction preset, "small" (CPU minutes per scene) or "full" (the paper's sizes);
            see :meth:`vid2sim.reconstruct.pipeline.ReconstructConfig.preset`.
        iterations: joint-optimisation iterations of the reconstruction's method instead of the preset's
            (:meth:`~vid2sim.reconstruct.config.JointConfig.with_iterations`: Gauss–Newton steps by default, Adam
            iterations with ``joint.method`` "windows"; None: the preset's).
        reconstruct: a complete ReconstructConfig used instead of the preset (tests, studies); ``iterations``
            still applies when given. suite.json then names the preset "custom".
        threads: torch threads per scene (None: torch's default in this process, 1 in a Ray task); a Ray
            task reserves this many CPUs. The thread count can change float sums in the last bits, so
            compare runs made with the same count.
        fovvdp: also score FoVVDP (needs the optional pyfvvdp).
    """

    preset: str = "small"
    iterations: int | None = None
    reconstruct: "ReconstructConfig | None" = None
    threads: int | None = None
    fovvdp: bool = False

    def __post_init__(self) -> None:
        if self.preset not in ("small", "full"):
            raise ConfigError(f"SuiteConfig.preset must be 'small' or 'full', got {self.preset!r}")
        if self.iterations is not None and (isinstance(self.iterations, bool) or not isinstance(self.iterations, int)
                                            or self.iterations < 0):
            raise ConfigError(f"SuiteConfig.iterations must be an integer >= 0, got {self.iterations!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):
            raise ConfigError(f"SuiteConfig.threads must be an integer >= 1, got {self.threads!r}")

    @property
    def preset_name(self) -> str:
        """The preset as suite.json names it: the preset, or "custom" for a ReconstructConfig other than the
        preset's."""

        differs = self.reconstruct is not None and self.reconstruct != ReconstructConfig.preset(self.preset)
        return "custom" if differs else self.preset

    def reconstruct_config(self) -> "ReconstructConfig":
        """The ReconstructConfig every scene uses (a fresh copy)."""

        cfg = copy.deepcopy(self.reconstruct) if self.reconstruct is not None else ReconstructConfig.preset(self.preset)
        if self.iterations is not None:
            cfg.joint = cfg.joint.with_iterations(self.iterations)
        return cfg

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the settings and the resolved ReconstructConfig."""
        return {"preset": self.preset_name, "iterations": self.iterations, "threads": self.threads,
                "fovvdp": self.fovvdp, "reconstruct": self.reconstruct_config().to_dict()}


@dataclass
class SceneTask:
    """One scene's job (picklable: it travels to a Ray worker). Paths are absolute."""

    name: str
    scene: str
    out: str
    config: SuiteConfig = field(default_factory=SuiteConfig)
    #: stage snapshots shared with other runs on this scene (:class:`~vid2sim.reconstruct.runner.StageSnapshots`)
    snapshots: StageSnapshots | None = None
    #: an interrupted reconstruction whose settings differ from a stage on runs that stage and the later ones again
    #: (``reconstruct(rerun_changed=)``) instead of failing
    rerun_changed: bool = False


def run_scene(task: SceneTask, progress: bool = False) -> dict[str, Any]:
    """Reconstruct and evaluate one scene into ``task.out`` (= ``OUT/NAME``); never raises for the scene's
    own errors (KeyboardInterrupt and the like still propagate).

    Returns:
        the scene record of suite.json: ``name``, ``scene``, ``asset`` (path or None), ``status`` ("ok" |
        "failed"), ``error`` (``"Type: message"`` or None), ``evaluation`` (the evaluation.json dict or
        None), ``report`` (the scene's HTML report folder, ``OUT/NAME/report``), ``seconds`` (wall time of reconstruct +
        evaluate, including the stage times an interrupted earlier run recorded and those of stages restored from a
        snapshot (log.json ``restored``); the report's time is not counted).
    """
    import torch


    out = Path(task.out)
    asset = out / "asset"
    record = _unfinished_record(task, "failed")
    threads = torch.get_num_threads()
    start = time.perf_counter()
    earlier = _interrupted_stage_seconds(asset)
    try:
        if task.config.threads is not None:
            torch.set_num_threads(task.config.threads)
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        if not (asset / "asset.json").is_file():  # save_asset moves a complete folder into place
            reconstruct(task.scene, asset, task.config.reconstruct_config(), progress=progress,
                        snapshots=task.snapshots, rerun_changed=task.rerun_changed,
                        rollout_processes=spare_threads())  # the scene's threads beyond one
            earlier += _restored_seconds(asset)
        else:
            earlier = _finished_asset_seconds(asset)
        record["asset"] = str(asset)
        t1 = time.perf_counter()
        report, renders = evaluate(asset, task.scene, fovvdp=task.config.fovvdp, progress=progress,
                                   return_renders=True)
        t2 = time.perf_counter()
        seconds = earlier + (t2 - start)
        write_json_atomic(out / RUN_JSON, {"seconds": seconds, "reconstruct_seconds": earlier + (t1 - t0),
                                            "evaluate_seconds": t2 - t1})
        write_report(out / REPORT_DIR, asset, scene=task.scene, evaluation=report, renders=renders,
                          progress=progress)
        write_evaluation(report, out / EVALUATION_JSON)  # last: its presence marks the scene finished
        (out / ERROR_TXT).unlink(missing_ok=True)
        record.update(status="ok", evaluation=report, seconds=seconds, report=str(out / REPORT_DIR))
    except Exception as exc:
        record.update(error=f"{type(exc).__name__}: {exc}", seconds=earlier + time.perf_counter() - start)
        if (asset / "asset.json").is_file():
            record["asset"] = str(asset)
        try:
            out.mkdir(parents=True, exist_ok=True)
            (out / ERROR_TXT).write_text(traceback.format_exc())
        except OSError:
            pass
    finally:
        torch.set_num_threads(threads)
    return record


def _interrupted_stage_seconds(asset: Path) -> float:
    """Seconds of the stages an interrupted reconstruction of ``asset`` finished (its work folder's
    timings.json), 0 when there is none."""
    work = asset.parent / f".{asset.name}.work"
    try:
        timings = json.loads((work / "timings.json").read_text())
        return float(sum(v for k, v in timings.items() if (work / f"{k}.done").is_file()))
    except (OSError, ValueError, TypeError, AttributeError):
        return 0.0


def _restored_seconds(asset: Path) -> float:
    """Seconds of the stages a finished asset restored from a snapshot (its log.json ``restored``), 0 if none."""
    try:
        return float((json.loads((asset / "log.json").read_text()).get("restored") or {}).get("seconds", 0.0))
    except (OSError, ValueError, TypeError, AttributeError):
        return 0.0


def _finished_asset_seconds(asset: Path) -> float:
    """Seconds the stages of a finished asset took (its log.json), 0 when unknown."""
    try:
        return float(sum(json.loads((asset / "log.json").read_text())["timings_seconds"].values()))
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return 0.0


def _unfinished_record(task: SceneTask, status: str, error: str | None = None) -> dict[str, Any]:
    """The record of a scene without a finished evaluation: ``status`` "failed" (with its ``error``) or "pending"."""
    return {"name": task.name, "scene": task.scene, "asset": None, "status": status, "error": error,
            "evaluation": None, "report": None, "seconds": 0.0}


def _finished_record(task: SceneTask) -> dict[str, Any] | None:
    """The record of a scene finished by an earlier run (its evaluation.json exists), else None."""
    out = Path(task.out)
    try:
        evaluation = json.loads((out / EVALUATION_JSON).read_text())
    except FileNotFoundError:
        return None
    except ValueError as exc:
        raise InputError(f"{out / EVALUATION_JSON} is not valid JSON ({exc}); delete it to rerun the scene") from None
    try:
        seconds = float(json.loads((out / RUN_JSON).read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        seconds = _finished_asset_seconds(out / "asset") + float(evaluation.get("timing", {}).get("seconds", 0.0))
    report = out / REPORT_DIR
    return {"name": task.name, "scene": task.scene, "asset": str(out / "asset"), "status": "ok", "error": None,
            "evaluation": evaluation, "report": str(report) if (report / "index.html").is_file() else None,
            "seconds": seconds}


def suite_index(suite_dir: str | Path) -> tuple[list[str], list[str]]:
    """The scene names of a ``make-benchmark`` suite (its ``index.json``): all of them, in order, and those made
    so far (all unless the suite was made in shards that have not all run, ``make-benchmark --scenes``).

    Raises:
        FileNotFoundError: no ``index.json``. InputError: not a benchmark index, or a listed scene folder that is
            missing.
    """
    root = Path(suite_dir)
    path = root / "index.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: SUITE must be a folder written by vid2sim make-benchmark")
    try:
        index = json.loads(path.read_text())
        made = [str(s["name"]) for s in index["scenes"]]
        n = int(index.get("n", len(made)))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} is not a make-benchmark index (expected 'scenes': [{{'name': ...}}, ...]): "
                         f"{exc!r}") from None
    missing = [name for name in made if not (root / name).is_dir()]
    if missing:
        raise InputError(f"{path} lists scenes whose folders are missing: {', '.join(missing)}")
    if index.get("complete", True) and len(made) == n:
        return made, made
    return [f"scene_{i:03d}" for i in range(n)], made  # make-benchmark names scene i so


def read_index(suite_dir: str | Path, scenes: slice | None = None) -> list[str]:
    """The scene names of a finished ``make-benchmark`` suite (its ``index.json``), in order; with ``scenes``
    only that slice of them, which must be made (the rest of the suite need not be).

    Raises:
        FileNotFoundError: no ``index.json``. InputError: not a benchmark index, an unfinished suite (or a
            selected scene not made yet), a selection of no scene, or a listed scene folder that is missing.
    """
    return select_scenes(suite_dir, *suite_index(suite_dir), scenes)


def select_scenes(suite_dir: str | Path, names: list[str], made: list[str], scenes: slice | None) -> list[str]:
    """:func:`read_index`'s answer from the suite's :func:`suite_index` (``names``, ``made``)."""
    path = Path(suite_dir) / "index.json"
    selected = names if scenes is None else names[scenes]
    if not selected:
        raise InputError(f"--scenes selects none of the {len(names)} scenes of {path}")
    unmade = [name for name in selected if name not in made]
    if unmade:
        what = "its" if scenes is None else "the selected"
        listed = ", ".join(unmade[:5]) + (f" and {len(unmade) - 5} more" if len(unmade) > 5 else "")
        raise InputError(f"{path} lists {len(made)} of its {len(names)} scenes: make-benchmark did not make "
                         f"{what} {listed} yet; run it again with the same settings to complete the "
                         "suite" + ("" if scenes is None else " (or that shard, --scenes)"))
    return selected


def run_suite(suite_dir: str | Path, out_dir: str | Path, config: SuiteConfig | None = None,
              progress: bool = True, ray_address: str | None = None,
              snapshots: StageSnapshots | None = None, rerun_changed: bool = False,
              scenes: slice | None = None) -> dict[str, Any]:
    """Reconstruct and evaluate every scene of the suite at ``suite_dir`` into ``out_dir`` (module docstring).

    Args:
        suite_dir: a finished ``make-benchmark`` folder (``index.json`` + scene folders).
        out_dir: the results folder (created; resumed when it holds a ``suite_config.json``).
        config: the settings (default :class:`SuiteConfig`).
        progress: a progress bar over the scenes.
        ray_address: run every unfinished scene as a Ray task there ("local", "auto", "HOST:PORT", …;
            :mod:`vid2sim.runtime.ray_runner`) instead of one after the other here.
        snapshots: stage snapshots shared with other suites over the same scenes (``bench ablation``'s variants):
            scene NAME's are in ``snapshots.dir / NAME`` (a folder the Ray workers can reach, like ``out_dir``).
        rerun_changed: a scene's interrupted reconstruction whose settings differ from a stage on (a release that
            added a setting, say) keeps its stages before that one and runs the rest again, instead of failing.
        scenes: run only this slice of the suite's scenes (a shard; they must be made, the others need not be).
            Other runs, here or elsewhere, may do the rest into the same ``out_dir``.
    Returns:
        the content of ``out_dir/suite.json``: ``{"suite": path, "preset": str, "scenes": [record, ...],
        "means": {key: float | None}, "failed": int}`` with the scene records of :func:`run_scene` in the
        order of ``index.json`` and the means (keys :data:`METRICS`) over the scenes with status "ok"
        (None when no finished scene has that metric). With ``scenes``, the records are this run's and those
        of the other scenes already finished in ``out_dir``.
    Raises:
        FileNotFoundError / ValueError: not a finished suite; ``out_dir`` is a foreign non-empty folder or
            holds a run made with other settings.
        vid2sim.runtime.ray_runner.RayUnavailable: ``ray_address`` given but Ray missing or unreachable.
    """
    from tqdm.auto import tqdm

    config = config or SuiteConfig()
    if ray_address is not None:  # fail before writing anything

        check_ray(ray_address)
    suite = Path(suite_dir).resolve()
    out = Path(out_dir).resolve()
    names, made = suite_index(suite)
    selected = set(select_scenes(suite, names, made, scenes))
    settings = {"suite": str(suite), **config.to_dict()}
    _prepare_out(out, settings)
    tasks = [SceneTask(name, str(suite / name), str(out / name), config,
                       None if snapshots is None else dataclasses.replace(snapshots, dir=Path(snapshots.dir) / name),
                       rerun_changed)
             for name in names]
    records: list[dict[str, Any] | None] = [_finished_record(t) for t in tasks]
    todo = [i for i, r in enumerate(records) if r is None and names[i] in selected]
    bar = tqdm(total=len(selected), initial=len(selected) - len(todo), desc="suite", unit="scene",
               disable=not progress)
    failed: list[str] = []

    def done(i: int, record: dict[str, Any]) -> None:
        records[i] = record
        if record["status"] != "ok":
            failed.append(record["name"])
            if progress:  # quiet runs list the failures in the table
                bar.write(f"[suite] {record['name']} failed: {record['error']}")
        bar.set_postfix_str(f"{record['name']} done" + (f", {len(failed)} failed" if failed else ""))
        bar.update(1)

    try:
        if ray_address is None:
            for i in todo:
                bar.set_postfix_str(f"{names[i]} running" + (f", {len(failed)} failed" if failed else ""))
                done(i, run_scene(tasks[i]))
        else:

            def gathered(i: int, result: Any) -> None:
                if isinstance(result, BaseException):  # the worker or its node died: the task never returned
                    t = tasks[i]
                    result = _unfinished_record(t, "failed", f"{type(result).__name__}: {result}")
                done(i, result)

            threads = config.threads or 1  # a task reserves this many CPUs and uses as many torch threads
            calls = [((dataclasses.replace(tasks[i], config=dataclasses.replace(config, threads=threads)),), {})
                     for i in todo]
            ray_map(run_scene, calls, ray_address, num_cpus=threads,
                    on_done=lambda k, result: gathered(todo[k], result))
    finally:
        bar.close()
    result = suite_summary(str(suite), config.preset_name, [r for r in records if r is not None])
    write_json_atomic(out / SUITE_JSON, result)

    write_suite_report(out / REPORT_DIR, result)
    return result


def check_out(out: Path, settings: dict[str, Any]) -> None:
    """Raise unless ``out`` can take a run with ``settings`` (``{"suite": path, **SuiteConfig.to_dict()}``):
    absent, empty, or resumable (its suite_config.json has the same settings). Writes nothing."""
    path = out / SUITE_CONFIG_JSON
    check_output_folder(out, path.is_file(), SUITE_CONFIG_JSON, "a suite")
    if path.is_file():
        previous = json.loads(path.read_text())
        # the resolved ReconstructConfig, not the preset's name: a run pinned with --config resumes after a release
        # changed the preset (its name then reads "custom"); the earlier settings read as this release reads a
        # config.json, so that a setting added since, at its default, is no difference; threads may change
        try:
            previous["reconstruct"] = ReconstructConfig.from_dict(previous["reconstruct"]).to_dict()
        except (ConfigError, KeyError, TypeError, ValueError):
            pass  # not a config this release reads: compared as it is, and so refused
        keys = ("suite", "iterations", "fovvdp", "reconstruct")
        differ = [k for k in keys if previous.get(k) != settings.get(k)]
        if differ:
            raise InputError(f"{out} holds a suite run with other settings ({', '.join(differ)} differ; see "
                             f"{path}): resume it with the same settings, or write to another folder")


def _prepare_out(out: Path, settings: dict[str, Any]) -> None:
    """Create ``out`` and its suite_config.json, or check that an earlier run there used ``settings``."""
    check_out(out, settings)
    out.mkdir(parents=True, exist_ok=True)
    remove_temp_files(out)  # what a run killed while writing a file left
    write_json_atomic(out / SUITE_CONFIG_JSON, settings)


def _metric(record: dict[str, Any], key: str) -> float | None:
    """The value of ``key`` (a :data:`METRICS` key) in a scene record, or None."""
    if key == "seconds":
        return record.get("seconds")
    value: Any = record.get("evaluation")
    for part in METRICS[key]:
        if not isinstance(value, dict):
            return None
        value = value.get(part)
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def suite_summary(suite: str, preset: str, records: list[dict[str, Any]]) -> dict[str, Any]:
    """The suite.json dict of these scene records: the means over the "ok" ones (None where none has the
    metric) and the number of failed scenes."""
    ok = [r for r in records if r["status"] == "ok"]
    means: dict[str, float | None] = {}
    for key in METRICS:
        values = [v for v in (_metric(r, key) for r in ok) if v is not None and math.isfinite(v)]
        means[key] = sum(values) / len(values) if values else None
    return {"suite": suite, "preset": preset, "scenes": records, "means": means,
            "failed": sum(r["status"] == "failed" for r in records)}


def suite_so_far(out_dir: str | Path) -> dict[str, Any]:
    """The :func:`suite_summary` of a ``bench suite`` results folder as it stands, finished or still running: the
    scenes with an evaluation.json are "ok", those with only an error.txt "failed" (``error``: its last line), the
    others "pending" (not reached yet, or running). Reads the folder only.

    Raises:
        InputError: ``out_dir`` holds no readable suite_config.json (not a ``bench suite`` results folder), or the
            suite it names is not there any more.
    """
    out = Path(out_dir)
    path = out / SUITE_CONFIG_JSON
    try:
        settings = json.loads(path.read_text())
        suite, preset = str(settings["suite"]), str(settings["preset"])
    except FileNotFoundError:
        raise InputError(f"{path} not found: OUT must be a results folder of vid2sim bench suite") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} is not a bench suite settings file: {exc!r}") from None
    try:
        names = suite_index(suite)[0]
    except FileNotFoundError as exc:
        raise InputError(f"the suite {suite} named in {path} is not readable: {exc}") from None
    records = []
    for name in names:
        task = SceneTask(name, str(Path(suite) / name), str(out / name))
        record = _finished_record(task)
        if record is None:
            error = out / name / ERROR_TXT
            lines = error.read_text(errors="replace").strip().splitlines() if error.is_file() else []
            record = _unfinished_record(task, "failed", lines[-1]) if lines else _unfinished_record(task, "pending")
        records.append(record)
    return suite_summary(suite, preset, records)


# the table: (group label, row label, suite key, scale, decimals)
TABLE_ROWS: list[tuple[str, str, str, float, int]] = [
    ("PSNR (dB)", "dynamic", "dynamic_psnr", 1.0, 2),
    ("", "future", "future_psnr", 1.0, 2),
    ("", "future, one rollout from frame 0", "future_from_start_psnr", 1.0, 2),
    ("", "novel views", "novel_psnr", 1.0, 2),
    ("", "at rest (frame 0)", "rest_psnr", 1.0, 2),
    ("SSIM", "dynamic", "dynamic_ssim", 1.0, 3),
    ("", "future", "future_ssim", 1.0, 3),
    ("", "novel views", "novel_ssim", 1.0, 3),
    ("|d log10 E|", "", "abs_error_log10_E", 1.0, 3),
    ("|d nu|", "", "abs_error_nu", 1.0, 3),
    ("start material", "|d log10 E|", "start_abs_error_log10_E", 1.0, 3),
    ("", "|d nu|", "start_abs_error_nu", 1.0, 3),
    ("Chamfer (cm)", "observed", "chamfer_observed", 100.0, 2),
    ("", "future", "chamfer_future", 100.0, 2),
    ("centre of mass (cm)", "frame 0", "centre_of_mass_frame_0", 100.0, 2),
    ("", "observed", "centre_of_mass_observed", 100.0, 2),
    ("", "future", "centre_of_mass_future", 100.0, 2),
    ("rotation off (deg)", "observed", "rotation_observed", 1.0, 1),
    ("", "future", "rotation_future", 1.0, 1),
    ("first contact adds", "c. of mass (cm)", "first_contact_added_centre_of_mass", 100.0, 2),
    ("", "rotation (deg)", "first_contact_added_rotation", 1.0, 1),
    ("solid's lowest mode", "/ truth's", "solid_frequency_ratio", 1.0, 3),
    ("solid's volume", "/ truth's", "solid_volume_ratio", 1.0, 3),
    ("solid's bottom (cm)", "- truth's", "solid_bottom_offset", 100.0, 2),
    ("interval holds truth", "log10 E", "interval_covers_log10_E", 1.0, 2),
    ("", "nu", "interval_covers_nu", 1.0, 2),
    ("joint beats start", "validation", "joint_improved", 1.0, 2),
    ("time (s)", "", "seconds", 1.0, 0),
]


def short_name(name: str) -> str:
    """A scene's column title: ``scene_007`` → ``007`` (other names unchanged)."""
    return name[len("scene_"):] if name.startswith("scene_") and len(name) > len("scene_") else name


def format_table(result: dict[str, Any]) -> str:
    """The suite as aligned text in the paper's Table 1 layout: rows = metric × subset, columns = the
    scenes (short names) then the mean over the finished scenes; a failed or pending scene's column reads "failed"
    or "pending" (:func:`suite_so_far`), a metric a scene does not have "-". Failed scenes and their errors are
    listed below the table."""
    records = result["scenes"]
    head = [short_name(r["name"]) for r in records] + ["mean"]
    rows: list[list[str]] = []
    for group, sub, key, scale, decimals in TABLE_ROWS:
        cells = []
        for r in records:
            value = _metric(r, key) if r["status"] == "ok" else None
            cells.append(r["status"] if r["status"] != "ok" else _fmt(value, scale, decimals))
        cells.append(_fmt(result["means"].get(key), scale, decimals))
        rows.append([group, sub] + cells)
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    widths = [max(len(h), 6, *(len(row[2 + j]) for row in rows)) for j, h in enumerate(head)]
    lines = [" " * (w0 + 2 + w1) + "".join(f"  {h:>{w}}" for h, w in zip(head, widths))]
    lines.append("-" * len(lines[0]))
    for row in rows:
        lines.append(f"{row[0]:<{w0}}  {row[1]:<{w1}}" + "".join(f"  {c:>{w}}" for c, w in zip(row[2:], widths)))
    ok = sum(r["status"] == "ok" for r in records)
    pending = sum(r["status"] == "pending" for r in records)
    waiting = f" ({pending} pending)" if pending else ""
    lines.append(f"{len(records)} scene{'s' if len(records) != 1 else ''}, mean over the {ok} finished{waiting}; "
                 f"preset {result['preset']}; suite {result['suite']}")
    for r in records:
        if r["status"] == "failed":
            lines.append(f"FAILED {r['name']}: {r['error']}")
    return "\n".join(lines)


def _fmt(value: float | None, scale: float, decimals: int) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value * scale:.{decimals}f}"
