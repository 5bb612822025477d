"""``d2f batch``: its own options, and the run (plan, skip what is done, render, summarise)."""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import Any

from ..io import READ_EXTENSIONS, SAVE_FORMATS, same_file
from .manifest import (
    DONE,
    Summary,
    check_manifest,
    fold_parts,
    parts_dir,
    read_rows,
    render_settings,
    rows_by_output,
    settings_differences,
    worker_name,
)
from .plan import Job, find_photos, plan_jobs
from .worker import PARTIAL_PREFIX

__all__ = ["MANIFEST_NAME", "add_batch_arguments", "run_batch"]

logger = logging.getLogger("d2f_core.batch")

#: The manifest's name in the output folder unless ``--manifest`` says otherwise.
MANIFEST_NAME = "manifest.jsonl"


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    """``d2f batch``'s own arguments (the render options come from the parent parser)."""
    parser.add_argument(
        "input",
        nargs="+",
        metavar="INPUT",
        help="a folder, a glob in quotes ('shoot/**/*.jpg'), a .txt/.csv file listing paths "
        "(one a line, or a 'path' column), or photos",
    )
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="DIR", help="output folder"
    )
    parser.add_argument(
        "-r", "--recursive", action="store_true", help="also the photos in subfolders"
    )
    parser.add_argument(
        "--format",
        choices=sorted({e.lstrip(".") for e in SAVE_FORMATS}),
        default=None,
        help="output format (default: the input's, or jpg when it cannot be written)",
    )
    parser.add_argument(
        "--suffix", default="_bokeh", help="added to each output file name (default _bokeh)"
    )
    run = parser.add_argument_group("run")
    run.add_argument(
        "--manifest",
        type=Path,
        metavar="FILE",
        help=f"JSON Lines record, one row per photo (default: OUT/{MANIFEST_NAME}); a rerun "
        "skips the photos it says are done with the same settings whose output is intact",
    )
    run.add_argument(
        "--force",
        action="store_true",
        help="also render again the photos the manifest says were done with other render "
        "settings (without it such a rerun is refused); photos done with these are kept",
    )
    run.add_argument(
        "--engine",
        choices=("local", "ray"),
        default="local",
        help="local: worker processes on this machine (default); ray: a Ray cluster "
        '(pip install "d2f[scale]")',
    )
    run.add_argument(
        "--workers",
        type=_count,
        metavar="N",
        help="worker processes or Ray actors (default: one per CPU, local or in the cluster)",
    )
    run.add_argument(
        "--threads",
        type=_count,
        metavar="T",
        help="torch threads per worker (default: the CPUs shared out among the workers)",
    )
    run.add_argument(
        "--ray-address",
        metavar="ADDR",
        help="join this Ray cluster (default: $RAY_ADDRESS, else a local one for the run)",
    )


def _check(args: argparse.Namespace) -> None:
    from ..photo_render import UsageError

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise UsageError(f"-o {os.fspath(out)!r} exists and is not a folder")
    for source in args.input:
        path = Path(source)
        if path.is_dir() and out.exists() and same_file(out, path):
            raise UsageError("-o must differ from the input folder: outputs never replace inputs")
        if path.is_dir() and args.save_maps is not None and args.save_maps.exists():
            if same_file(args.save_maps, path):
                raise UsageError("--save-maps must differ from the input folder")
    if "/" in args.suffix or os.sep in args.suffix:
        raise UsageError("--suffix must not contain a path separator")
    if args.depth is not None and not args.depth.is_dir():
        raise UsageError("--depth must be a folder of depth maps for 'd2f batch'")
    if args.depth is not None and args.depth_model is not None:
        raise UsageError(
            f"--depth DIR and --depth-model {args.depth_model.name} name two depth sources: "
            "give one"
        )
    if args.weights is not None and not args.weights.is_file():
        raise UsageError(f"--weights {os.fspath(args.weights)!r}: no such file")
    if args.engine == "local" and args.ray_address:
        raise UsageError("--ray-address needs --engine ray")


