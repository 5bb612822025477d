"""The batch manifest: one JSON line per photo rendered or failed, and the run's summary.

Each worker appends its rows to a part file of its own (``<manifest>.parts/<host>-<pid>-
<id>.jsonl``), so processes on several machines never write one file; the driver folds the
parts into the manifest at the end of a run, and at the start of the next one when a run was
killed. A rerun reads the last row of each input: ``done`` with its output present is
skipped. A line cut short by a kill is ignored.
"""

from __future__ import annotations

import collections
import json
import os
import socket
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "FIELDS",
    "PartWriter",
    "Summary",
    "check_manifest",
    "fold_parts",
    "last_rows",
    "parts_dir",
    "read_rows",
]

#: The columns of a row, in order.
FIELDS = (
    "input",  # the photo's absolute path
    "output",  # the output's absolute path
    "width",  # px rendered (after any --max-pixels downscale); null when it failed
    "height",
    "bytes",  # the output file's size
    "depth_source",  # d2f (the network), embedded (...), file:PATH (...), transformers:...
    "focus_point",  # [x, y] in the input's px that gave the focus, or null (a number given)
    "focus",  # focal disparity in [0, 1], 1 = nearest
    "blur_px",  # K at the rendered size
    "f_number",  # of the virtual lens (d2f_core.lens) that gives K; null for K = 0
    "seconds",  # wall time of the photo in its worker: read, depth, render, write
    "status",  # done | failed
    "error_kind",  # the exception's class for a failure, else null
    "error",  # the one-line message for a failure, else null
    "worker",  # host:pid
    "finished",  # Unix time
)
DONE = "done"
FAILED = "failed"


def parts_dir(manifest: str | os.PathLike) -> Path:
    """The folder of ``manifest``'s part files."""
    path = Path(manifest)
    return path.with_name(f".{path.name}.parts")


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class PartWriter:
    """Appends rows to a part file of its own, one flushed line each (a killed process loses
    at most the line being written, which readers skip)."""

    def __init__(self, manifest: str | os.PathLike) -> None:
        self.folder = parts_dir(manifest)
        host = socket.gethostname().replace(os.sep, "_")
        self.path = self.folder / f"{host}-{os.getpid()}-{uuid.uuid4().hex[:8]}.jsonl"
        self._file = None

    def write(self, row: dict[str, Any]) -> None:
        if self._file is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (kept open)
        self._file.write(json.dumps({k: row.get(k) for k in FIELDS}) + "\n")
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


_ROW_START = b'{"input": '


def check_manifest(path: str | os.PathLike) -> None:
    """Refuse a manifest path that rows must not be appended to: a folder, or a file that is
    not a manifest (a photo, a list of photos, any text that is not one JSON row a line).
    A missing or empty file, or one whose first line is a row (or the start of one, cut short
    by a kill), is fine.

    Raises:
        ValueError: naming the path and what it holds.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"--manifest {path} is a folder; name a .jsonl file")
    try:
        with open(path, "rb") as f:
            head = f.read(64 * 1024)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ValueError(f"--manifest {path} cannot be read: {exc.strerror or exc}") from None
    first = next((line.strip() for line in head.splitlines() if line.strip()), None)
    if first is None:
        return
    try:
        row = json.loads(first.decode("utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        row = None
    # a row, however written; or, cut short by a kill, the start of one as written here
    if not (isinstance(row, dict) and "input" in row) and not first.startswith(_ROW_START):
        raise ValueError(
            f"--manifest {path} exists and is not a d2f manifest (its first line is not a "
            "row); rows are never appended to another file: name a new .jsonl file"
        )


def _lines(path: Path) -> Iterator[dict[str, Any]]:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            for line in f:
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:  # cut short by a kill
                    continue
                if isinstance(row, dict) and "input" in row:
                    yield row
    except FileNotFoundError:
        return


def read_rows(manifest: str | os.PathLike) -> list[dict[str, Any]]:
    """Every row of ``manifest`` and of its part files not folded yet, oldest first."""
    rows = list(_lines(Path(manifest)))
    folder = parts_dir(manifest)
    if folder.is_dir():
        parts = sorted(folder.glob("*.jsonl"))
        rows.extend(sorted((r for p in parts for r in _lines(p)), key=_finished))
    return rows


def _finished(row: dict[str, Any]) -> float:
    value = row.get("finished")
    return float(value) if isinstance(value, (int, float)) else 0.0


def last_rows(rows: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The last row of each input."""
    return {row["input"]: row for row in rows}


def fold_parts(manifest: str | os.PathLike) -> int:
    """Append the part files' rows to ``manifest`` (ordered by time) and delete the parts;
    returns the number of rows added. Call it when no worker is writing."""
    path = Path(manifest)
    folder = parts_dir(path)
    if not folder.is_dir():
        return 0
    parts = sorted(folder.glob("*.jsonl"))
    rows = sorted((r for p in parts for r in _lines(p)), key=_finished)
    if rows:
        with open(path, "a", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps({k: row.get(k) for k in FIELDS}) + "\n")
            f.flush()
            os.fsync(f.fileno())
    for p in parts:
        p.unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:  # a file that is not ours
        pass
    return len(rows)


@dataclass
class Summary:
    """Counts of one run: ``skipped`` photos were done by an earlier run."""

    total: int = 0
    skipped: int = 0
    done: int = 0
    failed: int = 0
    seconds: float = 0.0  # wall time of the run
    photo_seconds: float = 0.0  # the workers' time on the photos rendered
    kinds: collections.Counter = field(default_factory=collections.Counter)

    def add(self, row: dict[str, Any]) -> None:
        if row.get("status") == DONE:
            self.done += 1
        else:
            self.failed += 1
            self.kinds[row.get("error_kind") or "unknown"] += 1
        self.photo_seconds += float(row.get("seconds") or 0.0)

    @property
    def throughput(self) -> float:
        """Photos per second of wall time, done and failed."""
        n = self.done + self.failed
        return n / self.seconds if self.seconds > 0 else 0.0

    def lines(self) -> list[str]:
        n = self.done + self.failed
        out = [
            f"{self.done} rendered, {self.failed} failed, {self.skipped} already done "
            f"(of {self.total} photos)",
        ]
        if n:
            out.append(
                f"{self.seconds:.1f} s: {self.throughput:.3f} photos/s "
                f"({self.photo_seconds / n:.2f} s per photo in a worker)"
            )
        if self.kinds:
            kinds = ", ".join(f"{k} {v}" for k, v in self.kinds.most_common())
            out.append(f"failures by kind: {kinds}")
        return out
