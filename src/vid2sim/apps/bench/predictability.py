"""``vid2sim bench predictability``: how well a synthetic scene's own physics predicts its frames.

A drop that bounces and tumbles on a frictionless floor is sensitive to its start: where it first touches the
floor decides how it spins away, and small differences grow with every bounce. A reconstruction knows the
start only as well as the pixels show it (about 1.4 cm per pixel at the small preset). So no reconstruction
can be expected to reproduce a scene's later frames better than the truth reproduces itself from a slightly
different start.

This benchmark measures that. The scene's ground truth is simulated again with everything the same (its
``synthetic.json``, its own tet mesh from ``fem_result.npz``, the same time-convergence schedule) except the
drop height, raised by ``height_offset`` (default 1 mm, a fourteenth of a pixel at 128²). The twin is written
as a scene folder, and its images are scored against the truth's exactly as ``vid2sim evaluate`` scores an
asset (:func:`vid2sim.evaluate.scores.scene_groups`: dynamic, future and novel-view PSNR / SSIM). With the
offset 0 the twin is the truth itself (the FEM and the renderer are deterministic), which the tests check.
The mean distance between the two surfaces (the same vertices) per frame is reported too.

Read the result as a ceiling, not a bound: a reconstruction whose start and geometry are off by more than the
offset will, on average, not reach the twin's future-frame PSNR; one may by luck. See docs/benchmarks.md.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vid2sim.evaluate.scores import scene_groups
from vid2sim.metrics.geometry import boundary_faces
from vid2sim.runtime.errors import InputError
from vid2sim.runtime.files import write_text_atomic
from vid2sim.scene.reading import load_scene
from vid2sim.synthetic.scenes import (
    FEM_RESULT_NPZ,
    SYNTHETIC_JSON,
    SyntheticSceneConfig,
    check_existing_scene,
    make_scene,
)

if TYPE_CHECKING:
    from vid2sim.synthetic.scenes import SyntheticSceneConfig

PREDICTABILITY_JSON = "predictability.json"
TWIN_DIR = "twin"


def twin_config(scene: str | Path, height_offset: float) -> "SyntheticSceneConfig":
    """The :class:`~vid2sim.synthetic.scenes.SyntheticSceneConfig` of a scene's twin: the scene's own settings
    and tet mesh, the drop height raised by ``height_offset`` (m, ≥ 0)."""
    from dataclasses import replace


    root = Path(scene)
    if not (isinstance(height_offset, (int, float)) and math.isfinite(height_offset) and height_offset >= 0):
        raise InputError(f"height_offset must be a finite number of metres >= 0, got {height_offset!r}")
    for name in (SYNTHETIC_JSON, FEM_RESULT_NPZ, "scene.json"):
        if not (root / name).is_file():
            raise FileNotFoundError(f"{root / name}: not found; bench predictability needs a synthetic scene "
                                    "folder written by vid2sim make-scene or make-benchmark")
    config = SyntheticSceneConfig.from_json(root / SYNTHETIC_JSON)
    meta = json.loads((root / "scene.json").read_text()).get("metadata", {})
    fem = meta.get("fem", {})
    try:
        height = float(meta["initial_pose"]["drop_height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{root / 'scene.json'}: metadata.initial_pose.drop_height is needed (a scene written by "
                         "make-scene)") from None
    schedule = fem.get("time_convergence", {}).get("substeps") if isinstance(fem, dict) else None
    # the same first substep count: the twin's time-convergence schedule is the truth's
    substeps = int(schedule[0]) if schedule else config.substeps
    return replace(config, drop_height=height + float(height_offset), tet_mesh=str(root / FEM_RESULT_NPZ),
                   substeps=substeps)


def _surface_offsets(truth: dict, twin: dict) -> list[float]:
    """Per frame, the mean distance (m) between the two runs' boundary vertices (the same mesh)."""
    import torch


    faces = boundary_faces(truth["tets"])
    surface = torch.unique(faces.reshape(-1))
    a, b = truth["vertices"][:, surface].double(), twin["vertices"][:, surface].double()
    return [float(v) for v in (a - b).norm(dim=-1).mean(dim=1)]


