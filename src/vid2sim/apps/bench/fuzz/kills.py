"""Kills and resumes: a long command SIGKILLed at a random moment, then run again, must end with the same
result as a run that was never interrupted, and its output must never look finished while it is not.

Each command runs at a toy size, in a fresh interpreter (``python -m vid2sim``: a real SIGKILL, no clean-up):

| command | looks finished when | compared with the uninterrupted run |
|---|---|---|
| ``make-training-data`` (reduced truth, 2 × 2 draws, 16 px, 4 frames) | ``index.json`` ``complete`` | shards bit for
bit, ``index.json`` except its timings |
| ``train-predictor`` (6 steps on that data, checkpoint every 2) | ``predictor.pt`` exists | the final weights within
1e-5 (one torch thread) |
| ``make-benchmark`` (2 scenes, 4 views at 40², 6 frames, linear tets reused with ``--tets-from``) | ``index.json``
``complete`` | every file bit for bit but the wall-clock times (in JSON and ``fem_result.npz``) |
| ``reconstruct`` (a scene of that suite, the demo's tiny settings, no report) | ``asset.json`` exists | every
file bit for bit but ``log.json`` (timings) |
| ``bench suite`` (that suite, the same settings) | ``suite.json`` exists | the assets as ``reconstruct``'s; the
evaluations and ``suite.json`` but their seconds and paths; the reports exist |
| ``import-capture`` (the capture twin of a scene of that suite) | ``scene.json`` exists | every file bit for bit but
``capture_report.json``'s seconds |

fTetWild's tets differ run to run, so the suite every case starts from is made once per campaign, and
``make-benchmark``'s cases reuse its tets (``--tets-from``), which makes them deterministic.

Case i draws the command and the moment (uniform between 0.3 s and the uninterrupted run's duration) from
``seed + i``. Two processes on one output (:mod:`vid2sim.runtime.locks`) are checked on every other case: while
the command runs, a second one on the same output must stop with exit code 2 and a line naming the first (the
kill then comes once that second one has ended, or at the drawn moment if later).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from vid2sim.runtime.locks import lock_path, read_owner

COMMANDS = ("make-training-data", "train-predictor", "make-benchmark", "reconstruct", "bench suite", "import-capture")
#: the toy suite of make-benchmark (and the input of reconstruct, bench suite and import-capture)
_SUITE_FLAGS = ["--n", "2", "--preset", "small", "--views", "4", "--held-out-views", "1", "--resolution", "40",
                "--frames", "6", "--observed-frames", "5", "--substeps", "4", "--element-order", "1", "--threads",
                "1", "--quiet"]


def _argv(command: str, out: Path, root: Path, quick: bool = False) -> list[str]:
    """The command line of ``command`` writing ``out``; its inputs are the campaign's in ``root`` (:func:`_inputs`)."""
    if command == "make-training-data":
        n = "1" if quick else "2"
        # the reduced truth: deterministic from the seed (the FEM truth's tets come from fTetWild, which is not, so
        # a resumed run could not be compared with an uninterrupted one) and seconds instead of minutes
        return ["make-training-data", str(out), "--truth", "reduced", "--objects", n, "--draws", n, "--resolution",
                "16", "--frames", "4", "--workers", "1", "--threads", "1", "--quiet"]
    if command == "train-predictor":
        return ["train-predictor", str(root / "ref_data"), str(out), "--steps", "6", "--batch-size", "2",
                "--eval-every", "2", "--image-size", "16", "--patch-size", "8", "--tubelet-size", "2", "--width",
                "32", "--layers", "1", "--heads", "1", "--val-fraction", "0.5", "--quiet"]
    if command == "make-benchmark":
        return ["make-benchmark", str(out), "--tets-from", str(root / "suite"), *_SUITE_FLAGS]
    if command == "reconstruct":
        return ["reconstruct", str(root / "suite" / "scene_000"), str(out), "--config", str(root / "tiny.json"),
                "--threads", "1", "--quiet", "--no-report"]
    if command == "bench suite":
        return ["bench", "suite", str(root / "suite"), str(out), "--config", str(root / "tiny.json"), "--threads",
                "1", "--quiet"]
    if command == "import-capture":
        return ["import-capture", str(root / "capture"), str(out), "--downscale", "2", "--every", "3", "--threads",
                "1", "--quiet", "--overwrite"]
    raise ValueError(f"unknown command {command!r}")


