"""Allocator setting for d2f's own long-running processes: the app, the CLI and the benches.

A render allocates frame-sized temporaries, 144 MB per three float32 channels at 12 MP.
glibc's malloc serves blocks above its mmap threshold (at most 32 MB) from fresh memory
mappings: the kernel zero-fills them page by page on first touch and unmaps them on free, so
every render pays those page faults again. Measured on the 2-core development machine, one
torch thread: a 12 MP ``D2F.render`` took 1.0-1.8 s, of which 0.35-0.9 s was system time for
200-300 thousand minor page faults; with :func:`keep_freed_memory` the same render took
0.64-0.84 s with 0-0.1 million faults.

:func:`keep_freed_memory` makes malloc serve large blocks from its heap and keep up to
``trim_threshold`` bytes of freed memory mapped for the next render. The cost is memory: the
process keeps the heap it grew to. The library never calls it (an application that embeds
d2f owns its process); ``D2F_KEEP_FREED_MEMORY=0`` turns it off in d2f's own commands.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

__all__ = ["keep_freed_memory"]

logger = logging.getLogger(__name__)

# glibc <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
ENV = "D2F_KEEP_FREED_MEMORY"


def keep_freed_memory(trim_threshold: int = 1 << 30) -> bool:
    """Serve large blocks from the heap and keep freed memory for reuse (glibc only).

    Args:
        trim_threshold: bytes of free memory at the top of the heap kept mapped; more is given
            back to the system.

    Returns:
        True when glibc accepted both settings; False on other C libraries or platforms, or
        when ``D2F_KEEP_FREED_MEMORY=0``.
    """
    if os.environ.get(ENV, "1").strip() in ("0", "false", "no", "off"):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018  (glibc only: musl has a no-op mallopt)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    value = max(0, min(int(trim_threshold), 2**31 - 1))
    ok = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, value))
    if ok:
        logger.debug("malloc: large blocks from the heap, %d MB of freed memory kept", value >> 20)
    return ok
