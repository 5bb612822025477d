"""Hostile and careless input through the library and the CLI: decompression bombs in the
project's own decoders, headers that claim huge sizes, files that are not regular files,
values that are out of range. Each case is refused with a ``ValueError`` that names the
problem (one line from the CLI), early, in bounded time and memory."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from _io_writers import png16_stream
from PIL import Image

from d2f_core.cli import main as cli_main
from d2f_core.io import load_depth, load_image, load_photo, read_depth_array


def _peak(fn):
    """``(result or exception, peak bytes that Python and NumPy allocated, seconds)``."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        out = fn()
    except Exception as exc:  # returned for the caller to check
        out = exc
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, peak, seconds


# ------------------------------------------------------------------------ 16-bit PNG


class TestPng16Bounds:
    def test_stream_that_inflates_past_the_header_is_bounded(self):
        # 1x1 RGBA whose image data inflates to 64 MiB (the audit's file: 1 GiB from 1 MB):
        # libpng would inflate all of it to ignore it; it is refused once the inflated data
        # passes the header's one row (tests/test_request_bounds.py has the 1x1 RGB one)
        data = png16_stream(1, 1, 4, inflated=64 << 20)
        assert len(data) < 200_000
        out, peak, seconds = _peak(lambda: load_image(data))
        assert isinstance(out, ValueError), out
        assert "image data holds more than the 9 bytes of a 1x1 image" in str(out)
        assert peak < 4 << 20, f"peak {peak / 1e6:.1f} MB"
        assert seconds < 2.0

    def test_exact_stream_still_decodes(self):
        data = png16_stream(40, 30, 3)
        image = load_image(data)
        assert image.shape == (30, 40, 3)
        np.testing.assert_allclose(image[0, 0], [0x8001 / 65535, 0x4002 / 65535, 0x2003 / 65535])

    def test_size_above_the_cap_is_checked_before_decoding(self):
        # 2000x1500 16-bit RGB (36 MB as samples) under a 0.3 MP cap: read by Pillow at 8 bits
        # per channel and reduced, never decoded at full precision
        data = png16_stream(2000, 1500, 3, ftype=4)
        cap = 300_000
        out, peak, seconds = _peak(lambda: load_photo(data, max_pixels=cap))
        assert not isinstance(out, Exception), out
        h, w = out.image.shape[:2]
        assert h * w <= cap and out.info.original_size == (1500, 2000)
        assert out.info.bit_depth == 16
        assert any("16-bit PNG above max_pixels" in c for c in out.info.conversions)
        # the returned picture is 3.6 MB of float32; full precision took over 100 MB
        assert peak < 4 * h * w * 3 * 4, f"peak {peak / 1e6:.1f} MB"
        assert seconds < 5.0


# ------------------------------------------------------------------------ item 4, library


def _npy_claiming(shape: tuple[int, ...], payload: int = 1000) -> bytes:
    """A ``.npy`` file whose header claims ``shape`` float32 values, with ``payload`` bytes."""
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), np.float32))
    header["shape"] = shape
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + b"\x00" * payload


def _run_cli(capsys, *argv) -> tuple[int, str]:
    code = cli_main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def _photo(path: Path, h: int = 48, w: int = 64) -> Path:
    rng = np.random.default_rng(0)
    Image.fromarray((rng.random((h, w, 3)) * 255).astype(np.uint8)).save(path)
    return path


class TestNpyHeader:
    def test_huge_shape_refused_before_allocating(self, tmp_path):
        path = tmp_path / "bomb.npy"
        path.write_bytes(_npy_claiming((100_000, 100_000)))
        out, peak, _ = _peak(lambda: read_depth_array(path))
        assert isinstance(out, ValueError), out  # was MemoryError
        assert "header claims shape (100000, 100000)" in str(out)
        assert peak < 1 << 20

    def test_shape_larger_than_the_file_refused(self, tmp_path):
        path = tmp_path / "short.npy"
        path.write_bytes(_npy_claiming((4000, 3000)))  # 48 MB claimed, 1 KB present
        out, peak, _ = _peak(lambda: load_depth(path))
        assert isinstance(out, ValueError) and "truncated .npy" in str(out), out
        assert peak < 1 << 20

    def test_cli_one_line(self, tmp_path, capsys):
        photo = _photo(tmp_path / "p.png")
        depth = tmp_path / "bomb.npy"
        depth.write_bytes(_npy_claiming((100_000, 100_000)))
        code, err = _run_cli(
            capsys, "render", photo, "-o", tmp_path / "o.png", "--blur", 5, "--depth", depth
        )
        assert code == 1
        assert err.strip().count("\n") == 0, err
        assert "header claims shape (100000, 100000)" in err and "MemoryError" not in err


