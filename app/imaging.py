"""Display-side image helpers for the web app: decoding uploads, colour maps, file output.

Nothing here is part of the method. Uploads are decoded by ``d2f_core.io`` (the project's
only file reader), checked and capped in size; maps from :class:`d2f_core.pipeline.Result`
are turned into pictures for the browser. Every failure is a ``ValueError`` whose message
can be shown to the user as it is.
"""

from __future__ import annotations

import html
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from d2f_core import io as d2f_io

#: Uploads above this many pixels are downscaled (with a notice) before ``prepare``.
#: 4096 x 3072, i.e. a 12.6 MP phone photo is kept at full resolution.
MAX_PIXELS = 4096 * 3072
#: Smallest accepted side in pixels: the networks and the 69 px kernels need some room.
MIN_SIDE = 16
#: Long side of the pictures sent to the browser; the download keeps full resolution.
DISPLAY_MAX_SIDE = 1600
#: File formats (Pillow's names) that browsers show; the photo panel gets a JPEG of any
#: other upload (HEIC, TIFF, ...), or the browser shows a broken image and cannot be clicked.
BROWSER_FORMATS = frozenset({"JPEG", "MPO", "PNG", "GIF", "WEBP", "BMP", "AVIF"})


@dataclass
class Photo:
    """A decoded upload.

    Attributes:
        image: ``(H, W, 3)`` float32 in [0, 1], EXIF orientation applied, at most
            ``MAX_PIXELS``.
        shown_size: ``(width, height)`` of the upload as a browser shows it (EXIF applied,
            before any downscale): the space ``SelectData.index`` is given in.
        notice: what the user is told about the decode (the image was downscaled, some of
            its pixels were NaN or infinite), else None.
        disparity: ``(H, W)`` float32 in [0, 1] depth embedded by a phone camera, or None.
        focus: the focal plane the phone recorded, or None.
        depth_source: where ``disparity`` came from (for the status line), or None.
        icc_profile: the upload's ICC profile bytes, or None.
        exif: the upload's EXIF bytes (orientation removed), or None.
        from_original: True when :attr:`image` is not the file's main picture but the
            all-in-focus original embedded in it (a Google Lens Blur JPEG, whose main
            picture is the phone's blurred rendering).
        browser_shows: whether a browser can show the uploaded file (its format is one of
            :data:`BROWSER_FORMATS`).
    """

    image: np.ndarray
    shown_size: tuple[int, int]
    notice: str | None = None
    disparity: np.ndarray | None = None
    focus: float | None = None
    depth_source: str | None = None
    icc_profile: bytes | None = None
    exif: bytes | None = None
    from_original: bool = False
    browser_shows: bool = True

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of :attr:`image`."""
        return self.image.shape[1], self.image.shape[0]


def _user_message(err: Exception, path: str, name: str) -> str:
    # d2f_core.io names the file in its messages; show the user's file name, not the
    # server's temporary path
    return str(err).replace(path, name)


def load_photo(
    path: str | os.PathLike,
    name: str = "photo",
    *,
    max_pixels: int = MAX_PIXELS,
    min_side: int = MIN_SIDE,
) -> Photo:
    """Decode an uploaded photo with ``d2f_core.io.load_photo`` and check its size.

    EXIF orientation is applied, larger photos are downscaled to ``max_pixels`` (JPEGs
    straight from the DCT), and phone depth embedded in the file is picked up.

    Args:
        path: file to decode.
        name: the user's file name, used in messages.
        max_pixels: larger photos are downscaled to this many pixels (``Photo.notice`` says so).
        min_side: photos with a smaller side are refused.

    Returns:
        :class:`Photo`.

    Raises:
        ValueError: empty, unreadable, truncated or too small file, or a decompression bomb;
            the message is meant for the user.
    """
    path = os.fspath(path)
    try:
        # the smallest side is checked from the header, before decoding
        loaded = d2f_io.load_photo(
            path, max_pixels=max_pixels, on_too_large="resize", min_side=min_side
        )
    except FileNotFoundError:
        raise ValueError(f"{name}: the upload could not be found on the server.") from None
    except ValueError as err:
        raise ValueError(_user_message(err, path, name)) from None
    info = loaded.info
    oh, ow = info.original_size
    if min(ow, oh) < min_side:
        raise ValueError(
            f"{name}: the photo is only {ow}x{oh} pixels; at least {min_side} pixels per side "
            "are needed."
        )
    image = loaded.image
    notes = []
    if image.shape[:2] != (oh, ow):
        notes.append(
            f"{name} is {ow}x{oh} ({ow * oh / 1e6:.1f} MP); it was resized to "
            f"{image.shape[1]}x{image.shape[0]} to stay within {max_pixels / 1e6:.1f} MP."
        )
    # said to the user, not only in the server's log: pixels the file does not hold
    notes += [f"{name}: {c}; they are shown black." for c in info.conversions if "NaN" in c]
    notice = " ".join(notes) or None
    source = None
    if loaded.disparity is not None:
        source = str((loaded.depth_info or {}).get("source", "embedded"))
    from_original = bool((loaded.depth_info or {}).get("used_original_image"))
    shows = str(info.format or "").upper() in BROWSER_FORMATS
    return Photo(
        image, (ow, oh), notice, loaded.disparity, loaded.focus, source, info.icc_profile,
        info.exif, from_original, shows,
    )  # fmt: skip


def load_depth_map(
    path: str | os.PathLike,
    size: tuple[int, int],
    kind: str = "disparity",
    name: str = "depth map",
    notes: list[str] | None = None,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Read a user's depth or disparity map with ``d2f_core.io`` and express it as disparity.

    Args:
        path: grey PNG/TIFF (8/16-bit or float), ``.npy`` or ``.pfm``.
        size: ``(width, height)`` of the photo; the map is resized to it.
        kind: ``"disparity"`` (bright = near) or ``"depth"`` (distances, small = near).
        name: the user's file name, used in messages.
        notes: where to add what the user should know of a map that loaded: its holes
            (filled from around them) and a map of one value (the photo at one depth).

    Returns:
        ``(disparity, stored_size)``: ``(H, W)`` float32 disparity in [0, 1], 1 = nearest, at
        the photo's size, and the file's ``(width, height)``, upright.

    Raises:
        ValueError: unreadable or colour-mapped file, no valid pixels, or an aspect ratio
            that does not match the photo.
    """
    path = os.fspath(path)
    try:
        # the map's size against the photo's from the header, before decoding
        raw = d2f_io.read_depth_array(path, size=(size[1], size[0]))
        disparity = d2f_io.depth_to_disparity(raw, kind=kind, size=(size[1], size[0]), name=name)
    except FileNotFoundError:
        raise ValueError(f"{name}: the upload could not be found on the server.") from None
    except ValueError as err:
        raise ValueError(_user_message(err, path, name)) from None
    if notes is not None:
        notes.extend(depth_notes(raw, kind, name))
    return disparity, (raw.shape[1], raw.shape[0])


