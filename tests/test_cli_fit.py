"""``vid2sim fit-gaussians``: fit one frame of a scene folder, write a viewer-ready PLY with its config."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vid2sim.cli import main
from vid2sim.scene.folder import Scene, SceneConfig
from vid2sim.scene.reading import load_scene
from vid2sim.scene.writing import write_scene
from vid2sim.splats.cameras import camera_ring
from vid2sim.splats.losses import psnr
from vid2sim.splats.ply import load_ply
from vid2sim.splats.preview import LABEL_HEIGHT
from vid2sim.splats.render import render, render_gaussians

pytestmark = pytest.mark.slow  # fits Gaussians / generates synthetic scenes


@pytest.fixture(scope="module")
def blob_scene_folder(tmp_path_factory) -> Path:
    """Two frames of 40 coloured Gaussians (the second shifted), 4 views at 40², written as a scene folder."""
    g = torch.Generator().manual_seed(0)
    n = 40
    d = torch.randn(n, 3, generator=g)
    means = d / d.norm(dim=1, keepdim=True) * 0.3 * torch.rand(n, 1, generator=g) ** (1 / 3)
    scales, quats = 0.06 + 0.08 * torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g)
    ops, cols = 0.7 + 0.29 * torch.rand(n, generator=g), torch.rand(n, 3, generator=g)
    cams = camera_ring(4, 2.0, 20.0, 40, 40, fov_x_deg=40.0)
    frames = []
    with torch.no_grad():
        for shift in (0.0, 0.1):
            out = render(means + torch.tensor([0.0, 0.0, shift]), ops, cols, cams, quats=quats, scales=scales)
            frames.append((out.rgb, out.alpha[..., 0]))
    images = torch.stack([f[0] for f in frames], dim=1)  # (V, T, H, W, 3)
    masks = torch.stack([f[1] for f in frames], dim=1)
    scene = Scene(cameras=cams, images=images, masks=masks, config=SceneConfig())
    return write_scene(scene, tmp_path_factory.mktemp("scenes") / "blobs")


def test_fit_gaussians_writes_ply_config_and_report(blob_scene_folder: Path, tmp_path: Path, capsys):
    out = tmp_path / "fit"
    argv = ["fit-gaussians", str(blob_scene_folder), str(out), "--frame", "1", "--iterations", "60",
            "--sh-degree", "1", "--quiet"]
    assert main(argv) == 0
    assert "dB on the 4 training views of frame 1" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["comparison.png", "fit_config.json", "fit_report.json",
                                                     "gaussians.ply"]
    g = load_ply(out / "gaussians.ply")
    config = json.loads((out / "fit_config.json").read_text())
    report = json.loads((out / "fit_report.json").read_text())
    assert config["iterations"] == 60 and config["sh_degree"] == 1 and config["lambda_dssim"] == 0.2
    assert report["frame"] == 1 and report["gaussians"] == g.num and g.sh_degree == 1
    assert len(report["psnr_db_per_view"]) == 4
    assert report["psnr_db"] > 24.0
    scene = load_scene(blob_scene_folder)  # it fitted frame 1 (the object shifted up by 0.1), not frame 0
    with torch.no_grad():
        rgb = render_gaussians(g, scene.cameras).rgb
    assert psnr(rgb, scene.images[:, 1]) == pytest.approx(report["psnr_db"], abs=1e-3)
    assert psnr(rgb, scene.images[:, 1]) > psnr(rgb, scene.images[:, 0]) + 5.0
    picture = np.array(Image.open(out / "comparison.png"))  # column headings, then per view: label strip,
    picture = picture[LABEL_HEIGHT:]                         # target | render | error
    row = LABEL_HEIGHT + 40
    assert picture.shape == (4 * row, 3 * 40, 3)
    target_panel = torch.from_numpy(picture[row + LABEL_HEIGHT : 2 * row, :40]).float() / 255
    render_panel = torch.from_numpy(picture[row + LABEL_HEIGHT : 2 * row, 40:80]).float() / 255
    assert torch.allclose(target_panel, scene.images[1, 1], atol=1 / 255)
    assert torch.allclose(render_panel, rgb[1], atol=1 / 255)
    assert picture[:LABEL_HEIGHT].max() > 200 and picture[:LABEL_HEIGHT].min() == 0  # white text on black

    assert main(argv) == 2  # the folder exists now
    assert "--overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite", "--iterations", "5"]) == 0
    assert json.loads((out / "fit_config.json").read_text())["iterations"] == 5
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--frame", "2"], "--frame 2 is outside the scene's frames 0..1"),
        (["--iterations", "0"], "iterations must be >= 1"),
        (["--test-views", "0,1,2,3"], "holds out all 4 views"),
        (["--test-views", "1,7"], "--test-views [7] outside the scene's views 0..3"),
        (["--test-views", "one"], "comma-separated view indices"),
    ],
)
def test_fit_gaussians_bad_arguments_are_one_line(blob_scene_folder, tmp_path, capsys, extra, message):
    assert main(["fit-gaussians", str(blob_scene_folder), str(tmp_path / "o"), "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_fit_gaussians_names_a_missing_scene(tmp_path, capsys):
    assert main(["fit-gaussians", str(tmp_path / "nope"), str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "Traceback" not in err


def test_fit_gaussians_refuses_to_replace_a_foreign_folder(blob_scene_folder, tmp_path, capsys):
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    assert main(["fit-gaussians", str(blob_scene_folder), str(foreign), "--overwrite", "--quiet"]) == 2
    assert "without gaussians.ply" in capsys.readouterr().err
    assert (foreign / "notes.txt").read_text() == "keep me"


def test_fit_gaussians_scores_held_out_views_separately(blob_scene_folder: Path, tmp_path: Path, capsys):
    out = tmp_path / "fit"
    assert main(["fit-gaussians", str(blob_scene_folder), str(out), "--iterations", "40", "--sh-degree", "0",
                 "--test-views", "2", "--quiet"]) == 0
    assert "dB on the 3 training views of frame 0" in capsys.readouterr().out
    report = json.loads((out / "fit_report.json").read_text())
    assert report["train_views"] == [0, 1, 3] and report["test_views"] == [2]
    assert len(report["psnr_db_per_view"]) == 3 and len(report["psnr_db_test_per_view"]) == 1
    g = load_ply(out / "gaussians.ply")
    scene = load_scene(blob_scene_folder)
    with torch.no_grad():
        rgb = render_gaussians(g, scene.cameras).rgb
    assert psnr(rgb[2:3], scene.images[2:3, 0]) == pytest.approx(report["psnr_db_test"], abs=1e-3)
    assert psnr(rgb[[0, 1, 3]], scene.images[[0, 1, 3], 0]) == pytest.approx(report["psnr_db"], abs=1e-3)
    # the held-out view was not fitted: it scores below every training view
    assert report["psnr_db_test"] < min(report["psnr_db_per_view"])
