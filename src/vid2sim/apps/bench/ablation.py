"""``vid2sim bench ablation``: the paper's Stage I ablation on a ``make-benchmark`` suite.

Three variants of the reconstruction (:data:`VARIANTS`, in this order) each run as a whole
:func:`vid2sim.apps.bench.suite.run_suite` into ``OUT/<variant>``:

* ``stage1_only`` — Stage I alone: the predictor's log10 E and ν are the asset's material and its last layer
  starts the skinning field; Stage II does nothing (``JointConfig.iterations`` and ``gauss_newton_iterations`` 0, no
  coarse search over E).
  The paper's "Ours (Stage I only)" for the physics (its Gaussians are still fitted, as in every variant).
* ``stage1_stage2`` — Stage I then the preset's Stage II (the paper's full method).
* ``stage2_prior`` — Stage II alone from ``ReconstructConfig.prior``'s E and ν and a seeded skinning
  field: the paper's "w/o Stage I".

Each variant's folder is an ordinary ``bench suite`` results folder (``suite.json``, ``suite_config.json``,
``NAME/asset``, ``NAME/evaluation.json``, reports), so the ablation resumes exactly as ``bench suite`` does:
finished scenes are skipped, failed and unfinished ones retried.

The variants' settings agree up to the appearance stage (:func:`last_shared_stage`): the first variant saves a
snapshot of each scene's reconstruction there (``OUT/.shared/NAME``,
:class:`~vid2sim.reconstruct.runner.StageSnapshots`) and the others start from it, so the Gaussians, the points,
the initial velocity and the appearance are fitted once a scene, not three times. Each variant's ``seconds``
still counts those stages (what the variant costs alone). The snapshots are deleted when every variant has
finished every scene. ``OUT/ablation.json`` (written atomically
at the end) gathers the three, with the Stage II iterations each scene needed to converge
(:func:`iterations_to_converge`); :func:`format_ablation_table` prints the paper's ablation layout, one row
per variant.

A Stage I variant's scene whose ``log.json`` says Stage I did not run (e.g. transformers missing in a Ray
worker) is recorded as failed with the reason, in ``ablation.json`` and the variant's ``suite.json``: a
Stage-II-only result is never reported as a Stage I one.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from vid2sim.apps.bench.suite import (
    SUITE_JSON,
    SuiteConfig,
    check_out,
    read_index,
    run_suite,
    suite_summary,
)
from vid2sim.predictor.predict import DEFAULT_PREDICTOR
from vid2sim.predictor.template import load_template
from vid2sim.reconstruct.runner import StageSnapshots, cache_keys
from vid2sim.reconstruct.stages import all_stages
from vid2sim.report import write_suite_report
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import check_output_folder, write_json_atomic
from vid2sim.runtime.ray_runner import check_ray

if TYPE_CHECKING:
    from vid2sim.reconstruct.pipeline import ReconstructConfig

ABLATION_JSON = "ablation.json"
SHARED_DIR = ".shared"  # the stage snapshots the variants share, one folder a scene
TOLERANCE_LOG10_E = 0.05  # decades
TOLERANCE_NU = 0.01


@dataclass(frozen=True)
class Variant:
    """One row of the ablation.

    Attributes:
        name: the variant's folder under OUT and its key in ablation.json.
        label: the paper's name for it.
        stage1: Stage I runs (``ReconstructConfig.stage1.enabled``).
        stage2: Stage II runs with the preset's settings; False: no coarse search, 0 iterations (of either
            method; the material keeps its start and gets its intervals there).
    """

    name: str
    label: str
    stage1: bool
    stage2: bool

    def reconstruct_config(self, base: "ReconstructConfig", predictor: str | None) -> "ReconstructConfig":
        """``base`` (not modified) with this variant applied; ``predictor`` (a checkpoint path, None: keep
        ``base.stage1.predictor``) is set in the Stage I variants."""
        cfg = copy.deepcopy(base)
        cfg.stage1.enabled = self.stage1
        if self.stage1 and predictor is not None:
            cfg.stage1.predictor = predictor
        if not self.stage2:
            cfg.joint = dataclasses.replace(cfg.joint, iterations=0, gauss_newton_iterations=0, coarse_log10_E=())
        return cfg


VARIANTS: tuple[Variant, ...] = (
    Variant("stage1_only", "Stage I only", stage1=True, stage2=False),
    Variant("stage1_stage2", "full (Stage I + II)", stage1=True, stage2=True),
    Variant("stage2_prior", "w/o Stage I", stage1=False, stage2=True),
)


@dataclass(frozen=True)
class Convergence:
    """Stage II iterations to converge of one reconstruction (:func:`iterations_to_converge`).

    Attributes:
        log10_E: the first iteration after which log10 E stays within its tolerance of the final value
            (None: it does not stay there until the last logged iteration).
        nu: the same for ν.
        iterations_to_converge: max(log10_E, nu); None when either is None.
        iterations: the last logged iteration (the iterations of the joint method that ran: Gauss–Newton steps,
            or Adam iterations with ``joint.method`` "windows").
    """

    log10_E: int | None
    nu: int | None
    iterations_to_converge: int | None
    iterations: int

    def to_dict(self) -> dict[str, int | None]:
        return dataclasses.asdict(self)


def _settled_from(log: Sequence[Mapping[str, Any]], key: str, final: float, tolerance: float) -> int | None:
    """The smallest iteration k of ``log`` such that every entry with iteration >= k that has ``key`` is within
    ``tolerance`` of ``final`` (None if the last such entry is not)."""
    entries = sorted(((int(e["iteration"]), float(e[key])) for e in log if key in e), key=lambda e: e[0])
    if not entries:
        return 0
    settled: int | None = None
    for iteration, value in reversed(entries):
        if not abs(value - final) <= tolerance:  # a NaN is never within tolerance
            break
        settled = iteration
    return settled


def iterations_to_converge(log: Sequence[Mapping[str, Any]], final_log10_E: float, final_nu: float,
                           tolerance_log10_E: float = TOLERANCE_LOG10_E,
                           tolerance_nu: float = TOLERANCE_NU) -> Convergence:
    """Stage II iterations a reconstruction needed to converge, from its joint log.

    The log is the asset's ``log.json`` ``"iterations"`` (:attr:`vid2sim.reconstruct.stages.joint.JointResult.log`): one
    dict per iteration of the joint method (a Gauss–Newton step, or an Adam iteration with ``joint.method``
    "windows") with ``iteration`` (1 … N) and the ``log10_E`` and ``nu`` *after* that iteration's
    step, preceded by the entry of iteration 0 (the state the iterations start from: after the coarse search
    over log10 E, or Stage I's prediction). For each of log10 E and ν the answer is the first iteration k after
    which the value stays within the tolerance of its final value for every later logged iteration:
    ``|log10_E(i) - final_log10_E| <= tolerance_log10_E`` for all logged i >= k (the same for ν). k = 0: the
    starting point was already there and Stage II's iterations did not move it away; the coarse search's
    rollouts are not counted.

    "Final" is the value the reconstruction kept — the asset's ``material.json``, the state with the best
    validation loss — not the last iterate: the question is how many iterations it took to reach the answer
    that was reported. The optimiser can wander off after that state; when the last logged iteration is outside
    the tolerance, the value never settled and the answer is None (not "N"): a bound rather than a count.

    Args:
        log: the joint log entries (any order; entries without ``log10_E``/``nu`` are ignored).
        final_log10_E: log10 of the kept E (E in Pa); final_nu: the kept ν.
        tolerance_log10_E: decades (default 0.05); tolerance_nu: absolute (default 0.01).
    Returns:
        :class:`Convergence` (``iterations_to_converge`` = max of the two; None if either is None). An empty
        log (Stage II did nothing) gives 0 throughout.
    """
    if not (tolerance_log10_E >= 0 and tolerance_nu >= 0):
        raise InputError(f"tolerances must be >= 0, got {tolerance_log10_E} (log10 E) and {tolerance_nu} (nu)")
    k_e = _settled_from(log, "log10_E", float(final_log10_E), tolerance_log10_E)
    k_nu = _settled_from(log, "nu", float(final_nu), tolerance_nu)
    both = None if k_e is None or k_nu is None else max(k_e, k_nu)
    last = max((int(e["iteration"]) for e in log if "iteration" in e), default=0)
    return Convergence(log10_E=k_e, nu=k_nu, iterations_to_converge=both, iterations=last)


def variant_configs(config: SuiteConfig | None = None, predictor: str | None = None) -> dict[str, SuiteConfig]:
    """The :class:`SuiteConfig` of each variant (name → config, in :data:`VARIANTS` order).

    Each carries the variant's full ReconstructConfig (``config``'s preset or ``reconstruct``, with
    ``config.iterations`` applied, then the variant) and ``config``'s threads and fovvdp. ``iterations`` stays
    ``config.iterations`` in the Stage II variants and is 0 in ``stage1_only``, whose settings therefore do not
    depend on it. ``predictor`` (None: the ReconstructConfig's, by default the shipped checkpoint) goes into
    the Stage I variants' ``stage1.predictor``.
    """
    config = config or SuiteConfig()
    base = config.reconstruct_config()
    return {v.name: dataclasses.replace(config, reconstruct=v.reconstruct_config(base, predictor),
                                        iterations=config.iterations if v.stage2 else 0)
            for v in VARIANTS}


def last_shared_stage(configs: Sequence["ReconstructConfig"]) -> str | None:
    """The last reconstruction stage whose cache key is the same under every config of ``configs`` (so all stages
    up to it compute the same outputs on a scene), or None when they differ from the first stage."""
    keys = [cache_keys(all_stages(), c, "scene") for c in configs]
    shared = None
    for stage in keys[0]:
        if any(k[stage] != keys[0][stage] for k in keys[1:]):
            break
        shared = stage
    return shared


def _check_stage1_possible(config: SuiteConfig, predictor: str | None) -> str:
    """Raise ValueError when Stage I could not run with these settings; returns the checkpoint's path."""

    base = config.reconstruct_config()
    handles = load_template().num_handles
    if base.networks.handles != handles:
        raise InputError(f"networks.handles is {base.networks.handles}: Stage I predicts the skinning field of the "
                         f"template's {handles} handles, so it could not run in the Stage I variants; set "
                         f"handles={handles}")
    path = Path(predictor if predictor is not None else base.stage1.predictor or DEFAULT_PREDICTOR).expanduser()
    if not path.is_file():
        raise InputError(f"predictor: no checkpoint file at {path} (train one with `vid2sim train-predictor`, "
                         "or pass the path of one)")
    return str(path.resolve())


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _annotate(record: dict[str, Any], variant: Variant) -> dict[str, Any]:
    """The scene record of a variant with ``stage1`` (the asset's log.json record, or None) and ``convergence``
    (:class:`Convergence` as a dict, or None for a failed scene); a Stage I variant's scene whose Stage I did
    not run becomes failed."""
    out = dict(record)
    asset = Path(record["asset"]) if record.get("asset") else None
    log = _read_json(asset / "log.json") if asset is not None else None
    stage1 = log.get("stage1") if isinstance(log, dict) else None
    out["stage1"] = stage1
    out["convergence"] = None
    if out["status"] != "ok":
        return out
    if variant.stage1 and not (isinstance(stage1, dict) and stage1.get("ran") is True):
        reason = stage1.get("reason", "no reason recorded") if isinstance(stage1, dict) else \
            f"{asset / 'log.json' if asset else 'the asset'} has no Stage I record"
        out.update(status="failed", evaluation=None,
                   error=f"Stage I did not run: {reason} (delete {Path(record['asset']).parent} to redo the scene)")
        return out
    if not variant.stage2:  # Stage I alone: no Stage II iteration, by definition
        out["convergence"] = Convergence(0, 0, 0, 0).to_dict()
        return out
    material = _read_json(asset / "material.json") if asset is not None else None
    iterations = log.get("iterations") if isinstance(log, dict) else None
    if isinstance(material, dict) and isinstance(iterations, list):
        out["convergence"] = iterations_to_converge(iterations, material["log10_E"], material["nu"]).to_dict()
    return out


CONVERGENCE_KEYS = {"iterations_to_converge": "iterations_to_converge",
                    "iterations_to_converge_log10_E": "log10_E", "iterations_to_converge_nu": "nu"}


def _mean(values: list[float]) -> float | None:
    values = [v for v in values if math.isfinite(v)]
    return sum(values) / len(values) if values else None


def _variant_summary(suite: str, preset: str, records: list[dict[str, Any]]) -> dict[str, Any]:
    summary = suite_summary(suite, preset, records)
    ok = [r for r in records if r["status"] == "ok" and r.get("convergence")]
    for key, field in CONVERGENCE_KEYS.items():
        summary["means"][key] = _mean([float(r["convergence"][field]) for r in ok
                                       if r["convergence"][field] is not None])
    return summary


def run_ablation(suite_dir: str | Path, out_dir: str | Path, config: SuiteConfig | None = None,
                 predictor: str | None = None, progress: bool = True,
                 ray_address: str | None = None) -> dict[str, Any]:
    """Run the three :data:`VARIANTS` on the suite at ``suite_dir`` into ``out_dir/<variant>`` (module docstring).

    Args:
        suite_dir: a finished ``make-benchmark`` folder.
        out_dir: the results folder (created; resumed when it holds an earlier ablation's variant folders).
        config: the settings shared by the variants (default :class:`SuiteConfig`: the small preset); its
            ReconstructConfig must have the template's 10 handles.
        predictor: the Stage I checkpoint (None: ``config``'s ``stage1.predictor``, by default the one
            shipped with vid2sim).
        progress: progress bars, and a line per variant.
        ray_address: run each variant's scenes as Ray tasks (:func:`vid2sim.apps.bench.suite.run_suite`).
    Returns:
        the content of ``out_dir/ablation.json``: ``{"suite": path, "preset": str, "predictor": path,
        "variants": {name: {"label", "out", "means", "failed", "scenes"}}, "iterations_to_converge":
        {"tolerance_log10_E", "tolerance_nu", "definition", "variants": {name: {"mean", "mean_log10_E",
        "mean_nu", "per_scene": {scene: int | None}, "not_settled": [scene, ...]}}}, "failed": int,
        "shared_stages_up_to": the last stage the variants shared (:func:`last_shared_stage`) or None}``.
        ``means`` holds the :data:`vid2sim.apps.bench.suite.METRICS` means over the variant's finished scenes and
        ``iterations_to_converge`` (+ ``_log10_E``, ``_nu``) means over those where it is defined; ``scenes``
        are :func:`vid2sim.apps.bench.suite.run_scene` records with ``stage1`` (log.json's) and ``convergence``
        (:class:`Convergence`, None for a failed scene) added.
    Raises:
        ValueError: handles != 10, the predictor checkpoint missing or transformers not installed (Stage I
            could not run), a variant folder holding a run with other settings — all before any work; and
            what :func:`~vid2sim.apps.bench.suite.run_suite` raises (not a finished suite, ...).
        FileExistsError: ``out_dir`` is a non-empty folder that holds no ablation.
    """
    from tqdm.auto import tqdm

    config = config or SuiteConfig()
    checkpoint = _check_stage1_possible(config, predictor)
    configs = variant_configs(config, checkpoint if predictor is not None else None)  # None: keep the config's
    suite = Path(suite_dir).resolve()
    out = Path(out_dir).resolve()
    read_index(suite)
    check_output_folder(out, any((out / n).exists() for n in (*configs, ABLATION_JSON)),
                        f"ablation run ({', '.join(configs)})", "one")
    if ray_address is not None:

        check_ray(ray_address)
    for name, cfg in configs.items():  # a resumed variant with other settings: refused before any work
        check_out(out / name, {"suite": str(suite), **cfg.to_dict()})
    shared = last_shared_stage([c.reconstruct_config() for c in configs.values()])
    snapshots = StageSnapshots(out / SHARED_DIR, (shared,)) if shared is not None else None

    variants: dict[str, Any] = {}
    convergence: dict[str, Any] = {}
    for i, variant in enumerate(VARIANTS):
        if progress:
            tqdm.write(f"[ablation {i + 1}/{len(VARIANTS)}] {variant.name}: {variant.label}")
        cfg = configs[variant.name]
        result = run_suite(suite, out / variant.name, cfg, progress=progress, ray_address=ray_address,
                           snapshots=snapshots)
        records = [_annotate(r, variant) for r in result["scenes"]]
        marked = [r for r, before in zip(records, result["scenes"]) if r["status"] != before["status"]]
        if marked:  # the variant's own suite.json and report must not count them as Stage I results either
            plain = suite_summary(result["suite"], result["preset"],
                                  [{k: r[k] for k in before} for r, before in zip(records, result["scenes"])])
            write_json_atomic(out / variant.name / SUITE_JSON, plain)

            write_suite_report(out / variant.name / "report", plain)
            if progress:
                for r in marked:
                    tqdm.write(f"[ablation] {variant.name}/{r['name']} failed: {r['error']}")
        summary = _variant_summary(result["suite"], result["preset"], records)
        variants[variant.name] = {"label": variant.label, "out": str(out / variant.name), "means": summary["means"],
                                  "failed": summary["failed"], "scenes": records}
        per_scene = {r["name"]: (r["convergence"] or {}).get("iterations_to_converge") for r in records
                     if r["status"] == "ok"}
        convergence[variant.name] = {
            "mean": summary["means"]["iterations_to_converge"],
            "mean_log10_E": summary["means"]["iterations_to_converge_log10_E"],
            "mean_nu": summary["means"]["iterations_to_converge_nu"],
            "per_scene": per_scene, "not_settled": [n for n, k in per_scene.items() if k is None]}
    result = {"suite": str(suite), "preset": config.preset_name, "predictor": checkpoint, "variants": variants,
              "iterations_to_converge": {
                  "tolerance_log10_E": TOLERANCE_LOG10_E, "tolerance_nu": TOLERANCE_NU,
                  "definition": "first Stage II iteration after which |log10 E - final| <= tolerance_log10_E "
                                "(and |nu - final| <= tolerance_nu) for every later iteration; final = the "
                                "asset's material (best validation); max of the two; 0 for stage1_only",
                  "variants": convergence},
              "failed": sum(v["failed"] for v in variants.values()), "shared_stages_up_to": shared}
    write_json_atomic(out / ABLATION_JSON, result)
    if result["failed"] == 0:  # a rerun retries failed scenes: their snapshots stay until then
        shutil.rmtree(out / SHARED_DIR, ignore_errors=True)
    return result


# the table's columns: (title, means key, scale, decimals)
TABLE_COLUMNS: list[tuple[str, str, float, int]] = [
    ("dyn PSNR", "dynamic_psnr", 1.0, 2),
    ("dyn SSIM", "dynamic_ssim", 1.0, 3),
    ("fut PSNR", "future_psnr", 1.0, 2),
    ("fut SSIM", "future_ssim", 1.0, 3),
    ("MAE log10 E", "abs_error_log10_E", 1.0, 3),
    ("MAE nu", "abs_error_nu", 1.0, 3),
    ("iters to conv.", "iterations_to_converge", 1.0, 1),
    ("time (s)", "seconds", 1.0, 0),
]


def _fmt(value: Any, scale: float, decimals: int) -> str:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        return "-"
    return f"{value * scale:.{decimals}f}"


def format_ablation_table(result: Mapping[str, Any]) -> str:
    """The ablation as aligned text in the paper's ablation layout: one row per variant (its name and the
    paper's label), columns = the means over the variant's finished scenes of dynamic and future PSNR / SSIM,
    the mean absolute errors of log10 E and ν, the mean Stage II iterations to converge and the mean wall time
    per scene. "-" marks a mean no finished scene has. Below: how many scenes each mean covers, scenes whose
    material never settled, and the failed scenes with their errors."""
    head = ["variant", ""] + [c[0] for c in TABLE_COLUMNS]
    rows = []
    for variant in VARIANTS:
        v = result["variants"].get(variant.name)
        if v is not None:
            rows.append([variant.name, variant.label]
                        + [_fmt(v["means"].get(key), scale, decimals) for _, key, scale, decimals in TABLE_COLUMNS])
    widths = [max([len(h)] + [len(r[j]) for r in rows]) for j, h in enumerate(head)]

    def line(cells: list[str]) -> str:  # the two name columns left-aligned, the numbers right-aligned
        return "  ".join([f"{c:<{w}}" for c, w in zip(cells[:2], widths)]
                         + [f"{c:>{w}}" for c, w in zip(cells[2:], widths[2:])])

    lines = [line(head)]
    lines.append("-" * len(lines[0]))
    lines += [line(r) for r in rows]
    counts = ", ".join(f"{name} {len(v['scenes']) - v['failed']}/{len(v['scenes'])}"
                       for name, v in result["variants"].items())
    conv = result.get("iterations_to_converge", {})
    lines.append(f"means over the finished scenes ({counts})")
    lines.append(f"iters to conv.: the first Stage II iteration after which |d log10 E| <= "
                 f"{conv.get('tolerance_log10_E', TOLERANCE_LOG10_E)} and |d nu| <= "
                 f"{conv.get('tolerance_nu', TOLERANCE_NU)} from the kept material at every later iteration")
    lines.append(f"preset {result['preset']}; predictor {result['predictor']}; suite {result['suite']}")
    for name, c in conv.get("variants", {}).items():
        if c.get("not_settled"):
            lines.append(f"NOT SETTLED {name}: {', '.join(c['not_settled'])} (left out of the iterations mean)")
    for name, v in result["variants"].items():
        for r in v["scenes"]:
            if r["status"] != "ok":
                lines.append(f"FAILED {name}/{r['name']}: {r['error']}")
    return "\n".join(lines)

