"""The network's scene maps applied to its disparity: subjects stood in front of what surrounds
them, the sky at the back.

A ``"-scene"`` defocus network (:data:`d2f_core.networks.SCENE_MAPS`) predicts, beside its
disparity, where the subjects are (every salient thing and near occluder that stage 0's
targets stand in front of the scene) and where the sky is. Stage 0's targets lift every subject
above what surrounds it, a non-local rule (the lift depends on a ring a tenth of the frame
wide) that a small network follows only loosely: its subjects come out level with, or behind,
the scene they stand in. :func:`stand_subjects` applies the rule to the network's own maps.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["stand_subjects"]


def _soft(p: np.ndarray) -> np.ndarray:
    """A probability map as an alpha: 0 below 0.3, 1 above 0.7, linear between."""
    return np.clip((p - 0.3) / 0.4, 0.0, 1.0)


def stand_subjects(
    disparity: np.ndarray,
    subject: np.ndarray,
    sky: np.ndarray | None = None,
    lift: float = 0.05,
    min_area: float = 0.002,
    ring: float = 0.1,
    max_parts: int = 8,
    min_clarity: float = 0.0,
    max_shift: float = math.inf,
    blend: float = 0.0,
) -> np.ndarray:
    """``disparity`` with its subjects in front of their surroundings and its sky farthest.

    - **Sky**: where ``sky`` says so, the map is pulled down to the farthest disparity of
      the rest of the frame (its 1st percentile), never raised.
    - **Subjects**: every connected part of ``subject >= 0.5`` covering at least
      ``min_area`` of the frame (the ``max_parts`` largest) is shifted nearer, as a whole,
      until its lower quartile is ``lift`` above the 90th percentile of the map in a ring
      ``ring`` of the frame's long side wide around it. The ring leaves out the rows below
      the part's lowest row: that is the ground in front of it. A part already in front is
      left as it is, and the shift keeps the part's own relief. Its soft rim (``subject``
      between 0.3 and 0.7) takes part of the shift. No part moves more than
      ``max_shift``: a part the map puts far behind its ring is brought that much nearer,
      not all the way (a wrong subject then costs the scene's order little).
    - **Blend**: every pixel is then moved nearer by ``blend`` times the square of its
      subject probability, a soft step that follows the subject map itself rather than its
      parts. The square keeps a hesitant map (0.5) to a quarter of the move of a sure one.
      It needs no part, and ``min_clarity`` does not gate it.

    Subjects are stood only when the subject map is clear (of its pixels above 0.1, the mean
    distance from 0.5, doubled, is at least ``min_clarity``): a hesitant map is a scene with
    no one subject (a room, a shelf, a flower bed), where lifting its parts breaks the
    scene's own order. Stage 0's targets judge U^2-Net-p's silhouettes the same way.

    The result is divided by its maximum when a shift or the blend takes it above 1, so the
    order of every pixel is kept.

    Args:
        disparity: ``H x W`` in [0, 1], 1 = nearest.
        subject, sky: ``H x W`` probabilities in [0, 1] (``sky`` may be ``None``).
        lift: how much nearer than its surroundings a subject stands, in disparity.
        min_area: smaller parts are left alone (a fraction of the frame).
        ring: the width of the ring around a part, as a fraction of the long side.
        max_parts: at most this many parts (the largest) are stood.
        min_clarity: below this clarity of ``subject``, no part is stood.
        max_shift: the most any part is moved nearer, in disparity (unbounded by default).
        blend: how far a pixel the subject map is sure of is moved nearer, in disparity.

    Returns:
        ``H x W`` float32 in [0, 1].

    Raises:
        ValueError: maps of different shapes, not 2-D, or not finite; a negative ``lift``,
            ``max_shift`` or ``blend``, an infinite ``blend``, ``min_area`` outside [0, 1) or
            ``ring`` not positive.
    """
    d = np.asarray(disparity, dtype=np.float32)
    s = np.asarray(subject, dtype=np.float32)
    maps = [("disparity", d), ("subject", s)]
    if sky is not None:
        sky = np.asarray(sky, dtype=np.float32)
        maps.append(("sky", sky))
    for name, m in maps:
        if m.ndim != 2 or m.shape != d.shape or m.size == 0:
            raise ValueError(f"{name} must be an H x W map of shape {d.shape}, got {m.shape}")
        if not np.isfinite(m).all():
            raise ValueError(f"{name} holds NaN or infinite values")
    if lift < 0 or not 0 <= min_area < 1 or ring <= 0 or not max_shift >= 0:
        raise ValueError("lift and max_shift must be >= 0, min_area in [0, 1) and ring > 0")
    if not 0 <= blend < math.inf:
        raise ValueError(f"blend must be finite and >= 0, got {blend}")
    out = d.copy()
    if sky is not None:
        a = _soft(sky)
        rest = out[sky < 0.5]
        if a.any() and rest.size:
            far = float(np.percentile(rest, 1))
            out = np.where(a > 0, (1 - a) * out + a * np.minimum(out, far), out)
    hard = s >= 0.5
    soft = s[s > 0.1]
    clarity = float(np.mean(np.abs(soft - 0.5)) * 2) if soft.size else 0.0
    moved = False
    if lift > 0 and max_shift > 0 and hard.any() and clarity >= min_clarity:
        out = out + _part_shift(out, s, hard, lift, min_area, ring, max_parts, max_shift)
        moved = True
    if blend > 0:
        out = out + blend * np.square(np.clip(s, 0.0, 1.0))
        moved = True
    top = float(out.max())
    if moved and top > 1.0:
        out = out / top
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _part_shift(
    base: np.ndarray,
    s: np.ndarray,
    hard: np.ndarray,
    lift: float,
    min_area: float,
    ring: float,
    max_parts: int,
    max_shift: float,
) -> np.ndarray:
    """How far :func:`stand_subjects` moves each pixel of ``base`` nearer to stand the parts
    of ``hard`` (``s >= 0.5``) in front of their rings."""
    from scipy import ndimage

    h, w = base.shape
    parts, n = ndimage.label(hard, structure=np.ones((3, 3), bool))
    sizes = np.bincount(parts.ravel(), minlength=n + 1)[1:]
    boxes = ndimage.find_objects(parts)
    order = np.argsort(sizes)[::-1][:max_parts]
    radius = max(2.0, ring * max(h, w))
    pad = int(np.ceil(radius)) + 1
    alpha = _soft(s)
    shift = np.zeros_like(base)
    for idx in order:
        if sizes[idx] < max(4, min_area * h * w):
            break
        # a window round the part wide enough for its ring
        ys, xs = boxes[idx]
        y0, y1 = max(0, ys.start - pad), min(h, ys.stop + pad)
        x0, x1 = max(0, xs.start - pad), min(w, xs.stop + pad)
        win = (slice(y0, y1), slice(x0, x1))
        part = parts[win] == idx + 1
        # the ring, and the soft rim a few pixels round the part, by distance to the part
        dist = ndimage.distance_transform_edt(~part)
        around = (dist > 0) & (dist <= radius)
        around[ys.stop - y0 :] = False  # the rows below its lowest: the ground in front
        if not around.any():
            continue
        local = base[win]
        floor = float(np.percentile(local[around], 90)) + lift
        need = min(floor - float(np.percentile(local[part], 25)), max_shift)
        if need <= 0:
            continue
        rim = part | ((dist <= 3) & (alpha[win] > 0))
        weight = np.where(part, 1.0, alpha[win])
        shift[win] = np.where(rim, np.maximum(shift[win], need * weight), shift[win])
    return shift
