"""The reconstruction's stage runner on stand-in stages: each stage runs with its own seed (a resumed run
computes what an uninterrupted one does) and stage snapshots let runs of one scene share their first stages."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import torch

from vid2sim.reconstruct.config import ReconstructConfig
from vid2sim.reconstruct.runner import (
    Context,
    ReconstructionError,
    StageSnapshots,
    State,
    WorkFolder,
    cache_keys,
    run_stages,
    scene_fingerprint,
)
from vid2sim.runtime import config as configs


class Draw:
    """A stand-in stage: draws from torch's global generator, writes it with what it read, counts its runs."""

    def __init__(self, name: str, section: str, runs: dict[str, int]) -> None:
        self.name, self.sections, self.runs, self.revision = name, (section,), runs, 0

    def title(self, ctx, state):
        return self.name

    def run(self, ctx, state):
        self.runs[self.name] = self.runs.get(self.name, 0) + 1
        before = [state.log[k] for k in sorted(state.log)]
        (ctx.work.dir / f"{self.name}.json").write_text(json.dumps([torch.rand(3).tolist(), before]))
        (ctx.work.dir / f".{self.name}.input").write_text("a transient input (hidden): snapshots leave it out")

    def load(self, ctx, state):
        state.log[self.name] = json.loads((ctx.work.dir / f"{self.name}.json").read_text())


def _run(out: Path, config: ReconstructConfig, snapshots: StageSnapshots | None, runs: dict[str, int],
         only: int | None = None, rerun_changed: bool = False) -> tuple[State, WorkFolder]:
    stages = [Draw("a", "gaussians", runs), Draw("b", "points", runs), Draw("c", "networks", runs)]
    work = WorkFolder(out, cache_keys(stages, config, "scene"), restart=False, snapshots=snapshots,
                      rerun_changed=rerun_changed)
    ctx = Context(config=config, scene=None, observed=None, device=torch.device("cpu"), work=work, progress=False,
                  threads=torch.get_num_threads())
    torch.manual_seed(12345)  # the global generator's state before the run does not matter
    return run_stages(stages[:only], ctx, State()), work


def test_each_stage_draws_the_same_numbers_whether_the_stages_before_it_ran_or_were_resumed(tmp_path):
    runs: dict[str, int] = {}
    whole, _ = _run(tmp_path / "one", ReconstructConfig(), None, runs)
    _run(tmp_path / "two", ReconstructConfig(), None, runs, only=2)  # interrupted after b
    torch.rand(100)  # the generator moves on in between
    resumed, _ = _run(tmp_path / "two", ReconstructConfig(), None, runs)
    assert runs == {"a": 2, "b": 2, "c": 2} and resumed.log == whole.log
    draws = [whole.log[k][0] for k in "abc"]
    assert draws[0] != draws[1] != draws[2]  # stages draw different numbers
    other = ReconstructConfig()
    other.seed += 1
    assert _run(tmp_path / "three", other, None, {})[0].log["a"][0] != draws[0]  # the config's seed decides


def test_runs_of_one_scene_share_stages_through_snapshots_when_their_settings_agree(tmp_path):
    snapshots = StageSnapshots(tmp_path / "shared", ("b",))
    runs: dict[str, int] = {}
    first, work = _run(tmp_path / "first", ReconstructConfig(), snapshots, runs)
    (saved,) = list((tmp_path / "shared").iterdir())
    assert saved.name.startswith("b-") and work.restored is None
    assert sorted(p.name for p in saved.iterdir()) == ["a.done", "a.json", "b.done", "b.json", "timings.json"]
    # the same settings up to b: a and b come from the snapshot, with the seconds they took there; c runs
    second, work = _run(tmp_path / "second", ReconstructConfig(), snapshots, runs)
    assert runs == {"a": 1, "b": 1, "c": 2} and work.restored == "b"
    assert second.log == first.log  # c read what the first run's a and b wrote, and drew the same numbers
    stored = json.loads((saved / "timings.json").read_text())
    assert {k: work.timings[k] for k in "ab"} == stored and work.timings["c"] >= 0
    # other settings of c only: still shared; of b: nothing to restore (b's key differs), everything runs
    changed = ReconstructConfig()
    changed.networks.handles += 1
    assert _run(tmp_path / "third", changed, snapshots, runs)[1].restored == "b" and runs["b"] == 1
    changed = ReconstructConfig()
    changed.points.resolution += 1
    _, work = _run(tmp_path / "fourth", changed, snapshots, runs)
    assert work.restored is None and runs == {"a": 2, "b": 2, "c": 4}
    assert len(list((tmp_path / "shared").iterdir())) == 2  # its own snapshot of b, beside the first
    # a folder that has already finished b is not overwritten
    again, work = _run(tmp_path / "second", ReconstructConfig(), snapshots, runs)
    assert work.restored is None and again.log == first.log and runs == {"a": 2, "b": 2, "c": 4}


