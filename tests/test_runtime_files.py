"""vid2sim.runtime.files's shared helpers: the JSON-ready copy of a record (both ways of treating NaN, byte for byte
as the two helpers it replaced wrote them) and the folder written whole or not at all."""

from __future__ import annotations

import json
import math
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vid2sim.runtime.files import (
    check_output_folder,
    holds_files,
    is_temp_file,
    jsonable,
    remove_leftovers,
    remove_temp_files,
    write_folder_atomic,
)
from vid2sim.scene.capture import jsonify

RECORD = {"a": (1, 2.5, np.float32(0.25)), 3: [np.int64(7), np.bool_(True), None, "x"], "nan": float("nan"),
          "inf": -math.inf, "np_nan": np.float64("nan"), "nested": {"t": ((1, 2), [3, (4,)])},
          "array": np.array([[1.0, np.nan], [np.inf, 2.0]]), "ints": np.arange(3, dtype=np.int32)}


def test_jsonable_turns_non_finite_floats_to_null_by_default_as_the_capture_importer_wrote_them():
    out = jsonable(RECORD)
    assert jsonify.jsonable is jsonable  # the importer's name for it
    text = json.dumps(out, indent=2, allow_nan=False)  # standard JSON: no NaN left
    assert json.loads(text) == {
        "a": [1, 2.5, 0.25], "3": [7, True, None, "x"], "nan": None, "inf": None, "np_nan": None,
        "nested": {"t": [[1, 2], [3, [4]]]}, "array": [[1.0, None], [None, 2.0]], "ints": [0, 1, 2]}
    assert type(out["a"][2]) is float and type(out["3"][0]) is int and type(out["3"][1]) is bool


def test_jsonable_keeps_non_finite_floats_when_asked_as_the_synthetic_scenes_wrote_them():
    record = {k: v for k, v in RECORD.items() if not isinstance(v, np.ndarray)}  # the scenes' records hold none
    out = jsonable(record, nan_to_null=False)
    text = json.dumps(out, indent=2)
    assert '"nan": NaN' in text and '"inf": -Infinity' in text and '"np_nan": NaN' in text
    assert text == json.dumps(_scenes_jsonable_before(record), indent=2)  # byte for byte as before
    assert json.dumps(jsonable(RECORD), indent=2) == json.dumps(_importer_jsonable_before(RECORD), indent=2)
    assert math.isnan(jsonable(RECORD["array"], nan_to_null=False)[0][1])  # arrays: lists, NaN kept


