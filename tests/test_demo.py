"""`vid2sim demo` end to end at toy sizes: every step's output, the printed summary, resuming, bad settings."""

import json

import pytest

from vid2sim.apps import demo as demo_module
from vid2sim.apps.demo import DemoConfig, run_demo
from vid2sim.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    assert main(["demo", str(out), "--size", "tiny", "--threads", "1", "--quiet"]) == 0
    return out


def test_demo_makes_scene_asset_evaluation_simulation_and_report(tiny_demo):
    for path in ("scene/scene.json", "asset/asset.json", "asset/evaluation.json", "simulation/summary.json",
                 "report/index.html", "demo.json", "demo_config.json"):
        assert (tiny_demo / path).is_file(), path
    summary = json.loads((tiny_demo / "demo.json").read_text())
    evaluation = json.loads((tiny_demo / "asset" / "evaluation.json").read_text())
    assert summary["true_E"] == 2e5 and summary["true_nu"] == 0.4
    assert summary["found_E"] == evaluation["material"]["fitted"]["E"]
    assert set(summary["seconds"]) == {"scene", "asset", "evaluation", "simulation", "report"}
    sim = json.loads((tiny_demo / "simulation" / "summary.json").read_text())
    ball = sim["scenario"]["obstacles"][0]
    assert sim["scenario"]["cameras"]["type"] == "orbit" and ball["radius"] > 0
    assert sim["scenario"]["initial"]["translation"] == [0.0, 0.0, 0.3]
    html = (tiny_demo / "report" / "index.html").read_text()
    assert 'id="simulations"' in html and 'id="videos"' in html


def test_demo_prints_true_and_recovered_material_and_the_report(tiny_demo, capsys, monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished step ran again")

    monkeypatch.setattr("vid2sim.apps.demo.reconstruct", must_not_run)  # the names the demo calls
    monkeypatch.setattr("vid2sim.apps.demo.make_scene", must_not_run)
    assert main(["demo", str(tiny_demo), "--size", "tiny", "--quiet"]) == 0  # resumes: only the report again
    out = capsys.readouterr().out
    assert "Young's modulus E: true 2e+05 Pa, recovered" in out and "nu: true 0.400" in out
    assert f"{tiny_demo / 'report' / 'index.html'}" in out


def test_demo_refuses_a_folder_that_is_not_its_own(tmp_path, capsys):
    (tmp_path / "mine.txt").write_text("x")
    assert main(["demo", str(tmp_path), "--size", "tiny", "--quiet"]) == 2
    assert "not a vid2sim demo" in capsys.readouterr().err
    with pytest.raises(FileExistsError, match="other settings"):
        out = tmp_path / "d"
        out.mkdir()
        (out / "demo_config.json").write_text(json.dumps({"size": "tiny", "seed": 5}))
        run_demo(out, DemoConfig(size="tiny"), progress=False)
    with pytest.raises(ValueError, match="DemoConfig.size"):
        DemoConfig(size="huge")
    assert demo_module.STEPS[-1] == "report"
