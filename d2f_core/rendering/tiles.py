"""Tiles of a large frame for the tiled path (:mod:`.tiled`): their extremes without a
padded copy (:class:`TileSource`), the bins of the layer coordinate each holds
(:func:`tile_bins`), and boxes that cover a layer's tiles (:func:`hit_boxes`).
"""

from __future__ import annotations

import math

import torch

from .blur import column_spans


class TileSource:
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


#: Bins of the layer coordinate per layer in :func:`tile_bins`.
TILE_BINS = 4
#: Rows of tiles :func:`tile_bins` counts at once.
TILE_BIN_ROWS = 4


def tile_bins(
    coord: torch.Tensor, tile: int, ny: int, nx: int, extremes: tuple[float, float] | None = None
):
    """Which bins of the layer coordinate each ``tile x tile`` tile of ``coord (H, W)``
    holds a pixel in: ``(ny * nx, bins)`` (0 or 1), and each bin's lowest and highest
    coordinate. Bins are 1 / :data:`TILE_BINS` of a layer wide, split at 0 with 0 a bin of
    its own, so a bin's pixels are all on one side of focus (or at it). ``extremes``: the
    coordinate's lowest and highest value when the caller has them."""
    height, width = coord.shape
    q = TILE_BINS
    low, high = (float(coord.min()), float(coord.max())) if extremes is None else extremes
    top = int(math.ceil(max(abs(low), abs(high)) * q))
    nb = 2 * top + 1
    j = torch.arange(-top, top + 1, dtype=coord.dtype, device=coord.device)
    lower = torch.where(j > 0, (j - 1) / q, j / q)
    upper = torch.where(j < 0, (j + 1) / q, j / q)
    rows = tile * TILE_BIN_ROWS
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


#: Rows of tiles per band in which a coarse layer's hit tiles are grouped into boxes.
HIT_BAND = 4


def hit_boxes(
    hit: torch.Tensor, ty0: int, ty1: int, tx0: int, tx1: int, tile: int, band_rows: int = 0
) -> list[tuple[int, int, int, int]]:
    """Boxes ``(y0, y1, x0, x1)`` (px, whole tiles, possibly past the frame) that cover the
    tiles set in ``hit`` ``(rows, cols)`` within rows ``ty0:ty1`` and columns ``tx0:tx1``:
    per band of ``band_rows`` (default :data:`HIT_BAND`) tile rows, spans of columns merged
    across gaps under two tiles, each cut to the band's rows it hits. Boxes do not overlap,
    and those of a band of ``n`` rows lie inside those of a band of ``m n`` rows."""
    boxes = []
    band_rows = band_rows or HIT_BAND
    sub = hit[ty0:ty1, tx0:tx1]
    for b0 in range(0, ty1 - ty0, band_rows):
        band = sub[b0 : b0 + band_rows]
        cols = torch.nonzero(band.any(dim=0)).flatten().tolist()
        for c0, c1 in column_spans(cols):
            rows = torch.nonzero(band[:, c0 : c1 + 1].any(dim=1)).flatten()
            r0, r1 = ty0 + b0 + int(rows[0]), ty0 + b0 + int(rows[-1]) + 1
            boxes.append((r0 * tile, r1 * tile, (tx0 + c0) * tile, (tx0 + c1 + 1) * tile))
    return boxes
