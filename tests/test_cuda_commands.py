"""Every command once on a CUDA GPU, at small sizes (``pytest -m cuda``; skipped without one, tests/conftest.py).

fit-gaussians, reconstruct (the tiny sizes, and the full preset cut short), evaluate, simulate, report, export,
bench speed and the tiny demo, each with ``--device cuda`` from the CPU-made tiny scene. Where the CPU can do the
same work in seconds the results are compared with it: evaluate's scores, the simulation's points, the exported
files. tests/test_devices.py checks the same paths on the CPU with a stand-in accelerator; this file is what runs
them on the real one (scripts/gpu_check.sh runs it, docs/benchmarks.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from vid2sim.cli import main

pytestmark = [pytest.mark.cuda, pytest.mark.slow]


def _config_file(path: Path, preset: str, overrides: dict) -> str:
    """A ``--config`` file: the preset with ``overrides`` on top."""
    from vid2sim.reconstruct.config import ReconstructConfig

    path.write_text(json.dumps(ReconstructConfig.preset(preset, overrides).to_dict()))
    return str(path)


@pytest.fixture(scope="module")
def cuda_asset(tiny_scene, tmp_path_factory):
    """The tiny scene reconstructed on the GPU at the demo's tiny sizes (and its report against the scene)."""
    from vid2sim.apps.demo import TINY

    root = tmp_path_factory.mktemp("cuda")
    config = _config_file(root / "tiny.json", "small", TINY)
    out = root / "asset"
    assert main(["reconstruct", str(tiny_scene), str(out), "--config", config, "--device", "cuda", "--quiet"]) == 0
    return out


def test_fit_gaussians_on_cuda(tiny_scene, tmp_path):
    out = tmp_path / "fit"
    assert main(["fit-gaussians", str(tiny_scene), str(out), "--iterations", "100", "--test-views", "0",
                 "--device", "cuda", "--quiet"]) == 0
    report = json.loads((out / "fit_report.json").read_text())
    assert report["device"].startswith("cuda")
    assert report["psnr_db"] > 18.0 and report["psnr_db_test"] is not None
    assert (out / "gaussians.ply").is_file() and (out / "comparison.png").is_file()


def test_reconstruct_small_on_cuda(cuda_asset):
    material = json.loads((cuda_asset / "material.json").read_text())
    assert np.isfinite(material["E"]) and 3.0 < material["log10_E"] < 7.0 and -1.0 < material["nu"] < 0.5
    assert (cuda_asset / "report" / "index.html").is_file()


def test_reconstruct_short_full_on_cuda(tiny_scene, tmp_path):
    """The full preset (gsplat, SH degree 3) cut to a few iterations, with the paper's windows (trained networks
    in the joint optimisation; the default Gauss-Newton fit runs in the other CUDA tests); the stiffness
    calibration, CPU work, is left to scripts/gpu_check.sh's full run."""
    config = _config_file(tmp_path / "full.json", "full", {
        "gaussians": {"iterations": 60}, "points": {"resolution": 24, "num_points": 1000},
        "networks": {"skinning_iterations": 50}, "calibration": {"enabled": False},
        "joint": {"method": "windows", "iterations": 3, "coarse_log10_E": [4.5, 5.0], "validate_every": 1,
                  "window": 2}})
    out = tmp_path / "asset"
    assert main(["reconstruct", str(tiny_scene), str(out), "--config", config, "--device", "cuda", "--no-report",
                 "--quiet"]) == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["joint"]["views_per_iteration"] == 4 and saved["gaussians"]["views_per_step"] == 2
    assert np.isfinite(json.loads((out / "material.json").read_text())["E"])


def test_evaluate_on_cuda_matches_cpu(cuda_asset, tiny_scene, tmp_path):
    from vid2sim.evaluate.scores import evaluate

    out = tmp_path / "evaluation.json"
    assert main(["evaluate", str(cuda_asset), str(tiny_scene), "--out", str(out), "--no-report", "--device", "cuda",
                 "--quiet"]) == 0
    gpu = json.loads(out.read_text())
    cpu = evaluate(cuda_asset, tiny_scene, progress=False, device="cpu")
    assert gpu["material"]["fitted"] == cpu["material"]["fitted"]
    for group in ("dynamic", "future", "novel_views"):  # the renderers differ (gsplat, the torch one) in detail only
        assert gpu[group]["psnr"] == pytest.approx(cpu[group]["psnr"], abs=1.0), group


def test_simulate_on_cuda_matches_cpu(cuda_asset, tmp_path):
    from vid2sim.splats.ply import load_ply

    args = ["--frames", "4", "--resolution", "32", "--obstacle", "0.5,0.5,0,0.1", "--cameras", "ring", "--views", "2",
            "--quiet"]
    assert main(["simulate", str(cuda_asset), str(tmp_path / "gpu"), *args, "--device", "cuda"]) == 0
    assert main(["simulate", str(cuda_asset), str(tmp_path / "cpu"), *args, "--no-video", "--device", "cpu"]) == 0
    summary = json.loads((tmp_path / "gpu" / "summary.json").read_text())
    assert summary["scenario"]["frames"] == 4
    assert list((tmp_path / "gpu").rglob("*.mp4")), "no video written"
    gpu, cpu = (load_ply(sorted((tmp_path / d / "ply").glob("*.ply"))[-1]) for d in ("gpu", "cpu"))
    assert torch.allclose(gpu.means.cpu(), cpu.means.cpu(), atol=1e-2)  # 1 cm after 4 frames


def test_report_on_cuda(cuda_asset, tmp_path):
    out = tmp_path / "report"
    assert main(["report", str(cuda_asset), str(out), "--video-format", "webp", "--device", "cuda", "--quiet"]) == 0
    assert (out / "index.html").is_file()


def test_export_of_a_cuda_asset_matches_cpu(cuda_asset, tmp_path):
    from vid2sim.asset.folder import load_asset
    from vid2sim.export.gltf import export_gltf
    from vid2sim.export.rig import export_rig, load_rig

    for device in ("cuda", "cpu"):
        asset = load_asset(cuda_asset, device)
        export_gltf(asset.gaussians, tmp_path / f"{device}.glb")
        export_rig(asset, tmp_path / f"rig_{device}")
    assert (tmp_path / "cuda.glb").read_bytes() == (tmp_path / "cpu.glb").read_bytes()
    (doc_gpu, arrays_gpu), (doc_cpu, arrays_cpu) = load_rig(tmp_path / "rig_cuda"), load_rig(tmp_path / "rig_cpu")
    assert doc_gpu == doc_cpu and arrays_gpu.keys() == arrays_cpu.keys()
    for key in arrays_gpu:
        np.testing.assert_array_equal(arrays_gpu[key], arrays_cpu[key], err_msg=key)
    assert main(["export", str(cuda_asset), str(tmp_path / "cli.glb"), "--quiet"]) == 0


def test_bench_speed_on_cuda(capsys):
    assert main(["bench", "speed", "--quick", "--json", "--device", "cuda"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["device"].startswith("cuda") and result["device_name"]
    timings = {k: v for k, v in result.items() if k.endswith("_ms") or "_ms_" in k}
    assert timings and all(np.isfinite(v) and v > 0 for v in timings.values()), timings


def test_demo_tiny_on_cuda(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", str(out), "--size", "tiny", "--device", "cuda", "--quiet"]) == 0
    summary = json.loads((out / "demo.json").read_text())
    assert np.isfinite(summary["found_E"])
    assert (out / "report" / "index.html").is_file() and (out / "simulation" / "summary.json").is_file()
