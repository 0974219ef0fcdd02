"""``vid2sim bench suite`` and the Ray runner: a 2-scene tiny suite reconstructed and evaluated locally and
through a local Ray instance; the table, suite.json's schema and means, resuming, a broken scene, and
``make-benchmark`` (through Ray, resuming, refusing to shrink a suite)."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path

import pytest
from conftest import fewer_fit_iterations

from vid2sim.apps.bench.suite import (
    EVALUATION_JSON,
    METRICS,
    SUITE_CONFIG_JSON,
    SUITE_JSON,
    SuiteConfig,
    format_table,
    run_suite,
    suite_so_far,
)
from vid2sim.cli import main
from vid2sim.synthetic.scenes import (
    SyntheticSceneConfig,
    benchmark_parameters,
    make_benchmark,
)

pytestmark = pytest.mark.slow  # end to end: scene generation, reconstruction, suites

TINY = {"resolution": 40, "frames": 6, "observed_frames": 5, "views": 4, "held_out_views": 1, "substeps": 4,
        "element_order": 1}
TINY_FLAGS = ["--preset", "small", "--seed", "0", "--resolution", "40", "--frames", "6", "--observed-frames", "5",
              "--views", "4", "--held-out-views", "1", "--substeps", "4", "--element-order", "1", "--quiet"]
SCENE_KEYS = {"name", "scene", "asset", "status", "error", "evaluation", "report", "seconds"}
TIMINGS: dict[str, float] = {}  # wall times, printed at the end of the module (pytest -s)
_RUNS: dict[str, dict] = {}


@pytest.fixture
def tiny_config(tiny_config):
    """The shared tiny ReconstructConfig factory (tests/conftest.py) with the stages a suite's bookkeeping does not
    judge fitted at fewer iterations: the three reconstructions below take a third less time."""

    return lambda: fewer_fit_iterations(tiny_config())


@pytest.fixture(scope="module")
def ray_local(ray_slot):
    """A local Ray instance (2 CPUs) for the whole module, started through the runner's own "local" mode,
    or None without Ray. Every Ray call below reuses it; it holds the run's Ray slot (tests/conftest.py)."""
    from vid2sim.runtime.ray_runner import ray_session

    if importlib.util.find_spec("ray") is None:
        yield None
        return
    t0 = time.perf_counter()
    with ray_slot(), ray_session("local", num_cpus=2) as ray:  # a failure to start Ray fails the tests that need it
        TIMINGS["ray_start_s"] = time.perf_counter() - t0
        yield ray
    for key, value in TIMINGS.items():
        print(f"[test_bench_suite] {key}: {value:.1f}")


@pytest.fixture(scope="module")
def suite_dir(tmp_path_factory, ray_local):
    """A finished 2-scene tiny make-benchmark suite (made through Ray when it is installed: the scenes are
    made side by side, and the make-benchmark Ray path is tested on them)."""
    root = tmp_path_factory.mktemp("bench") / "suite"
    t0 = time.perf_counter()
    make_benchmark(2, root, preset="small", seed=0, progress=False, workers=1,
                   ray_address="local" if ray_local is not None else None, **TINY)
    TIMINGS["make_benchmark_s"] = time.perf_counter() - t0
    return root


@pytest.fixture
def local_run(suite_dir, tiny_config, tmp_path_factory):
    """run_suite of the tiny suite here in this process with the tiny reconstruct config (run once)."""
    if "local" not in _RUNS:
        out = tmp_path_factory.mktemp("local") / "out"
        t0 = time.perf_counter()
        result = run_suite(suite_dir, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False)
        TIMINGS["suite_local_s"] = time.perf_counter() - t0
        _RUNS["local"] = {"out": out, "result": result}
    return _RUNS["local"]


def _numbers(evaluation: dict) -> dict:
    """An evaluation without what legitimately differs between two runs (paths, wall times)."""
    return {k: v for k, v in evaluation.items() if k not in ("asset", "scene", "timing")}


