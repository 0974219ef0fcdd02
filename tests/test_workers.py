"""Worker processes of the data generators leave when the process that started them is killed."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

PARENT = '''
import sys, time
from vid2sim.runtime.workers import process_pool

def work(path):
    import os, time
    with open(path + ".tmp", "w") as f:
        f.write(str(os.getpid()))
    os.replace(path + ".tmp", path)
    time.sleep(300)

if __name__ == "__main__":
    pool = process_pool(1, every=0.2)
    pool.submit(work, sys.argv[1])
    time.sleep(300)
'''


def _running(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_killed_generator_takes_its_workers_with_it(tmp_path):
    script, pid_file = tmp_path / "parent.py", tmp_path / "worker.pid"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script), str(pid_file)])
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists():
            assert time.monotonic() < deadline, "the worker never started"
            assert parent.poll() is None, "the parent exited early"
            time.sleep(0.1)
        worker = int(pid_file.read_text())
        assert _running(worker)
        parent.kill()  # SIGKILL: no clean-up in the parent at all
        parent.wait()
        deadline = time.monotonic() + 15
        while _running(worker):
            assert time.monotonic() < deadline, f"worker {worker} outlived its parent by 15 s"
            time.sleep(0.1)
    finally:
        if parent.poll() is None:
            parent.kill()
        if pid_file.exists() and _running(int(pid_file.read_text())):
            os.kill(int(pid_file.read_text()), 9)
