"""Blur: each layer convolved with its kernel ``K(s_l)`` of the size schedule, the
``K_l * (M_l X)`` of D2F's compositing, by direct convolution, by FFT with cached spectra, or
on a coarse grid (1/2 to 1/16 resolution) for large kernels.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .inputs import tracks_grad
from .kernels import coarse_kernel
from .plan import TILE, LayerPlan

DIRECT_MAX_SIZE = 11
# Largest kernel (px) whose coarse-grid version is fitted (kernels.coarse_kernel) rather than
# sampled: the float64 fit grows with the square of the kernel (40 ms at 513 px). Sampling
# costs little at that size: a 257 px kernel at 1/4 resolution measured 69 dB sampled and
# 80 dB fitted against the full-resolution blur of 8-px blocks.
_FIT_MAX_SIZE = 513
_CL = torch.channels_last


@dataclass(frozen=True)
class QualityPreset:
    """Reduced-resolution thresholds: kernels of at least ``half`` px (``quarter`` px) are
    applied at 1/2 (1/4) resolution, and kernels of at least 2 (4) times ``quarter`` px at
    1/8 (1/16): on every grid the kernel spans at least ``quarter / 4`` cells, the same
    error budget. ``None`` disables the reduction."""

    half: int | None
    quarter: int | None


QUALITY_PRESETS: dict[str, QualityPreset] = {
    "exact": QualityPreset(None, None),
    "high": QualityPreset(23, 45),
    "balanced": QualityPreset(15, 39),
    "fast": QualityPreset(11, 23),
}
#: The coarsest grid a layer is blurred on (px of the frame per cell).
MAX_FACTOR = 16

# convolution
# --------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=1024)
def fast_len(n: int) -> int:
    """Smallest 2-3-5-smooth integer >= n (fast FFT sizes)."""
    best = 1 << max(0, (n - 1).bit_length())
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


@dataclass(frozen=True)
class KernelSpec:
    """What defines an aperture kernel, independent of the layer it is used for."""

    shape: str = "soft"
    blades: int = 0
    rotation: float = 0.0


@functools.lru_cache(maxsize=64)
@torch.inference_mode(False)
def kernel_tensor(
    spec: KernelSpec, size: int, factor: int, device: str, dtype: torch.dtype, gain: float = 1.0
):
    """Kernel for a full-res CoC of ``size`` px applied on a grid ``factor`` px apart, times
    ``gain`` (``1 / factor**2`` applies it to cell sums instead of cell means).

    On a coarse grid this is the least-squares fit of :func:`coarse_kernel` up to
    ``_FIT_MAX_SIZE`` px, and the aperture sampled on the coarse grid above it.
    """
    if gain != 1.0:
        return kernel_tensor(spec, size, factor, device, dtype) * gain
    return coarse_kernel(
        size,
        factor,
        shape=spec.shape,
        blades=spec.blades,
        rotation=spec.rotation,
        fit=size <= _FIT_MAX_SIZE,
        device=device,
        dtype=dtype,
    )


# A spectrum of a 1024-px frame is several MB: 32 entries keep the cache to a few hundred MB
# while covering every kernel size of a render.
@functools.lru_cache(maxsize=32)
@torch.inference_mode(False)
def _spectrum(
    spec: KernelSpec, size: int, factor: int, fh: int, fw: int, device: str, dtype, gain: float
):
    k = kernel_tensor(spec, size, factor, device, dtype, gain)
    return torch.fft.rfft2(k, s=(fh, fw))


def direct_conv(zp: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Valid depthwise convolution of the zero-padded ``zp`` with the aperture kernel ``k``.

    Shape: ``(B, C, h + 2r, w + 2r) -> (B, C, h, w)``.
    """
    c = zp.shape[1]
    weight = k.flip(-1, -2).expand(c, 1, -1, -1)
    # channels-last depthwise convolution is several times faster on CPU for small kernels
    return F.conv2d(zp.contiguous(memory_format=_CL), weight, groups=c)


