"""Aperture kernels and the layer kernel-size schedules of D2F: the soft disk
``k(x, y) = 0.5 + 0.5 tanh(sigma (r^2 - x^2 - y^2) + phi)`` and the growing sizes
``1, 3, 5, ..., 69`` of the kernels ``K(s_l)``.

Every kernel is a 2-D tensor of shape ``(size, size)`` (``size`` odd) that sums to 1.
Builders take keyword-only ``device`` and ``dtype`` so a renderer can build them where its
data lives.
"""

from __future__ import annotations

import functools
import math

import torch

from ..errors import whole_number

__all__ = [
    "PAPER_GROWING_SIZES",
    "aperture_kernel",
    "coarse_kernel",
    "effective_diameter",
    "hard_disk_kernel",
    "kernel_sizes",
    "polygon_kernel",
    "soft_disk_kernel",
]

#: The paper's "growing sampling" schedule: 15 kernel sizes, steps of 2, 4, 6, then 8 px.
PAPER_GROWING_SIZES: tuple[int, ...] = (1, 3, 5, 7, 11, 15, 19, 23, 27, 33, 39, 45, 53, 61, 69)

SOFT_SIGMA = 0.25
SOFT_PHI = 0.5


def _check_size(size: int) -> int:
    size = whole_number(size, "size", 1)
    if size % 2 == 0:
        raise ValueError(f"size must be a positive odd integer, got {size}")
    return size


