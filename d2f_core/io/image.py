"""Image reading and writing: every photo enters and leaves the project through here.

``load_image`` turns any supported file (JPEG, PNG 8/16-bit, TIFF, WebP, HEIC/HEIF with
pillow-heif) into an upright ``HxWx3`` float32 array in [0, 1]. ``save_image`` writes such an
array back, keeping the source's ICC profile and EXIF (minus the orientation tag, because the
pixels are already upright).

Every decoding problem surfaces as a ``ValueError`` that names the file and the problem;
Pillow's own exceptions never escape.
"""

from __future__ import annotations

import io
import logging
import os
import stat
import struct
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Union

import numpy as np
from PIL import Image, ImageCms, UnidentifiedImageError

from ..errors import InputTypeError
from .formats import (
    apply_orientation,
    decode_png16,
    exif_orientation,
    png16_header,
    strip_orientation,
)

logger = logging.getLogger("d2f_core.io.image")


ImageSource = Union[str, os.PathLike, bytes, bytearray, memoryview]  # noqa: UP007 (runtime alias)


# Same threshold as Pillow's DecompressionBombError (2 x MAX_IMAGE_PIXELS, about 179 MP).
MAX_DECODE_PIXELS = 2 * 89_478_485
#: Largest file read (photo or depth map): 1 GiB, about a 179 MP 16-bit RGBA TIFF.
MAX_FILE_BYTES = 1 << 30


SAVE_FORMATS = {
    ".png": "PNG",
    ".jpg": "JPEG",
    ".jpeg": "JPEG",
    ".tif": "TIFF",
    ".tiff": "TIFF",
    ".webp": "WEBP",
}


# Extensions a batch run treats as photos (HEIC needs pillow-heif at read time).
READ_EXTENSIONS = frozenset(
    {".jpg", ".jpeg", ".jpe", ".png", ".tif", ".tiff", ".webp", ".heic", ".heif", ".bmp", ".mpo"}
)


# HEIF brands only: Pillow reads AVIF itself, so it must not require pillow-heif.
_HEIF_BRANDS = {b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"mif1", b"msf1"}


_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, IndexError)


_heif_registered = False


@dataclass
class ImageInfo:
    """What ``load_image_with_info`` learned about a file and did to its pixels.

    Attributes:
        name: the path as given, or ``"<bytes>"``.
        format: Pillow's format name (``"JPEG"``, ``"PNG"``, ``"HEIF"`` ...).
        mode: the decoded mode before conversion (``"RGB"``, ``"I;16"``, ``"CMYK"`` ...).
        bit_depth: bits per channel of the stored samples (8, 16 or 32).
        original_size: (H, W) of the upright image before any resize.
        size: (H, W) of the returned array.
        orientation: EXIF orientation that was applied (1 = none).
        icc_profile: ICC profile bytes that describe the returned pixels, or None.
        exif: EXIF bytes with the orientation tag removed, or None.
        xmp: raw XMP packet of the main image, or None.
        conversions: human-readable list of every conversion applied, in order.
    """

    name: str
    format: str | None = None
    mode: str | None = None
    bit_depth: int = 8
    original_size: tuple[int, int] = (0, 0)
    size: tuple[int, int] = (0, 0)
    orientation: int = 1
    icc_profile: bytes | None = None
    exif: bytes | None = None
    xmp: bytes | None = None
    conversions: list[str] = field(default_factory=list)

    @property
    def resized(self) -> bool:
        return self.size != self.original_size


def source_name(src: ImageSource) -> str:
    """Printable name of an image source for messages."""
    if isinstance(src, (bytes, bytearray, memoryview)):
        return "<bytes>"
    if not isinstance(src, (str, os.PathLike)):
        what = type(src).__name__
        hint = (
            " (an array is already loaded: give it where an array goes)"
            if hasattr(src, "shape")
            else ""
        )
        raise InputTypeError(f"expected a file path or the file's bytes, got {what}{hint}")
    return os.fspath(src)


