"""The measures of ``d2f-bench depth``: rank correlation, scale/shift-invariant error and the
subject AUC, with the masks they are read over."""

from __future__ import annotations

import numpy as np

__all__ = [
    "EVAL_SIDE",
    "above_feet",
    "edge_band",
    "eval_size",
    "rankdata",
    "spearman",
    "ssi_rmse",
    "subject_auc",
]

#: long side (px) at which maps are compared
EVAL_SIDE = 384


def eval_size(h: int, w: int, side: int = EVAL_SIDE) -> tuple[int, int]:
    """``(h, w)`` at which a photo's maps are compared: its aspect, long side ``side``."""
    s = side / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


def rankdata(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of a 1-D array, ties given the mean of their ranks (float64)."""
    x = np.asarray(x).ravel()
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(x.size, np.float64)
    sorted_x = x[order]
    starts = np.r_[0, np.nonzero(np.diff(sorted_x))[0] + 1]
    ends = np.r_[starts[1:], x.size]
    mean_rank = (starts + ends + 1) / 2.0  # ranks start..end-1, 1-based
    ranks[order] = np.repeat(mean_rank, ends - starts)
    return ranks


def spearman(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Tie-averaged Spearman rank correlation over ``valid`` pixels (0 for a constant map)."""
    p, t = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} does not match truth shape {t.shape}")
    if valid is not None:
        p, t = p[valid], t[valid]
    rp, rt = rankdata(p), rankdata(t)
    rp -= rp.mean()
    rt -= rt.mean()
    den = np.sqrt((rp * rp).sum() * (rt * rt).sum())
    return float((rp * rt).sum() / den) if den > 0 else 0.0


def ssi_rmse(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> float:
    """RMSE after fitting ``a * pred + b`` to ``truth`` normalised to [0, 1] (its 1st to 99th
    percentile, clipped, so that a few outlying pixels do not squash the rest)."""
    p, t = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} does not match truth shape {t.shape}")
    if valid is not None:
        p, t = p[valid], t[valid]
    p, t = p.ravel(), t.ravel()
    lo, hi = np.percentile(t, 1), np.percentile(t, 99)
    t = np.clip((t - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    a = np.stack([p, np.ones_like(p)], 1)
    coef, *_ = np.linalg.lstsq(a, t, rcond=None)
    return float(np.sqrt(np.mean((a @ coef - t) ** 2)))


def subject_auc(pred: np.ndarray, mask: np.ndarray) -> float:
    """Chance that a random subject pixel (``mask``) is predicted nearer than a random
    background pixel, ties counted half (Mann-Whitney U over the two sets)."""
    pred = np.asarray(pred, np.float64).ravel()
    m = np.asarray(mask, bool).ravel()
    n1, n0 = int(m.sum()), int((~m).sum())
    if n1 == 0 or n0 == 0:
        raise ValueError("the mask must hold both subject and background pixels")
    ranks = rankdata(pred)
    u = ranks[m].sum() - n1 * (n1 + 1) / 2.0
    return float(u / (n1 * n0))


def edge_band(mask: np.ndarray, width: int = 8) -> np.ndarray:
    """Pixels within ``width`` px of the mask's silhouette, on either side."""
    from skimage.morphology import dilation, disk, erosion

    m = np.asarray(mask, bool)
    fp = disk(width)
    return dilation(m, fp) & ~erosion(m, fp)


def above_feet(mask: np.ndarray) -> np.ndarray:
    """The subject and the background in rows no lower than the subject's lowest row: the
    pixels left when the ground in front of a standing subject is set aside."""
    m = np.asarray(mask, bool)
    rows = np.nonzero(m.any(axis=1))[0]
    if rows.size == 0:
        raise ValueError("the mask holds no subject pixel")
    keep = np.zeros_like(m)
    keep[: rows[-1] + 1] = True
    return keep | m
