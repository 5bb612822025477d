"""What image files hold that Pillow reads wrong or not at all: the EXIF orientation (applied
to the pixels, stripped from what is saved) and 16-bit PNG, decoded at full precision.
"""

from __future__ import annotations

import logging
import struct
import zlib

import numpy as np
from PIL import Image

logger = logging.getLogger("d2f_core.io.image")


EXIF_ORIENTATION = 0x0112


# --------------------------------------------------------------------------- orientation


def exif_orientation(im: Image.Image) -> int:
    """EXIF orientation (1..8) of a Pillow image; 1 when absent or invalid."""
    try:
        value = im.getexif().get(EXIF_ORIENTATION, 1)
    except Exception:  # a malformed EXIF block must not stop the photo from loading
        return 1
    try:
        value = int(value)
    except (TypeError, ValueError):
        return 1
    return value if 1 <= value <= 8 else 1


def apply_orientation(array: np.ndarray, orientation: int) -> np.ndarray:
    """Make an array upright according to an EXIF orientation value.

    Matches ``PIL.ImageOps.exif_transpose``. Works on HxW and HxWxC arrays.
    """
    a = array
    if orientation == 2:
        a = a[:, ::-1]
    elif orientation == 3:
        a = a[::-1, ::-1]
    elif orientation == 4:
        a = a[::-1]
    elif orientation == 5:
        a = a.swapaxes(0, 1)
    elif orientation == 6:
        a = np.rot90(a, -1)
    elif orientation == 7:
        a = np.rot90(a, 2).swapaxes(0, 1)
    elif orientation == 8:
        a = np.rot90(a, 1)
    return np.ascontiguousarray(a)


def strip_orientation(exif: bytes | Image.Exif | None) -> bytes | None:
    """EXIF bytes with the orientation tag removed (pixels are stored upright)."""
    if exif is None:
        return None
    try:
        if isinstance(exif, Image.Exif):
            ex = exif
        else:
            ex = Image.Exif()
            ex.load(bytes(exif))
        if EXIF_ORIENTATION in ex:
            del ex[EXIF_ORIENTATION]
        out = ex.tobytes()
    except Exception as exc:  # keep the photo, lose only its broken EXIF
        logger.warning("dropping unreadable EXIF block: %s", exc)
        return None
    return out if len(out) > 8 else None


# --------------------------------------------------------------------------- 16-bit PNG


def _png_chunks(data: bytes):
    pos = 8
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        ctype = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if len(body) < length:
            raise ValueError("truncated PNG chunk")
        yield ctype, body
        pos += 12 + length
        if ctype == b"IEND":
            return


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _png_unfilter(raw: np.ndarray, h: int, w: int, bpp: int) -> np.ndarray:
    """Undo PNG scanline filters. Returns (h, w, bpp) uint8.

    Average and Paeth depend on the left, upper and upper-left pixels, so rows cannot be
    decoded independently; sweeping anti-diagonals decodes every pixel whose neighbours are
    done in one vectorised step (h + w steps instead of h * w).
    """
    stride = w * bpp
    if raw.size < h * (stride + 1):
        raise ValueError("truncated PNG image data")
    rows = raw[: h * (stride + 1)].reshape(h, stride + 1)
    ftype = rows[:, 0].astype(np.int32)
    if (ftype > 4).any():
        raise ValueError("corrupt PNG filter type")
    filt = rows[:, 1:].reshape(h, w, bpp).astype(np.int32)
    out = np.zeros((h + 1, w + 1, bpp), np.int32)  # zero row/column = PNG's "outside" pixels
    if not ((ftype == 3) | (ftype == 4)).any():
        for i in range(h):
            if ftype[i] == 0:
                out[i + 1, 1:] = filt[i]
            elif ftype[i] == 1:
                out[i + 1, 1:] = np.cumsum(filt[i], axis=0) & 0xFF
            else:
                out[i + 1, 1:] = (filt[i] + out[i, 1:]) & 0xFF
        return out[1:, 1:].astype(np.uint8)
    for t in range(h + w - 1):
        i = np.arange(max(0, t - w + 1), min(h - 1, t) + 1)
        j = t - i
        a = out[i + 1, j]
        b = out[i, j + 1]
        c = out[i, j]
        ft = ftype[i][:, None]
        pred = np.where(ft == 1, a, np.where(ft == 2, b, np.where(ft == 3, (a + b) >> 1, 0)))
        paeth_rows = ft[:, 0] == 4
        if paeth_rows.any():
            pred[paeth_rows] = _paeth(a[paeth_rows], b[paeth_rows], c[paeth_rows])
        out[i + 1, j + 1] = (filt[i, j] + pred) & 0xFF
    return out[1:, 1:].astype(np.uint8)


def decode_png16(data: bytes) -> tuple[np.ndarray, bytes | None] | None:
    """Decode a non-interlaced 16-bit colour PNG (RGB, RGBA, grey+alpha) at full precision.

    Pillow reduces these to 8 bits. Returns (HxWxC uint16, eXIf bytes or None), or None when
    the file is not of this kind (the caller then uses Pillow).
    """
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return None
    chunks = list(_png_chunks(data))
    if not chunks or chunks[0][0] != b"IHDR":
        raise ValueError("PNG without IHDR chunk")
    w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", chunks[0][1][:13])
    channels = {2: 3, 4: 2, 6: 4}.get(ctype)
    if depth != 16 or channels is None:
        return None
    if interlace:
        logger.info("interlaced 16-bit PNG: decoded by Pillow at 8-bit precision")
        return None
    idat = b"".join(body for ctype_, body in chunks if ctype_ == b"IDAT")
    exif = next((body for ctype_, body in chunks if ctype_ == b"eXIf"), None)
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(idat)
    except zlib.error as exc:
        raise ValueError(f"corrupt PNG image data: {exc}") from exc
    if not inflater.eof:
        raise ValueError("truncated PNG image data (compressed stream ends early)")
    bytes_ = _png_unfilter(np.frombuffer(raw, np.uint8), h, w, channels * 2)
    pixels = bytes_.reshape(h, w, channels, 2)
    arr = (pixels[..., 0].astype(np.uint16) << 8) | pixels[..., 1]
    if exif is not None and not exif.startswith(b"Exif\x00\x00"):
        exif = b"Exif\x00\x00" + exif
    return arr, exif
