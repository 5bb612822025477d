"""Seeded fuzzing of the loaders, photo and depth: 16-bit PNG (libpng through imagecodecs,
behind the project's header checks), lines of 60,000 pixels with the Paeth and Average
filters, Apple portrait MPO and Google Lens Blur XMP (``d2f_core.io.embedded``), tiled float
TIFF (tifffile and Pillow behind the header checks), PFM and ``.npy``.

Each valid file (seed) is mutated: truncated, bit-flipped, chunks and segments duplicated,
header fields set to extremes (PNG IHDR fields with their CRC fixed, JPEG frame sizes, TIFF
tags, ``.npy`` dtypes and shapes, PFM sizes and scales), 16-bit PNG scanline filter bytes set
to every type and to invalid ones, and inflated (headers that claim more pixels than the file
holds, streams that inflate past their header, an extended-XMP length of 2 GB, a depth frame
or a depth PNG that claims a huge size).

Each format's mutants run in a child process whose address space is capped at 2 GiB
(``RLIMIT_AS``; the child needs about 180 MB), so a decoder that asks for what a header
claims fails there instead of taking the machine's memory. Every case must end in a result or
a ``ValueError``:

* within ``FLOOR_S`` + ``PER_PIXEL`` x the seconds per pixel of a square 8-bit PNG that
  Pillow decodes in the same child x the case's pixel count (the seed's or the result's,
  the larger): a time that follows the pixel count, whatever the shape, the filters or the
  damage;
* with the memory that Python and NumPy allocate (``tracemalloc``) under 4x the decoded
  bytes of the pixels it holds or claims in a header (both pictures of a Lens Blur file)
  plus a fixed 256 KB for the decoders' own small objects. C buffers (libpng's rows,
  Pillow's image) are not seen by ``tracemalloc``; the address-space cap bounds them.

About 1,340 cases, 7-10 s on two cores.
"""

from __future__ import annotations

import io
import json
import os
import random
import resource
import struct
import subprocess
import sys
import tempfile
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import _io_writers as writers
import numpy as np
import pytest
from PIL import Image

from d2f_core.io import load_mask, load_photo, read_depth_array, read_embedded_depth, write_pfm
from d2f_core.io.image import MAX_DECODE_PIXELS

pytestmark = pytest.mark.slow

H, W = 192, 256
LINE = 60_000  # pixels of the line seeds: 1 x 60,000 Paeth, 60,000 x 1 Average and Paeth
CASES_PER_KIND = 40  # truncations and bit flips per format: 3x this many
EXTREMES_PER_KIND = 64  # header fields set to extremes
SLACK = 256 << 10
FLOOR_S = 2.0
PER_PIXEL = 50.0
CHILD_AS = 2 << 30
CHILD_TIMEOUT_S = 300
MAX_FAILURES = 8  # a batch stops there (a slow decoder would take minutes)


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


# ------------------------------------------------------------------------ more seeds


def _png16_line(width: int, height: int, filters: list[int]) -> bytes:
    rng = np.random.default_rng(width + 7 * height)
    a = rng.integers(0, 65536, (height, width, 3), dtype=np.uint16)
    return writers.png16_bytes(a, filters=filters)


def _png16_wide() -> bytes:
    return _png16_line(LINE, 1, [4])


def _png16_tall() -> bytes:
    return _png16_line(1, LINE, [3, 4])


TILE = 128
TIFF_H, TIFF_W = 500, 600


def _tiff() -> bytes:
    return writers.tiled_float_tiff(TIFF_W, TIFF_H, TILE, lambda ty, tx: 1 + ty * 8 + tx)


# ------------------------------------------------------------------------ mutations


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


def _span_duplicates(data: bytes, rng: random.Random, n: int = 4) -> list[bytes]:
    """A random span of the file repeated in place (any format)."""
    out = []
    for _ in range(n):
        start = rng.randrange(len(data))
        stop = min(len(data), start + rng.randint(1, 4096))
        out.append(data[:stop] + data[start:stop] + data[stop:])
    return out


def _png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """``[(type, body)]`` of a valid PNG (the seeds), read from the specification."""
    out, pos = [], 8
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        out.append((data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]))
        pos += 12 + length
    return out


def _png_join(chunks: list[tuple[bytes, bytes]]) -> bytes:
    return b"\x89PNG\r\n\x1a\n" + b"".join(writers._chunk(t, b) for t, b in chunks)


