"""Which photos a batch renders and where each output goes.

Inputs are folders (``recursive`` descends into subfolders), globs (``photos/**/*.jpg``),
text or CSV files listing paths, or photo files; outputs keep each photo's path relative to
the inputs' root (the folder, the glob's fixed prefix, or the deepest folder that holds every
listed photo).

Output names are unique, compared case-folded (so they stay unique on a case-insensitive file
system), follow from the photos and their order alone (a rerun with the same inputs gets the
same names), and are never the path of a photo or depth map of the run: an output whose own
name is one is refused, a renamed one skips it.
"""

from __future__ import annotations

import csv
import glob
import itertools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..io import READ_EXTENSIONS, SAVE_FORMATS

__all__ = ["LIST_EXTENSIONS", "Job", "find_photos", "plan_jobs"]

#: Extensions of files that list photo paths (one a line, or a CSV column).
LIST_EXTENSIONS = (".txt", ".csv", ".lst", ".list")
#: Columns of a CSV list that hold the path, in order of preference (else the first column).
CSV_PATH_COLUMNS = ("path", "input", "file", "filename")


@dataclass(frozen=True)
class Job:
    """One photo to render.

    Attributes:
        input: the photo's absolute path.
        output: the output's absolute path.
        rel: the output's path relative to the output folder (POSIX separators).
        depth_file: the photo's depth map from ``--depth DIR``, or ``None``.
        given: the photo's path as the inputs named it (relative to the working folder when
            the source was), which the manifest records; ``None`` means ``input``.
    """

    input: str
    output: str
    rel: str
    depth_file: str | None = None
    given: str | None = None

    @property
    def named(self) -> str:
        """The path the manifest records: :attr:`given`, else :attr:`input`."""
        return self.given or self.input


def _hidden(path: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in path.relative_to(root).parts)


def _under(path: Path, folder: Path | None) -> bool:
    if folder is None:
        return False
    try:
        path.resolve().relative_to(folder)
    except ValueError:
        return False
    return True


