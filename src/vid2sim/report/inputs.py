"""Checks of the report's inputs: an evaluation dict (``evaluation.json``) and a benchmark-suite dict.

Each check raises :class:`~vid2sim.report.config.ReportInputError` naming the offending field by its path,
e.g. ``evaluation['dynamic']['psnr'] must be a number, got 'high'``. Unknown extra keys are allowed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from vid2sim.report.config import ReportInputError
from vid2sim.runtime.jsonvalues import is_finite_number as _is_number

GROUPS = ("dynamic", "future", "novel_views", "rest")
SCENE_KEYS = ("name", "scene", "asset", "status", "error", "evaluation", "report", "seconds")


def _number(value: Any, where: str, optional: bool = True) -> None:
    if value is None and optional:
        return
    if not _is_number(value):
        raise ReportInputError(f"{where} must be a number, got {value!r}")


def _numbers(value: Any, where: str) -> None:
    if value is None:
        return
    if not isinstance(value, (list, tuple)):
        raise ReportInputError(f"{where} must be a list of numbers, got {type(value).__name__}")
    for i, v in enumerate(value):
        if v is not None and not _is_number(v):
            raise ReportInputError(f"{where}[{i}] must be a number, got {v!r}")


def check_evaluation(evaluation: Any, name: str = "evaluation") -> dict[str, Any]:
    """Check an evaluation dict (the output of :func:`vid2sim.evaluate.scores.evaluate`); returns it.

    Checked: it is a dict; ``dynamic`` / ``future`` / ``novel_views`` / ``rest``, when present and non-empty, are dicts
    whose ``psnr``, ``ssim``, ``fovvdp_jod`` are numbers, whose per-frame lists hold numbers, one per entry
    of ``frames``; ``material`` is a dict whose ``fitted`` / ``truth`` hold numbers; ``geometry_stiffness``, when
    present, holds a numeric ``lowest_frequency_ratio`` and ``implied_log10_E_offset``; ``chamfer`` has numeric
    means and per-frame values.
    """
    if not isinstance(evaluation, Mapping):
        raise ReportInputError(f"{name} must be a dict (the JSON of vid2sim evaluate), got {type(evaluation).__name__}")
    for group in GROUPS:
        g = evaluation.get(group)
        if g is None or g == {}:
            continue
        where = f"{name}[{group!r}]"
        if not isinstance(g, Mapping):
            raise ReportInputError(f"{where} must be a dict, got {type(g).__name__}")
        for key in ("psnr", "ssim", "fovvdp_jod"):
            _number(g.get(key), f"{where}[{key!r}]")
        for key in ("frames", "views"):
            v = g.get(key)
            if v is not None and (not isinstance(v, (list, tuple)) or not all(isinstance(i, int) for i in v)):
                raise ReportInputError(f"{where}[{key!r}] must be a list of indices, got {v!r}")
        for key in ("psnr_per_frame", "ssim_per_frame"):
            _numbers(g.get(key), f"{where}[{key!r}]")
            if g.get(key) is not None and g.get("frames") is not None and len(g[key]) != len(g["frames"]):
                raise ReportInputError(f"{where}[{key!r}] has {len(g[key])} values for {len(g['frames'])} frames")
    material = evaluation.get("material")
    if material is not None:
        if not isinstance(material, Mapping):
            raise ReportInputError(f"{name}['material'] must be a dict, got {type(material).__name__}")
        for part in ("fitted", "truth"):
            d = material.get(part)
            if d is None:
                continue
            if not isinstance(d, Mapping):
                raise ReportInputError(f"{name}['material'][{part!r}] must be a dict, got {type(d).__name__}")
            for key in ("E", "nu", "log10_E", "damping_ratio"):
                _number(d.get(key), f"{name}['material'][{part!r}][{key!r}]")
        for key in ("abs_error_log10_E", "abs_error_nu"):
            _number(material.get(key), f"{name}['material'][{key!r}]")
    stiffness = evaluation.get("geometry_stiffness")
    if stiffness is not None:
        if not isinstance(stiffness, Mapping):
            raise ReportInputError(f"{name}['geometry_stiffness'] must be a dict, got {type(stiffness).__name__}")
        for key in ("lowest_frequency_ratio", "implied_log10_E_offset"):
            _number(stiffness.get(key), f"{name}['geometry_stiffness'][{key!r}]", optional=False)
        for key in ("nu", "omega_asset", "omega_truth"):
            _number(stiffness.get(key), f"{name}['geometry_stiffness'][{key!r}]")
    solid = evaluation.get("solid")
    if solid is not None:
        if not isinstance(solid, Mapping):
            raise ReportInputError(f"{name}['solid'] must be a dict, got {type(solid).__name__}")
        for key in ("volume_ratio", "outside_truth_fraction", "bottom_offset_m", "top_offset_m"):
            _number(solid.get(key), f"{name}['solid'][{key!r}]", optional=False)
    for part in ("chamfer", "centre_of_mass"):
        distances = evaluation.get(part)
        if distances is None:
            continue
        if not isinstance(distances, Mapping):
            raise ReportInputError(f"{name}[{part!r}] must be a dict, got {type(distances).__name__}")
        for key in ("observed_mean", "future_mean"):
            _number(distances.get(key), f"{name}[{part!r}][{key!r}]")
        _numbers(distances.get("per_frame"), f"{name}[{part!r}]['per_frame']")
    turn = evaluation.get("orientation")
    if turn is not None:
        if not isinstance(turn, Mapping):
            raise ReportInputError(f"{name}['orientation'] must be a dict, got {type(turn).__name__}")
        for key in ("observed_mean_deg", "future_mean_deg"):
            _number(turn.get(key), f"{name}['orientation'][{key!r}]")
        _numbers(turn.get("per_frame_deg"), f"{name}['orientation']['per_frame_deg']")
    return dict(evaluation)


def read_evaluation(path: Path) -> dict[str, Any]:
    """Read and check an ``evaluation.json`` (errors name the file)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ReportInputError(f"{path}: cannot read the evaluation JSON ({exc})") from exc
    return check_evaluation(data, name=str(path))


