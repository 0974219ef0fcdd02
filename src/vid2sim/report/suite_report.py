"""The report of a benchmark suite: :func:`write_suite_report`.

One page with the suite's means and a table with one row per scene — a thumbnail (frame 0, ground truth |
reconstruction), the metrics, the material truth and found, the status (with the error of a failed scene)
and the time — each row linking to that scene's own report. The thumbnails are copied into the suite's
``media/`` folder (from each scene report's ``media/thumb.png``, or, for a scene without a report, frame 0 of
the scene alone), so the page shows them even if the scene reports move; the links to the scene reports are
relative to the suite report's folder.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from vid2sim import __version__
from vid2sim.report import html as H
from vid2sim.report import media as M
from vid2sim.report.config import ReportConfig
from vid2sim.report.inputs import check_suite
from vid2sim.report.plots import material_scatter
from vid2sim.report.scene_report import check_out
from vid2sim.runtime.files import write_folder_atomic
from vid2sim.runtime.jsonvalues import is_finite_number as _isnum
from vid2sim.scene.reading import load_scene

#: suite means key → (label, unit, decimals, scale of the shown value)
MEAN_LABELS = {
    "dynamic_psnr": ("PSNR observed", "dB", 2, 1.0), "future_psnr": ("PSNR future", "dB", 2, 1.0),
    "novel_psnr": ("PSNR novel views", "dB", 2, 1.0), "rest_psnr": ("PSNR at rest (frame 0)", "dB", 2, 1.0),
    "dynamic_ssim": ("SSIM observed", "", 4, 1.0),
    "future_ssim": ("SSIM future", "", 4, 1.0), "novel_ssim": ("SSIM novel views", "", 4, 1.0),
    "abs_error_log10_E": ("|Δ log10 E|", "decades", 3, 1.0), "abs_error_nu": ("|Δ ν|", "", 3, 1.0),
    "start_abs_error_log10_E": ("|Δ log10 E| at the start (prior or Stage I)", "decades", 3, 1.0),
    "start_abs_error_nu": ("|Δ ν| at the start (prior or Stage I)", "", 3, 1.0),
    "chamfer_observed": ("Chamfer observed", "cm", 2, 100.0), "chamfer_future": ("Chamfer future", "cm", 2, 100.0),
    "centre_of_mass_frame_0": ("centre of mass off, frame 0", "cm", 2, 100.0),
    "centre_of_mass_observed": ("centre of mass off, observed", "cm", 2, 100.0),
    "centre_of_mass_future": ("centre of mass off, future", "cm", 2, 100.0),
    "rotation_observed": ("rotation off the truth's, observed", "deg", 1, 1.0),
    "rotation_future": ("rotation off the truth's, future", "deg", 1, 1.0),
    "first_contact_added_centre_of_mass": ("centre-of-mass error the first contact adds", "cm", 2, 100.0),
    "first_contact_added_rotation": ("rotation error the first contact adds", "deg", 1, 1.0),
    "solid_frequency_ratio": ("the solid's lowest elastic mode over the truth's", "", 3, 1.0),
    "solid_volume_ratio": ("the solid's volume over the truth's", "", 3, 1.0),
    "solid_bottom_offset": ("the solid's lowest point above the truth's (frame 0)", "cm", 2, 100.0),
    "interval_covers_log10_E": ("scenes whose log10 E interval holds the truth", "", 2, 1.0),
    "interval_covers_nu": ("scenes whose ν interval holds the truth", "", 2, 1.0),
    "joint_improved": ("scenes where the joint fit beats its start on validation", "", 2, 1.0),
    "seconds": ("time per scene", "s", 0, 1.0),
}


METRIC_COLUMNS = ("observed PSNR / SSIM", "future PSNR / SSIM", "novel views PSNR / SSIM", "E (Pa)", "ν",
                  "|Δ log10 E|", "|Δ ν|", "Chamfer (cm)", "centre of mass off (cm)")


def _thumbnail(scene: Mapping[str, Any], target: Path, config: ReportConfig) -> bool:
    """Copy the scene report's thumbnail to ``target``, or make one from the scene's frame 0; False if neither."""
    report = scene.get("report")
    if report is not None and (Path(report) / "media" / "thumb.png").is_file():
        shutil.copyfile(Path(report) / "media" / "thumb.png", target)
        return True
    if scene.get("scene") is None or not Path(scene["scene"]).is_dir():
        return False
    import torch


    try:
        s = load_scene(scene["scene"], dtype=torch.uint8)
    except (ValueError, OSError):
        return False
    cfg = s.config.resolved(s.images.shape[0], s.images.shape[1])
    v = cfg.observed_views[0] if cfg.observed_views else 0
    gt = s.images[v, 0].numpy()
    f = M.scale_factor(max(gt.shape[:2]), config.thumb_size)
    gt = M.rescale(gt, f)
    blank = np.full_like(gt, 225)
    M.save_png(target, M.titled_panels([gt, blank], ["ground truth", "no reconstruction"]))
    return True


def write_suite_report(out_dir: str | Path, suite: Mapping[str, Any], config: ReportConfig | None = None) -> Path:
    """Write the HTML report of a benchmark suite into ``out_dir`` (atomically; replaces a previous report).

    Args:
        out_dir: the report folder (``index.html``, ``media/`` with thumbnails and a material plot,
            ``suite.json`` with the input).
        suite: ``{"suite": path, "preset": str, "scenes": [{"name", "scene", "asset", "status": "ok" |
            "failed", "error", "evaluation": <evaluation.json dict> | None, "report": path | None,
            "seconds"}], "means": {"dynamic_psnr", "dynamic_ssim", "future_psnr", "future_ssim", "novel_psnr",
            "novel_ssim", "abs_error_log10_E", "abs_error_nu", ...}}`` (checked: a bad field raises
            :class:`~vid2sim.report.config.ReportInputError` naming it).
        config: :class:`ReportConfig` (thumbnail size); None for the defaults.

    Returns:
        ``out_dir`` as a Path.
    """

    t0 = time.perf_counter()
    config = config or ReportConfig()
    data = check_suite(suite)
    out = Path(out_dir)
    check_out(out)

    def write(staging: Path) -> None:
        (staging / "media").mkdir(parents=True)
        rows, scatter = [], []
        for i, s in enumerate(data["scenes"]):
            found, truth, point = _scene_material(s)
            if point is not None:
                scatter.append(point)
            rows += _scene_rows(i, s, found, truth, staging / "media" / f"thumb_{i:03d}.png", out, config)
        headers = ["#", "scene", "frame 0", "status"] + list(METRIC_COLUMNS) + ["seconds"]
        table = H.table(headers, rows, table_id="suite-table", foot=[_means_row(data)])
        cards = _mean_cards(data["means"])
        material_scatter(staging / "media" / "material.svg", scatter)
        sections = _suite_sections(data, cards, table)
        date = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
        suite_name = Path(str(data.get("suite") or "suite")).name
        subtitle = (f"suite <b>{H.esc(suite_name)}</b> ({H.esc(data.get('suite'))}) · preset "
                    f"<b>{H.esc(data.get('preset'))}</b> · {len(data['scenes'])} scenes<br>written {H.esc(date)} · "
                    f"vid2sim {H.esc(__version__)}")
        page = H.page(f"vid2sim benchmark · {suite_name}", subtitle, [(a, n) for a, n, _ in sections],
                      "\n".join(s for _, _, s in sections),
                      f"vid2sim {H.esc(__version__)} · written in {time.perf_counter() - t0:.1f} s", body_class="wide")
        (staging / "index.html").write_text(page, encoding="utf-8")
        (staging / "suite.json").write_text(json.dumps(data, indent=1, default=str), encoding="utf-8")

    return write_folder_atomic(out, write)


def _scene_material(s: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any] | None]:
    """A scene's material found and truth (with log10 E where only E is given), and its point of the material
    plot (None unless both are known)."""
    ev = s.get("evaluation") or {}
    mat = ev.get("material") or {}
    found, truth = dict(mat.get("fitted") or {}), dict(mat.get("truth") or {})
    for d in (found, truth):
        if _isnum(d.get("E")) and d["E"] > 0 and not _isnum(d.get("log10_E")):
            d["log10_E"] = math.log10(d["E"])
    if not (found and truth):
        return found, truth, None
    unc = mat.get("uncertainty") or {}
    return found, truth, {"name": s["name"], "found": found, "truth": truth,
                          "interval": {k: (unc.get(k) or {}).get("interval") for k in ("log10_E", "nu")},
                          "identifiable": {k: (unc.get(k) or {}).get("identifiable", True) for k in ("log10_E", "nu")}}


def _scene_rows(i: int, s: Mapping[str, Any], found: dict[str, Any], truth: dict[str, Any], thumb: Path, out: Path,
                config: ReportConfig) -> list[str]:
    """Scene ``i``'s table row (its thumbnail written to ``thumb``, its name linking to its report relative to
    ``out``), and a second row with its error when it has one the first does not show."""
    ev = s.get("evaluation") or {}
    has_thumb = _thumbnail(s, thumb, config)
    link = None
    if s.get("report") is not None and (Path(s["report"]) / "index.html").is_file():
        link = os.path.relpath(Path(s["report"]).resolve() / "index.html", out.resolve())
    name_html = (f'<a href="{H.esc(Path(link).as_posix())}">{H.esc(s["name"])}</a>' if link
                 else H.esc(s["name"]))
    thumb_html = (
        f'<img class="thumb" src="media/{thumb.name}" alt="{H.esc(s["name"])}" data-probe="thumb:{i}">'
        if has_thumb
        else '<span class="note">no picture</span>'
    )
    status = f'<span class="status {s["status"]}">{s["status"]}</span>'
    cells = [f"<td>{i}</td>", f"<td>{name_html}</td>", f"<td>{thumb_html}</td>", f"<td>{status}</td>"]
    if s["status"] == "failed" and not ev:
        cells.append(f'<td colspan="{len(METRIC_COLUMNS)}" class="error-text">'
                     f'{H.esc(s.get("error") or "failed (no error message)")}</td>')
    else:
        cells += _metric_cells(ev, found, truth)
    cells.append(H.num_cell(s.get("seconds"), H.fmt(s.get("seconds"), 0), key="seconds"))
    rows = ["".join(cells)]
    if s.get("error") and (s["status"] != "failed" or ev):
        rows.append(f'<td></td><td colspan="{3 + len(METRIC_COLUMNS) + 1}" class="error-text">'
                    f'{H.esc(s["error"])}</td>')
    return rows


def _metric_cells(ev: Mapping[str, Any], found: dict[str, Any], truth: dict[str, Any]) -> list[str]:
    """A scene row's :data:`METRIC_COLUMNS` cells from its evaluation ``ev``."""
    mat = ev.get("material") or {}
    cells = []
    for group, key in (("dynamic", "dynamic"), ("future", "future"), ("novel_views", "novel")):
        g = ev.get(group) or {}
        cells.append('<td class="pair">' + H.num_span(g.get("psnr"), H.fmt(g.get("psnr"), 2, "dB"),
                                                     key=f"{key}_psnr")
                     + H.num_span(g.get("ssim"), H.fmt(g.get("ssim"), 4), key=f"{key}_ssim") + "</td>")
    for key, label, f in (("E", "E", H.fmt_sci), ("nu", "ν", lambda x: H.fmt(x, 3))):
        cells.append('<td class="pair material">'
                     + f'<span class="v"><span class="lbl">truth</span>{H.esc(f(truth.get(key)))}</span>'
                     + H.num_span(found.get(key), "found " + f(found.get(key)), key=f"found_{key}")
                     + "</td>")
    cells.append(H.num_cell(mat.get("abs_error_log10_E"), digits=3, key="abs_error_log10_E"))
    cells.append(H.num_cell(mat.get("abs_error_nu"), digits=3, key="abs_error_nu"))
    for group, key in (("chamfer", "chamfer_observed"), ("centre_of_mass", "centre_of_mass_observed")):
        cm = (ev.get(group) or {}).get("observed_mean")
        cells.append(H.num_cell(cm, H.fmt(100 * cm, 2) if _isnum(cm) else "—", key=key))
    return cells


