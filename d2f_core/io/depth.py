"""Depth and disparity maps: from a file's raw values (read by :mod:`.depth_files`) to
normalised disparity, hole filling, and writing.

Everything the renderer sees is *normalised disparity*: an HxW float32 map in [0, 1] where
1 is the nearest point of the scene. ``load_depth`` gets there from 8/16-bit PNG (or any
grey image Pillow reads), ``.npy``, PFM and float TIFF, whether the file stores metric depth
(``kind="depth"``, converted with 1/depth) or something proportional to disparity
(``kind="disparity"``). Holes (0, NaN, inf) are filled edge-aware, never left at zero.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image

from .depth_files import (  # noqa: F401  (read here as before: part of this module's API)
    check_aspect,
    read_depth_array,
    read_pfm,
    write_pfm,
)
from .holes import fill_holes  # noqa: F401  (part of this module's API, as before)
from .image import resize_float, source_name
from .save import atomic_write, to_uint8

logger = logging.getLogger(__name__)

DEPTH_EXTENSIONS = frozenset({".png", ".npy", ".pfm", ".tif", ".tiff", ".jpg", ".jpeg", ".webp"})
# Robust range: measured on the Kinect sample, 0.17% of its pixels are bogus 1-7 cm readings;
# the 0.5 / 99.5 percentiles ignore such flying pixels.
ROBUST_PERCENTILES = (0.5, 99.5)


# --------------------------------------------------------------------------- normalising


def value_range(values: np.ndarray, *, robust: bool = True) -> tuple[float, float]:
    """The range :func:`normalize_disparity` stretches to [0, 1]: the 0.5th and 99.5th
    percentiles of ``values`` (finite, 1-D) with ``robust`` and 1000 values or more, else
    their extremes. A map whose range is empty is one value to the renderer."""
    if robust and values.size >= 1000:
        lo, hi = np.percentile(values, ROBUST_PERCENTILES)
        return float(lo), float(hi)
    return float(values.min()), float(values.max())


def one_value(lo: float, hi: float) -> bool:
    """Whether a map whose :func:`value_range` is ``(lo, hi)`` holds one value to the
    renderer (:func:`normalize_disparity` makes it 0.5 everywhere)."""
    return not hi - lo > 1e-12 * max(abs(hi), 1.0)


def holding_depth(
    raw: np.ndarray, kind: str = "disparity", zero_is_hole: bool | None = None
) -> np.ndarray:
    """The pixels of raw values that hold depth, the rest holes for :func:`fill_holes`:
    finite, and positive in a depth map (0 is no distance), non-zero in a disparity map with
    ``zero_is_hole``."""
    valid = np.isfinite(raw)
    if kind == "depth":
        valid &= raw > 0
    elif zero_is_hole:  # None -> False for disparity
        valid &= raw != 0
    return valid


def normalize_disparity(
    disparity: np.ndarray, valid: np.ndarray | None = None, *, robust: bool = True
) -> np.ndarray:
    """Min-max (or robust-percentile) normalise to [0, 1], clipped. HxW float32.

    A constant map has no range; it becomes 0.5 everywhere (with a warning).
    """
    d = np.asarray(disparity, dtype=np.float64)
    sample = d[valid] if valid is not None else d[np.isfinite(d)]
    if sample.size == 0:
        raise ValueError("disparity map has no valid pixels")
    lo, hi = value_range(sample, robust=robust)
    if one_value(lo, hi):
        logger.warning("depth map is constant; using disparity 0.5 everywhere")
        return np.full(d.shape, 0.5, np.float32)
    return np.clip((d - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def depth_to_disparity(
    raw: np.ndarray,
    *,
    kind: Literal["disparity", "depth"] = "disparity",
    near: Literal["bright", "dark"] | None = None,
    size: tuple[int, int] | None = None,
    guide: np.ndarray | None = None,
    zero_is_hole: bool | None = None,
    robust: bool = True,
    name: str = "depth",
) -> np.ndarray:
    """Turn raw depth/disparity values into normalised disparity (1 = nearest).

    Args:
        raw: HxW values as stored in a file.
        kind: ``"depth"``: values are distances (converted with 1/depth);
            ``"disparity"``: values grow linearly with disparity (inverse depth).
        near: which end is near. For disparity ``"bright"`` (default: large = near) or
            ``"dark"`` (map stored inverted); depth maps are always near = small (``"dark"``).
        size: (H, W) of the result (the image's resolution); None keeps the map's size.
        guide: the photo (HxWx3 in [0, 1], any size) to make hole filling follow its edges.
        zero_is_hole: treat exact zeros as missing. Default: yes for depth (a distance of 0
            is never valid); no for disparity, where 0 is the farthest value of a normalised
            map. Pass True for stereo ground truth such as Middlebury (0 = unknown).
        robust: normalise between the 0.5 and 99.5 percentiles instead of min/max.
        name: used in error messages.

    Returns:
        HxW float32 in [0, 1], 1 = nearest, at ``size``.

    Raises:
        ValueError: bad arguments, all pixels missing, aspect ratio far from ``size``.
    """
    if kind not in ("disparity", "depth"):
        raise ValueError(f"kind: expected 'disparity' or 'depth', got {kind!r}")
    if near is None:
        near = "bright" if kind == "disparity" else "dark"
    if near not in ("bright", "dark"):
        raise ValueError(f"near: expected 'bright' or 'dark', got {near!r}")
    if kind == "depth" and near == "bright":
        raise ValueError(
            "near: a depth map has small values near the camera (near='dark'); "
            "for a map where bright means near, use kind='disparity'"
        )
    a = np.asarray(raw, dtype=np.float64)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"{name}: expected a non-empty HxW map, got shape {a.shape}")
    if size is not None:
        h, w = int(size[0]), int(size[1])
        if h < 1 or w < 1:
            raise ValueError(f"size: expected positive (H, W), got {size}")
        check_aspect(a.shape, (h, w), name)
    valid = holding_depth(a, kind, zero_is_hole)
    n_holes = int(valid.size - valid.sum())
    if not valid.any():
        finite = np.isfinite(a)
        if kind == "depth" and finite.any() and (a[finite] < 0).any():
            raise ValueError(
                f"{name}: depth map has no positive values (from {a[finite].min():.4g} to "
                f"{a[finite].max():.4g}); a depth map holds distances, which are positive"
            )
        raise ValueError(f"{name}: depth map has no valid pixels (all zero, NaN or inf)")
    disp = np.where(valid, a, 0.0)
    if kind == "depth":
        disp = np.where(valid, 1.0 / np.where(valid, a, 1.0), 0.0)
    if n_holes:
        logger.info("%s: filling %d missing pixels (%.1f%%)", name, n_holes, 100 * n_holes / a.size)
        disp = fill_holes(disp, valid, guide)
    out = normalize_disparity(disp, valid, robust=robust)
    if near == "dark" and kind == "disparity":
        out = 1.0 - out
    if size is not None and out.shape != (size[0], size[1]):
        out = np.clip(resize_float(out, (int(size[0]), int(size[1])), "bilinear"), 0.0, 1.0)
    return np.ascontiguousarray(out, dtype=np.float32)


def load_depth(
    path: str | os.PathLike | bytes,
    *,
    kind: Literal["disparity", "depth"] = "disparity",
    near: Literal["bright", "dark"] | None = None,
    size: tuple[int, int] | None = None,
    guide: np.ndarray | None = None,
    zero_is_hole: bool | None = None,
    robust: bool = True,
) -> np.ndarray:
    """Load a depth or disparity map file as normalised disparity.

    Reads PNG 8/16-bit (and other grey images), ``.npy``, PFM and float TIFF, then applies
    :func:`depth_to_disparity` (see there for the arguments).

    Returns:
        HxW float32 in [0, 1], 1 = nearest, at ``size`` (the image's (H, W)) when given.
    """
    name = source_name(path)
    raw = read_depth_array(path, size=size)  # the aspect is checked before decoding
    return depth_to_disparity(
        raw,
        kind=kind,
        near=near,
        size=size,
        guide=guide,
        zero_is_hole=zero_is_hole,
        robust=robust,
        name=name,
    )


def save_depth(path: str | os.PathLike, disparity: np.ndarray) -> Path:
    """Write a normalised map (HxW in [0, 1]) by extension.

    ``.png``: 16-bit grey (0..65535); ``.npy``: float32; ``.pfm``: float32;
    ``.tif``/``.tiff``: 32-bit float; ``.jpg``/``.webp``: 8-bit grey (lossy, for viewing).
    """
    out = Path(path)
    a = np.asarray(disparity)
    if a.ndim != 2:
        raise ValueError(f"disparity: expected an HxW map, got shape {a.shape}")
    ext = out.suffix.lower()
    a32 = np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    if ext == ".npy":
        atomic_write(out, lambda fh: np.save(fh, a32))
    elif ext == ".pfm":
        write_pfm(out, a32)
    elif ext == ".png":
        a16 = np.round(np.clip(a32, 0.0, 1.0) * 65535.0).astype(np.uint16)
        img = Image.fromarray(a16)
        atomic_write(out, lambda fh: img.save(fh, format="PNG"))
    elif ext in (".tif", ".tiff"):
        img = Image.fromarray(a32)
        atomic_write(out, lambda fh: img.save(fh, format="TIFF"))
    elif ext in (".jpg", ".jpeg", ".webp"):
        img = Image.fromarray(to_uint8(np.clip(a32, 0, 1)))
        fmt = "JPEG" if ext != ".webp" else "WEBP"
        atomic_write(out, lambda fh: img.save(fh, format=fmt, quality=95))
    else:
        raise ValueError(f"path: unknown depth extension {ext!r} (use .png .npy .pfm .tif)")
    return out
