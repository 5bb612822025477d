"""Reading depth map files: the raw values of PNG 8/16-bit (and any grey image Pillow reads),
``.npy``, PFM and TIFF maps, each checked from its header against the photo it belongs to
(:func:`check_aspect`, the pixel limits) before a sample is decoded, and upright as their
photo is loaded. :mod:`d2f_core.io.depth` turns the values into normalised disparity.
"""

from __future__ import annotations

import io
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ..errors import whole_number
from .formats import apply_orientation, exif_orientation
from .image import MAX_DECODE_PIXELS, open_pil, read_source_bytes, source_name
from .save import atomic_write

# tifffile reports a malformed file through its logger, then raises or goes on; with no
# handler anywhere Python would print those lines bare on stderr, beside the CLI's one line
logging.getLogger("tifffile").addHandler(logging.NullHandler())


# --------------------------------------------------------------------------- PFM


def read_pfm(src: str | os.PathLike | bytes) -> np.ndarray:
    """Read a Portable Float Map.

    Returns:
        float32 array, HxW (``Pf``) or HxWx3 (``PF``), top row first (PFM stores bottom-up).

    Raises:
        ValueError: bad header or too little data.
    """
    data = read_source_bytes(src)
    name = source_name(src)
    return _read_pfm(data, name)


def _read_pfm(data: bytes, name: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """:func:`read_pfm` of a file's bytes; with ``size`` (the photo's (H, W)) the map's aspect
    ratio is checked from the header, before the samples are read."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if pos < len(data) and data[pos : pos + 1] == b"#":  # comment line
            pos = data.find(b"\n", pos) + 1 or len(data)
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            raise ValueError(f"{name}: truncated PFM header")
        tokens.append(data[start:pos])
    pos += 1  # exactly one whitespace byte separates the header from the samples
    magic = tokens[0]
    if magic not in (b"PF", b"Pf"):
        raise ValueError(f"{name}: not a PFM file (magic {magic[:8]!r})")
    try:
        width, height, scale = int(tokens[1]), int(tokens[2]), float(tokens[3])
    except ValueError as exc:
        raise ValueError(f"{name}: bad PFM header {b' '.join(tokens)!r}") from exc
    if width <= 0 or height <= 0 or scale == 0.0:
        raise ValueError(f"{name}: bad PFM size {width}x{height} or scale {scale}")
    channels = 3 if magic == b"PF" else 1
    if width * height > MAX_DECODE_PIXELS:
        raise ValueError(
            f"{name}: PFM header claims {width}x{height} = {width * height} pixels, more than "
            f"the limit of {MAX_DECODE_PIXELS}"
        )
    if size is not None:
        check_aspect((height, width), size, name)
    count = width * height * channels
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    if len(data) - pos < count * 4:
        raise ValueError(
            f"{name}: truncated PFM: {len(data) - pos} data bytes, expected {count * 4}"
        )
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=pos).astype(np.float32)
    arr = arr.reshape(height, width, channels)[::-1]
    return np.ascontiguousarray(arr[..., 0] if channels == 1 else arr)


def write_pfm(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write an HxW (``Pf``) or HxWx3 (``PF``) float array as little-endian PFM."""
    a = np.asarray(array, dtype=np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        magic = b"Pf"
    elif a.ndim == 3 and a.shape[2] == 3:
        magic = b"PF"
    else:
        raise ValueError(f"array: expected HxW or HxWx3, got shape {a.shape}")
    h, w = a.shape[:2]
    header = magic + b"\n%d %d\n-1.0\n" % (w, h)
    body = np.ascontiguousarray(a[::-1]).astype("<f4").tobytes()
    out = Path(path)
    atomic_write(out, lambda fh: fh.write(header + body))
    return out


# --------------------------------------------------------------------------- raw reading


def _grey_from_pil(im: Image.Image, name: str) -> np.ndarray:
    mode = im.mode
    if mode in ("L", "I", "F") or mode.startswith("I;16"):
        return np.asarray(im).astype(np.float64)
    if mode in ("LA", "La"):
        return np.asarray(im)[..., 0].astype(np.float64)
    if mode == "P":
        return np.asarray(im.convert("L")).astype(np.float64)
    if mode in ("RGB", "RGBA"):
        return _grey_channels(np.asarray(im)[..., :3].astype(np.float64), name, levels=255.0)
    raise ValueError(f"{name}: unsupported depth image mode {mode!r}")


def _grey_channels(a: np.ndarray, name: str, levels: float | None = None) -> np.ndarray:
    """The mean of an H x W x 3 map whose channels agree; a colour map is refused.

    ``levels`` is the full scale of the values (255 for 8-bit images); for other arrays the
    scale is the map's own range. JPEG chroma noise on a grey map stays far below the limit,
    16 / 255 of the scale; the hues of a colour-mapped visualisation do not.
    """
    spread = float(np.percentile(np.abs(a - a[..., :1]).max(axis=2), 99))
    scale = levels if levels is not None else max(float(a.max() - a.min()), 1e-12)
    if spread > 16.0 / 255.0 * scale:
        shown = (
            f"{spread:.0f} levels" if levels is not None else f"{spread / scale:.0%} of its range"
        )
        raise ValueError(
            f"{name}: depth map has colour (channels differ by {shown}); "
            "expected a single-channel map (a colour-mapped visualisation cannot be read)"
        )
    return a.mean(axis=2)


def _check_npy_header(data: bytes, name: str) -> tuple[int, ...]:
    """Refuse a ``.npy`` file from its header, before anything is allocated: a shape of more
    than :data:`~d2f_core.io.image.MAX_DECODE_PIXELS` values, or more bytes than the file
    holds (``np.load`` allocates the header's shape first, then reads)."""
    fh = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        elif version == (3, 0):
            shape, dtype = _npy_header_3_0(fh)
        else:
            raise ValueError(f"format version {version[0]}.{version[1]} is not 1.0, 2.0 or 3.0")
    except Exception as exc:  # noqa: BLE001 (any failure to parse it: tokenize, literal_eval)
        raise ValueError(f"{name}: unreadable .npy header: {exc}") from None
    count = 1
    for n in shape:
        count *= int(n)
    if count > MAX_DECODE_PIXELS:
        raise ValueError(
            f"{name}: .npy header claims shape {tuple(shape)} = {count} values, more than the "
            f"limit of {MAX_DECODE_PIXELS}"
        )
    have = len(data) - fh.tell()
    if not dtype.hasobject and count * dtype.itemsize > have:
        raise ValueError(
            f"{name}: truncated .npy file: shape {tuple(shape)} of {dtype} needs "
            f"{count * dtype.itemsize} bytes, the file holds {have}"
        )
    return tuple(int(n) for n in shape)


#: the longest ``.npy`` header read (numpy's own readers refuse longer ones the same way)
NPY_HEADER_LIMIT = 10_000


def _npy_header_3_0(fh: io.BytesIO) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` from a version 3.0 ``.npy`` header (after its magic): version 2.0's
    layout, a 4-byte length then the header's dict, in UTF-8. numpy reads it with no public
    function."""
    import ast
    import struct

    (length,) = struct.unpack("<I", fh.read(4))
    if length > NPY_HEADER_LIMIT:  # literal_eval of a huge header takes seconds and GBs
        raise ValueError(f"the header is {length} bytes, over the {NPY_HEADER_LIMIT} allowed")
    header = fh.read(length)
    if len(header) != length:
        raise ValueError("the header is cut short")
    d = ast.literal_eval(header.decode("utf-8"))
    if not isinstance(d, dict) or not {"descr", "fortran_order", "shape"} <= set(d):
        raise ValueError(f"the header is not a dict of descr, fortran_order and shape: {d!r}")
    shape = d["shape"]
    if not isinstance(shape, tuple) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise ValueError(f"shape is not a tuple of sizes: {shape!r}")
    return shape, np.lib.format.descr_to_dtype(d["descr"])


def _map_shape(shape: tuple[int, ...]) -> tuple[int, ...]:
    """The shape an array of ``shape`` has as a depth map: length-1 axes dropped after and
    before a map's two (``H x W x 1``, ``1 x H x W``), never the map's own (a ``1 x W`` map
    belongs to a photo one pixel tall)."""
    shape = tuple(shape)
    while len(shape) > 2 and shape[-1] == 1:  # a channel axis first: 1 x W x 1 is 1 x W
        shape = shape[:-1]
    while len(shape) > 2 and shape[0] == 1:
        shape = shape[1:]
    return shape


def _map_sides(shape: tuple[int, ...]) -> tuple[int, int] | None:
    """The (H, W) that an array of ``shape`` becomes as a depth map (the rules of
    :func:`read_depth_array`: :func:`_map_shape`, 3 or 4 equal channels averaged), or None
    when it is no map (refused after reading)."""
    kept = _map_shape(shape)
    if len(kept) == 3 and kept[2] in (3, 4):
        kept = kept[:2]
    return kept if len(kept) == 2 else None


#: A map is resized to its photo: one of more than this many times the photo's pixels (and
#: over :data:`MAP_PIXELS_FLOOR`) adds nothing and costs its decoding (a 144 MP float TIFF
#: took 5.9 GB to read), so it is refused from its header.
MAX_MAP_OVER_PHOTO = 4
#: any map up to this many pixels is read whatever the photo's size (4096 x 4096)
MAP_PIXELS_FLOOR = 4096 * 4096


def _check_map_header(
    sides: tuple[int, int] | None, size: tuple[int, int] | None, name: str
) -> None:
    """The map's (H, W) from a header against the photo's (H, W) ``size``, before any sample
    is decoded: the aspect ratio (:func:`check_aspect`) and the pixel count (at most
    :data:`MAX_MAP_OVER_PHOTO` times the photo's, or :data:`MAP_PIXELS_FLOOR`)."""
    if sides is None or size is None:
        return
    check_aspect(sides, size, name)
    pixels, photo = sides[0] * sides[1], size[0] * size[1]
    if pixels > max(MAX_MAP_OVER_PHOTO * photo, MAP_PIXELS_FLOOR):
        raise ValueError(
            f"{name}: depth map is {sides[1]}x{sides[0]} = {pixels} pixels for a "
            f"{size[1]}x{size[0]} photo; a map of more than {MAX_MAP_OVER_PHOTO} times the "
            f"photo's pixels (or {MAP_PIXELS_FLOOR}) is refused: resize it to the photo"
        )


TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # classic TIFF and BigTIFF
#: Largest decoded TIFF page in bytes: a page of :data:`MAX_DECODE_PIXELS` float32 values.
MAX_TIFF_PAGE_BYTES = 4 * MAX_DECODE_PIXELS
#: Largest tile of a smaller page: 1024 x 1024 float32 values.
MAX_TIFF_TILE_BYTES = 4 << 20


def _tiff_orientation(page: Any) -> int:
    """The orientation (1-8) a tifffile page's tag 274 gives; 1 when it has none."""
    try:
        value = int(page.tags[274].value)
    except Exception:  # noqa: BLE001 (no tag, or one that is not a number)
        return 1
    return value if 1 <= value <= 8 else 1


def _tiff_header(data: bytes, name: str):
    """``(first page, (H, W, samples, bytes decoded))`` of a TIFF from its header (tifffile
    parses the IFD; nothing is decoded), or None when tifffile is missing or cannot parse
    it. Raises ``ValueError`` for a page above the pixel or byte limit or a volume."""
    try:
        import tifffile
    except ImportError:
        return None
    try:
        page = tifffile.TiffFile(io.BytesIO(data)).pages[0]
        h, w = int(page.imagelength), int(page.imagewidth)
        depth, samples = int(page.imagedepth), int(page.samplesperpixel)
        bits = int(page.bitspersample)
        tile = (int(page.tilelength), int(page.tilewidth), int(page.tiledepth or 1))
        tile = tile if page.is_tiled else None
    except Exception:  # noqa: BLE001 (any failure to parse: Pillow may still read it)
        return None
    pixels = h * w * max(depth, 1)
    if pixels > MAX_DECODE_PIXELS:
        raise ValueError(
            f"{name}: TIFF page is {w}x{h}"
            + (f"x{depth}" if depth > 1 else "")
            + f" = {pixels} pixels, more than the limit of {MAX_DECODE_PIXELS} (refused "
            "from its header, before decoding)"
        )
    nbytes = pixels * samples * -(-bits // 8)
    if nbytes > MAX_TIFF_PAGE_BYTES:
        raise ValueError(
            f"{name}: TIFF page of {w}x{h} pixels with {samples} samples of {bits} bits is "
            f"{nbytes} bytes decoded, more than the limit of {MAX_TIFF_PAGE_BYTES}"
        )
    if depth > 1:
        raise ValueError(
            f"{name}: TIFF page is a volume of {depth} slices of {w}x{h}; expected a 2-D map"
        )
    if tile is not None:
        # a decoder holds a whole tile: one far larger than the page costs its memory
        tile_bytes = tile[0] * tile[1] * tile[2] * samples * -(-bits // 8)
        if tile_bytes > max(nbytes, MAX_TIFF_TILE_BYTES):
            raise ValueError(
                f"{name}: TIFF tiles of {tile[1]}x{tile[0]} pixels ({tile_bytes} bytes) are "
                f"larger than the {w}x{h} page they tile"
            )
    return page, (h, w, samples, nbytes)


def _read_tiff(data: bytes, name: str, size: tuple[int, int] | None) -> np.ndarray:
    """A TIFF depth map: its first page's size checked from the header (pixel and byte
    limits, the photo's aspect), then decoded by Pillow or, for what Pillow cannot decode
    (float pages with several samples, some tiled pages), by tifffile."""
    header = _tiff_header(data, name)
    turn = 1  # the TIFF's orientation, upright as its photo is loaded
    if header is not None:
        turn = _tiff_orientation(header[0])
        sides = _map_sides(header[1][:3])  # (H, W, samples) as stored
        if sides is not None and turn >= 5:
            sides = sides[::-1]
        _check_map_header(sides, size, name)
    try:
        im = open_pil(data, name)  # refuses a header above the pixel limit, unread
    except ValueError:
        if header is None:
            raise
        im = None
    if im is not None:
        with im:
            pending = exif_orientation(im)  # 1 where Pillow turns a TIFF itself
            w, h = im.size if pending < 5 else im.size[::-1]
            _check_map_header((h, w), size, name)
            try:
                im.load()
                return apply_orientation(_grey_from_pil(im, name), pending)
            except (OSError, SyntaxError, EOFError, ValueError) as exc:
                if header is None:
                    raise ValueError(f"{name}: truncated or corrupt depth image: {exc}") from exc
    if header is None:  # tifffile is missing (it comes with scikit-image)
        raise ValueError(f"{name}: cannot decode this TIFF (tifffile is not installed)")
    try:
        return apply_orientation(header[0].asarray(maxworkers=1), turn)
    except MemoryError as exc:
        raise ValueError(
            f"{name}: not enough memory to decode the {header[1][3]}-byte TIFF page"
        ) from exc
    except Exception as exc:  # noqa: BLE001 (tifffile's and its codecs' own errors)
        raise ValueError(f"{name}: cannot decode TIFF depth map: {exc}") from exc


def read_depth_array(
    src: str | os.PathLike | bytes, *, size: tuple[int, int] | None = None
) -> np.ndarray:
    """Read the raw values of a depth/disparity file as HxW float64 (no normalisation).

    Formats: ``.npy``, ``.pfm``, TIFF (float, 16/32-bit int), PNG 8/16-bit and any grey
    image Pillow reads. Bytes sources are sniffed by content.

    Every format's size is checked from its header before a sample is decoded: at most
    :data:`~d2f_core.io.image.MAX_DECODE_PIXELS` pixels and, with ``size`` (the (H, W) of
    the photo the map belongs to), the photo's aspect ratio (:func:`check_aspect`).

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: not a regular file (the message says what it is), unreadable, corrupt,
            above the limits, of another aspect ratio than ``size``, not a 2-D map.
    """
    name = source_name(src)
    size = _photo_size(size)
    data = read_source_bytes(src)
    try:
        return _depth_values(data, name, size)
    except MemoryError:  # within the pixel limit, but more than this process may have
        raise ValueError(f"{name}: not enough memory to read this depth map") from None


def _photo_size(size: Any) -> tuple[int, int] | None:
    """``size`` as the photo's ``(H, W)``: two whole numbers of at least 1, or ``None``."""
    if size is None:
        return None
    try:
        if len(size) == 3 and size[2] in (3, 4):  # an image's shape, (H, W, channels)
            size = tuple(size)[:2]
        h, w = size
        sides = (whole_number(h, "size's H", 1), whole_number(w, "size's W", 1))
    except (TypeError, ValueError):
        raise ValueError(
            f"size: expected the photo's (H, W), two whole numbers >= 1, got {size!r}"
        ) from None
    return sides


def _depth_values(data: bytes, name: str, size: tuple[int, int] | None) -> np.ndarray:
    """:func:`read_depth_array` of a file's bytes."""
    if data.startswith(b"\x93NUMPY"):
        _check_map_header(_map_sides(_check_npy_header(data, name)), size, name)
        try:
            arr = np.load(io.BytesIO(data), allow_pickle=False)
        except ValueError as exc:
            raise ValueError(f"{name}: unreadable .npy file: {exc}") from exc
    elif data[:2] in (b"PF", b"Pf") and data[2:3].isspace():
        arr = _read_pfm(data, name, size)
    elif data[:4] in TIFF_MAGICS:
        arr = _read_tiff(data, name, size)
    else:
        try:
            im = open_pil(data, name)  # refuses a header above the pixel limit, unread
            with im:
                # upright, as a viewer shows it and as the photo is loaded
                orientation = exif_orientation(im, data)
                w, h = im.size if orientation < 5 else im.size[::-1]
                _check_map_header((h, w), size, name)
                im.load()
                arr = apply_orientation(_grey_from_pil(im, name), orientation)
        except (OSError, SyntaxError, EOFError) as exc:
            raise ValueError(f"{name}: truncated or corrupt depth image: {exc}") from exc
    arr = np.asarray(arr)
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name}: depth map has non-numeric dtype {arr.dtype}")
    if np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name}: depth map has complex dtype {arr.dtype}; expected real values")
    arr = arr.reshape(_map_shape(arr.shape))
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        # the rule of a colour PNG: channels that agree are one map, a colour map is refused
        arr = _grey_channels(arr[..., :3].astype(np.float64), name)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D depth map, got shape {arr.shape}")
    return arr.astype(np.float64)


# --------------------------------------------------------------------------- shapes


def _rounded_alike(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether ``(H, W)`` ``a`` and ``b`` are one picture at two sizes, the smaller's sides
    the larger's at one scale, each rounded to a whole pixel: a 4000x16 photo shown 1600 px
    wide is 6 px tall (6.4), 7 % off its aspect."""
    (sh, sw), (lh, lw) = sorted((a, b), key=lambda s: s[0] * s[1])

    def scales(small: int, large: int) -> tuple[float, float]:
        """The scales at which ``large`` px round to ``small`` (1 px: anything smaller)."""
        return (0.0 if small <= 1 else (small - 0.5) / large), (small + 0.5) / large

    (h0, h1), (w0, w1) = scales(sh, lh), scales(sw, lw)
    return max(h0, w0) <= min(h1, w1)  # one scale gives both sides


def check_aspect(
    map_shape: tuple[int, ...], image_shape: tuple[int, ...], name: str, what: str = "depth map"
) -> None:
    """Raise ``ValueError`` when a depth map of ``(H, W)`` ``map_shape`` would be stretched onto
    an image of ``(H, W)`` ``image_shape``: their aspect ratios differ by more than 5 %, and
    by more than a side of the smaller rounded to a whole pixel (a map of another resolution
    and the same shape is only resized). The message says when the map
    looks turned a quarter relative to the image. A map or an image of one pixel passes.
    ``what`` names the map in the message (a painted mask is checked the same way).
    """
    mh, mw, h, w = int(map_shape[0]), int(map_shape[1]), int(image_shape[0]), int(image_shape[1])
    if min(mh, mw) < 1 or min(h, w) < 1:
        raise ValueError(f"{name}: {what} is {mw}x{mh} and the image {w}x{h}: a side is empty")
    if max(mh, mw) <= 1 or max(h, w) <= 1:
        return
    ar_map, ar_img = mw / mh, w / h
    if abs(math.log(ar_map / ar_img)) > 0.05 and not _rounded_alike((mh, mw), (h, w)):
        hint = ""
        if abs(math.log(ar_map * ar_img)) <= 0.05:
            hint = " (it looks rotated by 90 degrees relative to the image)"
        raise ValueError(
            f"{name}: {what} is {mw}x{mh} but the image is {w}x{h}: aspect ratios differ{hint}"
        )
