"""Weighted layered rendering (D2F's ``f_l``), radiance virtualisation boost and refocusing.

Pure tensor code: no file I/O, no learned parameters.

Two compositing orders are provided:

* ``order="depth"`` (default): a signed, depth-ordered refocus. For a disparity map ``d``
  (1 = nearest), a focal disparity ``focus`` and a blur amount ``K`` (px), a pixel's
  circle-of-confusion (CoC) diameter is ``K * |d - focus|``. Pixels behind and in front of the
  focal plane go to separate layers, and layers are composited far to near, so a blurred
  foreground spills over a sharp subject as it does through a real lens. With
  ``placement="nearest"`` (default) each pixel is drawn with the kernel nearest its CoC on
  both sides of focus; ``placement="paper"`` reads the kernel sizes as CoCs, which draws CoCs
  behind the focal plane with the next smaller kernel (see :func:`layer_plan`).
* ``order="paper"``: the authors' ordering by unsigned defocus ``D = |d - focus|`` (most blurred
  layer first, the sharp layer always on top), with layer ``l`` covering ``D = l / (L - 1)`` and
  the kernel schedule stretched so that ``D = 1`` gets a kernel of ``K`` px. With ``K = 69`` and
  ``focus = 0`` this is exactly the paper's ``f_l(X, D)``.

Both use the paper's soft layer masks ``0.5 + 0.5 tanh(gamma (1/(L-1) - |D - l/(L-1)|))`` and
the compositing ``acc = acc (1 - K*M) + K*(M X)``. The radiance normalisation
``f_l(R I, D) / f_l(R, D)`` is done in one pass: both share the alpha ``K*M``.

Speed (see ``python -m d2f_core.bench render``): layers holding no pixels are skipped, each
layer is blurred only inside its support box, kernels are applied by FFT with cached spectra
(direct convolution for small kernels), and large kernels are applied at reduced resolution
when ``quality`` allows it.
"""

from __future__ import annotations

import contextlib
import functools
import glob
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .errors import InputTypeError
from .kernels import coarse_kernel, kernel_sizes

__all__ = [
    "PLACEMENTS",
    "QUALITY_PRESETS",
    "LayeredRenderer",
    "LANES",
    "check_focus_blur",
    "disparity_tensor",
    "grid_factor",
    "hdr_boost",
    "highlight_mask",
    "image_tensor",
    "layer_plan",
    "render",
    "render_bokeh",
]

HDR_ALPHA = 3.0
HDR_BETA = 5.0
HDR_THRESHOLD = 0.99
GAMMA = 100.0
# Mask values below this are treated as empty when finding a layer's support.
_MASK_EPS = 1e-4
# Mask values at or below this are 0 (no denormal floats in a layer: see _layer_mask).
_MASK_TINY = 1e-20
# Layers are located on a coarse grid of this many pixels before exact masks are computed.
_TILE = 8
_DIRECT_MAX_SIZE = 11
# Largest kernel (px) whose coarse-grid version is fitted (kernels.coarse_kernel) rather than
# sampled: the float64 fit grows with the square of the kernel (40 ms at 513 px). Sampling
# costs little at that size: a 257 px kernel at 1/4 resolution measured 69 dB sampled and
# 80 dB fitted against the full-resolution blur of 8-px blocks.
_FIT_MAX_SIZE = 513
_CL = torch.channels_last
# Where a layer's other side is moved to in layer units: far enough that its mask is 0.
_FAR = 1e4
#: Layer placements of the depth order (:func:`layer_plan`), the default first.
PLACEMENTS = ("nearest", "paper")


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


# --------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------


