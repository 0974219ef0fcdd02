"""Files written whole or not at all, and JSON read with errors that name the file.

Every output vid2sim writes goes through :func:`write_json_atomic`, :func:`write_text_atomic` or
:func:`save_torch_atomic`: the data is written to a hidden temporary file beside the target and renamed onto it,
so a reader (or a run killed halfway) never sees half a file. The permissions are the umask's, as for a file
opened normally (``mkstemp`` would make it private).
"""

from __future__ import annotations

import json
import os
import pickle
import tempfile
from pathlib import Path
from typing import Any, Callable

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
