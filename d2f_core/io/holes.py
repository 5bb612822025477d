"""Filling the holes of a depth map (pixels with no measurement) by push-pull: averages over
a pyramid of 2x2 blocks, pulled back down where a pixel has none of its own.
"""

from __future__ import annotations

import numpy as np

from .image import resize_float

__all__ = ["fill_holes"]


def _pool2(a: np.ndarray) -> np.ndarray:
    """Sum of 2x2 blocks (odd sizes padded with zeros). Works on HxW and HxWxC."""
    h, w = a.shape[:2]
    pad = [(0, h % 2), (0, w % 2)] + [(0, 0)] * (a.ndim - 2)
    a = np.pad(a, pad)
    return a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]


def _coarse_taps(idx: np.ndarray, n_coarse: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps from fine indices into the 2x coarser axis (pixel centres aligned)."""
    x = idx / 2.0 - 0.25
    i0 = np.floor(x).astype(np.int64)
    frac = x - i0
    return np.clip(i0, 0, n_coarse - 1), np.clip(i0 + 1, 0, n_coarse - 1), frac


def _push_pull(
    values: np.ndarray, weight: np.ndarray, guide: np.ndarray | None, sigma: float
) -> np.ndarray:
    """Fill pixels with weight < 1 from coarser levels; recursion ends when nothing is missing.

    The pull step is a joint-bilateral upsampling: each coarse neighbour counts in proportion
    to how close its mean guide colour is to the pixel's own, so fill values come from the
    same surface rather than leaking across object edges.
    """
    if weight.min() >= 1.0:
        return values
    h, w = values.shape[:2]
    cw = _pool2(weight)
    cv = _pool2(values * weight) / np.maximum(cw, 1e-12)
    cw = np.minimum(cw, 1.0)
    cg = None
    if guide is not None:
        cg = _pool2(guide) / _pool2(np.ones((h, w, 1)))
    if cw.shape == (1, 1) and cw[0, 0] <= 0:
        raise ValueError("no valid pixels to fill from")
    coarse = _push_pull(cv, cw, cg, sigma)
    ch, cwid = coarse.shape
    # Only pixels that need filling are pulled: holes are usually a small fraction.
    ys, xs = np.nonzero(weight < 1.0)
    r0, r1, fr = _coarse_taps(ys, ch)
    c0, c1, fc = _coarse_taps(xs, cwid)
    num = np.zeros(ys.shape)
    den = np.zeros(ys.shape)
    for ri, wr in ((r0, 1.0 - fr), (r1, fr)):
        for ci, wc in ((c0, 1.0 - fc), (c1, fc)):
            tap = wr * wc
            if guide is not None:
                diff = guide[ys, xs] - cg[ri, ci]
                tap = tap * (np.exp(-(diff**2).sum(axis=1) / (2.0 * sigma**2)) + 1e-6)
            num += tap * coarse[ri, ci]
            den += tap
    out = values.copy()
    wk = weight[ys, xs]
    out[ys, xs] = wk * values[ys, xs] + (1.0 - wk) * num / np.maximum(den, 1e-300)
    return out


def fill_holes(
    values: np.ndarray,
    valid: np.ndarray,
    guide: np.ndarray | None = None,
    *,
    sigma: float = 0.1,
) -> np.ndarray:
    """Fill invalid pixels of a map from the valid ones, following image edges when a guide is
    given (push-pull pyramid with joint-bilateral pull).

    Args:
        values: HxW map (values at invalid pixels are ignored).
        valid: HxW bool mask of trustworthy pixels.
        guide: optional HxWx3 (or HxW) image in [0, 1] at the map's resolution.
        sigma: colour distance (in [0, 1] units) at which a neighbour's weight drops to 0.6.

    Returns:
        HxW float64 map equal to ``values`` on valid pixels.

    Raises:
        ValueError: no valid pixel at all.
    """
    v = np.asarray(values, dtype=np.float64)
    m = np.asarray(valid, dtype=bool)
    if v.shape != m.shape or v.ndim != 2:
        raise ValueError(f"values/valid: expected equal HxW shapes, got {v.shape} and {m.shape}")
    if not m.any():
        raise ValueError("depth map has no valid pixels (all holes)")
    if m.all():
        return v
    g = None
    if guide is not None:
        g = np.asarray(guide, dtype=np.float64)
        if g.ndim == 2:
            g = g[..., None]
        if g.shape[:2] != v.shape:
            g = resize_float(g.astype(np.float32), v.shape, "bilinear").astype(np.float64)
            if g.ndim == 2:
                g = g[..., None]
    out = _push_pull(np.where(m, v, 0.0), m.astype(np.float64), g, sigma)
    return np.where(m, v, out)
