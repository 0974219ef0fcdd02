"""The error every capture-import problem raises: an :class:`~vid2sim.runtime.errors.InputError` whose message
names the camera and the file concerned and says what to do about it."""

from __future__ import annotations

from pathlib import Path

from vid2sim.runtime.errors import InputError


class CaptureError(InputError):
    """A capture folder that vid2sim cannot import as it is; the message names the camera and the file.

    Attributes:
        camera: the camera concerned (its name in the capture), or None for the whole capture.
        file: the file concerned, or None.
    """

    def __init__(self, message: str, camera: str | None = None, file: str | Path | None = None) -> None:
        where = []
        if camera is not None:
            where.append(f"camera '{camera}'")
        if file is not None:
            where.append(f"{file}")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.camera = camera
        self.file = None if file is None else str(file)
