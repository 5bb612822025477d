"""The public renderer: :func:`render` (tensors), :func:`render_bokeh` (numpy) and
:class:`LayeredRenderer` (a module), D2F's layered rendering ``B = f_l(R I, D) / f_l(R, D)``
(step 5) end to end, from the checks to the composited frame.
"""

from __future__ import annotations

import contextlib
import functools
import os
from typing import Any

import numpy as np
import torch
from torch import nn

from ..errors import whole_number
from .blur import QUALITY_PRESETS, KernelSpec, with_ones
from .composite import composite_layers
from .hidden import hidden_surface, input_pixels
from .inputs import (
    check_blur,
    check_focus_blur,
    check_placement,
    check_tensor,
    disparity_tensor,
    focus_tensor,
    image_tensor,
    tensor_extremes,
    tracks_grad,
)
from .plan import GAMMA, layer_plan
from .radiance import HDR_ALPHA, HDR_THRESHOLD, SPOT_ALPHA, boost_strength, hdr_boost
from .schedule import check_focal_range, fold_focal_range
from .threads import ThreadChoice
from .tiled import render_tiled


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
    highlight_boost: bool | float = True,
    method: str = "fft",
    quality: str = "balanced",
    gamma: float = GAMMA,
    full_frame: bool = False,
    placement: str = "blend",
    behind: bool = False,
    front_size: float = 0.0,
    hidden: bool = True,
    focal_range: float = 0.0,
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
        highlight_boost: the HDR boost of saturated pixels (alpha 3, beta 5), a saturated
            spot with few saturated pixels around it weighing up to
            :data:`~d2f_core.rendering.radiance.SPOT_ALPHA` (``hdr_boost``'s ``spot``):
            ``True`` (default) or a strength that multiplies both (0 to 10; the app's
            "Boost"), ``False`` none.
        method: ``"fft"`` or ``"direct"`` convolution for kernels above 7 px.
        quality: ``"exact"``, ``"high"``, ``"balanced"`` or ``"fast"``: how large a kernel
            must be before it is applied at 1/2 or 1/4 resolution.
        full_frame: disable the per-layer support boxes and empty-layer skipping (reference).
        placement: ``"blend"`` (default), ``"nearest"`` or ``"paper"``: how a pixel whose CoC
            lies between two kernel sizes is drawn (depth order; see :func:`layer_plan`).
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
    image_max, disparity_range = _checked_inputs(
        image, disparity, radiance, method, quality, kernel, placement
    )
    num_layers = whole_number(num_layers, "num_layers", 1)
    f = focus_tensor(focus, image.shape[0], image, check=not checked)
    blur = float(blur) if checked else check_blur(blur)
    focal_range = check_focal_range(focal_range)
    if focal_range > 0:
        disparity = fold_focal_range(disparity, f, focal_range)  # [B,1,H,W]
        disparity_range = tensor_extremes(disparity) if disparity.numel() else (0.0, 0.0)
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
    return _render_each(image, disparity, f, blur, radiance, options)


def _render_each(
    image: torch.Tensor,
    disparity: torch.Tensor,
    f: torch.Tensor,
    blur: float,
    radiance: torch.Tensor | None,
    options: dict[str, Any],
):
    """:func:`_render` of a batch, image by image: the kernel schedule and the support boxes
    follow each image's own CoCs (one layer plan each), so a batch renders exactly as its
    images do one by one."""
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
                0.0 if empty else tensor_extremes(one)[1],
                (0.0, 0.0) if empty else tensor_extremes(disp),
                None if radiance is None else radiance[i : i + 1],
                **options,
            )
        )
    if options["behind"]:
        return tuple(torch.cat([p[i] for p in parts]) for i in range(3))
    return torch.cat(parts)


def _checked_inputs(
    image: torch.Tensor,
    disparity: torch.Tensor,
    radiance: torch.Tensor | None,
    method: str,
    quality: str,
    kernel: str,
    placement: str,
) -> tuple[float, tuple[float, float]]:
    """:func:`render`'s tensors and named options checked; returns the image's largest value
    and the disparity's extremes.

    Raises:
        ValueError: naming the bad input.
    """
    image_max = check_tensor("image", image, 3)[1]
    disparity_range = check_tensor("disparity", disparity, 1)
    if disparity.shape[0] != image.shape[0] or disparity.shape[-2:] != image.shape[-2:]:
        raise ValueError(
            f"disparity shape {tuple(disparity.shape)} does not match image {tuple(image.shape)}"
        )
    if radiance is not None:
        check_tensor("radiance", radiance, 1)
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
    check_placement(placement)
    return image_max, disparity_range


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
    highlight_boost: bool | float,
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

    grad = tracks_grad(image, disparity, radiance)

    # Without gradients, fewer threads while other processes keep the cores busy (see
    # ThreadChoice); a training step keeps its own.
    threads = None if grad else ThreadChoice()
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
                kernel=kernel,
                blades=int(blades),
            )
            weights = _pixel_weights(image, radiance, highlight_boost, image_max)
            x, weights = _layer_input(image, weights, radiance, grad, tiled)

            if tiled and any(size > 1 for _, size in plan.order):
                spec = KernelSpec(kernel, int(blades), float(rotation))
                return render_tiled(image, weights, plan, spec, quality, threads, hidden)
            # when nothing is blurred every layer is the identity, so is the composite
            blurred = any(size > 1 for _, size in plan.order)
            if blurred:
                spec = KernelSpec(kernel, int(blades), float(rotation))
                under = None
                if hidden and plan.signed:
                    under = hidden_surface(input_pixels(x, grad), plan)
                options = dict(
                    method=method,
                    quality=quality,
                    full_frame=full_frame,
                    front=behind and plan.signed,
                    front_size=front_size,
                    threads=threads,
                    hidden=under,
                )
                layers = _composited(x, plan, spec, weights, grad, options)
        if not blurred:
            return _with_behind(image.clamp(0, 1), behind)
        return _normalised(image, *layers, weights, grad, behind)


