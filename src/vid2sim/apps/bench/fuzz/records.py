"""Resumable case records: one JSON line per finished case in ``OUT/<section>.jsonl``.

A long campaign (a thousand simulations, fifty kills) is run in chunks: every case appends its record when it
finishes (one ``write`` of one line, flushed and synced), so a campaign stopped for any reason resumes with the
cases it has not recorded. A last line cut short by a kill is ignored on reading.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable


def read_records(path: str | Path) -> dict[int, dict[str, Any]]:
    """The records of ``path`` by case index (``record["index"]``); an unfinished last line is skipped."""
    path = Path(path)
    out: dict[int, dict[str, Any]] = {}
    if not path.is_file():
        return out
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and isinstance(record.get("index"), int):
            out[record["index"]] = record
    return out


class RecordFile:
    """Appends records to ``path`` (created with its folder), one synced line each."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = None if path is None else Path(path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # a line cut short by a kill would glue onto the next record: start on a fresh line
            if self.path.is_file() and self.path.stat().st_size and not self.path.read_bytes().endswith(b"\n"):
                with open(self.path, "ab") as f:
                    f.write(b"\n")

    def add(self, record: dict[str, Any]) -> None:
        if self.path is None:
            return
        line = (json.dumps(record, default=str) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)


def todo(indices: Iterable[int], done: dict[int, Any]) -> list[int]:
    """The indices not yet recorded."""
    return [i for i in indices if i not in done]