def _remove_stale_partials(folders: set[Path]) -> None:
    """Delete the partial folders that killed local workers left behind (this host's, of
    processes that are gone)."""
    host = socket.gethostname().replace(os.sep, "_")
    for folder in folders:
        if not folder.is_dir():
            continue
        for partial in folder.glob(f"{PARTIAL_PREFIX}{host}-*"):
            pid = partial.name[len(PARTIAL_PREFIX) + len(host) + 1 :].split("-")[0]
            if pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(partial, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` still runs. A killed worker whose parent died too can stay a
    zombie that nothing reaps (a container's first process may not), and a signal still
    reaches it: it counts as gone."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True  # no /proc here: trust the signal
    # the state follows the command name, which is in parentheses and may hold spaces
    return stat[stat.rfind(")") + 2 : stat.rfind(")") + 3] not in ("Z", "X")


def _show(row: dict[str, Any], here: str) -> None:
    if row.get("worker") != here:  # records of this process were shown as they happened
        for level, message in row.get("log") or ():
            logging.getLogger("d2f_core").log(level, message)
    if row.get("status") != DONE:
        logger.error("skipped %s", row.get("error"))


def _intact(row: dict[str, Any], job: Job) -> bool:
    """Whether ``job``'s output is the file ``row`` recorded: there, with its size."""
    try:
        size = os.stat(job.output).st_size
    except OSError:
        return False
    return row.get("bytes") == size and Path(job.output).is_file()


def _same_input(recorded: str, job: Job) -> bool:
    """Whether a row's input names ``job``'s photo: an absolute one (manifests written
    before) is its absolute path; a relative one, as the inputs named it from some working
    folder, is the end of it (``lib/a.jpg`` is ``/home/me/lib/a.jpg``), so naming the inputs
    from another folder, or absolutely, finds the same rows."""
    path = os.path.normpath(recorded)
    if os.path.isabs(path):
        return path == job.input
    parts = [p for p in Path(path).parts if p != os.pardir]
    return bool(parts) and Path(job.input).parts[-len(parts) :] == tuple(parts)


def _to_render(
    jobs: list[Job],
    latest: dict[str, dict[str, Any]],
    settings: dict[str, Any],
    args: argparse.Namespace,
    out: Path,
) -> list[Job]:
    """The jobs a run renders, given the last manifest row of each output.

    A job is done, and skipped, when its output's last row is ``done`` for the same input
    and the output has the size the row recorded, with this run's settings. Done with other
    settings, the run is refused (before any photo is rendered) unless ``--force``, which
    renders those again. Done by a manifest that recorded no settings: kept, with a warning
    (``--force`` renders them again). Everything else is rendered: no row, a failure, another
    photo's row, an output missing or of another size.
    """
    from ..photo_render import UsageError

    todo: set[str] = set()
    other: list[tuple[Job, list[str]]] = []
    unrecorded: list[Job] = []
    repaired = 0
    for job in jobs:
        row = latest.get(job.rel)
        if row is None or row["status"] != DONE or not _same_input(row["input"], job):
            todo.add(job.rel)
        elif not _intact(row, job):
            repaired += 1
            todo.add(job.rel)
        elif row.get("settings") is None:
            unrecorded.append(job)
        else:
            differences = settings_differences(row["settings"], settings, job.output)
            if differences:
                other.append((job, differences))
    if other and not args.force:
        job, differences = other[0]
        shown = "; ".join(differences[:3]) + ("; ..." if len(differences) > 3 else "")
        raise UsageError(
            f"{len(other)} of {len(jobs)} photos in {out} were rendered with other settings "
            f"({shown}, as {job.rel}); --force renders them again with these (photos done "
            "with these are kept), or choose another -o"
        )
    if repaired:
        logger.info("%d done photos whose output is missing or changed are rendered again",
                    repaired)  # fmt: skip
    if other:
        logger.info("--force: %d photos done with other settings are rendered again", len(other))
    if unrecorded and args.force:
        logger.info("--force: %d photos done without recorded settings are rendered again",
                    len(unrecorded))  # fmt: skip
    elif unrecorded:
        logger.warning(
            "%d photos were done by a run that recorded no settings: kept as they are, "
            "--force renders them again with these settings",
            len(unrecorded),
        )
    todo |= {job.rel for job, _ in other}
    if args.force:
        todo |= {job.rel for job in unrecorded}
    return [job for job in jobs if job.rel in todo]


def run_batch(args: argparse.Namespace) -> int:
    """Run ``d2f batch``; returns the exit status (1 when a photo failed)."""
    from ..photo_render import RenderError, UsageError, error_message
    from ..progress import logs_above_bar, progress

    _check(args)
    if args.engine == "ray":
        from .ray_engine import require_ray

        try:
            require_ray()
        except ImportError as exc:
            raise RenderError(str(exc)) from None
    out: Path = args.output
    try:
        root, photos, skipped_files = find_photos(args.input, recursive=args.recursive, exclude=out)
        jobs = plan_jobs(
            root, photos, out, suffix=args.suffix, fmt=args.format, depth_dir=args.depth
        )
    except ValueError as exc:
        raise UsageError(str(exc).removeprefix("input: ")) from None
    for p in skipped_files:
        logger.info("skipping %s: not a photo file extension", p)
    if not jobs:
        raise RenderError(f"no photos found in {' '.join(map(str, args.input))}")
    manifest: Path = args.manifest or out / MANIFEST_NAME
    named = [Path(p) for p in args.input if Path(p).is_file()]  # photos and lists named
    for job in jobs:
        named += [Path(p) for p in (job.input, job.output, job.depth_file) if p]
    if any(same_file(manifest, p) for p in named):
        raise UsageError(f"--manifest {manifest} is one of the photos, lists or outputs")
    if manifest.suffix.lower() in set(SAVE_FORMATS) | set(READ_EXTENSIONS):
        # an output or a map of this run or another, written or still to come
        raise UsageError(f"--manifest {manifest} has an image's extension; name a .jsonl file")
    try:
        check_manifest(manifest)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    fold_parts(manifest)  # rows a killed run left in its parts
    settings = render_settings(args)
    todo = _to_render(jobs, rows_by_output(read_rows(manifest), out), settings, args, out)
    args = argparse.Namespace(**{**vars(args), "batch_settings": settings})
    out.mkdir(parents=True, exist_ok=True)
    for folder in {Path(job.output).parent for job in jobs}:
        folder.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials({Path(job.output).parent for job in jobs})
    summary = Summary(total=len(jobs), skipped=len(jobs) - len(todo))
    if summary.skipped:
        logger.info(
            "%d of %d photos already done (manifest %s)", summary.skipped, len(jobs), manifest
        )

    level = logging.getLogger("d2f_core").getEffectiveLevel()
    here = worker_name()
    stopped: OSError | None = None
    start = time.perf_counter()
    try:
        if not todo:
            rows = iter(())
        elif args.engine == "ray":
            from .ray_engine import run_ray

            rows = run_ray(todo, args, manifest, workers=args.workers, threads=args.threads,
                           address=args.ray_address, level=level, quiet=args.quiet)  # fmt: skip
        else:
            from .local import cpu_count, default_split, run_local

            workers, threads = default_split(cpu_count(), len(todo))
            workers = args.workers or workers
            threads = args.threads or max(1, cpu_count() // workers)
            logger.info("%d photos on %d workers of %d threads", len(todo), workers, threads)
            rows = run_local(todo, args, manifest, workers=workers, threads=threads, level=level)
        show_bar = None if args.engine == "local" and not args.quiet else True
        with logs_above_bar():
            bar = progress(total=len(todo), desc="d2f", unit="photo", disable=show_bar)
            try:
                for row in rows:
                    summary.add(row)
                    _show(row, here)
                    bar.set_postfix_str(Path(row["input"]).name, refresh=False)
                    bar.update(1)
            except OSError as exc:  # the manifest could not be written (a full disk)
                stopped = exc
            finally:
                bar.close()
    finally:
        summary.seconds = time.perf_counter() - start
        try:
            fold_parts(manifest)
        except OSError as exc:  # the rows stay in the parts; the next run folds them
            logger.error(
                "could not add this run's rows to %s (%s): they stay in %s, and the next "
                "run adds them", manifest, error_message(exc), parts_dir(manifest),
            )  # fmt: skip
    attempted = summary.done + summary.failed
    logger.info("%d of %d photos rendered into %s", summary.done, attempted, out)
    if not args.quiet or stopped is not None:
        for line in summary.lines():
            print(f"d2f: {line}", file=sys.stderr)
    if stopped is not None:
        raise RenderError(
            f"the run stopped, its manifest cannot be written: {error_message(stopped)}"
        )
    if summary.failed:
        logger.error("%d of %d photos failed", summary.failed, attempted)
        return 1
    return 0