def _read_list(path: Path) -> list[Path]:
    """The paths a text or CSV list names, relative ones taken from the list's folder."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"input: cannot read the list {os.fspath(path)!r} ({exc})") from exc
    if path.suffix.lower() == ".csv":
        rows = [r for r in csv.reader(text.splitlines()) if r and any(c.strip() for c in r)]
        column = 0
        if rows:
            header = [c.strip().lower() for c in rows[0]]
            named = [header.index(c) for c in CSV_PATH_COLUMNS if c in header]
            if named:
                column, rows = named[0], rows[1:]
        entries = [r[column].strip() for r in rows if len(r) > column]
    else:
        entries = [line.strip() for line in text.splitlines()]
    entries = [e for e in entries if e and not e.startswith("#")]
    return [Path(os.path.join(path.parent, os.path.expanduser(e))) for e in entries]


def _glob_root(pattern: str) -> Path:
    """The folder part of ``pattern`` before its first wildcard."""
    parts = Path(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if glob.has_magic(part):
            break
        fixed.append(part)
    return Path(*fixed) if fixed else Path(".")


def find_photos(
    sources: Sequence[str | os.PathLike],
    *,
    recursive: bool = False,
    exclude: str | os.PathLike | None = None,
) -> tuple[Path, list[Path], list[Path]]:
    """The photos named by ``sources``: ``(root, photos, skipped)``.

    Args:
        sources: folders, globs, list files (:data:`LIST_EXTENSIONS`) or photo files.
        recursive: descend into the subfolders of folder sources (hidden ones are skipped).
        exclude: a folder whose files are never inputs (the output folder).

    Returns:
        The root that outputs are made relative to (absolute), the photos (as the sources
        name them: relative where the source was; sorted within each source; each file once,
        the first naming kept), and the files of folder and glob sources skipped for their
        extension. Listed paths are kept whatever their extension or existence: a listed
        file that cannot be read becomes a failed photo, not a silent omission.

    Raises:
        ValueError: a source is neither an existing folder, file nor a glob, a glob or
            folder names nothing, or all it names lies in ``exclude``.
    """
    if not sources:
        raise ValueError("sources: expected at least one folder, glob or list of photos")
    banned = None if exclude is None else Path(exclude).resolve()
    roots: list[Path] = []
    photos: list[Path] = []
    skipped: list[Path] = []
    for source in sources:
        text = os.fspath(source)
        path = Path(text).expanduser()
        if path.is_dir():
            root = path
            pattern = "**/*" if recursive else "*"
            found = sorted(p for p in path.glob(pattern) if p.is_file() and not _hidden(p, path))
        elif path.is_file() and path.suffix.lower() in LIST_EXTENSIONS:
            listed = _read_list(path)
            if not listed:
                raise ValueError(f"input: the list {text!r} names no photo")
            photos.extend(listed)
            roots.append(Path(os.path.commonpath([os.path.abspath(p.parent) for p in listed])))
            continue
        elif path.is_file():
            photos.append(path)
            roots.append(path.parent)
            continue
        elif glob.has_magic(text):
            root = _glob_root(text)
            found = sorted(Path(p) for p in glob.glob(text, recursive=True) if Path(p).is_file())
            if not found:
                raise ValueError(f"input: the glob {text!r} matches no file")
        else:
            raise ValueError(
                f"input: {text!r} is not a folder, a glob or a list of photos "
                f"({', '.join(LIST_EXTENSIONS)})"
            )
        kept = [p for p in found if not _under(p, banned)]
        if found and not kept:
            raise ValueError(
                f"input: every file of {text!r} lies in the output folder {exclude}, whose "
                "files are never inputs; choose another -o"
            )
        found = kept
        photos.extend(p for p in found if p.suffix.lower() in READ_EXTENSIONS)
        skipped.extend(p for p in found if p.suffix.lower() not in READ_EXTENSIONS)
        roots.append(root)
    unique: dict[str, Path] = {}
    for p in photos:
        unique.setdefault(os.path.abspath(p), p)
    root = Path(os.path.commonpath([os.path.abspath(r) for r in roots]))
    return root, list(unique.values()), skipped


def _depth_for(depth_dir: Path, rel_parent: Path, stem: str) -> Path | None:
    from ..photo_render import find_depth_file

    for folder in dict.fromkeys((depth_dir / rel_parent, depth_dir)):
        found = find_depth_file(folder, stem) if folder.is_dir() else None
        if found is not None:
            return found
    return None


def _key(path: str | os.PathLike) -> str:
    """What two paths of one file share: the real path (links resolved), case-folded, so a
    case-insensitive file system's two spellings of one name are one key (on a case-sensitive
    one, names differing only in case count as one too: safe, never lossy)."""
    return os.path.normcase(os.path.realpath(path)).casefold()


def _inode(path: str | os.PathLike) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _names(stem: str, tag: str, suffix: str, ext: str):
    """Candidate output names, in order: ``STEM<suffix>.EXT``, then with the input's
    extension (``STEM_png<suffix>.EXT``), then numbered (``STEM_png_2<suffix>.EXT``, ...)."""
    yield f"{stem}{suffix}{ext}"
    base = f"{stem}_{tag}" if tag else stem
    if tag:
        yield f"{base}{suffix}{ext}"
    for n in itertools.count(2):
        yield f"{base}_{n}{suffix}{ext}"


def plan_jobs(
    root: str | os.PathLike,
    photos: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    suffix: str = "_bokeh",
    fmt: str | None = None,
    depth_dir: str | os.PathLike | None = None,
) -> list[Job]:
    """One :class:`Job` per photo: ``out_dir / <path relative to root> / STEM<suffix>.EXT``.

    EXT is ``fmt``, else the photo's own when it can be written, else ``jpg``. A depth map is
    looked up by the photo's stem in ``depth_dir``'s matching subfolder, then in ``depth_dir``
    itself.

    Output paths are unique, compared case-folded. A photo whose name is taken by an earlier
    photo's output (``a.jpg`` and ``a.png`` with ``fmt="jpg"``, or ``a.JPG`` and ``a.jpg``)
    gets the input's extension in the name (``a_png_bokeh.jpg``), then a number
    (``a_jpg_2_bokeh.jpg``), whichever is free first. Names follow from the photos and their
    order alone, so the same inputs get the same names on every run. No output is the path of
    a photo or depth map of the run (compared by real path, case-folded, and by file
    identity): a renamed output skips such a name, and a photo whose own output name is one
    is refused.

    Raises:
        ValueError: ``suffix`` holds a path separator, ``fmt`` is not a writable format, a
            photo is not under ``root``, or a photo's output would be an input of the run
            (naming both).
    """
    if "/" in suffix or os.sep in suffix:
        raise ValueError(f"suffix: must not contain a path separator, got {suffix!r}")
    if fmt is not None and "." + fmt.lstrip(".").lower() not in SAVE_FORMATS:
        raise ValueError(f"fmt: expected one of {sorted(SAVE_FORMATS)}, got {fmt!r}")
    base = Path(os.path.abspath(root))
    out = Path(os.path.abspath(out_dir))
    planned = []
    for photo in photos:
        src = Path(os.path.abspath(photo))
        try:
            rel_parent = src.parent.relative_to(base)
        except ValueError:
            raise ValueError(
                f"photos: {os.fspath(src)!r} is not under {os.fspath(base)!r}"
            ) from None
        depth = None
        if depth_dir is not None:
            depth = _depth_for(Path(depth_dir), rel_parent, src.stem)
        planned.append((photo, src, rel_parent, depth))
    # every file the run reads, which no output may be
    inputs = [src for _, src, _, _ in planned] + [d for *_, d in planned if d is not None]
    banned = {_key(p): p for p in inputs}
    inodes = {i for i in map(_inode, inputs) if i is not None}

    def is_input(path: Path) -> Path | None:
        found = banned.get(_key(path))
        if found is None and path.exists() and _inode(path) in inodes:
            found = path
        return found

    used: set[str] = set()
    jobs = []
    for photo, src, rel_parent, depth in planned:
        ext = src.suffix.lower()
        if fmt:
            ext = "." + fmt.lstrip(".").lower()
        elif ext not in SAVE_FORMATS:
            ext = ".jpg"
        tag = src.suffix.lstrip(".").lower()
        for n, name in enumerate(_names(src.stem, tag, suffix, ext)):
            rel = (rel_parent / name).as_posix()
            if rel.casefold() in used:
                continue
            replaced = is_input(out / rel)
            if replaced is None:
                break
            if n == 0:
                target = os.fspath(out / rel)
                same = os.fspath(replaced) == target
                raise ValueError(
                    f"the output of {os.fspath(photo)} would be {target}, which is "
                    + ("" if same else f"{os.fspath(replaced)}, ")
                    + "an input of this run; outputs never replace inputs: choose another -o "
                    "or --suffix"
                )
        used.add(rel.casefold())
        jobs.append(
            Job(
                os.fspath(src),
                os.fspath(out / rel),
                rel,
                depth and os.fspath(depth),
                given=os.fspath(photo),
            )
        )
    return jobs
