"""The refocusing page's settings: the lens behind the f-number slider, the focus slider's
scale, and one render's parameters (:class:`RenderParams`) checked from the page's inputs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from app.reporting import user_error
from d2f_core.lens import FOCUS_DECIMALS, blur_px, focus_of_position, position_of_focus

#: The adaptive renderer's error budgets (``D2F.render(budget=...)``), fastest last.
QUALITIES = ("high", "balanced", "fast")
VIEWS = ("Bokeh", "Before / after", "Disparity", "Defocus", "Fusion mask")


PREVIEW_MAX_SIDE = 512
#: An upload of more pixels than this is shown first at the long side of the render pass
#: (``D2F.config.max_render_side``, 800 px), then at full resolution
FIRST_LOOK_PIXELS = 4_000_000
FIRST_LOOK_MAX_SIDE = 800


def wants_first_look(size: tuple[int, int]) -> bool:
    """Whether a photo of ``size`` (W, H) is shown first at :data:`FIRST_LOOK_MAX_SIDE`."""
    return size[0] * size[1] > FIRST_LOOK_PIXELS


#: The long side at which the result panel's picture of a larger photo is rendered
#: (``D2F.render(..., screen=...)``): the size the page shows it at; the full resolution is
#: rendered for the download and, region by region, for the 100 % loupe.
SCREEN_SIDE = 1600
#: The loupe's region, full-resolution pixels (width, height).
LOUPE_SIZE = (480, 360)

#: The Boost slider's top: the strength of the highlight boost (``D2F.render``'s
#: ``highlight_boost``; 1 makes clipped far lights as bright as a real lens does).
BOOST_MAX = 3.0

FORMATS = ("PNG", "JPEG")
DEPTH_KINDS = ("disparity (bright = near)", "depth (bright = far)")
#: File names of the pictures the app puts in the photo panel (:meth:`RefocusApp.photo_panel`):
#: when the panel sends one back as the photo, the upload it stands for is used.
PANEL_PREFIX = "d2f-rendered-from-"
#: The focal range slider's top (a span of disparity kept sharp around the focus) and step;
#: a click sets it to the clicked subject's range (``D2F.focus_at(..., with_range=True)``).
FOCAL_RANGE_MAX = 0.5
FOCAL_RANGE_STEP = 0.001

# The controls speak a photographer's language; the library keeps its own units. The focus
# slider reads near (0, left) to far (1, right); the library's focal plane is a disparity,
# 1 = near: disparity = 1 - slider. The disparity map is relative (normalised per photo,
# not metres), so no distance scale is invented: the slider stays linear in disparity, where
# the blur of a point grows linearly with its distance |d - f| from the focal plane, and
# equal steps of the slider change the blur by equal amounts.
#
# The blur control is the f-number N of a virtual lens. With the disparity read as
# d = z_near / z (1 at the nearest point, 0 at infinity), the thin-lens blur circle on the
# sensor is about F^2 / N * |1/z - 1/z_f| = F^2 / (N z_near) * |d - d_f|, so the library's K
# (blur circle diameter in px at full resolution for |d - f| = 1) is
#     K = F^2 / (N z_near) * (long side in px / sensor width).
# The lens itself (F, sensor, z_near, K per px at f/1, the 300 px cap) is d2f_core.lens's,
# which d2f render --f-number reads too.
#: The aperture slider's range and default: f/1 (most blur) to f/22.
F_NUMBER_RANGE = (1.0, 22.0)
DEFAULT_F_NUMBER = 1.4
#: The photo size the blur note under the aperture slider describes before an upload.
REFERENCE_SIZE = (4000, 3000)


def disparity_of(position: float) -> float:
    """The library's focal plane (disparity, 1 = near) for a focus slider position (0 =
    nearest, 1 = farthest): ``d2f render --focus-position`` reads it the same way."""
    return focus_of_position(position)


def position_of(disparity: float) -> float:
    """The focus slider position (0 = nearest, 1 = farthest) of a disparity (1 = near)."""
    return position_of_focus(disparity)


#: The CoC (px at the render pass) that the defocus map draws as 1 (the paper's schedule).


def _boost(value: Any) -> float:
    """The Boost slider's strength: a number in [0, :data:`BOOST_MAX`], or the old switch's
    True (1) and False (0)."""
    if value is None or isinstance(value, bool):
        return 1.0 if value in (True, None) else 0.0
    try:
        boost = round(float(value), 3)
    except (TypeError, ValueError):
        raise user_error(f"Boost must be a number, got {value!r}.") from None
    if not 0.0 <= boost <= BOOST_MAX:
        raise user_error(f"Boost must be in [0, {BOOST_MAX:g}], got {value!r}.")
    return boost


@dataclass(frozen=True)
class RenderParams:
    """What a render depends on besides the scene; equal params give equal pictures.

    ``focus`` and ``blur`` are the library's (disparity, 1 = near; K in px at full
    resolution); ``f_number`` is the aperture chosen (None: blur off, ``blur`` is 0);
    ``focal_range`` the span of disparity kept sharp around the focus (0 = thin lens);
    ``paint`` names the session's brush paint (its content's hash, "" for none): the same
    values with other paint are another picture.
    """

    focus: float
    blur: float
    blades: int = 0
    rotation: float = 0.0
    highlight_boost: float = 1.0
    fusion: bool = True
    quality: str = "balanced"
    f_number: float | None = None
    focal_range: float = 0.0
    paint: str = ""

    @classmethod
    def from_inputs(
        cls,
        focus: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        quality: Any = "balanced",
        blur_on: Any = True,
        focal_range: Any = 0.0,
        *,
        size: tuple[int, int] | None,
        paint: str = "",
    ) -> RenderParams:
        """Validate raw widget values (numbers may arrive as str/None from API callers).

        Args:
            focus: focus slider position, 0 = nearest .. 1 = farthest.
            f_number: aperture of the virtual lens (:func:`blur_px`).
            blur_on: False renders no blur (the photo as it is).
            focal_range: the span of disparity kept sharp around the focus, 0 (thin lens)
                to :data:`FOCAL_RANGE_MAX`.
            size: ``(width, height)`` of the photo K is computed for; None gives K = 0 (to
                check the inputs before the photo is known; :meth:`sized` sets it).
            paint: the session's paint (:attr:`app.sessions.Session.paint_id`).
        """
        try:
            position = round(float(focus), FOCUS_DECIMALS)
            n = round(float(f_number), 3)
            blades_n = int(float(blades or 0))
            r = round(float(rotation or 0.0), 3)
            span = round(float(focal_range or 0.0), 3)
        except (TypeError, ValueError):
            raise user_error(
                f"Invalid slider values: focus={focus!r}, f-number={f_number!r}, "
                f"blades={blades!r}, rotation={rotation!r}, focal range={focal_range!r}."
            ) from None
        if not 0.0 <= span <= FOCAL_RANGE_MAX:
            raise user_error(f"The focal range must be in [0, {FOCAL_RANGE_MAX:g}], got {span:g}.")
        if not 0.0 <= position <= 1.0:
            raise user_error(f"focus must be in [0, 1] (0 = near, 1 = far), got {position}.")
        if not 0.5 <= n <= 1000.0:
            raise user_error(f"The f-number must be in [0.5, 1000], got {n:g}.")
        if blades_n < 0 or blades_n in (1, 2):
            raise user_error(f"blades must be 0 (round) or at least 3, got {blades_n}.")
        quality = "balanced" if quality in (None, "") else str(quality)
        if quality not in QUALITIES:
            raise user_error(f"quality must be one of {', '.join(QUALITIES)}, got {quality!r}.")
        on = blur_on not in (False, None, 0, "false", "False")
        boost = _boost(highlight_boost)
        params = cls(disparity_of(position), 0.0, blades_n, r, boost,
                     bool(fusion), quality, n if on else None, span, paint)  # fmt: skip
        return params.sized(size)

    def sized(self, size: tuple[int, int] | None) -> RenderParams:
        """These params with K for a photo of ``size = (width, height)`` (0 for None)."""
        k = 0.0 if self.f_number is None or not size else blur_px(self.f_number, max(size))
        return dataclasses.replace(self, blur=k)

    @property
    def position(self) -> float:
        """The focus slider position of :attr:`focus` (0 = nearest, 1 = farthest)."""
        return position_of(self.focus)

    def blur_text(self) -> str:
        """The aperture and the blur it gives, for the status line."""
        if self.f_number is None:
            return "no blur"
        return f"f/{self.f_number:g}, blur {self.blur:g} px"

    def render_options(self) -> dict[str, Any]:
        """Keyword options for ``D2F.render`` (and on to ``rendering.render``)."""
        return {
            "fusion": self.fusion,
            "blades": self.blades,
            "rotation": self.rotation,
            "highlight_boost": self.highlight_boost,
            "budget": self.quality,
            "focal_range": self.focal_range,
        }
