"""Speed of the Stage I predictor (``vid2sim bench speed --only predictor``; issue #52's load and inference figures).

The shipped checkpoint (:data:`~vid2sim.predictor.predict.DEFAULT_PREDICTOR`) on the benchmark's device. Figures:

- ``predictor_checkpoint_mb`` — its size on disk (MiB);
- ``predictor_load_s`` — median over :data:`LOAD_REPEATS` fresh Python processes of the wall time from after
  ``import torch`` to a loaded model: importing :mod:`vid2sim.predictor.train` and :func:`load_predictor` (a
  fresh process, since a second load in one process finds every module imported);
- ``predictor_inference_s`` — median of :data:`INFERENCE_REPEATS` predictions of one 16-frame video at the model's
  input size (``predict_video``: the ensemble's members on the video and its mirror image), after one warm-up;
- ``transformers_import_s`` — the same-run baseline of what loading used to cost: median over fresh processes of
  importing transformers' VideoMAE model after ``import torch`` (None when transformers is not installed), which
  the predictor no longer needs (:mod:`vid2sim.predictor.videomae`).

Each child process runs with the parent's thread count (``OMP_NUM_THREADS``).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from typing import Any

import torch

from vid2sim.apps.bench.timing import time_ms
from vid2sim.predictor.predict import DEFAULT_PREDICTOR, predict_video
from vid2sim.predictor.train import load_predictor

LOAD_REPEATS = 5
"""Fresh processes per load figure (the median is reported)."""

INFERENCE_REPEATS = 7
"""Timed predictions (the median is reported)."""

_LOAD = """
import json, sys, time
import torch
t0 = time.perf_counter()
from vid2sim.predictor.predict import DEFAULT_PREDICTOR
from vid2sim.predictor.train import load_predictor
model = load_predictor(DEFAULT_PREDICTOR).to(sys.argv[1])
if sys.argv[1].startswith("cuda"):
    torch.cuda.synchronize()
print(json.dumps({"seconds": time.perf_counter() - t0}))
"""

_TRANSFORMERS = """
import json, time
import torch
t0 = time.perf_counter()
from transformers import VideoMAEModel  # noqa: F401
print(json.dumps({"seconds": time.perf_counter() - t0}))
"""


def _fresh_process_seconds(code: str, *args: str, repeats: int) -> float:
    """Median of the "seconds" a child Python process prints for ``code`` over ``repeats`` runs."""
    env = {**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())}
    samples = []
    for _ in range(repeats):
        done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                              timeout=600)
        if done.returncode != 0:
            raise RuntimeError(f"bench speed (predictor): the timing process failed:\n{done.stderr[-2000:]}")
        samples.append(float(json.loads(done.stdout.strip().splitlines()[-1])["seconds"]))
    samples.sort()
    return samples[len(samples) // 2]


def run(device: torch.device, quick: bool = False) -> dict[str, Any]:
    """The figures of the module docstring on ``device`` (``quick``: one fresh process and 3 predictions)."""
    load_repeats = 1 if quick else LOAD_REPEATS
    model = load_predictor(DEFAULT_PREDICTOR).to(device)
    video = torch.rand(model.num_frames, 3, model.image_size, model.image_size, device=device)
    seconds = time_ms(lambda: predict_video(model, video), device, 3 if quick else INFERENCE_REPEATS) / 1e3
    has_transformers = importlib.util.find_spec("transformers") is not None
    return {
        "predictor_checkpoint_mb": DEFAULT_PREDICTOR.stat().st_size / 2**20,
        "predictor_load_s": _fresh_process_seconds(_LOAD, str(device), repeats=load_repeats),
        "predictor_inference_s": seconds,
        "transformers_import_s": _fresh_process_seconds(_TRANSFORMERS, repeats=load_repeats)
        if has_transformers else None,
    }
