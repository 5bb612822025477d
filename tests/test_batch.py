"""``d2f batch``: inputs and layout, the manifest, resuming after a kill, the local process
pool against Ray Data on a real local cluster (these skip with the reason without Ray)."""

from __future__ import annotations

import io
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from d2f_core.batch import FIELDS, find_photos, last_rows, plan_jobs, read_rows
from d2f_core.cli import main
from d2f_core.io import save_depth
from d2f_core.lens import blur_px, f_number_for

#: The library of the engine tests: photos in two subfolders, two of them broken.
GOOD = [f"a/p{i:02d}.png" for i in range(9)] + [f"b/q{i:02d}.jpg" for i in range(9)]
BROKEN = {"a/truncated.jpg": "truncated", "b/notes.png": "not an image"}
RENDER = ["--blur", "12", "--threads", "1", "-q"]


def _photo(h: int, w: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A textured photo whose left part is near (disparity 1) and right part far (0)."""
    rng = np.random.default_rng(seed)
    img = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    disp = np.zeros((h, w), np.float32)
    disp[:, : w * (1 + seed % 3) // 4] = 1.0
    return img, disp


def _library(root: Path, names=GOOD, h: int = 96, w: int = 128) -> tuple[Path, Path]:
    """Photos under ``root/lib`` and their depth maps under ``root/depth``, same layout."""
    lib, depth = root / "lib", root / "depth"
    for i, name in enumerate(names):
        img, disp = _photo(h, w, i)
        for folder in (lib, depth):
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(lib / name, quality=95)
        save_depth(depth / Path(name).with_name(Path(name).stem + "_depth.png"), disp)
    return lib, depth


def _break(lib: Path) -> None:
    jpeg = lib / "a" / "truncated.jpg"
    Image.fromarray(_photo(96, 128, 99)[0]).save(jpeg, quality=95)
    jpeg.write_bytes(jpeg.read_bytes()[:600])
    (lib / "b" / "notes.png").write_text("a shopping list, not a photo")


def _cli(*argv, timeout: float = 300) -> subprocess.CompletedProcess:
    """``d2f`` in a fresh process, as a user runs it."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "D2F_WEIGHTS": "/nonexistent/weights.pt"}
    cmd = [sys.executable, "-m", "d2f_core.cli", *map(str, argv)]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)


def _outputs(out: Path) -> dict[str, bytes]:
    """The files under an output's name (not the manifest, its parts, partial writes)."""
    files = (p.relative_to(out) for p in sorted(out.rglob("*")) if p.is_file())
    return {
        p.as_posix(): (out / p).read_bytes()
        for p in files
        if p.name != "manifest.jsonl" and not any(part.startswith(".") for part in p.parts)
    }


def _output_name(name: str) -> str:
    path = Path(name)
    return path.with_name(f"{path.stem}_bokeh{path.suffix}").as_posix()


# --------------------------------------------------------------------------- inputs


