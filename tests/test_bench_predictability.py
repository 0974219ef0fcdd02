"""``vid2sim bench predictability``: the truth's twin from a raised start, scored like an asset."""

from __future__ import annotations

import json

import pytest

from vid2sim.apps.bench.predictability import (
    PREDICTABILITY_JSON,
    TWIN_DIR,
    predictability,
    twin_config,
)
from vid2sim.cli import main
from vid2sim.metrics.images import MSE_FLOOR


def test_a_twin_without_offset_is_the_truth_itself(tiny_scene, tmp_path):
    """The FEM (the scene's own tet mesh and time schedule) and the renderer are deterministic: with offset 0
    every image and vertex is the truth's, so the scores sit at the metric's floor."""
    report = predictability(tiny_scene, tmp_path / "zero", height_offset=0.0, progress=False, workers=1)
    top = -10.0 * __import__("math").log10(MSE_FLOOR)
    for key in ("dynamic", "future", "novel_views"):
        assert report[key]["psnr"] == pytest.approx(top), key
        assert report[key]["ssim"] == pytest.approx(1.0, abs=1e-9), key
    assert max(report["surface_offset_m"]) == 0.0
    assert report["fem_substeps"]["truth"] == report["fem_substeps"]["twin"]


def test_a_raised_twin_drifts_from_the_truth_and_is_reused(tiny_scene, tmp_path):
    out = tmp_path / "raised"
    report = predictability(tiny_scene, out, height_offset=0.02, progress=False, workers=1)
    offsets = report["surface_offset_m"]
    # frame 0: the whole body 2 cm higher, exactly; later the two bodies fall alike (same g) until one lands
    assert offsets[0] == pytest.approx(0.02, rel=1e-6)
    assert all(o > 0 for o in offsets)
    assert 20.0 < report["dynamic"]["psnr"] < 60.0
    saved = json.loads((out / PREDICTABILITY_JSON).read_text())
    assert saved["height_offset_m"] == 0.02 and saved["dynamic"]["psnr"] == pytest.approx(report["dynamic"]["psnr"])
    # a second run reuses the twin (same settings) and gives the same numbers
    stamp = (out / TWIN_DIR / "synthetic.json").stat().st_mtime_ns
    again = predictability(tiny_scene, out, height_offset=0.02, progress=False, workers=1)
    assert (out / TWIN_DIR / "synthetic.json").stat().st_mtime_ns == stamp
    assert again["future"]["psnr"] == report["future"]["psnr"]
    # another offset in the same folder is refused, naming the setting
    with pytest.raises(ValueError, match="drop_height"):
        predictability(tiny_scene, out, height_offset=0.03, progress=False, workers=1)


def test_bad_input_is_named(tmp_path, tiny_scene, capsys):
    with pytest.raises(ValueError, match="height_offset"):
        twin_config(tiny_scene, -0.001)
    (tmp_path / "plain").mkdir()
    assert main(["bench", "predictability", str(tmp_path / "plain"), str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "synthetic.json" in err and "make-scene" in err
    assert not (tmp_path / "out").exists()