#: IHDR fields: (offset, struct format, extreme values)
_IHDR_FIELDS = {
    "width": (0, ">I", [0, 1, 2, 65_536, 1_000_001, 2**31 - 1, 2**32 - 1]),
    "height": (4, ">I", [0, 1, 2, 65_536, 1_000_001, 2**31 - 1, 2**32 - 1]),
    "bit depth": (8, "B", [0, 1, 2, 4, 8, 15, 32, 255]),
    "colour type": (9, "B", [0, 1, 2, 3, 4, 5, 6, 7, 255]),
    "compression": (10, "B", [1, 8, 255]),
    "filter method": (11, "B", [1, 255]),
    "interlace": (12, "B", [1, 2, 255]),
}


def _png_extremes(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    """IHDR fields set to extreme values, the chunk's CRC made right again."""
    chunks = _png_chunks(data)
    combos = [(f, v) for f, (_, _, values) in _IHDR_FIELDS.items() for v in values]
    rng.shuffle(combos)
    out = []
    for field, value in combos[:n]:
        at, fmt, _ = _IHDR_FIELDS[field]
        body = bytearray(chunks[0][1])
        struct.pack_into(fmt, body, at, value)
        out.append(_png_join([(b"IHDR", bytes(body))] + chunks[1:]))
    return out


def _png_duplicates(data: bytes, rng: random.Random) -> list[bytes]:
    """Each chunk repeated once (IHDR, IDAT, IEND, ...), the image data split in two and the
    second half repeated, and random spans repeated."""
    chunks = _png_chunks(data)
    out = [_png_join(chunks[: i + 1] + chunks[i:]) for i in range(len(chunks))]
    idat = [i for i, (t, _) in enumerate(chunks) if t == b"IDAT"][0]
    body = chunks[idat][1]
    half = [(b"IDAT", body[: len(body) // 2]), (b"IDAT", body[len(body) // 2 :])]
    out.append(_png_join(chunks[:idat] + half + half[1:] + chunks[idat + 1 :]))
    return out + _span_duplicates(data, rng)


def _png_filters(data: bytes, rng: random.Random, n: int = 12) -> list[bytes]:
    """Scanline filter bytes set to each type (0-4) and to invalid ones (5, 128, 255), on a
    few rows or on every row, recompressed with the right CRC."""
    chunks = _png_chunks(data)
    w, h, depth, ctype = struct.unpack(">IIBB", chunks[0][1][:10])
    bpp = {2: 3, 4: 2, 6: 4}[ctype] * depth // 8
    raw = bytearray(zlib.decompress(b"".join(b for t, b in chunks if t == b"IDAT")))
    stride = 1 + w * bpp
    out = []
    for k in range(n):
        value = [0, 1, 2, 3, 4, 5, 128, 255][k % 8]
        rows = range(h) if k >= 8 else rng.sample(range(h), min(h, rng.randint(1, 50)))
        mutated = bytearray(raw)
        for r in rows:
            mutated[r * stride] = value
        idat = [(b"IDAT", zlib.compress(bytes(mutated)))]
        out.append(_png_join([c for c in chunks if c[0] != b"IDAT" and c[0] != b"IEND"]
                             + idat + [(b"IEND", b"")]))  # fmt: skip
    return out


def _jpeg_segments(data: bytes) -> list[tuple[int, int]]:
    """``[(start, end)]`` of the marker segments of every frame of a JPEG/MPO file (each
    frame's header segments up to its start-of-scan)."""
    out, pos = [], 0
    while (pos := data.find(b"\xff\xd8\xff", pos)) >= 0:
        at = pos + 2
        while at + 4 <= len(data) and data[at] == 0xFF and data[at + 1] not in (0xD9, 0xDA):
            (length,) = struct.unpack(">H", data[at + 2 : at + 4])
            out.append((at, at + 2 + length))
            at += 2 + length
        pos = at
    return out


def _jpeg_extremes(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    """Start-of-frame fields of each frame set to extremes: precision, height, width,
    component count."""
    frames = [s for s, _ in _jpeg_segments(data) if data[s + 1] in (0xC0, 0xC1, 0xC2)]
    fields = [(4, ">B", [0, 1, 12, 16, 255]), (5, ">H", [0, 1, 65_535]),
              (7, ">H", [0, 1, 65_535]), (9, ">B", [0, 2, 4, 255])]  # fmt: skip
    combos = [(f, at, fmt, v) for f in frames for at, fmt, vs in fields for v in vs]
    rng.shuffle(combos)
    out = []
    for frame, at, fmt, value in combos[:n]:
        patched = bytearray(data)
        struct.pack_into(fmt, patched, frame + at, value)
        out.append(bytes(patched))
    return out


def _jpeg_duplicates(data: bytes, rng: random.Random) -> list[bytes]:
    """Marker segments repeated in place (APP1 XMP, DQT, SOF, DHT ...), random spans."""
    segments = _jpeg_segments(data)
    out = []
    for start, end in rng.sample(segments, min(8, len(segments))):
        out.append(data[:end] + data[start:end] + data[end:])
    return out + _span_duplicates(data, rng)


def _tiff_entries(data: bytes) -> tuple[int, list[tuple[int, int, int, int]]]:
    """``(IFD offset, [(entry offset, tag, type, count)])`` of a little-endian TIFF."""
    (ifd,) = struct.unpack("<I", data[4:8])
    (n,) = struct.unpack("<H", data[ifd : ifd + 2])
    entries = []
    for k in range(n):
        at = ifd + 2 + 12 * k
        tag, typ, count = struct.unpack("<HHI", data[at : at + 8])
        entries.append((at, tag, typ, count))
    return ifd, entries


def _tiff_extremes(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    """Each tag's value, count or type set to extremes; the first tile's offset and byte
    count (stored after the IFD) too."""
    _, entries = _tiff_entries(data)
    combos = []
    for at, _tag, typ, count in entries:
        if count == 1:
            values = [0, 1, 2, 7, 0xFFFF] if typ == 3 else [0, 1, 40_000, 2**31, 2**32 - 1]
            fmt = "<H" if typ == 3 else "<I"
            combos += [(at + 8, fmt, v) for v in values]
        else:  # an array of LONGs: its first element and where it is
            (where,) = struct.unpack("<I", data[at + 8 : at + 12])
            combos += [(where, "<I", v) for v in (0, len(data) - 1, 2**31, 2**32 - 1)]
            combos += [(at + 8, "<I", v) for v in (0, len(data) - 2, 2**32 - 1)]
        combos += [(at + 4, "<I", v) for v in (0, 2, 2**32 - 1)]  # the count
        combos += [(at + 2, "<H", v) for v in (0, 12, 13, 0xFFFF)]  # the type
    rng.shuffle(combos)
    out = []
    for at, fmt, value in combos[:n]:
        patched = bytearray(data)
        struct.pack_into(fmt, patched, at, value)
        out.append(bytes(patched))
    return out


def _tiff_duplicates(data: bytes, rng: random.Random) -> list[bytes]:
    """The IFD linked to itself (a loop), a second page copied after it, entries repeated,
    every tile pointing at the first tile's bytes, random spans repeated."""
    ifd, entries = _tiff_entries(data)
    n = len(entries)
    next_at = ifd + 2 + 12 * n
    loop = bytearray(data)
    struct.pack_into("<I", loop, next_at, ifd)
    second = bytearray(data)
    struct.pack_into("<I", second, next_at, len(data))
    second += data[ifd : next_at + 4]
    repeated = bytearray(data)  # the last entry repeated in place of the one before it
    repeated[next_at - 24 : next_at - 12] = data[next_at - 12 : next_at]
    offsets = [e for e in entries if e[1] == 324][0]
    (where,) = struct.unpack("<I", data[offsets[0] + 8 : offsets[0] + 12])
    (first,) = struct.unpack("<I", data[where : where + 4])
    counts = [e for e in entries if e[1] == 325][0]
    (cwhere,) = struct.unpack("<I", data[counts[0] + 8 : counts[0] + 12])
    (ccount,) = struct.unpack("<I", data[cwhere : cwhere + 4])
    same = bytearray(data)
    for k in range(offsets[3]):
        struct.pack_into("<I", same, where + 4 * k, first)
        struct.pack_into("<I", same, cwhere + 4 * k, ccount)
    return [bytes(loop), bytes(second), bytes(repeated), bytes(same)] + _span_duplicates(data, rng)


def _npy_extremes(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    """Header dtypes, orders and shapes set to extremes (the samples kept)."""
    body = data[128:]
    out = []
    dtypes = ["<f8", "<f2", "|u1", ">i4", "<c8", "|b1", "|O", "<U8", "|V16", "<M8[s]"]
    shapes = [(0, W), (H, 0), (W, H), (H * W,), (1, H, W), (H, W, 1), (H // 2, W, 2)]
    for descr in dtypes:
        out.append(_npy_with({"descr": descr, "fortran_order": False, "shape": (H, W)}, body))
    for shape in shapes:
        out.append(_npy_with({"descr": "<f4", "fortran_order": False, "shape": shape}, body))
    out.append(_npy_with({"descr": "<f4", "fortran_order": True, "shape": (H, W)}, body))
    return out[:n]


def _npy_with(header: dict, body: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue() + body


def _pfm_extremes(data: bytes, rng: random.Random, n: int) -> list[bytes]:
    """Sizes and scales set to extremes (the samples kept)."""
    body = data[data.index(b"-1.0\n") + 5 :]
    heads = [b"Pf\n%d %d\n%s\n" % (w, h, s) for w, h, s in (
        (W, H, b"0"), (W, H, b"nan"), (W, H, b"inf"), (W, H, b"-0.0"), (W, H, b"1e308"),
        (0, H, b"-1.0"), (W, 0, b"-1.0"), (-1, H, b"-1.0"), (W, -1, b"-1.0"),
        (2**63, H, b"-1.0"), (W, H * 2, b"1.0"), (H, W, b"-1.0"), (1, H * W, b"-1.0"),
    )]  # fmt: skip
    return ([h + body for h in heads] + [b"PF\n%d %d\n-1.0\n" % (W, H) + body])[:n]


# ------------------------------------------------------------------------ the decoders


def _pixels(array) -> int:
    return int(np.prod(np.asarray(array).shape[:2]))


def _decode_photo(data: bytes) -> int:
    pixels = _pixels(load_photo(data).image)  # the photo is dropped before the next decoder
    read_embedded_depth(data)  # raises where load_photo logs and goes on
    return pixels


def _load_photo(data: bytes) -> int:
    return _pixels(load_photo(data).image)


def _read_depth(data: bytes) -> int:
    return _pixels(read_depth_array(data))


def _claimed_pixels(data: bytes) -> int:
    """The pixels the file's header claims, as Pillow or tifffile read it (0 when neither
    reads it, or the claim is past the loaders' limit: refused unread)."""
    claims = [0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with Image.open(io.BytesIO(data)) as im:
                claims.append(im.size[0] * im.size[1])
        except Exception:  # noqa: BLE001 (no claim)
            pass
        if data[:4] == b"II*\x00":
            try:
                import tifffile

                page = tifffile.TiffFile(io.BytesIO(data)).pages[0]
                claims.append(int(page.imagelength) * int(page.imagewidth))
            except Exception:  # noqa: BLE001 (no claim)
                pass
    return max(c for c in claims if c <= MAX_DECODE_PIXELS)


def _pfm_seed() -> bytes:
    with tempfile.TemporaryDirectory() as folder:
        path = write_pfm(Path(folder) / "d.pfm", _photo()[..., 0].astype(np.float32))
        return path.read_bytes()


def _inflations_none(data: bytes) -> list[bytes]:
    return []


def _mask_png() -> bytes:
    """A brush's mask: a soft grey stroke under alpha, 8-bit grey + alpha."""
    grey = np.round(_photo()[..., 0] * 255).astype(np.uint8)
    alpha = np.where(_photo()[..., 1] > 0.5, 255, 0).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.stack([grey, alpha], axis=-1), "LA").save(buf, "PNG")
    return buf.getvalue()


def _mask_tiff() -> bytes:
    """A float mask in [0, 1], tiled float TIFF."""
    return writers.tiled_float_tiff(TIFF_W, TIFF_H, TILE, lambda ty, tx: (ty * 5 + tx) % 11 / 10)


def _mask_extras(size: tuple[int, int]):
    """Masks of every mode and of values out of range: integers past 255 or 65535,
    negatives, NaN and infinities in float ones, 0/1 integers, and sizes far past the
    photo's (refused from the header)."""
    h, w = size
    ramp = np.linspace(0, 1, h * w).reshape(h, w)
    out = []
    for mode, values in (
        ("1", ramp > 0.5), ("L", ramp * 255), ("L", ramp > 0.5), ("P", ramp * 255),
        ("I;16", ramp * 65535), ("I;16", ramp > 0.5), ("I", ramp * 70000), ("I", -ramp),
        ("I", ramp > 0.5), ("F", ramp), ("F", np.where(ramp > 0.5, np.nan, ramp)),
        ("F", ramp * np.inf), ("F", ramp * 2 - 1), ("RGB", ramp * 255), ("RGBA", ramp * 255),
    ):  # fmt: skip
        a = np.asarray(values)
        if mode == "1":
            im = Image.fromarray(a)
        elif mode in ("L", "P"):
            im = Image.fromarray(a.astype(np.uint8), "L").convert(mode)
        elif mode == "I;16":
            im = Image.fromarray(a.astype(np.uint16))
        elif mode == "I":
            im = Image.fromarray(a.astype(np.int32))
        elif mode == "F":
            im = Image.fromarray(a.astype(np.float32))
        else:
            im = Image.fromarray(np.repeat(a.astype(np.uint8)[..., None], len(mode), axis=2))
        buf = io.BytesIO()
        im.save(buf, "TIFF" if mode in ("I", "F") else "PNG")
        out.append(buf.getvalue())
    for scale in (3, 64, 4096):  # a header that claims far more than the photo's pixels
        out.append(writers.png_bomb_header(w * scale, h * scale))
    return out


def _mask_png_inflations(data: bytes) -> list[bytes]:
    return _mask_extras((H, W))


def _mask_tiff_inflations(data: bytes) -> list[bytes]:
    nan = writers.tiled_float_tiff(TIFF_W, TIFF_H, TILE, lambda ty, tx: np.nan if tx else 0.5)
    huge = writers.tiled_float_tiff(40_000, 40_000, 256, lambda ty, tx: 1.0)
    return [nan, huge]


def _load_mask_png(data: bytes) -> int:
    return _pixels(load_mask(data, size=(H, W)))


def _load_mask_tiff(data: bytes) -> int:
    return _pixels(load_mask(data, size=(TIFF_H, TIFF_W)))


def _paint_layer_png() -> bytes:
    """The editor's paint layer: RGBA, a green stroke at 60 % over transparency."""
    layer = np.zeros((H, W, 4), np.uint8)
    layer[H // 4 : H // 2, W // 4 :] = (34, 197, 94, 153)
    buf = io.BytesIO()
    Image.fromarray(layer, "RGBA").save(buf, "PNG")
    return buf.getvalue()


def _paint_layer(data: bytes) -> int:
    """The app's way with a paint layer: checked from its header, decoded by Gradio's
    editor, made into masks; a refusal (``gr.Error``) counts as a ``ValueError``."""
    import gradio as gr

    from app.painting import bound_canvas, masks_from_layers

    editor = bound_canvas(gr.ImageEditor(type="numpy", image_mode="RGBA"))
    try:
        layer = editor.convert_and_format_image(data)
        sharp, blur = masks_from_layers([layer])
    except gr.Error as exc:
        raise ValueError(str(exc)) from None
    return _pixels(layer)


def _paint_layer_inflations(data: bytes) -> list[bytes]:
    return [writers.png_bomb_header(s, s) for s in (1601, 14_000, 100_000)] + _mask_extras((H, W))


KINDS = {
    # kind: (valid file, decoder, decoded bytes a pixel, inflations, extremes, duplicates)
    # 16-bit PNG: 4 float32 channels a pixel (a mutant's colour type may add alpha)
    "png16": (_png16, _load_photo, 4 * 4, _png16_inflations, _png_extremes, _png_duplicates),
    "png16_wide": (_png16_wide, _load_photo, 4 * 4, _inflations_none, _png_extremes,
                   _png_duplicates),
    "png16_tall": (_png16_tall, _load_photo, 4 * 4, _inflations_none, _png_extremes,
                   _png_duplicates),
    "mpo": (_mpo, _decode_photo, 3 * 4, _mpo_inflations, _jpeg_extremes, _jpeg_duplicates),
    # a Lens Blur file holds two photos, both decoded: the blurred one and the original
    "gdepth": (_lensblur, _decode_photo, 2 * 3 * 4, _xmp_inflations, _jpeg_extremes,
               _jpeg_duplicates),
    "tiff": (_tiff, _read_depth, 8, _inflations_none, _tiff_extremes, _tiff_duplicates),
    "pfm": (_pfm_seed, _read_depth, 8, _pfm_inflations, _pfm_extremes, _span_duplicates),
    "npy": (_npy, _read_depth, 8, _npy_inflations, _npy_extremes, _span_duplicates),
    # a brush's mask: float32 out, an RGBA copy and an LA copy on the way
    "mask_png": (_mask_png, _load_mask_png, 4 * 4, _mask_png_inflations, _png_extremes,
                 _png_duplicates),
    "mask_tiff": (_mask_tiff, _load_mask_tiff, 8, _mask_tiff_inflations, _tiff_extremes,
                  _tiff_duplicates),
    # the app's paint layer: RGBA out, and two masks
    "paint_layer": (_paint_layer_png, _paint_layer, 4 * 4, _paint_layer_inflations,
                    _png_extremes, _png_duplicates),
}  # fmt: skip


def _cases(kind: str) -> tuple[bytes, list[tuple[str, bytes]]]:
    make, _, _, inflations, extremes, duplicates = KINDS[kind]
    valid = make()
    rng = random.Random(f"d2f-fuzz-{kind}")
    cases = [("inflate", c) for c in inflations(valid)]
    cases += [("mutate", c) for c in _mutations(valid, rng, CASES_PER_KIND * 3)]
    cases += [("extreme", c) for c in extremes(valid, rng, EXTREMES_PER_KIND)]
    cases += [("duplicate", c) for c in duplicates(valid, rng)]
    if kind.startswith("png16"):
        cases += [("filter", c) for c in _png_filters(valid, rng)]
    return valid, cases


def _seconds_per_pixel() -> float:
    """Best of three decodes by Pillow of a square 8-bit RGB PNG, per pixel: the unit of
    time, measured in the same process, by a decoder that is not under test."""
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 256, (512, 512, 3), dtype=np.uint8)).save(buf, "PNG")
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        with Image.open(io.BytesIO(buf.getvalue())) as im:
            im.load()
        best = min(best, time.perf_counter() - t0)
    return best / (512 * 512)


def run_batch(kind: str) -> dict:
    """Every case of ``kind`` in this process (the child); what went wrong, as JSON-able."""
    _, decode, per_pixel_bytes, *_ = KINDS[kind]
    valid, cases = _cases(kind)
    Image.init()  # every Pillow plugin imported now, not counted in a case's memory
    seed_pixels = decode(valid)  # the valid file decodes (and the modules are imported)
    unit = _seconds_per_pixel()
    failures = []
    for index, (how, data) in enumerate(cases):
        claimed = _claimed_pixels(data)
        tracemalloc.start()
        t0 = time.perf_counter()
        pixels = 0
        try:
            pixels = decode(data)
            outcome = "result"
        except ValueError:
            outcome = "ValueError"
        except Exception as exc:  # noqa: BLE001 (the failure is recorded)
            outcome = f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        limit = 4 * per_pixel_bytes * max(seed_pixels, pixels, claimed) + SLACK
        allowed = FLOOR_S + PER_PIXEL * unit * max(seed_pixels, pixels)
        if outcome not in ("result", "ValueError") or peak > limit or seconds > allowed:
            failures.append(f"{how} #{index}: {outcome[:200]}, peak {peak / 1e6:.2f} MB "
                            f"(limit {limit / 1e6:.2f}), {seconds:.2f} s "
                            f"(allowed {allowed:.2f})")  # fmt: skip
            if len(failures) == MAX_FAILURES:
                failures.append(f"stopped after {MAX_FAILURES} failures, {index + 1} cases")
                break
    return {"cases": len(cases), "failures": failures, "unit_ns": unit * 1e9}


@pytest.mark.parametrize("kind", list(KINDS))
def test_fuzz(kind):
    here = Path(__file__).resolve().parent
    import d2f_core

    root = Path(d2f_core.__file__).resolve().parents[1]
    code = (
        f"import json, sys\nsys.path[:0] = [{str(here)!r}, {str(root)!r}]\n"
        "import test_fuzz_decoders as fuzz\n"
        f"print(json.dumps(fuzz.run_batch({kind!r})))\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (CHILD_AS, CHILD_AS))

    try:
        done = subprocess.run(
            [sys.executable, "-c", code], cwd=root, env=env, preexec_fn=cap,
            capture_output=True, text=True, timeout=CHILD_TIMEOUT_S,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail(f"{kind}: the batch ran past {CHILD_TIMEOUT_S} s")
    lines = done.stdout.strip().splitlines()
    assert done.returncode == 0 and lines, (
        f"{kind}: the child died (rc {done.returncode}): {done.stderr[-3000:]}"
    )
    report = json.loads(lines[-1])
    failures = report["failures"]
    assert report["cases"] > 100
    assert not failures, f"{len(failures)} of {report['cases']} {kind} cases:\n" + "\n".join(
        failures
    )
