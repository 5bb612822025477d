"""The paper's growing kernel schedule read as a map between CoC and normalised defocus ``D``
(layer ``l`` covers ``D = l / (L - 1)``), for the plan and the fusion network.

D2F describes how blurred a pixel is by its normalised defocus ``D`` in [0, 1]: the
position of its circle of confusion (CoC, diameter in px at the render pass) on the
paper's growing schedule of kernel sizes (:data:`~d2f_core.rendering.kernels.PAPER_GROWING_SIZES`,
1 px -> 0, 23 px -> 0.5, 69 px or more -> 1), linear between two sizes. The fusion network
reads ``D``; the fusion gate is a value of ``D``. This module owns that map both ways.
"""

from __future__ import annotations

import numpy as np
import torch

from .kernels import PAPER_GROWING_SIZES

__all__ = ["coc_to_defocus", "defocus_to_coc"]

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
