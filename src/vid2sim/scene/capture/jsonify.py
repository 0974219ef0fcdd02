"""JSON-ready copies of the import's records: numpy arrays and scalars to lists and numbers, tuples to lists,
non-finite floats to null (JSON has no NaN).

The helper is :func:`vid2sim.runtime.files.jsonable` (shared with the synthetic scenes), named here for the
capture importer."""

from __future__ import annotations

from vid2sim.runtime.files import jsonable

__all__ = ["jsonable"]
