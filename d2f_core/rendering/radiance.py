"""Radiance and the HDR boost, D2F step 4: ``R = M_h * alpha * I^beta + (1 - M_h) * R0``
with ``alpha = 3``, ``beta = 5`` and ``M_h`` the pixels with a channel at 0.99 or more;
optionally with a larger ``alpha`` for a saturated spot that stands alone (``spot``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .inputs import ROW_BAND, row_bands, tracks_grad

HDR_ALPHA = 3.0
HDR_BETA = 5.0
HDR_THRESHOLD = 0.99
#: The weight ``rendering.render`` gives a saturated pixel with no other saturated pixel
#: near it, when it has no radiance map (``hdr_boost(..., spot=SPOT_ALPHA)``).
SPOT_ALPHA = 12.0
#: Whether a saturated pixel stands alone is read from the saturated share of the
#: ``SPOT_CELLS x SPOT_CELLS`` cells of ``SPOT_CELL`` px around it (:func:`spot_share`).
SPOT_CELL = 4
SPOT_CELLS = 5
#: The strength ``highlight_boost=True`` stands for (a multiple of ``alpha`` and ``spot``):
#: :func:`boost_strength`.
DEFAULT_BOOST = 1.0
#: The strongest boost a caller may ask for.
MAX_BOOST = 10.0


def boost_strength(highlight_boost) -> float:
    """The multiple of the HDR boost's weights that ``highlight_boost`` asks for: ``True``
    :data:`DEFAULT_BOOST`, ``False`` 0 (no boost), a number itself (0 to :data:`MAX_BOOST`).

    Raises:
        ValueError: a number outside that range, not finite, or not a number.
    """
    if highlight_boost is True:
        return DEFAULT_BOOST
    if highlight_boost is False or highlight_boost is None:
        return 0.0
    try:
        value = float(highlight_boost)
    except (TypeError, ValueError):
        raise ValueError(
            f"highlight_boost must be True, False or a strength, got {highlight_boost!r}"
        ) from None
    if not 0.0 <= value <= MAX_BOOST:
        raise ValueError(f"highlight_boost must be in [0, {MAX_BOOST:g}], got {highlight_boost!r}")
    return value


# radiance
# --------------------------------------------------------------------------------------


def highlight_mask(image: torch.Tensor, threshold: float = HDR_THRESHOLD) -> torch.Tensor:
    """``M_h``: 1 where any of R, G, B is at least ``threshold``.

    Shape: ``(B, 3, H, W) -> (B, 1, H, W)``.
    """
    return (image >= threshold).any(dim=1, keepdim=True).to(image.dtype)


def _power(x: torch.Tensor, exponent: float) -> torch.Tensor:
    """``x ** exponent``; a small whole exponent by repeated squaring (``pow`` with one costs
    as much as with any other: 0.28 ms against 0.03 ms for the three products of ``x ** 5`` on
    a 384x576 map)."""
    n = float(exponent)
    if not (n.is_integer() and 1 <= n <= 16):
        return x.pow(exponent)
    n = int(n)
    out, base = None, x
    while n:
        if n & 1:
            out = base if out is None else out * base
        n >>= 1
        if n:
            base = base * base
    return out if out is not x else x.clone()


def spot_share(image: torch.Tensor, threshold: float = HDR_THRESHOLD) -> torch.Tensor:
    """Around each cell of :data:`SPOT_CELL` px, the share of saturated pixels (a channel at
    ``threshold`` or more) in the square of :data:`SPOT_CELLS` x :data:`SPOT_CELLS` cells
    centred on it (the part of it inside the frame): a saturated pixel's surroundings, read
    from the cell that holds it.

    Shape: ``(B, 3, H, W) -> (B, 1, ceil(H / SPOT_CELL), ceil(W / SPOT_CELL))`` in [0, 1];
    no gradient.
    """
    # the brightest channel is at least the threshold exactly where any channel is
    sat = image.detach().amax(dim=1, keepdim=True).ge_(threshold).to(image.dtype)
    cells = F.avg_pool2d(sat, SPOT_CELL, ceil_mode=True)
    r = SPOT_CELLS // 2
    return F.avg_pool2d(cells, SPOT_CELLS, 1, r, count_include_pad=False)


def _spot_alpha(share: torch.Tensor, alpha: float, spot: float) -> torch.Tensor:
    # alpha where saturated pixels fill the square, rising to spot as they thin out to one
    return (1 - share).pow_(4).mul_(spot - alpha).add_(alpha)


def _spot_boost(
    image: torch.Tensor, out: torch.Tensor, alpha: float, beta: float, threshold: float, spot
) -> torch.Tensor:
    """``out`` (the boost with ``alpha``) with every saturated pixel's ``alpha`` replaced by
    its spot weight (:func:`hdr_boost`); in place, only at the saturated pixels, without
    gradients."""
    share = spot_share(image, threshold)
    if tracks_grad(image, out):
        a = _spot_alpha(share, alpha, spot)
        a = a.repeat_interleave(SPOT_CELL, -2).repeat_interleave(SPOT_CELL, -1)
        a = a[..., : image.shape[-2], : image.shape[-1]]
        peak = image.amax(dim=1, keepdim=True)
        return torch.where(peak >= threshold, _power(peak.clamp(0, 1), beta) * a, out)
    b, y, x = torch.nonzero(out.detach()[:, 0] >= alpha * threshold**beta, as_tuple=True)
    if not b.numel():
        return out
    peak = image[b, :, y, x].amax(dim=1)
    saturated = peak >= threshold
    b, y, x, peak = b[saturated], y[saturated], x[saturated], peak[saturated]
    a = _spot_alpha(share[b, 0, y // SPOT_CELL, x // SPOT_CELL], alpha, spot)
    out[b, 0, y, x] = _power(peak.clamp(0, 1), beta).mul_(a)
    return out


def hdr_boost(
    image: torch.Tensor,
    radiance: torch.Tensor | None = None,
    *,
    alpha: float = HDR_ALPHA,
    beta: float = HDR_BETA,
    threshold: float = HDR_THRESHOLD,
    per_channel: bool = False,
    spot: float | None = None,
) -> torch.Tensor:
    """Radiance weights ``R = M_h * alpha * I^beta + (1 - M_h) * R0``.

    With ``per_channel=False`` (default) ``I`` is the brightest channel, so ``R`` has one
    channel: a saturated pixel keeps its hue and the renderer blurs 5 channels instead of 7.
    ``per_channel=True`` is the paper's literal per-channel form.

    A clipped pixel's radiance is unknown. With ``spot`` the boost of a saturated pixel grows
    from ``alpha`` to ``spot`` as the saturated pixels around it thin out: ``alpha + (spot -
    alpha) (1 - s)^4``, ``s`` their share of the 20 px square around it (:func:`spot_share`).
    A small clipped spot (a lamp, a glint) is far brighter than the clip level more often
    than a wide one (a white wall, an overcast sky); the first blurs into a bright disc, the
    second into itself. ``rendering.render`` uses
    ``spot=SPOT_ALPHA`` when it has no radiance map.

    Args:
        image: ``(B, 3, H, W)`` in [0, 1].
        radiance: ``R0``, ``(B, 1, H, W)`` from the radiance network; ``None`` means ones.

    Returns:
        ``(B, 1, H, W)`` (or ``(B, 3, H, W)`` per channel); saturated pixels weigh up to
        ``alpha`` (with ``spot``: ``max(alpha, spot)``) times more than ``R0``.
    """
    if spot is not None:
        spot = float(spot)
        if not spot >= 0:
            raise ValueError(f"spot must be a weight >= 0, got {spot!r}")
    if per_channel:
        mask = highlight_mask(image, threshold)  # [B,1,H,W]
        base = torch.ones_like(mask) if radiance is None else radiance
        out = mask * alpha * _power(image.clamp(0, 1), beta)
        if spot is not None:
            a = _spot_alpha(spot_share(image, threshold), alpha, spot)
            a = a.repeat_interleave(SPOT_CELL, -2).repeat_interleave(SPOT_CELL, -1)
            out = out * a[..., : image.shape[-2], : image.shape[-1]] / alpha
        return out + (1 - mask) * base
    whole = radiance is not None and (
        radiance.shape[-2:] != image.shape[-2:] or radiance.dtype != image.dtype
    )  # a radiance that broadcasts, or promotes: as over the whole frame
    if tracks_grad(image, radiance) or whole or image[:, :1].numel() <= ROW_BAND:
        out = _boost_rows(image, radiance, alpha, beta, threshold)
    else:
        # by bands of rows, each in cache (0.16 s of a 12 MP render over whole frames)
        out = image.new_empty(image.shape[0], 1, *image.shape[2:])
        for part in row_bands(image):
            r = None if radiance is None else radiance[..., part, :]
            out[..., part, :] = _boost_rows(image[..., part, :], r, alpha, beta, threshold)
    if spot is None:
        return out
    return _spot_boost(image, out, alpha, beta, threshold, spot)


def _boost_rows(image, radiance, alpha: float, beta: float, threshold: float) -> torch.Tensor:
    # the brightest channel is at least the threshold exactly where any channel is
    peak = image.amax(dim=1, keepdim=True)
    boost = _power(peak.clamp(0, 1), beta).mul_(alpha)
    return torch.where(peak >= threshold, boost, 1.0 if radiance is None else radiance)


# --------------------------------------------------------------------------------------
