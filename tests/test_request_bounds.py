"""No request costs more than its photo, and no setting is silently wrong.

* A mask much larger than its photo is refused from its header (the library, the CLI), and a
  paint layer larger than the canvas is refused before Gradio decodes it (the real server,
  its peak memory read from ``/proc``).
* Every float setting of a weights file is finite and in its range where the file is read.
* A mask of 0 and 1 (``(a > t).astype(np.uint8)``) paints at full strength, array or file.
* A mask holding NaN says so once, naming the file once.
* A full disk during ``d2f batch`` names the file that could not be written and prints the
  run's summary, what was rendered and what was not.
* The aperture's blades are advertised to API clients as the integers they are, and a
  number sent as text is taken.
* An upload cut short by its client leaves one line in the server's log, no traceback.
* A 16-bit PNG whose image data inflates far past its rows is refused, not inflated.
"""

from __future__ import annotations

import io
import json
import math
import os
import socket
import struct
import subprocess
import time
import zlib
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch
from _forged import call, file_data, upload
from PIL import Image

from d2f_core.cli import main as cli_main
from d2f_core.depth.brushes import mask_tensor
from d2f_core.io import load_image, load_mask
from d2f_core.pipeline import D2F, D2FConfig

KIND = "disparity (bright = near)"
REST = [KIND, 0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", "auto", "", True]


def _chunk(ctype: bytes, body: bytes) -> bytes:
    crc = zlib.crc32(ctype + body) & 0xFFFFFFFF
    return struct.pack(">I", len(body)) + ctype + body + struct.pack(">I", crc)


def _png(width: int, height: int, depth: int, colour: int, raw: bytes) -> bytes:
    """A PNG of one IDAT holding ``raw`` (the rows and whatever follows them), compressed."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    z = zlib.compressobj(9)
    idat = z.compress(raw) + z.flush()
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


def _transparent_bomb(path: Path, width: int = 14_000, height: int = 10_500) -> Path:
    """A fully transparent 8-bit grey + alpha PNG of ``width`` x ``height`` (a few hundred
    KB: every row compresses to almost nothing)."""
    row = b"\x00" * (1 + 2 * width)
    z = zlib.compressobj(9)
    parts = [z.compress(row) for _ in range(height)]
    idat = b"".join(parts) + z.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 4, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )
    return path


def _photo(path: Path, w: int = 320, h: int = 240) -> Path:
    rng = np.random.default_rng(0)
    Image.fromarray((rng.random((h, w, 3)) * 255).astype(np.uint8)).save(path)
    return path


# ------------------------------------------------------------------ 1. masks' size


def test_a_mask_far_larger_than_its_photo_is_refused_from_its_header(tmp_path):
    # a header that claims 14000x10500 over 1 KB of data: a decode would end in "truncated",
    # a refusal from the header names the sizes
    header_only = tmp_path / "claims.png"
    header_only.write_bytes(_png(14_000, 10_500, 8, 0, b"\x00" * 1024)[: 33 + 40])
    with pytest.raises(ValueError, match=r"14000x10500, far larger than its 320x240 photo"):
        load_mask(header_only, size=(240, 320))
    # twice the photo's sides, or a few MP whatever the photo, are taken
    Image.new("L", (640, 480), 255).save(tmp_path / "twice.png")
    assert load_mask(tmp_path / "twice.png", size=(240, 320)).shape == (480, 640)
    Image.new("L", (2048, 1536), 255).save(tmp_path / "screen.png")
    assert load_mask(tmp_path / "screen.png", size=(24, 32)).min() == 1.0


def test_the_cli_refuses_the_mask_bomb_at_once(tmp_path, capsys):
    photo = _photo(tmp_path / "p.png")
    bomb = _transparent_bomb(tmp_path / "bomb.png")
    assert bomb.stat().st_size < 1 << 20
    out = tmp_path / "o.png"
    code = cli_main(["render", str(photo), "-o", str(out), "--blur", "5", "--depth-model", "d2f",
                     "--sharp-mask", str(bomb)])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and not out.exists()
    assert len(err) == 1 and "bomb.png: the mask is 14000x10500, far larger" in err[0], err


# ------------------------------------------------------------------ 2. weights' settings


FLOAT_FIELDS = [f.name for f in fields(D2FConfig) if f.type in (float, "float")]


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_no_float_setting_of_a_weights_file_is_infinite_or_nan(tiny_checkpoint, tmp_path, value):
    assert {"sharp_coc", "fusion_theta", "train_blur"} <= set(FLOAT_FIELDS)
    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    for name in FLOAT_FIELDS:
        if name == "spread_clip" and value == math.inf:
            continue  # no clip limit: the map's ranks (D2FConfig.spread_clip)
        edited = {**ckpt, "config": {**ckpt["config"], name: value}}
        path = tmp_path / f"{name}.pt"
        torch.save(edited, path)
        with pytest.raises(ValueError, match=rf"config\.{name} must be"):
            D2F.from_checkpoint(path)


@pytest.mark.parametrize(
    ("name", "value"),
    [("sharp_coc", 1e6), ("sharp_coc", 0.0), ("fusion_theta", 1.5), ("fusion_theta", -0.1),
     ("train_blur", 1e9), ("refine_eps", 10.0)],
)  # fmt: skip
def test_float_settings_out_of_their_range_are_refused(name, value):
    with pytest.raises(ValueError, match=rf"config\.{name} must be in"):
        D2FConfig(**{name: value})


def test_the_cli_names_an_infinite_setting_in_one_line(tiny_checkpoint, tmp_path, capsys):
    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    bad = tmp_path / "inf.pt"
    torch.save({**ckpt, "config": {**ckpt["config"], "sharp_coc": math.inf}}, bad)
    out = tmp_path / "o.png"
    code = cli_main(["render", str(_photo(tmp_path / "p.png")), "-o", str(out), "--blur", "5",
                     "--weights", str(bad)])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and not out.exists()
    assert len(err) == 1 and "config.sharp_coc must be a finite number" in err[0], err


# ------------------------------------------------------------------ 3, 4. masks' values


def test_a_uint8_mask_of_0_and_1_paints_at_full_strength(tmp_path):
    a = np.zeros((24, 32), np.float32)
    a[4:12, 8:20] = 0.7
    binary = (a > 0.5).astype(np.uint8)
    as_bool = mask_tensor(a > 0.5, (24, 32), "sharp")
    assert torch.equal(mask_tensor(binary, (24, 32), "sharp"), as_bool)
    assert torch.equal(mask_tensor(np.repeat(binary[..., None], 3, 2), (24, 32), "m"), as_bool)
    assert float(as_bool.max()) == 1.0
    # a 0-255 mask is still read on its scale
    assert float(mask_tensor(binary * 128, (24, 32), "m").max()) == pytest.approx(128 / 255)
    # and the same mask as a file, grey, 16-bit and grey + alpha
    Image.fromarray(binary).save(tmp_path / "grey.png")
    Image.fromarray(binary.astype(np.uint16)).save(tmp_path / "sixteen.png")
    Image.fromarray(np.stack([binary, np.full_like(binary, 255)], -1), "LA").save(
        tmp_path / "la.png"
    )
    for name in ("grey.png", "sixteen.png", "la.png"):
        m = load_mask(tmp_path / name, size=(24, 32))
        np.testing.assert_array_equal(m, binary.astype(np.float32), err_msg=name)


def test_a_mask_holding_nan_says_so_naming_the_file_once(tmp_path):
    a = np.full((24, 32), 0.5, np.float32)
    a[3, 3] = np.nan
    path = tmp_path / "nan_mask.tiff"
    Image.fromarray(a).save(path)
    with pytest.raises(ValueError) as caught:
        load_mask(path, size=(24, 32))
    message = str(caught.value)
    assert "NaN" in message and "corrupt" not in message and "truncated" not in message
    assert message.count("nan_mask.tiff") == 1, message


# ------------------------------------------------------------------ 5. a full disk


@pytest.fixture
def full_disk(tmp_path):
    """A folder on a tmpfs of 256 KB filled to the last block; skips where a tmpfs cannot
    be mounted (not root)."""
    mount = tmp_path / "full"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs (a disk to fill) needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)],
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        fd = os.open(mount / "filler", os.O_WRONLY | os.O_CREAT)
        try:
            while os.write(fd, b"\0" * 4096):
                pass
        except OSError:
            pass
        finally:
            os.close(fd)
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _photos(folder: Path, n: int = 3) -> Path:
    folder.mkdir()
    for i in range(n):
        _photo(folder / f"p{i}.png", 64, 48)
    return folder


def test_a_full_disk_under_the_manifest_names_it_and_sums_up(
    tmp_path, full_disk, tiny_checkpoint, capsys
):
    photos = _photos(tmp_path / "in")
    out = tmp_path / "out"
    manifest = full_disk / "manifest.jsonl"
    code = cli_main(["batch", str(photos), "-o", str(out), "--blur", "5", "--workers", "1",
                     "--weights", str(tiny_checkpoint), "--manifest", str(manifest)])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert any("not rendered: the run stopped before them" in line for line in err), err
    assert any(line.startswith("d2f: 0 rendered") for line in err), err
    last = err[-1]
    assert "manifest cannot be written" in last and "No space left on device" in last, last
    assert str(full_disk) in last, last  # the part file it could not write
    assert "[Errno 28]" not in last


def test_a_full_disk_under_the_outputs_names_each_output(tmp_path, full_disk, tiny_checkpoint,
                                                         capsys):  # fmt: skip
    photos = _photos(tmp_path / "in", 2)
    code = cli_main(["batch", str(photos), "-o", str(full_disk / "out"), "--blur", "5",
                     "--weights", str(tiny_checkpoint), "--workers", "1",
                     "--manifest", str(tmp_path / "manifest.jsonl")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    for i in range(2):
        assert f"{full_disk / 'out' / f'p{i}_bokeh.png'}: No space left on device" in err, err
    assert ".d2f-partial" not in err
    assert "0 rendered, 2 failed" in err
    rows = [json.loads(line) for line in (tmp_path / "manifest.jsonl").read_text().splitlines()]
    assert [r["status"] for r in rows] == ["failed", "failed"]


# ------------------------------------------------ 1, 6, 7. the real server, forged requests


def _peak_mb(pid: int) -> float:
    status = Path(f"/proc/{pid}/status").read_text()
    return next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM"))


@pytest.mark.slow
def test_the_server_bounds_what_a_request_costs(app_server, two_plane_scene, tmp_path):
    server = app_server()
    url = server.url
    photo = upload(url, two_plane_scene.photo)
    event, answer = call(url, "load", [file_data(photo, "scene.png"), None, *REST], "s1")
    assert event == "complete", answer

    # 6: the blades are advertised as the integers they are; a number as text is taken
    with urllib_open(f"{url}/gradio_api/info") as r:
        info = json.load(r)
    blades = [p for p in info["named_endpoints"]["/render"]["parameters"]
              if "blades" in (p.get("label") or "")]  # fmt: skip
    assert blades and blades[0]["type"] == {"type": "integer", "enum": [0, 5, 6, 7, 8, 9]}
    render = [0.5, 2.8, "6", 0.0, True, True, "Bokeh", "balanced", True, 0.0, ""]
    event, answer = call(url, "render", render, "s1")
    assert event == "complete", answer
    event, answer = call(url, "render", [*render[:2], "4", *render[3:]], "s1")
    assert event == "error" and "4 is not in the list of choices" in answer["error"], answer

    # 1: a paint layer of 14000x10500 is refused from its header, the server's peak held
    bomb = upload(url, _transparent_bomb(tmp_path / "layer.png"))
    before = _peak_mb(server.process.pid)
    editor = {"background": None, "layers": [file_data(bomb, "layer.png")], "composite": None,
              "id": None}  # fmt: skip
    event, answer = call(url, "paint", [editor, True, *render], "s1")
    grown = (_peak_mb(server.process.pid) - before) / 1024
    assert event == "error" and "14000x10500" in answer["error"], answer
    assert "at most 1600 px" in answer["error"]
    assert grown < 150, f"the server's peak memory grew by {grown:.0f} MB"

    # 7: an upload whose body stops short of its declared length, its client gone
    boundary = "cut-short"
    body = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="x.png"'
        f"\r\nContent-Type: application/octet-stream\r\n\r\n"
    ).encode() + b"x" * 50_000
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port))) as s:
        s.sendall(
            (f"POST /gradio_api/upload?upload_id=cut HTTP/1.1\r\nHost: {host}\r\n"
             f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
             f"Content-Length: {len(body) + 1000}\r\n\r\n").encode() + body
        )  # fmt: skip
    deadline = time.monotonic() + 10
    while "ended before its declared length" not in server.log.read_text():
        assert time.monotonic() < deadline, server.log.read_text()[-3000:]
        time.sleep(0.1)
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
    assert log.count("ended before its declared length") == 1


def urllib_open(url: str):
    import urllib.request

    return urllib.request.urlopen(url, timeout=30)


# ------------------------------------------------------------------ 8. PNG image data


def test_a_16_bit_png_whose_data_inflates_past_its_rows_is_refused(tmp_path):
    rows = b"\x00" + b"\x12\x34" * 3  # one 16-bit RGB pixel, its filter byte first
    bomb = _png(1, 1, 16, 2, rows + b"\x00" * (128 << 20))
    assert len(bomb) < 1 << 20
    with pytest.raises(ValueError, match=r"holds more than the 7 bytes of a 1x1 image"):
        load_image(bomb)
    # the same pixel with nothing after its row, or a few bytes of padding, is read
    for tail in (b"", b"\x00" * 16):
        pixel = load_image(_png(1, 1, 16, 2, rows + tail))
        np.testing.assert_allclose(pixel[0, 0], [0x1234 / 65535] * 3, atol=1e-6)
    # a 16-bit photo of many rows and filters reads as before
    a = (np.arange(48 * 64 * 3).reshape(48, 64, 3) * 37 % 65536).astype(np.uint16)
    buf = io.BytesIO()
    raw = b"".join(b"\x00" + a[y].astype(">u2").tobytes() for y in range(48))
    buf.write(_png(64, 48, 16, 2, raw))
    np.testing.assert_allclose(load_image(buf.getvalue()), a / 65535.0, atol=1e-6)


EXTREMES = [math.inf, -math.inf, math.nan, 1e300, -1e300, -1.0, 0.0, 0.5, 1.0, 2.0, 1e6,
            2**63, -(2**63), "0.5", None, True, [], {"x": 1}]  # fmt: skip


def test_fuzz_every_setting_of_a_weights_file(tiny_checkpoint, tmp_path):
    """Every setting of a checkpoint's config set to each extreme value: the file loads with
    finite settings in their ranges, or is refused with a ValueError naming the setting; a
    sample of the edited files goes through ``D2F.from_checkpoint`` as written to disk."""
    import random

    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    names = [f.name for f in fields(D2FConfig)]
    cases = [(name, value) for name in names for value in EXTREMES]
    on_disk = set(random.Random("d2f-settings").sample(range(len(cases)), 24))
    loaded = 0
    for index, (name, value) in enumerate(cases):
        config = {**ckpt["config"], name: value}
        try:
            if index in on_disk:
                path = tmp_path / f"case{index}.pt"
                torch.save({**ckpt, "config": config}, path)
                cfg = D2F.from_checkpoint(path).config
            else:
                cfg = D2FConfig.from_dict(config)
        except ValueError as exc:  # InputTypeError is a ValueError too
            assert name in str(exc), (name, value, str(exc))
            continue
        loaded += 1
        for f in fields(cfg):
            v = getattr(cfg, f.name)
            if isinstance(v, float) and not (f.name == "spread_clip" and v == math.inf):
                assert math.isfinite(v), (name, value, f.name, v)
    assert 0 < loaded < len(cases)
