"""The tiled path: D2F step 5 (``f_l(R I, D) / f_l(R, D)``) on frames of 1.4 MP and more
without gradients, by tiles and row bands in bounded memory.
"""

from __future__ import annotations

import functools

import torch

from .blur import (
    DIRECT_MAX_SIZE,
    MAX_FACTOR,
    KernelSpec,
    blend_stacked,
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
from .tiles import TileSource, hit_boxes, tile_bins

# large frames: tiles and bands
# --------------------------------------------------------------------------------------

# Tile side (px) of the tiled path: a multiple of MAX_FACTOR.
_TT = 32
# Pixels per band of the full-resolution passes.
_BAND_PIXELS = 1_000_000


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
#: (:func:`tile_bins`), or with ``False`` from the tiles' coordinate ranges alone (which
#: put a tile across a depth edge in every layer between its two sides).
_EXACT_HITS = True


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


#: The same for the pieces a coarse layer is blurred by FFT in (:func:`_blend_fft`).
_FFT_BAND = 16
#: A layer is blurred by pieces when their padded area is under this share of its box's.
_FFT_PIECES_SHARE = 0.7


class _TiledFrame:
    """One large frame rendered by :func:`render_tiled`: where each layer reaches (per tile),
    the coarse layers' accumulators, the full-resolution layers, and the bands they end in.

    Shape: ``image (1, 3, H, W)``, ``weights (1, Cw, H, W)`` or ``None``.
    """

    def __init__(
        self,
        image: torch.Tensor,
        weights: torch.Tensor | None,
        plan: LayerPlan,
        spec: KernelSpec,
        quality: str,
        threads: ThreadChoice | None,
        hidden: bool,
    ) -> None:
        self.image, self.weights, self.plan, self.spec = image, weights, plan, spec
        self.quality, self.threads = quality, threads
        _, _, self.height, self.width = image.shape
        t = _TT
        self.nty, self.ntx = -(-self.height // t), -(-self.width // t)
        self.hp, self.wp = self.nty * t, self.ntx * t
        # the layer is [mask, mask w I, mask w] (or [mask, mask I]), read box by box or band
        # by band from the image, the weights (plus the floor, added in place by the caller)
        # and the layer coordinate: no padded or weighted copy of the frame is built
        cx = 3 if weights is None else 3 + weights.shape[1]
        self.chans = cx + 1
        self.coord = plan.coord[0]
        # the layer coordinate's range per tile; past the frame the coordinate is so far
        # that no mask reaches it
        ctiles = TileSource(self.coord, t, FAR)
        self.lo = ctiles.extreme(torch.amin)
        ctiles.refill(-FAR)
        self.hi = ctiles.extreme(torch.amax)
        self.layer_rows = functools.partial(_fill_layer, image, weights)
        self.bins = None
        if _EXACT_HITS:
            # (the tiles past the frame hold FAR in lo and -FAR in hi: the frame's extremes)
            extremes = (float(self.lo.min()), float(self.hi.max()))
            self.bins = tile_bins(self.coord[0], t, self.nty, self.ntx, extremes)
        self.under = None
        if hidden and plan.signed:
            self.under = hidden_surface(self._pixels, plan)
        self.half: _HalfSource | None = None  # the frame on cells of 2 px, made when needed
        self.back: tuple[int, torch.Tensor] | None = None  # (factor, colour) behind the focus
        self.front: list[list] = []  # [factor, colour, transmit] per grid, back to front
        self.sharp: list[tuple[int, int, torch.Tensor]] = []  # full-resolution layers

    def _pixels(self, ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        """The layer of mask one at single pixels: ``[1, x]`` as the layers are made."""
        out = self.image.new_empty(self.chans, ys.numel())
        self.layer_rows(ys, xs, self.image.new_ones(()), out)
        return out

    def hits(self, centre: int) -> torch.Tensor:
        """Tiles where layer ``centre`` has a mask above _MASK_EPS, ``(nty, ntx)``."""
        plan, reach = self.plan, self.plan.reach
        lo, hi = self.lo, self.hi
        a, b = lo, hi
        if plan.signed and centre > 0:
            a = lo.clamp(min=0.0)
            out = (hi > 0) & (b > centre - reach) & (a < centre + reach)
        elif plan.signed and centre < 0:
            b = hi.clamp(max=0.0)
            out = (lo < 0) & (b > centre - reach) & (a < centre + reach)
        else:
            out = (b > centre - reach) & (a < centre + reach)
        if self.bins is None:
            return out
        # a tile across a depth edge holds coordinates on both sides but none between them:
        # only the layers near the coordinates its pixels have
        present, lower, upper = self.bins
        near = (lower < centre + reach) & (upper > centre - reach)
        if plan.signed and centre:
            near &= upper > 0 if centre > 0 else lower < 0
        return out & (present @ near.to(present.dtype) > 0).view(self.nty, self.ntx)

    def gate(self, centre: int) -> int:
        """+1 or -1: the side of focus layer ``centre`` is masked to; 0: no gate needed."""
        # beyond one reach from 0 the other side's mask is already 0 in float32
        if not self.plan.signed or centre == 0 or abs(centre) > self.plan.reach + 1:
            return 0
        return 1 if centre > 0 else -1

    def layers(self) -> None:
        """Every layer in the plan's order: a full-resolution one is kept for the bands, a
        coarse one masked, blurred and composited on its grid (:meth:`coarse_layer`)."""
        phase = 0  # 0: behind the sharp layers, 1: sharp layers, 2: in front of them
        previous = MAX_FACTOR * 2
        for centre, size in self.plan.order:
            hit = self.hits(centre)
            index = torch.nonzero(hit.flatten()).flatten()
            if not index.numel():
                continue
            if self.threads is not None:
                self.threads.check()
            factor = 1 if size <= 1 else grid_factor(size, self.quality)
            if self.spec.blades and factor > 2:
                factor = 2
            if phase == 0 and (factor == 1 or factor > previous):
                phase = 1 if factor == 1 else 2
            elif phase == 1 and factor > 1:
                phase = 2
            previous = factor
            if factor == 1:
                self.sharp.append((centre, size, hit))
            else:
                self.coarse_layer(centre, size, hit, index, factor, behind=phase == 0)

    def _grid(self, centre: int, hit: torch.Tensor, box: tuple[int, int, int, int], factor: int):
        """Layer ``centre`` masked tile by tile over its hit tiles (``box``: tile rows and
        columns ``ty0, ty1, tx0, tx1``), summed into its grid of ``factor``."""
        t, image = _TT, self.image
        ty0, ty1, tx0, tx1 = box
        cell = t // factor
        grid = image.new_zeros(self.chans, (ty1 - ty0) * cell, (tx1 - tx0) * cell)
        g = self.gate(centre)
        if self.half is None:
            self.half = _HalfSource(
                image, self.weights, self.coord, self.hp, self.wp, self.chans, self.plan.signed
            )
        half = self.half
        # the layer masked on the half-resolution cells of its hit tiles (cells across a
        # depth edge pixel by pixel), summed into its grid
        for ya, yb, xa, xb in hit_boxes(hit, ty0, ty1, tx0, tx1, t):
            sy, sx = slice(ya // 2, yb // 2), slice(xa // 2, xb // 2)
            m = _tile_mask(half.c[sy, sx], centre, self.plan.mask, g)
            gy, gx = (ya - ty0 * t) // factor, (xa - tx0 * t) // factor
            dest = grid[:, gy : gy + (yb - ya) // factor, gx : gx + (xb - xa) // factor]
            if factor == 2:
                torch.mul(half.x[:, sy, sx], m, out=dest)
            else:
                pool_product(half.x[:, sy, sx], m, factor // 2, out=dest, mean=False)
        half.add_mixed(grid, centre, self.plan.mask, g, hit, (ty0 * t, tx0 * t), factor)
        return grid

    def coarse_layer(
        self,
        centre: int,
        size: int,
        hit: torch.Tensor,
        index: torch.Tensor,
        factor: int,
        behind: bool,
    ) -> None:
        """Layer ``centre`` (kernel ``size``, tiles ``hit``, their flat ``index``) on its grid
        of ``factor``: masked, blurred (directly, or by FFT by pieces) and composited into
        the accumulator behind the focus (``behind``) or the front grid of its factor."""
        t, image, spec = _TT, self.image, self.spec
        ty, tx = index // self.ntx, index % self.ntx
        box = int(ty.min()), int(ty.max()) + 1, int(tx.min()), int(tx.max()) + 1
        ty0, ty1, tx0, tx1 = box
        cell = t // factor
        grid = self._grid(centre, hit, box, factor)
        gh, gw = self.hp // factor, self.wp // factor
        # each grid cell sums (factor / 2)**2 cell means: the kernel carries 1 / cells**2
        cells = factor // 2
        k = kernel_tensor(spec, size, factor, str(image.device), image.dtype, 1.0 / cells**2)
        blurred = pieces = None
        if k.shape[-1] <= DIRECT_MAX_SIZE:
            cbox = (ty0 * cell, ty1 * cell, tx0 * cell, tx1 * cell)

            def rows_of(r0, r1, out=None, grid=grid):
                return grid[None, :, r0:r1] if out is None else out.copy_(grid[None, :, r0:r1])

            blurred, oy, ox = direct_stacked(rows_of, image, self.chans, cbox, k, (gh, gw))
        else:
            # blurred by FFT and composited one channel at a time (see _blend_fft), by
            # pieces when the layer's tiles and their blur fill little of its box
            r = k.shape[-1] // 2
            oy, ox = ty0 * cell - r, tx0 * cell - r
            pieces = [
                ((a - ty0 * t) // factor, (b - ty0 * t) // factor,
                 (c - tx0 * t) // factor, (d - tx0 * t) // factor)
                for a, b, c, d in hit_boxes(hit, ty0, ty1, tx0, tx1, t, _FFT_BAND)
            ]  # fmt: skip
            area = sum((b - a + 2 * r) * (d - c + 2 * r) for a, b, c, d in pieces)
            if area > _FFT_PIECES_SHARE * (grid.shape[1] + 2 * r) * (grid.shape[2] + 2 * r):
                pieces = None
        if behind:
            if self.back is None:
                self.back = (factor, image.new_zeros(1, self.chans, gh, gw))
            elif self.back[0] != factor:
                up = upsample_grid(self.back[1], self.back[0] // factor, gh, gw)
                self.back = (factor, up.contiguous())
            acc, transmit = self.back[1], None
        else:
            if not self.front or self.front[-1][0] != factor:
                self.front.append(
                    [factor, image.new_zeros(1, self.chans, gh, gw), image.new_ones(1, 1, gh, gw)]
                )
            acc, transmit = self.front[-1][1], self.front[-1][2]
        if blurred is not None:
            blend_stacked(acc, blurred, oy, ox, transmit=transmit)
        else:
            _blend_fft(acc, grid, spec, size, factor, oy, ox, transmit, pieces, cells=cells)

    def fold_front(self) -> tuple[int, torch.Tensor, torch.Tensor] | None:
        """The front grids folded into one, the coarsest on top: ``(factor, colour (C, h,
        w), transmit (1, h, w))``, or ``None`` when nothing is in front."""
        fold = None
        for factor, colour, transmit in reversed(self.front):
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
        self.front = []
        return None if fold is None else (fold[0], fold[1][0], fold[2][0])

    def bands(self, fold: tuple[int, torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
        """The full-resolution passes, band by band: the accumulator behind the focus
        upsampled, the full-resolution layers, the hidden surface under them, the front
        grids over them, and the normalisation; the result is an ordinary tensor."""
        image, weights, height, width = self.image, self.weights, self.height, self.width
        with torch.inference_mode(False):
            out = torch.empty_like(image)
        rows = max(MAX_FACTOR, _BAND_PIXELS // max(width, 1) // MAX_FACTOR * MAX_FACTOR)
        floor = 1e-6 if weights is None else 1e-8
        for y0 in range(0, height, rows):
            y1 = min(height, y0 + rows)
            if self.threads is not None:
                self.threads.check()
            if self.back is None:
                acc = image.new_zeros(self.chans, y1 - y0, width)
            else:
                acc = _upsample_rows(self.back[1][0], self.back[0], y0, y1, width).contiguous()
            for centre, size, hit in self.sharp:
                self._sharp_layer(acc, centre, size, hit, y0, y1)
            under = self.under
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

    def _sharp_layer(
        self, acc: torch.Tensor, centre: int, size: int, hit: torch.Tensor, y0: int, y1: int
    ) -> None:
        """Full-resolution layer ``centre`` composited into band ``y0:y1``'s ``acc``."""
        t, image, plan = _TT, self.image, self.plan
        height, width = self.height, self.width
        k = kernel_tensor(self.spec, size, 1, str(image.device), image.dtype)
        r = k.shape[-1] // 2
        # the layer's tiles whose blur reaches the band, as boxes of nearby columns (one
        # band of tile rows), cut to the rows the blur reaches
        first = max(0, (y0 - r) // t)
        last = min(self.nty, (y1 + r - 1) // t + 1)
        g = self.gate(centre)
        for ya, yb, xa, xb in hit_boxes(hit, first, last, 0, self.ntx, t, last - first):
            ya, yb, xb = max(ya, y0 - r), min(yb, height, y1 + r), min(xb, width)
            if yb <= ya:
                continue

            def rows_of(r0, r1, out=None, ya=ya, xa=xa, xb=xb):
                if out is None:
                    out = image.new_empty(1, self.chans, r1 - r0, xb - xa)
                ys = slice(ya + r0, ya + r1)
                m = _tile_mask(self.coord[0, ys, xa:xb], centre, plan.mask, g)
                self.layer_rows(ys, slice(xa, xb), m, out[0])
                return out

            if size <= 1:
                blend_part(acc[None], rows_of(0, yb - ya), ya - y0, xa, False)
                continue
            box = (ya - y0, yb - y0, xa, xb)
            out_s, oy0, ox0 = direct_stacked(rows_of, image, self.chans, box, k, (y1 - y0, width))
            blend_stacked(acc[None], out_s, oy0, ox0)


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
    coordinate the tile holds, :func:`tile_bins`), so a pixel is masked for the few layers it
    can reach, not for every layer whose bounding box holds it, nor (across a depth edge) for
    every layer between the edge's two sides. Coarse layers (1/2 to 1/16 grids) are masked
    on the frame averaged over cells of 2 px (:class:`_HalfSource`: a cell across a depth
    edge pixel by pixel) over boxes of their hit tiles (bands of tile rows, spans of nearby
    columns), summed into their grid and blurred there; the layers behind the focal plane are
    composited into one accumulator that moves to the next finer grid as their kernels
    shrink (upsampled once per grid), the layers in front into (colour, transmittance) per
    grid, folded into one at the end. The full-resolution layers, the merge of both and
    the normalisation run band by band, so no full-resolution accumulator is built
    (:class:`_TiledFrame`).

    Shape: ``image (1, 3, H, W)``, ``weights (1, Cw, H, W)`` or ``None`` ->
    ``(1, 3, H, W)``.
    """
    frame = _TiledFrame(image, weights, plan, spec, quality, threads, hidden)
    frame.layers()
    return frame.bands(frame.fold_front())
