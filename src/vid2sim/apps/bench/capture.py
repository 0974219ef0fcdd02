"""``vid2sim bench capture``: how much a real capture costs against a clean scene.

For every scene of a ``make-benchmark`` suite: its capture twin (:func:`vid2sim.synthetic.capture.make_capture_twin`),
imported (:func:`vid2sim.scene.capture.import_capture`), then — optionally — reconstructed and evaluated, next to
the clean scene's own run. The import is judged against the twin's ground truth (:func:`import_figures`): mask IoU
against the true coverage, metres-per-unit error, gravity-direction error, floor-height error and the import's
seconds.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from vid2sim.apps.bench.suite import EVALUATION_JSON, SceneTask, SuiteConfig, read_index, run_scene
from vid2sim.evaluate.scores import evaluate, write_evaluation
from vid2sim.reconstruct.pipeline import reconstruct
from vid2sim.runtime.files import write_json_atomic
from vid2sim.scene.capture import CaptureImportConfig, import_capture
from vid2sim.scene.capture.colmap import colmap_cameras, read_colmap
from vid2sim.scene.capture.layout import discover_capture
from vid2sim.scene.capture.metric import MetricConfig
from vid2sim.scene.capture.sfm import REPORT_JSON as SFM_REPORT_JSON
from vid2sim.scene.capture.sfm import SfmConfig, calibrate_capture
from vid2sim.scene.capture.undistort import reduce, to_opencv_K
from vid2sim.scene.folder import Scene
from vid2sim.scene.reading import load_scene
from vid2sim.scene.writing import write_scene
from vid2sim.splats.cameras import Camera
from vid2sim.synthetic.capture import CaptureTwinConfig, make_capture_twin, read_truth


def _undistorted_alpha(alpha: np.ndarray, truth_cam: dict, K_new: np.ndarray, downscale: int = 1) -> np.ndarray:
    """True coverage (T, H, W) of a distorted camera, (T, k·H, k·W) as filmed, resampled onto the imported pinhole
    camera ``K_new`` (its images reduced ``downscale`` = k times) the way the importer resamples the frames."""

    T, H, W = alpha.shape
    K_full = np.diag([downscale, downscale, 1.0]) @ K_new
    mx, my = cv2.initUndistortRectifyMap(to_opencv_K(np.array(truth_cam["K"])), np.array(truth_cam["distortion"]),
                                         None, to_opencv_K(K_full), (W, H), cv2.CV_32FC1)
    full = np.stack([cv2.remap(a, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                     for a in alpha.astype(np.float32)])
    return reduce(full, downscale, False)


def soft_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Σ min(a, b) / Σ max(a, b) of two coverage maps (the IoU for binary masks); 1 for two empty maps."""
    den = float(np.maximum(a, b).sum())
    return float(np.minimum(a, b).sum()) / den if den > 0 else 1.0


def similarity_to_model(capture: str | Path) -> dict[str, Any]:
    """The similarity from the twin's world (metres) to the frame of the COLMAP model in ``capture/colmap/``, fitted
    on the cameras' centres (Umeyama): the truth of a calibration the twin did not write (``calibrate-capture``).

    Returns:
        ``{"scale", "rotation", "translation"}`` as in ``truth.json``'s ``world_to_calibration``, and the fit's
        residuals: ``centre_error_m`` (largest, in metres) and ``rotation_error_deg`` (largest camera rotation
        error after the similarity).
    """
    capture = Path(capture)
    truth, _ = read_truth(capture)
    layout = discover_capture(capture)
    if layout.colmap is None:
        raise FileNotFoundError(f"{capture} has no COLMAP model (colmap/)")
    cams = colmap_cameras(read_colmap(layout.colmap), layout.camera_of_name)
    sim = truth["world_to_calibration"]
    s0, R0, t0 = sim["scale"], np.array(sim["rotation"]), np.array(sim["translation"])
    names = sorted(cams)
    world_w2c = {}
    for n in names:  # the true cameras, back from the twin's calibration frame to the world
        w2c = np.array(truth["true_cameras_calibration"][n]["world_to_camera"])
        R = w2c[:3, :3] @ R0
        world_w2c[n] = (R, (w2c[:3, 3] + w2c[:3, :3] @ t0) / s0)
    a = np.array([-Rw.T @ tw for Rw, tw in (world_w2c[n] for n in names)])
    b = np.array([cams[n].center for n in names])
    am, bm = a - a.mean(0), b - b.mean(0)
    U, S, Vt = np.linalg.svd(bm.T @ am)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float((S * np.diag(D)).sum() / (am ** 2).sum())
    t = b.mean(0) - scale * R @ a.mean(0)
    centre_error = float(np.linalg.norm(scale * am @ R.T - bm, axis=1).max() / scale)
    rotation_error = max(math.degrees(math.acos(float(np.clip(
        (np.trace(cams[n].rotation @ R @ world_w2c[n][0].T) - 1) / 2, -1, 1)))) for n in names)
    return {"scale": scale, "rotation": R.tolist(), "translation": t.tolist(), "centre_error_m": centre_error,
            "rotation_error_deg": rotation_error}