def _composited(
    x: torch.Tensor,
    plan: Any,
    spec: KernelSpec,
    weights: torch.Tensor | None,
    grad: bool,
    options: dict[str, Any],
) -> tuple[torch.Tensor, torch.Tensor, float, torch.Tensor, Any]:
    """The layers composited (:func:`composite_layers` with ``options``): ``(acc, norm,
    floor, covered, split)``, ``norm`` the weight each pixel got, at least ``floor``, and
    ``covered`` where some layer reached (every pixel, with soft masks)."""
    acc, alpha, split = composite_layers(x, plan, spec, **options)
    norm, floor = (alpha, 1e-6) if weights is None else (acc[:, 3:], 1e-8)
    # pixels no layer reached (cannot happen with soft masks, but stay defined) keep the input
    covered = norm > 1e-6
    norm = norm.clamp(min=floor) if grad else norm.clamp_(min=floor)
    return acc, norm, floor, covered, split


def _pixel_weights(
    image: torch.Tensor,
    radiance: torch.Tensor | None,
    highlight_boost: bool | float,
    image_max: float,
) -> torch.Tensor | None:
    """Each pixel's weight in the layers (``None``: all equal): the HDR boost of saturated
    pixels at the boost's strength (with the radiance map when there is one), the radiance
    map alone when the boost is off."""
    strength = boost_strength(highlight_boost)
    if strength > 0:
        if radiance is not None or image_max >= HDR_THRESHOLD:
            # a lone saturated spot weighs more (a lamp, a glint), with or without a
            # radiance map: on generated night scenes with true radiance the discs of
            # clipped far lights came out at 0.65 of the thin lens's brightness with
            # the paper's boost alone, 1.04 with this (docs/accuracy.md)
            spot = SPOT_ALPHA * strength
            return hdr_boost(image, radiance, alpha=HDR_ALPHA * strength, spot=spot)
        return None
    return radiance


def _layer_input(
    image: torch.Tensor,
    weights: torch.Tensor | None,
    radiance: torch.Tensor | None,
    grad: bool,
    tiled: bool,
) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """``(x, weights)``: what the layers cut out, ``[1, I]`` without weights (``I`` with
    gradients), ``[w I, w]`` with them (``[1, w I, w]`` without gradients), or ``None`` for a
    tiled render, which reads the image band by band; the weights with their floor of 1e-4,
    which keeps the normalisation defined where every weight is 0 (e.g. pure red)."""
    if tiled:
        if weights is not None:
            # the floor in place (a copy of a caller's radiance)
            weights = weights + 1e-4 if weights is radiance else weights.add_(1e-4)
        return None, weights
    if weights is None:
        return (image if grad else with_ones(image)), None
    if grad:
        weights = weights + 1e-4
        return torch.cat([weights * image, weights], dim=1), weights  # [B,3+Cr,H,W]
    # [1, w I, w] built in place: the layers are then mask * x in one product
    cw = weights.shape[1]
    x = image.new_empty(image.shape[0], 4 + cw, *image.shape[2:])
    x[:, :1] = 1
    torch.add(weights, 1e-4, out=x[:, 4:])
    torch.mul(image, x[:, 4:], out=x[:, 1:4])
    return x, weights


def _normalised(
    image: torch.Tensor,
    acc: torch.Tensor,
    norm: torch.Tensor,
    floor: float,
    covered: torch.Tensor,
    split: Any,
    weights: torch.Tensor | None,
    grad: bool,
    behind: bool,
):
    """The composite divided by its weight (pixels no layer reached keep the input), and
    with ``behind`` what the layers at and behind the focal plane make of each pixel."""
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


# Frames of at least this many pixels render by tiles and bands (render_tiled) when no
# gradient is needed: from about 1.4 MP it is the faster path (0.72-0.86x the time at
# 1024x1536, 0.99x at 896x1344 and 1.05-1.26x at 768x1152 and smaller, 2 threads), at
# 1.2-1.8 dB less against the exact render at 1024x1536 (58.5-61.1 dB).
_TILED_MIN_PIXELS = 1_400_000
