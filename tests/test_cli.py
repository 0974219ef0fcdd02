"""The vid2sim command: version, help, and clean errors for bad benchmark arguments."""

from __future__ import annotations

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
