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


def exif_orientation(im: Image.Image, data: bytes | None = None) -> int:
    """EXIF orientation (1..8) of a Pillow image; 1 when absent or invalid.

    For a PNG pass its bytes as ``data``: its eXIf chunk is then found by a scan of its
    chunks. Pillow's ``getexif`` decodes the whole image to look for an eXIf chunk after the
    image data, before any size check could refuse it.
    """
    try:
        if data is not None and im.format == "PNG":
            raw = _png_exif(data)
            if raw is None:
                return 1
            ex = Image.Exif()
            ex.load(raw)
            value = ex.get(EXIF_ORIENTATION, 1)
        else:
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

#: Bytes inflated at a time: the inflater never hands out more than this in one piece.
_INFLATE_STEP = 1 << 20


def _png_chunks(data: bytes):
    """``(type, body)`` of each chunk up to IEND; bodies are memoryviews (no copies)."""
    view = memoryview(data)
    pos = 8
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", view[pos : pos + 4])
        ctype = bytes(view[pos + 4 : pos + 8])
        body = view[pos + 8 : pos + 8 + length]
        if len(body) < length:
            raise ValueError("truncated PNG chunk")
        yield ctype, body
        pos += 12 + length
        if ctype == b"IEND":
            return


def _png_exif(data: bytes) -> bytes | None:
    """The eXIf chunk of a PNG as EXIF bytes (``Exif\\0\\0`` first), or None."""
    try:
        for ctype, body in _png_chunks(data):
            if ctype == b"eXIf":
                raw = bytes(body)
                return raw if raw.startswith(b"Exif\x00\x00") else b"Exif\x00\x00" + raw
    except (ValueError, struct.error):
        return None
    return None


def png16_header(data: bytes) -> tuple[int, int, int, bool] | None:
    """``(width, height, channels, interlaced)`` of a 16-bit colour PNG (RGB, RGBA,
    grey+alpha) from its IHDR chunk, or None for any other file."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n") or len(data) < 29 or data[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    channels = {2: 3, 4: 2, 6: 4}.get(ctype)
    if depth != 16 or channels is None:
        return None
    return w, h, channels, bool(interlace)


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _png_unfilter(rows: np.ndarray, h: int, w: int, bpp: int) -> np.ndarray:
    """Undo PNG scanline filters in place. ``rows``: (h, 1 + w * bpp) uint8, the filter type
    byte then the filtered bytes of each scanline. Returns the (h, w, bpp) uint8 view of
    ``rows`` that holds the pixels' bytes.

    Average and Paeth depend on the left, upper and upper-left pixels, so rows cannot be
    decoded independently; sweeping anti-diagonals decodes every pixel whose neighbours are
    done in one vectorised step (h + w steps instead of h * w). Each byte is read as filtered
    before it is written as decoded, so no second copy of the image is made.
    """
    ftype = rows[:, 0].copy()
    if (ftype > 4).any():
        raise ValueError("corrupt PNG filter type")
    pix = rows[:, 1:].reshape(h, w, bpp)  # a view: the decode writes into ``rows``
    if not ((ftype == 3) | (ftype == 4)).any():
        for i in range(h):
            if ftype[i] == 1:
                pix[i] = np.cumsum(pix[i], axis=0, dtype=np.uint8)  # wraps modulo 256
            elif ftype[i] == 2 and i > 0:
                pix[i] += pix[i - 1]
        return pix
    ft = ftype.astype(np.int16)
    for t in range(h + w - 1):
        i = np.arange(max(0, t - w + 1), min(h - 1, t) + 1)
        j = t - i
        left, up = j > 0, i > 0
        a = pix[i, np.maximum(j - 1, 0)].astype(np.int16)
        a[~left] = 0
        b = pix[np.maximum(i - 1, 0), j].astype(np.int16)
        b[~up] = 0
        c = pix[np.maximum(i - 1, 0), np.maximum(j - 1, 0)].astype(np.int16)
        c[~(left & up)] = 0
        f = ft[i][:, None]
        pred = np.where(f == 1, a, np.where(f == 2, b, np.where(f == 3, (a + b) >> 1, 0)))
        paeth_rows = f[:, 0] == 4
        if paeth_rows.any():
            pred[paeth_rows] = _paeth(a[paeth_rows], b[paeth_rows], c[paeth_rows])
        pix[i, j] = (pix[i, j] + pred) & 0xFF
    return pix


def _inflate_bounded(chunks, limit: int) -> np.ndarray:
    """The zlib stream spread over ``chunks``, inflated into at most ``limit`` bytes.

    The work and the memory never exceed what ``limit`` allows, whatever the stream claims:
    it is inflated a piece at a time (:data:`_INFLATE_STEP`), and one byte past ``limit``
    is refused as a corrupt file.
    """
    inflater = zlib.decompressobj()
    out = bytearray()
    try:
        for body in chunks:
            pending = body
            while pending and not inflater.eof:
                step = min(_INFLATE_STEP, limit + 1 - len(out))
                out += inflater.decompress(pending, step)
                if len(out) > limit:
                    raise ValueError(
                        f"corrupt PNG image data: it inflates to more than the {limit} bytes "
                        "that its header's size needs"
                    )
                pending = inflater.unconsumed_tail
            if inflater.eof:
                break
    except zlib.error as exc:
        raise ValueError(f"corrupt PNG image data: {exc}") from exc
    if not inflater.eof:
        raise ValueError("truncated PNG image data (compressed stream ends early)")
    return np.frombuffer(out, np.uint8)


def decode_png16(data: bytes) -> tuple[np.ndarray, bytes | None] | None:
    """Decode a non-interlaced 16-bit colour PNG (RGB, RGBA, grey+alpha) at full precision.

    Pillow reduces these to 8 bits. Returns (HxWxC uint16, eXIf bytes or None), or None when
    the file is not of this kind (the caller then uses Pillow).

    The image data is inflated with a bound: the rows that the header's size needs (its
    filter bytes included) and not one byte more, so the cost follows the header, never what
    the compressed stream claims; more data is refused as a corrupt file. The memory is the
    inflated rows (decoded in place) and the returned array.
    """
    header = png16_header(data)
    if header is None:
        return None
    w, h, channels, interlace = header
    if interlace:
        logger.info("interlaced 16-bit PNG: decoded by Pillow at 8-bit precision")
        return None
    if w <= 0 or h <= 0:
        raise ValueError(f"PNG image has no pixels ({w}x{h})")
    bpp = channels * 2
    needed = h * (w * bpp + 1)
    idat = []
    exif = None
    for ctype, body in _png_chunks(data):
        if ctype == b"IDAT":
            idat.append(body)
        elif ctype == b"eXIf" and exif is None:
            exif = bytes(body)
    raw = _inflate_bounded(idat, needed)
    if raw.size < needed:
        raise ValueError(f"truncated PNG image data ({raw.size} of {needed} bytes)")
    pix = _png_unfilter(raw.reshape(h, w * bpp + 1), h, w, bpp)
    arr = pix.view(">u2").astype(np.uint16)  # (h, w, channels), big-endian samples
    del pix, raw
    if exif is not None and not exif.startswith(b"Exif\x00\x00"):
        exif = b"Exif\x00\x00" + exif
    return arr, exif
