"""Every tensor a function makes follows its inputs' device (docs/development.md, "Devices"), checked on the CPU.

On a CPU-only machine ``torch.eye(3)`` and a matrix moved to ``--device cuda`` are on the same device, so a
function that forgets ``device=`` passes every CPU test and crashes on its first GPU run (the camera check's
``torch.allclose(R @ R.T, torch.eye(3))`` did, in every GPU path). :class:`vid2sim.runtime.device_check.DeviceCheck`
simulates an accelerator on the CPU and records each call that would mix devices on a GPU. The first tests pin
down what it flags and what it lets through; the end-to-end tests run the commands (fit-gaussians, reconstruct at
toy size with its report, evaluate, simulate, report, export) with ``--device cpu:0``, the stand-in accelerator,
from a scene on the CPU, and require no finding.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from vid2sim.runtime.device_check import ACCELERATOR, DeviceCheck, DeviceMixError

# ---- the check itself --------------------------------------------------------------------------------------------


def _rigid_check_before_the_fix(matrix: torch.Tensor) -> bool:
    """The camera check as it was when every GPU path crashed on first use: a CPU identity against the matrix."""
    m = matrix.to(torch.float64)
    rot = m[:3, :3]
    return torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-4)


def test_flags_a_cpu_constant_beside_an_accelerator_tensor():
    matrix = torch.eye(4)
    with DeviceCheck() as check:
        assert _rigid_check_before_the_fix(matrix.to(check.device))  # the values are computed as usual
    assert len(check.findings) == 1
    finding = check.findings[0]
    assert finding.op == "allclose"
    assert "test_devices.py" in finding.where and "test_devices.py" in (finding.made_at or "")
    with pytest.raises(DeviceMixError, match="allclose"):
        check.assert_clean()


def test_the_fixed_camera_check_is_clean():
    from vid2sim.splats.cameras import camera_ring

    camera = camera_ring(1, radius=2.0, elevation_deg=20.0, width=32, height=32)[0]
    with DeviceCheck() as check:
        moved = camera.to(check.device)
        assert moved.world_to_camera.device == ACCELERATOR  # .device reads as the stand-in accelerator
    check.assert_clean()


def test_following_an_input_device_is_clean_and_labels_propagate():
    with DeviceCheck() as check:
        x = torch.rand(5, 3, device=check.device)
        y = torch.zeros(3, device=x.device) + x.mean(0)  # device=x.device follows x
        z = torch.ones_like(x) * x  # *_like follows its source
        w = torch.cat([x, z, y[None]])
        n = x.new_tensor([1.0, 2.0, 3.0]) - x.sum()  # a host scalar beside accelerator tensors: allowed
        idx = torch.tensor([0, 2])  # host index tensors are allowed (CUDA moves them)
        _ = w[idx]
        w[1:3] = torch.zeros(3)  # a basic-index assignment is a copy
        host = w.cpu().numpy()
    check.assert_clean()
    assert check.label(w) == "accelerator" and check.label(n) == "accelerator"
    assert isinstance(host, np.ndarray) and host.shape == (11, 3)


@pytest.mark.parametrize("case", ["numpy", "cat_scalar", "setitem_advanced", "grad", "from_numpy"])
def test_flags_each_kind_of_mix(case):
    with DeviceCheck() as check:
        x = torch.rand(4, 3, device=check.device, requires_grad=(case == "grad"))
        if case == "numpy":
            x.detach().numpy()
        elif case == "cat_scalar":  # concatenations take no CPU scalar beside CUDA tensors
            torch.stack([x[0, 0], torch.tensor(1.0)])
        elif case == "setitem_advanced":
            y = x.detach().clone()
            y[torch.tensor([0, 1])] = torch.ones(2, 3)
        elif case == "grad":
            x.grad = torch.zeros(4, 3)
        elif case == "from_numpy":
            x * torch.from_numpy(np.ones(3, dtype=np.float32))
    assert len(check.findings) == 1, check.report()


def test_raise_on_finding_stops_at_the_first_mix_and_a_run_without_the_device_fails():
    with pytest.raises(DeviceMixError, match="add"):
        with DeviceCheck(raise_on_finding=True) as check:
            torch.ones(2, device=check.device) + torch.ones(2)
    with DeviceCheck() as check:  # the device was never passed: nothing was checked, which must not pass silently
        torch.ones(2) + torch.ones(2)
    with pytest.raises(DeviceMixError, match="passed as the device"):
        check.assert_clean()


# ---- the commands, end to end ------------------------------------------------------------------------------------

#: the demo's tiny sizes (the tiny_asset fixture's) cut further: the check adds Python work to every torch call
_RECONSTRUCT = ["--gaussians.iterations", "10", "--appearance.iterations", "2", "--motion_appearance.iterations", "2",
                "--networks.skinning_iterations", "4", "--iterations", "1"]


@pytest.fixture(scope="module")
def checked_commands(tiny_scene, tmp_path_factory):
    """Run every command once on the stand-in accelerator from the CPU scene, one :class:`DeviceCheck` per
    command (the report's ring of cameras, and the exporters, through their functions: the ``report`` command
    has no flag for a smaller ring, ``export`` loads assets on the CPU); returns {command: check} and the folder
    of the outputs."""
    from vid2sim.apps.demo import TINY
    from vid2sim.apps.report import asset_report
    from vid2sim.asset.folder import load_asset
    from vid2sim.cli import main
    from vid2sim.export.gltf import export_gltf
    from vid2sim.export.rig import export_rig
    from vid2sim.reconstruct.config import ReconstructConfig
    from vid2sim.report import ReportConfig
    from vid2sim.runtime import config as configs

    root = tmp_path_factory.mktemp("devices")
    dev, scene, asset = str(ACCELERATOR), str(tiny_scene), str(root / "asset")
    preset = root / "tiny.json"
    preset.write_text(json.dumps(configs.to_dict(configs.merge(ReconstructConfig(), TINY))))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    checks: dict[str, DeviceCheck] = {}

    def run(name: str, argv: list[str]) -> None:
        with DeviceCheck() as check:
            assert main([*argv, "--device", dev, "--quiet"]) == 0, argv
        checks[name] = check

    try:
        run("fit-gaussians", ["fit-gaussians", scene, str(root / "fit"), "--iterations", "5"])
        run("reconstruct", ["reconstruct", scene, asset, "--config", str(preset), *_RECONSTRUCT, "--no-report"])
        # evaluate, and the report against the scene from its renders
        run("evaluate", ["evaluate", asset, scene, "--out", str(root / "evaluation.json")])
        run("simulate", ["simulate", asset, str(root / "sim"), "--frames", "2", "--resolution", "16",
                         "--obstacle", "0.5,0.5,0,0.1", "--cameras", "ring", "--views", "1", "--no-video"])
        with DeviceCheck() as check:  # without a scene: the asset's drop simulated and rendered in a ring
            asset_report(root / "ring_report", asset, progress=False, device=check.device,
                         config=ReportConfig(ring_frames=4, ring_views=2, ring_resolution=32, video_format="webp"))
        checks["report"] = check
        with DeviceCheck() as check:  # the exporters given an asset that lives on the accelerator
            loaded = load_asset(asset, check.device)
            export_gltf(loaded.gaussians, root / "asset.glb")
            export_rig(loaded, root / "rig")
        checks["export"] = check
    finally:
        torch.set_num_threads(threads)
    return checks, root


@pytest.mark.slow
@pytest.mark.parametrize("command", ["fit-gaussians", "reconstruct", "evaluate", "simulate", "report", "export"])
def test_commands_keep_tensors_on_the_device(checked_commands, command):
    checks, root = checked_commands
    checks[command].assert_clean(min_accelerator_calls=100)
    outputs = {"fit-gaussians": "fit/gaussians.ply", "reconstruct": "asset/material.json",
               "evaluate": "asset/report/index.html", "simulate": "sim/ply", "report": "ring_report/index.html",
               "export": "rig"}
    assert Path(root, outputs[command]).exists()