def import_figures(capture: str | Path, scene_dir: str | Path, calibration_truth: dict[str, Any] | None = None
                   ) -> dict[str, Any]:
    """The imported scene ``scene_dir`` of the capture twin ``capture`` judged against the twin's truth.

    ``calibration_truth`` (:func:`similarity_to_model`) stands for the twin's own ``world_to_calibration`` when the
    import used a calibration the twin did not write.

    Returns:
        ``mask_iou`` (mean over views and scene frames of the soft IoU against the true coverage, undistorted the
        same way) and its worst view/frame, ``scale_error`` (relative error of metres per unit), ``gravity_error_deg``
        (angle between measured and true gravity directions), ``floor_error_m`` (height of the true floor below the
        object in the imported scene, whose floor is z = 0), ``seconds`` (the import's stages).
    """

    capture, scene_dir = Path(capture), Path(scene_dir)
    truth, alpha = read_truth(capture)
    if calibration_truth is not None:
        truth = _in_frame(truth, calibration_truth)
    report = json.loads((scene_dir / "capture_report.json").read_text())
    scene = load_scene(scene_dir)
    A, B = report["scene_frames"]
    keep = list(range(A, B, report.get("every", 1)))
    ious = []
    for v, name in enumerate(report["cameras"]):
        und = report["undistortion"][name]
        true = _undistorted_alpha(alpha[v, keep], truth["true_cameras_calibration"][name], np.array(und["K"]),
                                  und.get("downscale", 1))
        est = scene.masks[v].numpy()
        ious.append([soft_iou(est[t], true[t]) for t in range(len(keep))])
    ious = np.array(ious)
    metric = report["metric"]
    scale = metric["metres_per_unit"]["value"]
    scale_error = scale * truth["units_per_metre"] - 1.0
    down = np.array(metric["gravity_direction_calibration"]["value"])
    true_down = np.array(truth["gravity_direction_calibration"])
    angle = math.degrees(math.acos(float(np.clip(down @ true_down / np.linalg.norm(down), -1, 1))))
    # the true floor, under the object's mean position, mapped into the imported scene
    M = np.array(metric["calibration_to_scene"])
    sim = truth["world_to_calibration"]
    s, R, t = sim["scale"], np.array(sim["rotation"]), np.array(sim["translation"])
    track = np.array([c for c in (report["track_units"][t] for t in keep)
                      if c is not None and all(math.isfinite(x) for x in c)])
    centre_cal = track.mean(0)
    centre_world = (R.T @ (centre_cal - t)) / s
    foot_world = np.array([centre_world[0], centre_world[1], truth["floor_height_world"]])
    foot_cal = s * R @ foot_world + t
    foot_scene = M[:3, :3] @ foot_cal + M[:3, 3]
    return {
        "mask_iou": float(ious.mean()),
        "mask_iou_worst": float(ious.min()),
        "mask_iou_per_view": ious.mean(1).round(4).tolist(),
        "scale_error": float(scale_error),
        "scale_sigma": metric["metres_per_unit"]["sigma"] / scale,
        "gravity_error_deg": angle,
        "gravity_sigma_deg": metric["gravity_direction_calibration"]["sigma_deg"],
        "gravity_source": metric["gravity_direction_calibration"]["source"],
        "floor_error_m": float(foot_scene[2]),
        "floor_source": metric["floor_calibration"]["source"],
        "free_flight_frames": (metric["free_flight"] or {}).get("frames", 0),
        "lead_in_frames": truth["lead_in_frames"],
        "seconds": report.get("seconds", {}),
        "warnings": report.get("warnings", []),
    }