class TestPlan:
    def test_folder_recursive_keeps_layout_and_skips_hidden_and_output(self, tmp_path):
        lib, _ = _library(tmp_path, ["x.png", "sub/y.jpg", "sub/deeper/z.png", ".hidden/h.png"])
        (lib / "notes.txt").write_text("not a photo")
        out = lib / "rendered"  # inside the input folder: never read back as input
        (out / "sub").mkdir(parents=True)
        Image.fromarray(_photo(8, 8, 0)[0]).save(out / "sub" / "y_bokeh.jpg")
        root, photos, skipped = find_photos([lib], recursive=True, exclude=out)
        assert root == lib
        assert [p.relative_to(lib).as_posix() for p in photos] == [
            "sub/deeper/z.png",
            "sub/y.jpg",
            "x.png",
        ]
        assert [p.name for p in skipped] == ["notes.txt"]
        jobs = plan_jobs(root, photos, out, depth_dir=tmp_path / "depth")
        assert [j.rel for j in jobs] == ["sub/deeper/z_bokeh.png", "sub/y_bokeh.jpg", "x_bokeh.png"]
        assert all(j.output == os.fspath(out / j.rel) for j in jobs)
        assert jobs[1].depth_file == os.fspath(tmp_path / "depth" / "sub" / "y_depth.png")
        _, flat, _ = find_photos([lib])
        assert [p.name for p in flat] == ["x.png"]

    def test_glob_and_lists(self, tmp_path):
        lib, _ = _library(tmp_path, ["s1/a.png", "s1/b.jpg", "s2/c.png"])
        root, photos, _ = find_photos([os.fspath(lib / "*" / "*.png")])
        assert root == lib and [p.name for p in photos] == ["a.png", "c.png"]
        listing = tmp_path / "lib" / "list.txt"
        absolute = os.fspath(lib / "s2" / "c.png")
        listing.write_text(f"# picked\ns1/b.jpg\n\n{absolute}\ngone.png\n")
        root, photos, _ = find_photos([listing])
        assert root == lib
        listed = [p.relative_to(lib).as_posix() for p in photos]
        assert listed == ["s1/b.jpg", "s2/c.png", "gone.png"]
        table = tmp_path / "picks.csv"
        table.write_text("id,Path,stars\n1,lib/s1/a.png,5\n2,lib/s2/c.png,4\n")
        root, photos, _ = find_photos([table])
        assert [p.relative_to(lib).as_posix() for p in photos] == ["s1/a.png", "s2/c.png"]

    def test_name_collisions_and_bad_input(self, tmp_path):
        lib, _ = _library(tmp_path, ["a.png", "a.jpg"])
        root, photos, _ = find_photos([lib])
        jobs = plan_jobs(root, photos, tmp_path / "out", fmt="png")
        assert [j.rel for j in jobs] == ["a_bokeh.png", "a_png_bokeh.png"]
        with pytest.raises(ValueError, match="sources"):
            find_photos([])
        with pytest.raises(ValueError, match="not a folder, a glob or a list"):
            find_photos([tmp_path / "missing"])
        with pytest.raises(ValueError, match="matches no file"):
            find_photos([os.fspath(tmp_path / "*.tiff")])
        with pytest.raises(ValueError, match="suffix"):
            plan_jobs(root, photos, tmp_path / "out", suffix="x/y")
        with pytest.raises(ValueError, match="not under"):
            plan_jobs(tmp_path / "elsewhere", photos, tmp_path / "out")


def test_check_manifest_tells_a_manifest_from_other_files(tmp_path):
    """A manifest is any file that starts with a row, even one cut short by a kill (its
    first write); missing and empty files are new manifests; anything else is refused."""
    from d2f_core.batch.manifest import check_manifest

    row = json.dumps(
        {k: None for k in FIELDS} | {"input": "/photos/a.jpg", "output": "a.jpg", "status": "done"}
    )
    cases = {
        "missing.jsonl": None,
        "empty.jsonl": "",
        "rows.jsonl": f"\n{row}\n{row}\n",
        "cut.jsonl": row[:17],
        # rewritten by another tool: compact, keys in another order, a byte-order mark
        "compact.jsonl": json.dumps({"status": "done", "input": "/a.jpg"}, separators=(",", ":")),
        "bom.jsonl": "\ufeff" + row + "\n",
    }
    for name, text in cases.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        check_manifest(tmp_path / name)
    others = {"list.txt": "a.jpg\n", "table.csv": "id,path\n", "x.json": '{"a": 1}'}
    for name, text in others.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match="is not a d2f manifest"):
            check_manifest(tmp_path / name)
    with pytest.raises(ValueError, match="is a folder"):
        check_manifest(tmp_path)
    assert [r["input"] for r in read_rows(tmp_path / "bom.jsonl")] == ["/photos/a.jpg"]


class TestLens:
    def test_same_numbers_as_the_app(self):
        settings = pytest.importorskip("app.settings", reason="the app needs gradio")
        app_bench = pytest.importorskip("app.bench", reason="the app needs gradio")
        for n in (1.0, 1.4, 2.8, 8.0, 22.0):
            for side in (128, 1536, 4000, 6000):
                assert blur_px(n, side) == settings.blur_px(n, side)
                assert f_number_for(40.0, side) == app_bench.f_number_for(40.0, side)

    def test_bad_input(self):
        with pytest.raises(ValueError, match="f_number"):
            blur_px(0.1, 100)
        with pytest.raises(ValueError, match="long_side"):
            blur_px(2.0, 0)
        assert f_number_for(0.0, 100) is None

    def test_render_with_f_number_is_render_with_its_blur(self, tmp_path, capsys, one_thread):
        lib, depth = _library(tmp_path, ["p.png"])
        dmap = depth / "p_depth.png"
        k = blur_px(2.0, 128)
        for flag, value, name in (("--f-number", 2, "f.png"), ("--blur", k, "k.png")):
            code = main(["render", os.fspath(lib / "p.png"), "-o", os.fspath(tmp_path / name),
                         flag, str(value), "--depth", os.fspath(dmap), "--focus", "1"])  # fmt: skip
            assert code == 0, capsys.readouterr().err
        assert (tmp_path / "f.png").read_bytes() == (tmp_path / "k.png").read_bytes()
        code = main(["render", os.fspath(lib / "p.png"), "-o", os.fspath(tmp_path / "x.png"),
                     "--f-number", "0.1"])  # fmt: skip
        assert code == 2 and "f-number" in capsys.readouterr().err