def predictability(scene: str | Path, out: str | Path, height_offset: float = 1e-3, progress: bool = True,
                   workers: int = 1) -> dict[str, Any]:
    """Simulate and render the twin of ``scene`` into ``out/twin`` and score it against the scene.

    Args:
        scene: a synthetic scene folder (``make-scene`` / ``make-benchmark``).
        out: results folder: ``twin/`` (a scene folder, reused when a complete one with the same settings is
            there) and ``predictability.json`` (written last, atomically).
        height_offset: how much higher (m) the twin starts.
        progress: progress bars.
        workers: processes for the FEM's first pair of time resolutions.

    Returns:
        The JSON-ready report: ``dynamic``, ``future``, ``novel_views`` (as in ``vid2sim evaluate``),
        ``surface_offset_m`` (per frame), ``observed_mean_surface_offset_m``, ``future_mean_surface_offset_m``,
        the twin's and the truth's FEM substeps, and the settings.
    """

    root, out = Path(scene), Path(out)
    config = twin_config(root, height_offset)
    twin = out / TWIN_DIR
    if (twin / SYNTHETIC_JSON).is_file():  # a finished twin (make_scene renames it into place when complete)
        check_existing_scene(twin, config)
    else:
        make_scene(config, twin, progress=progress, workers=workers)
    truth, copy = load_scene(root), load_scene(twin)
    if truth.images.shape != copy.images.shape:
        raise InputError(f"{twin}: the twin's images {tuple(copy.images.shape)} differ in shape from the scene's "
                         f"{tuple(truth.images.shape)}")
    report: dict[str, Any] = {
        "what": "the scene's ground truth simulated again from a start raised by height_offset_m, scored "
                "against the scene like an asset (vid2sim evaluate): a ceiling for what a reconstruction "
                "can predict",
        "scene": str(root), "twin": str(twin), "height_offset_m": float(height_offset),
        **scene_groups(copy.images.float(), truth.images.float(), truth.config),
    }
    tt, tc = truth.extras.get("tet_trajectory"), copy.extras.get("tet_trajectory")
    if tt is not None and tc is not None:
        per_frame = _surface_offsets(tt, tc)
        obs, held = list(truth.config.observed_frames), list(truth.config.held_out_frames)
        report["surface_offset_m"] = per_frame
        report["observed_mean_surface_offset_m"] = sum(per_frame[f] for f in obs) / len(obs)
        report["future_mean_surface_offset_m"] = sum(per_frame[f] for f in held) / len(held) if held else None
    fem_truth = truth.config.metadata.get("fem", {}).get("substeps")
    fem_twin = copy.config.metadata.get("fem", {}).get("substeps")
    report["fem_substeps"] = {"truth": fem_truth, "twin": fem_twin}
    write_text_atomic(out / PREDICTABILITY_JSON, json.dumps(report, indent=2) + "\n")
    return report


def format_summary(report: dict[str, Any]) -> str:
    """A few lines for the terminal: the twin's PSNR per group and the surface offsets."""
    lines = [f"twin raised by {1000 * report['height_offset_m']:.3g} mm against {report['scene']}:"]
    for key in ("dynamic", "future", "novel_views"):
        group = report.get(key) or {}
        if group:
            lines.append(f"  {key:12s} PSNR {group['psnr']:.2f} dB  SSIM {group['ssim']:.4f}")
    if "observed_mean_surface_offset_m" in report:
        fut = report.get("future_mean_surface_offset_m")
        lines.append(f"  surface offset: observed frames {1000 * report['observed_mean_surface_offset_m']:.2f} mm"
                     + (f", future frames {1000 * fut:.2f} mm" if fut is not None else ""))
    subs = report.get("fem_substeps", {})
    if subs.get("truth") != subs.get("twin"):
        lines.append(f"  note: the FEM kept {subs.get('twin')} substeps per frame for the twin and "
                     f"{subs.get('truth')} for the truth; part of the difference is then time discretisation")
    return "\n".join(lines)