def _in_frame(truth: dict[str, Any], sim: dict[str, Any]) -> dict[str, Any]:
    """The truth's frame-dependent fields (scale, gravity direction, similarity) in the frame of ``sim``."""
    g = np.asarray(truth["gravity_world"], dtype=np.float64)
    return {**truth, "world_to_calibration": {k: sim[k] for k in ("scale", "rotation", "translation")},
            "units_per_metre": sim["scale"],
            "gravity_direction_calibration": (np.array(sim["rotation"]) @ (g / np.linalg.norm(g))).tolist()}


# ---- the clean scene in the imported scene's frame ---------------------------------------------------------------


def clean_in_import_frame(clean_dir: str | Path, capture: str | Path, imported: str | Path, out: str | Path,
                          calibration_truth: dict[str, Any] | None = None) -> Path:
    """The clean scene re-expressed in the gauge of its imported twin, so that an asset reconstructed from the
    import can be scored on the clean scene's own cameras and images.

    The imported scene's frame is the clean world up to the import's errors and choices (scale, gravity direction,
    the rotation about the vertical and the origin, which no capture can know): the clean cameras and the
    ground-truth tets are mapped by the twin's true world → calibration similarity followed by the import's
    calibration → scene similarity. Colours are those of the import's reference camera (the twin's sensor of that
    camera is applied to the clean object colours; the white background stays white). Scale or gravity errors of the
    import therefore show in the scores, as they should. ``calibration_truth``: as in :func:`import_figures`.
    """

    truth, _ = read_truth(capture)
    if calibration_truth is not None:
        truth = _in_frame(truth, calibration_truth)
    report = json.loads((Path(imported) / "capture_report.json").read_text())
    imported_scene_json = json.loads((Path(imported) / "scene.json").read_text())
    clean = load_scene(clean_dir)
    sim = truth["world_to_calibration"]
    s, R, t = sim["scale"], np.array(sim["rotation"]), np.array(sim["translation"])
    M = np.array(report["metric"]["calibration_to_scene"])
    # x_scene = A x_world + c
    A = M[:3, :3] @ (s * R)
    c = M[:3, :3] @ t + M[:3, 3]
    a = float(np.cbrt(np.linalg.det(A)))
    Q = A / a
    cams = []

    for cam in clean.cameras:
        w2c = cam.world_to_camera.double().numpy()
        Rc = w2c[:3, :3] @ Q.T
        tc = a * w2c[:3, 3] - Rc @ c
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = Rc, tc
        cams.append(Camera(torch.as_tensor(m, dtype=torch.float32), cam.K.clone(), cam.width, cam.height))
    ref = report["colour"]["reference"]
    sensor = truth["sensors"][ref]
    gain = torch.tensor(sensor["gain"], dtype=torch.float32)
    masks = clean.float_masks()
    images = clean.float_images()
    m = masks[..., None]
    straight = torch.where(m > 1e-3, (images - (1 - m)) / m.clamp_min(1e-3), torch.ones_like(images))
    coloured = (straight * gain + sensor["black"]).clamp(0, 1)
    images = coloured * m + (1 - m)
    extras = {}
    for name, group in clean.extras.items():
        extras[name] = dict(group)
        if name == "tet_trajectory":
            v = group["vertices"].double().numpy()
            extras[name]["vertices"] = torch.as_tensor(a * v @ Q.T + c, dtype=group["vertices"].dtype)
    config = dataclasses.replace(clean.config, gravity=tuple(imported_scene_json["gravity"]),
                                 floor_height=imported_scene_json["floor_height"],
                                 metadata={**clean.config.metadata, "capture_gauge": {
                                     "scale": a, "rotation": Q.tolist(), "translation": c.tolist(),
                                     "colour_reference": ref, "gain": sensor["gain"], "black": sensor["black"]}})
    scene = Scene(cams, images, masks, clean.times, config, extras=extras)
    return write_scene(scene, out, overwrite=True)