def read_source_bytes(src: ImageSource, max_bytes: int = MAX_FILE_BYTES) -> bytes:
    """Whole content of a path or bytes source.

    Only regular files are read: a pipe, a device (``/dev/zero``) or a socket is refused
    without reading from it (it is opened non-blocking, so a FIFO without a writer does not
    hang), and so is a file larger than ``max_bytes``.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: a directory, a FIFO, a device or a socket (the message says which),
            larger than ``max_bytes``, empty or unreadable.
    """
    name = source_name(src)
    if isinstance(src, (bytes, bytearray, memoryview)):
        data = bytes(src)
        if len(data) > max_bytes:
            raise ValueError(f"{name}: {len(data)} bytes, more than the limit of {max_bytes}")
    else:  # a path: source_name refused anything else
        data = _read_regular_file(Path(src), name, max_bytes)
    if len(data) == 0:
        raise ValueError(f"{name}: file is empty (0 bytes)")
    return data


def _kind_of_file(mode: int) -> str:
    """What a file that is not a regular file is, for messages."""
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a special file"


def _check_regular(st: os.stat_result, name: str, max_bytes: int) -> None:
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{name}: is a directory, not an image file")
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{name}: is {_kind_of_file(st.st_mode)}, not a regular file")
    if st.st_size > max_bytes:
        raise ValueError(f"{name}: {st.st_size} bytes, more than the limit of {max_bytes}")


def _read_regular_file(path: Path, name: str, max_bytes: int) -> bytes:
    """Read a regular file, looked at (``stat``) before it is opened; opened non-blocking and
    looked at again (``fstat``), so that a file swapped in between is refused too."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        _check_regular(os.stat(path), name, max_bytes)
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise FileNotFoundError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{name}: is a directory, not an image file") from None
    except OSError as exc:
        raise ValueError(f"{name}: cannot read file: {exc.strerror or exc}") from None
    with os.fdopen(fd, "rb") as fh:
        _check_regular(os.fstat(fd), name, max_bytes)
        try:
            parts = [fh.read(os.fstat(fd).st_size)]
            total = len(parts[0])
            while more := fh.read(1 << 16):  # a file that grew meanwhile, up to the cap
                total += len(more)
                if total > max_bytes:
                    raise ValueError(f"{name}: more than the limit of {max_bytes} bytes")
                parts.append(more)
        except OSError as exc:
            raise ValueError(f"{name}: cannot read file: {exc.strerror or exc}") from exc
    return parts[0] if len(parts) == 1 else b"".join(parts)


def is_heif(data: bytes) -> bool:
    """True when ``data`` starts like an ISO-BMFF HEIF/HEIC/AVIF file."""
    return len(data) >= 12 and data[4:8] == b"ftyp" and data[8:12] in _HEIF_BRANDS


def ensure_heif_support(name: str = "<bytes>") -> None:
    """Register pillow-heif's opener once; ``ValueError`` with install hint if it is missing."""
    global _heif_registered
    if _heif_registered:
        return
    try:
        import pillow_heif
    except ImportError as exc:
        raise ValueError(
            f"{name}: HEIC/HEIF images need the optional package pillow-heif "
            "(pip install pillow-heif, or pip install 'd2f[heif]')"
        ) from exc
    pillow_heif.register_heif_opener()
    _heif_registered = True