def depth_notes(raw: np.ndarray, kind: str, name: str) -> list[str]:
    """What a map's values say that its picture does not: pixels with no depth (NaN,
    infinite; zero or negative in a depth map), which the library fills from around them, and
    a map of one value (bar a 1 % of outliers, as the library stretches a map), which the
    library takes for the photo at one depth (a map it would refuse, with no valid pixel,
    never gets here)."""
    valid = d2f_io.depth.holding_depth(raw, kind)
    notes = []
    holes = int(valid.size - np.count_nonzero(valid))
    if holes:
        what = "NaN, infinite, zero or negative" if kind == "depth" else "NaN or infinite"
        notes.append(
            f"{name}: {holes} of its {raw.size} pixels ({100 * holes / raw.size:.1f} %) hold no "
            f"depth ({what}); they were filled from the depth around them."
        )
    values = raw[valid]
    if kind == "depth":
        values = 1.0 / values
    if values.size and d2f_io.depth.one_value(*d2f_io.depth.value_range(values)):
        notes.append(
            f"{name} holds one value nearly everywhere: the whole photo is taken to be at one "
            "depth, and it is blurred evenly or not at all."
        )
    return notes


def steady_page_faults() -> bool:
    """Stop NumPy from asking Linux for huge pages (``madvise(MADV_HUGEPAGE)``) for its
    large arrays, for this process; return whether NumPy offers the switch.

    Where the kernel compacts memory on demand for such regions (its ``defrag`` setting
    ``madvise``, a common default), a fresh 144 MB array (a 12 MP picture in floats) stalled
    0.2-1.7 s in turn on a busy machine while compaction ran; with 4 kB pages the same array
    costs a steady 0.1 s. The app waits on such arrays between a render and its picture, so
    it takes the steady time (``d2f-app`` calls this at start).
    """
    import importlib

    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            switch = importlib.import_module(module)._set_madvise_hugepage
        except (ImportError, AttributeError):
            continue
        switch(False)
        return True
    return False