# ---- the bench -------------------------------------------------------------------------------------------------


@dataclass
class CaptureBenchConfig:
    """Settings of :func:`run_capture_bench` (saved as ``OUT/capture_bench_config.json``).

    Attributes:
        twin: the capture twins' settings (its ``seed`` is offset by the scene's index).
        reconstruct: reconstruct and evaluate the imported scenes (False: the import's figures only).
        preset, iterations, threads: the reconstruction (as :class:`vid2sim.apps.bench.suite.SuiteConfig`).
        clean_results: a ``bench suite`` output folder whose ``NAME/evaluation.json`` are reused as the clean runs
            (None: the clean scenes are reconstructed here too, when ``reconstruct``).
        gravity: |g| the importer assumes; None takes the twin's true value (the synthetic world's).
        sfm: calibrate each twin by structure from motion (``calibrate-capture``: COLMAP on its plates and its
            ``twin.photos`` walkaround photos) instead of importing the calibration the twin writes (kept aside in
            ``ground_truth/twin_calibration/``, which the importer never reads). The import is then judged in
            COLMAP's frame (:func:`similarity_to_model`), and the SfM's own camera errors are reported.
    """

    twin: Any = None
    reconstruct: bool = True
    preset: str = "small"
    iterations: int | None = None
    threads: int | None = None
    clean_results: str | None = None
    gravity: float | None = None
    sfm: bool = False

    def __post_init__(self) -> None:
        if self.sfm and (self.twin is None or self.twin.photos < 1):
            raise ValueError("CaptureBenchConfig.sfm needs twins with walkaround photos (twin.photos >= 1): COLMAP "
                             "cannot link cameras far apart from their plates alone")

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["twin"] = None if self.twin is None else dataclasses.asdict(self.twin)
        return out


BENCH_JSON = "capture_bench.json"
BENCH_CONFIG_JSON = "capture_bench_config.json"
IMPORT_JSON = "import.json"

#: the figures compared between the capture run and the clean run (evaluation.json paths)
COMPARED: dict[str, tuple[str, ...]] = {
    "dynamic_psnr": ("dynamic", "psnr"),
    "future_psnr": ("future", "psnr"),
    "novel_psnr": ("novel_views", "psnr"),
    "abs_error_log10_E": ("material", "abs_error_log10_E"),
    "abs_error_nu": ("material", "abs_error_nu"),
}


def _get(d: dict | None, path: tuple[str, ...]) -> float | None:
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return float(d) if isinstance(d, (int, float)) and math.isfinite(d) else None


