"""The batch manifest: one JSON line per photo rendered or failed, and the run's summary.

Each worker appends its rows to a part file of its own (``<manifest>.parts/<host>-<pid>-
<id>.jsonl``), so processes on several machines never write one file; the driver folds the
parts into the manifest at the end of a run, and at the start of the next one when a run was
killed.

A row names its input as the inputs named it and its output relative to the output folder, so
the folder can move. A rerun reads the last row of each output (:func:`rows_by_output`): the
photo is done when that row is ``done`` for the same input, with the same render settings
(:func:`render_settings`), and the output has the size the row recorded. Lines that are not
rows as written here (cut short by a kill, other JSON, wrong types, missing keys) are skipped
with a warning naming the file and line.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import json
import logging
import os
import socket
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
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
    "render_settings",
    "row_problem",
    "rows_by_output",
    "settings_differences",
]

logger = logging.getLogger("d2f_core.batch")

#: The columns of a row, in order.
FIELDS = (
    "input",  # the photo's path as the inputs named it (relative when they were)
    "output",  # the output's path relative to the output folder (POSIX separators)
    "width",  # px rendered (after any --max-pixels downscale); null when it failed
    "height",
    "bytes",  # the output file's size
    "depth_source",  # scene (...), d2f (...), embedded (...), file:PATH (...), transformers:...
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
    "settings",  # the run's render settings (render_settings); null in rows of failures
)
#: Fields a row may lack: manifests written before they existed.
OPTIONAL_FIELDS = frozenset({"settings"})
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
        """Append ``row``; an ``OSError`` (a full disk) names the part file."""
        try:
            if self._file is None:
                self.folder.mkdir(parents=True, exist_ok=True)
                self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (kept open)
            self._file.write(json.dumps({k: row.get(k) for k in FIELDS}) + "\n")
            self._file.flush()
        except OSError as exc:
            self._failed = True
            raise _named(exc, self.path) from None

    def close(self) -> None:
        """Close the part file; after a failed write the same error is not raised again."""
        if self._file is not None:
            file, self._file = self._file, None
            try:
                file.close()
            except OSError as exc:
                if not getattr(self, "_failed", False):
                    raise _named(exc, self.path) from None


def _named(exc: OSError, path: str | os.PathLike) -> OSError:
    """``exc`` naming ``path`` (a failed flush names no file)."""
    if exc.filename:
        return exc
    return type(exc)(exc.errno, exc.strerror or str(exc), os.fspath(path))


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


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _text(value: Any) -> bool:
    return isinstance(value, str)


def _point(value: Any) -> bool:
    return isinstance(value, list) and len(value) == 2 and all(map(_number, value))


#: What each field of a row holds (besides null, allowed for every field but three).
_KINDS = {
    "width": (_count, "a whole number"),
    "height": (_count, "a whole number"),
    "bytes": (_count, "a whole number"),
    "depth_source": (_text, "a string"),
    "focus_point": (_point, "[x, y]"),
    "focus": (_number, "a number"),
    "blur_px": (_number, "a number"),
    "f_number": (_number, "a number"),
    "seconds": (_number, "a number"),
    "error_kind": (_text, "a string"),
    "error": (_text, "a string"),
    "worker": (_text, "a string"),
    "finished": (_number, "a number"),
    "settings": (lambda v: isinstance(v, dict), "an object"),
}


def row_problem(row: Any) -> str | None:
    """Why ``row`` is not a row as the manifest writes it, or ``None`` when it is one.

    A row is a JSON object with every field of :data:`FIELDS` (those of
    :data:`OPTIONAL_FIELDS` may be missing), ``input`` and ``output`` non-empty strings,
    ``status`` ``done`` or ``failed``, and every other field null or of its kind."""
    if not isinstance(row, dict):
        return f"not a JSON object but {type(row).__name__}"
    missing = [k for k in FIELDS if k not in row and k not in OPTIONAL_FIELDS]
    if missing:
        return f"no {', '.join(missing[:3])}" + (
            f" (nor {len(missing) - 3} more)" if len(missing) > 3 else ""
        )
    for key in ("input", "output"):
        if not isinstance(row[key], str) or not row[key]:
            return f"{key} is {json.dumps(row[key])[:40]}, not a path"
    if row["status"] not in (DONE, FAILED):
        return f"status is {json.dumps(row['status'])[:40]}, not {DONE} or {FAILED}"
    for key, (ok, kind) in _KINDS.items():
        value = row.get(key)
        if value is not None and not ok(value):
            return f"{key} is {json.dumps(value)[:40]}, not {kind}"
    return None


def _lines(path: Path) -> Iterator[dict[str, Any]]:
    """The rows of one file; any other line is skipped with a warning naming its number."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            for number, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    row = json.loads(line)
                except json.JSONDecodeError:
                    problem = "not a whole JSON line (cut short by a kill?)"
                else:
                    problem = row_problem(row)
                if problem is not None:
                    logger.warning("%s line %d skipped: %s", path, number, problem)
                    continue
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
    """The last row of each input (as the row names it)."""
    return {row["input"]: row for row in rows}


