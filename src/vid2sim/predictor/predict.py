"""Running a trained Stage I predictor on a scene (what ``vid2sim reconstruct`` does before Stage II).

**The video it sees** (:func:`front_video`):

- The view: among the scene's observed cameras, the one whose direction from the object is closest in angle to
  the front camera's (:func:`vid2sim.predictor.front_view.closest_view`; the front camera is camera 0 of the
  synthetic ring, azimuth 0°, elevation 20°, the camera the training videos were rendered from).
- The frames: ``num_frames`` (16) at the training data's frame spacing (``data_config["dt"]``, 0.05 s), taken
  from the scene's observed frames by nearest time. A scene shorter than 16 × 0.05 s repeats its last observed
  frame (the count is reported as ``padded_frames``); a scene with another frame rate is resampled in time so
  the motion has the speed the predictor was trained on.
- The framing (``PredictorConfig.framing``): ``"object"`` (the default of new checkpoints) crops every frame to
  one square around the object's whole motion — the union over the 16 frames of the pixels that are not
  background white, widened by ``OBJECT_MARGIN`` on each side and padded with white where it leaves the
  image (:func:`object_crop`). Training videos are cropped the same way, so the object fills the model's
  small input whatever the camera's distance and field of view; its deformation is then seen at the model's
  full resolution. ``"full"`` (checkpoints made before framing existed) keeps the whole frame; the camera's
  field of view and distance are then not corrected.
- Each frame (composited on white) is resized to the model's input side with area averaging and
  ImageNet-normalised, as the training videos.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor
from torch.nn import functional as Fn

from vid2sim.predictor.dataset import IMAGENET_MEAN, IMAGENET_STD
from vid2sim.predictor.front_view import FrontCamera, closest_view
from vid2sim.runtime.errors import InputError

#: the checkpoint shipped with vid2sim (package data; may be absent in a source checkout without it)
DEFAULT_PREDICTOR = Path(__file__).with_name("predictor_small.pt")
#: frame spacing of training data made before it was recorded in the checkpoint
DEFAULT_DT = 0.05
#: the object crop's margin on each side, as a share of the motion's bounding square
OBJECT_MARGIN = 0.1
#: a pixel is background when all its channels are at least this (frames are composited on white)
BACKGROUND_LEVEL = 0.94
FRAMINGS = ("object", "full")


def resample_frames(images: Tensor, scene_dt: float, target_dt: float, num_frames: int) -> tuple[Tensor, int]:
    """Frames at times k·target_dt, k < num_frames, from ``images`` (T, H, W, 3) at spacing ``scene_dt``, by
    nearest time; times past the last frame take the last one.

    Returns:
        ((num_frames, H, W, 3), how many frames were past the end).
    """
    if images.ndim != 4 or images.shape[0] < 1:
        raise InputError(f"images must be (T, H, W, 3) with T >= 1, got {tuple(images.shape)}")
    if not (scene_dt > 0 and target_dt > 0):
        raise InputError(f"frame spacings must be positive, got {scene_dt} and {target_dt}")
    T = images.shape[0]
    pos = [k * target_dt / scene_dt for k in range(num_frames)]
    idx = [min(T - 1, int(round(p))) for p in pos]
    padded = sum(1 for p in pos if round(p) > T - 1)
    return images[idx], padded


def to_model_input(frames: Tensor, size: int) -> Tensor:
    """(T, H, W, 3) RGB in [0, 1] → (T, 3, size, size) ImageNet-normalised, resized by area averaging."""
    x = frames.float().permute(0, 3, 1, 2)
    if x.shape[-1] != size or x.shape[-2] != size:
        x = Fn.interpolate(x, size=(size, size), mode="area") if x.shape[-1] >= size else Fn.interpolate(
            x, size=(size, size), mode="bilinear", align_corners=False)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x.clamp(0, 1) - mean) / std


def object_box(frames: Tensor, margin: float = OBJECT_MARGIN) -> tuple[int, int, int]:
    """The square that :func:`object_crop` cuts from ``frames`` (T, H, W, 3) in [0, 1]: (top, left, side) in
    pixels, possibly reaching past the image (the part outside is white).

    Raises:
        ValueError: no pixel of any frame differs from the white background (there is no object to frame).
    """
    fg = (frames < BACKGROUND_LEVEL).any(-1).any(0)  # (H, W)
    rows = torch.nonzero(fg.any(1)).flatten()
    cols = torch.nonzero(fg.any(0)).flatten()
    if rows.numel() == 0:
        raise InputError("the front view shows no object: every pixel of every frame is background white "
                         f"(all channels >= {BACKGROUND_LEVEL})")
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    side = max(r1 - r0, c1 - c0)
    side = max(1, int(round(side * (1.0 + 2.0 * margin))))
    top = (r0 + r1 - side) // 2
    left = (c0 + c1 - side) // 2
    return top, left, side


def object_crop(frames: Tensor, margin: float = OBJECT_MARGIN) -> Tensor:
    """``frames`` (T, H, W, 3) in [0, 1] cut to one square around the object's whole motion (:func:`object_box`),
    white where the square leaves the image. Returns (T, side, side, 3)."""
    top, left, side = object_box(frames, margin)
    T, H, W, C = frames.shape
    out = torch.ones(T, side, side, C, dtype=frames.dtype, device=frames.device)
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + side, H), min(left + side, W)
    out[:, r0 - top:r1 - top, c0 - left:c1 - left] = frames[:, r0:r1, c0:c1]
    return out


def frame_for_model(frames: Tensor, size: int, framing: str = "object") -> Tensor:
    """(T, H, W, 3) RGB in [0, 1] → (T, 3, size, size) ImageNet-normalised, after the ``framing`` ("object":
    :func:`object_crop`; "full": the whole frame)."""
    if framing not in FRAMINGS:
        raise InputError(f"framing must be one of {FRAMINGS}, got {framing!r}")
    if framing == "object":
        frames = object_crop(frames)
    return to_model_input(frames, size)


def front_video(images: Tensor, cameras: Sequence, dt: float, size: int, num_frames: int = 16,
                target_dt: float = DEFAULT_DT, target: Sequence[float] | None = None,
                front: FrontCamera | None = None, framing: str = "object") -> tuple[Tensor, int, int]:
    """The predictor's input from a scene's observed video (module docstring).

    Args:
        images: (V, T, H, W, 3) observed frames in [0, 1], composited on white.
        cameras: the V observed cameras.
        dt: the scene's seconds between frames; target_dt: the training data's.
        size, num_frames: the model's input side and frame count.
        target: the object's centre at frame 0 (angles are measured from it; default the front camera's target).
        framing: "object" or "full" (the model's ``config.framing``).
    Returns:
        (video (num_frames, 3, size, size), the chosen index into ``cameras``, padded frames).
    """
    v = closest_view(cameras, front, target)
    frames, padded = resample_frames(images[v], dt, target_dt, num_frames)
    return frame_for_model(frames, size, framing), v, padded


def predict_video(model, video: Tensor) -> dict[str, object]:
    """One video (T, 3, R, R) through ``model`` (a :class:`~vid2sim.predictor.model.PhysicsPredictor`):
    {"log10_E", "E" (Pa), "nu", "last_layer" (650,) float32 tensor, "seconds"}."""
    t0 = time.perf_counter()
    model.eval()
    y = model.predict(video)
    log_e = float(y["log10_E"])
    return {"log10_E": log_e, "E": 10.0 ** log_e, "nu": float(y["nu"]), "last_layer": y["last_layer"].float(),
            "seconds": time.perf_counter() - t0}


def centred_grid(grid: Sequence[float], centre: float) -> tuple[float, ...]:
    """``grid`` (sorted log10 E values) shifted so its midpoint (min + max)/2 is ``centre``; spacing and count kept
    (the joint stage's coarse search then brackets the prediction)."""
    g = sorted(float(v) for v in grid)
    if not g:
        return ()
    shift = centre - 0.5 * (g[0] + g[-1])
    return tuple(round(v + shift, 6) for v in g)
