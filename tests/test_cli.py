"""The vid2sim command: version, help, and clean errors for bad benchmark arguments."""

from __future__ import annotations

import json

import pytest

from vid2sim import __version__
from vid2sim.cli import main


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out
    assert main([]) == 0
    out = capsys.readouterr().out
    for command in ("bench", "make-scene", "make-benchmark", "fit-gaussians"):
        assert command in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["bench", "speed", "--only", "nonsense"], "unknown benchmark section"),
        (["bench", "jacobian", "--iterations", "0"], "iterations must be a positive integer"),
        (["bench", "speed", "--device", "cuda:7"], "CUDA is not available"),
        (["bench", "speed", "--device", "banana"], "--device 'banana' is not a torch device"),
        (["bench", "speed", "--device", "meta"], "vid2sim runs on cpu or cuda"),
        (["fit-gaussians", "no-scene", "no-out", "--iterations", "0"], "--iterations must be >= 1"),
        (["make-benchmark", "no-out", "--n", "0"], "--n must be >= 1"),
        (["reconstruct", "no-scene", "no-out", "--threads", "0"], "--threads must be >= 1"),
        (["bench", "fem", "--frames", "1"], "SyntheticSceneConfig.frames must be an integer >= 2"),
    ],
)
def test_bench_argument_errors_are_one_line(capsys, argv, message):
    if "cuda:7" in argv:
        import torch

        if torch.cuda.is_available():
            pytest.skip("the machine has CUDA")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.slow
def test_bench_fem_times_both_hessian_strategies_on_one_mesh(capsys):
    """Eight frames of the small preset's seed-0 drop (it reaches the floor): both Newton strategies
    solve every step to the tolerance, so they give the same trajectory."""
    assert main(["bench", "fem", "--frames", "8", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["preset"] == "small" and result["frames"] == 8 and result["tets"] > 1000
    assert result["fem_seconds"] > 0 and result["fem_seconds_always_projected"] > 0
    ratio = result["fem_seconds_always_projected"] / result["fem_seconds"]
    assert result["fem_speedup_vs_always_projected"] == pytest.approx(ratio)
    assert result["trajectory_max_difference_m"] < 1e-5
    for suffix in ("", "_always_projected"):
        assert 1 <= result[f"newton_iterations_mean{suffix}"] <= result[f"newton_iterations_max{suffix}"] < 100


def test_reconstruct_prints_the_material_with_its_intervals_and_what_the_video_says():
    """The lines `vid2sim reconstruct` prints of a material.json: E and ν, then each interval with its note (found,
    not identifiable, at the coarse search's end); an asset without an uncertainty record gets the first line only."""
    from vid2sim.cli.reconstruct import material_lines

    material = {"E": 9.98e3, "log10_E": 3.999, "nu": 0.293, "uncertainty": {
        "level": 0.68,
        "log10_E": {"interval": [3.793, 4.205], "note": "found; at the lower end of the coarse search (log10 E 4)"},
        "nu": {"interval": [0.194, 0.392], "note": "not identifiable from this video"}}}
    assert material_lines(material) == [
        "E = 9980 Pa (log10 E = 3.999), nu = 0.293",
        "  log10 E: 68 % interval [3.793, 4.205]; found; at the lower end of the coarse search (log10 E 4)",
        "  nu: 68 % interval [0.194, 0.392]; not identifiable from this video"]
    assert material_lines({"E": 1e5, "log10_E": 5.0, "nu": 0.3}) == ["E = 1e+05 Pa (log10 E = 5.000), nu = 0.300"]
