"""Compositing, far layers first: ``acc = acc (1 - K_l M_l) + K_l (M_l X)`` for the
colour and the alpha, normalised in one pass as D2F step 5 does twice:
``B = f_l(R I, D) / f_l(R, D)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .blur import (
    DIRECT_MAX_SIZE,
    KernelSpec,
    blend_stacked,
    direct_conv,
    direct_pads,
    direct_stacked,
    fft_conv,
    grid_factor,
    kernel_tensor,
    layer_input,
    layer_input_rows,
    pool_grid,
    support_boxes,
    upsample_grid,
)
from .hidden import HiddenSurface, under_hidden
from .inputs import tracks_grad
from .plan import LayerPlan
from .threads import ThreadChoice

# rendering
# --------------------------------------------------------------------------------------


def overlap_slices(
    frame: tuple[int, int], y0: int, x0: int, part: tuple[int, int]
) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
    """Where a ``part`` (h, w) placed at offset (y0, x0) meets a ``frame`` (H, W): the part's
    (rows, cols) and the frame's (rows, cols), or None when they do not meet."""
    height, width = frame
    by0, bx0 = max(0, -y0), max(0, -x0)
    ty0, tx0 = y0 + by0, x0 + bx0
    ty1 = min(height, y0 + part[0])
    tx1 = min(width, x0 + part[1])
    if ty1 <= ty0 or tx1 <= tx0:
        return None
    src = (slice(by0, by0 + ty1 - ty0), slice(bx0, bx0 + tx1 - tx0))
    return src, (slice(ty0, ty1), slice(tx0, tx1))


def blend_part(acc: torch.Tensor, part: torch.Tensor, y0: int, x0: int, grad: bool) -> torch.Tensor:
    """Composite ``part`` (alpha in channel 0, premultiplied colour after it) over ``acc``
    at offset (y0, x0), clipped to the frame. Returns the updated accumulator."""
    meet = overlap_slices(acc.shape[-2:], y0, x0, part.shape[-2:])
    if meet is None:
        return acc
    (rows, cols), (frows, fcols) = meet
    part = part[..., rows, cols]
    region = acc[..., frows, fcols]
    if grad:
        keep = 1 - part[:, :1].clamp(0, 1)
        acc = acc.clone()
        acc[..., frows, fcols] = region * keep + part
    else:  # acc (1 - alpha) as acc - acc alpha: one pass
        region.addcmul_(region, part[:, :1].clamp(0, 1), value=-1).add_(part)
    return acc


