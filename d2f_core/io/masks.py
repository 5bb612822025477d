"""Painted masks in: the focus and blur brushes' files (``d2f --sharp-mask``, ``--blur-mask``).

A mask is a grey image of the photo's aspect ratio and any size, white = painted, grey partial
paint; a transparent pixel of a mask with alpha is unpainted, so a stroke layer exported from
an editor works as it is. It is upright by its own EXIF orientation, as the photo is.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from PIL import Image

from .depth import check_aspect
from .formats import apply_orientation, exif_orientation
from .image import ImageSource, open_pil, read_source_bytes, source_name

__all__ = ["load_mask"]

#: What Pillow raises on a truncated or corrupt file while decoding it.
DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, IndexError)


def _mask_values(im: Image.Image, name: str) -> np.ndarray:
    """The decoded mask as ``H x W`` float32 in [0, 1]."""
    if im.mode.startswith("I;16"):
        return np.asarray(im, dtype=np.float32) / 65535.0
    if im.mode in ("I", "F"):
        a = np.asarray(im, dtype=np.float64)
        if not np.isfinite(a).all():
            raise ValueError(f"{name}: the mask holds NaN or infinite values")
        top = 1.0 if im.mode == "F" else (255.0 if a.max() <= 255 else 65535.0)
        if a.min() < 0 or a.max() > top:
            raise ValueError(f"{name}: mask values must be in [0, {top:g}]")
        return (a / top).astype(np.float32)
    has_alpha = "A" in im.getbands() or "transparency" in im.info
    if has_alpha:
        la = np.asarray(im.convert("RGBA").convert("LA"), dtype=np.float32) / 255.0
        return la[..., 0] * la[..., 1]
    return np.asarray(im.convert("L"), dtype=np.float32) / 255.0


def load_mask(src: ImageSource, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a painted mask (PNG, TIFF, JPEG, any grey or colour image Pillow reads).

    Args:
        src: a path or the file's bytes.
        size: the ``(H, W)`` of the photo it is painted on: its aspect ratio is checked from
            the header, before any pixel is decoded.

    Returns:
        ``H' x W'`` float32 in [0, 1] (1 = painted), at the file's own size, upright.

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
        try:
            im.load()
            values = _mask_values(im, name)
        except DECODE_ERRORS as exc:
            raise ValueError(f"{name}: truncated or corrupt mask image: {exc}") from exc
    return np.ascontiguousarray(apply_orientation(values, orientation))
