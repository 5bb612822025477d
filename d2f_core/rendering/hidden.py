"""The hidden surface: what lies behind the rim of a blurred near object, drawn under it in
the depth order (the fix of the paper's |defocus| ordering); it enters the same compositing
``acc = acc (1 - K_l M_l) + K_l (M_l X)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .blur import MAX_FACTOR, column_spans, upsample_axis, upsample_grid
from .inputs import tracks_grad
from .plan import LayerPlan

# what lies behind a blurred near edge
# --------------------------------------------------------------------------------------

# A depth edge is a jump of at least this many layers within 2 px; the hidden surface is drawn
# only where the pixel is at least this much nearer than it (its masks then barely overlap
# the pixel's own).
_HIDDEN_JUMP = 2.5
# Near sides whose kernel is at most this many px are opaque: nothing is seen past them.
_HIDDEN_MIN_SIZE = 3


@dataclass
class HiddenSurface:
    """What a lens sees behind the rim of a blurred near object, which the photo does not
    show: the far side of each depth edge continued under the near side, within the near
    side's CoC radius of the edge (:func:`hidden_surface`). It is composited under every
    layer: what the layers in front leave of it shows, and where they are opaque it does not
    matter.

    ``x`` ``(B, C, h, w)`` is its ``[1, x]`` content premultiplied by its coverage, on a grid
    of ``grid`` px whose first cell starts at frame pixel ``origin`` (a multiple of
    :data:`MAX_FACTOR`); ``box`` bounds it in the frame.
    """

    box: tuple[int, int, int, int]
    origin: tuple[int, int]
    grid: int
    x: torch.Tensor

    def window(self, y0: int, y1: int, x0: int, x1: int) -> torch.Tensor:
        """The surface on frame rows ``y0:y1`` and columns ``x0:x1`` (inside :attr:`box`),
        bilinearly upsampled, ``(B, C, y1 - y0, x1 - x0)``."""
        oy, ox = self.origin
        return upsample_window(self.x, self.grid, y0 - oy, y1 - oy, x0 - ox, x1 - ox)

    def spans(self, y0: int, y1: int) -> list[tuple[int, int]]:
        """Column ranges ``(x0, x1)`` (px, inside :attr:`box`) outside which the surface is 0
        on frame rows ``y0:y1`` (inside :attr:`box`): the cells it is drawn on, one cell
        wider each side (the bilinear upsampling reaches that far)."""
        oy, ox = self.origin
        g = self.grid
        a, b = max(0, (y0 - oy) // g - 1), (y1 - 1 - oy) // g + 2
        drawn = self.x[0, 0, a:b].detach().ne(0).any(dim=0)
        cols = torch.nonzero(drawn).flatten().tolist()
        out = []
        for c0, c1 in column_spans(cols, gap=3):
            x0 = max(self.box[2], ox + (c0 - 1) * g)
            x1 = min(self.box[3], ox + (c1 + 2) * g)
            if x0 < x1:
                out.append((x0, x1))
        return out

    def composite(self, acc: torch.Tensor, y0: int, y1: int, top: int = 0) -> None:
        """In place, without gradients: ``acc + (1 - alpha) * surface`` on frame rows
        ``y0:y1`` (inside :attr:`box`), where ``acc`` ``(C, rows, W)`` holds frame rows from
        ``top``, alpha first; only the columns where the surface is drawn."""
        for x0, x1 in self.spans(y0, y1):
            region = acc[:, y0 - top : y1 - top, x0:x1]
            left = 1 - region[:1].clamp(0, 1)
            region.addcmul_(self.window(y0, y1, x0, x1)[0], left)


def input_pixels(
    x: torch.Tensor, grad: bool
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """``[1, x]`` at frame pixels ``(ys, xs)`` as ``(C, n)``, from the renderer's layer input
    ``x`` ``(1, C, H, W)`` (which carries the channel of ones without gradients, and not with
    them)."""

    def pixels(ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        part = x[0][:, ys, xs]
        if not grad:
            return part
        return torch.cat([torch.ones_like(part[:1]), part])

    return pixels


def under_hidden(acc: torch.Tensor, hidden: HiddenSurface, grad: bool) -> torch.Tensor:
    """Composite ``hidden`` under the accumulator ``acc`` (alpha first):
    ``acc + (1 - alpha) * hidden`` over its box (in place without gradients). The hidden
    surface's gradient flows into the colours and layer coordinates it is made of (not
    into where it is drawn)."""
    y0, y1, x0, x1 = hidden.box
    if not grad:
        for i in range(acc.shape[0]):
            hidden.composite(acc[i], y0, y1)
        return acc
    part = hidden.window(y0, y1, x0, x1)
    region = acc[..., y0:y1, x0:x1]
    left = 1 - region[:, :1].clamp(0, 1)
    acc = acc.clone()
    acc[..., y0:y1, x0:x1] = region + part * left
    return acc


def upsample_window(grid: torch.Tensor, factor: int, y0: int, y1: int, x0: int, x1: int):
    """Rows ``y0:y1`` and columns ``x0:x1`` (px) of the bilinear upsampling of ``grid``
    ``(B, C, gh, gw)`` by ``factor`` (:func:`upsample_grid`): only the cells they read."""
    gh, gw = grid.shape[-2:]
    a, b = max(0, y0 // factor - 1), min(gh, -(-y1 // factor) + 1)
    c, d = max(0, x0 // factor - 1), min(gw, -(-x1 // factor) + 1)
    if factor <= 4 and not tracks_grad(grid):
        # the rows cut before the columns are interpolated: less work, and a contiguous
        # result when every column is kept
        rows = upsample_axis(grid[..., a:b, c:d], factor, -2)
        rows = rows[..., y0 - a * factor : y1 - a * factor, :]
        return upsample_axis(rows, factor, -1)[..., x0 - c * factor : x1 - c * factor]
    up = upsample_grid(grid[..., a:b, c:d], factor, (b - a) * factor, (d - c) * factor)
    return up[..., y0 - a * factor : y1 - a * factor, x0 - c * factor : x1 - c * factor]


def _window_max(t: torch.Tensor, size: int, dim: int, op=torch.maximum) -> torch.Tensor:
    """Running maximum (with ``op=torch.minimum`` minimum) over ``size`` samples centred on
    each (``size`` odd), along ``dim``, the edge values held: ``log2(size)`` elementwise
    maxima by window doubling."""
    n = t.shape[dim]
    r = size // 2
    if r == 0 or n == 0:
        return t
    first, last = t.narrow(dim, 0, 1), t.narrow(dim, n - 1, 1)
    pad = torch.cat([first.repeat_interleave(r, dim), t, last.repeat_interleave(r, dim)], dim)
    m, span = pad, 1  # m[i]: the maximum of pad[i : i + span]
    while 2 * span <= size:
        k = m.shape[dim] - span
        m = op(m.narrow(dim, 0, k), m.narrow(dim, span, k))
        span *= 2
    # a window of `size` is two overlapping windows of `span`
    return op(m.narrow(dim, 0, n), m.narrow(dim, size - span, n))


def _max_filter(t: torch.Tensor, size: int, op=torch.maximum) -> torch.Tensor:
    """Maximum (``op=torch.minimum``: minimum) over the ``size x size`` square centred on
    each pixel (edges held)."""
    return _window_max(_window_max(t, size, -2, op), size, -1, op)


def _cell_max(t: torch.Tensor, g: int) -> torch.Tensor:
    """Maximum over cells of ``g x g`` px, a partial last row or column of cells over what
    it holds: ``F.max_pool2d(t, g, ceil_mode=True)``, as two strided maxima (5-10x faster on
    CPU than the pooling kernel for small cells)."""
    if g == 1:
        return t
    ph, pw = -t.shape[-2] % g, -t.shape[-1] % g
    if ph or pw:
        t = F.pad(t, (0, pw, 0, ph), value=-math.inf)
    h, w = t.shape[-2:]
    lead = t.shape[:-2]
    rows = t.reshape(*lead, h // g, g, w).amax(dim=-2)
    return rows.reshape(*lead, h // g, w // g, g).amax(dim=-1)


def _push_pull(values: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fill ``values`` where ``weight`` is 0 from where it is not, by push-pull over an image
    pyramid: each level holds the weighted mean of its 2x2 cells, and a cell's value is
    blended with the bilinear upsampling of the level above by one minus its weight (up to 1).

    Shape: ``values (B, C, H, W)``, ``weight (B, 1, H, W)`` >= 0 -> ``(B, C, H, W)``.
    """
    levels = []
    v, w = values * weight, weight
    while True:
        levels.append((v, w))
        if v.shape[-2] <= 1 and v.shape[-1] <= 1:
            break
        # sums over 2x2 cells (the last row or column alone when odd)
        v = F.avg_pool2d(v, 2, ceil_mode=True, divisor_override=1)
        w = F.avg_pool2d(w, 2, ceil_mode=True, divisor_override=1)
    v, w = levels[-1]
    filled = v / w.clamp(min=1e-12)
    for v, w in reversed(levels[:-1]):
        up = upsample_grid(filled, 2, *v.shape[-2:])
        own = v / w.clamp(min=1e-12)
        filled = up.lerp_(own, w.clamp(max=1))
    return filled


