"""Thread choice: how many torch threads a render uses while other processes keep the cores
busy (no equation of D2F: this is the machine, not the method).
"""

from __future__ import annotations

import glob
import os
import time

import torch

# threads
# --------------------------------------------------------------------------------------

# How often (s) a render looks again at how busy the machine is.
_RECHECK_S = 0.05


def _running_elsewhere() -> int | None:
    """Threads of other processes running right now (Linux ``/proc``); ``None`` elsewhere.

    ``/proc/loadavg`` counts every runnable thread of the machine, this process's own
    (the reading thread, and OpenMP workers still spinning after an operation) among them.
    """
    try:
        with open("/proc/loadavg", encoding="ascii") as fh:
            running = int(fh.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return None
    ours = 0
    for path in glob.glob("/proc/self/task/*/stat"):
        try:
            with open(path, encoding="ascii", errors="replace") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):  # the thread ended meanwhile
            continue
        ours += state == "R"
    return max(0, running - max(ours, 1))


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _threads_free(wanted: int) -> int:
    """Of ``wanted`` threads, how many have a core to themselves now (at least 1)."""
    others = _running_elsewhere()
    if others is None:
        return wanted
    return max(1, min(wanted, _usable_cores() - others))


class ThreadChoice:
    """Torch threads for one render: the caller's count while the machine has a core free for
    each, fewer while other processes keep cores busy (looked at again every
    :data:`_RECHECK_S` s by :meth:`check`).

    A render is some hundreds of tensor operations, each an OpenMP parallel region whose end
    waits for every thread: with one thread descheduled by another process, each operation
    waits for the scheduler to run it again. 2-thread renders were 5-11x slower than 1-thread
    ones beside one busy process.
    """

    def __init__(self) -> None:
        self.saved = self.current = 1
        self.last = 0.0

    def __enter__(self) -> ThreadChoice:
        self.saved = self.current = torch.get_num_threads()
        self.check(force=True)
        return self

    def check(self, force: bool = False) -> None:
        if self.saved <= 1:
            return
        now = time.perf_counter()
        if not force and now - self.last < _RECHECK_S:
            return
        self.last = now
        want = _threads_free(self.saved)
        if want != self.current:
            torch.set_num_threads(want)
            self.current = want

    def __exit__(self, *exc) -> None:
        if self.current != self.saved:
            torch.set_num_threads(self.saved)
            self.current = self.saved


# --------------------------------------------------------------------------------------
