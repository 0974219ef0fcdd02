"""Files written whole or not at all, and JSON read with errors that name the file.

Every output vid2sim writes goes through :func:`write_json_atomic`, :func:`write_text_atomic` or
:func:`save_torch_atomic`: the data is written to a hidden temporary file beside the target and renamed onto it,
so a reader (or a run killed halfway) never sees half a file. The permissions are the umask's, as for a file
opened normally (``mkstemp`` would make it private). A folder is written whole the same way by
:func:`write_folder_atomic`, and :func:`jsonable` makes the JSON-ready copy of a record holding numpy values.
"""

from __future__ import annotations

import glob
import json
import math
import os
import pickle
import re
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from vid2sim.runtime.errors import InputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_file_atomic(path: str | Path, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp)`` (it writes the file at the path ``tmp``) on a temporary file beside ``path``, then rename
    it onto ``path``; returns the path. On any error the temporary file is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None:  # a full disk raises ENOSPC without a file name: say which file it was writing
            raise OSError(exc.errno, f"{exc.strerror or exc} (writing {path})") from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    return write_file_atomic(Path(path), lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def write_json_atomic(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    """Write ``obj`` as JSON (with a final newline) to ``path`` atomically; returns the path."""
    return write_text_atomic(path, json.dumps(obj, indent=indent) + "\n")


#: the name of the temporary file :func:`write_file_atomic` writes before renaming it onto ``NAME``:
#: ``.NAME.<8 characters mkstemp draws>.tmp``
_TEMP_FILE = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def is_temp_file(path: str | Path) -> bool:
    """Whether ``path`` is a file that :func:`write_file_atomic` left when its writer was killed mid-way (SIGKILL
    runs no clean-up): ``.NAME.<8 characters>.tmp``."""
    path = Path(path)
    return _TEMP_FILE.fullmatch(path.name) is not None and path.is_file() and not path.is_symlink()


def holds_files(folder: str | Path) -> bool:
    """Whether the folder ``folder`` holds anything but the temporary files of killed writers
    (:func:`is_temp_file`): a resumable command refuses to write into a folder that holds files and no output of
    its own, and a run killed while writing its first file left such a folder."""
    folder = Path(folder)
    return folder.is_dir() and any(not is_temp_file(p) for p in folder.iterdir())


def check_output_folder(folder: str | Path, holds_output: bool, output: str, what: str) -> None:
    """Refuse the output folder of a resumable command: FileExistsError when ``folder`` is a file, or a folder that
    holds files (:func:`holds_files`: the temporary files of killed writers do not count) but none of the command's
    own output (``holds_output`` False). ``output`` names that output and ``what`` what the command writes, for the
    message ("… is not empty and holds no {output}: refusing to write {what} there")."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder} exists and is not a folder")
    if not holds_output and holds_files(folder):
        raise FileExistsError(f"{folder} is not empty and holds no {output}: refusing to write {what} there")


def remove_temp_files(folder: str | Path) -> list[Path]:
    """Remove the temporary files killed writers left in ``folder`` and its subfolders (:func:`is_temp_file`).
    Call it when a resumable command starts on its output: the command holds the output's lock
    (:mod:`vid2sim.runtime.locks`), so no live writer owns them. A folder that does not exist holds none. Returns
    the files removed."""
    gone = [p for p in Path(folder).rglob(".*.tmp") if is_temp_file(p)]
    for p in gone:
        p.unlink(missing_ok=True)
    return gone


#: the tags of the hidden folders a folder writer stages beside its target (``.NAME.<tag>-<12 hex digits>``)
STAGING_TAGS = ("making", "old", "writing", "importing")


def remove_leftovers(path: str | Path) -> list[Path]:
    """Remove the hidden staging folders that writers killed mid-way (SIGKILL runs no clean-up) left beside the
    folder ``path``: ``.NAME.<tag>-<12 hex digits>`` for the :data:`STAGING_TAGS`. Call it when a new write of
    ``path`` starts: every command that writes a folder holds its output's lock (:mod:`vid2sim.runtime.locks`), so
    no live writer owns them then. Returns the folders removed."""
    path = Path(path)
    gone = []
    for tag in STAGING_TAGS:
        for p in path.parent.glob(f".{glob.escape(path.name)}.{tag}-*"):
            suffix = p.name.rsplit("-", 1)[-1]
            if len(suffix) == 12 and all(c in "0123456789abcdef" for c in suffix) and p.is_dir() \
                    and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
                gone.append(p)
    return gone


def write_folder_atomic(path: str | Path, write: Callable[[Path], None], create: bool = False) -> Path:
    """Call ``write(staging)`` (it fills the folder ``staging``) on a hidden folder ``.NAME.making-<id>`` beside
    ``path``, then move it into place (:func:`move_folder_into_place`); returns the path.

    ``create`` makes the staging folder before ``write`` is called (else ``write`` creates it). Staging folders
    that a killed writer of ``path`` left are removed first (:func:`remove_leftovers`). An empty folder
    at ``path`` is removed first; any other folder there is replaced only at the last moment, so the caller
    decides beforehand whether it may be. On any error (or an interrupt) the staging folder is removed and
    ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path)
    staging = path.parent / f".{path.name}.making-{uuid.uuid4().hex[:12]}"
    if create:
        staging.mkdir()
    try:
        write(staging)
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()
        move_folder_into_place(staging, path)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return path


def move_folder_into_place(tmp: Path, target: Path) -> None:
    """Rename the finished folder ``tmp`` to ``target``, replacing an existing ``target`` only at the last moment
    (it is restored if the rename fails). Both must be on the same file system; ``tmp`` is first given the
    permissions a folder made with ``mkdir`` would have (0777 minus the umask)."""
    os.chmod(tmp, 0o777 & ~_umask())
    if not target.exists():
        os.replace(tmp, target)
        return
    old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:12]}"
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except BaseException:
        os.replace(old, target)
        raise
    shutil.rmtree(old, ignore_errors=True)


