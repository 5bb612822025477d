"""The tiled path: D2F step 5 (``f_l(R I, D) / f_l(R, D)``) on frames of 1.4 MP and more
without gradients, by tiles and row bands in bounded memory.
"""

from __future__ import annotations

import functools
import math

import torch

from .blur import (
    DIRECT_MAX_SIZE,
    MAX_FACTOR,
    KernelSpec,
    blend_stacked,
    column_spans,
    direct_stacked,
    fast_len,
    fft_conv,
    fft_conv_by,
    grid_factor,
    kernel_tensor,
    pool_product,
    upsample_grid,
)
from .composite import blend_part, overlap_slices
from .hidden import hidden_surface, upsample_window
from .inputs import ROW_BAND
from .plan import FAR, LayerPlan
from .threads import ThreadChoice

# large frames: tiles and bands
# --------------------------------------------------------------------------------------

# Tile side (px) of the tiled path: a multiple of MAX_FACTOR.
_TT = 32
# Pixels per band of the full-resolution passes.
_BAND_PIXELS = 1_000_000


class _TileSource:
    """The ``tile x tile`` tiles of a ``(C, H, W)`` frame whose sides need not be whole
    tiles, for their extremes, without a padded copy of it: tiles inside the frame are read
    from it, the partial tiles of the last row and column from two small copies padded with
    ``fill``."""

    def __init__(self, x: torch.Tensor, tile: int, fill: float) -> None:
        c, h, w = x.shape
        self.tile, self.c = tile, c
        self.fy, self.fx = h // tile, w // tile  # whole tiles down and across
        self.ny, self.nx = -(-h // tile), -(-w // tile)
        body = x[:, : self.fy * tile, : self.fx * tile]
        self.body = body.unflatten(2, (self.fx, tile)).unflatten(1, (self.fy, tile))
        self.body = self.body.permute(1, 3, 0, 2, 4)  # (fy, fx, C, t, t)
        self.bottom = self.right = None
        self._pads: list[tuple[torch.Tensor, slice, slice]] = []
        if self.fy < self.ny:  # the last row of tiles, corner included
            b = x.new_empty(c, tile, self.nx * tile)
            b[:, : h - self.fy * tile, :w] = x[:, self.fy * tile :]
            self._pads += [
                (b, slice(h - self.fy * tile, None), slice(None)),
                (b, slice(None), slice(w, None)),
            ]
            self.bottom = b.view(c, tile, self.nx, tile).permute(2, 0, 1, 3)  # (nx, C, t, t)
        if self.fx < self.nx:  # the last column of tiles above that row
            r = x.new_empty(c, self.fy * tile, tile)
            r[:, :, : w - self.fx * tile] = x[:, : self.fy * tile, self.fx * tile :]
            self._pads.append((r, slice(None), slice(w - self.fx * tile, None)))
            self.right = r.view(c, self.fy, tile, tile).permute(1, 0, 2, 3)  # (fy, C, t, t)
        self.refill(fill)

    def refill(self, fill: float) -> None:
        """Set the padding past the frame to ``fill``."""
        for buf, rows, cols in self._pads:
            buf[:, rows, cols] = fill

    def extreme(self, op) -> torch.Tensor:
        """``op`` (``torch.amin`` or ``torch.amax``) over each tile and channel, padding
        included, ``(ny, nx)``."""
        out = self.body.new_empty(self.ny, self.nx)
        out[: self.fy, : self.fx] = op(self.body, dim=(2, 3, 4))
        if self.bottom is not None:
            out[self.fy] = op(self.bottom, dim=(1, 2, 3))
        if self.right is not None:
            out[: self.fy, self.fx] = op(self.right, dim=(1, 2, 3))
        return out


def _fill_layer(image, weights, ys, xs, m: torch.Tensor, out: torch.Tensor) -> None:
    """The layer ``[m, m w I, m w]`` (``[m, m I]`` when ``weights`` is None) of mask ``m`` at
    frame rows ``ys`` and columns ``xs`` (slices, or index tensors for single pixels) of
    ``image`` ``(1, 3, H, W)`` and ``weights`` ``(1, Cw, H, W)``, written into ``out``
    ``(chans, ...)``."""
    out[0] = m
    if weights is None:
        torch.mul(image[0, :, ys, xs], m, out=out[1:])
    else:
        torch.mul(weights[0, :, ys, xs], m, out=out[4:])
        torch.mul(image[0, :, ys, xs], out[4:5], out=out[1:4])


def _tile_mask(ct: torch.Tensor, centre: int, mask_of, gate: int) -> torch.Tensor:
    """Mask of layer ``centre`` for coordinates ``ct`` (``mask_of``: ``LayerPlan.mask``; in
    place on a copy), zero on the other side of focus when ``gate`` (+1 or -1) is set."""
    m = mask_of(ct, centre, False)
    if gate > 0:
        m.masked_fill_(ct <= 0, 0.0)
    elif gate < 0:
        m.masked_fill_(ct >= 0, 0.0)
    return m


#: A 2x2 cell whose layer coordinates span more than this many layers is masked pixel by
#: pixel (see :class:`_HalfSource`).
_MIXED_RANGE = 0.1
#: Which tiles a layer takes: from the bins of the coordinates each tile holds
#: (:func:`_tile_bins`), or with ``False`` from the tiles' coordinate ranges alone (which
#: put a tile across a depth edge in every layer between its two sides).
_EXACT_HITS = True


#: Bins of the layer coordinate per layer in :func:`_tile_bins`.
_TILE_BINS = 4
#: Rows of tiles :func:`_tile_bins` counts at once.
_TILE_BIN_ROWS = 4


def _tile_bins(
    coord: torch.Tensor, tile: int, ny: int, nx: int, extremes: tuple[float, float] | None = None
):
    """Which bins of the layer coordinate each ``tile x tile`` tile of ``coord (H, W)``
    holds a pixel in: ``(ny * nx, bins)`` (0 or 1), and each bin's lowest and highest
    coordinate. Bins are 1 / :data:`_TILE_BINS` of a layer wide, split at 0 with 0 a bin of
    its own, so a bin's pixels are all on one side of focus (or at it). ``extremes``: the
    coordinate's lowest and highest value when the caller has them."""
    height, width = coord.shape
    q = _TILE_BINS
    low, high = (float(coord.min()), float(coord.max())) if extremes is None else extremes
    top = int(math.ceil(max(abs(low), abs(high)) * q))
    nb = 2 * top + 1
    j = torch.arange(-top, top + 1, dtype=coord.dtype, device=coord.device)
    lower = torch.where(j > 0, (j - 1) / q, j / q)
    upper = torch.where(j < 0, (j + 1) / q, j / q)
    rows = tile * _TILE_BIN_ROWS
    cols = torch.arange(width, device=coord.device) // tile
    base = ((torch.arange(rows, device=coord.device) // tile)[:, None] * nx + cols) * nb + top
    if ny * nx * nb < 1 << 31:
        base = base.int()  # half the memory traffic of int64 indices
    present = coord.new_zeros(ny * nx * nb)
    for y0 in range(0, height, rows):
        y1 = min(height, y0 + rows)
        band = coord[y0:y1]
        b = band.abs().mul_(q).ceil_().copysign_(band).to(base.dtype).add_(base[: y1 - y0])
        counts = torch.bincount(b.view(-1), minlength=-(-(y1 - y0) // tile) * nx * nb)
        t0 = y0 // tile * nx * nb
        present[t0 : t0 + counts.numel()] = (counts > 0).to(coord.dtype)
    return present.view(ny * nx, nb), lower, upper


class _HalfSource:
    """The layer input ``[1, w I, w]`` (or ``[1, I]``) and the layer coordinate of the frame
    padded to ``hp x wp``, averaged over cells of 2x2 px, for the coarse layers to be masked
    on: ``x (chans, hp/2, wp/2)``, ``c (hp/2, wp/2)``.

    Past the frame the input is 0 and the coordinate is so far that no mask reaches it; a
    cell that the frame's last odd row or column cuts takes the coordinate of its pixels
    inside and their input over 4. A cell whose four coordinates span more than
    :data:`_MIXED_RANGE` layers (a depth edge), or with ``signed`` lie on both sides of the
    focal plane's gate, is 0 here: its pixels are kept one by one
    (``pc (n, 4)``, ``px (chans, n, 4)``) and masked as they are by :meth:`add_mixed`."""

    def __init__(
        self, image, weights, coord, hp: int, wp: int, chans: int, signed: bool = True
    ) -> None:
        _, _, height, width = image.shape
        self.x = image.new_zeros(chans, hp // 2, wp // 2)
        self.c = coord.new_full((hp // 2, wp // 2), FAR)
        gw = -(-width // 2)
        rows = max(2, (ROW_BAND // max(width, 1)) // 2 * 2)
        pc, px, cy, cx = [], [], [], []
        buf = cbuf = None
        one = image.new_ones(())  # the layer of mask one
        for y0 in range(0, height, rows):
            y1 = min(height, y0 + rows)
            n = y1 - y0
            ne = n + n % 2
            if buf is None or buf.shape[1] != ne:
                buf = image.new_zeros(chans, ne, 2 * gw)
                cbuf = coord.new_empty(ne, 2 * gw)
            _fill_layer(image, weights, slice(y0, y1), slice(None), one, buf[:, :n, :width])
            cbuf[:n, :width] = coord[0, y0:y1]
            if width % 2:  # the cut cells: their pixels inside stand for the rest
                cbuf[:n, width] = cbuf[:n, width - 1]
            if n % 2:
                cbuf[n] = cbuf[n - 1]
                buf[:, n] = 0.0  # past the frame (the buffer may hold an earlier band)
            quads = [cbuf[i::2, j::2] for i in (0, 1) for j in (0, 1)]
            r0 = y0 // 2
            out_c = self.c[r0 : r0 + ne // 2, :gw]
            torch.add(quads[0], quads[1], out=out_c)
            out_c.add_(quads[2]).add_(quads[3]).mul_(0.25)
            out_x = self.x[:, r0 : r0 + ne // 2, :gw]
            torch.add(buf[:, 0::2, 0::2], buf[:, 0::2, 1::2], out=out_x)
            out_x.add_(buf[:, 1::2, 0::2]).add_(buf[:, 1::2, 1::2]).mul_(0.25)
            high = torch.maximum(torch.maximum(quads[0], quads[1]), torch.maximum(*quads[2:]))
            low = torch.minimum(torch.minimum(quads[0], quads[1]), torch.minimum(*quads[2:]))
            mixed = high - low > _MIXED_RANGE
            if signed:
                # a cell with pixels on both sides of the focal plane's gate (0 belongs to
                # neither side's layers but 0's): its mean would put all of it on one side
                mixed |= ((low <= 0) & (high > 0)) | ((low < 0) & (high >= 0))
            mixed = torch.nonzero(mixed)
            if mixed.numel():
                yy, xx = mixed[:, 0], mixed[:, 1]
                pc.append(torch.stack([q[yy, xx] for q in quads], dim=-1))
                px.append(
                    torch.stack([buf[:, i::2, j::2][:, yy, xx] for i in (0, 1) for j in (0, 1)], -1)
                )
                cy.append(yy + r0)
                cx.append(xx)
                out_x[:, yy, xx] = 0.0
        self.n = sum(len(p) for p in pc)
        if self.n:
            self.pc, self.px = torch.cat(pc), torch.cat(px, dim=1)
            self.cy, self.cx = torch.cat(cy), torch.cat(cx)

    def add_mixed(self, grid, centre, mask_of, gate, hit, box, factor):
        """Add the mixed cells of the hit tiles (``hit``, tiles of :data:`_TT` px) to the
        summed cells of ``grid`` ``(chans, h, w)``, whose cells of ``factor`` px start at
        frame px ``box = (y0, x0)``."""
        if not self.n:
            return
        t = _TT
        tile = (self.cy * 2 // t) * hit.shape[1] + self.cx * 2 // t
        idx = torch.nonzero(hit.flatten()[tile]).flatten()
        if not idx.numel():
            return
        m = _tile_mask(self.pc[idx], centre, mask_of, gate)
        part = (self.px[:, idx] * m).sum(-1).mul_(0.25).to(grid.dtype)
        gy = (self.cy[idx] * 2 - box[0]) // factor
        gx = (self.cx[idx] * 2 - box[1]) // factor
        grid.view(grid.shape[0], -1).index_add_(1, gy * grid.shape[2] + gx, part)


def _upsample_rows(grid: torch.Tensor, factor: int, y0: int, y1: int, width: int):
    """Rows ``y0:y1`` (frame px) of the bilinear upsampling of the coarse ``grid``
    ``(C, gh, gw)`` by ``factor``, columns ``:width``: only the cells those rows read."""
    if factor == 1:
        return grid[:, y0:y1, :width]
    return upsample_window(grid[None], factor, y0, y1, 0, width)[0]


def _blend_fft(
    acc: torch.Tensor,
    grid: torch.Tensor,
    spec: KernelSpec,
    size: int,
    factor: int,
    y0: int,
    x0: int,
    transmit: torch.Tensor | None = None,
    pieces: list[tuple[int, int, int, int]] | None = None,
    *,
    cells: int,
) -> None:
    """:func:`blend_part` (and with ``transmit`` :func:`_blend_transmit`) in place of the
    coarse layer ``grid`` ``(C, h, w)`` (each cell the sum of ``cells**2`` cell means)
    blurred by :func:`fft_conv`, one channel at a time: a spectrum and a blurred channel at a
    time, not all of them, are held.

    With ``pieces`` (boxes ``(y0, y1, x0, x1)`` in cells outside which ``grid`` is 0), each
    piece is blurred by its own FFT and the blurs are summed (the blur is linear): a layer
    scattered over the frame is transformed over its pieces, not over their bounding box."""
    gain = 1.0 / cells**2
    if pieces is None:

        def blur(z: torch.Tensor) -> torch.Tensor:
            return fft_conv(z, spec, size, factor, gain)

    else:
        blur = _PieceBlur(pieces, spec, size, factor, gain)
    alpha = blur(grid[None, :1])
    meet = overlap_slices(acc.shape[-2:], y0, x0, alpha.shape[-2:])
    if meet is None:
        return
    (rows, cols), (frows, fcols) = meet
    alpha = alpha[..., rows, cols]
    clamped = alpha.clamp(0, 1)
    for c in range(grid.shape[0]):
        part = alpha if c == 0 else blur(grid[None, c : c + 1])
        region = acc[:, c : c + 1, frows, fcols]
        # acc (1 - alpha) as acc - acc alpha: one pass
        region.addcmul_(region, clamped, value=-1).add_(part if c == 0 else part[..., rows, cols])
    if transmit is not None:
        region = transmit[..., frows, fcols]
        region.addcmul_(region, clamped, value=-1)


class _PieceBlur:
    """:func:`fft_conv` of a ``(1, 1, h, w)`` layer that is 0 outside ``pieces`` (boxes in cells),
    as the sum of the pieces' own FFT blurs; each piece's kernel spectrum is made once, for
    every channel (not in :func:`_spectrum`'s cache: piece sizes vary)."""

    def __init__(self, pieces, spec: KernelSpec, size: int, factor: int, gain: float) -> None:
        self.pieces = pieces
        self.args = (spec, size, factor, gain)
        self.spectra: dict[tuple[int, int], torch.Tensor] = {}

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        spec, size, factor, gain = self.args
        k = kernel_tensor(spec, size, factor, str(z.device), z.dtype, gain)
        r = k.shape[-1] // 2
        h, w = z.shape[-2:]
        out = z.new_zeros(*z.shape[:-2], h + 2 * r, w + 2 * r)
        for a, b, c, d in self.pieces:
            ph, pw = b - a + 2 * r, d - c + 2 * r
            fh, fw = fast_len(ph), fast_len(pw)
            if (fh, fw) not in self.spectra:
                self.spectra[(fh, fw)] = torch.fft.rfft2(k, s=(fh, fw))
            spec_k = self.spectra[(fh, fw)]
            out[..., a : a + ph, c : c + pw] += fft_conv_by(
                z[..., a:b, c:d], spec_k, fh, fw, ph, pw
            )
        return out


#: Rows of tiles per band in which a coarse layer's hit tiles are grouped into boxes.
_HIT_BAND = 4
#: The same for the pieces a coarse layer is blurred by FFT in (:func:`_blend_fft`).
_FFT_BAND = 16
#: A layer is blurred by pieces when their padded area is under this share of its box's.
_FFT_PIECES_SHARE = 0.7


def _hit_boxes(
    hit: torch.Tensor, ty0: int, ty1: int, tx0: int, tx1: int, tile: int, band_rows: int = 0
) -> list[tuple[int, int, int, int]]:
    """Boxes ``(y0, y1, x0, x1)`` (px, whole tiles, possibly past the frame) that cover the
    tiles set in ``hit`` ``(rows, cols)`` within rows ``ty0:ty1`` and columns ``tx0:tx1``:
    per band of ``band_rows`` (default :data:`_HIT_BAND`) tile rows, spans of columns merged
    across gaps under two tiles, each cut to the band's rows it hits. Boxes do not overlap,
    and those of a band of ``n`` rows lie inside those of a band of ``m n`` rows."""
    boxes = []
    band_rows = band_rows or _HIT_BAND
    sub = hit[ty0:ty1, tx0:tx1]
    for b0 in range(0, ty1 - ty0, band_rows):
        band = sub[b0 : b0 + band_rows]
        cols = torch.nonzero(band.any(dim=0)).flatten().tolist()
        for c0, c1 in column_spans(cols):
            rows = torch.nonzero(band[:, c0 : c1 + 1].any(dim=1)).flatten()
            r0, r1 = ty0 + b0 + int(rows[0]), ty0 + b0 + int(rows[-1]) + 1
            boxes.append((r0 * tile, r1 * tile, (tx0 + c0) * tile, (tx0 + c1 + 1) * tile))
    return boxes


def render_tiled(
    image: torch.Tensor,
    weights: torch.Tensor | None,
    plan: LayerPlan,
    spec: KernelSpec,
    quality: str,
    threads: ThreadChoice | None,
    hidden: bool = True,
) -> torch.Tensor:
    """:func:`render` of one large frame without gradients, in bounded memory.

    Where each layer is masked is found per 32-px tile (from the bins of the layer
    coordinate the tile holds, :func:`_tile_bins`), so a pixel is masked for the few layers it
    can reach, not for every layer whose bounding box holds it, nor (across a depth edge) for
    every layer between the edge's two sides. Coarse layers (1/2 to 1/16 grids) are masked
    on the frame averaged over cells of 2 px (:class:`_HalfSource`: a cell across a depth
    edge pixel by pixel) over boxes of their hit tiles (bands of tile rows, spans of nearby
    columns), summed into their grid and blurred there; the layers behind the focal plane are
    composited into one accumulator that moves to the next finer grid as their kernels
    shrink (upsampled once per grid), the layers in front into (colour, transmittance) per
    grid, folded into one at the end. The full-resolution layers, the merge of both and
    the normalisation run band by band, so no full-resolution accumulator is built.

    Shape: ``image (1, 3, H, W)``, ``weights (1, Cw, H, W)`` or ``None`` ->
    ``(1, 3, H, W)``.
    """
    _, _, height, width = image.shape
    t = _TT
    nty, ntx = -(-height // t), -(-width // t)
    hp, wp = nty * t, ntx * t
    dev, dtype = str(image.device), image.dtype
    # the layer is [mask, mask w I, mask w] (or [mask, mask I]), read box by box or band by
    # band from the image, the weights (plus the floor, added in place by the caller) and the
    # layer coordinate: no padded or weighted copy of the frame is built
    cx = 3 if weights is None else 3 + weights.shape[1]
    chans = cx + 1
    coord = plan.coord[0]
    # the layer coordinate's range per tile; past the frame the coordinate is so far that no
    # mask reaches it
    ctiles = _TileSource(coord, t, FAR)
    lo = ctiles.extreme(torch.amin)
    ctiles.refill(-FAR)
    hi = ctiles.extreme(torch.amax)
    reach = plan.reach

    layer_rows = functools.partial(_fill_layer, image, weights)

    bins = None
    if _EXACT_HITS:
        # (the tiles past the frame hold FAR in lo and -FAR in hi: the frame's extremes)
        bins = _tile_bins(coord[0], t, nty, ntx, (float(lo.min()), float(hi.max())))

    def hits(centre: int) -> torch.Tensor:
        """Tiles where layer ``centre`` has a mask above _MASK_EPS, ``(nty, ntx)``."""
        a, b = lo, hi
        if plan.signed and centre > 0:
            a = lo.clamp(min=0.0)
            out = (hi > 0) & (b > centre - reach) & (a < centre + reach)
        elif plan.signed and centre < 0:
            b = hi.clamp(max=0.0)
            out = (lo < 0) & (b > centre - reach) & (a < centre + reach)
        else:
            out = (b > centre - reach) & (a < centre + reach)
        if bins is None:
            return out
        # a tile across a depth edge holds coordinates on both sides but none between them:
        # only the layers near the coordinates its pixels have
        present, lower, upper = bins
        near = (lower < centre + reach) & (upper > centre - reach)
        if plan.signed and centre:
            near &= upper > 0 if centre > 0 else lower < 0
        return out & (present @ near.to(present.dtype) > 0).view(nty, ntx)

    def gate(centre: int) -> int:
        # beyond one reach from 0 the other side's mask is already 0 in float32
        if not plan.signed or centre == 0 or abs(centre) > reach + 1:
            return 0
        return 1 if centre > 0 else -1

    under = None
    if hidden and plan.signed:

        def pixels(ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
            # the layer of mask one: [1, x] as the layers are made
            out = image.new_empty(chans, ys.numel())
            layer_rows(ys, xs, image.new_ones(()), out)
            return out

        under = hidden_surface(pixels, plan)

    half = None  # the frame on cells of 2 px, made for the first coarse layer

    back: tuple[int, torch.Tensor] | None = None  # (factor, colour) behind the focus
    front: list[list] = []  # [factor, colour, transmit] per grid, back to front
    sharp: list[tuple[int, int, torch.Tensor]] = []  # full-resolution layers
    phase = 0  # 0: behind the sharp layers, 1: sharp layers, 2: in front of them
    previous = MAX_FACTOR * 2
    grid = blurred = None
    for centre, size in plan.order:
        hit = hits(centre)
        index = torch.nonzero(hit.flatten()).flatten()
        if not index.numel():
            continue
        if threads is not None:
            threads.check()
        factor = 1 if size <= 1 else grid_factor(size, quality)
        if spec.blades and factor > 2:
            factor = 2
        if phase == 0 and (factor == 1 or factor > previous):
            phase = 1 if factor == 1 else 2
        elif phase == 1 and factor > 1:
            phase = 2
        previous = factor
        if factor == 1:
            sharp.append((centre, size, hit))
            continue
        # the layer, masked tile by tile and summed into its grid over its tiles' box
        ty, tx = index // ntx, index % ntx
        ty0, ty1 = int(ty.min()), int(ty.max()) + 1
        tx0, tx1 = int(tx.min()), int(tx.max()) + 1
        cell = t // factor
        grid = image.new_zeros(chans, (ty1 - ty0) * cell, (tx1 - tx0) * cell)
        g = gate(centre)
        if half is None:
            half = _HalfSource(image, weights, coord, hp, wp, chans, plan.signed)
        # the layer masked on the half-resolution cells of its hit tiles (cells across a
        # depth edge pixel by pixel), summed into its grid
        for ya, yb, xa, xb in _hit_boxes(hit, ty0, ty1, tx0, tx1, t):
            sy, sx = slice(ya // 2, yb // 2), slice(xa // 2, xb // 2)
            m = _tile_mask(half.c[sy, sx], centre, plan.mask, g)
            gy, gx = (ya - ty0 * t) // factor, (xa - tx0 * t) // factor
            dest = grid[:, gy : gy + (yb - ya) // factor, gx : gx + (xb - xa) // factor]
            if factor == 2:
                torch.mul(half.x[:, sy, sx], m, out=dest)
            else:
                pool_product(half.x[:, sy, sx], m, factor // 2, out=dest, mean=False)
        half.add_mixed(grid, centre, plan.mask, g, hit, (ty0 * t, tx0 * t), factor)
        gh, gw = hp // factor, wp // factor
        # each grid cell sums (factor / 2)**2 cell means: the kernel carries 1 / cells**2
        cells = factor // 2
        k = kernel_tensor(spec, size, factor, dev, dtype, 1.0 / cells**2)
        if k.shape[-1] <= DIRECT_MAX_SIZE:
            cbox = (ty0 * cell, ty1 * cell, tx0 * cell, tx1 * cell)

            def rows_of(r0, r1, out=None, grid=grid):
                return grid[None, :, r0:r1] if out is None else out.copy_(grid[None, :, r0:r1])

            blurred, oy, ox = direct_stacked(rows_of, image, chans, cbox, k, (gh, gw))
            stacked = True
        else:
            # blurred by FFT and composited one channel at a time (see _blend_fft), by
            # pieces when the layer's tiles and their blur fill little of its box
            blurred = None
            r = k.shape[-1] // 2
            oy, ox = ty0 * cell - r, tx0 * cell - r
            stacked = False
            pieces = [
                ((a - ty0 * t) // factor, (b - ty0 * t) // factor,
                 (c - tx0 * t) // factor, (d - tx0 * t) // factor)
                for a, b, c, d in _hit_boxes(hit, ty0, ty1, tx0, tx1, t, _FFT_BAND)
            ]  # fmt: skip
            area = sum((b - a + 2 * r) * (d - c + 2 * r) for a, b, c, d in pieces)
            if area > _FFT_PIECES_SHARE * (grid.shape[1] + 2 * r) * (grid.shape[2] + 2 * r):
                pieces = None
        if phase == 0:
            if back is None:
                back = (factor, image.new_zeros(1, chans, gh, gw))
            elif back[0] != factor:
                up = upsample_grid(back[1], back[0] // factor, gh, gw)
                back = (factor, up.contiguous())
            if stacked:
                blend_stacked(back[1], blurred, oy, ox)
            else:
                _blend_fft(back[1], grid, spec, size, factor, oy, ox, pieces=pieces, cells=cells)
            grid = blurred = None  # freed before the next layer's
            continue
        if not front or front[-1][0] != factor:
            front.append([factor, image.new_zeros(1, chans, gh, gw), image.new_ones(1, 1, gh, gw)])
        if stacked:
            blend_stacked(front[-1][1], blurred, oy, ox, transmit=front[-1][2])
        else:
            _blend_fft(
                front[-1][1], grid, spec, size, factor, oy, ox, front[-1][2], pieces, cells=cells
            )
        grid = blurred = None
    del grid, blurred  # the last coarse layer's buffers
    # fold the front grids into one: the coarsest is on top
    fold = None
    for factor, colour, transmit in reversed(front):
        if fold is None:
            fold = (factor, colour, transmit)
            continue
        f0, c0, t0 = fold
        up = upsample_grid(t0, f0 // factor, *colour.shape[-2:])
        colour.mul_(up)
        transmit.mul_(up)
        up = None
        colour.add_(upsample_grid(c0, f0 // factor, *colour.shape[-2:]))
        fold = (factor, colour, transmit)
    if fold is not None:
        fold = (fold[0], fold[1][0], fold[2][0])
    front = []

    # full-resolution passes, band by band; the result is an ordinary tensor
    with torch.inference_mode(False):
        out = torch.empty_like(image)
    rows = max(MAX_FACTOR, _BAND_PIXELS // max(width, 1) // MAX_FACTOR * MAX_FACTOR)
    floor = 1e-6 if weights is None else 1e-8
    for y0 in range(0, height, rows):
        y1 = min(height, y0 + rows)
        if threads is not None:
            threads.check()
        if back is None:
            acc = image.new_zeros(chans, y1 - y0, width)
        else:
            acc = _upsample_rows(back[1][0], back[0], y0, y1, width).contiguous()
        for centre, size, hit in sharp:
            k = kernel_tensor(spec, size, 1, dev, dtype)
            r = k.shape[-1] // 2
            # the layer's tiles whose blur reaches the band, as boxes of nearby columns (one
            # band of tile rows), cut to the rows the blur reaches
            first = max(0, (y0 - r) // t)
            last = min(nty, (y1 + r - 1) // t + 1)
            g = gate(centre)
            for ya, yb, xa, xb in _hit_boxes(hit, first, last, 0, ntx, t, last - first):
                ya, yb, xb = max(ya, y0 - r), min(yb, height, y1 + r), min(xb, width)
                if yb <= ya:
                    continue

                def rows_of(r0, r1, out=None, ya=ya, xa=xa, xb=xb, centre=centre, g=g):
                    if out is None:
                        out = image.new_empty(1, chans, r1 - r0, xb - xa)
                    ys = slice(ya + r0, ya + r1)
                    m = _tile_mask(coord[0, ys, xa:xb], centre, plan.mask, g)
                    layer_rows(ys, slice(xa, xb), m, out[0])
                    return out

                if size <= 1:
                    blend_part(acc[None], rows_of(0, yb - ya), ya - y0, xa, False)
                    continue
                box = (ya - y0, yb - y0, xa, xb)
                out_s, oy0, ox0 = direct_stacked(rows_of, image, chans, box, k, (y1 - y0, width))
                blend_stacked(acc[None], out_s, oy0, ox0)
        if under is not None:
            # under every layer (over is associative): what the layers leave of it shows
            a, b = max(y0, under.box[0]), min(y1, under.box[1])
            if a < b:
                under.composite(acc, a, b, top=y0)
        if fold is not None:
            # with weights the alpha channel is not read past here
            kept = acc if weights is None else acc[1:]
            kept.mul_(_upsample_rows(fold[2], fold[0], y0, y1, width))
            kept.add_(_upsample_rows(fold[1][kept is not acc :], fold[0], y0, y1, width))
        norm = acc[:1] if weights is None else acc[4:]
        covered = norm > 1e-6
        band_out = out[0, :, y0:y1]
        torch.div(acc[1:4], norm.clamp_(min=floor), out=band_out)
        if not bool(covered.all()):
            band_out.copy_(torch.where(covered, band_out, image[0, :, y0:y1]))
        band_out.clamp_(0, 1)
    return out