def test_suite_json_schema_means_and_table(local_run, suite_dir, tiny_config):
    out, result = local_run["out"], local_run["result"]
    assert json.loads((out / SUITE_JSON).read_text()) == result
    assert set(result) == {"suite", "preset", "scenes", "means", "failed"}
    assert result["suite"] == str(suite_dir.resolve()) and result["preset"] == "custom" and result["failed"] == 0
    assert set(result["means"]) == set(METRICS) == {
        "dynamic_psnr", "dynamic_ssim", "future_psnr", "future_ssim", "future_from_start_psnr", "novel_psnr",
        "novel_ssim", "rest_psnr",
        "abs_error_log10_E", "abs_error_nu", "start_abs_error_log10_E", "start_abs_error_nu", "chamfer_observed",
        "chamfer_future", "centre_of_mass_frame_0", "centre_of_mass_observed", "centre_of_mass_future",
        "rotation_observed", "rotation_future", "first_contact_added_centre_of_mass", "first_contact_added_rotation",
        "solid_frequency_ratio", "solid_volume_ratio", "solid_bottom_offset", "interval_covers_log10_E",
        "interval_covers_nu", "joint_improved", "seconds"}
    index = json.loads((suite_dir / "index.json").read_text())
    assert [r["name"] for r in result["scenes"]] == [s["name"] for s in index["scenes"]] == ["scene_000", "scene_001"]
    for record, truth in zip(result["scenes"], index["scenes"]):
        assert set(record) == SCENE_KEYS
        assert record["status"] == "ok" and record["error"] is None
        assert record["report"] == str(out.resolve() / record["name"] / "report")  # the scene's HTML report
        assert (Path(record["report"]) / "index.html").is_file()
        assert record["scene"] == str(suite_dir.resolve() / record["name"])
        assert record["asset"] == str(out.resolve() / record["name"] / "asset")
        assert record["evaluation"] == json.loads((out / record["name"] / EVALUATION_JSON).read_text())
        assert isinstance(record["seconds"], float) and 0 < record["seconds"] < 600
        # the material error is the fitted asset's against the suite's ground truth
        fitted = json.loads((out / record["name"] / "asset" / "material.json").read_text())
        assert record["evaluation"]["material"]["abs_error_log10_E"] == pytest.approx(
            abs(fitted["log10_E"] - math.log10(truth["E"])), abs=1e-6)
        assert record["evaluation"]["material"]["abs_error_nu"] == pytest.approx(abs(fitted["nu"] - truth["nu"]),
                                                                              abs=1e-6)
        ev = record["evaluation"]
        assert 10 < ev["dynamic"]["psnr"] < 60 and 0 < ev["novel_views"]["ssim"] < 1
        # the start of Stage II (the prior: Stage I is off) with its own errors, the fit's baseline
        prior = tiny_config()
        start = ev["material"]["start"]
        assert start["source"] == "prior" and start["E"] == prior.prior.E and start["nu"] == prior.prior.nu
        assert start["abs_error_log10_E"] == pytest.approx(abs(math.log10(prior.prior.E) - math.log10(truth["E"])))
        assert start["abs_error_nu"] == pytest.approx(abs(prior.prior.nu - truth["nu"]))
    # means: the plain average of the two scenes' evaluation.json values
    evs = [json.loads((out / n / EVALUATION_JSON).read_text()) for n in ("scene_000", "scene_001")]
    expected = {
        "dynamic_psnr": [e["dynamic"]["psnr"] for e in evs], "future_ssim": [e["future"]["ssim"] for e in evs],
        "novel_psnr": [e["novel_views"]["psnr"] for e in evs],
        "abs_error_nu": [e["material"]["abs_error_nu"] for e in evs],
        "start_abs_error_nu": [e["material"]["start"]["abs_error_nu"] for e in evs],
        "chamfer_future": [e["chamfer"]["future_mean"] for e in evs],
        "centre_of_mass_future": [e["centre_of_mass"]["future_mean"] for e in evs],
        "rotation_observed": [e["orientation"]["observed_mean_deg"] for e in evs],
        "seconds": [r["seconds"] for r in result["scenes"]],
    }
    for key, values in expected.items():
        assert result["means"][key] == pytest.approx(sum(values) / 2, rel=1e-12)
    settings = json.loads((out / SUITE_CONFIG_JSON).read_text())
    assert settings["reconstruct"] == tiny_config().to_dict() and settings["threads"] == 1
    suite_page = (out / "report" / "index.html").read_text()  # the suite's report links each scene's
    assert all(f"{name}/report/index.html" in suite_page for name in ("scene_000", "scene_001"))
    # the table: the paper's layout, one column per scene then the mean, values as in suite.json
    table = format_table(result)
    lines = table.splitlines()
    assert lines[0].split() == ["000", "001", "mean"]
    psnr = next(line for line in lines if line.startswith("PSNR (dB)")).split()
    assert psnr[2:4] == ["dynamic", f"{evs[0]['dynamic']['psnr']:.2f}"]
    assert psnr[-1] == f"{result['means']['dynamic_psnr']:.2f}"
    chamfer = next(line for line in lines if line.startswith("Chamfer (cm)")).split()
    assert chamfer[-1] == f"{100 * result['means']['chamfer_observed']:.2f}"  # metres in JSON, cm in the table
    row = next(i for i, line in enumerate(lines) if line.startswith("centre of mass (cm)"))
    com, observed = lines[row].split(), lines[row + 1].split()
    assert com[-1] == f"{100 * result['means']['centre_of_mass_frame_0']:.2f}"  # the row "frame 0", then observed
    assert observed[0] == "observed" and observed[-1] == f"{100 * result['means']['centre_of_mass_observed']:.2f}"
    assert len({len(line) for line in lines[2:16]}) == 1  # aligned columns
    assert "FAILED" not in table


