"""Focus and blur brushes: a photographer's correction of the depth where it is wrong.

Two masks painted over the photo (white = painted; soft values are partial paint):

- **keep sharp**: what is painted is drawn onto the focal plane of every render, wherever the
  focus is set afterwards, so it stays inside the focal range;
- **blur**: what is painted is moved away from the focal plane, to the end of the depth range
  on its own side of it (the far end when it sits at the focus), so it is at least as blurred
  as without the paint, and blurred even where the map put it in focus.

The masks edit the disparity at render time (:func:`apply_brushes`), not the scene's map:
the focus and the aperture can change afterwards and the paint keeps its meaning. Edges of a
stroke can follow the photo's own edges (:func:`follow_edges`, the "auto mask" of
Lightroom's brush): a stroke that spills over a silhouette is cut back to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..io.depth import check_aspect
from ..io.masks import integer_top
from ..sizing import resize, scaled_size
from .refine import box_mean, colour_share

__all__ = ["Brushes", "apply_brushes", "follow_edges", "mask_tensor", "snap_stroke"]

#: The long side at which a stroke's edges are moved onto the photo's (then upsampled).
EDGE_SIDE = 1024
#: The window of that move, as a share of the long side: a stroke may spill over a silhouette
#: by about this much and still be cut back to it.
EDGE_RADIUS = 0.02
#: Pixels this close to the focal plane (in disparity) count as at it: painted "blur", they go
#: to the end of the range farthest from the focus.
AT_FOCUS = 1e-3


def mask_tensor(mask: Any, size: tuple[int, int], name: str) -> Tensor:
    """A painted mask as ``[1, 1, H, W]`` float32 in [0, 1] at the photo's ``size``.

    ``mask``: an ``H' x W'`` array (bool, integers 0-255, or 0 and 1 only: a 0/1 mask, floats
    in [0, 1]) or ``H' x W' x C`` (grey, RGB or RGBA: the mean of the colour channels, times
    alpha when there is one), of the photo's aspect ratio and any size; a tensor of the same
    shapes.

    Raises:
        ValueError: not 2-D or 3-D, empty, holding NaN, outside its range, or of another
            aspect ratio than the photo.
    """
    if isinstance(mask, Tensor):
        mask = mask.detach().cpu().numpy()
    try:
        a = np.asarray(mask)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not an array: {exc}") from None
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise ValueError(f"{name}: expected a numeric mask, got dtype {a.dtype}")
    a = np.squeeze(a) if a.ndim > 3 else a
    if a.ndim == 3:
        if a.shape[2] not in (1, 2, 3, 4):
            raise ValueError(f"{name}: a mask has 1-4 channels, got shape {a.shape}")
        scale = integer_top(a, 255.0) if np.issubdtype(a.dtype, np.integer) else 1.0
        a = a.astype(np.float32) / scale
        colour = a[..., : 3 if a.shape[2] >= 3 else 1].mean(axis=2)
        alpha = a[..., -1] if a.shape[2] in (2, 4) else 1.0
        a = colour * alpha
    elif a.ndim != 2:
        raise ValueError(f"{name}: expected an H x W mask, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{name}: the mask is empty")
    if a.dtype == np.bool_:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        if a.min() < 0 or a.max() > 255:
            raise ValueError(f"{name}: integer mask values must be 0-255")
        a = a.astype(np.float32) / integer_top(a, 255.0)
    else:
        a = a.astype(np.float32)
        if not np.isfinite(a).all():
            raise ValueError(f"{name}: the mask holds NaN or infinite values")
        if a.min() < -1e-6 or a.max() > 1 + 1e-6:
            raise ValueError(f"{name}: float mask values must be in [0, 1]")
    check_aspect(a.shape, size, name, "mask")
    t = torch.from_numpy(np.ascontiguousarray(a))[None, None]
    return resize(t, tuple(size)).clamp_(0, 1)


def snap_stroke(image: Tensor, mask: Tensor, radius: int, eps: float = 0.01) -> Tensor:
    """A stroke's rim moved onto the photo's colour edges: in the window around each pixel
    that holds both painted and unpainted pixels, the painted ones' mean colour and the
    unpainted ones' are the two sides, and a pixel's paint is its share of the painted side's
    colour (the projection of its colour on the line between the two). Where the two colours
    are alike (less than ``eps`` apart, squared) the stroke is kept as painted.

    Shape: image (B, 3, H, W) in [0, 1], mask (B, 1, H, W) in [0, 1] -> (B, 1, H, W).
    """
    means = box_mean(torch.cat([mask, mask * image, image], 1), radius)
    painted = means[:, :1]
    c_in = means[:, 1:4] / painted.clamp_min(1e-4)
    c_out = (means[:, 4:7] - means[:, 1:4]) / (1.0 - painted).clamp_min(1e-4)
    share, conf = colour_share(image, c_in, c_out, eps, dim=1, keepdim=True)
    # only on the rim: windows with both sides (weight falling to 0 where one side is rare)
    mixed = (torch.minimum(painted, 1.0 - painted) * 20.0).clamp_(0, 1)
    return torch.lerp(mask, share.clamp(0, 1), conf * mixed)


def follow_edges(image: Tensor, mask: Tensor) -> Tensor:
    """``mask`` with its rim moved onto the photo's colour edges (:func:`snap_stroke`), at
    :data:`EDGE_SIDE` px, the change upsampled to full size; inside and outside a stroke
    nothing changes.

    Shape: image (1, 3, H, W) in [0, 1], mask (1, 1, H, W) in [0, 1] -> (1, 1, H, W).
    """
    size = tuple(image.shape[-2:])
    small = scaled_size(size, 1.0, EDGE_SIDE)
    radius = max(2, round(EDGE_RADIUS * max(small)))
    m_small = resize(mask, small).clamp(0, 1)
    snapped = snap_stroke(resize(image, small).clamp(0, 1), m_small, radius)
    return (mask + resize(snapped - m_small, size)).clamp_(0, 1)


@dataclass
class Brushes:
    """The paint of one photo: ``sharp`` and ``blur`` as ``[1, 1, H, W]`` uint8 (0-255, full
    resolution; ``None`` where unpainted). :meth:`at` gives them as float32 at a pass's size."""

    sharp: Tensor | None = None
    blur: Tensor | None = None
    cache: dict[Any, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def painted(
        cls, image: Tensor, sharp: Any = None, blur: Any = None, edges: bool = True
    ) -> Brushes | None:
        """The brushes from masks (see :func:`mask_tensor`) painted over ``image``
        (``[1, 3, H, W]``); with ``edges``, each stroke's rim follows the photo's edges.
        ``None`` when nothing is painted. Where both are painted, the larger paint wins
        (``blur`` on a tie)."""
        size = (int(image.shape[-2]), int(image.shape[-1]))
        masks = {}
        for name, m in (("sharp_mask", sharp), ("blur_mask", blur)):
            if m is None:
                continue
            t = mask_tensor(m, size, name).to(image.device)
            if edges and float(t.max()) > 0:
                t = follow_edges(image, t)
            masks[name] = t if float(t.max()) >= 1.0 / 255.0 else None
        s, b = masks.get("sharp_mask"), masks.get("blur_mask")
        if s is not None and b is not None:
            s = torch.where(s > b, s, torch.zeros_like(s))
            b = torch.where(s > 0, torch.zeros_like(b), b)
        if s is None and b is None:
            return None

        def to_u8(t: Tensor | None) -> Tensor | None:
            if t is None or float(t.max()) < 1.0 / 255.0:
                return None
            return (t * 255.0).round_().to(torch.uint8)

        out = cls(to_u8(s), to_u8(b))
        return out if out.sharp is not None or out.blur is not None else None

    def at(self, size: tuple[int, int]) -> tuple[Tensor | None, Tensor | None]:
        """``(sharp, blur)`` as ``[1, 1, h, w]`` float32 in [0, 1] at ``size`` (cached)."""
        size = (int(size[0]), int(size[1]))
        if size not in self.cache:
            self.cache[size] = tuple(
                None if m is None else resize(m.float() / 255.0, size).clamp_(0, 1)
                for m in (self.sharp, self.blur)
            )
        return self.cache[size]

    def apply(self, disparity: Tensor, focus: float) -> Tensor:
        """:func:`apply_brushes` with these masks at ``disparity``'s size."""
        sharp, blur = self.at(tuple(disparity.shape[-2:]))
        return apply_brushes(disparity, focus, sharp, blur)

    def coverage(self) -> tuple[float, float]:
        """The painted share of the frame, ``(sharp, blur)``, each in [0, 1]."""
        return tuple(
            0.0 if m is None else float(m.float().mean()) / 255.0 for m in (self.sharp, self.blur)
        )


def apply_brushes(
    disparity: Tensor, focus: float, sharp: Tensor | None, blur: Tensor | None
) -> Tensor:
    """The disparity as the brushes edit it for a render focused at ``focus``.

    ``sharp`` pulls each pixel toward the focal plane by its paint (``lerp(d, f, s)``: fully
    painted, it is on the plane); ``blur`` pushes it toward the end of the range on its own
    side of the plane (``0`` behind, ``1`` in front; at the plane, the end farther from it),
    so its distance from the plane only grows. Unpainted pixels are unchanged.

    Shape: (B, 1, H, W) -> (B, 1, H, W); masks (B or 1, 1, H, W) in [0, 1] or ``None``.
    """
    out = disparity
    if blur is not None:
        ahead = disparity - focus
        far_end = 0.0 if focus >= 0.5 else 1.0
        end = torch.where(
            ahead.abs() <= AT_FOCUS,
            torch.full_like(disparity, far_end),
            (ahead > 0).to(disparity.dtype),
        )
        out = torch.lerp(out, end, blur)
    if sharp is not None:
        out = torch.lerp(out, torch.full_like(out, float(focus)), sharp)
    return out
