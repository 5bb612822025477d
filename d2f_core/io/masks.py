"""Painted masks in: the focus and blur brushes' files (``d2f --sharp-mask``, ``--blur-mask``).

A mask is a grey image of the photo's aspect ratio and up to twice its sides, white = painted,
grey partial paint (a mask of 0 and 1 only is 0/1); a transparent pixel of a mask with alpha is
unpainted, so a stroke layer exported from an editor works as it is. It is upright by its own
EXIF orientation, as the photo is.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from PIL import Image

from .depth import check_aspect
from .formats import apply_orientation, exif_orientation
from .image import ImageSource, open_pil, read_source_bytes, source_name

__all__ = ["MASK_AREA_FACTOR", "MASK_FLOOR_PIXELS", "check_mask_size", "load_mask"]

#: What Pillow raises on a truncated or corrupt file while decoding it.
DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, IndexError)


#: A mask may hold at most this many times its photo's pixels (twice its width and its
#: height), or :data:`MASK_FLOOR_PIXELS` whatever the photo: checked from the header, before
#: a pixel is decoded, so a mask's memory is bounded by its photo's.
MASK_AREA_FACTOR = 4
#: The pixels any mask may have, however small its photo (4 MP: 20 MB decoded).
MASK_FLOOR_PIXELS = 1 << 22


def integer_top(a: np.ndarray, full: float) -> float:
    """The value that means "painted" in an integer mask: 1 when no value is above 1 (a 0/1
    mask, ``(a > t).astype(np.uint8)``), else ``full``."""
    return 1.0 if a.size and a.max() <= 1 else full


def _mask_values(im: Image.Image, name: str) -> np.ndarray:
    """The decoded mask as ``H x W`` float32 in [0, 1]."""
    if im.mode.startswith("I;16"):
        a = np.asarray(im).astype(np.float32)
        return a / integer_top(a, 65535.0)
    if im.mode in ("I", "F"):
        a = np.asarray(im, dtype=np.float64)
        if not np.isfinite(a).all():
            raise ValueError(f"{name}: the mask holds NaN or infinite values")
        if im.mode == "F":
            top = 1.0
        else:
            top = integer_top(a, 255.0 if a.max() <= 255 else 65535.0)
        if a.min() < 0 or a.max() > top:
            raise ValueError(f"{name}: mask values must be in [0, {top:g}]")
        return (a / top).astype(np.float32)
    has_alpha = "A" in im.getbands() or "transparency" in im.info
    if has_alpha:
        la = np.asarray(im.convert("RGBA").convert("LA"))
        grey = la[..., 0].astype(np.float32) / integer_top(la[..., 0], 255.0)
        return grey * (la[..., 1].astype(np.float32) / 255.0)
    grey = np.asarray(im.convert("L"))
    return grey.astype(np.float32) / integer_top(grey, 255.0)


def check_mask_size(mask: tuple[int, int], photo: tuple[int, int], name: str) -> None:
    """Refuse a mask of ``(H, W)`` ``mask`` that is far larger than its photo of ``(H, W)``
    ``photo``: more than :data:`MASK_AREA_FACTOR` times its pixels and more than
    :data:`MASK_FLOOR_PIXELS`."""
    (mh, mw), (h, w) = (int(mask[0]), int(mask[1])), (int(photo[0]), int(photo[1]))
    limit = max(MASK_AREA_FACTOR * h * w, MASK_FLOOR_PIXELS)
    if mh * mw > limit:
        raise ValueError(
            f"{name}: the mask is {mw}x{mh}, far larger than its {w}x{h} photo: a mask may "
            f"have at most {limit / 1e6:.1f} MP (the photo's own size is best)"
        )


def load_mask(src: ImageSource, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a painted mask (PNG, TIFF, JPEG, any grey or colour image Pillow reads).

    Args:
        src: a path or the file's bytes.
        size: the ``(H, W)`` of the photo it is painted on: its aspect ratio and its size
            (at most :data:`MASK_AREA_FACTOR` times the photo's pixels, or
            :data:`MASK_FLOOR_PIXELS`) are checked from the header, before any pixel is
            decoded.

    Returns:
        ``H' x W'`` float32 in [0, 1] (1 = painted), at the file's own size, upright. An
        integer mask whose largest value is 1 is a 0/1 mask (1 = painted), not 1/255.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: not a regular file, not an image, truncated, above the pixel limit, values
            out of range, or of another aspect ratio than ``size``.
    """
    name = source_name(src)
    data = read_source_bytes(src)
    im = open_pil(data, name)
    with im:
        orientation = exif_orientation(im, data)
        w, h = im.size
        upright = (w, h) if orientation in (1, 2, 3, 4) else (h, w)
        if size is not None:
            check_aspect((upright[1], upright[0]), size, name, "mask")
            check_mask_size((upright[1], upright[0]), size, name)
        try:
            im.load()
        except DECODE_ERRORS as exc:
            raise ValueError(f"{name}: truncated or corrupt mask image: {exc}") from exc
        values = _mask_values(im, name)
    return np.ascontiguousarray(apply_orientation(values, orientation))