def test_resume_skips_finished_scenes_and_refuses_other_settings(local_run, suite_dir, tiny_config, tmp_path,
                                                                  monkeypatch):
    import vid2sim.apps.bench.suite as evaluate_module  # where the suite looks evaluate up
    import vid2sim.apps.bench.suite as reconstruct_module  # where the suite looks reconstruct up

    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    before = local_run["result"]

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished scene was run again")

    monkeypatch.setattr(reconstruct_module, "reconstruct", must_not_run)
    real_evaluate = evaluate_module.evaluate
    monkeypatch.setattr(evaluate_module, "evaluate", must_not_run)
    again = run_suite(suite_dir, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False)
    assert again["failed"] == 0 and again["means"] == before["means"]
    assert [r["evaluation"]["dynamic"] for r in again["scenes"]] == [
        r["evaluation"]["dynamic"] for r in before["scenes"]
    ]
    # a finished asset without its evaluation (interrupted during evaluate): only evaluate runs
    (out / "scene_001" / EVALUATION_JSON).unlink()
    monkeypatch.setattr(evaluate_module, "evaluate", real_evaluate)
    again = run_suite(suite_dir, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False)
    assert again["failed"] == 0
    assert _numbers(again["scenes"][1]["evaluation"]) == _numbers(before["scenes"][1]["evaluation"])
    # the same resolved settings under another preset name (a release moved the preset a run was pinned to with
    # --config): resumed, nothing runs again ...
    settings = json.loads((out / SUITE_CONFIG_JSON).read_text())
    # ... and a settings file written before a release added a setting (here the hull track's), at its default
    del settings["reconstruct"]["joint"]["track_volume_tolerance"]
    (out / SUITE_CONFIG_JSON).write_text(json.dumps({**settings, "preset": "full"}))
    monkeypatch.setattr(evaluate_module, "evaluate", must_not_run)
    resumed = run_suite(suite_dir, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False)
    assert resumed["failed"] == 0 and resumed["means"] == again["means"]
    # other settings on the same results folder are refused before any work
    with pytest.raises(ValueError, match="other settings .*reconstruct"):
        run_suite(suite_dir, out, SuiteConfig(preset="small"), progress=False)


