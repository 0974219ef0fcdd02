"""The report of one asset (and the scene it was reconstructed from): :func:`write_report`.

A folder that a person opens in a browser (``index.html``, everything else under ``media/``)::

    index.html          header, summary figures, material found vs truth, metric tables, videos, key-frame
                        strips, per-frame PSNR, optimisation curves, stage timings, files
    report.json         the numbers shown (evaluation, material, per-view PSNR), the settings, the file list
    media/view_00.webm  per view: ground truth | reconstruction | |error| heat map, frame labels and timeline
    media/keyframes_*.png, media/psnr_per_frame.svg, media/optimisation.svg, media/thumb.png, …

With a scene, the videos compare the asset's simulated and rendered drop with the scene's frames in every
camera (observed and held-out views; observed and future frames, marked). Without one, the asset's own drop
is rendered in a ring of cameras around it.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from vid2sim import __version__
from vid2sim.metrics.images import psnr
from vid2sim.report import html as H
from vid2sim.report import media as M
from vid2sim.report.config import ReportConfig, ReportInputError
from vid2sim.report.inputs import GROUPS, check_evaluation
from vid2sim.report.plots import optimisation_figure, psnr_figure
from vid2sim.runtime.files import write_folder_atomic
from vid2sim.runtime.jsonvalues import is_finite_number as _isnum
from vid2sim.scene.folder import Scene
from vid2sim.scene.reading import load_scene

GROUP_TITLES = {"dynamic": "Dynamic reconstruction", "future": "Future prediction", "novel_views": "Novel views",
                "rest": "At rest (frame 0)"}


# ---------------------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------------------

def _read_json(path: Path, required: bool) -> dict[str, Any] | None:
    if not path.is_file():
        if required:
            raise ReportInputError(f"{path} not found (an asset folder written by vid2sim reconstruct holds it)")
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ReportInputError(f"{path}: cannot read it as JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ReportInputError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def check_out(out: Path) -> None:
    """Raise :class:`ReportInputError` unless ``out`` can become a report folder (absent, or a previous report)."""
    if out.exists() and not out.is_dir():
        raise ReportInputError(f"report folder {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "index.html").is_file():
        raise ReportInputError(f"report folder {out} is a non-empty folder without index.html; refusing to replace it")


def _same_folder(a: Any, b: Any) -> bool:
    try:
        return a is not None and b is not None and Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def _video_says(entry: dict[str, Any]) -> str:
    """What the report adds after a material value of the uncertainty ``entry`` (material.json): that the video does
    not determine it, or that the fit left it at its start (every step refused), or nothing."""
    if not entry.get("identifiable", True):
        return " · not identifiable from this video"
    if entry.get("moved") is False:
        return " · left at its start: no step of the fit lowered the validation loss"
    return ""


@dataclass
class RingRenders:
    """An asset's own drop rendered in a ring of cameras (the report without a scene).

    Attributes:
        renders: (V, T, R, R, 3) in [0, 1]: V ring cameras, T frames.
        azimuths_deg: (V,) the cameras' azimuths.
        dt: seconds between frames.
        observed_frames: frames of the observed video (the later ones are marked future).
    """

    renders: Tensor
    azimuths_deg: list[float]
    dt: float
    observed_frames: int


# ---------------------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------------------

def write_report(out_dir: str | Path, asset: str | Path, scene: Any = None, evaluation: Mapping[str, Any] | None = None,
                 renders: Tensor | None = None, ring: RingRenders | None = None, progress: bool = True,
                 config: ReportConfig | None = None, simulations: Sequence[str | Path] = (),
                 timings: Mapping[str, float] | None = None) -> Path:
    """Write the HTML report of an asset into ``out_dir`` (atomically; a previous report there is replaced).

    The report renders what it is given and computes nothing (:func:`vid2sim.apps.report.asset_report` simulates,
    renders and evaluates what is missing, then calls this).

    Args:
        out_dir: the report folder to create (``index.html`` + ``media/`` + ``report.json``).
        asset: the asset folder (``material.json``, ``log.json``, …; docs/asset-format.md).
        scene: the scene folder (path) or a loaded :class:`~vid2sim.scene.folder.Scene`, or None for the
            asset's own drop in a ring of cameras (``ring``).
        evaluation: the evaluation dict (``vid2sim evaluate``'s JSON), or None.
        renders: with a scene: (V, T, H, W, 3) renders in [0, 1] of the asset in the scene's cameras.
        ring: without a scene: the asset's drop in a ring of cameras.
        progress: tqdm progress bars.
        config: :class:`ReportConfig` (sizes, colour map, video format); None for the defaults.
        simulations: ``vid2sim simulate`` output folders of this asset, shown in a "New situations" section
            (each one's scenario, summary figures and its cameras' animated GIFs).
        timings: seconds the caller spent making the inputs, by what it did (shown with the report's own).

    Returns:
        ``out_dir`` as a Path.

    Raises:
        ReportInputError: a missing or malformed input (the message names it); SceneFormatError from loading
        the scene.
    """
    t_start = time.perf_counter()
    config = config or ReportConfig()
    out = Path(out_dir)
    asset_dir = Path(asset)
    if not asset_dir.is_dir():
        raise ReportInputError(f"asset folder {asset_dir} not found")
    material = _read_json(asset_dir / "material.json", required=True)
    log = _read_json(asset_dir / "log.json", required=False) or {}
    asset_json = _read_json(asset_dir / "asset.json", required=False) or {}
    check_out(out)
    if renders is not None and scene is None:
        raise ReportInputError("renders were given without a scene; renders are the asset in the scene's cameras")
    if scene is None and ring is None:
        raise ReportInputError("without a scene the report shows the asset's drop in a ring of cameras: give ring")
    if evaluation is not None:
        evaluation = check_evaluation(evaluation)
    scene_obj, scene_path = _scene(scene, progress)
    if scene_obj is not None:
        V, T, Hh, Ww, _ = scene_obj.images.shape
        if not isinstance(renders, Tensor) or tuple(renders.shape) != (V, T, Hh, Ww, 3):
            shape = tuple(renders.shape) if isinstance(renders, Tensor) else type(renders).__name__
            raise ReportInputError(f"renders must be a tensor of the scene's shape {(V, T, Hh, Ww, 3)} "
                                   f"(V, T, H, W, 3), got {shape}")
    def write(staging: Path) -> None:
        (staging / "media").mkdir(parents=True)
        builder = _Builder(staging, asset_dir, material, log, asset_json, evaluation, config, progress)
        if scene_obj is not None:
            builder.scene_media(scene_obj, scene_path, renders.detach().float().cpu())
        else:
            builder.ring_media(ring)
        for folder in simulations:
            builder.simulation_media(Path(folder))
        builder.timings.update(timings or {})
        builder.finish(time.perf_counter() - t_start)

    return write_folder_atomic(out, write)


def _scene(scene: Any, progress: bool) -> tuple[Scene | None, Path | None]:
    """The loaded scene and its folder (both None without a scene)."""
    if scene is None:
        return None, None
    if isinstance(scene, Scene):
        return scene, scene.root
    if isinstance(scene, (str, Path)):
        if not Path(scene).is_dir():
            raise ReportInputError(f"scene folder {scene} not found")
        return load_scene(scene, progress=progress), Path(scene)
    raise ReportInputError(f"scene must be a scene folder path or a loaded Scene, got {type(scene).__name__}")


class _Builder:
    """Writes the media of one report into ``root/media`` and assembles its page."""

    def __init__(self, root: Path, asset_dir: Path, material: dict, log: dict, asset_json: dict,
                 evaluation: dict | None, config: ReportConfig, progress: bool) -> None:
        self.root, self.media = root, root / "media"
        self.asset_dir, self.material, self.log, self.asset_json = asset_dir, material, log, asset_json
        self.evaluation, self.config, self.progress = evaluation, config, progress
        self.sections: list[tuple[str, str, str]] = []  # (anchor, nav label, html)
        self.timings: dict[str, float] = {}
        self.data: dict[str, Any] = {"asset": str(asset_dir), "evaluation": evaluation, "material": material,
                                     "config": config.to_dict()}
        self.scene_desc = ""
        self.truth: dict[str, Any] = {}
        self.video_count = 0

    # ---- media -------------------------------------------------------------------------------------

    def _encode(self, name: str, frames: np.ndarray) -> Path:
        return M.encode_video(self.media / name, frames, self.config.video_fps, self.config.video_crf,
                              self.config.video_format, threads=torch.get_num_threads())

    def _video_html(self, path: Path, probe: str, size: tuple[int, int]) -> str:
        """A looping, muted, synchronised ``<video>`` (WebM) or an animated ``<img>`` (WebP); ``size`` is the
        video's (width, height), given so the page does not reflow when it loads."""
        rel = f"media/{path.name}"
        wh = f'width="{size[0]}" height="{size[1]}"'
        if path.suffix == ".webm":
            return (f'<video class="sync" src="{H.esc(rel)}" {wh} data-fps="{self.config.video_fps:g}" '
                    f'data-probe="{probe}" autoplay muted loop playsinline preload="auto">'
                    f'Your browser cannot play WebM (VP9); open <a href="{H.esc(rel)}">{H.esc(path.name)}</a>.</video>')
        return f'<img class="anim" src="{H.esc(rel)}" {wh} alt="{H.esc(path.stem)}" data-probe="{probe}">'

    def scene_media(self, scene: Any, scene_path: Path | None, renders: Tensor) -> None:
        """The media and sections of a report with a scene: per view a video of ground truth | reconstruction |
        error, key-frame strips, the thumbnail, the per-frame PSNR plot, then the summary and tables.

        Args:
            scene: the loaded scene (images (V, T, H, W, 3)). scene_path: its folder, or None.
            renders: (V, T, H, W, 3) float in [0, 1], the asset rendered in the scene's cameras.
        """
        targets = scene.float_images() if hasattr(scene, "float_images") else scene.images.float()
        V, T, Hh, Ww, _ = targets.shape
        obs_v, held_v, obs_f, held_f = self._scene_facts(scene, scene_path, V, T, Hh, Ww)
        # per-view, per-frame PSNR (the same per-image PSNR as the evaluation's means)
        per_view = [[psnr(renders[v, t], targets[v, t]) for t in range(T)] for v in range(V)]
        self.data["psnr_per_view_frame"] = per_view
        panels = _view_panels(scene, targets, renders, self.config)
        self.data["crop_boxes_y0_y1_x0_x1"] = panels.boxes
        cards, videos = self._view_videos(panels, per_view, held_v, obs_f, held_f, (Hh, Ww))
        self.video_count = len(videos)
        self.data["videos"] = videos
        # key-frame strips of the first observed and first held-out view
        picks = _keyframes(T, held_f[0] if held_f else None, self.config.filmstrip_frames)
        strips = [self._keyframe_strip(panels, v, picks, held_v)
                  for v in ([obs_v[0]] if obs_v else []) + ([held_v[0]] if held_v else [])]
        # thumbnail: frame 0 of the first observed view, ground truth | reconstruction
        gt_t, rd_t, _ = panels(obs_v[0] if obs_v else 0, [0], self.config.thumb_size)
        M.save_png(self.media / "thumb.png", M.titled_panels([gt_t[0], rd_t[0]], ["ground truth", "reconstruction"]))
        self._psnr_plot(per_view, held_v, T)
        self._summary_and_tables()
        self._scene_sections(T, cards, videos, strips, len(picks))

    def _scene_facts(self, scene: Any, scene_path: Path | None, V: int, T: int, Hh: int, Ww: int
                     ) -> tuple[list[int], list[int], list[int], list[int]]:
        """Record what the report says of the scene (future frames, Δt, its truth, its description; report.json's
        scene entries); its observed and held-out views and frames."""
        sc = scene.config.resolved(V, T)
        obs_v, held_v = list(sc.observed_views), list(sc.held_out_views)
        obs_f, held_f = list(sc.observed_frames), list(sc.held_out_frames)
        future = [t in set(held_f) for t in range(T)]
        self.future, self.dt = future, float(sc.dt)
        meta = sc.metadata or {}
        self.truth = {
            k: meta[k] for k in ("E", "nu", "damping_ratio", "density") if isinstance(meta.get(k), (int, float))
        }
        if isinstance(self.truth.get("E"), (int, float)) and self.truth["E"] > 0:
            self.truth["log10_E"] = math.log10(self.truth["E"])
        name = scene_path.name if scene_path is not None else "scene"
        self.scene_name = name
        self.scene_desc = (f"{V} views ({len(obs_v)} observed, {len(held_v)} held out) · {Ww}×{Hh} px · "
                           f"{T} frames ({len(obs_f)} observed + {len(held_f)} future) · Δt = {sc.dt:g} s")
        self.data.update({"scene": None if scene_path is None else str(scene_path), "views": V, "frames": T,
                          "observed_views": obs_v, "held_out_views": held_v, "observed_frames": obs_f,
                          "held_out_frames": held_f, "dt": sc.dt, "truth": self.truth})
        return obs_v, held_v, obs_f, held_f

    def _view_videos(self, panels: "_ViewPanels", per_view: list[list[float]], held_v: list[int], obs_f: list[int],
                     held_f: list[int], size: tuple[int, int]) -> tuple[list[str], list[str]]:
        """Encode every view's video (ground truth | reconstruction | error, with its PSNR per frame); the views'
        cards (HTML) and the videos' file names. ``size``: the scene's (H, W)."""
        from tqdm.auto import tqdm

        cfg = self.config
        Hh, Ww = size
        headings = [("ground truth", "scene frames"), ("reconstruction", "simulated + rendered"), ("|error|", "")]
        cards = []
        videos = []
        for v in tqdm(range(len(per_view)), desc="report videos", disable=not self.progress, leave=False):
            frames = M.compose_video(panels(v, slice(None), cfg.panel_size), headings, self.future, self.dt,
                                     psnr=per_view[v], error_panel=2, error_max=cfg.error_max, cmap=cfg.error_cmap)
            path = self._encode(f"view_{v:02d}", frames)
            videos.append(path.name)
            held = v in held_v
            obs_mean = _mean([per_view[v][t] for t in obs_f if t > 0])
            fut_mean = _mean([per_view[v][t] for t in held_f])
            role = (
                '<span class="tag novel">held-out view</span>' if held else '<span class="tag obs">observed view</span>'
            )
            y0, y1, x0, x1 = panels.boxes[v]
            crop = ("full frame" if (y0, y1, x0, x1) == (0, Hh, 0, Ww)
                    else f"crop x {x0}–{x1 - 1}, y {y0}–{y1 - 1} of {Ww}×{Hh}")
            cards.append(
                f'<div class="video-card"><div class="caption"><span><b>View {v}</b> {role} '
                f'<span class="crop">{crop}</span></span>'
                f'<span>PSNR <span class="tag obs">observed frames</span> {H.fmt(obs_mean)} dB · '
                f'<span class="tag fut">future</span> {H.fmt(fut_mean)} dB</span></div>'
                f'{self._video_html(path, f"video:{v}", (frames.shape[2], frames.shape[1]))}</div>')
        return cards, videos

    def _keyframe_strip(self, panels: "_ViewPanels", v: int, picks: list[int], held_v: list[int]) -> str:
        """Save view ``v``'s key frames ``picks`` (ground truth, reconstruction and error rows) as a PNG; its HTML."""
        cfg = self.config
        rows = panels(v, picks, 128)
        kind = "held-out view" if v in held_v else "observed view"
        grid = M.labelled_grid(rows, ["ground truth", "reconstruction", f"|error|\n0 … {cfg.error_max:g}"],
                               [f"frame {t}" for t in picks],
                               [H.FUTURE_COLOUR if self.future[t] else H.OBSERVED_COLOUR for t in picks])
        path = M.save_png(self.media / f"keyframes_view_{v:02d}.png", grid)
        return (f'<h3>View {v} ({kind})</h3><div class="figure strip">'
                f'<img src="media/{path.name}" alt="key frames of view {v}" data-probe="strip:{v}"></div>')

    def _psnr_plot(self, per_view: list[list[float]], held_v: list[int], T: int) -> None:
        """The per-frame PSNR plot: one line per view, and the evaluation's means over the observed and the
        held-out views."""
        V = len(per_view)
        labels = {v: f"view {v}" + (" (held out)" if v in held_v else "") for v in range(V)}
        means = []
        ev = self.evaluation or {}
        obs_mean_curve: list[float | None] = [None] * T
        for group in ("dynamic", "future"):
            g = ev.get(group) or {}
            for f, value in zip(g.get("frames") or [], g.get("psnr_per_frame") or []):
                if 0 <= f < T:
                    obs_mean_curve[f] = value
        if any(x is not None for x in obs_mean_curve):
            means.append(("mean, observed views (evaluation)", obs_mean_curve, False))
        g = ev.get("novel_views") or {}
        novel_curve: list[float | None] = [None] * T
        for f, value in zip(g.get("frames") or [], g.get("psnr_per_frame") or []):
            if 0 <= f < T:
                novel_curve[f] = value
        if any(x is not None for x in novel_curve):
            means.append(("mean, held-out views (evaluation)", novel_curve, True))
        psnr_figure(self.media / "psnr_per_frame.svg", {labels[v]: per_view[v] for v in range(V)},
                    [labels[v] for v in held_v], self.future, means)

    def _scene_sections(self, T: int, cards: list[str], videos: list[str], strips: list[str], picks: int) -> None:
        """The videos, key-frames (``picks`` frames a strip) and per-frame PSNR sections of a report with a scene."""
        cfg = self.config
        controls = _controls(T, self.config, videos and videos[0].endswith(".webm"))
        crop_note = (" Each view is cropped to the square around everything that appears in it over the video "
                     "(named above the video)." if cfg.crop else "")
        self.sections.append(("videos", "Videos", H.section(
            "videos", "Videos: ground truth | reconstruction | error, per view",
            f'<div class="controls">{controls}</div><div class="video-grid">{"".join(cards)}</div>',
            "Each video shows the scene's frames, the asset simulated from its recovered initial state and rendered "
            "in the same camera, and their difference as a heat map (mean over RGB of the absolute error, "
            f"black = 0, brightest = {cfg.error_max:g} or more). The strip under each video names the frame, its "
            'PSNR and whether it was <span class="tag obs">observed</span> during the reconstruction or is a '
            '<span class="tag fut">future</span> frame the simulator predicted; the timeline below it marks the '
            "boundary. Held-out views were never seen by the reconstruction." + crop_note)))
        if strips:
            self.sections.append(("keyframes", "Key frames", H.section(
                "keyframes", "Key frames", "".join(strips),
                f"{picks} frames of the first observed and the first held-out view at a glance "
                "(green labels: observed frames, orange: future frames).")))
        self.sections.append(
            (
                "psnr",
                "Per-frame PSNR",
                H.section(
                    "psnr",
                    "PSNR per frame and view",
                    '<div class="figure"><img src="media/psnr_per_frame.svg" alt="PSNR per frame" '
                    'data-probe="plot:psnr"></div>',
                    "Per-image PSNR of the reconstruction against the ground truth, one line per view (held-out views "
                    "dashed); "
                    "bold lines are the evaluation's means over views. Frame 0 is the fitted initial state (not part "
                    "of "
                    "the evaluation's means); the shaded frames were held out and predicted.",
                ),
            )
        )

    def ring_media(self, ring: RingRenders) -> None:
        cfg = self.config
        renders, azimuths, T, observed = ring.renders, ring.azimuths_deg, ring.renders.shape[1], ring.observed_frames
        views, R = renders.shape[0], renders.shape[2]
        future = [t >= observed for t in range(T)]
        self.future, self.dt = future, float(ring.dt)
        self.scene_name = None
        self.scene_desc = (f"no scene: the asset's captured drop in {views} ring cameras · "
                           f"{R}×{R} px · {T} frames (the observed video had {observed}) · Δt = {ring.dt:g} s")
        self.data.update({"scene": None, "views": views, "frames": T, "dt": ring.dt, "ring_azimuths_deg": azimuths})
        ev_truth = ((self.evaluation or {}).get("material") or {}).get("truth") or {}
        self.truth = {k: ev_truth[k] for k in ("E", "nu") if isinstance(ev_truth.get(k), (int, float))}
        if self.truth.get("E", 0) > 0:
            self.truth["log10_E"] = math.log10(self.truth["E"])
        r8 = M.to_uint8(renders)
        factor = M.scale_factor(R, cfg.panel_size)
        video = M.compose_video([M.rescale(r8[v], factor) for v in range(views)],
                                [(f"camera {v}", f"azimuth {a:.0f}°") for v, a in enumerate(azimuths)], future, self.dt,
                                tags=("OBSERVED TIME SPAN", "FUTURE · predicted"))
        path = self._encode("ring", video)
        self.video_count = 1
        self.data["videos"] = [path.name]
        tf = M.scale_factor(R, cfg.thumb_size)
        M.save_png(self.media / "thumb.png", M.titled_panels([M.rescale(r8[0, 0], tf)], ["reconstruction"]))
        self._summary_and_tables()
        controls = _controls(T, cfg, path.suffix == ".webm")
        self.sections.append(("videos", "Video", H.section(
            "videos", "The asset's drop in a ring of cameras",
            f'<div class="controls">{controls}</div><div class="video-card">'
            f'{self._video_html(path, "video:ring", (video.shape[2], video.shape[1]))}</div>',
            "No scene was given, so there is no ground truth to compare with: the asset is simulated from its "
            f"recovered initial state with its recovered material and rendered in {views} cameras around "
            'its trajectory. Frames past the length of the observed video are marked <span class="tag fut">future'
            "</span>; give <code>--scene</code> for the comparison with the scene's frames.")))

    # ---- sections ----------------------------------------------------------------------------------

    def _summary_and_tables(self) -> None:
        """The summary cards, the material table (found vs truth) and the metrics table, from the asset's material
        and the evaluation."""
        ev = self.evaluation or {}
        found, truth, errors = self._material_comparison(ev)
        self._summary_section(ev, found, truth, errors)
        self._material_section(found, truth, errors, ev.get("geometry_stiffness"), ev.get("solid"))
        self._metrics_section(ev)

    def _material_comparison(self, ev: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        """The material found, the truth (the scene's, completed by the evaluation's) and their absolute errors
        (the evaluation's, else computed), each by parameter; kept for the later sections and report.json."""
        mat_ev = ev.get("material") or {}
        found = {"E": self.material.get("E"), "log10_E": self.material.get("log10_E"), "nu": self.material.get("nu"),
                 "damping_ratio": self.material.get("damping_ratio"), "density": self.material.get("density"),
                 "floor_friction": self.asset_json.get("floor_friction")}
        truth = dict(self.truth)
        if _isnum(mat_ev.get("true_floor_friction")):
            truth.setdefault("floor_friction", mat_ev["true_floor_friction"])
        for k, v in (mat_ev.get("truth") or {}).items():
            truth.setdefault(k, v)
        if isinstance(truth.get("E"), (int, float)) and truth["E"] > 0:
            truth.setdefault("log10_E", math.log10(truth["E"]))
        errors = {"log10_E": mat_ev.get("abs_error_log10_E"), "nu": mat_ev.get("abs_error_nu")}
        for key in ("log10_E", "nu", "damping_ratio", "floor_friction"):
            if errors.get(key) is None and _isnum(found.get(key)) and _isnum(truth.get(key)):
                errors[key] = abs(found[key] - truth[key])
        self.found, self.truth = found, truth
        self.data["material_table"] = {"found": found, "truth": truth, "errors": errors}
        return found, truth, errors

    def _summary_section(self, ev: dict[str, Any], found: dict[str, Any], truth: dict[str, Any],
                         errors: dict[str, Any]) -> None:
        """The summary cards: PSNR per group, E and ν against the truth, their errors against the targets,
        Chamfer and centre-of-mass distances."""
        cards = []
        groups = (("dynamic", "PSNR observed"), ("future", "PSNR future"), ("novel_views", "PSNR novel views"))
        for group, label in groups:
            g = ev.get(group) or {}
            if _isnum(g.get("psnr")):
                note = f"SSIM {H.fmt(g.get('ssim'), 4)}"
                single = ev.get("future_from_start") or {}
                if group == "future" and g.get("starts_from") == "continuation" and _isnum(single.get("psnr")):
                    note += f"; from the last observed frames' state (one rollout from frame 0: " \
                            f"{H.fmt(single['psnr'], 2)} dB)"
                cards.append(H.card(label, H.fmt(g["psnr"], 2), note, unit="dB"))
        cards.append(
            H.card(
                "Young's modulus E",
                H.fmt_sci(found["E"]),
                f"truth {H.fmt_sci(truth['E'])} Pa" if _isnum(truth.get("E")) else "truth unknown",
                unit="Pa",
            )
        )
        nu_entry = (self.material.get("uncertainty") or {}).get("nu") or {}
        cards.append(H.card("Poisson's ratio ν", H.fmt(found["nu"], 3),
                            (f"truth {H.fmt(truth['nu'], 3)}" if _isnum(truth.get("nu")) else "truth unknown")
                            + _video_says(nu_entry)))
        if _isnum(errors.get("log10_E")):
            cards.append(H.card("|Δ log10 E|", H.fmt(errors["log10_E"], 3), "target ≤ 0.2",
                                "good" if errors["log10_E"] <= 0.2 else "bad", unit="decades"))
        if _isnum(errors.get("nu")):
            cards.append(H.card("|Δ ν|", H.fmt(errors["nu"], 3), "target ≤ 0.05",
                                "good" if errors["nu"] <= 0.05 else "bad"))
        ch = ev.get("chamfer") or {}
        if _isnum(ch.get("observed_mean")):
            cards.append(H.card("Chamfer, observed frames", H.fmt(100 * ch["observed_mean"], 2),
                                f"future frames {H.fmt(100 * ch['future_mean'], 2, 'cm')}"
                                if _isnum(ch.get("future_mean")) else "", unit="cm"))
        com = ev.get("centre_of_mass") or {}
        if _isnum(com.get("observed_mean")):
            cards.append(H.card("Centre of mass off the truth's, observed frames", H.fmt(100 * com["observed_mean"], 2),
                                f"future frames {H.fmt(100 * com['future_mean'], 2, 'cm')}"
                                if _isnum(com.get("future_mean")) else "", unit="cm"))
        intro = ("Figures from the evaluation; green/red mark the issue's targets (|Δ log10 E| ≤ 0.2, |Δ ν| ≤ 0.05)."
                 if ev else "No evaluation is available (run <code>vid2sim evaluate ASSET SCENE</code> or give "
                            "<code>--scene</code>): only the material found is shown.")
        self.sections.append(("summary", "Summary", H.section("summary", "Summary",
                                                               f'<div class="cards">{"".join(cards)}</div>', intro)))

    def _material_section(self, found: dict[str, Any], truth: dict[str, Any], errors: dict[str, Any],
                          stiffness: dict[str, Any] | None = None, solid: dict[str, Any] | None = None) -> None:
        """The material table: each parameter at the start, found, truth, error and interval; under it, with the
        evaluation's ``geometry_stiffness``, the reconstructed solid's lowest elastic mode against the truth's, and
        with its ``solid``, the solid's volume and reach against the truth's body."""
        start = next((e for e in self.log.get("iterations", []) if isinstance(e, dict) and e.get("iteration") == 0), {})
        rows = []
        specs = [("Young's modulus E (Pa)", "E", H.fmt_sci, None),
                 ("log10 E", "log10_E", lambda x: H.fmt(x, 3), "decades"),
                 ("Poisson's ratio ν", "nu", lambda x: H.fmt(x, 3), ""),
                 ("damping ratio ζ", "damping_ratio", lambda x: H.fmt(x, 3), ""),
                 ("floor friction μ", "floor_friction", lambda x: H.fmt(x, 3), ""),
                 ("density (kg/m³, not fitted)", "density", lambda x: H.fmt(x, 0), None)]
        for label, key, f, unit in specs:
            st = start.get(key) if key != "E" else (10 ** start["log10_E"] if _isnum(start.get("log10_E")) else None)
            cells = [
                f"<td>{H.esc(label)}</td>",
                H.num_cell(st, f(st) if _isnum(st) else "—", key=f"start.{key}"),
                H.num_cell(found.get(key), f(found.get(key)), key=f"found.{key}"),
                H.num_cell(truth.get(key), f(truth.get(key)) if _isnum(truth.get(key)) else "—", key=f"truth.{key}"),
            ]
            if key == "E" and _isnum(found.get("E")) and _isnum(truth.get("E")):
                ratio = found["E"] / truth["E"]
                cells.append(H.num_cell(ratio, f"found / truth = {ratio:.2f}×", key="ratio.E"))
            elif unit is not None and _isnum(errors.get(key)):
                cells.append(H.num_cell(errors[key], f"{errors[key]:.3f}" + (f" {unit}" if unit else ""),
                                        key=f"error.{key}"))
            else:
                cells.append('<td class="na">—</td>')
            cells.append(self._interval_cell(key, f))
            rows.append("".join(cells))
        level = (self.material.get("uncertainty") or {}).get("level")
        interval_head = f"{100 * level:.0f} % interval" if _isnum(level) else "interval"
        body = H.table(["", "start (after the coarse search)", "found", "truth", "absolute error", interval_head], rows,
                       table_id="material-table")
        if stiffness:
            ratio, offset = stiffness["lowest_frequency_ratio"], stiffness["implied_log10_E_offset"]
            ratio_html = H.num_span(ratio, f"{ratio:.3f}", key="geometry_stiffness.lowest_frequency_ratio")
            offset_html = H.num_span(offset, f"{offset:+.3f}", key="geometry_stiffness.implied_log10_E_offset")
            body += ('<p class="note">The reconstructed solid’s lowest elastic mode is '
                     f"{ratio_html}× the truth’s (both at E = ρ = 1 and ν = {H.fmt(stiffness.get('nu'), 3)}): at a "
                     f"fixed ν a solid that vibrates r times faster fits E r² too low, so its shape alone implies "
                     f"log10 E {offset_html} decade. A score of the geometry (a hull that welds an object’s lobes "
                     "is stiffer than the object), not a correction to apply: a soft object’s motion is its squash "
                     "at the contact rather than this mode.</p>")
        if solid:
            spans = {key: H.num_span(solid[key], text, key=f"solid.{key}") for key, text in (
                ("volume_ratio", f"{solid['volume_ratio']:.3f}"),
                ("outside_truth_fraction", f"{100 * solid['outside_truth_fraction']:.1f} %"),
                ("bottom_offset_m", f"{100 * solid['bottom_offset_m']:+.2f} cm"),
                ("top_offset_m", f"{100 * solid['top_offset_m']:+.2f} cm"))}
            body += ('<p class="note">The simulation solid has '
                     f"{spans['volume_ratio']}× the truth’s volume, {spans['outside_truth_fraction']} of it outside "
                     f"the object; at frame 0 its lowest point is {spans['bottom_offset_m']} and its highest "
                     f"{spans['top_offset_m']} from the object’s, along gravity. The bottom meets the floor first: "
                     "a hull that reaches below the object bounces differently, and E is fitted to that bounce.</p>")
        self.sections.append(("material", "Material", H.section(
            "material", "Material found vs truth",
            body,
            "“Found” is the asset's material (the joint optimisation's best validation iterate); “truth” is the "
            "synthetic scene's ground truth when it is known. The interval is the reconstruction's own (a Laplace "
            "approximation of the whole clip's loss at the fit, widened by the reduced model's own error measured "
            "against FEM drops, material.json <code>uncertainty</code>); a parameter "
            "the images constrain less than the prior does is marked not identifiable from this video: its value "
            "is the prior's.")))

    def _metrics_section(self, ev: dict[str, Any]) -> None:
        """The metrics table: PSNR, SSIM (FoVVDP when evaluated), Chamfer, centre of mass and rotation per group."""
        ch = ev.get("chamfer") or {}
        com = ev.get("centre_of_mass") or {}
        turn = ev.get("orientation") or {}
        has_fov = any(_isnum((ev.get(g) or {}).get("fovvdp_jod")) for g in GROUPS)
        headers = ["", "views", "frames", "PSNR (dB)", "SSIM"] + (["FoVVDP (JOD)"] if has_fov else []) \
            + ["Chamfer (cm)", "centre of mass off (cm)", "rotation off (deg)"]
        rows = []
        chamfer_key = {"dynamic": "observed_mean", "future": "future_mean"}
        for group in GROUPS:
            g = ev.get(group) or {}
            if not g:
                continue
            cells = [f'<td><b>{GROUP_TITLES[group]}</b></td>', f"<td>{H.esc(_ranges(g.get('views')))}</td>",
                     f"<td>{H.esc(_ranges(g.get('frames')))}</td>",
                     H.num_cell(g.get("psnr"), digits=2, key=f"{group}.psnr"),
                     H.num_cell(g.get("ssim"), digits=4, key=f"{group}.ssim")]
            if has_fov:
                cells.append(H.num_cell(g.get("fovvdp_jod"), digits=3, key=f"{group}.fovvdp_jod"))
            cv = ch.get(chamfer_key[group]) if group in chamfer_key else None
            cells.append(H.num_cell(cv, H.fmt(100 * cv, 2) if _isnum(cv) else "—",
                                    key=f"chamfer.{chamfer_key[group]}" if group in chamfer_key else ""))
            mv = com.get(chamfer_key[group]) if group in chamfer_key else None
            cells.append(H.num_cell(mv, H.fmt(100 * mv, 2) if _isnum(mv) else "—",
                                    key=f"centre_of_mass.{chamfer_key[group]}" if group in chamfer_key else ""))
            tv = turn.get(f"{chamfer_key[group]}_deg") if group in chamfer_key else None
            cells.append(H.num_cell(tv, H.fmt(tv, 1) if _isnum(tv) else "—",
                                    key=f"orientation.{chamfer_key[group]}_deg" if group in chamfer_key else ""))
            rows.append("".join(cells))
        if rows:
            note = ("PSNR and SSIM are means over every (view, frame) image of the group (3DGS-lineage SSIM); "
                    "Chamfer is the mean distance between the simulated Gaussian centres and the ground-truth surface "
                    "over the observed / future frames, the centre of mass's the mean distance between the "
                    "simulated body's centre of mass and the truth's (the cells' data-values are in metres), and the "
                    "rotation's the mean angle between the simulated body's rotation from frame 0 and the truth's.")
            if has_fov:
                disp = next(((ev.get(g) or {}).get("fovvdp_display") for g in GROUPS
                             if (ev.get(g) or {}).get("fovvdp_display")), None)
                note += f" FoVVDP in JOD (10 = identical), display model {H.esc(disp or 'unknown')}."
            if ev.get("scene") and self.scene_desc.startswith("no scene"):
                note += f" From the asset's evaluation.json on {H.esc(ev['scene'])}."
            body = H.table(headers, rows, table_id="metrics-table")
        else:
            note, body = "", '<p class="note">No evaluation: no metrics.</p>'
        self.sections.append(("metrics", "Metrics", H.section("metrics", "Metrics", body, note)))

    def _interval_cell(self, key: str, f: Any) -> str:
        """The material table's interval cell of ``key`` (log10 E: also in Pa) from material.json's uncertainty."""
        entry = (self.material.get("uncertainty") or {}).get("log10_E" if key == "E" else key)
        if not isinstance(entry, dict) or not isinstance(entry.get("interval"), list):
            return '<td class="na">—</td>'
        lo, hi = entry["interval"]
        text = f"{H.fmt_sci(10 ** lo)} … {H.fmt_sci(10 ** hi)}" if key == "E" else f"{f(lo)} … {f(hi)}"
        text += _video_says(entry)
        if entry.get("at_coarse_edge"):
            text += f" · at the coarse search's {entry['at_coarse_edge']} end"
        return H.num_cell(hi - lo, text, key=f"interval.{key}")

    def _optimisation_section(self) -> None:

        if not self.log:
            self.sections.append(("optimisation", "Optimisation", H.section(
                "optimisation", "Optimisation", '<p class="note">The asset has no log.json.</p>')))
            return
        optimisation_figure(self.media / "optimisation.svg", self.log, self.found, self.truth)
        n = sum(1 for e in self.log.get("iterations", []) if isinstance(e, dict) and "loss" in e)
        fit = self.log.get("joint_fit")
        method = fit.get("method") if isinstance(fit, dict) else None
        if method == "gauss_newton":
            steps = "Gauss–Newton entries (the start, then one per step)"
            training = ("The fit's loss at each step (grey: the whole observed clip in every observed view, at the "
                        "fit's resolution; a rejected step keeps the last accepted state's)")
        else:
            steps = "joint iterations" + (" (the log does not name the method)" if method is None else "")
            training = "The training loss of each iteration (grey: the paper's random window of frames and views)"
        track = fit.get("track") if isinstance(fit, dict) else None
        track_note = ""
        if isinstance(track, dict) and track.get("displacement_error"):
            errors = [float(x) for x in track["displacement_error"]]
            rms = (sum(x * x for x in errors) / len(errors)) ** 0.5
            track_note = (" The fit also followed the hull track, the visual hulls' centroids over the observed "
                          f"frames (σ = {1000 * float(track['sd']):.1f} mm): the kept motion's centre of mass moves "
                          f"from frame 0 within {1000 * rms:.1f} mm RMS of it (at most {1000 * max(errors):.1f} mm).")
        self.sections.append(("optimisation", "Optimisation", H.section(
            "optimisation", "Joint optimisation of the material and the motion",
            '<div class="figure"><img src="media/optimisation.svg" alt="optimisation curves" '
            'data-probe="plot:optimisation"></div>',
            f"{n} {steps}. {training} "
            "and the validation rollout over all observed frames at full resolution (blue; the asset keeps the best, "
            "★); log10 E, ν and ζ per iteration against the value found (blue dotted) and the truth (red dashed); "
            "the coarse grid search of E that picks the start; the wall time of each iteration." + track_note)))

    def _timings_section(self, total: float) -> None:
        rows = []
        stages = {f"reconstruct: {k}": v for k, v in (self.log.get("timings_seconds") or {}).items() if _isnum(v)}
        ev_t = ((self.evaluation or {}).get("timing") or {}).get("seconds")
        if _isnum(ev_t):
            stages["evaluate (evaluation.json)"] = ev_t
        stages.update({f"report: {k}": v for k, v in self.timings.items()})
        stages["report: total (this page)"] = total
        top = max(stages.values()) if stages else 1.0
        for name, secs in stages.items():
            rows.append(f"<td>{H.esc(name)}</td>" + H.num_cell(secs, H.fmt(secs, 1)) +
                        f'<td style="width:45%"><div class="bar" '
                        f'style="width:{100 * secs / max(top, 1e-9):.1f}%"></div></td>')
        recon_total = sum(v for k, v in stages.items() if k.startswith("reconstruct:"))
        foot = ([f"<td>reconstruct: total</td>{H.num_cell(recon_total, H.fmt(recon_total, 1))}<td></td>"]
                if recon_total else [])
        self.sections.append(("timings", "Timings", H.section(
            "timings", "Stage timings", H.table(["stage", "seconds", ""], rows, table_id="timings-table", foot=foot),
            "Wall-clock seconds of the reconstruction's stages (log.json), of the evaluation, and of writing this "
            "report.")))

    def simulation_media(self, folder: Path) -> None:
        """A "New situations" entry for one ``vid2sim simulate`` output folder (its GIFs copied into media/)."""
        summary = _read_json(folder / "summary.json", required=True)
        gifs = sorted((folder / "videos").glob("*.gif"))
        if not gifs:
            raise ReportInputError(f"{folder / 'videos'}: no .gif (was the simulation written with --no-video?)")
        k = sum(1 for a, _, _ in self.sections if a == "simulations")
        images = []
        for gif in gifs:
            name = f"simulation{k}_{gif.name}"
            shutil.copyfile(gif, self.media / name)
            images.append(f'<figure><img src="media/{H.esc(name)}" alt="{H.esc(gif.stem)}">'
                          f"<figcaption>{H.esc(gif.stem)}</figcaption></figure>")
        sc = summary.get("scenario", {})
        mat = summary.get("material", {})
        plastic = mat.get("plasticity") or {}
        lines = [f"material: {mat.get('preset', '?')} ({mat.get('model', '?')}), E = {H.fmt_sci(mat.get('E'))} Pa, "
                 f"ν = {H.fmt(mat.get('nu'), 3)}" + (f", plasticity {plastic}" if plastic else "")]
        floor = sc.get("floor", {})
        if floor.get("enabled", True):
            moving = [f"{k} {floor[k]:g}" for k in ("velocity", "amplitude", "frequency", "tilt_deg", "tilt_rate_deg")
                      if _isnum(floor.get(k)) and floor[k] != 0]
            lines.append(f"floor at {H.fmt(floor.get('height'), 3)} m" + (f" ({', '.join(moving)})" if moving else ""))
        else:
            lines.append("no floor")
        for o in sc.get("obstacles", []):
            lines.append(f"sphere obstacle at {[round(c, 3) for c in o.get('center', [])]} m, radius "
                         f"{H.fmt(o.get('radius'), 3)} m")
        init = sc.get("initial", {})
        if init.get("euler_deg") or init.get("axis_angle") or any(init.get("translation") or []):
            lines.append(f"new pose: rotation {init.get('euler_deg') or init.get('axis_angle')}, translation "
                         f"{init.get('translation')} m")
        lines.append(f"{summary.get('frames', '?')} frames of {H.fmt(summary.get('dt'), 3)} s, "
                     f"{sc.get('cameras', {}).get('type', '?')} cameras; simulated in "
                     f"{H.fmt((summary.get('timings_seconds') or {}).get('simulate'), 1)} s")
        body = ("<ul>" + "".join(f"<li>{H.esc(line)}</li>" for line in lines) + "</ul>"
                + f'<div class="gifs">{"".join(images)}</div>'
                + f'<p class="note">From <code>{H.esc(folder)}</code> (scenario.yaml, frames, mp4, per-frame PLY)'
                "</p>")
        self.data.setdefault("simulations", []).append({"folder": str(folder), "summary": summary})
        self.sections.append(("simulations", "New situations", H.section(
            "simulations" if k == 0 else f"simulations{k}", "New situations" if k == 0 else f"New situation {k + 1}",
            body, "The reconstructed asset simulated where it was never seen (vid2sim simulate).")))

    def finish(self, elapsed: float) -> None:

        self._optimisation_section()
        self._timings_section(elapsed)
        self.data["timings_seconds"] = {**self.timings, "total": elapsed}
        files = sorted(p.relative_to(self.root).as_posix() for p in self.media.iterdir())
        self.data["files"] = ["index.html", "report.json"] + files
        items = "".join(f'<li><a href="{H.esc(f)}">{H.esc(f)}</a> ({_size(self.root / f)})</li>' for f in files)
        scene = self.data.get("scene")
        command = f"vid2sim report {self.asset_dir} OUT" + (f" --scene {scene}" if scene else "")
        self.sections.append(("files", "Files", H.section(
            "files", "Files",
            f'<ul>{items}<li><a href="report.json">report.json</a>: the numbers of this page</li></ul>'
            f"<p class=\"note\">Reproduce: <code>{H.esc(command)}</code></p>")))
        date = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
        self.data.update({"date": date, "vid2sim_version": __version__})
        order = ["summary", "material", "metrics", "videos", "keyframes", "psnr", "simulations", "optimisation",
                 "timings", "files"]
        secs = sorted(self.sections, key=lambda s: order.index(s[0]))
        subtitle = (f"asset <b>{H.esc(self.asset_dir.name)}</b> <span title=\"{H.esc(self.asset_dir)}\">"
                    f"({H.esc(self.asset_dir)})</span>")
        if scene:
            subtitle += f" · scene <b>{H.esc(Path(scene).name)}</b> ({H.esc(scene)})"
        extra = self.asset_json.get("extra") or {}
        if isinstance(extra.get("gaussians"), int):
            subtitle += f" · {extra['gaussians']:,} Gaussians".replace(",", " ")
        subtitle += f"<br>{H.esc(self.scene_desc)}<br>written {H.esc(date)} · vid2sim {H.esc(__version__)}"
        title = f"vid2sim report · {self.asset_dir.name}"
        page = H.page(title, subtitle, [(a, n) for a, n, _ in secs], "\n".join(s for _, _, s in secs),
                      f"vid2sim {H.esc(__version__)} · self-contained report: open index.html; no network needed.")
        (self.root / "index.html").write_text(page, encoding="utf-8")
        (self.root / "report.json").write_text(json.dumps(self.data, indent=1, default=str), encoding="utf-8")


# ---------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------

@dataclass
class _ViewPanels:
    """A report's three panels per view, uint8 (V, T, H, W, 3): the scene's frames, the renders and their error
    heat maps, with each view's crop box (y0, y1, x0, x1) in pixels."""

    gt8: np.ndarray
    rd8: np.ndarray
    err8: np.ndarray
    boxes: list[tuple[int, int, int, int]]

    def __call__(self, v: int, frames: Any, target: int) -> list[np.ndarray]:
        """View ``v``'s ``frames`` (a slice or indices) of the three panels, cropped and scaled towards side
        ``target``."""
        y0, y1, x0, x1 = self.boxes[v]
        f = M.scale_factor(max(y1 - y0, x1 - x0), target)
        return [M.rescale(x[v][frames, y0:y1, x0:x1], f) for x in (self.gt8, self.rd8, self.err8)]


def _view_panels(scene: Any, targets: Tensor, renders: Tensor, cfg: ReportConfig) -> _ViewPanels:
    """The panels of the scene's frames ``targets`` and the ``renders`` (V, T, H, W, 3) float in [0, 1]; each view
    cropped to the box around everything its masks and renders show when ``cfg.crop``."""
    V, _, Hh, Ww, _ = targets.shape
    gt8, rd8 = M.to_uint8(targets), M.to_uint8(renders)
    err8 = np.stack([M.error_heatmap(renders[v], targets[v], cfg.error_max, cfg.error_cmap) for v in range(V)])
    masks = scene.float_masks() if hasattr(scene, "float_masks") else scene.masks.float()
    boxes = [M.crop_box(masks[v], renders[v]) if cfg.crop else (0, Hh, 0, Ww) for v in range(V)]
    return _ViewPanels(gt8, rd8, err8, boxes)


def _mean(values: Sequence[float]) -> float | None:
    values = [v for v in values if _isnum(v)]
    return sum(values) / len(values) if values else None


def _ranges(indices: Sequence[int] | None) -> str:
    """[1, 2, 3, 5] → "1–3, 5"."""
    if not indices:
        return "—"
    parts, start, prev = [], indices[0], indices[0]
    for i in list(indices[1:]) + [None]:
        if i is not None and i == prev + 1:
            prev = i
            continue
        parts.append(f"{start}" if start == prev else f"{start}–{prev}")
        if i is not None:
            start = prev = i
    return ", ".join(parts)


def _keyframes(T: int, first_future: int | None, k: int) -> list[int]:
    """``k`` frames spread over 0 … T−1 that include the last observed and the first future frame."""
    k = min(k, T)
    picks = {round(i * (T - 1) / max(1, k - 1)) for i in range(k)}
    if first_future is not None and first_future > 0:
        picks |= {first_future - 1, first_future}
    picks = sorted(picks)
    while len(picks) > k:  # drop the evenly spread frame nearest another pick, never the boundary pair
        keep = {0, T - 1, (first_future or 0) - 1, first_future}
        gaps = [(picks[i + 1] - picks[i - 1], picks[i]) for i in range(1, len(picks) - 1) if picks[i] not in keep]
        if not gaps:
            break
        picks.remove(min(gaps)[1])
    return picks


def _controls(T: int, config: ReportConfig, webm: bool) -> str:
    if not webm:
        return ("Animated images (WebP) play on their own; "
                f"{config.video_fps:g} frames per second.")
    speeds = "".join(f'<option value="{s}"{" selected" if s == 1 else ""}>{s:g}×</option>' for s in (0.25, 0.5, 1, 2))
    return (f'<button id="play-toggle" type="button">Pause</button>'
            f'<label>speed <select id="speed">{speeds}</select></label>'
            f'<label>frame <input id="frame-slider" type="range" min="0" max="{T - 1}" value="0" step="1"></label>'
            f'<span id="frame-label">frame 0</span>'
            f'<span class="note" style="margin:0">played at {config.video_fps:g} frames/s; the slider pauses all '
            "videos on one frame</span>")


def _size(path: Path) -> str:
    n = path.stat().st_size
    return f"{n / 1e6:.2f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"
