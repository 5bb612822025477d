"""Subject finding: where the nearest prominent thing of a disparity map is, for the first focus
(:meth:`d2f_core.pipeline.D2F.subject_focus`, ``d2f --focus subject``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def find_subject(
    disparity: np.ndarray, min_prominence: float = 0.02
) -> tuple[float, tuple[float, float]] | None:
    """Where the subject of a disparity map is, and its focal disparity.

    A subject is what stands out nearer than the rest of its rows: the map minus each row's
    30th percentile (a floor or a wall sloping away in depth stands out from nothing), box
    smoothed over a fortieth of the frame and weighted by a broad centre prior. The
    subject's pixels are those within half the strongest score; the focus is their
    score-weighted median disparity and the point is the strongest of them.

    Args:
        disparity: ``H x W`` in [0, 1], 1 = nearest (any size; 128 px is plenty).
        min_prominence: below this strongest score nothing stands out.

    Returns:
        ``(focus, (x, y))`` with ``x, y`` as fractions of the width and height (pixel
        centres), or ``None`` when nothing stands out.
    """
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"disparity must be a non-empty H x W map, got shape {d.shape}")
    h, w = d.shape
    prominence = d - np.percentile(d, 30, axis=1, keepdims=True)
    k = max(1, round(max(h, w) / 40))
    n = 2 * k + 1
    cs = np.pad(np.pad(prominence, k, mode="edge").cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    smooth = (cs[n:, n:] - cs[:-n, n:] - cs[n:, :-n] + cs[:-n, :-n]) / (n * n)
    yy, xx = np.mgrid[0:h, 0:w]
    centre = np.exp(-(((yy + 0.5) / h - 0.5) ** 2 + ((xx + 0.5) / w - 0.5) ** 2) / 0.18)
    score = np.clip(smooth, 0, None) * centre
    top = float(score.max())
    if not top >= min_prominence:
        return None
    region = score >= 0.5 * top
    values, weights = d[region], score[region]
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    focus = float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return float(np.clip(focus, 0.0, 1.0)), ((ix + 0.5) / w, (iy + 0.5) / h)


def locate_subject(
    disparity: np.ndarray, size: tuple[int, int], focus_at: Callable[[float, float], float]
) -> tuple[float, tuple[float, float]]:
    """:func:`find_subject` on a small ``disparity`` map of a photo of ``size`` = ``(H, W)``,
    the point in that photo's pixels; where nothing stands out, the centre and
    ``focus_at(x, y)`` there.

    Returns:
        ``(focus, (x, y))``.
    """
    height, width = size
    found = find_subject(disparity)
    if found is None:
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        return focus_at(cx, cy), (cx, cy)
    focus, (fx, fy) = found
    return focus, (fx * width - 0.5, fy * height - 0.5)


def click_window(
    size: tuple[int, int], x: float, y: float, radius: int | None = None
) -> tuple[slice, slice]:
    """The rows and columns of the ``(2r+1)^2`` window a click at pixel ``(x, y)`` of a map of
    ``size = (H, W)`` reads (:meth:`D2F.focus_at`, :func:`focus_in_map`), clipped to the map;
    ``radius`` defaults to ``max(2, round(max(H, W) / 200))`` px."""
    h, w = size
    r = max(2, round(max(h, w) / 200)) if radius is None else radius
    xi = min(max(round(x), 0), w - 1)
    yi = min(max(round(y), 0), h - 1)
    return slice(max(0, yi - r), yi + r + 1), slice(max(0, xi - r), xi + r + 1)


def focus_in_map(disparity: np.ndarray, x: float, y: float) -> float:
    """:meth:`D2F.focus_at` on a bare ``H x W`` disparity map: the median in the same
    window around pixel ``(x, y)`` (:func:`click_window`)."""
    win = disparity[click_window(disparity.shape, x, y)]
    return float(np.clip(np.median(win), 0.0, 1.0))


def subject_in_map(disparity: np.ndarray) -> tuple[float, tuple[float, float]]:
    """:meth:`D2F.subject_focus` on a bare ``H x W`` disparity map (what the CLI does with a
    map and no weights): :func:`locate_subject` on a copy of about 128 px, the centre when
    nothing stands out.

    Returns:
        ``(focus, (x, y))``, the point in the map's pixels.
    """
    step = max(1, max(disparity.shape) // 128)
    return locate_subject(
        disparity[::step, ::step], disparity.shape, lambda x, y: focus_in_map(disparity, x, y)
    )


#: A subject's focal range is never wider than this span of disparity: a click on a thing
#: that fills the depth (a floor, a wall seen at an angle) keeps most of the photo blurred.
MAX_FOCAL_RANGE = 0.25
#: A step of disparity between two neighbours of the map at :data:`RANGE_MAP_SIDE` px that
#: ends a subject (a silhouette); steps inside a face or a body are far smaller.
SUBJECT_STEP = 0.03
#: The long side of the map :func:`subject_range` reads.
RANGE_MAP_SIDE = 256


def subject_range(
    disparity: np.ndarray,
    point: tuple[float, float],
    focus: float,
    *,
    step: float = SUBJECT_STEP,
    cap: float = MAX_FOCAL_RANGE,
    percentiles: tuple[float, float] = (2.0, 98.0),
) -> float:
    """The focal range that covers the subject at ``point``: the extent in depth of the
    connected region around it.

    The region is grown from the point over neighbours whose disparity differs by less than
    ``step`` (a silhouette's step stops it), within ``cap / 2`` of ``focus``; its extent is
    a percentile band of its disparity (a few noisy pixels do not widen it), and the range
    is the band's width on both sides of ``focus``: ``2 max(f - low, high - f)``, at most
    ``cap``.

    Args:
        disparity: ``H x W`` in [0, 1], 1 = nearest (about :data:`RANGE_MAP_SIDE` px).
        point: ``(x, y)`` as fractions of the width and height.
        focus: the focal disparity set at the point.

    Returns:
        The focal range in [0, ``cap``]; 0 where no region is found.
    """
    from skimage.measure import label

    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"disparity must be a non-empty H x W map, got shape {d.shape}")
    h, w = d.shape
    jump = np.zeros(d.shape, dtype=bool)
    dy = np.abs(np.diff(d, axis=0)) >= step
    dx = np.abs(np.diff(d, axis=1)) >= step
    jump[1:] |= dy
    jump[:-1] |= dy
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    inside = ~jump & (np.abs(d - focus) <= 0.5 * cap)
    labels = label(inside, connectivity=1)
    xi = min(max(int(point[0] * w), 0), w - 1)
    yi = min(max(int(point[1] * h), 0), h - 1)
    # the click may land on a silhouette's step: the region most of its neighbourhood holds
    k = max(1, round(max(h, w) / 100))
    window = labels[max(0, yi - k) : yi + k + 1, max(0, xi - k) : xi + k + 1]
    found = window[window > 0]
    if not found.size:
        return 0.0
    region = labels == np.bincount(found).argmax()
    low, high = np.percentile(d[region], percentiles)
    extent = 2.0 * max(focus - low, high - focus, 0.0)
    return round(float(min(extent, cap)), 3)


def range_in_map(disparity: np.ndarray, x: float, y: float, focus: float) -> float:
    """:meth:`D2F.focus_at`'s focal range (``with_range``) on a bare ``H x W`` disparity map:
    :func:`subject_range` on a copy of about :data:`RANGE_MAP_SIDE` px, at pixel ``(x, y)``."""
    h, w = disparity.shape
    step = max(1, max(h, w) // RANGE_MAP_SIDE)
    return subject_range(disparity[::step, ::step], ((x + 0.5) / w, (y + 0.5) / h), focus)


def index_runs(columns: list[int]) -> list[tuple[int, int]]:
    """Merge sorted column indices into inclusive runs: [1, 2, 3, 7] -> [(1, 3), (7, 7)]."""
    runs: list[list[int]] = []
    for c in columns:
        if runs and c == runs[-1][1] + 1:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    return [(a, b) for a, b in runs]
