"""`vid2sim reconstruct` and `vid2sim evaluate` end to end on a tiny synthetic scene: the asset folder, resuming
an interrupted run, clear errors for bad input, and the evaluation report."""

import json
import shutil

import pytest
import torch

from vid2sim.cli import main
from vid2sim.pipeline import reconstruct as reconstruct_module
from vid2sim.pipeline.asset import load_asset
from vid2sim.pipeline.reconstruct import ReconstructConfig, ReconstructionError, reconstruct
from vid2sim.scene.folder import load_scene, write_scene
from vid2sim.synthetic.scenes import SyntheticSceneConfig, make_scene


def test_reconstruct_writes_a_complete_asset(tiny_asset, tiny_scene):
    names = {p.name for p in tiny_asset.iterdir()}
    assert {"asset.json", "material.json", "gaussians.ply", "skinning.pt", "points.npz", "config.json",
            "log.json"} <= names
    assert not (tiny_asset.parent / f".{tiny_asset.name}.work").exists()  # the stage cache is removed
    asset = load_asset(tiny_asset)
    assert asset.material["E"] == pytest.approx(10 ** asset.material["log10_E"])
    assert asset.material["density"] == 1000.0 and asset.floor_height == pytest.approx(-0.7)
    config = json.loads((tiny_asset / "config.json").read_text())
    assert config["joint"]["iterations"] == 2 and config["handles"] == 3
    log = json.loads((tiny_asset / "log.json").read_text())
    assert [r["log10_E"] for r in log["coarse_search"]] == [4.5, 5.0]
    assert set(log["timings_seconds"]) == {"gaussians", "points", "velocity", "appearance", "networks", "joint"}
    # the simulator runs in the scene's metric frame: the Gaussians sit where the object is at frame 0
    scene = load_scene(tiny_scene)
    truth = scene.extras["tet_trajectory"]["vertices"][0]
    centre = asset.gaussians.means.mean(0)
    assert float((centre - truth.mean(0)).norm()) < 0.05
    sim = asset.simulator()
    states = sim.rollout(asset.initial_state(sim), 3)
    assert all(torch.isfinite(s.z).all() for s in states)


def test_evaluate_reports_views_frames_material_and_chamfer(tiny_asset, tiny_scene, tmp_path):
    asset = shutil.copytree(tiny_asset, tmp_path / "asset")  # the HTML report is written into the asset folder
    out = tmp_path / "eval.json"
    assert main(["evaluate", str(asset), str(tiny_scene), "--out", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    shown = json.loads((asset / "report" / "report.json").read_text())  # the report shows the same evaluation
    assert (asset / "report" / "index.html").is_file()
    assert shown["evaluation"]["dynamic"]["psnr"] == report["dynamic"]["psnr"]
    assert report["dynamic"]["frames"] == [1, 2, 3, 4] and report["future"]["frames"] == [5]
    assert report["novel_views"]["views"] == [2]  # the held-out ring camera
    for key in ("dynamic", "future", "novel_views"):
        assert 5 < report[key]["psnr"] < 60 and 0 < report[key]["ssim"] <= 1
    material = report["material"]
    assert material["truth"] == {"E": 1e5, "nu": 0.3}
    assert material["abs_error_log10_E"] == pytest.approx(abs(material["fitted"]["log10_E"] - 5.0), abs=1e-6)
    assert len(report["chamfer"]["per_frame"]) == 6 and 0 < report["chamfer"]["observed_mean"] < 0.1


def test_an_interrupted_reconstruction_resumes_after_its_last_finished_stage(tiny_scene, tmp_path, monkeypatch, tiny_config):
    out = tmp_path / "asset"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("vid2sim.pipeline.joint.joint_optimisation", interrupted)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(tiny_scene, out, tiny_config(), progress=False)
    work = tmp_path / ".asset.work"
    assert not out.exists()  # nothing that looks like a finished asset
    assert {p.name for p in work.glob("*.done")} == {"gaussians.done", "points.done", "velocity.done", "appearance.done",
                                                      "networks.done"}
    monkeypatch.undo()

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished stage ran again")

    monkeypatch.setattr("vid2sim.splats.fitting.fit_gaussians", must_not_run)
    monkeypatch.setattr("vid2sim.physics.skinning_training.train_skinning", must_not_run)
    reconstruct(tiny_scene, out, tiny_config(), progress=False)
    assert (out / "material.json").is_file() and not work.exists()
    other = tiny_config()
    other.handles = 4
    (tmp_path / ".asset2.work").mkdir()
    (tmp_path / ".asset2.work" / "key.json").write_text(json.dumps({"config": {}, "scene": None}))
    with pytest.raises(ReconstructionError, match="--restart"):
        reconstruct(tiny_scene, tmp_path / "asset2", other, progress=False)


def test_bad_scenes_get_clear_errors_and_leave_nothing(tiny_scene, tmp_path, tiny_config):
    scene = load_scene(tiny_scene)
    scene.masks[1, 0] = 0.0
    scene.images[1, 0] = 1.0
    broken = write_scene(scene, tmp_path / "broken")
    with pytest.raises(ReconstructionError, match="view 1 is empty"):
        reconstruct(broken, tmp_path / "asset", tiny_config(), progress=False)
    assert not (tmp_path / "asset").exists() and not (tmp_path / ".asset.work").exists()
    rc = main(["reconstruct", str(broken), str(tmp_path / "asset"), "--quiet"])
    assert rc == 2
    shutil.rmtree(broken)
    assert main(["reconstruct", str(tmp_path / "missing"), str(tmp_path / "asset"), "--quiet"]) == 2


def test_presets_and_config_errors():
    small, full = ReconstructConfig.preset("small"), ReconstructConfig.preset("full")
    assert small.joint.iterations < full.joint.iterations == 400  # the paper's 400 at full size
    assert full.joint.lr_log10_E == 5e-3 and full.joint.lr_nu == 1e-3 and full.joint.window == 4
    with pytest.raises(ValueError, match="jacobian"):
        ReconstructConfig(jacobian="finite_differences")
    with pytest.raises(ValueError, match="preset"):
        ReconstructConfig.preset("huge")
    assert reconstruct_module.STAGES == ("gaussians", "points", "velocity", "appearance", "networks", "joint")


def test_a_drop_that_meets_the_floor_by_frame_1_still_reconstructs(tiny_scene, tmp_path, monkeypatch, tiny_config):
    from vid2sim.pipeline import initial_state

    real = initial_state.estimate_initial_velocity
    calls = []

    def early_contact(*args, **kwargs):
        calls.append(args[5])  # floor_height
        if args[5] is not None:
            raise initial_state.TooFewBallisticFrames("fewer than 2 usable frames (frame 1 reaches the floor)")
        return real(*args, **kwargs)

    monkeypatch.setattr(initial_state, "estimate_initial_velocity", early_contact)
    out = reconstruct(tiny_scene, tmp_path / "asset", tiny_config(), progress=False)
    assert calls == [pytest.approx(-0.7), None]  # then frames 0 and 1 without the floor test
    extra = json.loads((out / "asset.json").read_text())["extra"]
    assert extra["initial_velocity_estimate"]["contact_before_frame_1"] is True
    assert extra["initial_velocity_estimate"]["frames_used"] == 2
