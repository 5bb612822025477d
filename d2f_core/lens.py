"""The virtual lens behind an f-number: blur in px for a photo of a given size.

The library's blur K is the circle-of-confusion diameter in px at full resolution for
``|d - focus| = 1``. With the disparity read as ``d = z_near / z`` (1 at the nearest point, 0
at infinity), a thin lens of focal length F at f-number N gives a blur circle on the sensor
of about ``F^2 / (N z_near) * |d - d_f|``, so

    K = F^2 / (N z_near) * (long side in px / sensor width).

The focus speaks the app's language too: a focus position 0 (nearest) .. 1 (farthest), the
app's slider, is the focal disparity ``1 - position`` (1 = nearest), to 3 decimals.

These are the numbers of the app's aperture slider (``app/handlers.py`` keeps its own copy,
which its tests patch; ``tests/test_batch.py`` checks that the two agree), so ``d2f render
--f-number`` and ``d2f batch --f-number`` give the app's look.
"""

from __future__ import annotations

__all__ = [
    "BLUR_PER_PX_AT_F1",
    "FOCUS_DECIMALS",
    "F_NUMBER_LIMITS",
    "MAX_BLUR_PX",
    "blur_px",
    "f_number_for",
    "focus_of_position",
    "position_of_focus",
]

#: The virtual lens: focal length (mm) on a full-frame sensor whose 36 mm width spans the
#: photo's long side, with the nearest point of the photo this far away (m).
LENS_FOCAL_MM = 50.0
SENSOR_WIDTH_MM = 36.0
NEAREST_M = 1.0
#: K per px of the photo's long side at f/1: F^2 / (z_near * sensor width) = 0.0694.
BLUR_PER_PX_AT_F1 = LENS_FOCAL_MM**2 / (NEAREST_M * 1000.0 * SENSOR_WIDTH_MM)
#: K is capped here: f/1 reaches it on a long side of 4320 px (12 MP at 3:2).
MAX_BLUR_PX = 300.0
#: The f-numbers accepted (the app's API range).
F_NUMBER_LIMITS = (0.5, 1000.0)


def blur_px(f_number: float, long_side: int) -> float:
    """K (px at full resolution, for ``|d - f| = 1``) at ``f_number`` on a photo whose long
    side is ``long_side`` px, capped at :data:`MAX_BLUR_PX`, to 0.1 px.

    Raises:
        ValueError: ``f_number`` outside :data:`F_NUMBER_LIMITS` or ``long_side`` < 1.
    """
    lo, hi = F_NUMBER_LIMITS
    if not lo <= float(f_number) <= hi:
        raise ValueError(f"f_number: expected a number in [{lo:g}, {hi:g}], got {f_number!r}")
    if int(long_side) < 1:
        raise ValueError(f"long_side: expected a positive number of px, got {long_side!r}")
    return round(min(MAX_BLUR_PX, BLUR_PER_PX_AT_F1 * int(long_side) / float(f_number)), 1)


def f_number_for(blur: float, long_side: int) -> float | None:
    """The f-number whose K is ``blur`` px on a photo with this long side (the inverse of
    :func:`blur_px` below its cap), to 3 decimals; ``None`` for zero blur (no lens has it)."""
    if float(blur) <= 0.0:
        return None
    return round(BLUR_PER_PX_AT_F1 * int(long_side) / float(blur), 3)


#: Focus positions and disparities are rounded to the app's focus slider step.
FOCUS_DECIMALS = 3


def focus_of_position(position: float) -> float:
    """The focal disparity (1 = nearest) of a focus position (0 = nearest, 1 = farthest, the
    app's slider), to :data:`FOCUS_DECIMALS` decimals.

    Raises:
        ValueError: ``position`` not a number in [0, 1].
    """
    try:
        value = float(position)
    except (TypeError, ValueError):
        raise ValueError(f"focus position: expected a number in [0, 1], got {position!r}") from None
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"focus position: expected a number in [0, 1], got {position!r}")
    return round(1.0 - value, FOCUS_DECIMALS)


def position_of_focus(focus: float) -> float:
    """The focus position (0 = nearest, 1 = farthest) of a focal disparity (1 = nearest)."""
    return round(1.0 - float(focus), FOCUS_DECIMALS)
