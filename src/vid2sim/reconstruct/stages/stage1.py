"""Stage ``stage1``: the feed-forward predictor (paper §4.1) on the observed video.

The predictor (:mod:`vid2sim.predictor.predict`; the shipped ``predictor_small.pt`` unless ``stage1.predictor``
names another checkpoint) sees 16 frames of the observed view closest to the front camera and predicts log10 E, ν
and the skinning field's last layer. They become the prior material, the centre of the joint stage's coarse search
over log10 E (its grid shifted, spacing kept), and the skinning field's starting point (the template's hidden layers
with the predicted last layer) for the data-free skinning training. It is skipped — and the reason is written to
``log.json`` ``stage1`` — when switched off (the default while the shipped predictor misses its accuracy targets,
docs/predictor.md; the paper's "w/o Stage I"), or when the checkpoint is missing or cannot be read:
the prior then is ``prior.E``/``prior.nu`` and the field a seeded initialisation. With ``networks.handles`` other
than the template's (10) it gives the material only (the predicted last layer is for 10 handles), and ``log.json``
says so (``skinning_start`` false).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from vid2sim.predictor.predict import (
    DEFAULT_PREDICTOR,
    centred_grid,
    front_video,
    predict_video,
)
from vid2sim.predictor.template import load_template
from vid2sim.predictor.train import load_predictor
from vid2sim.reconstruct.config import ReconstructConfig
from vid2sim.reconstruct.runner import Context, State
from vid2sim.runtime.files import read_json, save_torch_atomic, write_json_atomic


def say(progress: bool, text: str) -> None:
    """A progress line when ``progress``."""
    if progress:
        tqdm.write(text)


def run_stage1(cfg: ReconstructConfig, images: torch.Tensor, cameras: list, dt: float, centre: list[float],
               progress: bool = False) -> dict[str, Any]:
    """Stage I on the observed video (module docstring).

    Args:
        images: (V, T, H, W, 3) observed frames; cameras: the V observed cameras; dt: seconds between frames;
        centre: the object's centre at frame 0 (the front view is chosen by the angle seen from it).
    Returns:
        the record written to ``log.json`` ``stage1``: {"ran": False, "reason"} or {"ran": True, "E", "log10_E",
        "nu", "seconds", "view" (index into the observed views), "padded_frames", "checkpoint",
        "coarse_log10_E", "skinning_start", "skinning_note"} plus "last_layer" (650,) (a tensor, not written to
        the log). With ``cfg.networks.handles`` other than the template's, the predicted last layer does not fit the
        field: the material is used, "skinning_start" is False, "skinning_note" says why and "last_layer" is
        None.
    """
    if not cfg.stage1.enabled:
        return {"ran": False, "reason": "disabled (stage1.enabled false / --no-stage1: the 'w/o Stage I' ablation)"}
    path = Path(cfg.stage1.predictor) if cfg.stage1.predictor is not None else DEFAULT_PREDICTOR
    if not path.is_file():
        reason = f"no predictor checkpoint at {path}"
        say(progress, f"      Stage I skipped: {reason}")
        return {"ran": False, "reason": reason, "checkpoint": str(path)}

    template = load_template()
    skinning_note = None
    if cfg.networks.handles != template.num_handles:
        skinning_note = (f"networks.handles is {cfg.networks.handles}, the predicted last layer is for the template's "
                         f"{template.num_handles} handles: the skinning field starts from its own initialisation")
    say(progress, "[Stage I] predicting the material and skinning field from the front view")
    t0 = time.perf_counter()
    try:
        model = load_predictor(path)
    except ImportError as exc:  # a checkpoint whose backbone needs a package that is not installed
        reason = f"the predictor cannot be loaded: {exc}"
        say(progress, f"      Stage I skipped: {reason}")
        return {"ran": False, "reason": reason, "checkpoint": str(path)}
    target_dt = float((model.data_config or {}).get("dt", 0.05))
    video, view, padded = front_video(images, cameras, dt, model.image_size, model.num_frames, target_dt, centre,
                                      framing=model.config.framing)
    pred = predict_video(model, video)
    if skinning_note is not None:
        say(progress, f"      Stage I gives the material only: {skinning_note}")
    return {"ran": True, "E": pred["E"], "log10_E": pred["log10_E"], "nu": pred["nu"],
            "seconds": time.perf_counter() - t0, "inference_seconds": pred["seconds"], "view": view,
            "padded_frames": padded, "checkpoint": str(path),
            "coarse_log10_E": list(centred_grid(cfg.joint.coarse_log10_E, pred["log10_E"])),
            "skinning_start": skinning_note is None, "skinning_note": skinning_note,
            "last_layer": pred["last_layer"] if skinning_note is None else None}


class Stage1Stage:
    """Runs Stage I (``config.stage1``); writes ``stage1.json`` and ``stage1_last_layer.pt``."""

    name = "stage1"
    sections = ("stage1", "networks.handles", "joint.coarse_log10_E")
    revision = 0

    def title(self, ctx: Context, state: State) -> str:
        return "Stage I: the material and skinning field predicted from the front view"

    def run(self, ctx: Context, state: State) -> None:
        o = ctx.observed
        record = run_stage1(ctx.config, o.images_cpu, o.cameras_cpu, o.dt, state.obj_cpu.centre.tolist(), ctx.progress)
        if record["ran"]:
            record["scene_view"] = int(o.views[record["view"]])
        save_torch_atomic(record.pop("last_layer", None), ctx.path("stage1_last_layer.pt"))
        write_json_atomic(ctx.path("stage1.json"), record)

    def load(self, ctx: Context, state: State) -> None:
        state.stage1 = read_json(ctx.path("stage1.json"), "the Stage I record")
        state.last_layer = torch.load(ctx.path("stage1_last_layer.pt"), weights_only=True)
        state.log["stage1"] = state.stage1


def prior_material(config: ReconstructConfig, record: dict[str, Any]) -> tuple[float, float]:
    """(E in Pa, ν) the joint optimisation starts from: Stage I's prediction when it ran (``record``, the stage's
    record), else ``config.prior``'s."""
    if record["ran"]:
        return float(record["E"]), float(record["nu"])
    return config.prior.E, config.prior.nu
