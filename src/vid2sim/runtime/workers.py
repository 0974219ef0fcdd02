"""Local worker processes for the data generators (training data, FEM ground truth).

:func:`process_pool` gives a ``ProcessPoolExecutor`` whose workers are fresh interpreters (``spawn``: no
inherited torch or OpenMP thread state) and leave when the process that started them is gone. Without that, a
generator stopped by ``kill`` (SIGTERM and SIGKILL skip Python's clean-up) left its workers running their
queued tasks for many minutes, taking the cores from whatever ran next.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor

#: seconds between a worker's checks that its parent is alive
PARENT_CHECK_SECONDS = 1.0


def _watch_parent(parent: int, every: float) -> None:
    while True:
        time.sleep(every)
        if os.getppid() != parent:  # re-parented: the starting process has exited
            os._exit(1)


def _start_parent_watch(parent: int, every: float) -> None:
    """Worker initialiser: a daemon thread that ends the worker once ``parent`` is no longer its parent."""
    threading.Thread(target=_watch_parent, args=(parent, every), daemon=True, name="vid2sim-parent-watch").start()


def process_pool(workers: int, every: float = PARENT_CHECK_SECONDS) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes that exit within ``every`` seconds of this process's end."""
    import multiprocessing as mp

    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                               initializer=_start_parent_watch, initargs=(os.getpid(), every))
