"""``--engine ray``: the same per-photo function on a Ray cluster, through Ray Data.

Ray Data reads the list of jobs; ``map_batches`` runs them on a fixed pool of actors, each a
:class:`~d2f_core.batch.worker.PhotoWorker` that loads the model once and keeps it. The
actors write the outputs and their manifest rows themselves (every node must see the input
and output folders at the same paths: one machine, or a shared file system), and return the
rows, which the driver counts and reports.

Ray is the optional extra ``scale`` (``pip install "d2f[scale]"``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
from collections.abc import Iterator, Sequence
from typing import Any

from .plan import Job
from .worker import PhotoWorker

__all__ = ["RAY_MISSING", "cluster_cpus", "require_ray", "run_ray"]

RAY_MISSING = '--engine ray needs Ray, the optional extra "scale": pip install "d2f[scale]"'


def require_ray() -> None:
    """Raise ``ImportError`` with :data:`RAY_MISSING` when Ray Data cannot be imported."""
    try:
        import ray  # noqa: F401
        import ray.data  # noqa: F401
    except ImportError as exc:
        raise ImportError(RAY_MISSING) from exc


class _PhotoActor:
    """A Ray Data actor: one model for every batch of jobs it is given."""

    def __init__(
        self, args: argparse.Namespace, manifest: str, threads: int | None, level: int
    ) -> None:
        self.worker = PhotoWorker(args, manifest, threads, level)

    def __call__(self, batch: dict[str, Any]) -> dict[str, Any]:
        import numpy as np

        rows = [self.worker(Job(**json.loads(str(job)))) for job in batch["job"]]
        return {"row": np.array([json.dumps(row) for row in rows], dtype=object)}


def cluster_cpus() -> int:
    """CPUs of the Ray cluster this process is connected to."""
    import ray

    return max(1, int(ray.cluster_resources().get("CPU", 1)))


def run_ray(
    jobs: Sequence[Job],
    args: argparse.Namespace,
    manifest: str | os.PathLike,
    *,
    workers: int | None,
    threads: int | None,
    address: str | None = None,
    level: int = logging.WARNING,
    quiet: bool = False,
) -> Iterator[dict[str, Any]]:
    """Render ``jobs`` on ``workers`` Ray actors of ``threads`` CPUs each (default: one thread,
    an actor per CPU of the cluster); yields each row as it comes back.

    ``address`` (else ``$RAY_ADDRESS``) joins a running cluster; without either, a local one
    starts for this run and stops at its end.
    """
    require_ray()
    import ray
    import ray.data

    address = address or os.environ.get("RAY_ADDRESS") or None
    try:
        ray.init(
            address=address,
            include_dashboard=False,
            log_to_driver=not quiet,
            logging_level=logging.ERROR if quiet else logging.WARNING,
        )
    except Exception as exc:  # ConnectionError, RuntimeError, ValueError: several lines
        where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConnectionError(f"cannot start or join {where}: {first}") from exc
    if quiet:  # Ray Data's notices (ray.init has set up Ray's loggers by now)
        for name in ("ray", "ray.data"):
            logging.getLogger(name).setLevel(logging.ERROR)
    try:
        context = ray.data.DataContext.get_current()
        context.enable_progress_bars = not quiet
        context.print_on_execution_start = not quiet
        threads = threads or 1
        if workers is None:
            workers = max(1, min(len(jobs), cluster_cpus() // threads))
        items = [{"job": json.dumps(dataclasses.asdict(job))} for job in jobs]
        # one block per photo: blocks are what the actor pool hands out
        dataset = ray.data.from_items(items, override_num_blocks=len(items))
        rows = dataset.map_batches(
            _PhotoActor,
            fn_constructor_kwargs={
                "args": args,
                "manifest": os.fspath(manifest),
                "threads": threads,
                "level": level,
            },
            batch_size=1,
            batch_format="numpy",
            compute=ray.data.ActorPoolStrategy(size=workers),
            num_cpus=threads,
        )
        for row in rows.iter_rows():
            yield json.loads(row["row"])
    finally:
        ray.shutdown()
