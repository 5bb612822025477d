"""The one per-photo function of both engines, and the worker that holds a model for it.

:func:`render_job` renders a :class:`~d2f_core.batch.plan.Job` with ``d2f render``'s own
code (:func:`d2f_core.photo_render.render_file`) into a temporary name beside the output, renames it
into place, and returns the manifest row; any failure becomes a ``failed`` row, never an
exception. :class:`PhotoWorker` loads the model once (a process of the local pool, or a Ray
actor), renders jobs and appends their rows to its manifest part.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import socket
import time
import uuid
from pathlib import Path
from typing import Any

from .manifest import DONE, FAILED, PartWriter, worker_name
from .plan import Job

__all__ = ["PARTIAL_PREFIX", "PhotoWorker", "failed_row", "render_job"]

#: Outputs are written into ``<output folder>/<PARTIAL_PREFIX><host>-<pid>-<id>/`` and renamed
#: into place, so a killed run never leaves a half-written file under an output's name.
PARTIAL_PREFIX = ".d2f-partial-"

_PKG = logging.getLogger("d2f_core")


class _Collect(logging.Handler):
    """Keeps the records of one photo, to be shown by the process that drives the run."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.levelno, record.getMessage()))


def _partial_folder(dst: Path) -> Path:
    host = socket.gethostname().replace(os.sep, "_")
    return dst.parent / f"{PARTIAL_PREFIX}{host}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


def render_job(job: Job, args: argparse.Namespace, engine: Any) -> dict[str, Any]:
    """Render one photo as ``d2f render`` does and return its manifest row.

    ``args`` holds ``d2f render``'s options; ``engine`` is a
    :class:`d2f_core.photo_render.Engine` (the model, loaded on first use and kept). The
    output appears under its name only once it is whole; the input is only read. Never
    raises for a bad photo: the row says ``failed`` with the error's kind and one-line
    message. The row names the input as the inputs did (:attr:`Job.named`), the output
    relative to the output folder, and, when done, ``args.batch_settings`` (the run's
    :func:`~d2f_core.batch.manifest.render_settings`, set by ``d2f batch``) as ``settings``.
    """
    from .. import photo_render
    from ..lens import f_number_for

    start = time.perf_counter()
    row: dict[str, Any] = {"input": job.named, "output": job.rel, "status": FAILED}
    src, dst = Path(job.input), Path(job.output)
    options = args
    if args.save_maps is not None:  # the maps keep the inputs' layout too
        options = argparse.Namespace(**vars(args))
        options.save_maps = Path(args.save_maps) / Path(job.rel).parent
    partial = _partial_folder(dst)
    try:
        if not src.is_file():
            raise FileNotFoundError(2, "no such file", os.fspath(src))
        partial.mkdir(parents=True, exist_ok=True)
        depth = None if job.depth_file is None else Path(job.depth_file)
        info = photo_render.render_file(src, partial / dst.name, options, engine, depth)
        os.replace(partial / dst.name, dst)
        w, h = info.size
        row.update(
            width=w,
            height=h,
            bytes=dst.stat().st_size,
            depth_source=info.depth_source,
            focus_point=None if info.focus_point is None else list(info.focus_point),
            focus=round(info.focus, 6),
            blur_px=info.blur,
            f_number=(
                args.f_number
                if getattr(args, "f_number", None)
                else f_number_for(info.blur, max(w, h))
            ),
            status=DONE,
            settings=getattr(args, "batch_settings", None),
        )
    except Exception as exc:  # one bad photo must never stop a worker
        if isinstance(exc, OSError) and exc.filename and Path(exc.filename).parent == partial:
            # a write into the hidden folder (a full disk) names the output it was for
            exc = type(exc)(
                exc.errno, exc.strerror, os.fspath(dst.parent / Path(exc.filename).name)
            )
        row.update(error_kind=type(exc).__name__, error=_one_line(src, exc))
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    row.update(
        seconds=round(time.perf_counter() - start, 3), worker=worker_name(), finished=time.time()
    )
    return row


def failed_row(job: Job, exc: BaseException, seconds: float = 0.0) -> dict[str, Any]:
    """The row of a job that failed outside :func:`render_job` (the model would not load,
    the worker process died)."""
    return {
        "input": job.named,
        "output": job.rel,
        "status": FAILED,
        "error_kind": type(exc).__name__,
        "error": _one_line(Path(job.input), exc),
        "seconds": round(seconds, 3),
        "worker": worker_name(),
        "finished": time.time(),
    }


def _one_line(src: Path, exc: BaseException) -> str:
    from ..photo_render import error_message

    msg = " ".join(error_message(exc).split())
    return msg if os.fspath(src) in msg or src.name in msg else f"{src}: {msg}"


class PhotoWorker:
    """Renders jobs with one model, loaded on the first photo that needs it and kept.

    Args:
        args: ``d2f batch``'s parsed options (those of ``d2f render`` among them).
        manifest: the manifest path; rows go to a part file of this worker's own.
        threads: torch threads for this worker (``None`` leaves torch's default).
        level: the ``d2f_core`` log level; records are returned with each row.
    """

    def __init__(
        self,
        args: argparse.Namespace,
        manifest: str | os.PathLike,
        threads: int | None = None,
        level: int = logging.WARNING,
    ) -> None:
        from ..photo_render import Engine

        self._threads = None
        if threads is not None:
            import torch

            self._threads = torch.get_num_threads()  # restored by close() (one worker in-process)
            torch.set_num_threads(int(threads))
        self.args = args
        self.engine = Engine(args.weights)
        self.writer = PartWriter(manifest)
        self.level = level
        self.load_error: Exception | None = None
        try:  # once per worker, before the first photo
            self.engine.model()
        except Exception as exc:  # every photo's row will say why
            self.load_error = exc

    def __call__(self, job: Job) -> dict[str, Any]:
        """The job's row, written to the manifest part, with ``"log"``: the (level, message)
        records the photo logged, for the driver to show."""
        collect = _Collect()
        old = _PKG.level
        _PKG.setLevel(self.level)
        _PKG.addHandler(collect)
        try:
            if self.load_error is None:
                row = render_job(job, self.args, self.engine)
            else:
                row = failed_row(job, self.load_error)
        finally:
            _PKG.removeHandler(collect)
            _PKG.setLevel(old)
        self.writer.write(row)
        return {**row, "log": collect.records}

    def close(self) -> None:
        self.writer.close()
        if self._threads is not None:
            import torch

            torch.set_num_threads(self._threads)
            self._threads = None