def fft_conv(
    z: torch.Tensor, spec: KernelSpec, size: int, factor: int, gain: float = 1.0
) -> torch.Tensor:
    """Full linear convolution of ``z`` (zero outside) by FFT with a cached kernel spectrum
    (of the kernel times ``gain``).

    Shape: ``(B, C, h, w) -> (B, C, h + 2r, w + 2r)``.
    """
    k = kernel_tensor(spec, size, factor, str(z.device), z.dtype)
    r = k.shape[-1] // 2
    h, w = z.shape[-2:]
    fh, fw = fast_len(h + 2 * r), fast_len(w + 2 * r)
    spec_k = _spectrum(spec, size, factor, fh, fw, str(z.device), z.dtype, gain)
    return fft_conv_by(z.contiguous(), spec_k, fh, fw, h + 2 * r, w + 2 * r)


def fft_conv_by(
    z: torch.Tensor, spec_k: torch.Tensor, fh: int, fw: int, height: int, width: int
) -> torch.Tensor:
    """Convolution of ``z`` by the kernel whose real FFT at size ``fh x fw`` is ``spec_k``,
    cropped to ``height x width``."""
    spectrum = torch.fft.rfft2(z, s=(fh, fw))
    if tracks_grad(z):
        spectrum = spectrum * spec_k
    else:
        spectrum.mul_(spec_k)
    return torch.fft.irfft2(spectrum, s=(fh, fw))[..., :height, :width]


def pool_grid(
    z: torch.Tensor, factor: int, out: torch.Tensor | None = None, mean: bool = True
) -> torch.Tensor:
    """Mean (or with ``mean=False`` the sum) over ``factor x factor`` cells (a power of 2
    dividing H and W), written into ``out`` when given.

    Sums of strided views: several times faster than ``avg_pool2d`` on CPU.
    """
    if factor == 1:
        return z
    return _pool_from_rows(z[..., 0::2, :] + z[..., 1::2, :], factor, out, mean)


def pool_product(
    x: torch.Tensor,
    mask: torch.Tensor,
    factor: int,
    out: torch.Tensor | None = None,
    mean: bool = True,
) -> torch.Tensor:
    """``pool_grid(mask * x, factor, mean=mean)`` without building ``mask * x`` at full
    resolution: the rows of each cell are multiplied and summed in one step (height and width
    divisible by ``factor``)."""
    rows = x[..., 0::2, :] * mask[..., 0::2, :]
    rows.addcmul_(x[..., 1::2, :], mask[..., 1::2, :])
    return _pool_from_rows(rows, factor, out, mean)


