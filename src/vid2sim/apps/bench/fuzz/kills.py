"""Kills and resumes: a long command SIGKILLed at a random moment, then run again, must end with the same
result as a run that was never interrupted, and its output must never look finished while it is not.

Each command runs at a toy size, in a fresh interpreter (``python -m vid2sim``: a real SIGKILL, no clean-up):

| command | looks finished when | compared with the uninterrupted run |
|---|---|---|
| ``make-training-data`` (reduced truth, 2 × 2 draws, 16 px, 4 frames) | ``index.json`` ``complete`` | shards bit for
bit, ``index.json`` except its timings |
| ``train-predictor`` (6 steps on that data, checkpoint every 2) | ``predictor.pt`` exists | the final weights within
1e-5 (one torch thread) |

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

COMMANDS = ("make-training-data", "train-predictor")


def _argv(command: str, out: Path, data: Path | None, quick: bool = False) -> list[str]:
    if command == "make-training-data":
        n = "1" if quick else "2"
        # the reduced truth: deterministic from the seed (the FEM truth's tets come from fTetWild, which is not, so
        # a resumed run could not be compared with an uninterrupted one) and seconds instead of minutes
        return ["make-training-data", str(out), "--truth", "reduced", "--objects", n, "--draws", n, "--resolution",
                "16", "--frames", "4", "--workers", "1", "--threads", "1", "--quiet"]
    assert data is not None
    return ["train-predictor", str(data), str(out), "--steps", "6", "--batch-size", "2", "--eval-every", "2",
            "--image-size", "16", "--patch-size", "8", "--tubelet-size", "2", "--width", "32", "--layers", "1",
            "--heads", "1", "--val-fraction", "0.5", "--quiet"]


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


def looks_finished(command: str, out: Path) -> bool:
    """Whether ``out`` claims to be a finished output of ``command``."""
    if command == "make-training-data":
        try:
            return bool(json.loads((out / "index.json").read_text()).get("complete"))
        except (OSError, ValueError):
            return False
    return (out / "predictor.pt").is_file()


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
    import torch

    pa, pb = (torch.load(p / "predictor.pt", map_location="cpu", weights_only=True) for p in (a, b))
    sa, sb = pa["state_dict"], pb["state_dict"]
    if sorted(sa) != sorted(sb):
        return False, "different parameters"
    worst = max(float((sa[k].double() - sb[k].double()).abs().max()) for k in sa) if sa else 0.0
    return worst <= 1e-5, f"largest weight difference {worst:.3g}"


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
            ref: dict[str, tuple[Path, float]] = {}
            rc, secs, err = _run_to_end(_argv("make-training-data", root / "ref_data", None, config.quick),
                                         config.threads, limit)
            if rc != 0:
                raise RuntimeError(f"the uninterrupted make-training-data failed: {err[-1500:]}")
            ref["make-training-data"] = (root / "ref_data", secs)
            commands = COMMANDS if not config.quick else ("make-training-data",)
            if "train-predictor" in commands:
                rc, secs, err = _run_to_end(_argv("train-predictor", root / "ref_train", root / "ref_data"),
                                            config.threads, limit)
                if rc != 0:
                    raise RuntimeError(f"the uninterrupted train-predictor failed: {err[-1500:]}")
                ref["train-predictor"] = (root / "ref_train", secs)
            for i in todo:
                rng = np.random.default_rng([config.seed + i, 5301])
                command = commands[int(rng.integers(len(commands)))]
                ref_out, ref_secs = ref[command]
                out = root / f"case{i}"
                argv = _argv(command, out, root / "ref_data", config.quick)
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