class TestNotRegularFiles:
    def test_fifo_is_refused_without_hanging(self, tmp_path, capsys):
        fifo = tmp_path / "p.jpg"
        os.mkfifo(fifo)
        done: dict = {}

        def run():
            done["out"] = _run_cli(capsys, "render", fifo, "-o", tmp_path / "o.png", "--blur", 20)

        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        worker.join(10)
        if worker.is_alive():  # unblock the reader that the old code left waiting
            with open(fifo, "wb"):
                pass
            worker.join(5)
            pytest.fail("d2f render on a FIFO hung")
        code, err = done["out"]
        assert code == 1 and "not a regular file" in err

    def test_device_is_refused_unread(self):
        if not os.path.exists("/dev/zero"):
            pytest.skip("no /dev/zero")
        # in a child limited to 2 GB of address space: reading /dev/zero to its end (the old
        # behaviour) fills any memory, which must not take the test machine down
        code = (
            "import resource, time\n"
            "resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"
            "from d2f_core.io import load_image, read_depth_array\n"
            "for fn in (load_image, read_depth_array):\n"
            "    t = time.perf_counter()\n"
            "    try:\n"
            "        fn('/dev/zero')\n"
            "    except ValueError as exc:\n"
            "        print(f'{time.perf_counter() - t:.3f}', exc)\n"
        )
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
            cwd=Path(__file__).resolve().parents[1],
        )  # fmt: skip
        lines = done.stdout.splitlines()
        assert len(lines) == 2, done.stdout + done.stderr[-2000:]
        for line in lines:
            seconds, message = line.split(" ", 1)
            assert "not a regular file" in message and float(seconds) < 1.0

    def test_size_cap(self, tmp_path):
        from d2f_core.io.image import read_source_bytes

        path = tmp_path / "big.png"
        path.write_bytes(b"\x00" * 2048)
        with pytest.raises(ValueError, match="more than the limit of 1024"):
            read_source_bytes(path, max_bytes=1024)
        assert len(read_source_bytes(path, max_bytes=4096)) == 2048


class TestFloatTiff:
    @pytest.mark.parametrize("fill", [0.0, -1.0])
    def test_nothing_above_zero_is_refused(self, tmp_path, fill):
        values = np.full((32, 48), fill, np.float32)
        values[3, 4] = np.nan
        path = tmp_path / "dark.tif"
        Image.fromarray(values).save(path)
        with pytest.raises(ValueError, match="no value above 0"):
            load_image(path)

    def test_some_nan_still_loads(self, tmp_path):
        values = np.full((32, 48), 0.5, np.float32)
        values[3, 4] = np.nan
        path = tmp_path / "nan.tif"
        Image.fromarray(values).save(path)
        assert load_image(path).shape == (32, 48, 3)


class TestMessages:
    @pytest.mark.parametrize("rotation", [float("nan"), 1e300, float("inf")])
    def test_rotation_is_named(self, tiny_model, rotation):
        scene = tiny_model.prepare(np.random.default_rng(0).random((48, 64, 3)))
        with pytest.raises(ValueError, match="rotation must be a finite angle"):
            tiny_model.render(scene, 0.5, 20.0, blades=6, rotation=rotation)

    def test_rotation_in_the_cli(self, tmp_path, capsys):
        photo = _photo(tmp_path / "p.png")
        depth = tmp_path / "d.npy"
        np.save(depth, np.tile(np.linspace(0, 1, 64, dtype=np.float32), (48, 1)))
        args = ["-o", tmp_path / "o.png", "--blur", 20, "--depth", depth]
        args += ["--aperture-blades", 6, "--rotation", "1e300"]
        code, err = _run_cli(capsys, "render", photo, *args)
        assert code == 1 and "rotation must be a finite angle" in err, err

    def test_focus_at_outside_is_refused(self, tiny_model):
        scene = tiny_model.prepare(np.random.default_rng(0).random((48, 64, 3)))
        with pytest.raises(ValueError, match="outside the 64x48 photo"):
            tiny_model.focus_at(scene, 64, 10)
        with pytest.raises(ValueError, match="outside the 64x48 photo"):
            tiny_model.focus_at(scene, -3, 10)

    def test_negative_focus_at_in_the_cli(self, tmp_path, capsys):
        photo = _photo(tmp_path / "p.png")
        code, err = _run_cli(
            capsys, "render", photo, "-o", tmp_path / "o.png", "--blur", 5, "--focus-at", "-1,-1"
        )
        assert code == 2
        assert "expected one argument" not in err
        assert "'-1,-1' is outside the photo" in err


def test_depth_training_resumes_weights_only(tmp_path, monkeypatch):
    """``depth_last.pt`` is read with ``weights_only=True``: a pickle that runs code is refused
    before it runs."""
    import torch

    from d2f_core.train import depth_cli, depth_train

    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    out = tmp_path / "out"
    out.mkdir()
    torch.save({"state_dict": Payload(), "step": 1}, out / "depth_last.pt")
    monkeypatch.setattr(depth_train, "RealDepthData", lambda *a, **k: object())
    args = depth_cli.build_parser().parse_args(
        ["--data", str(tmp_path), "--labels", str(tmp_path), "--out", str(out), "--threads", "1"]
    )
    with pytest.raises(Exception, match="(?i)weights only|unpickl|unsupported"):
        depth_train.train_depth(args)
    assert not marker.exists()
