"""The report's plots (matplotlib, Agg, written as SVG with real text so they stay sharp at any zoom).

Figures are built as :class:`matplotlib.figure.Figure` objects directly — no pyplot, so writing a report
never changes the backend or state of a user's matplotlib session.

* :func:`optimisation_figure` — the joint optimisation: loss (training and validation), log10 E, ν and the
  damping ratio over iterations, the coarse search of E, and the time per iteration;
* :func:`psnr_figure` — PSNR per frame and view, the future frames shaded;
* :func:`material_scatter` — a suite's found against true log10 E and ν.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from vid2sim.report.config import FUTURE_COLOUR, OBSERVED_COLOUR

_RC = {"svg.fonttype": "none", "font.size": 10, "axes.titlesize": 11, "axes.titleweight": "bold",
       "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True, "grid.alpha": 0.3,
       "legend.fontsize": 8.5, "legend.frameon": False, "svg.hashsalt": "vid2sim"}
TRUTH_COLOUR = "#b42318"
FOUND_COLOUR = "#1f4e9c"
LINE_COLOUR = "#3b4452"


def _figure(width_in: float, height_in: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def _save(fig: Any, path: Path) -> Path:
    import matplotlib

    with matplotlib.rc_context(_RC):
        fig.savefig(path, format="svg", metadata={"Date": None})
    return path


def _integer_x(ax: Any) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _empty(ax: Any, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="#666")
    ax.set_xticks([])
    ax.set_yticks([])


def _finite(values: Sequence[Any]) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def optimisation_figure(path: Path, log: Mapping[str, Any], found: Mapping[str, Any],
                        truth: Mapping[str, Any] | None = None) -> Path:
    """Six panels of the joint optimisation of ``log.json``.

    Args:
        log: ``log.json`` of an asset: ``iterations`` (per joint iteration ``loss``, ``log10_E``, ``nu``,
            ``damping_ratio``, ``ms``; validation entries ``validation_loss``), ``coarse_search`` (``log10_E``,
            ``loss``, and ``floor_friction`` when the search ran over the floor's friction too), ``joint_fit``
            ``method`` (names the training loss: the windows' or the Gauss–Newton fit's whole clip).
        found: the asset's material (``log10_E``, ``nu``, ``damping_ratio``): the best validation snapshot.
        truth: the ground truth (``log10_E``, ``nu``, ``damping_ratio`` — each optional), or None.
    """
    import matplotlib

    truth = truth or {}
    entries = [e for e in log.get("iterations", []) if isinstance(e, Mapping)]
    train = [e for e in entries if "loss" in e]
    val = [e for e in entries if "validation_loss" in e]
    fit = log.get("joint_fit")
    gauss_newton = isinstance(fit, Mapping) and fit.get("method") == "gauss_newton"
    with matplotlib.rc_context(_RC):
        fig = _figure(11.5, 5.6)
        axes = fig.subplots(2, 3)
        ax = axes[0, 0]
        if train or val:
            if train:
                ax.plot([e["iteration"] for e in train], [e["loss"] for e in train], color="#9aa3ad", lw=0.8,
                        marker=".", ms=3, alpha=0.8,
                        label="whole-clip loss (fit's resolution)" if gauss_newton else "training loss (window)")
            if val:
                ax.plot([e["iteration"] for e in val], [e["validation_loss"] for e in val], color=FOUND_COLOUR,
                        lw=1.6, marker="o", ms=3.5, label="validation loss (all frames)")
                best = min(val, key=lambda e: e["validation_loss"])
                ax.plot([best["iteration"]], [best["validation_loss"]], marker="*", ms=13, color="#f2b705",
                        mec="#6b4f00", ls="none", label=f"kept (iteration {best['iteration']})")
            if all(v > 0 for v in [e["loss"] for e in train] + [e["validation_loss"] for e in val]):
                ax.set_yscale("log")
            ax.legend(loc="best")
        else:
            _empty(ax, "no iterations logged")
        ax.set_title("image loss")
        ax.set_xlabel("Gauss–Newton step" if gauss_newton else "iteration")
        _integer_x(ax)
        for ax, key, title in ((axes[0, 1], "log10_E", "log10 E  (E in Pa)"), (axes[0, 2], "nu", "Poisson's ratio ν"),
                               (axes[1, 0], "damping_ratio", "damping ratio ζ")):
            pts = [e for e in entries if isinstance(e.get(key), (int, float))]
            if pts:
                ax.plot([e["iteration"] for e in pts], [e[key] for e in pts], color=LINE_COLOUR, lw=1.4,
                        marker=".", ms=3, label="iterate")
            if isinstance(found.get(key), (int, float)):
                ax.axhline(found[key], color=FOUND_COLOUR, ls=":", lw=1.6, label=f"found {found[key]:.3f}")
            if isinstance(truth.get(key), (int, float)):
                ax.axhline(truth[key], color=TRUTH_COLOUR, ls="--", lw=1.4, label=f"truth {truth[key]:.3f}")
            if not pts:
                ax.text(0.5, 0.92, "not logged", ha="center", transform=ax.transAxes, color="#666")
            elif len({round(e[key], 9) for e in pts}) == 1:
                ax.text(0.5, 0.08, "constant: not fitted", ha="center", transform=ax.transAxes, color="#666")
            ax.set_title(title)
            ax.set_xlabel("iteration")
            _integer_x(ax)
            ax.legend(loc="best")
            ax.ticklabel_format(axis="y", useOffset=False)
        _coarse_panel(axes[1, 1], log, entries, found, truth)
        ax = axes[1, 2]
        timed = [e for e in train if isinstance(e.get("ms"), (int, float))]
        if timed:
            ms = [e["ms"] / 1000 for e in timed]
            ax.plot([e["iteration"] for e in timed], ms, color=LINE_COLOUR, lw=1, marker=".", ms=3)
            med = sorted(ms)[len(ms) // 2]
            ax.axhline(med, color=FOUND_COLOUR, ls=":", lw=1.4, label=f"median {med:.2f} s")
            ax.set_ylim(bottom=0)
            ax.legend(loc="best")
        else:
            _empty(ax, "no timings logged")
        ax.set_title("time per iteration (s)")
        ax.set_xlabel("iteration")
        _integer_x(ax)
        return _save(fig, path)


def _coarse_panel(ax: Any, log: Mapping[str, Any], entries: list, found: Mapping[str, Any],
                  truth: Mapping[str, Any]) -> None:
    """The coarse search's loss over log10 E (one line per floor friction and contact surface it tried), with the
    start, the found and the true E."""
    coarse = [c for c in log.get("coarse_search", []) if isinstance(c, Mapping)]
    if coarse:
        ys = [c["loss"] for c in coarse]
        groups = sorted({(c.get("contact_surface") or "", c.get("floor_friction")) for c in coarse},
                        key=lambda g: (g[0], -1.0 if g[1] is None else g[1]))
        for k, (surface, mu) in enumerate(groups):  # one line per contact surface and floor friction searched
            row = [c for c in coarse if c.get("floor_friction") == mu and (c.get("contact_surface") or "") == surface]
            what = ([] if mu is None else [f"floor friction {mu:g}"]) + ([f"{surface} contact"] if surface else [])
            ax.plot([c["log10_E"] for c in row], [c["loss"] for c in row], color=LINE_COLOUR, marker="o", ms=5,
                    lw=1.4, alpha=1.0 - 0.5 * k / max(1, len(groups) - 1),
                    label="loss on the grid" if not what else "loss, " + ", ".join(what))
        start = next((e["log10_E"] for e in entries if e.get("iteration") == 0), None)
        if isinstance(start, (int, float)):
            ax.axvline(start, color="#7a5af8", ls="-.", lw=1.3, label=f"start {start:.2f}")
        if isinstance(found.get("log10_E"), (int, float)):
            ax.axvline(found["log10_E"], color=FOUND_COLOUR, ls=":", lw=1.6, label=f"found {found['log10_E']:.2f}")
        if isinstance(truth.get("log10_E"), (int, float)):
            ax.axvline(truth["log10_E"], color=TRUTH_COLOUR, ls="--", lw=1.4, label=f"truth {truth['log10_E']:.2f}")
        if all(y > 0 for y in ys) and max(ys) > 10 * min(ys):
            ax.set_yscale("log")
        ax.legend(loc="best")
    else:
        _empty(ax, "no coarse search logged")
    ax.set_title("coarse search of E")
    ax.set_xlabel("log10 E")


def psnr_figure(path: Path, per_view: Mapping[str, Sequence[float | None]], held_out_views: Sequence[str],
                future: Sequence[bool], means: Sequence[tuple[str, Sequence[float | None], bool]] = ()) -> Path:
    """PSNR (dB) per frame: one line per view (held-out views dashed), future frames shaded.

    Args:
        per_view: view label → T values (None where a frame is not scored, e.g. frame 0).
        held_out_views: the labels of ``per_view`` that are held-out (novel) views.
        future: T booleans (True = a held-out future frame).
        means: (label, T values, dashed) curves drawn bold (e.g. the evaluation's means over views).
    """
    import matplotlib

    T = len(future)
    with matplotlib.rc_context(_RC):
        fig = _figure(11.5, 3.6)
        ax = fig.subplots()
        first_future = next((t for t in range(T) if future[t]), None)
        if first_future is not None:
            ax.axvspan(first_future - 0.5, T - 0.5, color=FUTURE_COLOUR, alpha=0.09, lw=0)
            ax.axvline(first_future - 0.5, color=FUTURE_COLOUR, lw=1.2)
            ax.text(first_future - 0.35, 1.0, "future →", color=FUTURE_COLOUR, transform=ax.get_xaxis_transform(),
                    va="top", fontsize=9, fontweight="bold")
            ax.text(first_future - 0.65, 1.0, "← observed", color=OBSERVED_COLOUR,
                    transform=ax.get_xaxis_transform(), va="top", ha="right", fontsize=9, fontweight="bold")
        obs_cmap = matplotlib.colormaps["Blues"]
        novel_cmap = matplotlib.colormaps["Oranges"]
        observed = [k for k in per_view if k not in held_out_views]
        for i, key in enumerate(per_view):
            values = per_view[key]
            xs = [t for t in range(T) if values[t] is not None]
            if key in held_out_views:
                j = list(held_out_views).index(key)
                colour, ls = novel_cmap(0.55 + 0.35 * j / max(1, len(held_out_views) - 1)), "--"
            else:
                j = observed.index(key)
                colour, ls = obs_cmap(0.45 + 0.45 * j / max(1, len(observed) - 1)), "-"
            ax.plot(xs, [values[t] for t in xs], color=colour, ls=ls, lw=1.2, marker=".", ms=3, label=key)
        for key, values, dashed in means:
            xs = [t for t in range(T) if values[t] is not None]
            ax.plot(xs, [values[t] for t in xs], color="#111", lw=2.2, ls="--" if dashed else "-", label=key)
        ax.set_xlim(-0.5, T - 0.5)
        ax.set_xlabel("frame")
        _integer_x(ax)
        ax.set_ylabel("PSNR (dB)")
        ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5))
        return _save(fig, path)


def material_scatter(path: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    """Found against true log10 E and ν of a suite's scenes (``rows``: ``name``, ``truth``, ``found`` dicts
    with ``log10_E`` and ``nu``; optional ``interval`` dict: ``log10_E`` / ``nu`` → [lo, hi], the reconstruction's
    own interval, drawn as an error bar, hollow where the parameter was not identifiable (``identifiable`` dict))."""
    import matplotlib

    with matplotlib.rc_context(_RC):
        fig = _figure(8.0, 3.6)
        axes = fig.subplots(1, 2)
        for ax, key, title, lo, hi in ((axes[0], "log10_E", "log10 E", 3.5, 6.5), (axes[1], "nu", "ν", 0.0, 0.5)):
            pts = [(r["truth"][key], r["found"][key], r["name"]) for r in rows
                   if _finite([r.get("truth", {}).get(key), r.get("found", {}).get(key)])]
            if pts:
                lo = min([lo] + [min(p[0], p[1]) for p in pts])
                hi = max([hi] + [max(p[0], p[1]) for p in pts])
                ax.plot([lo, hi], [lo, hi], color="#999", lw=1, ls="--", label="found = truth")
                ax.scatter([p[0] for p in pts], [p[1] for p in pts], color=FOUND_COLOUR, s=22, zorder=3,
                           label="scene")
                bars = [(r["truth"][key], r["found"][key], r["interval"][key],
                         (r.get("identifiable") or {}).get(key, True))
                        for r in rows if _finite([r.get("truth", {}).get(key), r.get("found", {}).get(key)])
                        and isinstance((r.get("interval") or {}).get(key), (list, tuple))]
                for x, y, (a, b), known in bars:
                    ax.errorbar([x], [y], yerr=[[max(0.0, y - a)], [max(0.0, b - y)]], color=FOUND_COLOUR,
                                lw=1.0, capsize=2, ls="none", alpha=1.0 if known else 0.4)
                    if not known:
                        ax.scatter([x], [y], s=60, facecolors="none", edgecolors="#666", zorder=4)
                ax.set_xlim(lo, hi)
                ax.set_ylim(lo, hi)
                ax.legend(loc="upper left")
            else:
                _empty(ax, "no scene with a known truth")
            ax.set_title(f"{title}: found vs truth")
            ax.set_xlabel(f"true {title}")
            ax.set_ylabel(f"found {title}")
        return _save(fig, path)