def _inputs(root: Path, commands: tuple[str, ...], threads: int, limit: float) -> None:
    """The inputs the commands read, made once in ``root``: the toy suite (fresh tets), the tiny reconstruction
    settings and the capture twin of the suite's first scene."""
    if not {"make-benchmark", "reconstruct", "bench suite", "import-capture"} & set(commands):
        return
    from vid2sim.apps.demo import TINY
    from vid2sim.reconstruct.config import ReconstructConfig
    from vid2sim.runtime import config as configs

    (root / "tiny.json").write_text(json.dumps(configs.to_dict(configs.merge(ReconstructConfig(), TINY))))
    steps = [["make-benchmark", str(root / "suite"), *_SUITE_FLAGS],
             ["make-capture", str(root / "suite" / "scene_000"), str(root / "capture"), "--threads", "1", "--quiet"]]
    for argv in steps:
        rc, _, err = _run_to_end(argv, threads, limit)
        if rc != 0:
            raise RuntimeError(f"making the campaign's input with `vid2sim {' '.join(argv[:2])}` failed: {err[-1500:]}")


def _wait_for_owner(proc: subprocess.Popen, out: Path, timeout: float) -> bool:
    """Whether ``proc`` came to own ``out``'s lock file (:func:`vid2sim.runtime.locks.lock_path`) within
    ``timeout`` seconds while running (False: it exited first or never took it)."""
    path = lock_path(out)
    t0 = time.perf_counter()
    while proc.poll() is None and time.perf_counter() - t0 < timeout:
        if read_owner(path).get("pid") == proc.pid:
            return True
        time.sleep(0.02)
    return False


