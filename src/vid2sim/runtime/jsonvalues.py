"""Checks on values read from JSON: one meaning of "a number" for every reader of our files."""

from __future__ import annotations

import math
from typing import Any


def is_number(value: Any) -> bool:
    """A JSON number: an int or a float, not a bool (``True`` is an int in Python)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_finite_number(value: Any) -> bool:
    """A JSON number (:func:`is_number`) that is neither NaN nor ±inf (Python's JSON reader accepts both)."""
    return is_number(value) and math.isfinite(value)