def open_pil(data: bytes, name: str) -> Image.Image:
    """Open (not decode) an image from bytes, translating every failure into ``ValueError``."""
    if is_heif(data):
        ensure_heif_support(name)
    try:
        with warnings.catch_warnings():
            # Pillow warns above 89 MP; the hard limit below is what protects us.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data))
    except Image.DecompressionBombError as exc:
        raise ValueError(f"{name}: refused as a possible decompression bomb: {exc}") from exc
    except UnidentifiedImageError as exc:
        raise ValueError(f"{name}: not an image file (unknown or unsupported format)") from exc
    except _DECODE_ERRORS as exc:
        raise ValueError(f"{name}: corrupt image header: {exc}") from exc
    w, h = im.size
    if w <= 0 or h <= 0:
        raise ValueError(f"{name}: image has no pixels ({w}x{h})")
    if w * h > MAX_DECODE_PIXELS:
        raise ValueError(
            f"{name}: refused as a possible decompression bomb: {w}x{h} = {w * h} pixels "
            f"exceeds the limit of {MAX_DECODE_PIXELS}"
        )
    return im


# --------------------------------------------------------------------------- conversions


def _composite_over_white(rgb: np.ndarray, alpha: np.ndarray, conv: list[str]) -> np.ndarray:
    if alpha.min() >= 1.0:
        conv.append("dropped an all-opaque alpha channel")
        return rgb
    conv.append("composited transparent pixels over white")
    logger.info("image has transparency: composited over white")
    a = alpha[..., None]
    return rgb * a + (1.0 - a)


def _rgb_profile(icc: bytes | None, conv: list[str]) -> bytes | None:
    """``icc`` when it describes RGB pixels, as the loaded picture's are; else ``None``. A grey
    photo's GRAY profile, written with its RGB copy, makes a file that colour-managed
    software cannot convert; its tone curve is close to sRGB's, which a file with no profile
    is taken for."""
    if not icc or icc[16:20] == b"RGB ":
        return icc
    space = icc[16:20].decode("latin-1").strip() or "unknown"
    conv.append(f"the {space} ICC profile dropped (it does not describe RGB pixels)")
    return None


