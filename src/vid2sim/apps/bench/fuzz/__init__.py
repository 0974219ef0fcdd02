"""``vid2sim bench fuzz``: the reliability and security campaign (docs/reliability.md).

Four sections, each a module of this package, each run by its ``run(config, records)`` and summarised in one
JSON object of figures:

- :mod:`~vid2sim.apps.bench.fuzz.physics`: random simulations through the public scenario API;
- :mod:`~vid2sim.apps.bench.fuzz.inputs`: corrupted files of every kind vid2sim reads, each fed to the command
  that reads it in a child process with a time limit;
- :mod:`~vid2sim.apps.bench.fuzz.hostile`: files made by someone else that try to run code, reach outside the
  folder, inject into a report or exhaust memory;
- :mod:`~vid2sim.apps.bench.fuzz.kills`: commands killed (SIGKILL) at random moments and resumed; two
  processes on one output; a full disk and a read-only output.

With an output folder (``--out``) every finished case is appended to ``OUT/<section>.jsonl`` and the settings
to ``OUT/fuzz_config.json``, so a long campaign runs in chunks: the same command resumes where it stopped.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from vid2sim.runtime.errors import ConfigError

SECTIONS = ("physics", "inputs", "hostile", "kills")


@dataclass
class FuzzConfig:
    """Settings of a campaign (saved as ``fuzz_config.json`` beside the records).

    Attributes:
        physics: random simulations.
        inputs: corrupted-input cases.
        hostile: run the hostile-file checks.
        kills: kill-and-resume cases.
        quick: toy sizes everywhere (the test suite's run: well under a minute on two cores).
        seed: the first case's seed; case i uses seed + i.
        workers: processes running physics cases side by side.
        threads: torch threads per process.
        timeout: seconds a corrupted-input case may take before it counts as a hang.
        browser: check the hostile report in headless Chromium when one is installed.
    """

    physics: int = 0
    inputs: int = 0
    hostile: bool = False
    kills: int = 0
    quick: bool = False
    seed: int = 0
    workers: int = 1
    threads: int = 1
    timeout: float = 60.0
    browser: bool = True

    def __post_init__(self) -> None:
        for name in ("physics", "inputs", "kills", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"FuzzConfig.{name} must be an integer >= 0, got {v!r}")
        for name in ("workers", "threads"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"FuzzConfig.{name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.timeout, (int, float)) and 0 < self.timeout < 1e6):
            raise ConfigError(f"FuzzConfig.timeout must be a positive number of seconds, got {self.timeout!r}")

    @classmethod
    def quick_run(cls, **overrides: Any) -> "FuzzConfig":
        """The ``--quick`` campaign: a few cases of every section."""
        values: dict[str, Any] = {"physics": 2, "inputs": 20, "hostile": True, "kills": 1, "quick": True,
                                  "timeout": 30.0}
        values.update(overrides)
        return cls(**values)


def run_fuzz(config: FuzzConfig, out: str | Path | None = None, progress: bool = False) -> dict[str, Any]:
    """Run the campaign of ``config``; returns its figures (one JSON-ready dict, a key per section run).

    ``out``: the records folder (resumable; None keeps nothing)."""
    from vid2sim.runtime.files import write_json_atomic

    folder = None if out is None else Path(out)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        write_json_atomic(folder / "fuzz_config.json", asdict(config))
    figures: dict[str, Any] = {"config": asdict(config)}
    t0 = time.perf_counter()
    record = lambda name: None if folder is None else folder / f"{name}.jsonl"  # noqa: E731
    if config.inputs or config.hostile:  # forked cases first, while this process has run no torch threads
        import tempfile

        from vid2sim.apps.bench.fuzz import hostile, inputs

        with tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-seeds-") as tmp:
            seeds = inputs.seeds_in_child(Path(tmp) / "seeds", config.quick)
            if config.inputs:
                figures["inputs"] = inputs.run(config, record("inputs"), seeds, progress)
            if config.hostile:
                figures["hostile"] = hostile.run(config, record("hostile"), seeds, progress)
    if config.kills:
        from vid2sim.apps.bench.fuzz import kills

        figures["kills"] = kills.run(config, record("kills"), progress)
    if config.physics:
        from vid2sim.apps.bench.fuzz import physics

        figures["physics"] = physics.run(config, record("physics"), progress)
    figures["seconds"] = round(time.perf_counter() - t0, 1)
    return figures
