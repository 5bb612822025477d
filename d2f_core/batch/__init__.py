"""Photo libraries: ``d2f batch`` on local worker processes or a Ray cluster.

* :mod:`~d2f_core.batch.plan`: which photos (folders, globs, lists) and where outputs go.
* :mod:`~d2f_core.batch.worker`: the one per-photo function (:func:`render_job`) of both
  engines, and the worker that keeps a model for it.
* :mod:`~d2f_core.batch.local` and :mod:`~d2f_core.batch.ray_engine`: the engines.
* :mod:`~d2f_core.batch.manifest`: the JSON Lines manifest and the run's summary.
* :mod:`~d2f_core.batch.command`: the ``d2f batch`` command.

Ray is imported only by ``--engine ray`` (the optional extra ``scale``).
"""

from .manifest import FIELDS, Summary, last_rows, read_rows, render_settings, rows_by_output
from .plan import Job, find_photos, plan_jobs
from .worker import PhotoWorker, render_job

__all__ = [
    "FIELDS",
    "Job",
    "PhotoWorker",
    "Summary",
    "find_photos",
    "last_rows",
    "plan_jobs",
    "read_rows",
    "render_job",
    "render_settings",
    "rows_by_output",
]