def _grid(size: int, scale: float, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    half = size // 2
    coords = torch.arange(-half, half + 1, device=device, dtype=dtype) * scale
    y, x = torch.meshgrid(coords, coords, indexing="ij")
    return x, y


def _normalise(kernel: torch.Tensor) -> torch.Tensor:
    total = kernel.sum()
    if not torch.isfinite(total) or total <= 0:
        raise ValueError("kernel has no positive weight")
    return kernel / total


#: Largest blade rotation accepted, in degrees: beyond it a float32 angle is too coarse.
MAX_ROTATION = 1e6


def check_rotation(rotation: float) -> float:
    """The blade rotation in degrees as a float; ``ValueError`` naming it when it is not a
    number, not finite or larger than :data:`MAX_ROTATION` in size."""
    try:
        value = float(rotation)
    except (TypeError, ValueError):
        raise ValueError(f"rotation must be a number of degrees, got {rotation!r}") from None
    if not math.isfinite(value) or abs(value) > MAX_ROTATION:
        raise ValueError(
            f"rotation must be a finite angle in degrees, at most {MAX_ROTATION:g} in size, "
            f"got {rotation!r}"
        )
    return value


def _radius_profile(x: torch.Tensor, y: torch.Tensor, blades: int, rotation: float) -> torch.Tensor:
    """Squared 'aperture radius' of each point: plain r^2 for a disk, polygon-scaled for blades."""
    rho2 = x * x + y * y
    if blades < 3:
        return rho2
    theta = torch.atan2(y, x) - math.radians(rotation)
    sector = 2.0 * math.pi / blades
    # A point at angle t inside a regular n-gon of circumradius r lies on the edge at
    # distance r*cos(pi/n)/cos(t' - pi/n); scale rho so the polygon edge maps to r.
    t = torch.remainder(theta, sector) - sector / 2.0
    scale = torch.cos(t) / math.cos(math.pi / blades)
    return rho2 * scale * scale


def aperture_kernel(
    size: int,
    *,
    shape: str = "soft",
    blades: int = 0,
    rotation: float = 0.0,
    radius: float | None = None,
    scale: float = 1.0,
    sigma: float = SOFT_SIGMA,
    phi: float = SOFT_PHI,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Build an aperture (bokeh) kernel.

    Args:
        size: odd side length of the kernel grid in pixels.
        shape: ``"soft"`` (the paper's tanh disk) or ``"hard"`` (1 inside the radius).
        blades: number of aperture blades; ``0`` (or < 3) gives a round aperture.
        rotation: polygon rotation in degrees.
        radius: aperture radius in grid pixels; defaults to ``size // 2`` as in the paper.
        scale: grid spacing, in units of the full-resolution pixel. A kernel for a layer that is
            rendered at 1/f resolution uses ``scale=f`` and ``radius`` in full-res pixels, so
            that it samples the same continuous aperture.
        sigma, phi: soft-edge parameters, ``k = 0.5 + 0.5 tanh(sigma (r^2 - x^2 - y^2) + phi)``.

    Returns:
        Tensor of shape ``(size, size)`` summing to 1.
    """
    size = _check_size(size)
    if shape not in ("soft", "hard"):
        raise ValueError(f"shape must be 'soft' or 'hard', got {shape!r}")
    if blades < 0 or blades in (1, 2):
        raise ValueError(f"blades must be 0 (round) or >= 3, got {blades}")
    dtype = dtype or torch.get_default_dtype()
    r = float(size // 2) if radius is None else float(radius)
    if r < 0 or not math.isfinite(r):
        raise ValueError(f"radius must be finite and >= 0, got {radius}")
    rotation = check_rotation(rotation)
    x, y = _grid(size, scale, device, dtype)
    rho2 = _radius_profile(x, y, blades, rotation)
    if shape == "soft":
        kernel = 0.5 + 0.5 * torch.tanh(sigma * (r * r - rho2) + phi)
    else:
        kernel = (rho2 <= r * r + 1e-6).to(dtype)
    return _normalise(kernel)


def _bilinear_matrix(n: int, factor: int, dtype: torch.dtype) -> torch.Tensor:
    """``(n * factor, n)``: 1-D bilinear upsampling by ``factor`` (``align_corners=False``),
    zero outside the ``n`` samples."""
    pos = (torch.arange(n * factor, dtype=dtype) + 0.5) / factor - 0.5
    lo = torch.floor(pos)
    frac = pos - lo
    cols = torch.arange(n, dtype=dtype)
    return (cols == lo[:, None]) * (1 - frac[:, None]) + (cols == lo[:, None] + 1) * frac[:, None]


def coarse_kernel(
    size: int,
    factor: int,
    *,
    shape: str = "soft",
    blades: int = 0,
    rotation: float = 0.0,
    fit: bool = True,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """The aperture kernel of ``size`` px for a layer rendered at ``1 / factor`` resolution.

    A reduced-resolution layer is averaged over ``factor x factor`` cells, convolved on the
    coarse grid and upsampled bilinearly (``align_corners=False``). Sampling the aperture on
    the coarse grid and then upsampling blurs its rim twice more (the cell average and the
    interpolation). This kernel is instead the least-squares fit: upsampled, it is closest to
    the full-resolution kernel averaged over a cell, the most a cell average can keep of it.
    The fit has small negative taps just outside the rim. ``fit=False`` gives the aperture
    sampled on the coarse grid instead, with the same taps.

    ``factor == 1`` returns the full-resolution kernel. The fit works in float64 on a canvas
    about ``size`` px wide, so its cost grows with ``size**2`` (40 ms at 513 px and factor 4
    here); cache the result.

    Returns:
        ``(n, n)`` with ``n = 2 ceil(r / factor + 1/2) + 1``, ``r = size // 2``; sums to 1.
    """
    size = _check_size(size)
    factor = whole_number(factor, "factor", 1)
    dtype = dtype or torch.get_default_dtype()
    options = dict(shape=shape, blades=blades, rotation=rotation)
    if factor == 1:
        return aperture_kernel(size, **options, device=device, dtype=dtype)
    radius = size // 2
    half = int(math.ceil(radius / factor + 0.5))
    if not fit:
        return aperture_kernel(
            2 * half + 1, **options, radius=radius, scale=float(factor), device=device, dtype=dtype
        )
    fine = aperture_kernel(2 * radius + 1, **options, dtype=torch.float64)
    # the full-resolution kernel averaged over the pixels of one cell
    # (a box, so one 1-D average per axis: a 2-D convolution by the cell took 20-30 ms in
    # float64 at factor 16)
    row = torch.full((1, 1, 1, factor), 1.0 / factor, dtype=torch.float64)
    target_small = torch.nn.functional.conv2d(fine[None, None], row, padding=(0, factor - 1))
    target_small = torch.nn.functional.conv2d(
        target_small, row.transpose(-1, -2), padding=(factor - 1, 0)
    )[0, 0]
    # on a fine canvas one coarse sample wider than the taps on every side, the centre tap's
    # cell centred where the target is
    n = 2 * half + 1
    canvas = (n + 2) * factor
    target = torch.zeros(canvas, canvas, dtype=torch.float64)
    o = (half + 1) * factor - radius
    target[o : o + target_small.shape[0], o : o + target_small.shape[1]] = target_small
    # the taps upsampled are u kc u^T (u is separable), so the least-squares kc is
    # g^-1 u^T target u g^-1 with g = u^T u; the scale is set by the normalisation
    u = _bilinear_matrix(n + 2, factor, torch.float64)[:, 1:-1]
    g_inv = torch.linalg.inv(u.T @ u)
    kernel = g_inv @ u.T @ target @ u @ g_inv
    return _normalise(kernel).to(device=device, dtype=dtype)


def soft_disk_kernel(
    size: int,
    *,
    sigma: float = SOFT_SIGMA,
    phi: float = SOFT_PHI,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """The paper's soft disk, ``0.5 + 0.5 tanh(sigma (r^2 - x^2 - y^2) + phi)``, r = size // 2.

    Shape: ``(size, size)``, sums to 1.
    """
    return aperture_kernel(size, shape="soft", sigma=sigma, phi=phi, device=device, dtype=dtype)


def hard_disk_kernel(
    size: int, *, device: torch.device | str | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """A binary disk of radius ``size // 2``. Shape: ``(size, size)``, sums to 1."""
    return aperture_kernel(size, shape="hard", device=device, dtype=dtype)


def polygon_kernel(
    size: int,
    blades: int,
    rotation: float = 0.0,
    *,
    soft: bool = True,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """A regular ``blades``-gon aperture inscribed in radius ``size // 2``, rotated by degrees.

    Shape: ``(size, size)``, sums to 1.
    """
    if blades < 3:
        raise ValueError(f"blades must be >= 3 for a polygonal aperture, got {blades}")
    return aperture_kernel(
        size,
        shape="soft" if soft else "hard",
        blades=blades,
        rotation=rotation,
        device=device,
        dtype=dtype,
    )


@functools.lru_cache(maxsize=512)
def effective_diameter(size: int, shape: str = "soft", blades: int = 0) -> float:
    """The CoC (px) a kernel of ``size`` px draws: the diameter of the thin-lens disc that,
    integrated over each pixel, spreads a point as widely as the kernel does (the same second
    moment: a disc of diameter ``c`` has variance ``c**2 / 16`` along an axis, a pixel's area
    adds ``1 / 12``). 0 for the 1-px kernel (no blur).

    The paper's soft disk of radius ``r`` reaches past ``r``, most so for small kernels: its
    3 px kernel draws a CoC of 3.0 px, its 5 and 7 px kernels 5.0 and 6.7 px, its 69 px
    kernel 68.0 px (a hard disk: 2.3, 4.0, 6.0 and 67.9 px). A regular polygon's second
    moment is the same along every axis, so the rotation does not change it.
    """
    size = _check_size(size)
    if size == 1:
        return 0.0
    k = aperture_kernel(size, shape=shape, blades=blades, dtype=torch.float64)
    x = torch.arange(size, dtype=torch.float64) - size // 2
    variance = 0.5 * float((k * (x[None, :] ** 2 + x[:, None] ** 2)).sum())
    return 4.0 * math.sqrt(max(variance - 1.0 / 12.0, 0.0))


def _nearest_odd(value: float) -> int:
    return max(1, 2 * int(math.floor((value - 1.0) / 2.0 + 0.5)) + 1)


def kernel_sizes(
    count: int = 15, max_size: float | None = None, schedule: str = "growing"
) -> list[int]:
    """Kernel sizes (odd, px) for ``count`` layers, smallest (1 = sharp) first.

    ``"growing"`` follows the paper's piecewise-linear curve (steps of 2, 4, 6, 8 px), stretched
    to ``count`` entries and ``max_size`` (default 69, the paper's schedule exactly).
    ``"uniform"`` uses equal steps; with no ``max_size`` the step is 4 px as in the paper's
    ablation. Sizes are non-decreasing; duplicates can occur for small ``max_size``.
    """
    count = whole_number(count, "count", 1)
    if schedule not in ("growing", "uniform"):
        raise ValueError(f"schedule must be 'growing' or 'uniform', got {schedule!r}")
    if count == 1:
        return [1]
    if schedule == "uniform":
        top = 1 + 4 * (count - 1) if max_size is None else float(max_size)
    else:
        top = PAPER_GROWING_SIZES[-1] if max_size is None else float(max_size)
    if not math.isfinite(top) or top < 1:
        raise ValueError(f"max_size must be finite and >= 1, got {max_size!r}")
    if schedule == "growing" and count == len(PAPER_GROWING_SIZES) and max_size is None:
        return list(PAPER_GROWING_SIZES)
    sizes = []
    n_paper = len(PAPER_GROWING_SIZES) - 1
    for i in range(count):
        t = i / (count - 1)
        if schedule == "uniform":
            value = 1 + t * (top - 1)
        else:
            pos = t * n_paper
            lo = min(int(math.floor(pos)), n_paper - 1)
            frac = pos - lo
            paper = PAPER_GROWING_SIZES[lo] * (1 - frac) + PAPER_GROWING_SIZES[lo + 1] * frac
            value = 1 + (paper - 1) * (top - 1) / (PAPER_GROWING_SIZES[-1] - 1)
        sizes.append(_nearest_odd(value))
    sizes[0] = 1
    for i in range(1, count):
        sizes[i] = max(sizes[i], sizes[i - 1])
    return sizes
