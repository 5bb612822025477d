"""The paper's growing kernel schedule read as a map between CoC and normalised defocus ``D``
(layer ``l`` covers ``D = l / (L - 1)``), for the plan and the fusion network.

D2F describes how blurred a pixel is by its normalised defocus ``D`` in [0, 1]: the
position of its circle of confusion (CoC, diameter in px at the render pass) on the
paper's growing schedule of kernel sizes (:data:`~d2f_core.rendering.kernels.PAPER_GROWING_SIZES`,
1 px -> 0, 23 px -> 0.5, 69 px or more -> 1), linear between two sizes. The fusion network
reads ``D``; the fusion gate is a value of ``D``. This module owns that map both ways.

It also owns the focal range ``r``: a depth band around the focal plane that stays sharp,
the blur growing from its edges, ``CoC = K * max(0, |d - f| - r / 2)``. Folding the band
away, ``d' = d - clamp(d - f, -r/2, r/2)``, keeps the depth order and gives every pixel that
CoC as ``K * |d' - f|``, so the rest of the renderer runs on ``d'`` unchanged.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .kernels import PAPER_GROWING_SIZES

__all__ = [
    "check_focal_range",
    "coc_to_defocus",
    "defocus_to_coc",
    "fold_focal_range",
    "outside_range",
]

_TOP = len(PAPER_GROWING_SIZES) - 1


def _inverse_lines(sizes: tuple[int, ...]) -> list[tuple[float, float]]:
    """The schedule's inverse as lines ``(a, b)``: layer index = min over lines of a + b * coc.

    The schedule's steps never shrink, so its inverse is concave and piecewise linear: the
    minimum of its segments' lines (a few elementwise ops where a table lookup at 12 MP
    costs seconds).
    """
    lines: list[tuple[float, float]] = []
    for i in range(len(sizes) - 1):
        slope = 1.0 / (sizes[i + 1] - sizes[i])
        if lines and abs(lines[-1][1] - slope) < 1e-12:
            continue
        if lines and slope > lines[-1][1]:
            raise ValueError(f"kernel schedule steps must not shrink: {sizes}")
        lines.append((i - slope * sizes[i], slope))
    return lines


_LINES = _inverse_lines(PAPER_GROWING_SIZES)


def coc_to_defocus(coc: torch.Tensor | np.ndarray | float):
    """Normalised defocus ``D`` in [0, 1] of a CoC diameter in px at the render pass.

    Shape: any -> same. A tensor gives a tensor (same device), an array a float32 array, a
    number a float.
    """
    if isinstance(coc, torch.Tensor):
        out = None
        for a, b in _LINES:
            line = coc * b + a
            out = line if out is None else torch.minimum(out, line)
        return out.clamp(0, _TOP) / _TOP
    arr = np.asarray(coc, dtype=np.float64)
    d = np.interp(np.maximum(arr, 1.0), PAPER_GROWING_SIZES, np.linspace(0, 1, _TOP + 1))
    return d.astype(np.float32) if isinstance(coc, np.ndarray) else float(d)


def defocus_to_coc(defocus: float) -> float:
    """CoC diameter (px at the render pass) of normalised defocus ``defocus`` (clipped to
    [0, 1]); the inverse of :func:`coc_to_defocus` above 1 px."""
    sizes = PAPER_GROWING_SIZES
    pos = min(max(float(defocus), 0.0), 1.0) * _TOP
    i = min(int(pos), _TOP - 1)
    return sizes[i] + (pos - i) * (sizes[i + 1] - sizes[i])


def check_focal_range(focal_range) -> float:
    """``focal_range`` as a float in [0, 1] (a span of disparity), or ``ValueError`` naming it."""
    if isinstance(focal_range, bool):
        raise ValueError(f"focal_range must be a number in [0, 1], got {focal_range!r}")
    try:
        value = float(focal_range)
    except (TypeError, ValueError):
        raise ValueError(f"focal_range must be a number in [0, 1], got {focal_range!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"focal_range must be a number in [0, 1], got {focal_range!r}")
    return value


def fold_focal_range(
    disparity: torch.Tensor, focus: float | torch.Tensor, focal_range: float
) -> torch.Tensor:
    """The disparity with the focal range folded away: ``d - clamp(d - f, -r/2, r/2)``.

    Pixels inside the band land on the focal plane, the others move toward it by ``r / 2``,
    so ``|d' - f| = max(0, |d - f| - r / 2)`` and the depth order is kept. ``focal_range``
    0 returns ``disparity`` itself.

    Shape: (B, 1, H, W) -> (B, 1, H, W); ``focus`` a float or (B, 1, 1, 1).
    """
    if focal_range <= 0:
        return disparity
    half = 0.5 * float(focal_range)
    return disparity - (disparity - focus).clamp(-half, half)


def outside_range(distance, focal_range: float):
    """``max(0, distance - r / 2)``: a distance ``|d - f|`` from the focal plane measured from
    the focal range's edge instead (``distance`` itself for 0). Tensor or float."""
    if focal_range <= 0:
        return distance
    half = 0.5 * float(focal_range)
    if isinstance(distance, torch.Tensor):
        return (distance - half).clamp(min=0.0)
    return max(0.0, float(distance) - half)
