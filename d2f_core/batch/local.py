"""``--engine local``: worker processes on this machine, each with its model and torch threads.

One worker renders in the calling process (no start-up, no copy of the model). More start
with ``spawn`` (torch and fork do not mix) and load the model once each; a worker holds one
photo at a time, so a worker that dies (out of memory on a huge photo) costs the photos it
held, which get failed rows, and a fresh pool takes over the rest.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from .manifest import PartWriter
from .plan import Job
from .worker import PhotoWorker, failed_row

__all__ = ["cpu_count", "default_split", "run_local"]

_WORKER: PhotoWorker | None = None
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def cpu_count() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_split(cpus: int, photos: int) -> tuple[int, int]:
    """``(workers, torch threads each)`` for ``photos`` photos on ``cpus`` CPUs: one thread per
    worker and as many workers as CPUs, never more workers than photos. ``d2f-bench batch`` on
    2 shared cores (docs/batch.md): 2 workers of 1 thread rendered 3 to 7 times the photos per
    second of 1 worker of 2 threads (reading, depth refinement and encoding are
    single-threaded, and two threads of one photo wait on each other on a busy machine)."""
    workers = max(1, min(cpus, photos))
    return workers, max(1, cpus // workers)


def _init(args: argparse.Namespace, manifest: str, threads: int | None, level: int) -> None:
    global _WORKER
    _WORKER = PhotoWorker(args, manifest, threads, level)


def _work(job: Job) -> dict[str, Any]:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER(job)


def run_local(
    jobs: Sequence[Job],
    args: argparse.Namespace,
    manifest: str | os.PathLike,
    *,
    workers: int,
    threads: int | None,
    level: int = logging.WARNING,
) -> Iterator[dict[str, Any]]:
    """Render ``jobs`` on ``workers`` processes; yields each row as its photo finishes (in
    the order they finish). Rows are already in the manifest's parts when yielded."""
    if workers < 1:
        raise ValueError(f"workers: expected at least 1, got {workers}")
    manifest = os.fspath(manifest)
    if workers == 1:
        worker = PhotoWorker(args, manifest, threads, level)
        try:
            for job in jobs:
                yield worker(job)
        finally:
            worker.close()
        return
    pending = list(reversed(jobs))  # popped from the end: input order
    context = multiprocessing.get_context("spawn")
    # the workers' OpenMP and BLAS pools get their share of the CPUs from the start, as Ray
    # gives its actors (torch.set_num_threads alone leaves numpy's and OpenMP's defaults)
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    if threads is not None:
        os.environ.update({name: str(threads) for name in _THREAD_VARIABLES})
    try:
        yield from _pools(pending, context, args, manifest, workers, threads, level)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _pools(pending, context, args, manifest, workers, threads, level):
    while pending:
        pool = ProcessPoolExecutor(
            max_workers=min(workers, len(pending)),
            mp_context=context,
            initializer=_init,
            initargs=(args, manifest, threads, level),
        )
        held: dict[Future, Job] = {}
        try:
            while pending or held:
                while pending and len(held) < workers:
                    job = pending.pop()
                    held[pool.submit(_work, job)] = job
                finished, _ = wait(held, return_when=FIRST_COMPLETED)
                for future in finished:
                    row = future.result()
                    del held[future]
                    yield row
        except BrokenProcessPool as exc:
            # the photos held by the pool fail; the rest go to a fresh pool
            writer = PartWriter(manifest)
            for job in held.values():
                row = failed_row(job, RuntimeError(f"the worker process died ({exc})"))
                writer.write(row)
                yield row
            writer.close()
            held.clear()
        finally:
            for future in held:
                future.cancel()
            pool.shutdown(wait=True, cancel_futures=True)
