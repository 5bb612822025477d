"""The library's error for input of the wrong type."""

from __future__ import annotations

__all__ = ["InputTypeError"]


class InputTypeError(TypeError, ValueError):
    """Input of the wrong type or dtype (an int16 image, a list where a tensor goes, text for a
    number).

    A ``ValueError`` like every other bad-input error of the library, so one
    ``except ValueError`` catches them all, and a ``TypeError`` for callers that expect one.
    """
