"""Running one fuzz case in a child process with a time limit, and judging what it printed.

:func:`run_in_child` forks the current process (which has imported vid2sim and torch once, so a case starts in
milliseconds instead of the two seconds of a fresh interpreter), runs a callable there with its standard output
and error going to files, and kills the child's whole process group when it runs past its time limit. The child
behaves as ``python -m vid2sim`` would: :func:`cli_call` runs :func:`vid2sim.cli.main`; an exception that
escapes is printed as Python prints it (a traceback, exit code 1).

The parent must not have run torch on several threads before forking (an OpenMP pool does not survive a fork):
the campaign keeps torch on one thread in the parent (``--threads 1``) or runs its torch work in spawned workers.
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence


@dataclass
class ChildResult:
    """What a child did: exit code (None when killed for running too long), its output, its wall time."""

    returncode: int | None
    stdout: str
    stderr: str
    seconds: float

    @property
    def timed_out(self) -> bool:
        return self.returncode is None

    def error_lines(self) -> list[str]:
        """The non-empty lines of the standard error."""
        return [line for line in self.stderr.splitlines() if line.strip()]


def run_in_child(fn: Callable[[], int], timeout: float, cwd: str | Path | None = None,
                 env: dict[str, str] | None = None) -> ChildResult:
    """Run ``fn()`` (returning an exit code) in a forked child; kill its process group once it has used
    ``timeout`` s of CPU (or :data:`WALL_FACTOR` × ``timeout`` s of wall time)."""
    with tempfile.TemporaryDirectory(prefix="vid2sim-fuzz-child-") as tmp:
        out_path, err_path = Path(tmp) / "stdout", Path(tmp) / "stderr"
        sys.stdout.flush()
        sys.stderr.flush()
        t0 = time.perf_counter()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            code = 1
            try:
                os.setpgid(0, 0)
                for fd, path in ((1, out_path), (2, err_path)):
                    f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                    os.dup2(f, fd)
                    os.close(f)
                if cwd is not None:
                    os.chdir(cwd)
                if env:
                    os.environ.update(env)
                try:
                    code = int(fn() or 0)
                except SystemExit as exc:
                    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                except BaseException:  # as the interpreter does for an uncaught exception
                    traceback.print_exc()
                    code = 1
            finally:
                try:
                    sys.stdout.flush()
                    sys.stderr.flush()
                finally:
                    os._exit(code)
        status = None
        while True:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = st
                break
            wall = time.perf_counter() - t0
            # the limit is on CPU time (a loaded machine slows a case down without making it hang), with a wall
            # limit of WALL_FACTOR × the limit for a child that waits without computing (a deadlock)
            if wall > WALL_FACTOR * timeout or (wall > timeout and _cpu_seconds(pid) > timeout):
                _kill_group(pid)
                os.waitpid(pid, 0)
                break
            time.sleep(0.01 if wall < 1 else 0.1)
        seconds = time.perf_counter() - t0
        _kill_group(pid)  # grandchildren left behind (a process pool) go with it
        code = None if status is None else (os.waitstatus_to_exitcode(status))
        read = lambda p: p.read_text(encoding="utf-8", errors="replace") if p.exists() else ""  # noqa: E731
        return ChildResult(code, read(out_path), read(err_path), seconds)


#: a child may run this many times its time limit in wall time while its CPU time stays under the limit
WALL_FACTOR = 10.0


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a running process (Linux /proc; elsewhere its wall time counts)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("inf")


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def cli_call(argv: Sequence[str]) -> Callable[[], int]:
    """A child body running ``vid2sim ARGV`` (one torch thread)."""

    def call() -> int:
        import torch

        torch.set_num_threads(1)
        from vid2sim.cli import main

        return main(list(argv))

    return call


def reader_call(what: str, fn: Callable[[], Any]) -> Callable[[], int]:
    """A child body for a reader without a command of its own (e.g. glTF): as the command line would, an
    :class:`~vid2sim.runtime.errors.InputError` or ``OSError`` is one line and exit code 2; anything else escapes
    (a traceback, exit code 1)."""

    def call() -> int:
        from vid2sim.runtime.errors import InputError

        try:
            fn()
        except (InputError, OSError) as exc:
            print(f"vid2sim {what}: error: {exc}", file=sys.stderr)
            return 2
        return 0

    return call


def judge(result: ChildResult, names: Sequence[str]) -> tuple[str, str]:
    """(verdict, why) of a case expected to fail cleanly or succeed.

    Verdicts: ``clean`` (exit code 2, no traceback, one line ``vid2sim …: error: …`` naming one of ``names``),
    ``accepted`` (exit code 0: the file was still usable), ``vague`` (an error that names none of ``names``),
    ``noisy`` (other lines before the error line), ``multiline`` (the error continued on more lines), ``bug`` (a
    traceback or any other exit code), ``hang`` (killed at the time limit)."""
    if result.timed_out:
        return "hang", f"still running after {result.seconds:.1f} s"
    lines = result.error_lines()
    if result.returncode == 0:
        return "accepted", ""
    if "Traceback (most recent call last)" in result.stderr or result.returncode != 2:
        tail = " | ".join(lines[-3:])
        return "bug", f"exit code {result.returncode}: {tail[-600:]}"
    first = next((k for k, line in enumerate(lines) if line.startswith("vid2sim") and ": error: " in line), None)
    if first is None:
        return "bug", f"exit code 2 without an error line: {' | '.join(lines[-3:])[-600:]}"
    message = " | ".join(lines[first:])
    if not any(n and n in message for n in names):
        return "vague", message[:600]
    if first > 0:  # warnings or progress before the error line
        return "noisy", " | ".join(lines[:3])[-600:]
    if len(lines) > 1:  # a message of several lines (a scene folder's list of problems)
        return "multiline", message[:600]
    return "clean", lines[0][:600]
