"""Small files that must not hold a core or the memory.

* A 16-bit PNG decodes in a time that follows its pixel count, whatever its shape and its
  scanline filters: a line of 200,000 pixels, Paeth or Average filtered, within a small
  factor of a square file of the same pixel count (a ratio measured in the same run).
* The smallest side and the pixel caps are checked from the header, before decoding: the
  app refuses a 12,000,000 x 1 line (105 KB) at once.
* A TIFF depth map's page is checked from its header (the pixel limit, the photo's aspect)
  before any pixel is decoded, on every surface (``read_depth_array`` / ``load_depth``, the
  app's depth upload, ``d2f render --depth``): each load runs in a child process whose
  address space is capped (``RLIMIT_AS``), and must end in a clean ``ValueError`` naming
  the size.
* A FIFO or a device given as a depth map is refused as what it is.
"""

from __future__ import annotations

import functools
import io
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import _io_writers as writers
import numpy as np
import pytest
from PIL import Image

import d2f_core  # the checkout whose code the children run
from d2f_core.cli import main as cli_main
from d2f_core.io import load_depth, load_image, load_photo, read_depth_array

ROOT = Path(d2f_core.__file__).resolve().parents[1]
#: Address space of a child that imports d2f_core.io (about 180 MB of it is the interpreter,
#: NumPy, Pillow and tifffile); the old decoders took 2.6-2.8 GB for these files.
CHILD_AS = 1 << 30
#: The CLI's child imports torch too (650 MB of address space at rest).
CLI_AS = 2 << 30