def _scenes_jsonable_before(obj):
    """vid2sim.synthetic.scenes._jsonable as it was (tuples to lists, numpy scalars to Python numbers)."""
    if isinstance(obj, dict):
        return {str(k): _scenes_jsonable_before(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_scenes_jsonable_before(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _importer_jsonable_before(obj):
    """vid2sim.scene.capture.jsonify.jsonable as it was."""
    if isinstance(obj, dict):
        return {str(k): _importer_jsonable_before(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_importer_jsonable_before(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _importer_jsonable_before(obj.tolist())
    if isinstance(obj, np.generic):
        return _importer_jsonable_before(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def test_a_folder_is_written_whole_replacing_an_empty_or_an_old_one(tmp_path):
    out = tmp_path / "deep" / "out"

    def fill(folder, text):
        def write(staging):
            assert staging.parent == out.parent and staging.name.startswith(".out.making-")
            (staging / "a.txt").write_text(text)
        return write

    assert write_folder_atomic(out, fill(out, "one"), create=True) == out
    assert (out / "a.txt").read_text() == "one"
    mode = stat.S_IMODE(os.stat(out).st_mode)
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o777 & ~umask
    write_folder_atomic(out, fill(out, "two"), create=True)  # an existing folder is replaced
    assert (out / "a.txt").read_text() == "two" and sorted(p.name for p in out.parent.iterdir()) == ["out"]
    empty = tmp_path / "empty"
    empty.mkdir()

    def makes_it(staging):
        staging.mkdir()
        (staging / "b").write_text("b")

    write_folder_atomic(empty, makes_it)  # without create, write makes the folder
    assert (empty / "b").read_text() == "b"


def test_a_failed_folder_write_leaves_nothing_and_the_old_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep").write_text("old")

    def fails(staging):
        (staging / "half").write_text("x")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_folder_atomic(out, fails, create=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert [p.name for p in out.iterdir()] == ["keep"] and (out / "keep").read_text() == "old"


def test_a_new_folder_write_removes_what_a_killed_writer_left(tmp_path):
    """SIGKILL runs no clean-up: the staging and replaced folders a killed writer of the same target left beside it
    are removed when the next write starts (found by the kill campaign: a report's `.report.making-…` inside a
    resumed `bench suite` output); other hidden folders stay."""
    out = tmp_path / "out"
    left = [tmp_path / f".out.{tag}-0123456789ab" for tag in ("making", "old", "writing", "importing")]
    kept = [tmp_path / ".out.making-notahexname", tmp_path / ".other.making-0123456789ab", tmp_path / ".out.lock"]
    for p in left + kept[:2]:
        p.mkdir()
        (p / "half").write_text("x")
    kept[2].write_text("{}")
    write_folder_atomic(out, lambda staging: (staging / "a").write_text("a"), create=True)
    assert (out / "a").read_text() == "a"
    assert not any(p.exists() for p in left)
    assert all(p.exists() for p in kept)
    assert remove_leftovers(out) == []


def test_the_temporary_file_of_a_writer_killed_mid_file_is_recognised_and_removed(tmp_path):
    """A SIGKILLed ``write_file_atomic`` leaves its ``.NAME.<8 characters>.tmp``. A folder holding only that is
    as good as empty to a resumable command (the kill campaign found `make-training-data` killed while writing
    its first index.json refusing to resume: "not empty and holds no index.json"), and the next run removes it;
    other hidden files and a user's own ``.tmp`` files stay."""
    out = tmp_path / "data"
    out.mkdir()
    code = ("import sys, time\nfrom vid2sim.runtime.files import write_file_atomic\n"
            "def write(tmp):\n    open(tmp, 'w').write('{\"comp')\n    print('writing', flush=True)\n"
            "    time.sleep(60)\n"
            "write_file_atomic(sys.argv[1], write)\n")
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", code, str(out / "index.json")], stdout=subprocess.PIPE,
                            text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == "writing"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    left = list(out.iterdir())
    assert len(left) == 1 and is_temp_file(left[0]) and not (out / "index.json").exists()
    assert not holds_files(out) and not holds_files(tmp_path / "absent")
    (out / "sub").mkdir()
    nested = out / "sub" / ".object_000001.npz.ab_cd123.tmp"
    nested.write_bytes(b"PK")
    kept = [out / ".notes.tmp", out / ".x.toolong123.tmp", out / "x.abcdefgh.tmp", out / ".index.json.lock"]
    for p in kept:
        p.write_text("mine")
    assert holds_files(out)
    assert sorted(remove_temp_files(out)) == sorted([left[0], nested])
    assert all(p.exists() for p in kept) and not left[0].exists() and not nested.exists()


def test_an_output_folder_is_refused_when_it_is_a_file_or_holds_files_but_none_of_the_output(tmp_path) -> None:
    out = tmp_path / "out"
    check_output_folder(out, False, "index.json", "a benchmark")  # absent: fine
    out.mkdir()
    (out / ".index.json.abcd_123.tmp").write_text("{")  # a killed writer's leftover does not count
    check_output_folder(out, False, "index.json", "a benchmark")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"out is not empty and holds no index.json: refusing to write a "
                                              r"benchmark there"):
        check_output_folder(out, False, "index.json", "a benchmark")
    check_output_folder(out, True, "index.json", "a benchmark")  # the command's own output: a resume
    with pytest.raises(FileExistsError, match="notes.txt exists and is not a folder"):
        check_output_folder(out / "notes.txt", True, "index.json", "a benchmark")


def test_a_json_number_is_not_a_bool_and_a_finite_one_not_nan_or_inf() -> None:
    import json

    from vid2sim.runtime.jsonvalues import is_finite_number, is_number

    values = json.loads('[1, 2.5, -0.0, true, false, null, "3", [1], NaN, Infinity, -Infinity]')
    assert [is_number(v) for v in values] == [True, True, True, False, False, False, False, False, True, True, True]
    assert [is_finite_number(v) for v in values] == [True, True, True] + [False] * 8
