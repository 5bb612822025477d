"""Writing images: float to 8-bit in bands of bounded memory, atomic writes that keep the
target's permissions, and :func:`save_image` (PNG, JPEG, TIFF, WebP; ``.npy`` float).
"""

from __future__ import annotations

import io
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ..errors import InputTypeError, whole_number
from .formats import strip_orientation
from .image import SAVE_FORMATS

# --------------------------------------------------------------------------- saving


def to_uint8(array: np.ndarray, name: str = "array") -> np.ndarray:
    """HxWx3 / HxW float [0, 1] or uint8 array -> uint8 (rounded; floats more than
    :data:`ROUNDING` outside [0, 1] are refused)."""
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise ValueError(f"{name}: expected an HxW or HxWx3 array, got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name}: empty image of shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    if not np.issubdtype(a.dtype, np.floating):
        raise InputTypeError(f"{name}: expected float [0, 1] or uint8 values, got dtype {a.dtype}")
    return float_to_uint8(a, name, check_range=True)


#: Elements of the float32 band :func:`float_to_uint8` works on at once (4 MB). A float
#: temporary of the whole picture (144 MB at 12 MP) is fresh memory each call, and its page
#: faults cost 70 ms to 1.8 s in turn on a busy machine; a band costs a steady 35-40 ms.
_BAND_ELEMENTS = 1 << 20


#: How far past [0, 1] a float image may go and still be saved (clipped): half an 8-bit
#: level, what rounding leaves. Further is another scale (0-255) or a fault, and is refused.
ROUNDING = 0.5 / 255.0


def float_to_uint8(
    a: np.ndarray, name: str | None = "array", *, check_range: bool = False
) -> np.ndarray:
    """Float ``a`` (any shape, values in [0, 1]) -> uint8 of the same shape, clipped and
    rounded half up, by bands of rows in one reused float32 buffer.

    ``name`` set: NaN or infinite values raise ``ValueError`` naming it, and with
    ``check_range`` values more than :data:`ROUNDING` outside [0, 1] too (else they are
    clipped); ``None``: nothing is looked for (a renderer's output, clamped already).
    """
    if a.ndim == 0:
        return float_to_uint8(a.reshape(1), name, check_range=check_range).reshape(())
    out = np.empty(a.shape, np.uint8)
    if a.size == 0:
        return out
    rows = max(1, _BAND_ELEMENTS // max(1, a[0].size))
    scratch = np.empty((min(rows, a.shape[0]), *a.shape[1:]), np.float32)
    for r0 in range(0, a.shape[0], rows):
        band = a[r0 : r0 + rows]
        if name is not None:
            if not np.isfinite(band).all():
                raise ValueError(f"{name}: contains NaN or infinite values")
            if check_range:
                low, high = float(band.min()), float(band.max())
                if low < -ROUNDING or high > 1.0 + ROUNDING:
                    hint = " (a 0-255 image? divide it by 255)" if high > 1.0 + ROUNDING else ""
                    raise ValueError(
                        f"{name}: float values must be in [0, 1], got {low:g} to {high:g}{hint}"
                    )
        buf = scratch[: band.shape[0]]
        # clip, scale and add 0.5 in float32: rounds half up, 2x faster than np.round
        np.clip(band, 0.0, 1.0, out=buf)
        buf *= 255.0
        buf += 0.5
        out[r0 : r0 + rows] = buf  # the cast truncates: floor of x + 0.5
    return out


#: The longest side each format's encoder writes (libjpeg: 65,500 px; libwebp: 16,383 px).
_SIDE_LIMITS = {"JPEG": 65500, "WEBP": 16383}


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when two paths name the same file (existing or not)."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
    except OSError:
        pass
    return pa.resolve() == pb.resolve()


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write) -> None:
    """Call ``write(file_object)`` on a temp file next to ``path``, then rename it into place,
    so that a failure never leaves a half-written output."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise _named(exc, path) from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        # mkstemp creates 0600 files; give the output the permissions open() would have
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno is not None:
            raise _named(exc, path) from exc
        raise


def _named(exc: OSError, path: Path) -> OSError:
    """``exc`` about the output ``path``, not the hidden temporary file beside it (a full
    disk says no file at all): ``[Errno 28] No space left on device: 'out.jpg'``."""
    return type(exc)(exc.errno, exc.strerror or str(exc), os.fspath(path))


#: the share of Pillow's one-shot buffer for optimised Huffman tables (1 byte a pixel, 2 from
#: quality 95) that a JPEG written with the standard tables may fill for its optimised
#: tables to be tried (optimised tables make it smaller, never larger)
JPEG_OPTIMIZE_FILL = 0.9


def _jpeg_bytes(img: Image.Image, params: dict) -> bytes:
    """The JPEG of ``img``, with optimised Huffman tables where they fit.

    libjpeg needs the whole optimised file in one buffer, which Pillow sizes at 1 byte a pixel
    (2 from quality 95); a grainy photo at a high quality needs more, and libjpeg stops with
    "Suspension not allowed here" on stderr. The file with the standard tables streams and
    tells the size first (about a tenth of a second at 12 MP): the optimised one is made only
    when that fits the buffer, else the standard one is kept (a few per cent larger)."""

    def encode(**extra) -> bytes:
        buf = io.BytesIO()
        img.save(buf, format="JPEG", **{**params, **extra})
        return buf.getvalue()

    plain = encode(optimize=False)
    per_pixel = 2 if params.get("quality", 75) >= 95 else 1
    if len(plain) > JPEG_OPTIMIZE_FILL * per_pixel * img.width * img.height:
        return plain
    return encode(optimize=True)


def check_side_limit(path: str | os.PathLike, size: tuple[int, int]) -> None:
    """Refuse a picture of ``size`` ``(H, W)`` that the format of ``path`` cannot hold (JPEG:
    65,500 px a side, WebP: 16,383), as :func:`save_image` would; a command checks it before
    it renders."""
    out = Path(path)
    fmt = SAVE_FORMATS.get(out.suffix.lower())
    limit = _SIDE_LIMITS.get(fmt)
    h, w = (int(n) for n in size)
    if limit is not None and max(h, w) > limit:
        raise ValueError(
            f"cannot save {out.name!r}: {fmt} holds at most {limit} px a side and the "
            f"image is {w}x{h}; save it as .png or .tif"
        )


def _photo_info(source: Any) -> Any:
    """The :class:`ImageInfo` behind ``source``: a ``Photo`` (``.info``), a ``Scene`` or a
    ``Result`` (``.photo_info``), an ``ImageInfo`` itself; ``None`` when it has none."""
    if source is None:
        return None
    if hasattr(source, "icc_profile") and hasattr(source, "exif"):
        return source
    for attr in ("photo_info", "info"):
        info = getattr(source, attr, None)
        if info is not None and hasattr(info, "icc_profile"):
            return info
    if hasattr(source, "photo_info") or hasattr(source, "info"):
        return None  # a scene or a result of a bare array: nothing to keep
    raise InputTypeError(
        f"like: expected a Photo from load_photo, a Scene, a Result or an ImageInfo, got "
        f"{type(source).__name__}"
    )


def save_image(
    path: str | os.PathLike,
    array: Any,
    *,
    like: Any = None,
    quality: int = 95,
    icc_profile: bytes | None = None,
    exif: bytes | Image.Exif | None = None,
    protect: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
) -> Path:
    """Write an RGB (or grey) image; the format follows the extension.

    The photo's colour profile and EXIF go with the picture when they are known: from a
    ``Result`` of a scene prepared from a loaded photo (``save_image(path, result)``), or
    from ``like=`` (the ``Photo`` of ``load_photo``). Without its profile a Display P3 photo
    would be read as sRGB by every viewer, its colours washed out.

    Args:
        path: ``.png``, ``.jpg``/``.jpeg``, ``.tif``/``.tiff`` or ``.webp``.
        array: HxWx3 (or HxW) float in [0, 1] (rounded; values past it by more than half a
            level are refused, as ``D2F.prepare`` refuses them) or uint8; or a ``Result`` of
            ``D2F.render`` (its ``bokeh``, with its photo's profile and EXIF).
        like: where the ICC profile and EXIF come from: a ``Photo`` (``load_photo``), a
            ``Scene``, a ``Result`` or an ``ImageInfo``; ``icc_profile=`` and ``exif=``
            given explicitly win over it.
        quality: JPEG/WebP quality 1..100.
        icc_profile: ICC profile bytes to embed (e.g. the input's), or None.
        exif: EXIF bytes or ``PIL.Image.Exif`` to embed; its orientation tag is dropped
            because the pixels are already upright (so is a photo's, from ``like``).
        protect: path(s) that must not be overwritten (e.g. the input photo).

    Returns:
        The written path.

    Raises:
        ValueError: unknown extension, bad array, or ``path`` is a protected file.
    """
    info = _photo_info(like)
    if hasattr(array, "bokeh") and hasattr(array, "fusion_mask"):  # a Result
        info = info if like is not None else _photo_info(array)
        array = array.bokeh
    if info is not None:
        icc_profile = info.icc_profile if icc_profile is None else icc_profile
        exif = info.exif if exif is None else exif
    out = Path(path)
    fmt = SAVE_FORMATS.get(out.suffix.lower())
    if fmt is None:
        known = ", ".join(sorted(SAVE_FORMATS))
        raise ValueError(f"path: cannot save {out.name!r}: unknown extension (use one of {known})")
    if not 1 <= whole_number(quality, "quality", 1) <= 100:
        raise ValueError(f"quality: expected 1..100, got {quality}")
    if protect is not None:
        protected = [protect] if isinstance(protect, (str, os.PathLike)) else list(protect)
        for p in protected:
            if same_file(out, p):
                raise ValueError(f"path: refusing to overwrite the input file {os.fspath(p)!r}")
    if out.is_dir():
        raise ValueError(f"path: {os.fspath(out)!r} is a directory")
    if not out.parent.exists():
        raise ValueError(f"path: directory {os.fspath(out.parent)!r} does not exist")
    if np.ndim(array) >= 2:  # refused before the picture is converted
        check_side_limit(out, np.shape(array)[:2])
    pixels = to_uint8(array, "array")
    if pixels.ndim == 3 and pixels.shape[2] == 4:
        pixels = pixels[..., :3]
    img = Image.fromarray(pixels)
    params: dict = {}
    if icc_profile:
        params["icc_profile"] = icc_profile
    exif_bytes = strip_orientation(exif)
    if exif_bytes:
        params["exif"] = exif_bytes
    if fmt == "JPEG":
        params.update(quality=int(quality))
        if quality >= 90:
            params["subsampling"] = 0  # 4:4:4 keeps thin in-focus detail at high quality
    elif fmt == "WEBP":
        params.update(quality=int(quality), method=4)
    elif fmt == "PNG":
        params.update(compress_level=6)
    elif fmt == "TIFF":
        # Uncompressed: Pillow's own TIFF writer keeps the EXIF sub-IFDs, the libtiff
        # (compressing) writer rejects them.
        params.update(compression="raw")

    if fmt == "JPEG":
        data = _jpeg_bytes(img, params)
        atomic_write(out, lambda fh: fh.write(data))
    else:
        atomic_write(out, lambda fh: img.save(fh, format=fmt, **params))
    return out