def check_suite(suite: Any) -> dict[str, Any]:
    """Check a benchmark-suite dict; returns a normalised copy (missing optional scene keys set to None).

    The schema (agreed with ``vid2sim bench``)::

        {"suite": path, "preset": str,
         "scenes": [{"name": str, "scene": path, "asset": path | None, "status": "ok" | "failed",
                     "error": str | None, "evaluation": <evaluation.json dict> | None,
                     "report": path of that scene's report folder | None, "seconds": float}],
         "means": {"dynamic_psnr": float | None, ..., "abs_error_nu": float | None, ...}}
    """
    if not isinstance(suite, Mapping):
        raise ReportInputError(f"suite must be a dict, got {type(suite).__name__}")
    scenes = suite.get("scenes")
    if not isinstance(scenes, (list, tuple)):
        raise ReportInputError(f"suite['scenes'] must be a list of scene dicts, got {type(scenes).__name__}")
    for key in ("suite", "preset"):
        if suite.get(key) is not None and not isinstance(suite[key], (str, Path)):
            raise ReportInputError(f"suite[{key!r}] must be a string, got {suite[key]!r}")
    means = suite.get("means", {}) or {}
    if not isinstance(means, Mapping):
        raise ReportInputError(f"suite['means'] must be a dict of numbers, got {type(means).__name__}")
    for key, value in means.items():
        _number(value, f"suite['means'][{key!r}]")
    out_scenes = []
    names = set()
    for i, s in enumerate(scenes):
        where = f"suite['scenes'][{i}]"
        if not isinstance(s, Mapping):
            raise ReportInputError(f"{where} must be a dict, got {type(s).__name__}")
        if not isinstance(s.get("name"), str) or not s["name"]:
            raise ReportInputError(f"{where}['name'] must be a non-empty string, got {s.get('name')!r}")
        if s["name"] in names:
            raise ReportInputError(f"{where}['name'] {s['name']!r} is used twice")
        names.add(s["name"])
        if s.get("status") not in ("ok", "failed"):
            raise ReportInputError(f"{where}['status'] must be 'ok' or 'failed', got {s.get('status')!r}")
        for key in ("scene", "asset", "report"):
            if s.get(key) is not None and not isinstance(s[key], (str, Path)):
                raise ReportInputError(f"{where}[{key!r}] must be a path or None, got {s[key]!r}")
        if s.get("error") is not None and not isinstance(s["error"], str):
            raise ReportInputError(f"{where}['error'] must be a string or None, got {s['error']!r}")
        _number(s.get("seconds"), f"{where}['seconds']")
        if s.get("evaluation") is not None:
            check_evaluation(s["evaluation"], name=f"{where}['evaluation']")
        out_scenes.append({**{k: s.get(k) for k in SCENE_KEYS}, **{k: v for k, v in s.items() if k not in SCENE_KEYS}})
    return {"suite": suite.get("suite"), "preset": suite.get("preset"), "scenes": out_scenes, "means": dict(means),
            **{k: v for k, v in suite.items() if k not in ("suite", "preset", "scenes", "means")}}