def _means_row(data: Mapping[str, Any]) -> str:
    """The table's footer: the suite's means (and how many scenes ran)."""
    means = data["means"]
    foot_cells = ['<td></td><td>mean</td><td></td>',
                  f"<td>{sum(s['status'] == 'ok' for s in data['scenes'])} ok</td>"]
    for key in ("dynamic", "future", "novel"):
        psnr, ssim = means.get(f"{key}_psnr"), means.get(f"{key}_ssim")
        foot_cells.append('<td class="pair">' + H.num_span(psnr, H.fmt(psnr, 2, "dB"), key=f"{key}_psnr")
                          + H.num_span(ssim, H.fmt(ssim, 4), key=f"{key}_ssim") + "</td>")
    foot_cells.append("<td></td><td></td>")
    foot_cells.append(H.num_cell(means.get("abs_error_log10_E"), digits=3, key="abs_error_log10_E"))
    foot_cells.append(H.num_cell(means.get("abs_error_nu"), digits=3, key="abs_error_nu"))
    for key in ("chamfer_observed", "centre_of_mass_observed"):
        cm = means.get(key)
        foot_cells.append(H.num_cell(cm, H.fmt(100 * cm, 2) if _isnum(cm) else "", key=key))
    foot_cells.append(
        H.num_cell(
            means.get("seconds"),
            H.fmt(means.get("seconds"), 0) if _isnum(means.get("seconds")) else "",
            key="seconds",
        )
    )
    return "".join(foot_cells)