def _to_float_rgb(im: Image.Image, conv: list[str]) -> tuple[np.ndarray, bytes | None]:
    """Convert any Pillow mode to HxWx3 float32 in [0, 1]. Also returns the ICC profile that
    describes the result (changed when CMYK is converted to sRGB)."""
    icc = im.info.get("icc_profile") or None
    mode = im.mode
    if mode == "P":
        target = "RGBA" if "transparency" in im.info else "RGB"
        im = im.convert(target)
        conv.append(f"palette -> {target}")
    elif mode == "PA":
        im = im.convert("RGBA")
        conv.append("palette+alpha -> RGBA")
    elif mode == "1":
        im = im.convert("L")
        conv.append("1-bit -> grayscale")
    elif mode in ("RGBa", "La"):
        im = im.convert("RGBA" if mode == "RGBa" else "LA")
        conv.append("premultiplied alpha -> straight alpha")
    elif mode == "CMYK":
        converted = None
        if icc:
            try:
                src = ImageCms.ImageCmsProfile(io.BytesIO(icc))
                dst = ImageCms.createProfile("sRGB")
                converted = ImageCms.profileToProfile(im, src, dst, outputMode="RGB")
                icc = ImageCms.ImageCmsProfile(dst).tobytes()
                conv.append("CMYK -> sRGB via the embedded ICC profile")
            except Exception as exc:  # broken profile: naive conversion is still usable
                logger.warning("CMYK ICC conversion failed (%s); using a naive conversion", exc)
        if converted is None:
            converted = im.convert("RGB")
            icc = None
            conv.append("CMYK -> RGB (naive, no ICC profile)")
        im = converted
    elif mode in ("YCbCr", "LAB", "HSV", "RGBX"):
        im = im.convert("RGB")
        conv.append(f"{mode} -> RGB")

    mode = im.mode
    if mode == "RGB":
        rgb = np.asarray(im, dtype=np.float32)
        rgb *= 1.0 / 255.0
        return rgb, icc
    if mode == "RGBA":
        a = np.asarray(im, dtype=np.float32) / 255.0
        return _composite_over_white(a[..., :3], a[..., 3], conv), icc
    if mode == "L":
        g = np.asarray(im, dtype=np.float32) / 255.0
        conv.append("grayscale -> RGB")
        return np.repeat(g[..., None], 3, axis=2), icc
    if mode == "LA":
        a = np.asarray(im, dtype=np.float32) / 255.0
        conv.append("grayscale -> RGB")
        rgb = np.repeat(a[..., :1], 3, axis=2)
        return _composite_over_white(rgb, a[..., 1], conv), icc
    if mode.startswith("I;16"):
        g = np.asarray(im).astype(np.float32) / 65535.0
        conv.append("16-bit grayscale -> RGB")
        return np.repeat(g[..., None], 3, axis=2), icc
    if mode == "I":
        g = np.asarray(im).astype(np.float64)
        hi = float(g.max()) if g.size else 0.0
        scale = 65535.0 if hi <= 65535.0 else hi
        conv.append(f"32-bit integer grayscale scaled by 1/{scale:g} -> RGB")
        g = np.clip(g / scale, 0.0, 1.0).astype(np.float32)
        return np.repeat(g[..., None], 3, axis=2), icc
    if mode == "F":
        g = np.asarray(im).astype(np.float32)
        finite = np.isfinite(g)
        if g.size and not finite.any():
            raise ValueError("float image holds no finite value (every pixel is NaN or infinite)")
        if not finite.all():
            n_bad = int(g.size - finite.sum())
            conv.append(f"{n_bad} NaN or infinite pixels set to 0")
            # said where the user sees it (the CLI prints warnings), not only in the info
            logger.warning(
                "float image: %d of %d pixels are NaN or infinite and are shown black",
                n_bad,
                g.size,
            )
            g = np.where(finite, g, 0.0)
        hi = float(g.max()) if g.size else 0.0
        if g.size and not hi > 0.0:
            raise ValueError(
                "float image holds no value above 0 (every pixel is 0, negative, NaN or "
                "infinite): it would be all black"
            )
        if hi > 1.0:
            g = g / hi
            conv.append(f"float grayscale scaled by 1/{hi:g}")
        conv.append("float grayscale -> RGB")
        g = np.clip(g, 0.0, 1.0).astype(np.float32)
        return np.repeat(g[..., None], 3, axis=2), icc
    try:
        rgb = im.convert("RGB")
    except _DECODE_ERRORS as exc:
        raise ValueError(f"unsupported image mode {mode!r}") from exc
    conv.append(f"{mode} -> RGB (generic conversion)")
    return np.asarray(rgb, dtype=np.float32) / 255.0, icc


def _png16_to_float_rgb(arr: np.ndarray, conv: list[str]) -> np.ndarray:
    a = arr.astype(np.float32)
    a *= 1.0 / 65535.0
    if a.shape[2] == 2:
        conv.append("16-bit grayscale -> RGB")
        return _composite_over_white(np.repeat(a[..., :1], 3, axis=2), a[..., 1], conv)
    if a.shape[2] == 4:
        return _composite_over_white(a[..., :3], a[..., 3], conv)
    return a


# --------------------------------------------------------------------------- resizing


def fit_size(width: int, height: int, max_pixels: int) -> tuple[int, int]:
    """Largest (w, h) with the same aspect ratio and w * h <= max_pixels."""
    if width * height <= max_pixels:
        return width, height
    scale = (max_pixels / float(width * height)) ** 0.5
    w = max(1, int(width * scale))
    h = max(1, int(height * scale))
    while w * h > max_pixels and (w > 1 or h > 1):
        if w >= h:
            w -= 1
        else:
            h -= 1
    return w, h