def _check_tensor(name: str, x: torch.Tensor, channels: int | None) -> tuple[float, float]:
    """Check shape, dtype and finiteness; returns ``x``'s (min, max) ((0, 0) when empty)."""
    if not isinstance(x, torch.Tensor):
        raise InputTypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4:
        raise ValueError(f"{name} must have shape (B, C, H, W), got {tuple(x.shape)}")
    if channels is not None and x.shape[1] != channels:
        raise ValueError(f"{name} must have {channels} channel(s), got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise InputTypeError(f"{name} must be a floating-point tensor, got {x.dtype}")
    if not x.numel():
        return 0.0, 0.0
    extremes = _extremes(x)
    if not all(math.isfinite(v) for v in extremes):
        raise ValueError(f"{name} contains NaN or inf")
    return extremes


def _extremes(x: torch.Tensor) -> tuple[float, float]:
    """(min, max) of ``x`` in one pass; NaN when ``x`` holds a NaN."""
    lo, hi = torch.aminmax(x.detach())
    return float(lo), float(hi)


#: the largest blur ``K`` (CoC diameter in px at ``|d - focus| = 1``) any entry point takes
MAX_BLUR = 10000.0


def _number(name: str, value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputTypeError(f"{name} must be a number, got {value!r}") from None


def _check_focus(focus) -> float:
    f = _number("focus", focus)
    if not math.isfinite(f) or not 0 <= f <= 1:
        raise ValueError(f"focus must be in [0, 1], got {focus!r}")
    return f


def _check_blur(blur) -> float:
    b = _number("blur", blur)
    if not math.isfinite(b) or not 0 <= b <= MAX_BLUR:
        raise ValueError(f"blur must be a number in [0, {MAX_BLUR:g}] px, got {blur!r}")
    return b


def check_focus_blur(focus, blur) -> tuple[float, float]:
    """``(focus, blur)`` as floats: focus in [0, 1], blur (K, px) in [0, :data:`MAX_BLUR`].

    The one check of both. Each public entry that takes them (``D2F.render``,
    :func:`render`, :func:`render_bokeh`, :class:`LayeredRenderer`,
    ``adaptive.choose_settings`` and ``adaptive.render_adaptive``) checks them once, here,
    and passes the floats on with ``checked=True`` so that no layer below checks them again.
    Raises ``ValueError`` (:class:`~d2f_core.InputTypeError` for a value that is not a number)
    naming the value.
    """
    return _check_focus(focus), _check_blur(blur)


def _check_placement(placement: str) -> None:
    if placement not in PLACEMENTS:
        raise ValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")


def _focus_tensor(focus, batch: int, ref: torch.Tensor, check: bool = True) -> torch.Tensor:
    """``focus`` (a number or ``batch`` values) as a ``(batch, 1, 1, 1)`` tensor on ``ref``'s
    device and dtype; checked as :func:`check_focus_blur` does unless ``check`` is False."""
    if not isinstance(focus, torch.Tensor):
        value = _check_focus(focus) if check else float(focus)
        return torch.full((batch, 1, 1, 1), value, device=ref.device, dtype=ref.dtype)
    f = focus.detach().to(device=ref.device, dtype=ref.dtype).reshape(-1)
    if f.numel() == 1:
        f = f.expand(batch)
    if f.numel() != batch:
        raise ValueError(f"focus must be a scalar or have {batch} values, got {f.numel()}")
    if check:
        for value in _extremes(f):  # NaN when f holds one
            _check_focus(value)
    return f.view(batch, 1, 1, 1)


# --------------------------------------------------------------------------------------
# threads
# --------------------------------------------------------------------------------------

# How often (s) a render looks again at how busy the machine is.
_RECHECK_S = 0.05


def _running_elsewhere() -> int | None:
    """Threads of other processes running right now (Linux ``/proc``); ``None`` elsewhere.

    ``/proc/loadavg`` counts every runnable thread of the machine, this process's own
    (the reading thread, and OpenMP workers still spinning after an operation) among them.
    """
    try:
        with open("/proc/loadavg", encoding="ascii") as fh:
            running = int(fh.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return None
    ours = 0
    for path in glob.glob("/proc/self/task/*/stat"):
        try:
            with open(path, encoding="ascii", errors="replace") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):  # the thread ended meanwhile
            continue
        ours += state == "R"
    return max(0, running - max(ours, 1))


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _threads_free(wanted: int) -> int:
    """Of ``wanted`` threads, how many have a core to themselves now (at least 1)."""
    others = _running_elsewhere()
    if others is None:
        return wanted
    return max(1, min(wanted, _usable_cores() - others))


class _ThreadChoice:
    """Torch threads for one render: the caller's count while the machine has a core free for
    each, fewer while other processes keep cores busy (looked at again every
    :data:`_RECHECK_S` s by :meth:`check`).

    A render is some hundreds of tensor operations, each an OpenMP parallel region whose end
    waits for every thread: with one thread descheduled by another process, each operation
    waits for the scheduler to run it again. 2-thread renders were 5-11x slower than 1-thread
    ones beside one busy process.
    """

    def __init__(self) -> None:
        self.saved = self.current = 1
        self.last = 0.0

    def __enter__(self) -> _ThreadChoice:
        self.saved = self.current = torch.get_num_threads()
        self.check(force=True)
        return self

    def check(self, force: bool = False) -> None:
        if self.saved <= 1:
            return
        now = time.perf_counter()
        if not force and now - self.last < _RECHECK_S:
            return
        self.last = now
        want = _threads_free(self.saved)
        if want != self.current:
            torch.set_num_threads(want)
            self.current = want

    def __exit__(self, *exc) -> None:
        if self.current != self.saved:
            torch.set_num_threads(self.saved)
            self.current = self.saved


# --------------------------------------------------------------------------------------
# radiance
# --------------------------------------------------------------------------------------


def highlight_mask(image: torch.Tensor, threshold: float = HDR_THRESHOLD) -> torch.Tensor:
    """``M_h``: 1 where any of R, G, B is at least ``threshold``.

    Shape: ``(B, 3, H, W) -> (B, 1, H, W)``.
    """
    return (image >= threshold).any(dim=1, keepdim=True).to(image.dtype)


def _tracks_grad(*tensors: torch.Tensor | None) -> bool:
    """Whether autograd records work on any of ``tensors`` (``None`` skipped) now."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


#: Pixels (over the batch) of the bands of rows that the plan and the highlight weights are
#: computed in without gradients (1 MB of float32 each).
_ROW_BAND = 1 << 18


def _row_bands(t: torch.Tensor) -> list[slice]:
    """Slices of rows of ``t`` ``(B, C, H, W)`` by :data:`_ROW_BAND` pixels over the batch
    (at least one row each)."""
    rows = max(1, _ROW_BAND // max(1, t.shape[0] * t.shape[-1]))
    return [slice(r0, r0 + rows) for r0 in range(0, t.shape[-2], rows)]


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


def hdr_boost(
    image: torch.Tensor,
    radiance: torch.Tensor | None = None,
    *,
    alpha: float = HDR_ALPHA,
    beta: float = HDR_BETA,
    threshold: float = HDR_THRESHOLD,
    per_channel: bool = False,
) -> torch.Tensor:
    """Radiance weights ``R = M_h * alpha * I^beta + (1 - M_h) * R0``.

    With ``per_channel=False`` (default) ``I`` is the brightest channel, so ``R`` has one
    channel: a saturated pixel keeps its hue and the renderer blurs 5 channels instead of 7.
    ``per_channel=True`` is the paper's literal per-channel form.

    Args:
        image: ``(B, 3, H, W)`` in [0, 1].
        radiance: ``R0``, ``(B, 1, H, W)`` from the radiance network; ``None`` means ones.

    Returns:
        ``(B, 1, H, W)`` (or ``(B, 3, H, W)`` per channel); saturated pixels weigh up to
        ``alpha`` times more than ``R0``.
    """
    if per_channel:
        mask = highlight_mask(image, threshold)  # [B,1,H,W]
        base = torch.ones_like(mask) if radiance is None else radiance
        return mask * alpha * _power(image.clamp(0, 1), beta) + (1 - mask) * base
    whole = radiance is not None and (
        radiance.shape[-2:] != image.shape[-2:] or radiance.dtype != image.dtype
    )  # a radiance that broadcasts, or promotes: as over the whole frame
    if _tracks_grad(image, radiance) or whole or image[:, :1].numel() <= _ROW_BAND:
        return _boost_rows(image, radiance, alpha, beta, threshold)
    # by bands of rows, each in cache (0.16 s of a 12 MP render over whole frames)
    out = image.new_empty(image.shape[0], 1, *image.shape[2:])
    for part in _row_bands(image):
        r = None if radiance is None else radiance[..., part, :]
        out[..., part, :] = _boost_rows(image[..., part, :], r, alpha, beta, threshold)
    return out


def _boost_rows(image, radiance, alpha: float, beta: float, threshold: float) -> torch.Tensor:
    # the brightest channel is at least the threshold exactly where any channel is
    peak = image.amax(dim=1, keepdim=True)
    boost = _power(peak.clamp(0, 1), beta).mul_(alpha)
    return torch.where(peak >= threshold, boost, 1.0 if radiance is None else radiance)


# --------------------------------------------------------------------------------------
# layer plan
# --------------------------------------------------------------------------------------


@dataclass
class LayerPlan:
    """Where each pixel sits among the layers, and the layers in compositing order.

    ``coord`` is the per-pixel layer coordinate (layer ``j`` is centred on ``coord == j``),
    ``order`` lists ``(centre, kernel size)`` back to front, ``gamma`` is the mask sharpness in
    layer units, ``signed`` says whether a layer only takes pixels on its side of focus.
    """

    coord: torch.Tensor  # [B,1,H,W]
    order: list[tuple[int, int]]
    gamma: float
    signed: bool

    def __post_init__(self) -> None:
        self._sides: dict[int, torch.Tensor] = {}

    def side_coord(self, centre: int) -> torch.Tensor:
        """``coord`` with the pixels on the other side of focus pushed out of reach.

        A layer on one side of the focal plane never takes pixels from the other side: their
        mask underflows to exactly 0.
        """
        if not self.signed or centre == 0:
            return self.coord
        side = 1 if centre > 0 else -1
        if side not in self._sides:
            far = torch.full_like(self.coord, -_FAR * side)
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
    placement: str = "nearest",
    extremes: tuple[float, float] | None = None,
) -> LayerPlan:
    """Assign pixels to layers (back-to-front compositing order).

    ``placement`` (depth order only) says where a pixel goes between two layers:

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
    _check_placement(placement)
    banded = (
        isinstance(focus, torch.Tensor)
        and focus.dtype == disparity.dtype
        and disparity.numel() > _ROW_BAND
        and not _tracks_grad(disparity, focus)
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
    # sits with "nearest" placement (the 1-px kernel at CoC 0). The schedule is in absolute px
    # (the paper's sizes up to 69 px, stretched only for larger CoCs), cut after the first
    # kernel that covers the scene's largest CoC: a small blur needs few layers, and a largest
    # CoC of at most 1 px none.
    nearest = placement == "nearest"
    full = kernel_sizes(num_layers, max_size=max(max_coc + nearest, max_size), schedule=schedule)
    sizes = []
    for size in _unique_sizes(full):
        sizes.append(size)
        if size - nearest >= max_coc or max_coc <= 1:
            break
    knots = [float(s - nearest) for s in sizes]
    half = nearest and len(sizes) > 1
    if banded:
        # by bands of rows: a dozen elementwise passes over a band that stays in cache, not
        # over frames of fresh memory (0.39 s of a 12 MP render)
        coord = torch.empty_like(disparity)
        for part in _row_bands(disparity):
            band = disparity[..., part, :] - focus
            coord[..., part, :] = _plan_coord(band, band.abs() * blur, knots, half)
    else:
        coord = _plan_coord(signed, coc, knots, half)
    n = len(sizes)
    layers = [(j, sizes[abs(j)]) for j in range(-(n - 1), n)]
    return LayerPlan(coord, layers, gamma / 14.0, True)


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


def _layer_mask(coord: torch.Tensor, centre: int, gamma: float, grad: bool = True) -> torch.Tensor:
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


def _mask_reach(gamma: float) -> float:
    # distance beyond |coord - centre| = 1 where the soft mask drops below _MASK_EPS
    return math.atanh(1 - 2 * _MASK_EPS) / gamma


# --------------------------------------------------------------------------------------
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
        return _upsample_window(self.x, self.grid, y0 - oy, y1 - oy, x0 - ox, x1 - ox)

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
        for c0, c1 in _spans(cols, gap=3):
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


def _input_pixels(
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


def _under(acc: torch.Tensor, hidden: HiddenSurface, grad: bool) -> torch.Tensor:
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


def _upsample_window(grid: torch.Tensor, factor: int, y0: int, y1: int, x0: int, x1: int):
    """Rows ``y0:y1`` and columns ``x0:x1`` (px) of the bilinear upsampling of ``grid``
    ``(B, C, gh, gw)`` by ``factor`` (:func:`_upsample`): only the cells they read."""
    gh, gw = grid.shape[-2:]
    a, b = max(0, y0 // factor - 1), min(gh, -(-y1 // factor) + 1)
    c, d = max(0, x0 // factor - 1), min(gw, -(-x1 // factor) + 1)
    if factor <= 4 and not _tracks_grad(grid):
        # the rows cut before the columns are interpolated: less work, and a contiguous
        # result when every column is kept
        rows = _upsample_axis(grid[..., a:b, c:d], factor, -2)
        rows = rows[..., y0 - a * factor : y1 - a * factor, :]
        return _upsample_axis(rows, factor, -1)[..., x0 - c * factor : x1 - c * factor]
    up = _upsample(grid[..., a:b, c:d], factor, (b - a) * factor, (d - c) * factor)
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
        up = _upsample(filled, 2, *v.shape[-2:])
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
        # rounding would go either way); the largest of them, from the extremes
        most, least = float(ahead.max()), float(ahead.min())
        if most > 0:
            top = max(top, math.ceil(most))
        if least <= 0:
            top = max(top, math.floor(-least))
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
# convolution
# --------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=1024)
def _fast_len(n: int) -> int:
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
def _kernel(
    spec: KernelSpec, size: int, factor: int, device: str, dtype: torch.dtype, gain: float = 1.0
):
    """Kernel for a full-res CoC of ``size`` px applied on a grid ``factor`` px apart, times
    ``gain`` (``1 / factor**2`` applies it to cell sums instead of cell means).

    On a coarse grid this is the least-squares fit of :func:`coarse_kernel` up to
    ``_FIT_MAX_SIZE`` px, and the aperture sampled on the coarse grid above it.
    """
    if gain != 1.0:
        return _kernel(spec, size, factor, device, dtype) * gain
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
    k = _kernel(spec, size, factor, device, dtype, gain)
    return torch.fft.rfft2(k, s=(fh, fw))


def _direct(zp: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Valid depthwise convolution of the zero-padded ``zp`` with the aperture kernel ``k``.

    Shape: ``(B, C, h + 2r, w + 2r) -> (B, C, h, w)``.
    """
    c = zp.shape[1]
    weight = k.flip(-1, -2).expand(c, 1, -1, -1)
    # channels-last depthwise convolution is several times faster on CPU for small kernels
    return F.conv2d(zp.contiguous(memory_format=_CL), weight, groups=c)


def _fft(
    z: torch.Tensor, spec: KernelSpec, size: int, factor: int, gain: float = 1.0
) -> torch.Tensor:
    """Full linear convolution of ``z`` (zero outside) by FFT with a cached kernel spectrum
    (of the kernel times ``gain``).

    Shape: ``(B, C, h, w) -> (B, C, h + 2r, w + 2r)``.
    """
    k = _kernel(spec, size, factor, str(z.device), z.dtype)
    r = k.shape[-1] // 2
    h, w = z.shape[-2:]
    fh, fw = _fast_len(h + 2 * r), _fast_len(w + 2 * r)
    spec_k = _spectrum(spec, size, factor, fh, fw, str(z.device), z.dtype, gain)
    return _fft_by(z.contiguous(), spec_k, fh, fw, h + 2 * r, w + 2 * r)


def _fft_by(
    z: torch.Tensor, spec_k: torch.Tensor, fh: int, fw: int, height: int, width: int
) -> torch.Tensor:
    """Convolution of ``z`` by the kernel whose real FFT at size ``fh x fw`` is ``spec_k``,
    cropped to ``height x width``."""
    spectrum = torch.fft.rfft2(z, s=(fh, fw))
    if _tracks_grad(z):
        spectrum = spectrum * spec_k
    else:
        spectrum.mul_(spec_k)
    return torch.fft.irfft2(spectrum, s=(fh, fw))[..., :height, :width]


def _pool(
    z: torch.Tensor, factor: int, out: torch.Tensor | None = None, mean: bool = True
) -> torch.Tensor:
    """Mean (or with ``mean=False`` the sum) over ``factor x factor`` cells (a power of 2
    dividing H and W), written into ``out`` when given.

    Sums of strided views: several times faster than ``avg_pool2d`` on CPU.
    """
    if factor == 1:
        return z
    return _pool_from_rows(z[..., 0::2, :] + z[..., 1::2, :], factor, out, mean)


def _pool_product(
    x: torch.Tensor,
    mask: torch.Tensor,
    factor: int,
    out: torch.Tensor | None = None,
    mean: bool = True,
) -> torch.Tensor:
    """``_pool(mask * x, factor, mean=mean)`` without building ``mask * x`` at full
    resolution: the rows of each cell are multiplied and summed in one step (height and width
    divisible by ``factor``)."""
    rows = x[..., 0::2, :] * mask[..., 0::2, :]
    rows.addcmul_(x[..., 1::2, :], mask[..., 1::2, :])
    return _pool_from_rows(rows, factor, out, mean)


def _pool_from_rows(
    rows: torch.Tensor, factor: int, out: torch.Tensor | None, mean: bool
) -> torch.Tensor:
    """The rest of :func:`_pool` once row pairs are summed: column pairs, the mean, and the
    further halvings."""
    if factor == 2 and out is not None:
        torch.add(rows[..., 0::2], rows[..., 1::2], out=out)
        return out.mul_(0.25) if mean else out
    z = rows[..., 0::2] + rows[..., 1::2]
    return _pool(z.mul_(0.25) if mean else z, factor // 2, out=out, mean=mean)


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


def _layer_input(
    x: torch.Tensor,
    coord: torch.Tensor,
    centre: int,
    gamma: float,
    box: tuple[int, int, int, int],
    pads: tuple[int, int, int, int],
    grad: bool,
) -> torch.Tensor:
    """The premultiplied layer ``[M, M x]`` inside ``box``, zero-padded by ``pads``
    (top, bottom, left, right).

    Without gradients ``x`` is ``[1, x]`` (a leading channel of ones, see :func:`_with_ones`),
    so the layer is one product.

    Shape: ``x (B, C, H, W) -> (B, C + 1, h + top + bottom, w + left + right)``
    (``(B, C, ...)`` for ``[1, x]``).
    """
    y0, y1, x0, x1 = box
    mask = _layer_mask(coord[..., y0:y1, x0:x1], centre, gamma, grad)
    xs = x[..., y0:y1, x0:x1]
    if grad:
        z = torch.cat([mask, mask * xs], dim=1)
        top, bottom, left, right = pads
        return F.pad(z, (left, right, top, bottom)) if any(pads) else z
    z, inner = _empty_padded(x, x.shape[1], y1 - y0, x1 - x0, pads)
    torch.mul(xs, mask, out=inner)
    return z


def _layer_rows(
    x: torch.Tensor,
    coord: torch.Tensor,
    centre: int,
    gamma: float,
    box: tuple[int, int, int, int],
    factor: int,
):
    """The premultiplied layer ``mask * [1, x]`` inside ``box``, summed over ``factor x factor``
    cells, row by row on demand (no-gradient path; ``x`` is ``[1, x]``, the box a whole number
    of cells).

    Returns ``rows(r0, r1, out=None)``: rows ``r0:r1`` of the (pooled) layer, written into
    ``out`` when given. Only the mask is computed at once.
    """
    y0, y1, x0, x1 = box
    mask = _layer_mask(coord[..., y0:y1, x0:x1], centre, gamma, False)
    xs = x[..., y0:y1, x0:x1]

    def rows(r0: int, r1: int, out: torch.Tensor | None = None) -> torch.Tensor:
        span = slice(r0 * factor, r1 * factor)
        if factor == 1:
            return torch.mul(xs[..., span, :], mask[..., span, :], out=out)
        return _pool_product(xs[..., span, :], mask[..., span, :], factor, out=out, mean=False)

    return rows


def _with_ones(x: torch.Tensor) -> torch.Tensor:
    """``[1, x]``: a premultiplied layer is then ``mask * [1, x]`` in one product."""
    out = x.new_empty(x.shape[0], x.shape[1] + 1, *x.shape[2:])
    out[:, :1] = 1
    out[:, 1:] = x
    return out


def _direct_pads(
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


def _direct_stacked(
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
    ``dest``, ``(B, channels, r1 - r0, box width)`` (see :func:`_layer_rows`). The output
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


def _blend_stacked(
    acc: torch.Tensor, out: torch.Tensor, oy0: int, ox0: int, transmit: torch.Tensor | None = None
) -> None:
    """Composite a strip-stacked layer ``out`` (from :func:`_direct_stacked`) over ``acc`` in
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


# Layer-coordinate bins per layer in the support histograms (:func:`_support_boxes`).
_BINS = 4


def _support_boxes(
    plan: LayerPlan, height: int, width: int
) -> dict[int, tuple[int, int, int, int]]:
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
    down, across = -(-height // _TILE), -(-width // _TILE)
    reach = 1.0 + _mask_reach(plan.gamma)
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
    row = torch.arange(height, device=dev, dtype=dtype).div_(_TILE).floor_().view(-1, 1)
    col = torch.arange(width, device=dev, dtype=dtype).div_(_TILE).floor_().view(1, -1)
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
            int(rows[0]) * _TILE,
            min(height, (int(rows[-1]) + 1) * _TILE),
            int(cols[0]) * _TILE,
            min(width, (int(cols[-1]) + 1) * _TILE),
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
# rendering
# --------------------------------------------------------------------------------------


def _overlap(
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


def _blend(acc: torch.Tensor, part: torch.Tensor, y0: int, x0: int, grad: bool) -> torch.Tensor:
    """Composite ``part`` (alpha in channel 0, premultiplied colour after it) over ``acc``
    at offset (y0, x0), clipped to the frame. Returns the updated accumulator."""
    meet = _overlap(acc.shape[-2:], y0, x0, part.shape[-2:])
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


def _composite(
    x: torch.Tensor,
    plan: LayerPlan,
    spec: KernelSpec,
    *,
    method: str,
    quality: str,
    full_frame: bool,
    front: bool = False,
    front_size: float = 0.0,
    threads: _ThreadChoice | None = None,
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

    Without gradients ``x`` carries the leading channel of ones of :func:`_with_ones`.

    Layers whose kernel is large enough for ``quality`` are masked, pooled, blurred and
    composited on a 1/2 or 1/4 resolution grid. A run of consecutive such layers is composited
    there from zero into (colour, transmittance) and merged into the full-resolution
    accumulator once, ``acc = acc * T + C``, which is exact at the coarse level because
    compositing is linear in the accumulator.

    Without gradients a layer convolved directly is written strip by strip into a
    channels-last buffer that stacks its strips along the channel axis (:func:`_direct_stacked`),
    sized so that only the part of its blur that lands in the frame is computed, and coarse
    layers are pooled straight from the product (:func:`_layer_rows`). The accumulator and
    everything else stay planar.

    Shape: ``x (B, C, H, W) -> acc (B, C, H, W), alpha (B, 1, H, W)``, split
    ``((B, C + 1, H, W), (B, 1, H, W))``.
    """
    b, c, height, width = x.shape
    grad = _tracks_grad(x, plan.coord)
    dev, dtype = str(x.device), x.dtype
    if not grad:
        c -= 1  # the channel of ones
    acc = x.new_zeros(b, c + 1, height, width)  # channel 0 is the alpha
    if full_frame:
        boxes = {centre: (0, height, 0, width) for centre, _ in plan.order}
    else:
        boxes = _support_boxes(plan, height, width)
    blank = True  # nothing composited into acc yet
    group: tuple[int, torch.Tensor, torch.Tensor | None] | None = None

    def flush(acc: torch.Tensor) -> torch.Tensor:
        nonlocal group, blank
        if group is None:
            return acc
        factor, colour, transmit = group
        group = None
        if transmit is None:
            # over an empty accumulator the composite is the group's colour alone
            blank = False
            return _upsample(colour, factor, height, width)
        up = _upsample(torch.cat([colour, transmit], dim=1), factor, height, width)
        if grad:
            return acc * up[:, -1:] + up[:, :-1]
        return acc.mul_(up[:, -1:]).add_(up[:, :-1])

    back = None  # the accumulator behind the focal plane, once the front layers begin
    for centre, size in plan.order:
        box = boxes.get(centre)
        if box is None:
            continue
        if threads is not None:
            threads.check()
        if front and back is None and plan.signed and centre > 0 and size >= front_size:
            back = flush(acc)
            acc = x.new_zeros(b, c + 1, height, width)
            blank = True
        factor = 1 if size <= 1 else grid_factor(size, quality)
        if spec.blades and factor > 2:
            # a 1/4-resolution grid rounds off a polygon's corners: visible in highlights
            factor = 2
        if group is not None and group[0] != factor:
            acc = flush(acc)
        coord = plan.side_coord(centre)
        k = _kernel(spec, size, factor, dev, dtype)
        r = k.shape[-1] // 2
        direct = method == "direct" or k.shape[-1] <= _DIRECT_MAX_SIZE
        if factor == 1:
            blank = False
            if size <= 1:
                z = _layer_input(x, coord, centre, plan.gamma, box, (0, 0, 0, 0), grad)
                acc = _blend(acc, z, box[0], box[2], grad)
            elif direct and not grad:
                rows = _layer_rows(x, coord, centre, plan.gamma, box, 1)
                out, oy0, ox0 = _direct_stacked(rows, x, c + 1, box, k, (height, width))
                _blend_stacked(acc, out, oy0, ox0)
            elif direct:
                pads, oy0, ox0 = _direct_pads(box, r, height, width)
                z = _layer_input(x, coord, centre, plan.gamma, box, pads, grad)
                acc = _blend(acc, _direct(z, k), oy0, ox0, grad)
            else:
                z = _layer_input(x, coord, centre, plan.gamma, box, (0, 0, 0, 0), grad)
                acc = _blend(acc, _fft(z, spec, size, 1), box[0] - r, box[2] - r, grad)
            continue
        # coarse layer: the box snapped to the coarse grid; the premultiplied layer is pooled,
        # so colour from other layers in the same cell never leaks into this one
        y0, y1, x0, x1 = box
        y0, x0 = y0 - y0 % factor, x0 - x0 % factor
        lh, lw = -(-height // factor), -(-width // factor)
        if group is None:
            # nothing to transmit to while the accumulator is empty
            transmit = None if blank and not grad else x.new_ones(b, 1, lh, lw)
            group = (factor, x.new_zeros(b, c + 1, lh, lw), transmit)
        # zero padding past the frame edge: the pooled alpha there is partial, as it should be
        bh, bw = (-(y1 - y0)) % factor, (-(x1 - x0)) % factor
        cbox = (y0 // factor, (y1 + bh) // factor, x0 // factor, (x1 + bw) // factor)
        # without gradients, cells are summed and the kernel carries the 1 / factor**2 of
        # the mean: one pass less per layer
        gain = 1.0 if grad else 1.0 / factor**2
        if grad or bh or bw:
            z = _layer_input(x, coord, centre, plan.gamma, (y0, y1, x0, x1), (0, bh, 0, bw), grad)

            def rows(r0, r1, out=None, z=z, factor=factor):
                span = slice(r0 * factor, r1 * factor)
                return _pool(z[..., span, :], factor, out=out, mean=grad)

        else:  # product and pooling in one: no full-resolution layer is built
            rows = _layer_rows(x, coord, centre, plan.gamma, (y0, y1, x0, x1), factor)
        if direct and not grad:
            k = _kernel(spec, size, factor, dev, dtype, gain)
            out, oy0, ox0 = _direct_stacked(rows, x, c + 1, cbox, k, (lh, lw))
            _blend_stacked(group[1], out, oy0, ox0, transmit=group[2])
            continue
        if direct:
            pads, oy0, ox0 = _direct_pads(cbox, r, lh, lw)
            zc = F.pad(rows(0, cbox[1] - cbox[0]), (pads[2], pads[3], pads[0], pads[1]))
            blurred = _direct(zc, k)
        else:
            blurred = _fft(rows(0, cbox[1] - cbox[0]), spec, size, factor, gain)
            oy0, ox0 = cbox[0] - r, cbox[2] - r
        colour = _blend(group[1], blurred, oy0, ox0, grad)
        transmit = group[2]
        if transmit is not None:
            transmit = _blend_transmit(transmit, blurred[:, :1], oy0, ox0, grad)
        group = (factor, colour, transmit)
    acc = flush(acc)
    if hidden is not None:
        # under every layer (over is associative): what the layers leave of it shows
        if back is not None:
            back = _under(back, hidden, grad)
        else:
            acc = _under(acc, hidden, grad)
    split = None
    if back is not None:
        transmit = 1 - acc[:, :1].clamp(0, 1)
        acc = back * transmit + acc if grad else acc.addcmul_(back, transmit)
        split = (back, transmit)
    return acc[:, 1:], acc[:, :1], split


def _upsample(z: torch.Tensor, factor: int, height: int, width: int) -> torch.Tensor:
    """Bilinear upsampling of a coarse-grid layer by ``factor`` (``F.interpolate``'s
    ``align_corners=False``, edges held), cropped to the frame.

    Without gradients and by 2 or 4, one interpolation per output phase and axis: 5-15 %
    faster than ``F.interpolate`` at slider sizes on this CPU (torch 2.13), which is
    1.5-2x faster by 8 and 16.
    """
    if factor > 4 or _tracks_grad(z):
        up = F.interpolate(z, scale_factor=factor, mode="bilinear", align_corners=False)
    else:
        up = _upsample_axis(_upsample_axis(z, factor, -2), factor, -1)
    return up[..., :height, :width]


def _upsample_axis(a: torch.Tensor, factor: int, dim: int) -> torch.Tensor:
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


def _blend_transmit(
    transmit: torch.Tensor, alpha: torch.Tensor, y0: int, x0: int, grad: bool
) -> torch.Tensor:
    """Multiply the transmittance by ``1 - alpha`` at offset (y0, x0), clipped to the frame."""
    meet = _overlap(transmit.shape[-2:], y0, x0, alpha.shape[-2:])
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
# large frames: tiles and bands
# --------------------------------------------------------------------------------------

# Frames of at least this many pixels render by tiles and bands (_render_tiled) when no
# gradient is needed: from about 1.4 MP it is the faster path (0.72-0.86x the time at
# 1024x1536, 0.99x at 896x1344 and 1.05-1.26x at 768x1152 and smaller, 2 threads), at
# 1.2-1.8 dB less against the exact render at 1024x1536 (58.5-61.1 dB).
_TILED_MIN_PIXELS = 1_400_000
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


def _tile_mask(ct: torch.Tensor, centre: int, gamma: float, gate: int) -> torch.Tensor:
    """Soft mask of layer ``centre`` for coordinates ``ct`` (in place on a copy), zero on
    the other side of focus when ``gate`` (+1 or -1) is set."""
    m = _layer_mask(ct, centre, gamma, False)
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
        self.c = coord.new_full((hp // 2, wp // 2), _FAR)
        gw = -(-width // 2)
        rows = max(2, (_ROW_BAND // max(width, 1)) // 2 * 2)
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

    def add_mixed(self, grid, centre, gamma, gate, hit, box, factor):
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
        m = _tile_mask(self.pc[idx], centre, gamma, gate)
        part = (self.px[:, idx] * m).sum(-1).mul_(0.25).to(grid.dtype)
        gy = (self.cy[idx] * 2 - box[0]) // factor
        gx = (self.cx[idx] * 2 - box[1]) // factor
        grid.view(grid.shape[0], -1).index_add_(1, gy * grid.shape[2] + gx, part)


def _upsample_rows(grid: torch.Tensor, factor: int, y0: int, y1: int, width: int):
    """Rows ``y0:y1`` (frame px) of the bilinear upsampling of the coarse ``grid``
    ``(C, gh, gw)`` by ``factor``, columns ``:width``: only the cells those rows read."""
    if factor == 1:
        return grid[:, y0:y1, :width]
    return _upsample_window(grid[None], factor, y0, y1, 0, width)[0]


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
    """:func:`_blend` (and with ``transmit`` :func:`_blend_transmit`) in place of the
    coarse layer ``grid`` ``(C, h, w)`` (each cell the sum of ``cells**2`` cell means)
    blurred by :func:`_fft`, one channel at a time: a spectrum and a blurred channel at a
    time, not all of them, are held.

    With ``pieces`` (boxes ``(y0, y1, x0, x1)`` in cells outside which ``grid`` is 0), each
    piece is blurred by its own FFT and the blurs are summed (the blur is linear): a layer
    scattered over the frame is transformed over its pieces, not over their bounding box."""
    gain = 1.0 / cells**2
    if pieces is None:

        def blur(z: torch.Tensor) -> torch.Tensor:
            return _fft(z, spec, size, factor, gain)

    else:
        blur = _PieceBlur(pieces, spec, size, factor, gain)
    alpha = blur(grid[None, :1])
    meet = _overlap(acc.shape[-2:], y0, x0, alpha.shape[-2:])
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
    """:func:`_fft` of a ``(1, 1, h, w)`` layer that is 0 outside ``pieces`` (boxes in cells),
    as the sum of the pieces' own FFT blurs; each piece's kernel spectrum is made once, for
    every channel (not in :func:`_spectrum`'s cache: piece sizes vary)."""

    def __init__(self, pieces, spec: KernelSpec, size: int, factor: int, gain: float) -> None:
        self.pieces = pieces
        self.args = (spec, size, factor, gain)
        self.spectra: dict[tuple[int, int], torch.Tensor] = {}

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        spec, size, factor, gain = self.args
        k = _kernel(spec, size, factor, str(z.device), z.dtype, gain)
        r = k.shape[-1] // 2
        h, w = z.shape[-2:]
        out = z.new_zeros(*z.shape[:-2], h + 2 * r, w + 2 * r)
        for a, b, c, d in self.pieces:
            ph, pw = b - a + 2 * r, d - c + 2 * r
            fh, fw = _fast_len(ph), _fast_len(pw)
            if (fh, fw) not in self.spectra:
                self.spectra[(fh, fw)] = torch.fft.rfft2(k, s=(fh, fw))
            spec_k = self.spectra[(fh, fw)]
            out[..., a : a + ph, c : c + pw] += _fft_by(z[..., a:b, c:d], spec_k, fh, fw, ph, pw)
        return out


def _spans(columns: list[int], gap: int = 2) -> list[tuple[int, int]]:
    """Sorted tile columns as inclusive spans, merged across gaps under ``gap`` tiles:
    [1, 2, 5, 9] -> [(1, 5), (9, 9)] with ``gap=3``."""
    spans: list[list[int]] = []
    for c in columns:
        if spans and c - spans[-1][1] <= gap:
            spans[-1][1] = c
        else:
            spans.append([c, c])
    return [(a, b) for a, b in spans]


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
        for c0, c1 in _spans(cols):
            rows = torch.nonzero(band[:, c0 : c1 + 1].any(dim=1)).flatten()
            r0, r1 = ty0 + b0 + int(rows[0]), ty0 + b0 + int(rows[-1]) + 1
            boxes.append((r0 * tile, r1 * tile, (tx0 + c0) * tile, (tx0 + c1 + 1) * tile))
    return boxes


def _render_tiled(
    image: torch.Tensor,
    weights: torch.Tensor | None,
    plan: LayerPlan,
    spec: KernelSpec,
    quality: str,
    threads: _ThreadChoice | None,
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
    ctiles = _TileSource(coord, t, _FAR)
    lo = ctiles.extreme(torch.amin)
    ctiles.refill(-_FAR)
    hi = ctiles.extreme(torch.amax)
    reach = 1.0 + _mask_reach(plan.gamma)

    layer_rows = functools.partial(_fill_layer, image, weights)

    bins = None
    if _EXACT_HITS:
        # (the tiles past the frame hold _FAR in lo and -_FAR in hi: the frame's extremes)
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
            m = _tile_mask(half.c[sy, sx], centre, plan.gamma, g)
            gy, gx = (ya - ty0 * t) // factor, (xa - tx0 * t) // factor
            dest = grid[:, gy : gy + (yb - ya) // factor, gx : gx + (xb - xa) // factor]
            if factor == 2:
                torch.mul(half.x[:, sy, sx], m, out=dest)
            else:
                _pool_product(half.x[:, sy, sx], m, factor // 2, out=dest, mean=False)
        half.add_mixed(grid, centre, plan.gamma, g, hit, (ty0 * t, tx0 * t), factor)
        gh, gw = hp // factor, wp // factor
        # each grid cell sums (factor / 2)**2 cell means: the kernel carries 1 / cells**2
        cells = factor // 2
        k = _kernel(spec, size, factor, dev, dtype, 1.0 / cells**2)
        if k.shape[-1] <= _DIRECT_MAX_SIZE:
            cbox = (ty0 * cell, ty1 * cell, tx0 * cell, tx1 * cell)

            def rows_of(r0, r1, out=None, grid=grid):
                return grid[None, :, r0:r1] if out is None else out.copy_(grid[None, :, r0:r1])

            blurred, oy, ox = _direct_stacked(rows_of, image, chans, cbox, k, (gh, gw))
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
                up = _upsample(back[1], back[0] // factor, gh, gw)
                back = (factor, up.contiguous())
            if stacked:
                _blend_stacked(back[1], blurred, oy, ox)
            else:
                _blend_fft(back[1], grid, spec, size, factor, oy, ox, pieces=pieces, cells=cells)
            grid = blurred = None  # freed before the next layer's
            continue
        if not front or front[-1][0] != factor:
            front.append([factor, image.new_zeros(1, chans, gh, gw), image.new_ones(1, 1, gh, gw)])
        if stacked:
            _blend_stacked(front[-1][1], blurred, oy, ox, transmit=front[-1][2])
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
        up = _upsample(t0, f0 // factor, *colour.shape[-2:])
        colour.mul_(up)
        transmit.mul_(up)
        up = None
        colour.add_(_upsample(c0, f0 // factor, *colour.shape[-2:]))
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
            k = _kernel(spec, size, 1, dev, dtype)
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
                    m = _tile_mask(coord[0, ys, xa:xb], centre, plan.gamma, g)
                    layer_rows(ys, slice(xa, xb), m, out[0])
                    return out

                if size <= 1:
                    _blend(acc[None], rows_of(0, yb - ya), ya - y0, xa, False)
                    continue
                box = (ya - y0, yb - y0, xa, xb)
                out_s, oy0, ox0 = _direct_stacked(rows_of, image, chans, box, k, (y1 - y0, width))
                _blend_stacked(acc[None], out_s, oy0, ox0)
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


@functools.cache
def _keep_freed_heap() -> bool:
    """Let glibc keep freed frame-sized blocks for the next render (once per process).

    glibc maps blocks above its mmap threshold afresh and returns free memory at the top of
    its heap to the kernel once more than twice that threshold is free; the threshold rises by
    itself (to at most 32 MB) when a mapped block is freed. At its 128 kB starting point a
    render's temporaries are mapped, unmapped or trimmed and then zero-filled page by page again
    on the next render: 5-7 thousand page faults per 384x576 render, 5-14 thousand at 512x768.
    Freeing one 31 MB block moves the threshold where it would move in any long-running process
    that freed such a block: blocks under 31 MB then come from the heap, which glibc trims only
    when more than 62 MB is free at its top.
    Blocks over 31 MB (5-channel frames above about 1.6 MP) are still mapped each time.
    """
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc"):
            return False
    except (AttributeError, ValueError, OSError):  # not glibc, or not POSIX
        return False
    block = torch.empty(31 << 20, dtype=torch.uint8)
    del block
    return True


def render(
    image: torch.Tensor,
    disparity: torch.Tensor,
    focus: float | torch.Tensor,
    blur: float,
    *,
    radiance: torch.Tensor | None = None,
    order: str = "depth",
    num_layers: int = 15,
    schedule: str = "growing",
    kernel: str = "soft",
    blades: int = 0,
    rotation: float = 0.0,
    highlight_boost: bool = True,
    method: str = "fft",
    quality: str = "balanced",
    gamma: float = GAMMA,
    full_frame: bool = False,
    placement: str = "nearest",
    behind: bool = False,
    front_size: float = 0.0,
    hidden: bool = True,
    checked: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render bokeh with weighted layered rendering.

    Args:
        image: all-in-focus image, ``(B, 3, H, W)`` in [0, 1].
        disparity: ``(B, 1, H, W)`` in [0, 1], 1 = nearest.
        focus: focal disparity in [0, 1], a float or a ``(B,)`` tensor.
        blur: ``K``, the CoC diameter in px (at this resolution) for ``|d - focus| = 1``.
        radiance: ``R0`` from the radiance network, ``(B, 1, H, W)``; ``None`` means ones.
        order: ``"depth"`` (occlusion-correct refocus) or ``"paper"`` (authors' ordering).
        num_layers: kernel sizes per side of the focal plane (``L`` in the paper).
        schedule: ``"growing"`` (paper) or ``"uniform"`` kernel-size schedule.
        kernel: ``"soft"`` (paper's tanh disk) or ``"hard"`` disk aperture.
        blades: aperture blades (0 = round), ``rotation`` in degrees.
        highlight_boost: apply the HDR boost (alpha 3, beta 5) to saturated pixels.
        method: ``"fft"`` or ``"direct"`` convolution for kernels above 7 px.
        quality: ``"exact"``, ``"high"``, ``"balanced"`` or ``"fast"``: how large a kernel
            must be before it is applied at 1/2 or 1/4 resolution.
        full_frame: disable the per-layer support boxes and empty-layer skipping (reference).
        placement: ``"nearest"`` or ``"paper"``: which layer a pixel between two layers goes
            to (depth order; see :func:`layer_plan`).
        behind: also return what the layers at and behind the focal plane make of each
            pixel (depth order): their share of the result and their own colour. A step
            that puts the photo's sharp pixels back where they are in focus must replace
            only that part: an in-focus pixel behind a blurred foreground is partly hidden
            by it, and pasting the photo over it cuts the foreground's blur off.
        front_size: with ``behind``, the layers in front of the focal plane drawn with a
            kernel under this many px count as behind it (a near subject's own slightly
            defocused rim is for the sharpening step to decide, like the subject).
        hidden: depth order: draw what lies behind the rim of a blurred near object
            (:func:`hidden_surface`), which a real lens sees past it and the photo does not
            show; ``False`` leaves those pixels to the near object alone. Gradients flow
            into the colours and layer coordinates it carries, not into where it is drawn.
        checked: ``True`` from a caller that has put ``focus`` and ``blur`` through
            :func:`check_focus_blur` already (``D2F.render``, :func:`render_bokeh`,
            ``adaptive.render_adaptive``): they are used as given, not checked again.

    Returns:
        ``(B, 3, H, W)`` in [0, 1]; with ``behind``, ``(image, share, colour)``: ``share``
        ``(B, 1, H, W)`` in [0, 1] and ``colour`` ``(B, 3, H, W)``, so that the image is
        ``share * colour + (the layers in front)``. Where nothing is in front of the
        focal plane (and in the paper order) ``share`` is ones and ``colour`` the image.
    """
    image_max = _check_tensor("image", image, 3)[1]
    disparity_range = _check_tensor("disparity", disparity, 1)
    if disparity.shape[0] != image.shape[0] or disparity.shape[-2:] != image.shape[-2:]:
        raise ValueError(
            f"disparity shape {tuple(disparity.shape)} does not match image {tuple(image.shape)}"
        )
    if radiance is not None:
        _check_tensor("radiance", radiance, 1)
        if radiance.shape[-2:] != image.shape[-2:] or radiance.shape[0] != image.shape[0]:
            raise ValueError(
                f"radiance shape {tuple(radiance.shape)} does not match image {tuple(image.shape)}"
            )
    if method not in ("fft", "direct"):
        raise ValueError(f"method must be 'fft' or 'direct', got {method!r}")
    if quality not in QUALITY_PRESETS:
        raise ValueError(f"quality must be one of {sorted(QUALITY_PRESETS)}, got {quality!r}")
    if kernel not in ("soft", "hard"):
        raise ValueError(f"kernel must be 'soft' or 'hard', got {kernel!r}")
    _check_placement(placement)
    if int(num_layers) != num_layers or num_layers < 1:
        raise ValueError(f"num_layers must be a positive integer, got {num_layers!r}")
    f = _focus_tensor(focus, image.shape[0], image, check=not checked)
    blur = float(blur) if checked else _check_blur(blur)
    options = dict(
        order=order,
        num_layers=num_layers,
        schedule=schedule,
        kernel=kernel,
        blades=blades,
        rotation=rotation,
        highlight_boost=highlight_boost,
        method=method,
        quality=quality,
        gamma=gamma,
        full_frame=full_frame,
        placement=placement,
        behind=behind,
        front_size=front_size,
        hidden=hidden,
    )
    if image.shape[0] <= 1:
        return _render(image, disparity, f, blur, image_max, disparity_range, radiance, **options)
    # one layer plan per image: the kernel schedule and the support boxes follow each
    # image's own CoCs, so a batch renders exactly as its images do one by one
    parts = []
    for i in range(image.shape[0]):
        one, disp = image[i : i + 1], disparity[i : i + 1]
        empty = not one.numel()
        parts.append(
            _render(
                one,
                disp,
                f[i : i + 1],
                blur,
                0.0 if empty else _extremes(one)[1],
                (0.0, 0.0) if empty else _extremes(disp),
                None if radiance is None else radiance[i : i + 1],
                **options,
            )
        )
    if behind:
        return tuple(torch.cat([p[i] for p in parts]) for i in range(3))
    return torch.cat(parts)


def _render(
    image: torch.Tensor,
    disparity: torch.Tensor,
    f: torch.Tensor,
    blur: float,
    image_max: float,
    disparity_range: tuple[float, float],
    radiance: torch.Tensor | None,
    *,
    order: str,
    num_layers: int,
    schedule: str,
    kernel: str,
    blades: int,
    rotation: float,
    highlight_boost: bool,
    method: str,
    quality: str,
    gamma: float,
    full_frame: bool,
    placement: str,
    behind: bool,
    front_size: float,
    hidden: bool,
):
    """:func:`render` of one image whose input it has checked: ``f`` the focal plane as a
    ``(1, 1, 1, 1)`` tensor, ``blur`` a float, ``image_max`` and ``disparity_range`` the
    extremes of the image and the disparity."""
    _keep_freed_heap()
    if disparity_range[0] < 0 or disparity_range[1] > 1:
        disparity = disparity.clamp(0, 1)
        disparity_range = tuple(min(max(v, 0.0), 1.0) for v in disparity_range)
    if blur == 0 and order == "depth":
        return _with_behind(image.clamp(0, 1), behind)

    grad = _tracks_grad(image, disparity, radiance)

    # Without gradients, fewer threads while other processes keep the cores busy (see
    # _ThreadChoice); a training step keeps its own.
    threads = None if grad else _ThreadChoice()
    # a large frame without gradients renders by tiles and bands, in bounded memory
    tiled = (
        not grad
        and not full_frame
        and not behind
        and method == "fft"
        and quality != "exact"
        and image.shape[-2] * image.shape[-1] >= _TILED_MIN_PIXELS
    )
    with threads or contextlib.nullcontext():
        # Without gradients the layers run in inference mode: no autograd bookkeeping in a few
        # hundred small tensor operations (about 1 ms per render). The result is divided out of
        # it, so callers get an ordinary tensor.
        with contextlib.nullcontext() if grad else torch.inference_mode():
            # the plan before the weights: the peak of either is then lower
            plan = layer_plan(
                disparity,
                f,
                blur,
                order=order,
                num_layers=int(num_layers),
                schedule=schedule,
                gamma=gamma,
                placement=placement,
                extremes=disparity_range,
            )
            weights = None
            if highlight_boost:
                if radiance is not None or image_max >= HDR_THRESHOLD:
                    weights = hdr_boost(image, radiance)
            elif radiance is not None:
                weights = radiance
            # a floor keeps the normalisation defined where every weight is 0 (e.g. pure red)
            if tiled:
                x = None  # read tile by tile and band by band by _render_tiled
                if weights is not None:
                    # the floor in place (a copy of a caller's radiance)
                    weights = weights + 1e-4 if weights is radiance else weights.add_(1e-4)
            elif weights is None:
                x = image if grad else _with_ones(image)
            elif grad:
                weights = weights + 1e-4
                x = torch.cat([weights * image, weights], dim=1)  # [B,3+Cr,H,W]
            else:
                # [1, w I, w] built in place: the layers are then mask * x in one product
                cw = weights.shape[1]
                x = image.new_empty(image.shape[0], 4 + cw, *image.shape[2:])
                x[:, :1] = 1
                torch.add(weights, 1e-4, out=x[:, 4:])
                torch.mul(image, x[:, 4:], out=x[:, 1:4])

            if tiled and any(size > 1 for _, size in plan.order):
                spec = KernelSpec(kernel, int(blades), float(rotation))
                return _render_tiled(image, weights, plan, spec, quality, threads, hidden)
            # when nothing is blurred every layer is the identity, so is the composite
            blurred = any(size > 1 for _, size in plan.order)
            if blurred:
                spec = KernelSpec(kernel, int(blades), float(rotation))
                under = None
                if hidden and plan.signed:
                    under = hidden_surface(_input_pixels(x, grad), plan)
                acc, alpha, split = _composite(
                    x,
                    plan,
                    spec,
                    method=method,
                    quality=quality,
                    full_frame=full_frame,
                    front=behind and plan.signed,
                    front_size=front_size,
                    threads=threads,
                    hidden=under,
                )
                norm, floor = (alpha, 1e-6) if weights is None else (acc[:, 3:], 1e-8)
                # pixels no layer reached (cannot happen with soft masks, but stay defined) keep
                # the input
                covered = norm > 1e-6
                norm = norm.clamp(min=floor) if grad else norm.clamp_(min=floor)
        if not blurred:
            return _with_behind(image.clamp(0, 1), behind)
        out = acc[:, :3] / norm
        if not bool(covered.all()):
            out = torch.where(covered, out, image)
        out = out.clamp(0, 1) if grad else out.clamp_(0, 1)
        if not behind:
            return out
        if split is None:
            return _with_behind(out, True)
        back, transmit = split  # back: alpha, colour (weighted), then the weight if any
        back_norm = back[:, :1] if weights is None else back[:, 4:]
        # the back layers' share of the normalised result, and their own normalised colour
        share = (back_norm * transmit / norm).clamp(0, 1)
        colour = (back[:, 1:4] / back_norm.clamp(min=floor)).clamp(0, 1)
        return out, share, torch.where(back_norm > 1e-6, colour, out)


def _with_behind(out: torch.Tensor, behind: bool):
    """``out``, or ``(out, ones, out)`` for a caller asking what lies behind the focal
    plane of a render with nothing in front of it."""
    return (out, torch.ones_like(out[:, :1]), out) if behind else out


def image_tensor(image) -> torch.Tensor:
    """Check an image (numpy ``H x W x 3`` or tensor ``[1, 3, H, W]`` / ``[3, H, W]``, uint8
    or float in [0, 1]) and return it as a ``(1, 3, H, W)`` float32 tensor.

    Raises ``ValueError`` (:class:`~d2f_core.InputTypeError` for a wrong type or dtype) for
    another shape or dtype, an empty image, NaN or inf, or float values outside [0, 1].
    """
    if isinstance(image, torch.Tensor):
        x = image
        if x.ndim == 3:
            x = x[None]
        if x.ndim != 4 or x.shape[:2] != (1, 3):
            raise ValueError(f"image tensor must have shape [1,3,H,W], got {tuple(image.shape)}")
        if x.dtype == torch.uint8:
            x = x.float() / 255.0
        elif not x.is_floating_point():
            raise InputTypeError(f"image tensor must be uint8 or float, got {x.dtype}")
        x = x.detach().float()
    elif isinstance(image, np.ndarray):
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image must have shape (H, W, 3), got {image.shape}")
        if image.dtype == np.uint8:
            x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]
            x = x.float().div_(255.0)
        elif np.issubdtype(image.dtype, np.floating):
            x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))
            x = x.permute(2, 0, 1)[None]
        else:
            raise InputTypeError(f"image must be uint8 or float, got {image.dtype}")
    else:
        kind = type(image).__name__
        raise InputTypeError(f"image must be a numpy array or torch tensor, got {kind}")
    if min(x.shape[-2:]) < 1:
        raise ValueError(f"image is empty: shape {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError("image contains NaN or inf")
    lo, hi = float(x.min()), float(x.max())
    if lo < 0 or hi > 1:
        raise ValueError(f"image float values must be in [0, 1], got [{lo:.3g}, {hi:.3g}]")
    return x.contiguous()


# Disparity maps converted from 8- or 16-bit depth round a little past [0, 1]: that much is
# clamped, anything beyond it refused.
_DISPARITY_SLACK = 1e-3


def disparity_tensor(disparity) -> torch.Tensor:
    """Check a disparity map (numpy array or tensor, ``H x W``, ``H x W x 1`` or with leading
    axes of 1) and return it as a ``(1, 1, H, W)`` float32 tensor in [0, 1].

    Raises ``ValueError`` (:class:`~d2f_core.InputTypeError` for a wrong type or dtype) for a
    map that is not real numbers, not 2-D, empty, holds NaN or inf, or leaves [0, 1] by more
    than 1e-3 (values within it are clamped).
    """
    if isinstance(disparity, torch.Tensor):
        if disparity.is_complex() or disparity.dtype == torch.bool:
            raise InputTypeError(f"disparity must be real numbers, got {disparity.dtype}")
        d = disparity.detach()
    elif isinstance(disparity, np.ndarray):
        kind = disparity.dtype
        if not (np.issubdtype(kind, np.integer) or np.issubdtype(kind, np.floating)):
            raise InputTypeError(f"disparity must be real numbers, got {kind}")
        d = torch.from_numpy(np.ascontiguousarray(disparity, dtype=np.float32))
    else:
        raise InputTypeError(
            f"disparity must be a numpy array or torch tensor, got {type(disparity).__name__}"
        )
    while d.ndim > 2 and d.shape[0] == 1:
        d = d[0]
    if d.ndim == 3 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 2 or min(d.shape) < 1:
        raise ValueError(f"disparity must have shape (H, W), got {tuple(disparity.shape)}")
    d = d.float()
    if not bool(torch.isfinite(d).all()):
        raise ValueError("disparity contains NaN or inf")
    lo, hi = float(d.min()), float(d.max())
    if lo < -_DISPARITY_SLACK or hi > 1 + _DISPARITY_SLACK:
        raise ValueError(f"disparity must be in [0, 1], got [{lo:.3g}, {hi:.3g}]")
    return d.clamp(0, 1)[None, None].contiguous()


def render_bokeh(image, disparity, focus: float, blur: float, **options) -> np.ndarray:
    """Render refocused bokeh for one image (numpy in, numpy out).

    Args:
        image: ``H x W x 3``, float32 in [0, 1] or uint8.
        disparity: ``H x W`` in [0, 1], 1 = nearest (checked by :func:`disparity_tensor`:
            values up to 1e-3 outside [0, 1] are clamped).
        focus: focal disparity in [0, 1].
        blur: ``K``, CoC diameter in px for ``|d - focus| = 1``, at the image's resolution.
        **options: passed to :func:`render` (``order``, ``num_layers``, ``kernel``, ``blades``,
            ``rotation``, ``highlight_boost``, ``quality``, ``method``...).

    Returns:
        ``H x W x 3`` float32 in [0, 1].
    """
    img = image_tensor(np.asarray(image))  # H x W x 3, whatever holds it
    if not isinstance(disparity, torch.Tensor):
        disparity = np.asarray(disparity)  # nested lists as numpy reads them
    disp = disparity_tensor(disparity)
    if disp.shape[-2:] != img.shape[-2:]:
        raise ValueError(
            f"disparity shape {tuple(disp.shape[-2:])} does not match image shape "
            f"{tuple(img.shape[-2:])}"
        )
    focus, blur = check_focus_blur(focus, blur)
    with torch.no_grad():
        out = render(img, disp, focus, blur, checked=True, **options)
    return out[0].permute(1, 2, 0).contiguous().numpy()


class LayeredRenderer(nn.Module):
    """Module form of :func:`render` with fixed options, for repeated renders.

    Kernel spectra are cached across calls (keyed by kernel, size and FFT shape).

    Shape: ``image (B, 3, H, W), disparity (B, 1, H, W) -> (B, 3, H, W)``.
    """

    def __init__(self, **options) -> None:
        super().__init__()
        self.options = dict(options)
        # validates the options once, on a 1-pixel image
        render(torch.zeros(1, 3, 1, 1), torch.zeros(1, 1, 1, 1), 0.0, 1.0, **self.options)

    def forward(
        self,
        image: torch.Tensor,
        disparity: torch.Tensor,
        focus: float | torch.Tensor,
        blur: float,
        radiance: torch.Tensor | None = None,
    ) -> torch.Tensor:
        return render(image, disparity, focus, blur, radiance=radiance, **self.options)
