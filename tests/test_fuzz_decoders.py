"""Seeded fuzzing of every format the project decodes itself: 16-bit PNG (``decode_png16``),
Apple portrait MPO and Google Lens Blur XMP (``d2f_core.io.embedded``), PFM and ``.npy``
(``d2f_core.io.depth``).

Each valid file is truncated, bit-flipped and inflated (headers that claim more pixels than
the file holds, streams that inflate past their header, an extended-XMP length of 2 GB, a
depth frame or a depth PNG that claims a huge size). Every case must end in a result or a
``ValueError``, within a few seconds, with the memory that Python and NumPy allocate
(``tracemalloc``) under 4x the size of the valid file's decoded image (both pictures of a
Lens Blur file) plus a fixed 256 KB for the decoders' own small objects. Pillow's C buffers
are not seen by ``tracemalloc``; the caps that bound them (the embedded depth no larger than
the photo, the pixel caps) are checked from the headers. About 410 cases, 5-20 s.
"""

from __future__ import annotations

import io
import random
import struct
import time
import tracemalloc
import zlib

import _io_writers as writers
import numpy as np
import pytest
from PIL import Image

from d2f_core.io import load_photo, read_depth_array, read_embedded_depth, write_pfm

pytestmark = pytest.mark.slow

H, W = 192, 256
CASES_PER_KIND = 26  # truncations and bit flips per format (plus the inflations)
SLACK = 256 << 10
SECONDS = 3.0