def to_uint8(image: np.ndarray) -> np.ndarray:
    """``(H, W[, 3])`` float in [0, 1] (or uint8) -> uint8, rounded."""
    if image.dtype == np.uint8:
        return image
    # by bands of rows: a 12 MP picture's float temporary took 70 ms to 1.8 s in page faults
    return d2f_io.float_to_uint8(np.asarray(image), name=None)


def _shrink(img: Image.Image, size: tuple[int, int]) -> Image.Image:
    """``img`` resized to ``size = (width, height)``, bilinearly, by whole cells first where
    it shrinks by 2x or more (PIL's ``reducing_gap``, which keeps the geometry exact)."""
    return img.resize(size, Image.Resampling.BILINEAR, reducing_gap=2.0)


def fit_display(image: np.ndarray, max_side: int = DISPLAY_MAX_SIDE) -> np.ndarray:
    """Downscale ``(H, W[, 3])`` uint8 so its long side is at most ``max_side``."""
    h, w = image.shape[:2]
    if max(h, w) <= max_side:
        return image
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return np.asarray(_shrink(Image.fromarray(image), size))


def resize_to(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize ``(H, W[, 3])`` uint8 to ``size = (width, height)`` for display."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    return np.asarray(Image.fromarray(image).resize(size, Image.Resampling.BILINEAR))


# Colour maps as 9 evenly spaced RGB stops sampled from matplotlib's "viridis" and "magma"
# (so that the app does not need matplotlib); linear interpolation in between.
COLORMAPS: dict[str, np.ndarray] = {
    "viridis": np.array(
        [
            (68, 1, 84), (71, 45, 123), (59, 82, 139), (44, 114, 142), (33, 145, 140),
            (40, 174, 128), (94, 201, 98), (173, 220, 48), (253, 231, 37),
        ],
        np.float32,
    ),
    "magma": np.array(
        [
            (0, 0, 4), (29, 17, 71), (81, 18, 124), (131, 38, 129), (183, 55, 121),
            (231, 82, 99), (252, 137, 97), (254, 196, 136), (252, 253, 191),
        ],
        np.float32,
    ),
    "gray": np.array([(0, 0, 0), (255, 255, 255)], np.float32),
}  # fmt: skip


def _lut(cmap: str) -> np.ndarray:
    """256-entry uint8 table of ``cmap``, linearly interpolated between its stops."""
    stops = COLORMAPS[cmap]
    x = np.linspace(0.0, len(stops) - 1.0, 256)
    i = np.minimum(x.astype(np.int32), len(stops) - 2)
    t = (x - i)[:, None]
    return (stops[i] * (1.0 - t) + stops[i + 1] * t + 0.5).astype(np.uint8)


_LUTS = {name: _lut(name) for name in COLORMAPS}


def colorize(values: np.ndarray, cmap: str = "viridis") -> np.ndarray:
    """Map ``(H, W)`` values in [0, 1] to ``(H, W, 3)`` uint8 colours of ``cmap``.

    Values are quantised to 256 levels (plenty for display) and looked up in a table, which
    is ~50x faster than interpolating every pixel; out-of-range values are clipped.
    """
    v = np.nan_to_num(np.asarray(values, np.float32), nan=0.0)
    idx = (np.clip(v, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return _LUTS[cmap][idx]


class DisplayViews:
    """The last render's pictures by view name (``"Bokeh"`` and the maps), at display size.

    The bokeh is kept as given. A map is kept grey (one byte a pixel, NaN as 0) at the size
    it was rendered at, and brought to the bokeh's size the first time its view is shown
    (bilinearly, by whole cells first where it shrinks by 2x or more, so a 12 MP map keeps
    its mean): most renders are never looked at as maps, and resizing the three maps of a
    12 MP photo's then 1024x768 pass to 1600x1200 cost about 22 ms of every render on one thread.
    """

    def __init__(self, bokeh: np.ndarray, maps: dict[str, np.ndarray]) -> None:
        self._lock = threading.Lock()  # events of one session may show a view at once
        self._size = (int(bokeh.shape[1]), int(bokeh.shape[0]))
        self._shown: dict[str, np.ndarray] = {"Bokeh": bokeh}
        self._grey = {
            name: to_uint8(np.nan_to_num(np.asarray(a, np.float32), nan=0.0))
            for name, a in maps.items()
        }

    def __getitem__(self, name: str) -> np.ndarray:
        with self._lock:
            if name not in self._shown:
                grey = self._grey[name]  # KeyError for a view it does not hold
                if (grey.shape[1], grey.shape[0]) != self._size:
                    grey = np.asarray(_shrink(Image.fromarray(grey), self._size))
                self._shown[name] = grey
                del self._grey[name]
            return self._shown[name]

    def get(self, name: str, default: np.ndarray | None = None) -> np.ndarray | None:
        return self[name] if name in self else default

    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._shown or name in self._grey

    def __len__(self) -> int:
        with self._lock:
            return len(self._shown) + len(self._grey)

    def keys(self) -> list[str]:
        with self._lock:
            return [*self._shown, *self._grey]

    def values(self) -> list[np.ndarray]:
        """Every view at display size (the maps resized now)."""
        return [self[name] for name in self.keys()]


def legend_html(cmap: str, low: str, high: str, title: str) -> str:
    """A horizontal colour bar for ``cmap`` with end labels, as an HTML snippet."""
    stops = COLORMAPS[cmap]
    n = len(stops) - 1
    grad = ", ".join(
        f"rgb({int(r)},{int(g)},{int(b)}) {100 * k / n:.0f}%" for k, (r, g, b) in enumerate(stops)
    )
    return (
        f'<div class="d2f-legend"><div style="font-size:0.85em">{html.escape(title)}</div>'
        f'<div style="height:14px;border-radius:3px;background:linear-gradient(to right, '
        f'{grad})"></div><div style="display:flex;justify-content:space-between;'
        f'font-size:0.85em"><span>{html.escape(low)}</span><span>{html.escape(high)}</span>'
        "</div></div>"
    )


#: JPEG quality of the pictures sent to the browser (the download keeps its own format).
DISPLAY_QUALITY = 90


def write_display(image: np.ndarray, path: str | os.PathLike) -> Path:
    """Write ``(H, W[, 3])`` uint8 as the JPEG the browser shows (quality
    :data:`DISPLAY_QUALITY`, 4:4:4 so the colour maps' edges stay crisp).

    A 1600x1200 picture took 7 ms and 262 KB this way, against 95 ms and 1.66 MB as a
    level-1 PNG (the download, at full resolution, is written separately).
    """
    Image.fromarray(image).save(path, format="JPEG", quality=DISPLAY_QUALITY, subsampling=0)
    return Path(path)


def save_image(
    image: np.ndarray,
    path: str | os.PathLike,
    *,
    icc_profile: bytes | None = None,
    exif: bytes | None = None,
) -> Path:
    """Write ``(H, W, 3)`` uint8/float with ``d2f_core.io.save_image`` (format from suffix).

    The input photo's ICC profile and EXIF (orientation dropped: pixels are upright) are
    carried over, so the download looks like the upload in colour-managed viewers.
    """
    return d2f_io.save_image(path, image, quality=95, icc_profile=icc_profile, exif=exif)