def capture_scene(name: str, scene_dir: Path, out: Path, index: int, config: CaptureBenchConfig,
                  progress: bool = False) -> dict[str, Any]:
    """One scene of the bench (resumable stage by stage): twin, import (+ its figures), then optionally the
    reconstruction of the import scored on the clean scene, and the clean run."""
    import time


    out.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {"name": name, "scene": str(scene_dir)}
    twin_cfg = dataclasses.replace(config.twin or CaptureTwinConfig(), seed=(config.twin.seed if config.twin else 0)
                                   + index)
    capture = out / "capture"
    if not (capture / "ground_truth" / "truth.json").is_file():
        make_capture_twin(scene_dir, capture, twin_cfg, overwrite=True, progress=progress)
    truth, _ = read_truth(capture)
    calibration_truth = _calibrated(capture, config) if config.sfm else None
    imported = out / "imported"
    import_json = out / IMPORT_JSON
    if not import_json.is_file():
        clean_cfg = json.loads((scene_dir / "scene.json").read_text())
        held = clean_cfg.get("held_out_views") or []
        gravity = config.gravity if config.gravity is not None else float(np.linalg.norm(truth["gravity_world"]))
        icfg = CaptureImportConfig(
            frames=tuple(truth["scene_frames"]),
            held_out_views=held or None,
            every=int(truth.get("frame_step", 1)),
            downscale=int(truth.get("resolution_scale", 1)),
            observed_frames=clean_cfg.get("observed_frames"),
            threads=config.threads,
            metric=MetricConfig(gravity=gravity),
        )
        t0 = time.perf_counter()
        import_capture(capture, imported, icfg, overwrite=True, progress=progress)
        seconds = time.perf_counter() - t0
        figures = import_figures(capture, imported, calibration_truth)
        figures["import_seconds"] = seconds
        if calibration_truth is not None:
            sfm = json.loads((capture / "colmap" / SFM_REPORT_JSON).read_text())
            figures.update(sfm_centre_error_mm=1000 * calibration_truth["centre_error_m"],
                           sfm_rotation_error_deg=calibration_truth["rotation_error_deg"],
                           sfm_reprojection_px=sfm["mean_reprojection_error_px"], sfm_seconds=sfm["seconds"])
        write_json_atomic(import_json, figures)
    record["import"] = json.loads(import_json.read_text())
    if not config.reconstruct:
        return record

    suite_cfg = SuiteConfig(preset=config.preset, iterations=config.iterations, threads=config.threads)
    evaluation = out / EVALUATION_JSON
    if not evaluation.is_file():
        asset = out / "asset"
        if not (asset / "asset.json").is_file():
            reconstruct(imported, asset, suite_cfg.reconstruct_config(), progress=progress)
        gauge = clean_in_import_frame(scene_dir, capture, imported, out / "clean_in_import_frame",
                                      calibration_truth)
        report = evaluate(asset, gauge, progress=progress)
        write_evaluation(report, evaluation)
    record["capture_run"] = json.loads(evaluation.read_text())
    clean_eval: dict | None = None
    if config.clean_results is not None and (Path(config.clean_results) / name / EVALUATION_JSON).is_file():
        clean_eval = json.loads((Path(config.clean_results) / name / EVALUATION_JSON).read_text())
        record["clean_source"] = str(Path(config.clean_results) / name)
    else:
        clean_out = out / "clean"
        if not (clean_out / EVALUATION_JSON).is_file():
            rec = run_scene(SceneTask(name, str(scene_dir), str(clean_out), suite_cfg), progress=progress)
            if rec["status"] != "ok":
                raise RuntimeError(f"the clean run of {name} failed: {rec['error']}")
        clean_eval = json.loads((clean_out / EVALUATION_JSON).read_text())
        record["clean_source"] = str(clean_out)
    record["clean_run"] = clean_eval
    record["compared"] = {}
    for key, path in COMPARED.items():
        cap, cl = _get(record["capture_run"], path), _get(clean_eval, path)
        record["compared"][key] = {"capture": cap, "clean": cl,
                                   "difference": None if cap is None or cl is None else cap - cl}
    return record


def _calibrated(capture: Path, config: CaptureBenchConfig) -> dict[str, Any]:
    """Calibrate the twin ``capture`` by structure from motion once (its own calibration moved aside first), and
    return the truth of COLMAP's frame (:func:`similarity_to_model`)."""
    if not (capture / "colmap" / SFM_REPORT_JSON).is_file():
        aside = capture / "ground_truth" / "twin_calibration"
        aside.mkdir(exist_ok=True)
        for name in ("colmap", "transforms.json"):
            if (capture / name).exists():
                (capture / name).replace(aside / name)
        calibrate_capture(capture, SfmConfig(threads=config.threads), progress=False)
    return similarity_to_model(capture)