def rows_by_output(
    rows: Iterable[dict[str, Any]], out_dir: str | os.PathLike
) -> dict[str, dict[str, Any]]:
    """The last row of each output, keyed by its path relative to ``out_dir`` (POSIX).

    Rows name outputs relative to the output folder; an absolute one (manifests written
    before) counts when it lies under ``out_dir``."""
    out = os.path.abspath(out_dir)
    latest: dict[str, dict[str, Any]] = {}
    for row in rows:
        path = row["output"]
        if os.path.isabs(path):
            path = os.path.normpath(path)
            if os.path.commonpath([out, path]) != out or path == out:
                continue
            path = os.path.relpath(path, out)
        latest[PurePosixPath(*Path(os.path.normpath(path)).parts).as_posix()] = row
    return latest


def _end_line(path: Path) -> None:
    """End the last line of ``path`` when a kill cut it short, so the next row appended is a
    line of its own (not glued to the cut one, which would lose both)."""
    try:
        with open(path, "rb+") as f:
            if f.seek(0, os.SEEK_END) == 0:
                return
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                f.write(b"\n")
    except FileNotFoundError:
        return


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
        try:
            _end_line(path)
            with open(path, "a", encoding="utf-8") as f:
                for row in rows:
                    f.write(json.dumps({k: row.get(k) for k in FIELDS}) + "\n")
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:  # the parts are kept: the next fold adds their rows
            raise _named(exc, path) from None
    for p in parts:
        p.unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:  # a file that is not ours
        pass
    return len(rows)


#: The options of ``d2f render`` that change the pixels of an output; a rerun with other
#: values of any of them is refused unless ``--force`` (the names are the parsed options').
SETTINGS = (
    "blur",
    "f_number",
    "focus",
    "focus_position",
    "focus_at",
    "focal_range",
    "aperture_blades",
    "rotation",
    "quality",
    "placement",
    "no_highlight_boost",
    "highlight_boost",
    "no_fusion",
    "depth_kind",
    "near",
    "zero_is_hole",
    "no_embedded_depth",
    "depth_model",
    "no_refine_depth",
    "max_pixels",
    "jpeg_quality",
)
#: Settings that only matter to some output formats.
_FORMAT_SETTINGS = {"jpeg_quality": (".jpg", ".jpeg")}


def _plain(value: Any) -> Any:
    """``value`` as JSON holds it (tuples as lists, paths and depth sources as strings)."""
    if hasattr(value, "kind") and hasattr(value, "name"):  # a DepthSource
        value = value.name
    elif isinstance(value, os.PathLike):
        value = os.fspath(value)
    return json.loads(json.dumps(value, default=str))


def _weights_identity(weights: str | os.PathLike | None) -> dict[str, Any] | None:
    """The network weights a run renders with, by content: ``{"name", "sha256"}``, or
    ``None`` when there are none (photos with depth maps render without them)."""
    if weights is None:
        from ..bundled import shipped_weights

        env = os.environ.get("D2F_WEIGHTS")
        weights = Path(env) if env else shipped_weights()
    path = Path(weights)
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return {"name": path.name, "sha256": digest.hexdigest()[:16]}


def render_settings(args: argparse.Namespace) -> dict[str, Any]:
    """What a manifest row records of the settings that made its output: the options of
    :data:`SETTINGS` as parsed, whether maps came from a ``--depth`` folder (``depth``: the
    maps themselves are not compared), and the weights by content (``weights``: their file's
    name and the start of its SHA-256; a moved copy is the same weights)."""
    settings = {key: _plain(getattr(args, key, None)) for key in SETTINGS}
    settings["depth"] = getattr(args, "depth", None) is not None
    settings["weights"] = _weights_identity(getattr(args, "weights", None))
    return settings


def settings_differences(
    recorded: dict[str, Any], current: dict[str, Any], output: str | os.PathLike = ""
) -> list[str]:
    """``"KEY OLD -> NEW"`` for each setting that differs between a row's and this run's
    (those of :data:`_FORMAT_SETTINGS` only for the formats they change)."""
    ext = os.path.splitext(os.fspath(output))[1].lower()
    out = []
    for key in dict.fromkeys([*current, *recorded]):
        if key in _FORMAT_SETTINGS and ext not in _FORMAT_SETTINGS[key]:
            continue
        old, new = recorded.get(key), current.get(key)
        if old != new:
            out.append(f"{key} {json.dumps(old)} -> {json.dumps(new)}")
    return out


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
        left = self.total - self.skipped - n
        if left > 0:
            out.append(f"{left} not rendered: the run stopped before them")
        return out