def composite_layers(
    x: torch.Tensor,
    plan: LayerPlan,
    spec: KernelSpec,
    *,
    method: str,
    quality: str,
    full_frame: bool,
    front: bool = False,
    front_size: float = 0.0,
    threads: ThreadChoice | None = None,
    hidden: HiddenSurface | None = None,
) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
    """Composite the layers of ``x`` back to front. Returns (acc, alpha, split).

    A ``hidden`` surface (:func:`hidden_surface`) is composited under all the layers
    (under the layers behind the focal plane with ``front``).

    With ``front`` (a signed plan), the layers in front of the focal plane are composited
    from zero into their own accumulator, ``(C_f, A_f)``, and merged once,
    ``acc = acc * (1 - A_f) + C_f``: the same composite (over is linear in what lies
    under it). Front layers are those in front of the focal plane with a kernel of at least
    ``front_size`` px. ``split`` is then ``(back, 1 - A_f)``: the accumulator of all the
    other layers (alpha first, as ``acc``) and what the front layers leave of it; ``None``
    without ``front`` or when no layer is in front.

    Without gradients ``x`` carries the leading channel of ones of :func:`with_ones`.

    Layers whose kernel is large enough for ``quality`` are masked, pooled, blurred and
    composited on a 1/2 or 1/4 resolution grid. A run of consecutive such layers is composited
    there from zero into (colour, transmittance) and merged into the full-resolution
    accumulator once, ``acc = acc * T + C``, which is exact at the coarse level because
    compositing is linear in the accumulator.

    Without gradients a layer convolved directly is written strip by strip into a
    channels-last buffer that stacks its strips along the channel axis (:func:`direct_stacked`),
    sized so that only the part of its blur that lands in the frame is computed, and coarse
    layers are pooled straight from the product (:func:`layer_input_rows`). The accumulator and
    everything else stay planar.

    Shape: ``x (B, C, H, W) -> acc (B, C, H, W), alpha (B, 1, H, W)``, split
    ``((B, C + 1, H, W), (B, 1, H, W))``.
    """
    b, c, height, width = x.shape
    grad = tracks_grad(x, plan.coord)
    if not grad:
        c -= 1  # the channel of ones
    layers = _Layers(x, plan, spec, method, grad, c + 1)
    acc = x.new_zeros(b, c + 1, height, width)  # channel 0 is the alpha
    if full_frame:
        boxes = {centre: (0, height, 0, width) for centre, _ in plan.order}
    else:
        boxes = support_boxes(plan, height, width)
    blank = True  # nothing composited into acc yet
    group: tuple[int, torch.Tensor, torch.Tensor | None] | None = None
    back = None  # the accumulator behind the focal plane, once the front layers begin
    for centre, size in plan.order:
        box = boxes.get(centre)
        if box is None:
            continue
        if threads is not None:
            threads.check()
        if front and back is None and plan.signed and centre > 0 and size >= front_size:
            back, group = layers.flush(acc, group), None
            acc = x.new_zeros(b, c + 1, height, width)
            blank = True
        factor = 1 if size <= 1 else grid_factor(size, quality)
        if spec.blades and factor > 2:
            # a 1/4-resolution grid rounds off a polygon's corners: visible in highlights
            factor = 2
        if group is not None and group[0] != factor:
            blank = blank and group[2] is not None  # over a blank acc, the group's colour
            acc, group = layers.flush(acc, group), None
        if factor == 1:
            blank = False
            acc = layers.full(acc, centre, size, box)
        else:
            group = layers.coarse(group, blank, centre, size, box, factor)
    acc = layers.flush(acc, group)
    if hidden is not None:
        # under every layer (over is associative): what the layers leave of it shows
        if back is not None:
            back = under_hidden(back, hidden, grad)
        else:
            acc = under_hidden(acc, hidden, grad)
    split = None
    if back is not None:
        transmit = 1 - acc[:, :1].clamp(0, 1)
        acc = back * transmit + acc if grad else acc.addcmul_(back, transmit)
        split = (back, transmit)
    return acc[:, 1:], acc[:, :1], split