def run_capture_bench(suite_dir: str | Path, out_dir: str | Path, config: CaptureBenchConfig | None = None,
                      progress: bool = True) -> dict[str, Any]:
    """:func:`capture_scene` for every scene of a ``make-benchmark`` suite; ``OUT/capture_bench.json`` holds every
    scene's record and the means. A scene that fails is recorded with its error and the bench goes on; a rerun
    resumes each scene after its last finished stage."""
    import traceback


    config = CaptureBenchConfig() if config is None else config
    suite_dir, out = Path(suite_dir), Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / BENCH_CONFIG_JSON, config.to_dict())
    records = []
    for i, name in enumerate(read_index(suite_dir)):
        if progress:
            print(f"[bench capture] {name}", flush=True)
        try:
            rec = capture_scene(name, suite_dir / name, out / name, i, config, progress=progress)
            rec["status"] = "ok"
            (out / name / "error.txt").unlink(missing_ok=True)
        except Exception as exc:  # one scene's failure is recorded; the others go on
            rec = {"name": name, "status": "failed", "error": f"{type(exc).__name__}: {exc}"}
            (out / name).mkdir(parents=True, exist_ok=True)
            (out / name / "error.txt").write_text(traceback.format_exc())
        records.append(rec)
    result = {"suite": str(suite_dir), "config": config.to_dict(), "scenes": records, "means": _means(records)}
    write_json_atomic(out / BENCH_JSON, result)
    return result


IMPORT_FIGURES = ("mask_iou", "mask_iou_worst", "scale_error", "gravity_error_deg", "floor_error_m", "import_seconds",
                  "sfm_centre_error_mm", "sfm_rotation_error_deg", "sfm_seconds")


def _means(records: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in records if r.get("status") == "ok"]
    means: dict[str, Any] = {"scenes": len(ok)}
    for key in IMPORT_FIGURES:
        vals = [r["import"].get(key) for r in ok if r.get("import") and r["import"].get(key) is not None]
        if key in ("scale_error", "floor_error_m"):
            vals = [abs(v) for v in vals]
            key = f"abs_{key}"
        if vals:
            means[key] = float(np.mean(vals))
            # the worst scene: the lowest IoU, the largest error or time
            means[f"worst_{key}"] = float(np.min(vals)) if key.startswith("mask_iou") else float(np.max(vals))
    for key in COMPARED:
        diffs = [r["compared"][key]["difference"] for r in ok if "compared" in r
                 and r["compared"][key]["difference"] is not None]
        if diffs:
            means[f"{key}_difference"] = float(np.mean(diffs))
            means[f"{key}_capture"] = float(np.mean([r["compared"][key]["capture"] for r in ok if "compared" in r
                                                     and r["compared"][key]["capture"] is not None]))
            means[f"{key}_clean"] = float(np.mean([r["compared"][key]["clean"] for r in ok if "compared" in r
                                                   and r["compared"][key]["clean"] is not None]))
    return means


def format_capture_table(result: dict[str, Any]) -> str:
    """One row per scene: the import's figures and, when reconstructed, capture − clean differences."""
    rows = [f"{'scene':<12} {'IoU':>6} {'scale%':>7} {'grav°':>6} {'floor mm':>8} {'s':>5} "
            f"{'ΔPSNR dyn':>9} {'ΔPSNR fut':>9} {'ΔPSNR nov':>9} {'Δ|dlogE|':>8} {'Δ|dnu|':>7}"]
    for r in result["scenes"]:
        if r.get("status") != "ok":
            rows.append(f"{r['name']:<12} failed: {r.get('error', '')[:80]}")
            continue
        f = r["import"]
        c = r.get("compared", {})
        d = lambda k: "" if k not in c or c[k]["difference"] is None else f"{c[k]['difference']:+.2f}"  # noqa: E731
        rows.append(
            f"{r['name']:<12} {f['mask_iou']:6.3f} {100 * f['scale_error']:+7.2f} "
            f"{f['gravity_error_deg']:6.2f} {1000 * f['floor_error_m']:+8.1f} {f.get('import_seconds', 0):5.1f} "
            f"{d('dynamic_psnr'):>9} {d('future_psnr'):>9} {d('novel_psnr'):>9} {d('abs_error_log10_E'):>8} "
            f"{d('abs_error_nu'):>7}"
        )
    m = result["means"]
    rows.append(f"means over {m.get('scenes', 0)} scenes: " + ", ".join(f"{k} {v:.5g}" for k, v in m.items()
                                                                       if k != "scenes"))
    return "\n".join(rows)