# --------------------------------------------------------------------------- local engine


@pytest.fixture(scope="module")
def library(tmp_path_factory, tiny_checkpoint):
    """The 20-photo library and one run of the local engine on it (2 workers)."""
    root = tmp_path_factory.mktemp("library")
    lib, depth = _library(root)
    _break(lib)
    out = root / "local"
    run = _cli("batch", lib, "-r", "-o", out, "--depth", depth, "--weights", tiny_checkpoint,
               "--workers", 2, *RENDER[:-1])  # fmt: skip
    return lib, depth, out, run


class TestLocalEngine:
    def test_outputs_manifest_and_summary(self, library):
        lib, _, out, run = library
        assert run.returncode == 1, run.stderr  # two photos failed
        assert "Traceback" not in run.stderr
        assert "18 rendered, 2 failed, 0 already done (of 20 photos)" in run.stderr
        assert "failures by kind:" in run.stderr and "2 of 20 photos failed" in run.stderr
        assert sorted(_outputs(out)) == sorted(_output_name(n) for n in GOOD)
        for data in _outputs(out).values():
            Image.open(io.BytesIO(data)).load()  # whole files
        rows = read_rows(out / "manifest.jsonl")
        assert len(rows) == 20 and all(list(r) == list(FIELDS) for r in rows)
        last = last_rows(rows)
        assert sorted(last) == sorted(os.fspath(lib / n) for n in [*GOOD, *BROKEN])
        assert not (out / ".manifest.jsonl.parts").exists()
        for name in GOOD:
            row = last[os.fspath(lib / name)]
            assert row["status"] == "done" and row["error"] is None
            assert row["output"] == _output_name(name)  # relative to the output folder
            assert (row["width"], row["height"], row["blur_px"]) == (128, 96, 12.0)
            assert row["bytes"] == (out / _output_name(name)).stat().st_size
            assert row["depth_source"].startswith("file:")
            assert (
                Path(name).with_name(Path(name).stem + "_depth.png").as_posix()
                in row["depth_source"]
            )
            assert 0.0 <= row["focus"] <= 1.0 and len(row["focus_point"]) == 2
            assert row["f_number"] == f_number_for(12.0, 128) and row["seconds"] > 0
        for name in BROKEN:
            row = last[os.fspath(lib / name)]
            assert row["status"] == "failed" and row["error_kind"]
            assert Path(name).name in row["error"] and "\n" not in row["error"]
            assert Path(name).name in run.stderr
        assert lib.joinpath("b", "notes.png").read_text() == "a shopping list, not a photo"
        assert not list(out.rglob(".d2f-partial-*"))

    def test_rerun_renders_only_what_is_not_done(self, library, tiny_checkpoint):
        """On the library's own output folder (the end state is the same: one thread per
        worker renders the same bytes)."""
        lib, depth, out, _ = library
        before = _outputs(out)
        (out / _output_name(GOOD[3])).unlink()  # a done photo whose output went missing
        rows = read_rows(out / "manifest.jsonl")
        run = _cli("batch", lib, "-r", "-o", out, "--depth", depth, "--weights", tiny_checkpoint,
                   "--workers", 1, *RENDER[:-1])  # fmt: skip
        assert run.returncode == 1  # the broken ones fail again
        assert "1 rendered, 2 failed, 17 already done (of 20 photos)" in run.stderr
        new = read_rows(out / "manifest.jsonl")[len(rows) :]
        assert sorted(r["input"] for r in new) == sorted(
            os.fspath(lib / n) for n in [GOOD[3], *BROKEN]
        )
        assert _outputs(out) == before

    @pytest.mark.slow
    def test_killed_run_resumes_without_truncated_outputs(self, tmp_path, tiny_checkpoint):
        """SIGKILL to the whole local engine (driver and workers) once some outputs exist; the
        rerun renders only the photos without a done row and an output."""
        names = [f"s{i // 12}/p{i:02d}.png" for i in range(36)]
        lib, depth = _library(tmp_path, names, h=192, w=256)
        out = tmp_path / "out"
        argv = ["batch", lib, "-r", "-o", out, "--depth", depth, "--weights", tiny_checkpoint,
                "--workers", 2, "--blur", 40, "--threads", 1, "-q"]  # fmt: skip
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        cmd = [sys.executable, "-m", "d2f_core.cli", *map(str, argv)]
        proc = subprocess.Popen(cmd, env=env, start_new_session=True, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 240
        while len(list(out.rglob("*_bokeh.png"))) < 4 and proc.poll() is None:
            assert time.monotonic() < deadline, "no outputs after 4 minutes"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"

        rows = read_rows(out / "manifest.jsonl")  # the killed run's parts, not folded yet
        done = {r["input"] for r in rows if r["status"] == "done" and (out / r["output"]).is_file()}
        # an output renamed into place whose row was not written yet counts as not done
        assert 1 <= len(done) < len(names)
        killed = _outputs(out)
        for data in killed.values():  # what carries an output's name is whole
            Image.open(io.BytesIO(data)).load()

        rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert rerun.returncode == 0, rerun.stderr
        new = [r["input"] for r in read_rows(out / "manifest.jsonl")[len(rows) :]]
        missing = [os.fspath(lib / n) for n in names if os.fspath(lib / n) not in done]
        assert sorted(new) == sorted(missing)
        final = _outputs(out)
        assert sorted(final) == sorted(_output_name(n) for n in names)
        for rel, data in killed.items():  # outputs done before the kill are kept as they were
            assert final[rel] == data
        assert not list(out.rglob(".d2f-partial-*"))
        assert not (out / ".manifest.jsonl.parts").exists()

    def test_cli_errors_are_one_line(self, tmp_path, capsys, monkeypatch, one_thread):
        lib, _ = _library(tmp_path, ["p.png"])
        cases = [
            (["batch", os.fspath(tmp_path / "none"), "-o", "o", "--blur", "5"], 2, "not a folder"),
            (["batch", os.fspath(lib), "-o", os.fspath(lib), "--blur", "5"], 2, "differ"),
            (["batch", os.fspath(lib), "-o", "o", "--blur", "5", "--workers", "0"], 2, "positive"),
            (["batch", os.fspath(lib), "-o", "o", "--blur", "5", "--ray-address", "x:1"], 2, "ray"),
        ]
        monkeypatch.chdir(tmp_path)
        for argv, status, words in cases:
            assert main(argv) == status
            err = capsys.readouterr().err
            assert words in err and "Traceback" not in err
            assert err.strip().splitlines()[-1].startswith("d2f: error:")
        # rows are appended only to a manifest: never to a photo, a list, an output or a
        # file of other text, and a glob whose files all lie in -o says so
        listing = tmp_path / "picks.txt"
        listing.write_text(os.fspath(lib / "p.png") + "\n")
        notes = tmp_path / "notes.txt"
        notes.write_text("my notes\n")
        binary = tmp_path / "blob.bin"
        binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
        out = tmp_path / "out"
        refused = [
            ([listing, "--manifest", listing], "is one of the photos, lists or outputs"),
            ([lib, "--manifest", lib / "p.png"], "is one of the photos, lists or outputs"),
            ([lib, "--manifest", out / "p_bokeh.png"], "is one of the photos, lists or outputs"),
            ([lib, "--manifest", notes], "exists and is not a d2f manifest"),
            ([lib, "--manifest", binary], "exists and is not a d2f manifest"),
            ([lib, "--manifest", tmp_path], "is a folder"),
            # a map still to be written by --save-maps, or any picture
            ([lib, "--manifest", tmp_path / "maps" / "p_bokeh_disparity.png"], "image's ext"),
        ]
        kept = {p: p.read_bytes() for p in (listing, notes, binary, lib / "p.png")}
        for args, words in refused:
            argv = ["batch", *map(os.fspath, args), "-o", os.fspath(out), "--blur", "5"]
            assert main(argv) == 2
            err = capsys.readouterr().err
            last = err.strip().splitlines()[-1]
            assert last.startswith("d2f: error:") and words in last, (args, err)
        assert {p: p.read_bytes() for p in kept} == kept and not out.exists()
        assert main(["batch", os.fspath(lib / "*.png"), "-o", os.fspath(lib), "--blur", "5"]) == 2
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert last.startswith("d2f: error:") and "lies in the output folder" in last
        monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
        assert main(["batch", os.fspath(lib), "-o", "o", "--blur", "5", "--engine", "ray"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and 'pip install "d2f[scale]"' in err


# --------------------------------------------------------------------------- Ray engine


@pytest.fixture(scope="module")
def ray_cluster():
    """A real Ray head on this machine (``ray start --head --block``), its address, and the
    environment that reaches it; stopped (its whole process group) at the end."""
    pytest.importorskip("ray.data", reason='Ray is the optional extra "scale"')
    ray_bin = Path(sys.executable).with_name("ray")
    if not ray_bin.is_file():
        pytest.skip(f"no ray command beside {sys.executable}")
    from app.latency_server import free_port

    port = free_port()
    temp = tempfile.mkdtemp(prefix="d2f-ray-", dir="/tmp")  # short: Ray's sockets live in it
    env = {
        **os.environ,
        "RAY_AUTH_MODE": "token",  # a token of the test's own, not ~/.ray/auth_token
        "RAY_AUTH_TOKEN": secrets.token_hex(16),
        "RAY_USAGE_STATS_ENABLED": "0",
        "OMP_NUM_THREADS": "1",
    }
    cmd = [os.fspath(ray_bin), "start", "--head", "--port", str(port), "--block",
           "--node-ip-address", "127.0.0.1", "--num-cpus", "2", "--include-dashboard=false",
           "--disable-usage-stats", "--object-store-memory", str(100 * 2**20),
           "--temp-dir", temp]  # fmt: skip
    log = open(Path(temp) / "start.log", "w+")  # noqa: SIM115 (closed at the end)
    head = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while "--block" not in Path(log.name).read_text():
            if head.poll() is not None or time.monotonic() > deadline:
                pytest.fail("ray start failed:\n" + Path(log.name).read_text()[-3000:])
            time.sleep(0.5)
        yield f"127.0.0.1:{port}", env
    finally:
        # SIGINT: ray start --block stops its processes and exits (in about 1 s)
        for sig, wait in ((signal.SIGINT, 20), (signal.SIGKILL, 10)):
            try:
                os.killpg(head.pid, sig)
            except ProcessLookupError:
                break
            try:
                head.wait(timeout=wait)
                break
            except subprocess.TimeoutExpired:
                continue
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


class TestRayEngine:
    @pytest.mark.slow
    def test_same_outputs_as_local_and_a_complete_manifest(
        self, ray_cluster, library, tmp_path, tiny_checkpoint
    ):
        address, env = ray_cluster
        lib, depth, local_out, _ = library
        out = tmp_path / "ray"
        cmd = [sys.executable, "-m", "d2f_core.cli", "batch", os.fspath(lib), "-r", "-o",
               os.fspath(out), "--depth", os.fspath(depth), "--weights", os.fspath(tiny_checkpoint),
               "--engine", "ray", "--ray-address", address, "--workers", "2", *RENDER]  # fmt: skip
        run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
        assert run.returncode == 1, run.stdout + run.stderr  # two photos failed
        assert "Traceback" not in run.stderr
        assert _outputs(out) == _outputs(local_out)  # bit-identical, 18 outputs
        rows = read_rows(out / "manifest.jsonl")
        assert len(rows) == 20 and all(list(r) == list(FIELDS) for r in rows)
        last = last_rows(rows)
        local = last_rows(read_rows(local_out / "manifest.jsonl"))
        assert sorted(last) == sorted(local)
        for name in GOOD:
            row, twin = last[os.fspath(lib / name)], local[os.fspath(lib / name)]
            assert row["status"] == "done"
            for key in ("width", "height", "bytes", "depth_source", "focus", "focus_point"):
                assert row[key] == twin[key], (name, key)
        for name in BROKEN:
            row = last[os.fspath(lib / name)]
            assert row["status"] == "failed" and Path(name).name in row["error"]
            assert row["error"] == local[os.fspath(lib / name)]["error"]
        assert not list(out.rglob(".d2f-partial-*"))
