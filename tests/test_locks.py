"""One writer per output folder (vid2sim.runtime.locks): a second process stops with one line naming the first;
a lock left by a killed process is taken over; the command line holds the lock of every long command."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from vid2sim.runtime.locks import (
    OutputLocked,
    lock_path,
    output_lock,
    pid_alive,
    read_owner,
)

HOLD = textwrap.dedent("""
    import sys, time
    from vid2sim.runtime.locks import output_lock
    with output_lock(sys.argv[1], "holder"):
        print("held", flush=True)
        time.sleep(60)
""")


def _holder(out: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_and_a_dead_owners_lock_is_taken_over(tmp_path):
    out = tmp_path / "asset"
    proc = _holder(out)
    try:
        owner = read_owner(lock_path(out))
        assert owner["pid"] == proc.pid and owner["command"] == "holder"
        with pytest.raises(OutputLocked, match=rf"pid {proc.pid} \(holder"):
            with output_lock(out, "second"):
                pass
        assert not out.exists()  # the lock lives beside the output, which it does not create
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert lock_path(out).exists() and not pid_alive(proc.pid)  # a killed owner leaves its file behind ...
    with output_lock(out, "third") as path:  # ... and the next run takes it over
        assert read_owner(path)["pid"] == os.getpid()
    assert not lock_path(out).exists()  # released on exit


def test_a_stale_lock_file_with_a_live_foreign_pid_but_no_flock_is_taken_over(tmp_path):
    """The flock decides, not the pid written in the file: a pid can be reused by an unrelated process."""
    out = tmp_path / "data"
    lock_path(out).write_text(json.dumps({"pid": 1, "host": "x", "command": "old"}))
    with output_lock(out, "new") as path:
        assert read_owner(path)["command"] == "new"


def test_the_command_line_refuses_a_second_process_on_the_same_output(tmp_path, capsys):
    from vid2sim.cli import main

    out = tmp_path / "scene"
    proc = _holder(out)
    try:
        t0 = time.perf_counter()
        code = main(["make-scene", str(out), "--frames", "2", "--resolution", "8", "--views", "1"])
        assert time.perf_counter() - t0 < 30  # stopped before any work
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert f"pid {proc.pid}" in err[0] and "another vid2sim process is writing this output" in err[0]
    assert not out.exists()
