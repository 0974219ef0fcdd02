"""Self-contained HTML reports: one folder a person opens in a browser (docs/report.md).

* :func:`write_report` — one asset, with the scene it was reconstructed from (side-by-side ground truth |
  reconstruction | error videos per view over observed and future frames, metric tables, material found vs
  truth, per-frame PSNR, optimisation curves, timings) or without one (the asset's drop in a ring of cameras);
* :func:`write_suite_report` — a benchmark suite: one row per scene with thumbnails, metrics, material and
  status, linking to each scene's report;
* :class:`ReportConfig` — sizes, colour map and video encoding; :class:`ReportInputError` — bad inputs.

``vid2sim report ASSET OUT [--scene SCENE]`` is the command.
"""

from __future__ import annotations

from vid2sim.report.config import ReportConfig, ReportInputError
from vid2sim.report.scene_report import write_report
from vid2sim.report.suite_report import write_suite_report

__all__ = ["ReportConfig", "ReportInputError", "write_report", "write_suite_report"]