def test_a_broken_scene_is_reported_and_the_others_finish(local_run, suite_dir, tiny_config, tmp_path):
    suite = tmp_path / "suite"
    shutil.copytree(suite_dir, suite)
    (suite / "scene_000" / "scene.json").write_text("{ not json")
    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    shutil.rmtree(out / "scene_000")
    (out / "scene_001" / EVALUATION_JSON).unlink()  # scene_001 has its asset: evaluated after scene_000 fails
    settings = json.loads((out / SUITE_CONFIG_JSON).read_text())
    (out / SUITE_CONFIG_JSON).write_text(json.dumps({**settings, "suite": str(suite.resolve())}))
    result = run_suite(suite, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False)
    bad, good = result["scenes"]
    assert result["failed"] == 1 and bad["status"] == "failed" and good["status"] == "ok"
    assert "scene.json" in bad["error"] and bad["evaluation"] is None and bad["asset"] is None
    assert set(bad) == SCENE_KEYS and isinstance(bad["seconds"], float)
    assert "Traceback" in (out / "scene_000" / "error.txt").read_text()
    assert _numbers(good["evaluation"]) == _numbers(local_run["result"]["scenes"][1]["evaluation"])
    # means over the finished scene only
    assert result["means"]["dynamic_psnr"] == good["evaluation"]["dynamic"]["psnr"]
    table = format_table(result)
    assert "failed" in next(line for line in table.splitlines() if line.startswith("PSNR"))
    assert f"FAILED scene_000: {bad['error']}" in table


