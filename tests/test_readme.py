"""The README's Python example runs as written and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    x = namespace["x"]
    assert x.shape == (4000, 3)
    lowest = float(x[:, 2].min().detach())
    assert -0.72 < lowest < -0.68  # resting on the floor at -0.7
    assert "lowest point" in capsys.readouterr().out


def test_readme_commands_exist_and_ci_runs_the_readme_test_command():
    """Every `vid2sim COMMAND` the README shows is a real subcommand; .ci/run runs the README's test command."""
    from vid2sim.cli import build_parser

    text = README.read_text()
    shell = "\n".join(re.findall(r"```bash\n(.*?)```", text, flags=re.S))
    commands = set(re.findall(r"^vid2sim ([a-z][a-z-]*)", shell, flags=re.M))
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert commands and commands <= set(sub.choices), commands - set(sub.choices)
    ci = (README.parent / ".ci" / "run").read_text()
    assert "python -m pytest -q" in shell and "python3 -m pytest -q\n" in ci
