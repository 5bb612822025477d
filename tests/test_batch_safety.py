"""What ``d2f batch`` promises: inputs (photos and depth maps) are never written, outputs never
collide, a rerun after a kill or a move of the output folder finishes the job with nothing
lost, a rerun with other settings is refused unless ``--force``, damaged manifest rows are
skipped with a warning. Small photos made here, the tiny seeded checkpoint, one worker in
the test's own process."""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import os
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from d2f_core.batch import FIELDS, find_photos, plan_jobs, read_rows
from d2f_core.batch.manifest import fold_parts, parts_dir, rows_by_output
from d2f_core.cli import main
from d2f_core.io import save_depth


def _photo(path: Path, seed: int, h: int = 24, w: int = 32) -> Path:
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((rng.random((h, w, 3)) * 255).astype(np.uint8)).save(path, quality=95)
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _tree(folder: Path) -> dict[str, str]:
    """Checksums of every file under ``folder`` (manifest included)."""
    return {p.relative_to(folder).as_posix(): _sha(p) for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def batch(tiny_checkpoint, capsys, one_thread):
    """``d2f batch ARGV`` in this process on one worker: ``(exit status, stderr lines)``."""

    def run(*argv, blur=("--blur", "2")) -> tuple[int, list[str]]:
        args = ["batch", *map(os.fspath, (*argv, *blur)), "--weights", os.fspath(tiny_checkpoint),
                "--workers", "1", "--threads", "1"]  # fmt: skip
        code = main(args)
        err = capsys.readouterr().err
        assert "Traceback" not in err
        return code, err.strip().splitlines()

    return run


def _summary(err: list[str]) -> str:
    return next(line for line in err if " rendered, " in line)


# --------------------------------------------------------------------------- 1. inputs


class TestInputsAreNeverWritten:
    def test_an_output_named_like_another_photo_is_refused(self, tmp_path, batch, monkeypatch):
        """``same/a.png same/a_bokeh.jpg -o same --format jpg``: a.png's output would be the
        user's other photo."""
        monkeypatch.chdir(tmp_path)
        same = tmp_path / "same"
        _photo(same / "a.png", 1)
        _photo(same / "a_bokeh.jpg", 2)
        before = _tree(same)
        code, err = batch("same/a.png", "same/a_bokeh.jpg", "-o", "same", "--format", "jpg")
        assert code == 2
        assert len(err) == 1 and err[0].startswith("d2f: error:")
        assert "same/a.png" in err[0] and "a_bokeh.jpg" in err[0]
        assert _tree(same) == before  # nothing written, nothing replaced
        # the same photos through a list
        (tmp_path / "picks.txt").write_text("same/a.png\nsame/a_bokeh.jpg\n")
        code, err = batch("picks.txt", "-o", "same", "--format", "jpg")
        assert code == 2 and len(err) == 1 and "a_bokeh.jpg" in err[0]
        assert _tree(same) == before

    def test_case_folded_and_depth_maps(self, tmp_path, batch):
        same = tmp_path / "same"
        _photo(same / "a.png", 1)
        _photo(same / "A_BOKEH.JPG", 2)  # the same name on a case-insensitive file system
        before = _tree(same)
        code, err = batch(same / "a.png", same / "A_BOKEH.JPG", "-o", same, "--format", "jpg")
        assert code == 2 and len(err) == 1 and "A_BOKEH.JPG" in err[0]
        assert _tree(same) == before
        # a depth map of the run: --suffix _depth into the maps' folder
        maps = tmp_path / "maps"
        maps.mkdir()
        save_depth(
            maps / "p_depth.png", np.linspace(0, 1, 24 * 32, dtype=np.float32).reshape(24, 32)
        )
        _photo(tmp_path / "lib" / "p.png", 3)
        before = _tree(maps)
        code, err = batch(tmp_path / "lib", "-o", maps, "--depth", maps, "--suffix", "_depth")
        assert code == 2 and len(err) == 1 and "p_depth.png" in err[0]
        assert _tree(maps) == before

    def test_plan_refuses_only_its_own_name_and_skips_inputs_when_renaming(self, tmp_path):
        """A renamed candidate that is an input is passed over, not refused."""
        same = tmp_path / "same"
        names = ["a.jpg", "a.png", "a_png_bokeh.jpg"]
        photos = [_photo(same / n, i) for i, n in enumerate(names)]
        jobs = plan_jobs(same, photos, same, fmt="jpg")
        rels = [j.rel for j in jobs]
        assert rels == ["a_bokeh.jpg", "a_png_2_bokeh.jpg", "a_png_bokeh_bokeh.jpg"]
        assert not {r.casefold() for r in rels} & {n.casefold() for n in names}


# --------------------------------------------------------------------------- 2. collisions


def _check_unique(jobs, inputs) -> None:
    folded = [j.rel.casefold() for j in jobs]
    assert len(set(folded)) == len(jobs), sorted(folded)
    banned = {os.path.abspath(p).casefold() for p in inputs}
    assert not {j.output.casefold() for j in jobs} & banned


class TestOutputsNeverCollide:
    def test_list_and_case_variants(self, tmp_path):
        lib = tmp_path / "lib"
        for i, n in enumerate(["a_png.jpg", "a.jpg", "a.png"]):
            _photo(lib / n, i)
        (lib / "list.txt").write_text("a_png.jpg\na.jpg\na.png\n")
        root, photos, _ = find_photos([lib / "list.txt"])
        jobs = plan_jobs(root, photos, tmp_path / "out", fmt="jpg")
        assert [Path(j.input).name for j in jobs] == ["a_png.jpg", "a.jpg", "a.png"]
        _check_unique(jobs, photos)
        assert jobs[0].rel == "a_png_bokeh.jpg" and jobs[1].rel == "a_bokeh.jpg"
        # a folder of a.JPG, a.Jpg, a.jpg (a case-sensitive file system holds all three)
        case = tmp_path / "case"
        for i, n in enumerate(["a.JPG", "a.Jpg", "a.jpg"]):
            _photo(case / n, i)
        root, photos, _ = find_photos([case])
        assert len(photos) == 3
        jobs = plan_jobs(root, photos, tmp_path / "out2")
        _check_unique(jobs, photos)
        # subfolders that differ only in case are one folder on such a file system
        both = [_photo(tmp_path / "sub" / d / "x.jpg", i) for i, d in enumerate(["A", "a"])]
        _check_unique(plan_jobs(tmp_path / "sub", both, tmp_path / "out3"), both)

    def test_many_same_stem_files_deterministic(self, tmp_path):
        """Photos of random names over a tiny alphabet (stems that are other photos'
        renamed outputs among them), output into their own folder: unique, never an input,
        the same on a second plan."""
        rng = random.Random(7)
        stems = ["a", "A", "a_jpg", "a_png", "a_jpg_2", "a_bokeh", "a_png_bokeh"]
        exts = [".jpg", ".JPG", ".Jpg", ".png", ".PNG", ".tif", ".webp", ".jpeg"]
        names = sorted({rng.choice(stems) + rng.choice(exts) for _ in range(60)})
        folder = tmp_path / "lib"
        folder.mkdir()
        for n in names:
            (folder / n).write_bytes(b"")  # names are all a plan reads
        photos = sorted(folder.iterdir())
        for fmt, suffix in itertools.product((None, "jpg", "png"), ("_bokeh", "")):
            if not suffix and fmt is None:
                with pytest.raises(ValueError, match="an input of this run"):
                    plan_jobs(folder, photos, folder, fmt=fmt, suffix=suffix)
                continue
            try:
                jobs = plan_jobs(folder, photos, folder, fmt=fmt, suffix=suffix)
            except ValueError as exc:  # a photo whose own output name is another photo
                assert "an input of this run" in str(exc)
                continue
            assert len(jobs) == len(photos)
            _check_unique(jobs, photos)
            again = plan_jobs(folder, photos, folder, fmt=fmt, suffix=suffix)
            assert [j.rel for j in again] == [j.rel for j in jobs]
        jobs = plan_jobs(folder, photos, tmp_path / "out", fmt="jpg")
        _check_unique(jobs, photos)
        assert len(jobs) == len(names) > 20

    def test_every_photo_rendered_and_rerun_matches(self, tmp_path, batch):
        """The audit's list: 3 photos, 3 outputs of 3 different renders, 3 rows; a rerun
        finds all three done."""
        lib = tmp_path / "lib"
        for i, n in enumerate(["a_png.jpg", "a.jpg", "a.png"]):
            _photo(lib / n, i)
        (lib / "list.txt").write_text("a_png.jpg\na.jpg\na.png\n")
        out = tmp_path / "out"
        code, err = batch(lib / "list.txt", "-o", out, "--format", "jpg")
        assert code == 0 and "3 rendered, 0 failed" in _summary(err)
        written = sorted(p.name for p in out.glob("*.jpg"))
        assert len(written) == 3
        rows = read_rows(out / "manifest.jsonl")
        assert sorted(r["output"] for r in rows) == written
        assert len({_sha(out / r["output"]) for r in rows}) == 3
        code, err = batch(lib / "list.txt", "-o", out, "--format", "jpg")
        assert code == 0 and "0 rendered, 0 failed, 3 already done" in _summary(err)


# --------------------------------------------------------------------------- 3. manifest rows


def _row(**values) -> dict:
    row = {k: None for k in FIELDS}
    row.update(input="lib/p.png", output="p_bokeh.png", status="done", bytes=10)
    row.update(values)
    return row


class TestDamagedRows:
    def test_malformed_rows_are_skipped_with_their_line(self, tmp_path, batch):
        _photo(tmp_path / "lib" / "p.png", 1)
        out = tmp_path / "out"
        assert batch(tmp_path / "lib", "-o", out)[0] == 0
        manifest = out / "manifest.jsonl"
        good = manifest.read_text()
        bad = [
            json.dumps(_row(input=["x"])),  # the audit's row
            json.dumps([1, 2]),
            json.dumps("a string"),
            json.dumps({"input": "lib/p.png", "status": "done"}),  # keys missing
            json.dumps(_row(bytes="2396")),
            json.dumps(_row(status="finished")),
            json.dumps(_row(settings=[1])),
            json.dumps(_row())[:30],  # cut short
        ]
        manifest.write_text(good + "\n".join(bad) + "\n")
        code, err = batch(tmp_path / "lib", "-o", out)
        assert code == 0, err
        assert "0 rendered, 0 failed, 1 already done" in _summary(err)
        warnings = [line for line in err if line.startswith("d2f: warning:")]
        assert len(warnings) == len(bad)
        first = good.count("\n") + 1
        for number, line in enumerate(warnings, first):
            assert f"manifest.jsonl line {number} skipped" in line
        assert len(read_rows(manifest)) == good.count("\n")

    def test_a_part_folded_after_a_cut_line_keeps_its_row(self, tmp_path):
        manifest = tmp_path / "manifest.jsonl"
        manifest.write_text(json.dumps(_row(output="a.png")) + "\n" + json.dumps(_row())[:25])
        parts = parts_dir(manifest)
        parts.mkdir()
        (parts / "host-1-x.jsonl").write_text(json.dumps(_row(output="b.png")) + "\n")
        assert fold_parts(manifest) == 1
        assert [r["output"] for r in read_rows(manifest)] == ["a.png", "b.png"]


# --------------------------------------------------------------------------- 4. outputs changed


def test_a_truncated_or_replaced_output_is_rendered_again(tmp_path, batch):
    for i in range(2):
        _photo(tmp_path / "lib" / f"p{i}.png", i)
    out = tmp_path / "out"
    assert batch(tmp_path / "lib", "-o", out)[0] == 0
    whole = {n: (out / n).read_bytes() for n in ("p0_bokeh.png", "p1_bokeh.png")}
    (out / "p0_bokeh.png").write_bytes(whole["p0_bokeh.png"][:100])  # truncated
    _photo(out / "p1_bokeh.png", 9, 48, 64)  # replaced by another picture
    code, err = batch(tmp_path / "lib", "-o", out)
    assert code == 0 and "2 rendered, 0 failed, 0 already done" in _summary(err)
    for name, data in whole.items():  # renders of one thread are the same bytes
        assert (out / name).read_bytes() == data
        Image.open(io.BytesIO(data)).load()


# --------------------------------------------------------------------------- 5. moved folder


class TestMovedOutputFolder:
    def test_rows_are_relative_and_a_moved_folder_is_done(self, tmp_path, batch, monkeypatch):
        monkeypatch.chdir(tmp_path)
        for i in range(3):
            _photo(tmp_path / "lib" / f"p{i}.png", i)
        assert batch("lib", "-o", "out")[0] == 0
        rows = read_rows(tmp_path / "out" / "manifest.jsonl")
        assert sorted((r["input"], r["output"]) for r in rows) == [
            (f"lib/p{i}.png", f"p{i}_bokeh.png") for i in range(3)
        ]
        shutil.move(tmp_path / "out", tmp_path / "moved")
        before = _tree(tmp_path / "moved")
        code, err = batch("lib", "-o", "moved")
        assert code == 0 and "0 rendered, 0 failed, 3 already done" in _summary(err)
        assert _tree(tmp_path / "moved") == before
        # the same inputs named absolutely, and a missing output rendered again
        (tmp_path / "moved" / "p1_bokeh.png").unlink()
        code, err = batch(tmp_path / "lib", "-o", tmp_path / "moved")
        assert code == 0 and "1 rendered, 0 failed, 2 already done" in _summary(err)

    def test_manifests_with_absolute_paths_are_read(self, tmp_path, batch):
        """Rows as manifests were written before: absolute paths, no settings. They count
        as done (with a warning that their settings are unknown); --force renders them."""
        lib, out = tmp_path / "lib", tmp_path / "out"
        for i in range(2):
            _photo(lib / f"p{i}.png", i)
        assert batch(lib, "-o", out)[0] == 0
        manifest = out / "manifest.jsonl"
        rows = read_rows(manifest)
        old = []
        for r in rows:
            absolute = {"input": os.fspath(lib / Path(r["input"]).name),
                        "output": os.fspath(out / r["output"])}  # fmt: skip
            old.append({k: r[k] for k in FIELDS if k != "settings"} | absolute)
        manifest.write_text("".join(json.dumps(r) + "\n" for r in old))
        assert sorted(rows_by_output(read_rows(manifest), out)) == ["p0_bokeh.png", "p1_bokeh.png"]
        before = _tree(out)
        code, err = batch(lib, "-o", out)
        assert code == 0 and "0 rendered, 0 failed, 2 already done" in _summary(err)
        assert any("recorded no settings" in line for line in err) and _tree(out) == before
        code, err = batch(lib, "-o", out, "--force")
        assert code == 0 and "2 rendered, 0 failed, 0 already done" in _summary(err)


# --------------------------------------------------------------------------- 6. settings


def test_a_rerun_with_other_settings_is_refused_unless_force(tmp_path, batch):
    """f/2, then f/4 into the same folder: refused, nothing written; --force renders those
    done at f/2 and keeps those done at f/4, so a killed --force run resumes."""
    lib, out, maps = tmp_path / "lib", tmp_path / "out", tmp_path / "maps"
    maps.mkdir()
    ramp = np.tile(np.linspace(0, 1, 128, dtype=np.float32), (96, 1))  # near on the right
    for i in range(3):
        _photo(lib / f"p{i}.png", i, 96, 128)
        save_depth(maps / f"p{i}_depth.png", ramp)
    # the same depth maps and focus: only the f-number differs
    f2, f4 = (("--f-number", n, "--depth", maps, "--focus", "1") for n in ("2", "4"))
    assert batch(lib, "-o", out, blur=f2)[0] == 0
    rows = read_rows(out / "manifest.jsonl")
    assert [r["settings"]["f_number"] for r in rows] == [2.0] * 3
    at_f2 = _tree(out)
    code, err = batch(lib, "-o", out, blur=f4)
    assert code == 2 and len(err) == 1, err
    assert "--force" in err[0] and "f_number 2.0 -> 4.0" in err[0] and "3 of 3" in err[0]
    assert _tree(out) == at_f2  # nor a row added

    # one photo at f/4 (the start of a --force run that was killed)
    code, err = batch(os.fspath(lib / "p0.*"), "-o", out, "--force", blur=f4)
    assert code == 0 and "1 rendered" in _summary(err)
    code, err = batch(lib, "-o", out, blur=f4)
    assert code == 2 and "2 of 3 photos" in err[0]
    code, err = batch(lib, "-o", out, "--force", blur=f4)
    assert code == 0 and "2 rendered, 0 failed, 1 already done" in _summary(err)
    at_f4 = _tree(out)
    for i in range(3):  # every output is another render now
        assert at_f4[f"p{i}_bokeh.png"] != at_f2[f"p{i}_bokeh.png"]
    code, err = batch(lib, "-o", out, blur=f4)
    assert code == 0 and "0 rendered, 0 failed, 3 already done" in _summary(err)
    # --jpeg-quality changes no PNG: not another setting for these outputs
    code, err = batch(lib, "-o", out, "--jpeg-quality", "70", blur=f4)
    assert code == 0 and "3 already done" in _summary(err)
    assert _tree(out) == at_f4


def test_a_fifo_in_the_depth_folder_fails_its_photo_by_name(tmp_path, batch):
    """A FIFO named as a photo's depth map is that photo's failed row, named as a FIFO; the
    photo is never rendered from the network's map instead, and the others are rendered."""
    _photo(tmp_path / "lib" / "a.png", 1)
    _photo(tmp_path / "lib" / "b.png", 2)
    maps = tmp_path / "maps"
    maps.mkdir()
    save_depth(maps / "b.png", np.tile(np.linspace(0, 1, 32, dtype=np.float32), (24, 1)))
    os.mkfifo(maps / "a.png")
    code, err = batch(tmp_path / "lib", "-o", tmp_path / "out", "--depth", maps)
    assert code != 0
    assert "1 rendered, 1 failed" in _summary(err)
    assert any("a.png" in line and "FIFO" in line for line in err), err
    assert not (tmp_path / "out" / "a_bokeh.png").exists()
    assert (tmp_path / "out" / "b_bokeh.png").is_file()