def test_cli_bench_suite_prints_the_table_and_exit_codes(local_run, suite_dir, tmp_path, capsys):
    # a finished run (settings as the CLI's small preset would write them): the command only reports
    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    (out / SUITE_JSON).unlink()
    settings = {"suite": str(suite_dir.resolve()), **SuiteConfig(preset="small", threads=1).to_dict()}
    (out / SUITE_CONFIG_JSON).write_text(json.dumps(settings))
    assert main(["bench", "suite", str(suite_dir), str(out), "--threads", "1", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out.splitlines()[0].split() == ["000", "001", "mean"]
    assert f"wrote {out / SUITE_JSON}" in captured.out
    assert json.loads((out / SUITE_JSON).read_text())["preset"] == "small"
    # every scene broken: both reported, exit code 1, the failed scenes named
    suite = tmp_path / "broken"
    shutil.copytree(suite_dir, suite)
    for name in ("scene_000", "scene_001"):
        (suite / name / "scene.json").unlink()
    assert main(["bench", "suite", str(suite), str(tmp_path / "out2"), "--threads", "1", "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "2 of 2 scenes failed (scene_000, scene_001)" in captured.err
    assert captured.out.count("FAILED scene_") == 2
    # an unfinished suite and a foreign results folder are one-line errors
    index = json.loads((suite / "index.json").read_text())
    (suite / "index.json").write_text(json.dumps({**index, "complete": False, "n": 3}))
    assert main(["bench", "suite", str(suite), str(tmp_path / "out3"), "--quiet"]) == 2
    assert "lists 2 of its 3 scenes" in capsys.readouterr().err
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "x.txt").write_text("x")
    assert main(["bench", "suite", str(suite_dir), str(tmp_path / "foreign"), "--quiet"]) == 2
    assert "holds no suite_config.json" in capsys.readouterr().err


def test_cli_bench_suite_passes_rerun_changed_to_each_reconstruction(suite_dir, tmp_path, monkeypatch):
    import vid2sim.apps.bench.suite as reconstruct_module  # where the suite looks reconstruct up

    seen = []

    def fake(scene, out, config, progress=False, snapshots=None, rerun_changed=False, rollout_processes=0):
        seen.append((rerun_changed, rollout_processes))
        raise ValueError("stop here")

    monkeypatch.setattr(reconstruct_module, "reconstruct", fake)
    assert main(["bench", "suite", str(suite_dir), str(tmp_path / "a"), "--threads", "1", "--quiet"]) == 1
    assert main(["bench", "suite", str(suite_dir), str(tmp_path / "b"), "--threads", "1", "--quiet",
                 "--rerun-changed"]) == 1
    assert seen == [(False, 0), (False, 0), (True, 0), (True, 0)]  # one thread a scene: no rollout workers


def test_ray_suite_gives_the_local_numbers(ray_local, local_run, suite_dir, tiny_config, tmp_path, monkeypatch):
    import vid2sim.apps.bench.suite as reconstruct_module  # where the suite looks reconstruct up

    if ray_local is None:
        pytest.skip("ray is not installed (pip install \"vid2sim[ray]\")")

    def not_here(*args, **kwargs):
        raise AssertionError("reconstruct ran in the driver, not in a Ray worker")

    monkeypatch.setattr(reconstruct_module, "reconstruct", not_here)  # the worker processes have the real one
    # scene_000 finished by the local run (skipped), scene_001 made from scratch by a Ray task: the test's
    # time stays in check on a shared 2-core machine; the make-benchmark fixture gathers several Ray tasks
    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    shutil.rmtree(out / "scene_001")
    (out / SUITE_JSON).unlink()
    t0 = time.perf_counter()
    result = run_suite(suite_dir, out, SuiteConfig(reconstruct=tiny_config(), threads=1), progress=False,
                       ray_address="local")
    TIMINGS["suite_ray_one_scene_s"] = time.perf_counter() - t0
    local = local_run["result"]
    assert result["failed"] == 0 and [r["status"] for r in result["scenes"]] == ["ok", "ok"]
    assert (out / "scene_001" / "asset" / "asset.json").is_file()
    for ours, theirs in zip(result["scenes"], local["scenes"]):
        assert ours["name"] == theirs["name"]
        assert ours["asset"] == str(out.resolve() / ours["name"] / "asset")
        assert _numbers(ours["evaluation"]) == _numbers(theirs["evaluation"])  # bit for bit: same seeds, 1 thread
    assert {k: v for k, v in result["means"].items() if k != "seconds"} == \
        {k: v for k, v in local["means"].items() if k != "seconds"}
    assert json.loads((out / SUITE_JSON).read_text()) == result


def test_make_benchmark_through_ray_writes_what_the_local_run_writes(ray_local, suite_dir, tmp_path):
    if ray_local is None:
        pytest.skip("ray is not installed (pip install \"vid2sim[ray]\")")
    # suite_dir was made through Ray. Resumed locally, make_benchmark checks every scene's synthetic.json
    # against its own settings and rewrites index.json: byte for byte the same as the Ray run's.
    copy = tmp_path / "suite"
    shutil.copytree(suite_dir, copy)
    make_benchmark(2, copy, preset="small", seed=0, progress=False, workers=1, **TINY)
    assert (copy / "index.json").read_bytes() == (suite_dir / "index.json").read_bytes()
    for i, params in enumerate(benchmark_parameters(2, seed=0)):
        written = json.loads((suite_dir / f"scene_{i:03d}" / "synthetic.json").read_text())
        expected = json.loads(json.dumps(asdict(SyntheticSceneConfig.preset("small", **TINY, **params))))
        assert written == expected
        meta = json.loads((suite_dir / f"scene_{i:03d}" / "scene.json").read_text())["metadata"]
        assert (meta["E"], meta["nu"], meta["seed"]) == (params["youngs_modulus"], params["poisson_ratio"],
                                                         params["seed"])


def test_make_benchmark_refuses_to_shrink_a_suite_and_counts_scenes(suite_dir, tmp_path, capsys):
    copy = tmp_path / "suite"
    shutil.copytree(suite_dir, copy)
    index = (copy / "index.json").read_bytes()
    assert main(["make-benchmark", str(copy), "--n", "1", *TINY_FLAGS]) == 2
    err = capsys.readouterr().err
    assert "holds a suite of 2 scenes; asking for 1 would leave scene_001 outside index.json" in err
    assert "n = 2 or more" in err
    assert (copy / "index.json").read_bytes() == index and (copy / "scene_001" / "scene.json").is_file()
    # without the orphan the smaller suite is fine, and the message counts grammatically
    shutil.rmtree(copy / "scene_001")
    assert main(["make-benchmark", str(copy), "--n", "1", *TINY_FLAGS]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {copy} (1 scene, index.json)"
    written = json.loads((copy / "index.json").read_text())
    assert written["n"] == 1 and written["complete"] and [s["name"] for s in written["scenes"]] == ["scene_000"]


def test_ray_address_without_ray_says_how_to_install_it(suite_dir, tmp_path, monkeypatch, capsys):
    if importlib.util.find_spec("ray") is not None:  # an address where nothing answers fails at once
        assert main(["bench", "suite", str(suite_dir), str(tmp_path / "out"), "--ray-address", "127.0.0.1:1"]) == 2
        assert "nothing accepts connections at 127.0.0.1:1" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    assert main(["bench", "suite", str(suite_dir), str(tmp_path / "out"), "--ray-address", "local", "--quiet"]) == 2
    assert 'pip install "vid2sim[ray]"' in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing written
    assert main(["make-benchmark", str(tmp_path / "b"), "--n", "1", "--ray-address", "local", *TINY_FLAGS]) == 2
    assert 'pip install "vid2sim[ray]"' in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_bench_table_reads_a_results_folder_as_it_stands(local_run, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    assert main(["bench", "table", str(out)]) == 0  # a finished suite: the run's own table
    assert capsys.readouterr().out.strip() == format_table(local_run["result"]).strip()
    (out / "scene_001" / EVALUATION_JSON).unlink()  # not finished yet
    so_far = suite_so_far(out)
    assert [r["status"] for r in so_far["scenes"]] == ["ok", "pending"] and so_far["failed"] == 0
    assert so_far["means"]["dynamic_psnr"] == local_run["result"]["scenes"][0]["evaluation"]["dynamic"]["psnr"]
    table = format_table(so_far)
    assert "pending" in next(line for line in table.splitlines() if line.startswith("PSNR"))
    assert "mean over the 1 finished (1 pending)" in table and "FAILED" not in table
    (out / "scene_001" / "error.txt").write_text("Traceback ...\nValueError: the scene broke\n")
    so_far = suite_so_far(out)
    assert so_far["scenes"][1]["status"] == "failed" and so_far["failed"] == 1
    assert "FAILED scene_001: ValueError: the scene broke" in format_table(so_far)
    assert main(["bench", "table", str(tmp_path)]) == 2  # not a results folder: one line, no traceback
    assert "suite_config.json not found" in capsys.readouterr().err


def test_a_suite_made_and_run_in_shards(local_run, suite_dir, tiny_config, tmp_path, monkeypatch, capsys):
    import vid2sim.apps.bench.suite as suite_module  # where the suite looks reconstruct and evaluate up

    # make-benchmark --scenes: a shard of the suite; index.json lists what is made, complete once all are
    suite = tmp_path / "suite"
    shutil.copytree(suite_dir, suite)
    shutil.rmtree(suite / "scene_001")
    assert main(["make-benchmark", str(suite), "--n", "2", "--scenes", "0", *TINY_FLAGS]) == 0  # made: kept
    assert capsys.readouterr().out.strip() == f"wrote {suite} (a shard of 1 scene; index.json lists 1 of the suite's 2)"
    index = json.loads((suite / "index.json").read_text())
    assert index["n"] == 2 and not index["complete"] and [s["name"] for s in index["scenes"]] == ["scene_000"]
    assert not (suite / "scene_001").exists()
    with pytest.raises(ValueError, match="scene index 2 is not one of the suite's 2"):
        make_benchmark(2, suite, preset="small", progress=False, scenes=[2], **TINY)
    assert main(["make-benchmark", str(suite), "--n", "2", "--scenes", "5:", *TINY_FLAGS]) == 2
    assert "selects none of the suite's 2 scenes" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse's usage error
        main(["make-benchmark", str(suite), "--n", "2", "--scenes", "x", *TINY_FLAGS])
    assert "expected A:B" in capsys.readouterr().err

    # bench suite --scenes runs the made shard of the unfinished suite; the whole suite is refused
    out = tmp_path / "out"
    shutil.copytree(local_run["out"], out)
    settings = json.loads((out / SUITE_CONFIG_JSON).read_text())
    (out / SUITE_CONFIG_JSON).write_text(json.dumps({**settings, "suite": str(suite.resolve())}))
    shutil.rmtree(out / "scene_001")

    def must_not_run(*args, **kwargs):
        raise AssertionError("a finished scene was run again")

    monkeypatch.setattr(suite_module, "reconstruct", must_not_run)
    monkeypatch.setattr(suite_module, "evaluate", must_not_run)
    config = SuiteConfig(reconstruct=tiny_config(), threads=1)
    shard = run_suite(suite, out, config, progress=False, scenes=slice(0, 1))
    assert [r["name"] for r in shard["scenes"]] == ["scene_000"] and shard["failed"] == 0
    assert _numbers(shard["scenes"][0]["evaluation"]) == _numbers(local_run["result"]["scenes"][0]["evaluation"])
    with pytest.raises(ValueError, match="did not make its scene_001 yet"):
        run_suite(suite, out, config, progress=False)
    with pytest.raises(ValueError, match=r"the selected scene_001 yet.*--scenes"):
        run_suite(suite, out, config, progress=False, scenes=slice(1, None))
    so_far = suite_so_far(out)  # bench table: the scene not made yet is pending
    assert [(r["name"], r["status"]) for r in so_far["scenes"]] == [("scene_000", "ok"), ("scene_001", "pending")]

    # on the finished suite a shard's suite.json holds the scenes finished in OUT besides the shard's own
    out = tmp_path / "out_full"
    shutil.copytree(local_run["out"], out)
    result = run_suite(suite_dir, out, config, progress=False, scenes=slice(1, 2))
    assert result["means"] == local_run["result"]["means"] and len(result["scenes"]) == 2
    assert main(["bench", "suite", str(suite_dir), str(tmp_path / "out2"), "--scenes", "7:9", "--quiet"]) == 2
    assert "--scenes selects none of the 2 scenes" in capsys.readouterr().err


def test_a_results_folder_holding_only_a_killed_writers_temporary_file_is_taken(tmp_path):
    """A run killed while writing its first suite_config.json leaves only that file's temporary copy: the next run
    takes the folder (and removes it), while a folder holding anything else is still refused."""
    from vid2sim.apps.bench.suite import _prepare_out, check_out

    out = tmp_path / "out"
    out.mkdir()
    left = out / f".{SUITE_CONFIG_JSON}.k1lled00.tmp"
    left.write_text('{"sui')
    settings = {"suite": str(tmp_path / "suite"), **SuiteConfig().to_dict()}
    check_out(out, settings)
    _prepare_out(out, settings)
    assert not left.exists() and json.loads((out / SUITE_CONFIG_JSON).read_text()) == json.loads(json.dumps(settings))
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        check_out(other, settings)
