"""The library's error for input of the wrong type."""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = ["InputTypeError", "whole_number"]


class InputTypeError(TypeError, ValueError):
    """Input of the wrong type or dtype (an int16 image, a list where a tensor goes, text for a
    number).

    A ``ValueError`` like every other bad-input error of the library, so one
    ``except ValueError`` catches them all, and a ``TypeError`` for callers that expect one.
    """


def whole_number(value: Any, name: str, minimum: int) -> int:
    """``value`` as an ``int`` of at least ``minimum``: Python and NumPy integers, and floats
    with no fraction (``2.0``); never a bool, a fraction, NaN or text, which a plain ``int()``
    would truncate or fail on with a message that does not name ``name``.

    Raises:
        InputTypeError: not a real number.
        ValueError: a fraction, not finite, or under ``minimum``.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputTypeError(f"{name} must be a whole number, got {value!r}")
    if isinstance(value, numbers.Integral):
        number = int(value)  # exactly, however large: never through a float
    else:
        real = float(value)
        if not math.isfinite(real) or real != int(real):
            raise ValueError(f"{name} must be a whole number, got {value!r}")
        number = int(real)
    if number < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return number