# Rows of the frame the hidden surface's full-resolution passes work on at once.
_HIDDEN_ROWS = 256


def hidden_surface(
    pixels: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    plan: LayerPlan,
    jump: float = _HIDDEN_JUMP,
) -> HiddenSurface | None:
    """The surface behind the rims of blurred near objects, for the depth order's plan
    ``plan`` of one image; ``None`` when no blurred near side meets a depth edge (or for a
    batch: :func:`render` plans image by image). ``pixels(ys, xs)`` gives the frame's
    ``[1, x]`` (ones, the weighted colour, the weights) at the frame pixels ``(ys, xs)`` as
    ``(C, n)``: only the few pixels along the edges are read.

    At a depth edge (a jump of at least ``jump`` layers within 2 px) the photo shows only the
    near side, but where the near side is blurred a lens sees past its rim, up to its CoC
    radius inside it, to what lies behind: the far side, continued under the near one. The
    far-side pixels along each edge are the known pixels; their colour and layer coordinate
    are carried under the near side by push-pull (:func:`_push_pull`) on a grid of 2, 4 or
    8 px as that radius grows (the fill is smooth), and drawn where a cell is within the
    largest blurred near side's CoC radius of an edge and holds a pixel at least ``jump``
    layers nearer than what is carried under it.
    The full-resolution passes run by bands of rows, in bounded memory.
    """
    coord = plan.coord.detach()  # where it is drawn: no gradient
    if coord.shape[0] != 1 or coord.numel() == 0:
        return None
    height, width = coord.shape[-2:]
    cell, step = 4, _HIDDEN_ROWS
    # near sides of edges, marked on the cell grid, and the largest |coord| among them
    grid = coord.new_zeros(1, 1, -(-height // cell), -(-width // cell))
    top = -1.0
    for y0 in range(0, height, step):
        y1 = min(height, y0 + step)
        a, b = max(0, y0 - 2), min(height, y1 + 2)
        c = coord[..., a:b, :]
        near = (c - _max_filter(c, 5, torch.minimum))[..., y0 - a : y1 - a, :] >= jump
        ahead = c[..., y0 - a : y1 - a, :][near]
        if not ahead.numel():
            continue
        # the layer that draws each near pixel: of the two either side of its coordinate, the
        # more blurred one in front of the focal plane (ceil) and the sharper one behind it
        # (floor of |coord|; a CoC on a kernel size sits half-way between two layers:
        # rounding would go either way), or with the blend masks (which draw a pixel with
        # both) the more blurred one on both sides; the largest of them, from the extremes
        most, least = float(ahead.max()), float(ahead.min())
        if most > 0:
            top = max(top, math.ceil(most))
        if least <= 0:
            top = max(top, math.ceil(-least) if plan.blend else math.floor(-least))
        cells = _cell_max(near.to(coord.dtype), cell)
        grid[..., y0 // cell : y0 // cell + cells.shape[-2], :] = cells
    if top < 0:
        return None
    # kernel sizes grow with |coord| on both sides: the near side's radius
    sizes = {abs(centre): size for centre, size in plan.order}
    radius = sizes[min(int(top), max(sizes))] // 2
    if 2 * radius + 1 < _HIDDEN_MIN_SIZE:
        return None
    band = _max_filter(grid, 2 * (-(-radius // cell)) + 1)
    rows = torch.nonzero(band.amax(dim=(0, 1, 3)) > 0).flatten()
    cols = torch.nonzero(band.amax(dim=(0, 1, 2)) > 0).flatten()
    y0, y1 = int(rows[0]) * cell, min(height, (int(rows[-1]) + 1) * cell)
    x0, x1 = int(cols[0]) * cell, min(width, (int(cols[-1]) + 1) * cell)
    # the known pixels: the far side of each edge, from a margin around the band, summed
    # into cells of `g` px by bands of rows; a blur of that radius smooths what is seen past
    # it, so the cells grow with it
    g = 2 if radius < 16 else 4 if radius < 32 else 8
    m = 2 + radius
    py0, px0 = max(0, y0 - m) // MAX_FACTOR * MAX_FACTOR, max(0, x0 - m) // MAX_FACTOR * MAX_FACTOR
    py1, px1 = min(height, y1 + m), min(width, x1 + m)
    hh, hw = -(-(py1 - py0) // g), -(-(px1 - px0) // g)
    sums = known = None
    nearest = coord.new_zeros(1, 1, hh, hw)
    for r0 in range(py0, py1, step):
        r1 = min(py1, r0 + step)
        a, b = max(0, r0 - 2), min(height, r1 + 2)
        c = coord[..., a:b, px0:px1]
        carried = plan.coord[..., r0:r1, px0:px1]
        # each cell's nearest pixel: the hidden surface is drawn under the cells that hold a
        # near side
        top_c = _cell_max(carried, g)
        nearest[..., (r0 - py0) // g : (r0 - py0) // g + top_c.shape[-2], :] = top_c
        # the far-side pixels (few: along the edges), summed into their cells
        far = torch.nonzero((_max_filter(c, 5) - c)[0, 0, r0 - a : r1 - a] >= jump)
        if not far.numel():
            continue
        ys, xs = far[:, 0], far[:, 1]
        values = pixels(ys + r0, xs + px0)
        values = torch.cat([values, carried[0][:, ys, xs]])  # (C + 1, pixels)
        index = ((r0 - py0) // g + ys // g) * hw + xs // g
        if sums is None:
            sums = values.new_zeros(values.shape[0], hh * hw)
            known = coord.new_zeros(hh * hw)
        sums.index_add_(1, index, values)
        known.index_add_(0, index, torch.ones_like(index, dtype=known.dtype))
    if sums is None:
        return None
    sums, known = sums.view(1, -1, hh, hw), known.view(1, 1, hh, hw)
    fill = _push_pull(sums / known.clamp(min=1e-12), known)
    # drawn where the cell holds a pixel well in front of what is carried under it (fading
    # in over a layer), within reach of an edge
    if g > cell:
        band = _cell_max(band, g // cell)
    elif g < cell:
        band = band.repeat_interleave(cell // g, -2).repeat_interleave(cell // g, -1)
    band = band[..., py0 // g : py0 // g + hh, px0 // g : px0 // g + hw]
    band = F.pad(band, (0, hw - band.shape[-1], 0, hh - band.shape[-2]))
    weight = (nearest - fill[:, -1:]).sub_(jump - 1).clamp_(0, 1).mul_(band)
    if not bool(weight.any()):
        return None
    return HiddenSurface((py0, py1, px0, px1), (py0, px0), g, fill[:, :-1] * weight)


# --------------------------------------------------------------------------------------