def resize_float(array: np.ndarray, size: tuple[int, int], resample: str = "lanczos") -> np.ndarray:
    """Resize a float HxW or HxWxC array to ``size`` = (H, W), antialiased when shrinking."""
    filt = {
        "lanczos": Image.Resampling.LANCZOS,
        "bilinear": Image.Resampling.BILINEAR,
        "nearest": Image.Resampling.NEAREST,
    }[resample]
    h, w = size
    if array.shape[:2] == (h, w):
        return array.astype(np.float32, copy=False)
    if array.ndim == 2:
        img = Image.fromarray(np.ascontiguousarray(array, dtype=np.float32))
        return np.asarray(img.resize((w, h), filt), dtype=np.float32)
    chans = [resize_float(array[..., c], size, resample) for c in range(array.shape[2])]
    return np.stack(chans, axis=-1)


# --------------------------------------------------------------------------- loading


def _check_limits(max_pixels: int | None, on_too_large: str, min_side: int | None = None) -> None:
    if min_side is not None:
        if isinstance(min_side, bool) or not isinstance(min_side, (int, np.integer)):
            raise InputTypeError(
                f"min_side: expected an int or None, got {type(min_side).__name__}"
            )
        if min_side < 1:
            raise ValueError(f"min_side: must be >= 1, got {min_side}")
    if max_pixels is not None:
        if isinstance(max_pixels, bool) or not isinstance(max_pixels, (int, np.integer)):
            kind = type(max_pixels).__name__
            raise InputTypeError(f"max_pixels: expected an int or None, got {kind}")
        if max_pixels < 1:
            raise ValueError(f"max_pixels: must be >= 1, got {max_pixels}")
    if on_too_large not in ("resize", "error"):
        raise ValueError(f"on_too_large: expected 'resize' or 'error', got {on_too_large!r}")


def decode_image(
    data: bytes,
    name: str,
    *,
    max_pixels: int | None = None,
    on_too_large: Literal["resize", "error"] = "resize",
    min_side: int | None = None,
) -> tuple[np.ndarray, ImageInfo]:
    """Decode image bytes (see ``load_image_with_info``); ``name`` is used in messages."""
    _check_limits(max_pixels, on_too_large, min_side)
    try:
        return _decode_image(data, name, max_pixels, on_too_large, min_side)
    except MemoryError:  # within the pixel limit, but more than this process may have
        raise ValueError(
            f"{name}: not enough memory to decode this image; pass max_pixels"
        ) from None