class _Layers:
    """What the layers of one :func:`composite_layers` share: the layer input ``x``, the
    plan, the kernel, the blur method, whether gradients flow, and the channels of the
    accumulator (alpha first)."""

    def __init__(
        self, x: torch.Tensor, plan: LayerPlan, spec: KernelSpec, method: str, grad: bool,
        chans: int,
    ) -> None:  # fmt: skip
        self.x, self.plan, self.spec, self.method, self.grad = x, plan, spec, method, grad
        self.chans = chans
        self.height, self.width = x.shape[-2:]
        self.dev, self.dtype = str(x.device), x.dtype

    def _kernel(self, size: int, factor: int, gain: float = 1.0) -> tuple[torch.Tensor, bool]:
        """The kernel of ``size`` on a grid of ``factor``, and whether it is convolved
        directly (else by FFT)."""
        k = kernel_tensor(self.spec, size, factor, self.dev, self.dtype, gain)
        return k, self.method == "direct" or k.shape[-1] <= DIRECT_MAX_SIZE

    def flush(self, acc: torch.Tensor, group: tuple | None) -> torch.Tensor:
        """``acc`` with a run of coarse layers, ``group = (factor, colour, transmit)``, merged
        into it (``acc T + C`` upsampled; the colour alone over an empty accumulator,
        ``transmit`` ``None``)."""
        if group is None:
            return acc
        factor, colour, transmit = group
        if transmit is None:
            # over an empty accumulator the composite is the group's colour alone
            return upsample_grid(colour, factor, self.height, self.width)
        up = upsample_grid(torch.cat([colour, transmit], dim=1), factor, self.height, self.width)
        if self.grad:
            return acc * up[:, -1:] + up[:, :-1]
        return acc.mul_(up[:, -1:]).add_(up[:, :-1])

    def full(self, acc: torch.Tensor, centre: int, size: int, box: tuple) -> torch.Tensor:
        """``acc`` with layer ``centre`` (kernel ``size``, over ``box``) composited at full
        resolution."""
        x, plan, grad = self.x, self.plan, self.grad
        coord = plan.side_coord(centre)
        k, direct = self._kernel(size, 1)
        r = k.shape[-1] // 2
        if size <= 1:
            z = layer_input(x, coord, centre, plan.mask, box, (0, 0, 0, 0), grad)
            return blend_part(acc, z, box[0], box[2], grad)
        if direct and not grad:
            rows = layer_input_rows(x, coord, centre, plan.mask, box, 1)
            out, oy0, ox0 = direct_stacked(rows, x, self.chans, box, k, (self.height, self.width))
            blend_stacked(acc, out, oy0, ox0)
            return acc
        if direct:
            pads, oy0, ox0 = direct_pads(box, r, self.height, self.width)
            z = layer_input(x, coord, centre, plan.mask, box, pads, grad)
            return blend_part(acc, direct_conv(z, k), oy0, ox0, grad)
        z = layer_input(x, coord, centre, plan.mask, box, (0, 0, 0, 0), grad)
        return blend_part(acc, fft_conv(z, self.spec, size, 1), box[0] - r, box[2] - r, grad)

    def coarse(
        self, group: tuple | None, blank: bool, centre: int, size: int, box: tuple, factor: int
    ) -> tuple:
        """``group`` (a run of coarse layers on the grid of ``factor``; ``None`` starts one,
        with no transmittance while the accumulator is ``blank``) with layer ``centre``
        composited into it: the box snapped to the grid, the premultiplied layer pooled (so
        colour from other layers in the same cell never leaks into this one) and blurred."""
        x, plan, grad, b = self.x, self.plan, self.grad, self.x.shape[0]
        coord = plan.side_coord(centre)
        k, direct = self._kernel(size, factor)
        r = k.shape[-1] // 2
        y0, y1, x0, x1 = box
        y0, x0 = y0 - y0 % factor, x0 - x0 % factor
        lh, lw = -(-self.height // factor), -(-self.width // factor)
        if group is None:
            # nothing to transmit to while the accumulator is empty
            transmit = None if blank and not grad else x.new_ones(b, 1, lh, lw)
            group = (factor, x.new_zeros(b, self.chans, lh, lw), transmit)
        # zero padding past the frame edge: the pooled alpha there is partial, as it should be
        bh, bw = (-(y1 - y0)) % factor, (-(x1 - x0)) % factor
        cbox = (y0 // factor, (y1 + bh) // factor, x0 // factor, (x1 + bw) // factor)
        # without gradients, cells are summed and the kernel carries the 1 / factor**2 of
        # the mean: one pass less per layer
        gain = 1.0 if grad else 1.0 / factor**2
        if grad or bh or bw:
            z = layer_input(x, coord, centre, plan.mask, (y0, y1, x0, x1), (0, bh, 0, bw), grad)

            def rows(r0, r1, out=None, z=z, factor=factor):
                span = slice(r0 * factor, r1 * factor)
                return pool_grid(z[..., span, :], factor, out=out, mean=grad)

        else:  # product and pooling in one: no full-resolution layer is built
            rows = layer_input_rows(x, coord, centre, plan.mask, (y0, y1, x0, x1), factor)
        if direct and not grad:
            k, _ = self._kernel(size, factor, gain)
            out, oy0, ox0 = direct_stacked(rows, x, self.chans, cbox, k, (lh, lw))
            blend_stacked(group[1], out, oy0, ox0, transmit=group[2])
            return group
        if direct:
            pads, oy0, ox0 = direct_pads(cbox, r, lh, lw)
            zc = F.pad(rows(0, cbox[1] - cbox[0]), (pads[2], pads[3], pads[0], pads[1]))
            blurred = direct_conv(zc, k)
        else:
            blurred = fft_conv(rows(0, cbox[1] - cbox[0]), self.spec, size, factor, gain)
            oy0, ox0 = cbox[0] - r, cbox[2] - r
        colour = blend_part(group[1], blurred, oy0, ox0, grad)
        transmit = group[2]
        if transmit is not None:
            transmit = _blend_transmit(transmit, blurred[:, :1], oy0, ox0, grad)
        return (factor, colour, transmit)


def _blend_transmit(
    transmit: torch.Tensor, alpha: torch.Tensor, y0: int, x0: int, grad: bool
) -> torch.Tensor:
    """Multiply the transmittance by ``1 - alpha`` at offset (y0, x0), clipped to the frame."""
    meet = overlap_slices(transmit.shape[-2:], y0, x0, alpha.shape[-2:])
    if meet is None:
        return transmit
    (rows, cols), (frows, fcols) = meet
    keep = 1 - alpha[..., rows, cols].clamp(0, 1)
    if grad:
        updated = transmit[..., frows, fcols] * keep
        transmit = transmit.clone()
        transmit[..., frows, fcols] = updated
    else:
        transmit[..., frows, fcols].mul_(keep)
    return transmit


# --------------------------------------------------------------------------------------
