"""Test helpers that build image files the project must read: a Google Lens Blur JPEG with
standard + extended XMP, an Apple-style portrait MPO, 16-bit colour PNGs with every
scanline filter, a PNG header that claims a huge size, and tiled float TIFFs.

Written from the format specifications so that the readers are tested against independent
writers, not against themselves.
"""

from __future__ import annotations

import base64
import hashlib
import io
import random
import struct
import zlib

import numpy as np
from PIL import Image

XMP_STD_SIG = b"http://ns.adobe.com/xap/1.0/\x00"
XMP_EXT_SIG = b"http://ns.adobe.com/xmp/extension/\x00"


# --------------------------------------------------------------------------- PNG


def _chunk(ctype: bytes, body: bytes) -> bytes:
    crc = zlib.crc32(ctype + body) & 0xFFFFFFFF
    return struct.pack(">I", len(body)) + ctype + body + struct.pack(">I", crc)


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The PNG Paeth predictor (PNG specification, 9.4) of arrays, ties broken as written
    there: a, then b, then c."""
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def png16_bytes(array: np.ndarray, filters: list[int] | None = None, exif: bytes = b"") -> bytes:
    """Encode an HxWxC uint16 array (C = 2, 3 or 4) as a 16-bit PNG.

    ``filters`` gives the PNG filter type (0..4) of each row (cycled); this exercises every
    unfilter path of the reader. The encoder predicts from the original bytes only (left,
    up, upper left), so every row and filter is computed at once with NumPy: lines of a
    100,000 pixels take milliseconds.
    """
    h, w, c = array.shape
    ctype = {2: 4, 3: 2, 4: 6}[c]
    bpp = 2 * c
    cur = array.astype(">u2").reshape(h, w * c).view(np.uint8).reshape(h, w * bpp)
    cur = cur.astype(np.int64)
    up = np.zeros_like(cur)
    up[1:] = cur[:-1]
    left = np.zeros_like(cur)
    left[:, bpp:] = cur[:, :-bpp]
    upleft = np.zeros_like(cur)
    upleft[:, bpp:] = up[:, :-bpp]
    predictions = np.stack(
        [np.zeros_like(cur), left, up, (left + up) // 2, _paeth(left, up, upleft)]
    )
    cycle = np.asarray(filters or [0], np.int64)
    ftype = cycle[np.arange(h) % len(cycle)]
    lines = (cur - predictions[ftype, np.arange(h)]) & 0xFF
    raw = np.concatenate([ftype[:, None], lines], axis=1).astype(np.uint8).tobytes()
    ihdr = struct.pack(">IIBBBBB", w, h, 16, ctype, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr)
    if exif:
        data += _chunk(b"eXIf", exif[6:] if exif.startswith(b"Exif\x00\x00") else exif)
    return data + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


def png16_stream(
    width: int, height: int, channels: int = 3, *, inflated: int | None = None, ftype: int = 0
) -> bytes:
    """A 16-bit PNG (C = 2, 3 or 4) of a smooth pattern, written fast for large sizes: every
    row has filter ``ftype`` and the same bytes. ``inflated`` makes the IDAT stream inflate
    to that many bytes instead of the header's rows (a decompression bomb when larger)."""
    ctype = {2: 4, 3: 2, 4: 6}[channels]
    ihdr = struct.pack(">IIBBBBB", width, height, 16, ctype, 0, 0, 0)
    pattern = np.array([0x80, 1, 0x40, 2, 0x20, 3, 0xFF, 0xFF], np.uint8)[: 2 * channels]
    row = bytes([ftype]) + np.tile(pattern, width).tobytes()
    total = len(row) * height if inflated is None else inflated
    comp = zlib.compressobj(9)
    parts = []
    block = row * max(1, (1 << 20) // len(row))  # whole rows
    left = total
    while left > 0:
        piece = block[:left] if left < len(block) else block
        parts.append(comp.compress(piece))
        left -= len(piece)
    idat = b"".join(parts) + comp.flush()
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


def png_bomb_header(width: int = 100_000, height: int = 100_000) -> bytes:
    """A tiny PNG whose header claims ``width`` x ``height`` 8-bit grey pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 1024)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


# --------------------------------------------------------------------------- Lens Blur


def encode_gdepth(z: np.ndarray, near: float, far: float, fmt: str, bits: int = 8) -> bytes:
    """Google depth-map encoding of metric depth ``z`` as a PNG (8 or 16-bit)."""
    if fmt == "RangeInverse":
        dn = far * (z - near) / (z * (far - near))
    else:
        dn = (z - near) / (far - near)
    dn = np.clip(dn, 0.0, 1.0)
    if bits == 16:
        img = Image.fromarray(np.round(dn * 65535).astype(np.uint16))
    else:
        img = Image.fromarray(np.round(dn * 255).astype(np.uint8))
    buf = io.BytesIO()
    img.save(buf, "PNG")
    return buf.getvalue()


def _jpeg(array: np.ndarray, quality: int = 95) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, "JPEG", quality=quality, subsampling=0)
    return buf.getvalue()


def lensblur_jpeg(
    photo: np.ndarray,
    rendered: np.ndarray,
    z: np.ndarray,
    *,
    near: float,
    far: float,
    fmt: str = "RangeInverse",
    bits: int = 8,
    focal_distance: float | None = None,
    focal_point: tuple[float, float] | None = None,
    chunk_size: int = 65000,
    shuffle: bool = False,
    drop_chunk: bool = False,
    seed: int = 0,
) -> bytes:
    """Build a Lens Blur JPEG: main image ``rendered`` (uint8 HxWx3), the original ``photo``
    in GImage:Data, depth ``z`` in GDepth:Data, focus in GFocus.

    The extended XMP is split into APP1 chunks of ``chunk_size`` bytes (<= 65400); they can
    be written in shuffled order, or one left out to simulate a damaged file.
    """
    depth_png = encode_gdepth(z, near, far, fmt, bits)
    ext = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">'
        '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about=""'
        ' xmlns:GImage="http://ns.google.com/photos/1.0/image/"'
        ' xmlns:GDepth="http://ns.google.com/photos/1.0/depthmap/"'
        f' GImage:Data="{base64.b64encode(_jpeg(photo)).decode()}"'
        f' GDepth:Data="{base64.b64encode(depth_png).decode()}"/>'
        "</rdf:RDF></x:xmpmeta>"
    ).encode()
    guid = hashlib.md5(ext).hexdigest().upper().encode()
    focus_attrs = ""
    if focal_distance is not None:
        focus_attrs += f' GFocus:FocalDistance="{focal_distance}"'
    if focal_point is not None:
        focus_attrs += (
            f' GFocus:FocalPointX="{focal_point[0]}" GFocus:FocalPointY="{focal_point[1]}"'
        )
    std = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">'
        '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about=""'
        ' xmlns:GFocus="http://ns.google.com/photos/1.0/focus/"'
        ' xmlns:GImage="http://ns.google.com/photos/1.0/image/"'
        ' xmlns:GDepth="http://ns.google.com/photos/1.0/depthmap/"'
        ' xmlns:xmpNote="http://ns.adobe.com/xmp/note/"'
        f'{focus_attrs} GImage:Mime="image/jpeg" GDepth:Format="{fmt}"'
        f' GDepth:Near="{near}" GDepth:Far="{far}" GDepth:Mime="image/png"'
        f' xmpNote:HasExtendedXMP="{guid.decode()}"/>'
        "</rdf:RDF></x:xmpmeta>"
    ).encode()
    segments = [
        b"\xff\xe1" + struct.pack(">H", 2 + len(XMP_STD_SIG) + len(std)) + XMP_STD_SIG + std
    ]
    parts = []
    for offset in range(0, len(ext), chunk_size):
        body = XMP_EXT_SIG + guid + struct.pack(">II", len(ext), offset)
        body += ext[offset : offset + chunk_size]
        parts.append(b"\xff\xe1" + struct.pack(">H", 2 + len(body)) + body)
    if shuffle:
        random.Random(seed).shuffle(parts)
    if drop_chunk:
        parts = parts[:-1]
    main = _jpeg(rendered)
    return main[:2] + b"".join(segments + parts) + main[2:]


# --------------------------------------------------------------------------- Apple MPO


def apple_mpo(
    photo: np.ndarray,
    disparity_u8: np.ndarray,
    *,
    float_min: float,
    float_max: float,
    focus_region: tuple[float, float, float, float] | None = None,
    aux_type: str = "disparity",
) -> bytes:
    """An Apple-style portrait MPO: frame 0 the photo (with an MWG Focus region), frame 1 an
    8-bit disparity map described by ``apdi`` XMP."""
    regions = ""
    if focus_region is not None:
        x, y, w, h = focus_region
        regions = (
            "<mwg-rs:Regions rdf:parseType='Resource'><mwg-rs:RegionList><rdf:Seq>"
            "<rdf:li rdf:parseType='Resource'><mwg-rs:Area rdf:parseType='Resource'>"
            f"<stArea:y>{y}</stArea:y><stArea:w>{w}</stArea:w><stArea:x>{x}</stArea:x>"
            f"<stArea:h>{h}</stArea:h><stArea:unit>normalized</stArea:unit></mwg-rs:Area>"
            "<mwg-rs:Type>Focus</mwg-rs:Type></rdf:li></rdf:Seq></mwg-rs:RegionList>"
            "</mwg-rs:Regions>"
        )
    primary_xmp = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">'
        '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about=""'
        ' xmlns:mwg-rs="http://www.metadataworkinggroup.com/schemas/regions/"'
        ' xmlns:stArea="http://ns.adobe.com/xmp/sType/Area#">'
        f"{regions}</rdf:Description></rdf:RDF></x:xmpmeta>"
    ).encode()
    depth_xmp = (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">'
        '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about="" xmlns:apdi="http://ns.apple.com/pixeldatainfo/1.0/">'
        f"<apdi:AuxiliaryImageType>{aux_type}</apdi:AuxiliaryImageType>"
        f"<apdi:FloatMinValue>{float_min}</apdi:FloatMinValue>"
        f"<apdi:FloatMaxValue>{float_max}</apdi:FloatMaxValue>"
        "<apdi:IntMinValue>0</apdi:IntMinValue><apdi:IntMaxValue>255</apdi:IntMaxValue>"
        "</rdf:Description></rdf:RDF></x:xmpmeta>"
    ).encode()
    main = Image.fromarray(photo)
    depth = Image.fromarray(disparity_u8)
    depth.encoderinfo = {"xmp": depth_xmp, "quality": 100}
    buf = io.BytesIO()
    main.save(buf, "MPO", save_all=True, append_images=[depth], xmp=primary_xmp, quality=95)
    return buf.getvalue()


# --------------------------------------------------------------------------- tiled TIFF


def tiled_float_tiff(
    width: int,
    height: int,
    tile: int = 256,
    value=lambda ty, tx: 1.0,
    *,
    compress: bool = True,
) -> bytes:
    """A little-endian TIFF of one ``height`` x ``width`` float32 page stored in square tiles
    of ``tile`` pixels, each tile Deflate-compressed (``compress``) and filled with
    ``value(tile_row, tile_column)``.

    Tiles of equal value share one stored copy (every tile offset may point at the same
    bytes, which TIFF allows), so a 40000 x 40000 page of one value takes a few hundred KB:
    the size a reader must refuse from the header, before it decodes anything.
    Written from the TIFF 6.0 specification (tags 256-339) for the readers under test.
    """
    across, down = -(-width // tile), -(-height // tile)
    stored: dict[float, tuple[int, int]] = {}
    blobs = bytearray()
    offsets, counts = [], []
    header_room = 8
    for ty in range(down):
        for tx in range(across):
            v = float(value(ty, tx))
            if v not in stored:
                raw = np.full(tile * tile, v, "<f4").tobytes()
                body = zlib.compress(raw, 9) if compress else raw
                stored[v] = (len(blobs), len(body))
                blobs += body
            at, n = stored[v]
            offsets.append(header_room + at)
            counts.append(n)
    n_tiles = len(offsets)
    # the IFD follows the tile data; the two long arrays follow the IFD
    ifd_at = header_room + len(blobs)
    ifd_at += ifd_at % 2  # word boundary
    entries = [
        (256, 4, 1, width),  # ImageWidth, LONG
        (257, 4, 1, height),  # ImageLength
        (258, 3, 1, 32),  # BitsPerSample, SHORT
        (259, 3, 1, 8 if compress else 1),  # Compression: Deflate (Adobe) or none
        (262, 3, 1, 1),  # PhotometricInterpretation: BlackIsZero
        (277, 3, 1, 1),  # SamplesPerPixel
        (284, 3, 1, 1),  # PlanarConfiguration: chunky
        (322, 4, 1, tile),  # TileWidth
        (323, 4, 1, tile),  # TileLength
        (324, 4, n_tiles, None),  # TileOffsets
        (325, 4, n_tiles, None),  # TileByteCounts
        (339, 3, 1, 3),  # SampleFormat: IEEE float
    ]
    ifd_size = 2 + 12 * len(entries) + 4
    arrays_at = ifd_at + ifd_size
    ifd = bytearray(struct.pack("<H", len(entries)))
    extra = bytearray()
    for tag, typ, count, v in entries:
        if v is None:  # an array of LONGs stored after the IFD (or inline when it fits)
            values = offsets if tag == 324 else counts
            if count == 1:
                ifd += struct.pack("<HHII", tag, typ, 1, values[0])
                continue
            ifd += struct.pack("<HHII", tag, typ, count, arrays_at + len(extra))
            extra += struct.pack(f"<{count}I", *values)
        elif typ == 3:
            ifd += struct.pack("<HHIHH", tag, typ, count, v, 0)
        else:
            ifd += struct.pack("<HHII", tag, typ, count, v)
    ifd += struct.pack("<I", 0)  # no next IFD
    out = bytearray(b"II*\x00" + struct.pack("<I", ifd_at))
    out += blobs
    out += b"\x00" * (ifd_at - len(out))
    return bytes(out + ifd + extra)