def test_a_scene_made_again_in_the_same_place_is_another_scene_to_the_cache(tmp_path):
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "scene.json").write_text("{}")
    (scene / "images" / "c00_t000.png").write_bytes(b"x" * 10)
    first = scene_fingerprint(scene)
    assert first.startswith(str(scene.resolve()) + "#") and scene_fingerprint(tmp_path / "scene" / ".") == first
    (scene / ".hidden").write_text("a viewer's cache")  # hidden files are not the scene's
    assert scene_fingerprint(scene) == first
    (scene / "images" / "c00_t000.png").write_bytes(b"y" * 11)  # a frame written again
    assert scene_fingerprint(scene) != first
    keys = [cache_keys([Draw("a", "gaussians", {})], ReconstructConfig(), s) for s in (first, scene_fingerprint(scene))]
    assert keys[0]["a"] != keys[1]["a"]


def test_an_interrupted_run_with_other_settings_is_refused_or_rerun_from_the_first_changed_stage(tmp_path):
    runs: dict[str, int] = {}
    first, _ = _run(tmp_path / "out", ReconstructConfig(), None, runs)  # a, b and c finished (not yet the asset)
    changed = ReconstructConfig()
    changed.points.resolution += 1  # b's section: b and c change, a does not
    with pytest.raises(ReconstructionError, match="'b' stage ran with other settings.*--rerun-changed"):
        _run(tmp_path / "out", changed, None, runs)
    assert runs == {"a": 1, "b": 1, "c": 1} and (tmp_path / ".out.work" / "b.done").is_file()  # nothing discarded
    rerun, work = _run(tmp_path / "out", changed, None, runs, rerun_changed=True)
    assert work.rerun == ["b", "c"] and runs == {"a": 1, "b": 2, "c": 2}
    assert rerun.log["a"] == first.log["a"]  # a kept, b and c run again in their turn (their own seeds)
    assert rerun.log["b"][0] == first.log["b"][0] and rerun.log["c"] == first.log["c"]
    _, work = _run(tmp_path / "out", changed, None, runs, rerun_changed=True)  # now they agree: nothing to rerun
    assert work.rerun == [] and runs == {"a": 1, "b": 2, "c": 2}


def test_a_revised_stage_is_not_resumed_or_restored_as_the_old_method(tmp_path):
    stages = [Draw("a", "gaussians", {}), Draw("b", "points", {}), Draw("c", "networks", {})]
    before = cache_keys(stages, ReconstructConfig(), "scene")
    # revision 0 adds nothing to the key: the keys of stages never revised are the ones earlier releases wrote
    config = ReconstructConfig()
    start = hashlib.sha256(json.dumps({"scene": "scene", "seed": config.seed}).encode()).hexdigest()
    text = json.dumps({"previous": start, "sections": {"gaussians": configs.to_dict(config.gaussians)}}, sort_keys=True)
    assert before["a"] == hashlib.sha256(text.encode()).hexdigest()
    stages[1].revision = 1  # a release changed b's method: b and every stage after it have new keys, a keeps its
    after = cache_keys(stages, ReconstructConfig(), "scene")
    assert after["a"] == before["a"] and after["b"] != before["b"] and after["c"] != before["c"]
    # a work folder and a snapshot that b's old method finished: refused, and not restored
    snapshots = StageSnapshots(tmp_path / "shared", ("b",))
    WorkFolder(tmp_path / "out", before, restart=False, snapshots=snapshots)
    work_dir = tmp_path / ".out.work"
    for name in "ab":
        (work_dir / f"{name}.done").write_text("")
    snapshots.save(work_dir, "b", before["b"])
    with pytest.raises(ReconstructionError, match="'b' stage ran with other settings, on another scene or with an "
                                                  "older version of the stage"):
        WorkFolder(tmp_path / "out", after, restart=False)
    assert WorkFolder(tmp_path / "other", after, restart=False, snapshots=snapshots).restored is None
    assert WorkFolder(tmp_path / "third", before, restart=False, snapshots=snapshots).restored == "b"