def _child(code: str, limit: int, timeout: float = 120.0) -> dict:
    """Run ``code`` (which leaves its answer in ``out``) in a child process under an
    address-space cap; its outcome (``result`` / ``ValueError`` / another exception), the
    message (``out`` itself when it is a list) and the peak resident memory in MB."""
    script = (
        "import json, resource, sys\n"
        "sys.path.insert(0, '.')\n"
        "try:\n"
        + "".join(f"    {line}\n" for line in code.strip().splitlines())
        + "    outcome, message = 'result', out if isinstance(out, list) else repr(out)[:300]\n"
        "except ValueError as exc:\n"
        "    outcome, message = 'ValueError', str(exc)\n"
        "except BaseException as exc:\n"
        "    outcome, message = type(exc).__name__, str(exc)[:300]\n"
        # the peak of this program's own memory: VmHWM starts afresh at exec, where
        # getrusage's ru_maxrss keeps the forking parent's (a test run's 1.2 GB)
        "rss = next(int(l.split()[1]) for l in open('/proc/self/status')\n"
        "           if l.startswith('VmHWM:')) / 1024\n"
        "print(json.dumps({'outcome': outcome, 'message': message, 'rss_mb': rss}))\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    try:
        done = subprocess.run(
            [sys.executable, "-c", script], cwd=ROOT, env=env, preexec_fn=cap,
            capture_output=True, text=True, timeout=timeout,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail(f"the load ran past {timeout:.0f} s")
    lines = done.stdout.strip().splitlines()
    assert lines, f"child died (rc {done.returncode}): {done.stderr[-2000:]}"
    return json.loads(lines[-1])


# ------------------------------------------------------------------------ 16-bit PNG time


def _best_times(files: dict[str, bytes], rounds: int = 5, give_up: float = 50.0) -> dict:
    """Best ``load_image`` time of each file over ``rounds`` rounds, interleaved; stops after
    a round in which a file took ``give_up`` times the first file's best (the old decoder
    took 20 s a line: one round shows it)."""
    best: dict[str, float] = {}
    for _ in range(rounds):
        for key, data in files.items():
            t0 = time.perf_counter()
            load_image(data)
            best[key] = min(best.get(key, float("inf")), time.perf_counter() - t0)
        first = best[next(iter(files))]
        if max(best.values()) > give_up * first:
            break
    return best


class TestPng16Time:
    PIXELS = 200_000

    def _files(self) -> dict[str, bytes]:
        files = {"square 400x500 Paeth": writers.png16_stream(400, 500, 3, ftype=4)}
        for ftype, filt in ((4, "Paeth"), (3, "Average")):
            files[f"200000x1 {filt}"] = writers.png16_stream(self.PIXELS, 1, 3, ftype=ftype)
            files[f"1x200000 {filt}"] = writers.png16_stream(1, self.PIXELS, 3, ftype=ftype)
        return files

    def test_lines_decode_as_fast_as_a_square(self):
        # the audit's files: 200,000 x 1 took 16.7 s, 1 x 200,000 Average 20 s, with a
        # square file of the same pixel count decoded in 0.05 s
        files = self._files()
        assert all(len(d) < 4000 for d in files.values())
        best = _best_times(files)
        square = best["square 400x500 Paeth"]
        slow = {k: round(v / square, 1) for k, v in best.items() if v > 8 * square}
        assert not slow, f"times the square file's {square * 1e3:.1f} ms: {slow}"

    def test_lines_decode_to_the_right_values(self):
        # Pillow decodes these files too, keeping the high byte of each sample: an
        # independent decoder for the shape and the filters
        for key, data in self._files().items():
            ours = np.round(load_image(data) * 65535).astype(np.uint16)
            with Image.open(io.BytesIO(data)) as im:
                pil = np.asarray(im.convert("RGB"))
            assert ours.shape == pil.shape, key
            np.testing.assert_array_equal(ours >> 8, pil, err_msg=key)

    def test_random_lines_every_filter(self):
        rng = np.random.default_rng(5)
        for shape, filters in (((1, 5000, 3), [4]), ((5000, 1, 4), [3, 4, 1, 2, 0])):
            a = rng.integers(0, 65536, shape, dtype=np.uint16)
            if shape[2] == 4:
                a[..., 3] = 65535
            out = load_image(writers.png16_bytes(a, filters=filters))
            np.testing.assert_allclose(out, a[..., :3] / 65535.0, atol=1e-6)


# ------------------------------------------------------------------------ smallest side


@functools.lru_cache(maxsize=4)
def _line_png(width: int, corrupt: bool = False) -> bytes:
    data = writers.png16_stream(width, 1, 3, ftype=4)
    if corrupt:  # image data that no decoder can read: any decoding would say so
        start = data.index(b"IDAT") + 4
        data = data[:start] + b"\x00" * 64 + data[start + 64 :]
    return data


class TestMinSide:
    def test_checked_from_the_header(self):
        # the image data is garbage: the refusal names the side, so nothing was decoded
        data = _line_png(12_000_000, corrupt=True)
        for load in (load_image, lambda d, **k: load_photo(d, **k).image):
            with pytest.raises(ValueError, match="12000000x1 pixels; at least 16 pixels"):
                load(data, min_side=16)
        with pytest.raises(ValueError, match="corrupt"):
            load_image(data)  # the same file without the rule: decoding fails

    def test_app_refuses_the_twelve_megapixel_line_at_once(self, tmp_path):
        # 12,000,000 x 1 Paeth (105 KB), under the app's 12.58 MP cap: the audit measured
        # 17 minutes of one core before the side was checked
        path = tmp_path / "line.png"
        path.write_bytes(_line_png(12_000_000))
        assert path.stat().st_size < 120_000
        got = _child(
            f"from app.imaging import load_photo\nout = load_photo({str(path)!r}, 'line.png')",
            CHILD_AS,
            timeout=60,
        )
        assert got["outcome"] == "ValueError", got
        assert got["message"].startswith("line.png: ") and "at least 16 pixels" in got["message"]
        assert "12000000x1" in got["message"]

    def test_bad_min_side(self):
        with pytest.raises(ValueError, match="min_side"):
            load_image(_line_png(20), min_side=0)


# ------------------------------------------------------------------------ TIFF depth maps


@pytest.fixture(scope="module")
def tiffs(tmp_path_factory) -> dict[int, Path]:
    """Tiled float32 TIFFs of one value, n x n pixels (28 KB for 15000^2, 198 KB for
    40000^2): 225 and 1600 MP, above the 179 MP limit, and 12000^2 = 144 MP, under it."""
    folder = tmp_path_factory.mktemp("tiffs")
    out = {}
    for n in (12000, 15000, 40000):
        out[n] = folder / f"d{n}.tif"
        out[n].write_bytes(writers.tiled_float_tiff(n, n))
    return out


def _refused_unread(path: Path, size: tuple[int, int], says: str) -> None:
    """The map at ``path`` for a photo of ``size`` (H, W), through the library and the app:
    a ValueError that ``says`` so, in a child that stayed under 300 MB."""
    p, (h, w) = str(path), size
    calls = {
        "library": f"from d2f_core.io import load_depth\nout = load_depth({p!r}, size=({h}, {w}))",
        "app": "from app.imaging import load_depth_map\n"
        f"out = load_depth_map({p!r}, ({w}, {h}), name='d.tif')",
    }
    for surface, code in calls.items():
        got = _child(code, CHILD_AS)
        assert got["outcome"] == "ValueError", (surface, got)
        assert says in got["message"], got
        assert got["rss_mb"] < 300, (surface, got)


class TestTiffHeader:
    @pytest.mark.parametrize("n", [15000, 40000])
    def test_above_the_pixel_limit_refused_unread(self, tiffs, n):
        assert tiffs[n].stat().st_size < 250_000
        for call in ("read_depth_array(p)", "load_depth(p, size=(n, n))"):
            got = _child(
                f"from d2f_core.io import load_depth, read_depth_array\n"
                f"p, n = {str(tiffs[n])!r}, {n}\nout = {call}",
                CHILD_AS,
            )
            assert got["outcome"] == "ValueError", got
            assert f"{n}x{n} = {n * n} pixels, more than the limit" in got["message"], got
            assert got["rss_mb"] < 300, got

    def test_aspect_checked_before_decoding(self, tiffs):
        # 144 MP, under the limit, but square, for a 64x48 photo: the old code decoded it
        # (2.8 GB) before it compared the shapes
        _refused_unread(tiffs[12000], (48, 64), "depth map is 12000x12000 but the image is 64x48")

    def test_a_map_far_larger_than_the_photo_refused_unread(self, tiffs):
        # 144 MP, under the limit and the photo's aspect, for a 64x64 photo: read, it took
        # 5.9 GB (a map is resized to its photo; one over 4x the photo's pixels, and over
        # 4096^2, adds nothing)
        says = "depth map is 12000x12000 = 144000000 pixels for a 64x64 photo"
        _refused_unread(tiffs[12000], (64, 64), says)
        # as large as the floor: read whatever the photo (a 4096^2 map for a 64x64 photo)
        from d2f_core.io.depth_files import _check_map_header

        _check_map_header((4096, 4096), (64, 64), "d.tif")
        with pytest.raises(ValueError, match="more than 4 times the photo's pixels"):
            _check_map_header((4096, 4097), (64, 64), "d.tif")
        _check_map_header((6000, 8000), (3000, 4000), "d.tif")  # 4x a 12 MP photo

    @pytest.mark.slow
    def test_cli_one_line(self, tiffs, tmp_path):
        photo = tmp_path / "p.png"
        rng = np.random.default_rng(0)
        Image.fromarray((rng.random((48, 64, 3)) * 255).astype(np.uint8)).save(photo)
        cases = {
            12000: "depth map is 12000x12000 but the image is 64x48",
            15000: "15000x15000 = 225000000 pixels, more than the limit",
        }
        for n, says in cases.items():
            argv = ["render", str(photo), "-o", str(tmp_path / "o.png"), "--blur", "5"]
            argv += ["--depth", str(tiffs[n])]
            got = _child(
                "import contextlib, io\nfrom d2f_core.cli import main\nerr = io.StringIO()\n"
                f"with contextlib.redirect_stderr(err):\n    code = main({argv!r})\n"
                "out = [code, err.getvalue()]",
                CLI_AS,
            )
            assert got["outcome"] == "result", got
            code, err = got["message"]
            assert code == 1 and err.strip().count("\n") == 0, err
            assert says in err and "Traceback" not in err, err
            assert got["rss_mb"] < 800, got

    def test_tiled_tiff_decodes(self, tmp_path):
        # 600 x 500 in 256-pixel tiles (edge tiles padded), each tile its own value
        data = writers.tiled_float_tiff(600, 500, 256, lambda ty, tx: 10 * ty + tx + 1)
        want = np.empty((500, 600))
        for ty in range(2):
            for tx in range(3):
                want[ty * 256 : (ty + 1) * 256, tx * 256 : (tx + 1) * 256] = 10 * ty + tx + 1
        np.testing.assert_array_equal(read_depth_array(data), want)
        np.testing.assert_array_equal(read_depth_array(data, size=(1000, 1200)), want)
        with pytest.raises(ValueError, match="depth map is 600x500 but the image is 64x48"):
            read_depth_array(data, size=(48, 64))
        d = load_depth(data, size=(250, 300))
        assert d.shape == (250, 300) and d[0, 0] == 0.0 and d[-1, -1] == 1.0


# ------------------------------------------------------------------------ not files


def _with_deadline(fn, seconds: float = 20.0):
    """``fn()`` in a thread; fails the test when it has not returned after ``seconds`` (a
    reader blocked on a FIFO)."""
    done: dict = {}

    def run():
        try:
            done["out"] = fn()
        except Exception as exc:  # handed to the caller
            done["out"] = exc

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(seconds)
    if worker.is_alive():
        pytest.fail("blocked reading a special file")
    return done["out"]


class TestNotFiles:
    @pytest.fixture
    def fifo(self, tmp_path) -> Path:
        path = tmp_path / "depth.png"
        os.mkfifo(path)
        return path

    def test_library_says_what_it_is(self, fifo):
        for fn in (load_depth, read_depth_array, load_image):
            out = _with_deadline(lambda fn=fn: fn(fifo))
            assert isinstance(out, ValueError), out
            assert str(out) == f"{fifo}: is a FIFO (named pipe), not a regular file"
        if os.path.exists("/dev/null"):
            out = _with_deadline(lambda: load_depth("/dev/null"))
            assert str(out) == "/dev/null: is a device, not a regular file"

    def test_cli_says_what_it_is(self, fifo, tmp_path, capsys):
        photo = tmp_path / "p.png"
        Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(photo)
        targets = [(fifo, "is a FIFO (named pipe), not a regular file")]
        if os.path.exists("/dev/null"):
            targets.append((Path("/dev/null"), "is a device, not a regular file"))
        for target, says in targets:
            argv = ["render", str(photo), "-o", str(tmp_path / "o.png"), "--blur", "5"]
            argv += ["--depth", str(target)]
            code = _with_deadline(lambda argv=argv: cli_main(argv))
            err = capsys.readouterr().err
            assert code == 1 and err.strip().count("\n") == 0, err
            assert f"{target}: {says}" in err and "no such file" not in err, err