def _mean_cards(means: Mapping[str, Any]) -> list[str]:
    """A card per suite mean (:data:`MEAN_LABELS` names and scales it)."""
    cards = []
    for key, value in means.items():
        label, unit, digits, scale = MEAN_LABELS.get(key, (key, "", 3, 1.0))
        shown = H.fmt(scale * value, digits) if _isnum(value) else "—"
        cards.append(H.card(label, shown, "mean over the scenes that ran", unit=unit if _isnum(value) else ""))
    return cards


def _suite_sections(data: Mapping[str, Any], cards: list[str], table: str) -> list[tuple[str, str, str]]:
    """The page's sections (anchor, navigation label, HTML): the means, the scenes' table, the material plot."""
    n_ok = sum(s["status"] == "ok" for s in data["scenes"])
    n_failed = len(data["scenes"]) - n_ok
    return [
        ("means", "Means", H.section("means", "Means", f'<div class="cards">{"".join(cards)}</div>',
                                     f"{n_ok} of {len(data['scenes'])} scenes ran"
                                     + (f"; {n_failed} failed (their rows say why)." if n_failed else "."))),
        ("scenes", "Scenes", H.section("scenes", "Scenes", table,
                                       "One row per scene; the name links to the scene's own report. Chamfer and "
                                       "centre of mass: means over the observed frames; E in Pa; the footer "
                                       "holds the suite's means.")),
        ("material", "Material", H.section(
            "material", "Material found vs truth",
            '<div class="figure"><img src="media/material.svg" alt="material found vs truth" '
            'data-probe="plot:material"></div>')),
    ]