def _decode_image(
    data: bytes, name: str, max_pixels: int | None, on_too_large: str, min_side: int | None
) -> tuple[np.ndarray, ImageInfo]:
    info = ImageInfo(name=name)
    conv = info.conversions
    im = open_pil(data, name)
    info.format = im.format
    info.mode = im.mode
    info.xmp = im.info.get("xmp") or None
    w, h = im.size
    orientation = exif_orientation(im, data)
    info.orientation = orientation
    upright = (w, h) if orientation < 5 else (h, w)
    info.original_size = (upright[1], upright[0])
    if min_side is not None and min(w, h) < min_side:
        # from the header, before any pixel is decoded
        raise ValueError(
            f"{name}: image is only {upright[0]}x{upright[1]} pixels; at least {min_side} "
            "pixels per side are needed"
        )
    target = None
    if max_pixels is not None and w * h > max_pixels:
        if on_too_large == "error":
            raise ValueError(
                f"{name}: image is {w}x{h} = {w * h} pixels, more than max_pixels={max_pixels}"
            )
        target = fit_size(w, h, max_pixels)

    png16_size = png16_header(data) if im.format == "PNG" else None
    if png16_size is not None and target is not None:
        # checked from the header, before any decoding: a 16-bit PNG above the cap is read
        # by Pillow at 8 bits per channel, row by row (4 bytes a pixel, as an 8-bit PNG),
        # and reduced to the cap; at full precision it would take several times that
        info.bit_depth = 16
        conv.append("16-bit PNG above max_pixels: read at 8 bits per channel, then resized")
        png16_size = None
    try:
        png16 = decode_png16(data) if png16_size is not None else None
        if png16 is not None:
            arr16, exif_raw = png16
            info.bit_depth = 16
            rgb = _png16_to_float_rgb(arr16, conv)
            icc = im.info.get("icc_profile") or None
        else:
            if png16_size is not None:  # interlaced, a side over libpng's limit, no codec
                info.bit_depth = 16
                conv.append("16-bit PNG read at 8 bits per channel (see the log for why)")
            if target is not None and im.format in ("JPEG", "MPO"):
                # DCT-domain downscale: decoding a 48 MP JPEG at 1/4 is ~10x cheaper.
                im.draft(im.mode, target)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                im.load()
            exif_raw = im.info.get("exif") or None
            if info.bit_depth != 16:
                info.bit_depth = 32 if im.mode in ("I", "F") else 8
            if im.mode.startswith("I;16"):
                info.bit_depth = 16
            if target is not None and im.mode in ("RGB", "L", "RGBA", "LA"):
                im = im.resize(target, Image.Resampling.LANCZOS, reducing_gap=3.0)
            rgb, icc = _to_float_rgb(im, conv)
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(name) else f"{name}: {msg}") from exc
    except _DECODE_ERRORS as exc:
        kind = im.format or "image"
        raise ValueError(f"{name}: truncated or corrupt {kind} data: {exc}") from exc
    except MemoryError as exc:
        raise ValueError(
            f"{name}: not enough memory to decode {w}x{h} pixels; pass max_pixels"
        ) from exc
    finally:
        im.close()

    if target is not None:
        if rgb.shape[:2] != (target[1], target[0]):
            rgb = resize_float(rgb, (target[1], target[0]))
        conv.append(f"resized from {w}x{h} to {target[0]}x{target[1]} (max_pixels={max_pixels})")
        logger.info(
            "%s: %dx%d exceeds max_pixels=%d, resized to %dx%d",
            name,
            w,
            h,
            max_pixels,
            target[0],
            target[1],
        )
    if orientation != 1:
        rgb = apply_orientation(rgb, orientation)
        conv.append(f"applied EXIF orientation {orientation}")
    rgb = np.clip(rgb, 0.0, 1.0, out=np.ascontiguousarray(rgb, dtype=np.float32))
    info.icc_profile = _rgb_profile(icc, conv)
    info.exif = strip_orientation(exif_raw)
    info.size = (rgb.shape[0], rgb.shape[1])
    return rgb, info


def load_image_with_info(
    src: ImageSource,
    *,
    max_pixels: int | None = None,
    on_too_large: Literal["resize", "error"] = "resize",
    min_side: int | None = None,
) -> tuple[np.ndarray, ImageInfo]:
    """Load a photo as an upright RGB float array, with what was learned and done.

    Args:
        src: a path or the file's bytes.
        max_pixels: cap on H * W of the result; None = no cap.
        on_too_large: ``"resize"`` shrinks (aspect kept, logged) an image above the cap,
            ``"error"`` raises ``ValueError`` instead.
        min_side: refuse an image with a side shorter than this many pixels; None = any.
            Like the pixel caps, it is checked from the file's header, before decoding.

    Returns:
        (image, info): image is HxWx3 float32 in [0, 1], upright (EXIF orientation applied),
        transparency composited over white; info is an :class:`ImageInfo`.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: empty, truncated, corrupt, unsupported, oversized or too small input;
            HEIC without pillow-heif. The message starts with the file name.
    """
    name = source_name(src)
    data = read_source_bytes(src)
    return decode_image(
        data, name, max_pixels=max_pixels, on_too_large=on_too_large, min_side=min_side
    )


def load_image(
    src: ImageSource,
    *,
    max_pixels: int | None = None,
    on_too_large: Literal["resize", "error"] = "resize",
    min_side: int | None = None,
) -> np.ndarray:
    """Load a photo as an upright HxWx3 float32 array in [0, 1].

    See :func:`load_image_with_info` for arguments and errors.
    """
    return load_image_with_info(
        src, max_pixels=max_pixels, on_too_large=on_too_large, min_side=min_side
    )[0]