def jsonable(obj: Any, nan_to_null: bool = True) -> Any:
    """A copy of ``obj`` that ``json.dumps`` writes: dict keys as strings, tuples as lists, numpy arrays as
    (nested) lists and numpy scalars as Python numbers.

    Args:
        nan_to_null: non-finite floats (NaN, ±inf; JSON has none) become None. With False they are kept, and
            ``json.dumps`` writes them as ``NaN`` / ``Infinity`` (as Python's ``json`` reads back).
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v, nan_to_null) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, nan_to_null) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), nan_to_null)
    if isinstance(obj, np.generic):
        return jsonable(obj.item(), nan_to_null)
    if nan_to_null and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def save_torch_atomic(obj: Any, path: str | Path) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (tensors and plain containers only: loaded back with
    ``torch.load(..., weights_only=True)``); returns the path."""
    return write_file_atomic(Path(path), lambda tmp: torch.save(obj, tmp))


def read_json(path: str | Path, what: str = "a JSON file", error: type[InputError] = InputError,
              expect: type = dict) -> Any:
    """The JSON value of ``path``, checked to be an ``expect`` (a dict by default).

    Args:
        what: what the file should be, for the messages ("an asset's material.json").
        error: the :class:`~vid2sim.runtime.errors.InputError` subclass to raise.
    Raises:
        ``error``: the file is missing, unreadable, not UTF-8, not JSON, or not an ``expect``; the message names
        the file.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: missing (expected {what})")
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text (expected {what})") from None
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc}); expected {what}") from None
    if not isinstance(value, expect):
        raise error(f"{path}: expected a JSON {expect.__name__} ({what}), got {type(value).__name__}")
    return value


def load_torch_file(path: str | Path, what: str = "a torch file", error: type[InputError] = InputError,
                    map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` (tensors and plain containers only: a file from someone else
    cannot run code), with every way the file can be broken turned into ``error`` naming it.

    Raises:
        ``error``: missing, a directory, truncated, not a torch file, or holding objects other than tensors and
        plain containers (a pickle that would run code is refused here, unexecuted).
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: missing (expected {what})")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except OSError as exc:
        raise error(f"{path}: cannot read it ({exc}); expected {what}") from None
    except pickle.UnpicklingError as exc:
        if "Unsupported global" in str(exc):  # a pickle naming a Python callable (what an exploit needs)
            raise error(f"{path}: refused: it holds Python objects other than tensors and plain containers, and "
                        f"loading them could run code (expected {what})") from None
        raise error(f"{path}: not {what}, or corrupt (UnpicklingError: {str(exc).splitlines()[0][:200]})") from None
    except Exception as exc:  # noqa: BLE001 - a corrupt or hostile file fails in many ways inside the unpickler
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise error(f"{path}: not {what}, or corrupt ({type(exc).__name__}: {first[:200]})") from None