def _pool_from_rows(
    rows: torch.Tensor, factor: int, out: torch.Tensor | None, mean: bool
) -> torch.Tensor:
    """The rest of :func:`pool_grid` once row pairs are summed: column pairs, the mean, and the
    further halvings."""
    if factor == 2 and out is not None:
        torch.add(rows[..., 0::2], rows[..., 1::2], out=out)
        return out.mul_(0.25) if mean else out
    z = rows[..., 0::2] + rows[..., 1::2]
    return pool_grid(z.mul_(0.25) if mean else z, factor // 2, out=out, mean=mean)


def _empty_padded(
    like: torch.Tensor,
    channels: int,
    h: int,
    w: int,
    pads: tuple[int, int, int, int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """A ``(B, channels, h + top + bottom, w + left + right)`` buffer whose padding is zero,
    and a view of its ``h x w`` interior (to be filled by the caller)."""
    top, bottom, left, right = pads
    z = torch.empty(
        like.shape[0],
        channels,
        h + top + bottom,
        w + left + right,
        dtype=like.dtype,
        device=like.device,
    )
    if top:
        z[..., :top, :].zero_()
    if bottom:
        z[..., top + h :, :].zero_()
    if left:
        z[..., top : top + h, :left].zero_()
    if right:
        z[..., top : top + h, left + w :].zero_()
    return z, z[..., top : top + h, left : left + w]


def layer_input(
    x: torch.Tensor,
    coord: torch.Tensor,
    centre: int,
    mask_of,
    box: tuple[int, int, int, int],
    pads: tuple[int, int, int, int],
    grad: bool,
) -> torch.Tensor:
    """The premultiplied layer ``[M, M x]`` inside ``box``, zero-padded by ``pads``
    (top, bottom, left, right); ``M = mask_of(coord, centre, grad)`` (``LayerPlan.mask``).

    Without gradients ``x`` is ``[1, x]`` (a leading channel of ones, see :func:`with_ones`),
    so the layer is one product.

    Shape: ``x (B, C, H, W) -> (B, C + 1, h + top + bottom, w + left + right)``
    (``(B, C, ...)`` for ``[1, x]``).
    """
    y0, y1, x0, x1 = box
    mask = mask_of(coord[..., y0:y1, x0:x1], centre, grad)
    xs = x[..., y0:y1, x0:x1]
    if grad:
        z = torch.cat([mask, mask * xs], dim=1)
        top, bottom, left, right = pads
        return F.pad(z, (left, right, top, bottom)) if any(pads) else z
    z, inner = _empty_padded(x, x.shape[1], y1 - y0, x1 - x0, pads)
    torch.mul(xs, mask, out=inner)
    return z


def layer_input_rows(
    x: torch.Tensor,
    coord: torch.Tensor,
    centre: int,
    mask_of,
    box: tuple[int, int, int, int],
    factor: int,
):
    """The premultiplied layer ``mask * [1, x]`` inside ``box``, summed over ``factor x factor``
    cells, row by row on demand (no-gradient path; ``x`` is ``[1, x]``, the box a whole number
    of cells).

    Returns ``rows(r0, r1, out=None)``: rows ``r0:r1`` of the (pooled) layer, written into
    ``out`` when given. Only the mask (``mask_of(coord, centre, False)``, ``LayerPlan.mask``)
    is computed at once.
    """
    y0, y1, x0, x1 = box
    mask = mask_of(coord[..., y0:y1, x0:x1], centre, False)
    xs = x[..., y0:y1, x0:x1]

    def rows(r0: int, r1: int, out: torch.Tensor | None = None) -> torch.Tensor:
        span = slice(r0 * factor, r1 * factor)
        if factor == 1:
            return torch.mul(xs[..., span, :], mask[..., span, :], out=out)
        return pool_product(xs[..., span, :], mask[..., span, :], factor, out=out, mean=False)

    return rows


def with_ones(x: torch.Tensor) -> torch.Tensor:
    """``[1, x]``: a premultiplied layer is then ``mask * [1, x]`` in one product."""
    out = x.new_empty(x.shape[0], x.shape[1] + 1, *x.shape[2:])
    out[:, :1] = 1
    out[:, 1:] = x
    return out


def direct_pads(
    box: tuple[int, int, int, int], r: int, height: int, width: int
) -> tuple[tuple[int, int, int, int], int, int]:
    """Zero padding around ``box`` for a valid convolution whose output is the box grown by
    ``r``, clipped to the frame. Returns the pads and the output's top-left corner."""
    y0, y1, x0, x1 = box
    oy0, ox0 = max(0, y0 - r), max(0, x0 - r)
    oy1, ox1 = min(height, y1 + r), min(width, x1 + r)
    return (r + y0 - oy0, r + oy1 - y1, r + x0 - ox0, r + ox1 - x1), oy0, ox0


# CPU depthwise convolution in channels-last vectorises over channels: a 5-channel layer fills
# a third of a 16-lane vector. Without gradients, a directly convolved layer is cut into
# horizontal strips stacked along the channel axis, so one convolution fills the lanes.
#: Vector lanes a directly convolved layer's stacked strips fill (``d2f-bench render`` sets
#: it to 1 to time the authors' one-convolution-per-layer way).
LANES = 16


def _strip_count(channels: int, rows: int, r: int, frame_rows: int) -> int:
    """How many strips to stack: each at least ``2 r`` rows (the halo stays at most half the
    input), and all of them fitting in the frame once the rows are rounded up."""
    s = max(1, LANES // channels)
    while s > 1 and (-(-rows // s) < 2 * max(r, 1) or s * -(-rows // s) > frame_rows):
        s -= 1
    return s


#: Rows of a tall matrix that :func:`_transposed` copies at once.
_TRANSPOSE_ROWS = 8192


def _transposed(m: torch.Tensor) -> torch.Tensor:
    """``m.t().contiguous()`` of a tall ``(N, C)`` matrix, by blocks of
    :data:`_TRANSPOSE_ROWS` rows: each block's reads and writes stay in cache. For the
    ``(pixels, 10-16)`` outputs of the stacked convolutions, 2-3x faster than one transpose
    with 2 threads (3.8 against 11.2 ms for 541 thousand rows of 15), 10-20 % with 1."""
    n = m.shape[0]
    if n <= _TRANSPOSE_ROWS:
        return m.t().contiguous()
    out = m.new_empty(m.shape[1], n)
    for i in range(0, n, _TRANSPOSE_ROWS):
        out[:, i : i + _TRANSPOSE_ROWS].copy_(m[i : i + _TRANSPOSE_ROWS].t())
    return out


def direct_stacked(
    rows_of,
    like: torch.Tensor,
    channels: int,
    box: tuple[int, int, int, int],
    k: torch.Tensor,
    frame: tuple[int, int],
) -> tuple[torch.Tensor, int, int]:
    """Depthwise convolution of a layer that is zero outside ``box``, computed over the box
    grown by the kernel radius and clipped to ``frame``, with the layer's strips stacked along
    the channel axis.

    ``rows_of(r0, r1, out=dest)`` writes rows ``r0:r1`` of the layer inside its box into
    ``dest``, ``(B, channels, r1 - r0, box width)`` (see :func:`layer_input_rows`). The output
    rows are rounded up to a whole number of strips, growing into the frame: the extra rows
    hold zeros, which composite as nothing.

    Returns ``(out, oy0, ox0)``: ``out`` is ``(B, channels, strips, rows per strip, width)``
    and covers the frame from ``(oy0, ox0)``.
    """
    height, width = frame
    b = like.shape[0]
    r = k.shape[-1] // 2
    y0, y1, x0, x1 = box
    h, w = y1 - y0, x1 - x0
    oy0, oy1 = max(0, y0 - r), min(height, y1 + r)
    ox0, ox1 = max(0, x0 - r), min(width, x1 + r)
    s = _strip_count(channels, oy1 - oy0, r, height)
    hs = -(-(oy1 - oy0) // s)
    oy1 = min(height, oy0 + s * hs)
    oy0 = oy1 - s * hs
    top, left, right = r + y0 - oy0, r + x0 - ox0, r + ox1 - x1
    rows, wp = hs + 2 * r, ox1 - ox0 + 2 * r
    base = torch.empty(b, rows, wp, s, channels, dtype=like.dtype, device=like.device)
    strips = base.permute(0, 4, 3, 1, 2)  # (B, C, S, rows, wp)
    if left:
        strips[..., :left].zero_()
    if right:
        strips[..., wp - right :].zero_()
    for i in range(s):
        strip = strips[:, :, i, :, left : left + w]
        a = min(max(top - i * hs, 0), rows)
        e = min(max(top + h - i * hs, 0), rows)
        if e <= a:
            strip.zero_()
            continue
        if a:
            strip[..., :a, :].zero_()
        if e < rows:
            strip[..., e:, :].zero_()
        rows_of(i * hs + a - top, i * hs + e - top, out=strip[..., a:e, :])
    stacked = base.view(b, rows, wp, s * channels).permute(0, 3, 1, 2)  # channels-last
    weight = k.flip(-1, -2).expand(s * channels, 1, -1, -1)
    out = F.conv2d(stacked, weight, groups=s * channels).permute(0, 2, 3, 1).contiguous()
    # planar for the blend (elementwise ops on mixed layouts are several times slower): a
    # transpose of the (pixels, s * channels) matrix
    out = _transposed(out.view(-1, s * channels))
    out = out.view(s, channels, b, hs, ox1 - ox0).permute(2, 1, 0, 3, 4)
    return out, oy0, ox0


def blend_stacked(
    acc: torch.Tensor, out: torch.Tensor, oy0: int, ox0: int, transmit: torch.Tensor | None = None
) -> None:
    """Composite a strip-stacked layer ``out`` (from :func:`direct_stacked`) over ``acc`` in
    place; with ``transmit``, also multiply it by ``1 - alpha``."""
    s, hs, wo = out.shape[-3:]
    region = acc[..., oy0 : oy0 + s * hs, ox0 : ox0 + wo].unflatten(2, (s, hs))
    # in the accumulator's (planar) layout: elementwise ops on mixed layouts are several
    # times slower
    alpha = torch.clamp(out[:, :1], 0, 1, out=region.new_empty(region[:, :1].shape))
    # acc (1 - alpha) as acc - acc alpha: one pass
    region.addcmul_(region, alpha, value=-1).add_(out)
    if transmit is not None:
        t = transmit[..., oy0 : oy0 + s * hs, ox0 : ox0 + wo].unflatten(2, (s, hs))
        t.addcmul_(t, alpha, value=-1)


# Layer-coordinate bins per layer in the support histograms (:func:`support_boxes`).
_BINS = 4


def support_boxes(plan: LayerPlan, height: int, width: int) -> dict[int, tuple[int, int, int, int]]:
    """Bounding box (y0, y1, x0, x1) of each layer's mask support, on an 8-px tile grid, for
    the plan of one image (``render`` plans a batch image by image).

    A layer reaches a pixel whose layer coordinate is within the mask's reach of it, on its
    side of focus. Two histograms of the coordinate (bins a quarter of a layer wide), one per
    row of tiles and one per column of tiles, answer for every layer at once: the box spans
    the rows and the columns of tiles holding a pixel the layer reaches (or one up to a
    quarter layer farther). A tile across a depth edge thus counts only for the layers its
    pixels are in, not for every layer between the two sides of the edge, and a layer no
    pixel is near is skipped.
    """
    coord = plan.coord.detach().reshape(height, width)
    dev = coord.device
    down, across = -(-height // TILE), -(-width // TILE)
    reach = plan.reach
    centres = np.array([centre for centre, _ in plan.order], dtype=np.float64)
    # Bin b > 0 holds coordinates in ((b - 1) / _BINS, b / _BINS], b < 0 in [b / _BINS,
    # (b + 1) / _BINS), and bin 0 holds 0 alone: an in-focus pixel is on neither side.
    low = math.floor(_BINS * (centres.min() - reach))
    high = math.ceil(_BINS * (centres.max() + reach))
    nbins = high - low + 1
    # the indices in floating point (float32 holds whole numbers exactly up to 2**24), cast
    # once for the counts
    dtype = coord.dtype if nbins * max(down, across) < 1 << 24 else torch.float64
    scaled = coord.to(dtype).mul(_BINS)
    bins = scaled.abs().ceil_().copysign_(scaled).clamp_(low, high).sub_(low)
    row = torch.arange(height, device=dev, dtype=dtype).div_(TILE).floor_().view(-1, 1)
    col = torch.arange(width, device=dev, dtype=dtype).div_(TILE).floor_().view(1, -1)
    index = torch.add(row, bins, alpha=down).long().view(-1)
    per_row = torch.bincount(index, minlength=nbins * down)
    index = torch.add(col, bins, alpha=across).long().view(-1)
    per_col = torch.bincount(index, minlength=nbins * across)
    # window[j, b]: bin b holds coordinates within reach of layer j, on its side of focus
    b = np.arange(low, high + 1)
    lo = np.where(b > 0, b - 1, np.where(b < 0, b, 0)) / _BINS
    hi = np.where(b > 0, b, np.where(b < 0, b + 1, 0)) / _BINS
    c = centres[:, None]
    window = (lo < c + reach) & (hi > c - reach)
    if plan.signed:
        window &= ((c > 0) & (b > 0)) | ((c < 0) & (b < 0)) | (c == 0)
    window = window.astype(np.int64)
    rows_hit = window @ per_row.view(nbins, down).cpu().numpy() > 0  # [L, tile rows]
    cols_hit = window @ per_col.view(nbins, across).cpu().numpy() > 0  # [L, tile columns]
    boxes = {}
    for (centre, _), rows, cols in zip(plan.order, rows_hit, cols_hit):
        if not rows.any():
            continue
        rows, cols = np.flatnonzero(rows), np.flatnonzero(cols)
        boxes[centre] = (
            int(rows[0]) * TILE,
            min(height, (int(rows[-1]) + 1) * TILE),
            int(cols[0]) * TILE,
            min(width, (int(cols[-1]) + 1) * TILE),
        )
    return boxes


def grid_factor(size: int, quality: str) -> int:
    """Grid (px of the frame per cell) a kernel of ``size`` px is applied on with the
    ``quality`` preset (1: full resolution)."""
    preset = QUALITY_PRESETS[quality]
    if preset.quarter is not None and size >= preset.quarter:
        factor = 4
        while factor < MAX_FACTOR and size >= preset.quarter * factor // 2:
            factor *= 2
        return factor
    if preset.half is not None and size >= preset.half:
        return 2
    return 1


# --------------------------------------------------------------------------------------


def upsample_grid(z: torch.Tensor, factor: int, height: int, width: int) -> torch.Tensor:
    """Bilinear upsampling of a coarse-grid layer by ``factor`` (``F.interpolate``'s
    ``align_corners=False``, edges held), cropped to the frame.

    Without gradients and by 2 or 4, one interpolation per output phase and axis: 5-15 %
    faster than ``F.interpolate`` at slider sizes on this CPU (torch 2.13), which is
    1.5-2x faster by 8 and 16.
    """
    if factor > 4 or tracks_grad(z):
        up = F.interpolate(z, scale_factor=factor, mode="bilinear", align_corners=False)
    else:
        up = upsample_axis(upsample_axis(z, factor, -2), factor, -1)
    return up[..., :height, :width]


def upsample_axis(a: torch.Tensor, factor: int, dim: int) -> torch.Tensor:
    n = a.shape[dim]
    shape = list(a.shape)
    shape[dim] = n * factor
    out = a.new_empty(shape)
    phases = out.unflatten(dim, (n, factor))
    for p in range(factor):
        # output sample p of each cell lies ``offset`` input samples from the cell's centre
        offset = (p + 0.5) / factor - 0.5
        phase = phases.select(dim, p)  # dim < 0: the phase axis after unflatten
        if offset < 0:  # between the sample and the one before it; the first is held
            src, nbr, edge = a.narrow(dim, 1, n - 1), a.narrow(dim, 0, n - 1), 0
            dst = phase.narrow(dim, 1, n - 1)
        else:  # between the sample and the one after it; the last is held
            src, nbr, edge = a.narrow(dim, 0, n - 1), a.narrow(dim, 1, n - 1), n - 1
            dst = phase.narrow(dim, 0, n - 1)
        torch.lerp(src, nbr, abs(offset), out=dst)
        phase.narrow(dim, edge, 1).copy_(a.narrow(dim, edge, 1))
    return out


def column_spans(columns: list[int], gap: int = 2) -> list[tuple[int, int]]:
    """Sorted tile columns as inclusive spans, merged across gaps under ``gap`` tiles:
    [1, 2, 5, 9] -> [(1, 5), (9, 9)] with ``gap=3``."""
    spans: list[list[int]] = []
    for c in columns:
        if spans and c - spans[-1][1] <= gap:
            spans[-1][1] = c
        else:
            spans.append([c, c])
    return [(a, b) for a, b in spans]
