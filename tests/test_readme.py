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
