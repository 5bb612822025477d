"""What image files hold that Pillow reads wrong or not at all: the EXIF orientation (applied
to the pixels, stripped from what is saved) and 16-bit PNG, decoded at full precision.
"""

from __future__ import annotations

import functools
import io
import logging
import struct
import zlib

import numpy as np
from PIL import Image

logger = logging.getLogger("d2f_core.io.image")


EXIF_ORIENTATION = 0x0112


# --------------------------------------------------------------------------- orientation


@functools.cache
def pillow_orients_tiff() -> bool:
    """Whether this Pillow turns a TIFF upright itself: it reports the upright size when it
    opens one and transposes the pixels when it loads them (Pillow 12 does). Found once, on a
    2x1 TIFF with orientation 6, whatever the version."""
    buf = io.BytesIO()
    exif = Image.Exif()
    exif[EXIF_ORIENTATION] = 6
    Image.new("L", (2, 1)).save(buf, format="TIFF", exif=exif)
    buf.seek(0)
    with Image.open(buf) as im:
        im.load()
        return im.size == (1, 2)


def exif_orientation(im: Image.Image, data: bytes | None = None) -> int:
    """EXIF orientation (1..8) of a Pillow image that is still to be applied; 1 when absent,
    invalid, or applied by Pillow itself (a TIFF, where :func:`pillow_orients_tiff`).

    For a PNG pass its bytes as ``data``: its eXIf chunk is then found by a scan of its
    chunks. Pillow's ``getexif`` decodes the whole image to look for an eXIf chunk after the
    image data, before any size check could refuse it.
    """
    if im.format == "TIFF" and pillow_orients_tiff():
        return 1
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

#: Most bytes one byte of a Deflate stream can inflate to (RFC 1951: a 258-byte match in
#: about 2 bits; 1032:1 overall).
DEFLATE_MAX_RATIO = 1032

#: libpng's default limit on a side (``png_set_user_limits``): a wider or taller 16-bit PNG is
#: read by Pillow at 8 bits per channel instead (libpng would refuse its header).
LIBPNG_MAX_SIDE = 1_000_000

# libpng's warnings (image data past the last row, a known-bad sRGB profile) come through the
# "imagecodecs" logger; with no handler anywhere Python would print them bare on stderr, next
# to the CLI's one-line messages. They still reach any handler an application installs.
logging.getLogger("imagecodecs").addHandler(logging.NullHandler())


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


def _png_codec():
    """imagecodecs' libpng decoder, or None when the package is missing (logged once)."""
    global _codec_missing_logged
    try:
        from imagecodecs import png_decode
    except ImportError:
        if not _codec_missing_logged:
            logger.warning("imagecodecs is not installed: 16-bit PNGs are read at 8 bits")
            _codec_missing_logged = True
        return None
    return png_decode


_codec_missing_logged = False


#: Most bytes inflated per step by :func:`_inflates_past` (its memory, whatever the stream).
_INFLATE_STEP = 1 << 20


def _inflates_past(data: bytes, needed: int) -> bool:
    """Whether a PNG's image data (its IDAT chunks, one zlib stream) inflates to more than
    ``needed`` bytes. Stops a step past ``needed``, so a stream of any length costs the
    inflating of the image's own rows, with memory of one step."""
    inflate = zlib.decompressobj()
    total = 0
    try:
        for ctype, body in _png_chunks(data):
            if ctype != b"IDAT":
                continue
            pending = bytes(body)
            while pending and not inflate.eof:
                total += len(inflate.decompress(pending, _INFLATE_STEP))
                if total > needed:
                    return True
                pending = inflate.unconsumed_tail
    except (ValueError, struct.error, zlib.error):
        return False  # a truncated or corrupt stream: libpng says where
    return False


def decode_png16(data: bytes) -> tuple[np.ndarray, bytes | None] | None:
    """Decode a non-interlaced 16-bit colour PNG (RGB, RGBA, grey+alpha) at full precision.

    Pillow reduces these to 8 bits. Returns (HxWxC uint16, eXIf bytes or None), or None when
    the file is not of this kind or the decoder cannot take it (the caller then uses
    Pillow, at 8 bits): an interlaced file, a side over :data:`LIBPNG_MAX_SIDE`, no
    imagecodecs.

    libpng (through imagecodecs) decodes it in C, a row at a time: the time follows the
    pixel count whatever the shape and the filters, and the memory is the returned array
    (sized from the header, which the caller has checked against its pixel limits) and a
    row or two; a header that claims more than its compressed data can hold is refused
    before that array exists. libpng checks every chunk's CRC; image data past the header's
    rows is ignored.
    A transparency (tRNS) chunk becomes an alpha channel.
    """
    header = png16_header(data)
    if header is None:
        return None
    w, h, channels, interlace = header
    if w <= 0 or h <= 0:
        raise ValueError(f"PNG image has no pixels ({w}x{h})")
    if interlace:
        logger.info("interlaced 16-bit PNG: decoded by Pillow at 8-bit precision")
        return None
    if max(w, h) > LIBPNG_MAX_SIDE:
        logger.info(
            "16-bit PNG of %dx%d: a side over %d pixels, decoded by Pillow at 8-bit precision",
            w, h, LIBPNG_MAX_SIDE,
        )  # fmt: skip
        return None
    png_decode = _png_codec()
    if png_decode is None:
        return None
    exif, compressed = None, 0
    try:
        for ctype, body in _png_chunks(data):
            if ctype == b"IDAT":
                compressed += len(body)
            elif ctype == b"eXIf" and exif is None:
                exif = bytes(body)
    except (ValueError, struct.error):
        pass  # a truncated file: libpng says where
    needed = h * (1 + w * channels * 2)  # the filter byte and the samples of each row
    if needed > DEFLATE_MAX_RATIO * compressed + 64:
        # checked before libpng allocates the header's image: a small file that claims a
        # large one is refused without its memory
        raise ValueError(
            f"truncated PNG image data: {compressed} compressed bytes cannot hold the "
            f"{needed} bytes of a {w}x{h} image"
        )
    if _inflates_past(data, needed + needed // 64 + 4096):
        # libpng would inflate all of it (a 1 MB file can hold a GiB of zeros) to ignore it;
        # a little padding past the rows, which some encoders leave, is taken
        raise ValueError(
            f"corrupt PNG: its image data holds more than the {needed} bytes of a {w}x{h} image"
        )
    try:
        arr = png_decode(data)
    except MemoryError:
        raise
    except Exception as exc:  # noqa: BLE001 (imagecodecs.PngError is a RuntimeError)
        raise ValueError(f"truncated or corrupt PNG image data: {exc}") from None
    if arr.dtype != np.uint16 or arr.ndim != 3 or arr.shape[:2] != (h, w):
        raise ValueError(f"corrupt PNG: decoded as {arr.shape} {arr.dtype}, header says {w}x{h}")
    if exif is not None and not exif.startswith(b"Exif\x00\x00"):
        exif = b"Exif\x00\x00" + exif
    return arr, exif