def _photo(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    base = np.stack([x / W, y / H, (x + y) / (W + H)], axis=-1)
    return np.clip(base + 0.1 * rng.random((H, W, 3)), 0, 1)


def _png16() -> bytes:
    a = np.round(_photo() * 65535).astype(np.uint16)
    return writers.png16_bytes(a, filters=[0, 1, 2, 3, 4])


def _mpo() -> bytes:
    photo = (_photo() * 255).astype(np.uint8)
    disp = (np.tile(np.linspace(0, 255, W // 2), (H // 2, 1))).astype(np.uint8)
    return writers.apple_mpo(photo, disp, float_min=0.5, float_max=2.0,
                             focus_region=(0.5, 0.5, 0.2, 0.2))  # fmt: skip


def _lensblur(depth_png: bytes | None = None) -> bytes:
    photo = (_photo() * 255).astype(np.uint8)
    z = np.tile(np.linspace(1.0, 5.0, W // 2), (H // 2, 1))
    if depth_png is None:
        return writers.lensblur_jpeg(photo, photo, z, near=1.0, far=5.0, focal_distance=2.0)
    original = writers.encode_gdepth
    writers.encode_gdepth = lambda *a, **k: depth_png
    try:
        return writers.lensblur_jpeg(photo, photo, z, near=1.0, far=5.0)
    finally:
        writers.encode_gdepth = original


def _pfm(tmp_path) -> bytes:
    path = write_pfm(tmp_path / "d.pfm", _photo()[..., 0].astype(np.float32))
    return path.read_bytes()


def _npy() -> bytes:
    buf = io.BytesIO()
    np.save(buf, _photo()[..., 0].astype(np.float32))
    return buf.getvalue()


def _grey_png_claiming(width: int, height: int, inflated: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * inflated, 9)
    return (b"\x89PNG\r\n\x1a\n" + writers._chunk(b"IHDR", ihdr) + writers._chunk(b"IDAT", idat)
            + writers._chunk(b"IEND", b""))  # fmt: skip


# ------------------------------------------------------------------------ inflations


def _png16_inflations(data: bytes) -> list[bytes]:
    out = [writers.png16_stream(W, H, 3, inflated=n) for n in (10 << 20, 40 << 20)]
    out.append(writers.png16_stream(1, 1, 4, inflated=30 << 20))
    for scale in (2, 64, 4096):  # the header claims more rows and columns than the data
        ihdr = struct.pack(">II", W * scale, H * scale)
        out.append(data[:16] + ihdr + data[24:])
    return out


def _npy_inflations(data: bytes) -> list[bytes]:
    out = []
    for shape in ((H * 10, W * 10), (100_000, 100_000), (2**31, 2**31), (H, W, 1 << 20)):
        header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), np.float32))
        header["shape"] = shape
        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, header)
        out.append(buf.getvalue() + data[128:])
    return out


def _pfm_inflations(data: bytes) -> list[bytes]:
    body = data[data.index(b"-1.0\n") + 5 :]
    return [b"Pf\n%d %d\n-1.0\n" % (w, h) + body for w, h in
            ((W * 10, H * 10), (100_000, 100_000), (2**31, 2**31))]  # fmt: skip


def _xmp_inflations(data: bytes) -> list[bytes]:
    sig = writers.XMP_EXT_SIG
    out = []
    for total in (1 << 31, 0xFFFFFFFF):
        patched = bytearray(data)
        pos = patched.find(sig)
        while pos >= 0:
            at = pos + len(sig) + 32
            patched[at : at + 4] = struct.pack(">I", total)
            pos = patched.find(sig, pos + 1)
        out.append(bytes(patched))
    out.append(_lensblur(_grey_png_claiming(W // 2, H // 2, 30 << 20)))  # inflates too far
    out.append(_lensblur(_grey_png_claiming(30_000, 30_000, 1 << 10)))  # claims 900 MP
    return out


def _mpo_inflations(data: bytes) -> list[bytes]:
    out = []
    second = data.find(b"\xff\xd8", 2)
    sof = data.find(b"\xff\xc0", second)
    for h, w in ((30_000, 30_000), (H * 8, W * 8), (65_535, 65_535)):
        patched = bytearray(data)
        patched[sof + 5 : sof + 9] = struct.pack(">HH", h, w)
        out.append(bytes(patched))
    return out


# ------------------------------------------------------------------------ the run


def _mutations(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    out = []
    for k in range(n):
        if k % 2 == 0:  # truncated anywhere, most often in the headers
            end = min(len(data), 4096) if k % 4 == 0 else len(data)
            cut = rng.randrange(1, end)
            out.append(data[:cut])
        else:  # 1 to 8 bits flipped, half of the cases in the first 512 bytes
            flipped = bytearray(data)
            span = min(len(data), 512) if k % 4 == 1 else len(data)
            for _ in range(rng.randint(1, 8)):
                pos = rng.randrange(span)
                flipped[pos] ^= 1 << rng.randrange(8)
            out.append(bytes(flipped))
    return out


def _decode_photo(data: bytes) -> None:
    load_photo(data)  # the photo is dropped before the next decoder runs
    read_embedded_depth(data)  # raises where load_photo logs and goes on


KINDS = {
    # kind: (valid file, decoder, decoded bytes of the valid file, inflations)
    "png16": (_png16, load_photo, H * W * 3 * 4, _png16_inflations),
    "mpo": (_mpo, _decode_photo, H * W * 3 * 4, _mpo_inflations),
    # a Lens Blur file holds two photos, both decoded: the blurred one and the original
    "gdepth": (_lensblur, _decode_photo, 2 * H * W * 3 * 4, _xmp_inflations),
    "pfm": (None, read_depth_array, H * W * 8, _pfm_inflations),
    "npy": (_npy, read_depth_array, H * W * 8, _npy_inflations),
}


@pytest.mark.parametrize("kind", list(KINDS))
def test_fuzz(kind, tmp_path):
    make, decode, decoded_bytes, inflations = KINDS[kind]
    valid = _pfm(tmp_path) if make is None else make()
    Image.init()  # every Pillow plugin imported now, not counted in a case's memory
    decode(valid)  # the valid file decodes (and the decoder's modules are imported)
    rng = random.Random(f"d2f-fuzz-{kind}")
    cases = [("inflate", c) for c in inflations(valid)]
    cases += [("mutate", c) for c in _mutations(valid, rng, CASES_PER_KIND * 3)]
    limit = 4 * decoded_bytes + SLACK
    failures = []
    for index, (how, data) in enumerate(cases):
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            decode(data)
            outcome = "result"
        except ValueError:
            outcome = "ValueError"
        except Exception as exc:  # noqa: BLE001 (the failure is recorded)
            outcome = f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        if outcome not in ("result", "ValueError") or peak > limit or seconds > SECONDS:
            failures.append(f"{how} #{index}: {outcome[:200]}, peak {peak / 1e6:.2f} MB "
                            f"(limit {limit / 1e6:.2f}), {seconds:.2f} s")  # fmt: skip
    assert not failures, f"{len(failures)} of {len(cases)} {kind} cases:\n" + "\n".join(failures)
