"""The layer plan and masks of D2F's layered rendering ``f_l``: each pixel's CoC placed
between two kernel sizes, with the soft masks
``M_l = 0.5 + 0.5 tanh(gamma (1/(L-1) - |D - l/(L-1)|))`` (``gamma = 100``), or with
``placement="blend"`` the masks that draw a pixel with both kernels around its CoC.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .inputs import ROW_BAND, check_placement, row_bands, tracks_grad
from .kernels import effective_diameter, kernel_sizes

GAMMA = 100.0
# Mask values below this are treated as empty when finding a layer's support.
_MASK_EPS = 1e-4
# Mask values at or below this are 0 (no denormal floats in a layer: see layer_mask).
_MASK_TINY = 1e-20
# Layers are located on a coarse grid of this many pixels before exact masks are computed.
TILE = 8
# Where a layer's other side is moved to in layer units: far enough that its mask is 0.
FAR = 1e4
# layer plan
# --------------------------------------------------------------------------------------


@dataclass
class LayerPlan:
    """Where each pixel sits among the layers, and the layers in compositing order.

    ``coord`` is the per-pixel layer coordinate (layer ``j`` is centred on ``coord == j``),
    ``order`` lists ``(centre, kernel size)`` back to front, ``gamma`` is the mask sharpness in
    layer units, ``signed`` says whether a layer only takes pixels on its side of focus.
    ``blend`` (``placement="blend"``): the layers' masks are :func:`blend_mask`, not the
    soft :func:`layer_mask` (``gamma`` is then unused).
    """

    coord: torch.Tensor  # [B,1,H,W]
    order: list[tuple[int, int]]
    gamma: float
    signed: bool
    blend: bool = False

    def __post_init__(self) -> None:
        self._sides: dict[int, torch.Tensor] = {}

    def mask(self, coord: torch.Tensor, centre: int, grad: bool = True) -> torch.Tensor:
        """Layer ``centre``'s mask at the layer coordinates ``coord`` (a part of
        :meth:`side_coord`'s), :func:`blend_mask` or :func:`layer_mask` as the plan's."""
        if self.blend:
            return blend_mask(coord, centre, grad)
        return layer_mask(coord, centre, self.gamma, grad)

    @property
    def reach(self) -> float:
        """How far (layer units) from its centre a layer's mask holds pixels: 1 for
        :func:`blend_mask`, a little more for the soft masks (:func:`mask_reach`)."""
        return 1.0 if self.blend else 1.0 + mask_reach(self.gamma)

    def side_coord(self, centre: int) -> torch.Tensor:
        """``coord`` with the pixels on the other side of focus pushed out of reach.

        A layer on one side of the focal plane never takes pixels from the other side: their
        mask underflows to exactly 0.
        """
        if not self.signed or centre == 0:
            return self.coord
        side = 1 if centre > 0 else -1
        if side not in self._sides:
            far = torch.full_like(self.coord, -FAR * side)
            keep = self.coord > 0 if side > 0 else self.coord < 0
            self._sides[side] = torch.where(keep, self.coord, far)
        return self._sides[side]


def _interp(x: torch.Tensor, xp: list[float]) -> torch.Tensor:
    """Piecewise-linear map of ``x`` onto the index of the increasing knots ``xp``."""
    if len(xp) == 1:
        return torch.zeros_like(x)
    xc = x.clamp(xp[0], xp[-1])
    if all(float(v).is_integer() for v in xp) and xp[-1] - xp[0] <= 1 << 16:
        # knots on integers (kernel sizes): the map is linear between consecutive integers,
        # so a table over them replaces a binary search per pixel (several times slower)
        base, slope = _integer_table(tuple(int(v) for v in xp), x.dtype, str(x.device))
        m = xc.detach().floor().clamp_(max=xp[-1] - 1)
        idx = m.sub(xp[0]).long().view(-1)
        lo = base.index_select(0, idx).view(x.shape)
        return lo.add_((xc - m).mul_(slope.index_select(0, idx).view(x.shape)))
    knots = torch.tensor(xp, device=x.device, dtype=x.dtype)
    idx = torch.searchsorted(knots, xc.detach().contiguous(), right=True).clamp(1, len(xp) - 1)
    flat = idx.view(-1)
    lo = knots.index_select(0, flat - 1).view(idx.shape)
    hi = knots.index_select(0, flat).view(idx.shape)
    return (idx - 1).to(x.dtype) + (xc - lo) / (hi - lo)


@functools.lru_cache(maxsize=32)
@torch.inference_mode(False)
def _integer_table(xp: tuple[int, ...], dtype: torch.dtype, device: str):
    """Knot index at each integer from ``xp[0]`` to ``xp[-1] - 1``, and the slope after it."""
    grid = np.interp(np.arange(xp[0], xp[-1] + 1), xp, np.arange(len(xp)))
    as_tensor = functools.partial(torch.tensor, dtype=dtype, device=device)
    return as_tensor(grid[:-1]), as_tensor(np.diff(grid))


def _unique_sizes(sizes: list[int]) -> list[int]:
    out: list[int] = []
    for s in sizes:
        if not out or s > out[-1]:
            out.append(s)
    return out


def layer_plan(
    disparity: torch.Tensor,
    focus: torch.Tensor,
    blur: float,
    *,
    order: str = "depth",
    num_layers: int = 15,
    schedule: str = "growing",
    gamma: float = GAMMA,
    max_size: float = 69.0,
    placement: str = "blend",
    extremes: tuple[float, float] | None = None,
    kernel: str = "soft",
    blades: int = 0,
) -> LayerPlan:
    """Assign pixels to layers (back-to-front compositing order).

    ``placement`` (depth order only) says where a pixel goes between two layers:

    * ``"blend"`` (default): layer ``j`` sits at the CoC its kernel draws
      (:func:`~d2f_core.rendering.kernels.effective_diameter` of the ``kernel`` and
      ``blades`` the render uses), and a pixel whose CoC lies between two layers is drawn
      by both (:func:`blend_mask`): by the one composited first in full and by the other over
      it in proportion to where its CoC lies between them, so that where the pixel's
      neighbours share its depth it is blurred by the two kernels mixed linearly, a kernel
      of its own CoC. A small blur is drawn with the CoC it has, not with the nearest of
      kernels 2 and 4 px apart that each reach a pixel further than their size says.

    * ``"nearest"``: layer ``j`` sits at the CoC its kernel draws (``size - 1`` px across) and
      pixels move half a layer toward the side the overlapping soft masks hide, so every pixel
      shows the kernel nearest its CoC on both sides of focus.
    * ``"paper"``: layer ``j`` sits at a CoC of ``size`` px, as the paper's schedule reads.
      Where two layers overlap the nearer one wins, so behind the focal plane a CoC is drawn
      with the next smaller kernel (a 10 px CoC with the 7 px one) and in front with the next
      larger. The shipped ``lite`` weights were trained with it.

    ``extremes``, the disparity's lowest and highest value when the caller has them (one
    image), spares a pass over it.
    """
    if order == "paper":
        signed = disparity - focus  # [B,1,H,W]
        sizes = kernel_sizes(num_layers, max_size=max(blur, 1.0), schedule=schedule)
        n = len(sizes)
        coord = signed.abs().clamp(max=1.0) * (n - 1)
        # most blurred first: the sharp layer always ends on top (the authors' code)
        layers = [(j, sizes[j]) for j in range(n - 1, -1, -1)]
        return LayerPlan(coord, layers, gamma / max(n - 1, 1), False)
    if order != "depth":
        raise ValueError(f"order must be 'depth' or 'paper', got {order!r}")
    check_placement(placement)
    banded = (
        isinstance(focus, torch.Tensor)
        and focus.dtype == disparity.dtype
        and disparity.numel() > ROW_BAND
        and not tracks_grad(disparity, focus)
    )
    signed = None if banded else disparity - focus  # [B,1,H,W]
    if banded:
        # the largest CoC from the disparity's extremes (|d - f| is largest at one of them):
        # the same float as the maximum over every pixel, without a frame of temporaries
        if extremes is not None and disparity.shape[0] == 1:
            low, high = (disparity.new_tensor([v]) for v in extremes)
        else:
            low, high = disparity.detach().flatten(1).aminmax(dim=1)
        f = focus.detach().reshape(-1).to(disparity.dtype)
        coc = torch.maximum((high - f).abs(), (low - f).abs()) * blur
    else:
        coc = signed.abs() * blur
    max_coc = float(coc.detach().max()) if coc.numel() else 0.0
    # A kernel of s px (radius s // 2) draws a disc s - 1 px across, which is where layer j
    # sits with "nearest" placement (the 1-px kernel at CoC 0); with "blend" at the CoC the
    # kernel draws (effective_diameter). The schedule is in absolute px (the paper's sizes up
    # to 69 px, stretched only for larger CoCs), cut after the first kernel that covers the
    # scene's largest CoC: a small blur needs few layers, and a largest CoC of at most 1 px
    # none.
    nearest = placement != "paper"
    full = kernel_sizes(num_layers, max_size=max(max_coc + nearest, max_size), schedule=schedule)
    if placement == "blend":

        def drawn(size: int) -> float:
            return effective_diameter(size, kernel, int(blades))

    else:

        def drawn(size: int) -> float:
            return float(size - nearest)

    sizes = []
    for size in _unique_sizes(full):
        sizes.append(size)
        if drawn(size) >= max_coc or max_coc <= 1:
            break
    knots = [drawn(s) for s in sizes]
    half = placement == "nearest" and len(sizes) > 1
    if banded:
        # by bands of rows: a dozen elementwise passes over a band that stays in cache, not
        # over frames of fresh memory (0.39 s of a 12 MP render)
        coord = torch.empty_like(disparity)
        for part in row_bands(disparity):
            band = disparity[..., part, :] - focus
            coord[..., part, :] = _plan_coord(band, band.abs() * blur, knots, half)
    else:
        coord = _plan_coord(signed, coc, knots, half)
    n = len(sizes)
    layers = [(j, sizes[abs(j)]) for j in range(-(n - 1), n)]
    return LayerPlan(coord, layers, gamma / 14.0, True, placement == "blend")


def _plan_coord(
    signed: torch.Tensor, coc: torch.Tensor, knots: list[float], half: bool
) -> torch.Tensor:
    """The depth-order layer coordinate of the pixels whose disparity minus focus is
    ``signed`` and whose CoC is ``coc``, for layers at the CoCs ``knots`` (``half``:
    "nearest" placement)."""
    u = _interp(coc, knots)
    if half:
        # Between two layers both soft masks are close to 1 and the nearer layer hides the
        # other: behind the focal plane that is the sharper one, in front the more blurred
        # one. Half a layer toward the hidden side makes every pixel show the layer whose
        # kernel is nearest its CoC, on both sides; in front, CoCs under half a layer (1 px)
        # stay on the sharp layer.
        u = torch.where(signed < 0, u + 0.5, (u - 0.5).clamp(min=0))
    return torch.copysign(u, signed)


def layer_mask(coord: torch.Tensor, centre: int, gamma: float, grad: bool = True) -> torch.Tensor:
    """Soft layer mask ``0.5 + 0.5 tanh(gamma (1 - |coord - centre|))`` (``coord`` in layer
    units, already side-gated by :meth:`LayerPlan.side_coord`)."""
    # 0.5 + 0.5 tanh(x) == sigmoid(2 x); in place when no gradient is needed (hot path).
    # Values under _MASK_TINY are set to 0: the sigmoid's tail reaches denormal floats
    # (under 1.2e-38), and arithmetic on them (convolutions of the layer) is tens of times
    # slower on x86 CPUs.
    if grad:
        return F.threshold(
            torch.sigmoid(2 * gamma * (1.0 - (coord - centre).abs())), _MASK_TINY, 0.0
        )
    t = coord - centre
    return F.threshold_(t.abs_().mul_(-2 * gamma).add_(2 * gamma).sigmoid_(), _MASK_TINY, 0.0)


def blend_mask(coord: torch.Tensor, centre: int, grad: bool = True) -> torch.Tensor:
    """The ``"blend"`` placement's layer mask: ``clamp(t + 1, 0, 1)`` for ``t = coord -
    centre < 1``, else 0 (``coord`` in layer units, already side-gated).

    Layers composite in increasing ``coord``. A pixel at ``coord = j + t`` (``0 <= t < 1``)
    is in layer ``j`` in full and in layer ``j + 1`` by ``t``; where its neighbours share its
    depth, ``j + 1`` (over ``j``) hides ``t`` of ``j``: the pixel shows ``(1 - t) K_j + t
    K_{j + 1}``, the kernels mixed in proportion to where the CoC lies between theirs (the
    plan puts ``coord`` on that scale). A pixel on a layer's centre is in that layer alone.
    Where the pixel stands alone in front of another depth (a highlight on a far wall), both
    layers show it: it weighs ``1 + t`` there (the soft masks of the other placements put such
    a pixel in both of its layers in full, so it weighs 2).
    """
    if grad:
        t = coord - centre
        m = torch.where(t < 1, (t + 1).clamp(0, 1), torch.zeros_like(t))
        return F.threshold(m, _MASK_TINY, 0.0)
    m = (coord - centre).add_(1)
    m.masked_fill_(m >= 2, 0.0)
    return F.threshold_(m.clamp_(0, 1), _MASK_TINY, 0.0)


def mask_reach(gamma: float) -> float:
    # distance beyond |coord - centre| = 1 where the soft mask drops below _MASK_EPS
    return math.atanh(1 - 2 * _MASK_EPS) / gamma


# --------------------------------------------------------------------------------------
