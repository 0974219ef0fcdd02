"""One writer per output folder: a lock file beside the folder, holding its owner's pid.

Every long command (``reconstruct``, ``make-benchmark``, ``make-training-data``, ``train-predictor``, ``bench
suite``, ``simulate``, ...) takes :func:`output_lock` on its output before any work. A second process given the
same output stops at once with one line naming the owner (:class:`OutputLocked`, exit code 2), instead of both
writing the same files and each resuming from the other's half-written work.

The lock is the file ``.NAME.lock`` in the output's parent folder (beside the output, so that it neither
creates the output early nor lands inside a folder that is written elsewhere and renamed into place). It holds
``{"pid", "host", "command", "started"}`` and an exclusive ``flock`` for as long as the owner runs. The kernel
drops the ``flock`` when the owner dies however it dies (SIGKILL included), so a lock left behind by a killed
run is taken over by the next one: a lock whose ``flock`` is free is stale whatever its pid says. The file is
removed when the owner finishes.

A file system without ``flock`` (some network file systems) raises ``OSError`` when locking; the lock then
falls back to the pid alone: taken over when the recorded pid is not alive on this host.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time
from pathlib import Path
from typing import Iterator

from vid2sim.runtime.errors import InputError

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows: the pid fallback alone
    fcntl = None  # type: ignore[assignment]


class OutputLocked(InputError):
    """Another live process is writing the same output folder (the message names its pid and command)."""


def lock_path(output: str | Path) -> Path:
    """The lock file of ``output``: ``.NAME.lock`` beside it."""
    output = Path(output).absolute()
    return output.parent / f".{output.name}.lock"


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid exists on this machine (a zombie counts as gone)."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    try:  # a zombie (killed, not yet reaped by its parent) holds nothing
        with open(f"/proc/{pid}/stat", encoding="utf-8") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def read_owner(path: str | Path) -> dict:
    """The owner record of a lock file ({} when missing or unreadable)."""
    try:
        value = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def _describe(owner: dict) -> str:
    pid = owner.get("pid", "?")
    what = f"pid {pid}"
    if owner.get("host") and owner.get("host") != socket.gethostname():
        what += f" on {owner['host']}"
    if owner.get("command"):
        what += f" ({owner['command']}"
        if isinstance(owner.get("started"), (int, float)):
            what += f", started {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(owner['started']))}"
        what += ")"
    return what


@contextlib.contextmanager
def output_lock(output: str | Path, command: str) -> Iterator[Path]:
    """Hold the lock of ``output`` for the ``with`` block; yields the lock file's path.

    Raises:
        OutputLocked: a live process holds it (the message names it and the lock file).
    """
    path = lock_path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"pid": os.getpid(), "host": socket.gethostname(), "command": command, "started": time.time()}
    fd = _acquire(path, Path(output))
    try:
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(record) + "\n").encode())
        os.fsync(fd)
        yield path
    finally:
        with contextlib.suppress(OSError):
            if os.path.exists(path) and os.stat(path).st_ino == os.fstat(fd).st_ino:
                os.unlink(path)
        os.close(fd)


def _acquire(path: Path, output: Path) -> int:
    """Open and lock ``path``; returns the descriptor (the file is the one at ``path`` when it returns)."""
    for _ in range(50):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            locked = _flock(fd)
            if locked is None:  # no flock here: the pid decides
                owner = read_owner(path)
                pid = owner.get("pid")
                if pid not in (None, os.getpid()) and owner.get("host") in (None, socket.gethostname()) \
                        and pid_alive(pid):
                    raise OutputLocked(_message(output, path, owner))
            elif not locked:
                owner = read_owner(path)
                raise OutputLocked(_message(output, path, owner))
            # the file may have been removed (a finishing owner) or replaced since we opened it: retry then
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)
    raise OutputLocked(f"{output}: could not take the lock {path} (it keeps changing)")


def _flock(fd: int) -> bool | None:
    """True: locked; False: another process holds it; None: this file system has no flock."""
    if fcntl is None:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return False
        return None
    return True


def _message(output: Path, path: Path, owner: dict) -> str:
    return (f"{output}: another vid2sim process is writing this output: {_describe(owner)}; wait for it to finish "
            f"or stop it, or choose another output (lock file {path}, taken over automatically once that process "
            "has ended)")
