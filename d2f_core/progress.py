"""Progress bars that need tqdm only when it is installed (the ``[train]`` and ``[dev]``
extras): without it, a bar does nothing and the loggers report as usual."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterable, Iterator

__all__ = ["NoBar", "logs_above_bar", "progress"]


class NoBar:
    """Stands in for a tqdm bar without tqdm: iterates over ``iterable`` and ignores every
    update."""

    def __init__(self, iterable: Iterable | None = None) -> None:
        self._iterable = () if iterable is None else iterable

    def __iter__(self) -> Iterator:
        return iter(self._iterable)

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass

    def set_postfix_str(self, text: str = "", refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass


def progress(iterable: Iterable | None = None, **options):
    """``tqdm(iterable, **options)``, or a :class:`NoBar` over ``iterable`` without tqdm."""
    try:
        from tqdm import tqdm
    except ImportError:
        return NoBar(iterable)
    return tqdm(iterable, **options)


def logs_above_bar(logger: str = "d2f_core"):
    """A context in which ``logger``'s records print above the bar instead of through it
    (tqdm's ``logging_redirect_tqdm``); a context that does nothing without tqdm."""
    try:
        from tqdm.contrib.logging import logging_redirect_tqdm
    except ImportError:
        return contextlib.nullcontext()
    return logging_redirect_tqdm(loggers=[logging.getLogger(logger)])