def _env(threads: int) -> dict[str, str]:
    src = str(Path(__file__).resolve().parents[4])  # the vid2sim package's folder (src/)
    return {**os.environ, "PYTHONPATH": os.pathsep.join([src, os.environ.get("PYTHONPATH", "")]),
            "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


def _start(argv: list[str], threads: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vid2sim", *argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=_env(threads), start_new_session=True)


#: the file whose presence says an output is finished, for the commands that write one at the end
_FINISHED = {"train-predictor": "predictor.pt", "reconstruct": "asset.json", "bench suite": "suite.json",
             "import-capture": "scene.json"}


def looks_finished(command: str, out: Path) -> bool:
    """Whether ``out`` claims to be a finished output of ``command``."""
    if command in ("make-training-data", "make-benchmark"):
        try:
            return bool(json.loads((out / "index.json").read_text()).get("complete"))
        except (OSError, ValueError):
            return False
    return (out / _FINISHED[command]).is_file()


def _wall_clock(key: str) -> bool:
    return key in ("seconds", "timing", "timings", "timings_seconds") or key.endswith("_seconds") \
        or key.startswith("wall_time")


def _core(obj: Any, a: str, b: str) -> Any:
    """A JSON value without its wall-clock fields, the output folder ``a``'s path written as ``b``'s."""
    if isinstance(obj, dict):
        return {k: _core(v, a, b) for k, v in obj.items() if not _wall_clock(k)}
    if isinstance(obj, list):
        return [_core(v, a, b) for v in obj]
    return obj.replace(a, b) if isinstance(obj, str) else obj


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True)


def _same_npz(x: Path, y: Path) -> bool:
    """Two ``.npz`` files hold the same arrays but their wall-clock times (a JSON string array included)."""
    with np.load(x, allow_pickle=False) as p, np.load(y, allow_pickle=False) as q:
        if sorted(p.files) != sorted(q.files):
            return False
        for k in p.files:
            if _wall_clock(k):
                continue
            u, v = p[k], q[k]
            if u.dtype.kind == "U" and u.ndim == 0 and v.dtype.kind == "U" and v.ndim == 0:
                try:
                    if _canonical(_core(json.loads(str(u)), "", "")) != _canonical(_core(json.loads(str(v)), "", "")):
                        return False
                    continue
                except ValueError:
                    pass
            if u.shape != v.shape or u.dtype != v.dtype or not np.array_equal(u, v, equal_nan=u.dtype.kind in "fc"):
                return False
    return True


def same_tree(a: Path, b: Path, skip: tuple[str, ...] = ()) -> tuple[bool, str]:
    """Whether the folders ``a`` and ``b`` hold the same files with the same content: bit for bit, but JSON files
    and ``.npz`` archives without their wall-clock times (and ``a``'s path read as ``b``'s); files named in
    ``skip`` (their name, or a folder they are in) must only exist in both."""
    files = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
    other = sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
    if files != other:
        return False, f"different files: {sorted(set(files) ^ set(other))[:4]}"
    for rel in files:
        if any(part in skip for part in Path(rel).parts):
            continue
        x, y = a / rel, b / rel
        if rel.endswith(".json"):  # compared as canonical text: NaN (which scene files may hold) equals NaN there
            same = _canonical(_core(json.loads(x.read_text()), str(a), str(b))) == \
                _canonical(_core(json.loads(y.read_text()), str(b), str(b)))
        elif rel.endswith(".npz"):
            same = _same_npz(x, y)
        else:
            same = x.read_bytes() == y.read_bytes()
        if not same:
            return False, f"{rel} differs"
    return True, f"{len(files)} files equal"


def same_result(command: str, a: Path, b: Path) -> tuple[bool, str]:
    """Whether the outputs ``a`` and ``b`` of ``command`` are the same result (module docstring)."""
    if command == "make-training-data":
        shards = sorted(p.name for p in a.glob("*.npz"))
        if shards != sorted(p.name for p in b.glob("*.npz")):
            return False, "different shard files"
        for name in shards:
            if (a / name).read_bytes() != (b / name).read_bytes():
                return False, f"shard {name} differs"
        ia, ib = (json.loads((p / "index.json").read_text()) for p in (a, b))

        def core(d: dict) -> dict:  # all but the wall-clock timings
            return {
                "config": d.get("config"),
                "complete": d.get("complete"),
                "shards": [
                    {k: v for k, v in e.items() if k not in ("seconds", "timings")} for e in d.get("shards", [])
                ],
            }

        if core(ia) != core(ib):
            return False, "index.json differs beyond its timings"
        return True, f"{len(shards)} shards bit for bit"
    if command == "train-predictor":
        import torch

        pa, pb = (torch.load(p / "predictor.pt", map_location="cpu", weights_only=True) for p in (a, b))
        sa, sb = pa["state_dict"], pb["state_dict"]
        if sorted(sa) != sorted(sb):
            return False, "different parameters"
        worst = max(float((sa[k].double() - sb[k].double()).abs().max()) for k in sa) if sa else 0.0
        return worst <= 1e-5, f"largest weight difference {worst:.3g}"
    # a run's own timings, and the reports' pages and videos (they print times and dates)
    skip = {"reconstruct": ("log.json",), "bench suite": ("log.json", "report")}.get(command, ())
    return same_tree(a, b, skip)


def _run_to_end(argv: list[str], threads: int, timeout: float) -> tuple[int, float, str]:
    t0 = time.perf_counter()
    proc = _start(argv, threads)
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return -9, time.perf_counter() - t0, "timed out"
    return proc.returncode, time.perf_counter() - t0, err


def run(config, records_path: str | Path | None, progress: bool = False) -> dict[str, Any]:
    """``config.kills`` kill-and-resume cases (resumed from ``records_path``); returns the figures."""
    from vid2sim.apps.bench.fuzz.records import RecordFile, read_records

    done = read_records(records_path) if records_path is not None else {}
    sink = RecordFile(records_path)
    results = dict(done)
    todo = [i for i in range(config.kills) if i not in done]
    limit = max(config.timeout, 600.0)
    if todo:
        with tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-kills-") as tmp:
            root = Path(tmp)
            commands = COMMANDS if not config.quick else ("make-training-data",)
            _inputs(root, commands, config.threads, limit)
            ref: dict[str, tuple[Path, float]] = {}
            for command in commands:  # train-predictor reads ref_data: make-training-data comes first
                name = "ref_data" if command == "make-training-data" else "ref_" + command.replace(" ", "_")
                rc, secs, err = _run_to_end(_argv(command, root / name, root, config.quick), config.threads, limit)
                if rc != 0:
                    raise RuntimeError(f"the uninterrupted {command} failed: {err[-1500:]}")
                ref[command] = (root / name, secs)
            for i in todo:
                rng = np.random.default_rng([config.seed + i, 5301])
                command = commands[int(rng.integers(len(commands)))]
                ref_out, ref_secs = ref[command]
                out = root / f"case{i}"
                argv = _argv(command, out, root, config.quick)
                moment = float(rng.uniform(0.3, max(0.6, ref_secs)))
                proc = _start(argv, config.threads)
                second = None
                if i % 2 == 0:  # every other case: a second process on the same output first (it takes a few s)
                    # once the first holds the lock, it is paused while the second runs: the second must find it
                    # holding the lock however long the second takes to start (seconds on a loaded machine, longer
                    # than a quick case's whole run); then it goes on and is killed at the drawn moment or at once
                    t_start = time.perf_counter()
                    if _wait_for_owner(proc, out, 60.0):
                        os.killpg(proc.pid, signal.SIGSTOP)
                        try:
                            second = _run_to_end(argv, config.threads, 120.0)
                        finally:
                            os.killpg(proc.pid, signal.SIGCONT)
                    time.sleep(max(0.0, moment - (time.perf_counter() - t_start)))
                else:  # the others are killed at the drawn moment exactly
                    time.sleep(moment)
                killed = proc.poll() is None
                premature = False
                if killed:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                    # an output that claims to be finished must be the finished result (a kill can come after the
                    # last file is in place and before the process exits)
                    premature = looks_finished(command, out) and not same_result(command, ref_out, out)[0]
                rc, _, err = _run_to_end(argv, config.threads, limit)
                same, why = same_result(command, ref_out, out) if rc == 0 else (False, f"rerun failed: {err[-500:]}")
                lock_ok = None
                if second is not None and killed:
                    lines = [ln for ln in second[2].splitlines() if ln.strip()]
                    lock_ok = second[0] == 2 and len(lines) == 1 and "another vid2sim process" in lines[0]
                record = {"index": i, "seed": config.seed + i, "command": command, "moment": round(moment, 2),
                          "killed": killed, "looked_finished_when_killed": premature, "resumed_equal": same,
                          "why": why, "second_process_refused": lock_ok}
                results[i] = record
                sink.add(record)
                shutil.rmtree(out, ignore_errors=True)
                if progress:
                    print(f"kills {len(results)}/{config.kills}: {command} at {moment:.2f} s "
                          f"(killed {killed}): equal {same} ({why}); lock {lock_ok}", flush=True)
    records = [results[i] for i in sorted(results) if i < config.kills]
    killed = [r for r in records if r["killed"]]
    locks = [r["second_process_refused"] for r in records if r["second_process_refused"] is not None]
    return {"cases": len(records), "killed": len(killed),
            "resumed_equal": sum(1 for r in killed if r["resumed_equal"]),
            "looked_finished_while_not": sum(1 for r in killed if r["looked_finished_when_killed"]),
            "second_process_refused": f"{sum(locks)} of {len(locks)}",
            "by_command": {c: sum(1 for r in killed if r["command"] == c) for c in COMMANDS},
            "problems": [r for r in records if not r["resumed_equal"] or r["looked_finished_when_killed"]
                         or r["second_process_refused"] is False][:20]}
