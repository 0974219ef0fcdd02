"""The benchmark sections in quick mode, as a user runs them (`vid2sim bench speed --quick`, `bench jacobian
--quick`): every figure is there and makes sense, so a broken benchmark fails the suite instead of waiting for
the next person who runs it."""

from __future__ import annotations

import json
import math

from vid2sim.cli import main


def _finite_positive(result: dict, keys: list[str]) -> None:
    for k in keys:
        assert isinstance(result[k], (int, float)) and math.isfinite(result[k]) and result[k] > 0, (k, result[k])


def test_bench_speed_physics_training_and_render_quick(capsys):
    assert main(["bench", "speed", "--only", "physics", "training", "render", "--quick", "--json", "--threads",
                 "1"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["device"] == "cpu" and result["threads"] == 1
    _finite_positive(result, ["sim_step_ms", "sim_frame_ms", "sim_window_ms", "render_ms",
                              "skinning_train_ms_per_iter", "skinning_train_it_per_s", "skinning_iter_ops",
                              "jacobian_train_ms_per_iter", "render_forward_ms_448", "render_forward_tensor_ratio",
                              "render_tensor_ratio"])
    assert abs(result["skinning_train_it_per_s"] * result["skinning_train_ms_per_iter"] - 1e3) < 1e-6
    assert result["sim_frame_substeps"] >= 4
    # the drop rests on the floor: penetration is a small fraction of the 1 m object
    assert 0 <= result["sim_floor_penetration_m"] < 0.05
    # BDF2 with substeps is converged in time to a few percent of the size (docs/architecture.md)
    assert 0 <= result["sim_step_time_convergence_percent"] < 20


def test_bench_speed_predictor_quick(capsys):
    assert main(["bench", "speed", "--only", "predictor", "--quick", "--json", "--threads", "1"]) == 0
    result = json.loads(capsys.readouterr().out)
    _finite_positive(result, ["predictor_checkpoint_mb", "predictor_load_s", "predictor_inference_s",
                              "transformers_import_s"])  # transformers is a test dependency
    assert result["predictor_checkpoint_mb"] < 20  # issue #52's size ceiling


def test_bench_jacobian_quick(capsys):
    assert main(["bench", "jacobian", "--iterations", "5", "--quick", "--quiet", "--threads", "1"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["quick"] is True and result["jacobian_train_iterations"] == 5
    _finite_positive(result, ["jacobian_mse", "jacobian_relative_frobenius", "jacobian_max_abs",
                              "jacobian_train_ms_per_iter"])
    # five iterations teach the network little: its error is of the order of J itself, and the rollout still
    # converges (every frame's Newton iterations counted)
    assert result["jacobian_relative_frobenius"] <= 1.5
    assert len(result["jacobian_rollout_newton_iterations"]) == 3
    assert math.isfinite(result["jacobian_rollout_max_deviation"])
