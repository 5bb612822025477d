"""Input checks and tensors: a render's photo, disparity ``d``, focal plane and blur ``K``
checked and brought to ``(B, C, H, W)`` tensors, from which the renderer reads each pixel's
CoC ``K |d - focus|`` (D2F step 2, ``D = |D_d - f|``, kept signed).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from ..errors import InputTypeError

#: Layer placements of the depth order (:func:`layer_plan`), the default first.
PLACEMENTS = ("blend", "nearest", "paper")


def check_tensor(name: str, x: torch.Tensor, channels: int | None) -> tuple[float, float]:
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
    return finite_extremes(name, x)


def finite_extremes(name: str, x: torch.Tensor) -> tuple[float, float]:
    """(min, max) of a non-empty ``x``; ``ValueError`` naming ``name`` when it holds NaN or
    an infinity. NaN carries through the extremes and an infinity is one of them, so one pass
    checks it all (isfinite, min and max took three: 0.15 s for a 12 MP image)."""
    extremes = tensor_extremes(x)
    if not all(math.isfinite(v) for v in extremes):
        raise ValueError(f"{name} contains NaN or inf")
    return extremes


def tensor_extremes(x: torch.Tensor) -> tuple[float, float]:
    """(min, max) of ``x`` in one pass; NaN when ``x`` holds a NaN."""
    lo, hi = torch.aminmax(x.detach())
    return float(lo), float(hi)


#: the largest blur ``K`` (CoC diameter in px at ``|d - focus| = 1``) any entry point takes
MAX_BLUR = 10000.0


def _number(name: str, value) -> float:
    """``value`` as a float: a Python or NumPy number, or a one-value tensor; never text or a
    bool, which ``float()`` would take ("0.5", ``True`` as 1 px)."""
    dtype = getattr(value, "dtype", None)  # a 0-d array or a one-value tensor of bools or text
    if (
        isinstance(value, (str, bytes, bool, np.bool_))
        or dtype == torch.bool
        or (isinstance(dtype, np.dtype) and dtype.kind in "bUSO")
    ):
        raise InputTypeError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputTypeError(f"{name} must be a number, got {value!r}") from None


def _check_focus(focus) -> float:
    f = _number("focus", focus)
    if not math.isfinite(f) or not 0 <= f <= 1:
        raise ValueError(f"focus must be in [0, 1], got {focus!r}")
    return f


def check_blur(blur) -> float:
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
    return _check_focus(focus), check_blur(blur)


def check_placement(placement: str) -> None:
    if placement not in PLACEMENTS:
        raise ValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")


def focus_tensor(focus, batch: int, ref: torch.Tensor, check: bool = True) -> torch.Tensor:
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
        for value in tensor_extremes(f):  # NaN when f holds one
            _check_focus(value)
    return f.view(batch, 1, 1, 1)


# --------------------------------------------------------------------------------------
def _planar(image: np.ndarray) -> torch.Tensor:
    """``(H, W, 3)`` numpy -> contiguous ``(1, 3, H, W)`` tensor of the same dtype, copied once
    (a strided copy into planes; 0.15 s at 12 MP where a copy through a float view took 0.8)."""
    if any(step < 0 for step in image.strides):
        image = np.ascontiguousarray(image)  # torch cannot view negative strides
    # always a copy (a 1x1 photo's view is already contiguous, and would share the array)
    with warnings.catch_warnings():
        # a read-only array (a decoded file's) is only read here: the planes are a copy
        warnings.filterwarnings("ignore", "The given NumPy array is not writable")
        planes = torch.from_numpy(image).permute(2, 0, 1)
    return planes.clone(memory_format=torch.contiguous_format)[None]


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
        if min(image.shape[:2]) < 1:
            raise ValueError(f"image is empty: shape {image.shape}")
        if image.dtype == np.uint8:
            return _planar(image).float().div_(255.0)  # in [0, 1] and finite by its type
        if not np.issubdtype(image.dtype, np.floating):
            raise InputTypeError(f"image must be uint8 or float, got {image.dtype}")
        image = np.asarray(image, dtype=np.float32)
        # NaN carries through min and max, and an infinity is one of them: two passes over
        # the photo check it all (torch's checks of the strided view took 0.6 s at 12 MP)
        lo, hi = float(image.min()), float(image.max())
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError("image contains NaN or inf")
        if lo < 0 or hi > 1:
            raise ValueError(f"image float values must be in [0, 1], got [{lo:.3g}, {hi:.3g}]")
        return _planar(image)
    else:
        kind = type(image).__name__
        raise InputTypeError(f"image must be a numpy array or torch tensor, got {kind}")
    if min(x.shape[-2:]) < 1:
        raise ValueError(f"image is empty: shape {tuple(x.shape)}")
    lo, hi = finite_extremes("image", x)
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
    lo, hi = finite_extremes("disparity", d)
    if lo < -_DISPARITY_SLACK or hi > 1 + _DISPARITY_SLACK:
        raise ValueError(f"disparity must be in [0, 1], got [{lo:.3g}, {hi:.3g}]")
    return d.clamp(0, 1)[None, None].contiguous()


def tracks_grad(*tensors: torch.Tensor | None) -> bool:
    """Whether autograd records work on any of ``tensors`` (``None`` skipped) now."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def row_bands(t: torch.Tensor) -> list[slice]:
    """Slices of rows of ``t`` ``(B, C, H, W)`` by :data:`ROW_BAND` pixels over the batch
    (at least one row each)."""
    rows = max(1, ROW_BAND // max(1, t.shape[0] * t.shape[-1]))
    return [slice(r0, r0 + rows) for r0 in range(0, t.shape[-2], rows)]


#: Pixels (over the batch) of the bands of rows that the plan and the highlight weights are
#: computed in without gradients (1 MB of float32 each).
ROW_BAND = 1 << 18
