"""The 100 % loupe: a click on the result shows the region around that point at the photo's
full resolution, rendered for that region only (``D2F.render_region``), beside the picture the
page shows at the screen's size. It follows the page's values: a new render of the result
renders the loupe's region again.
"""

from __future__ import annotations

import math
from typing import Any

import gradio as gr

from app import imaging
from app.reporting import user_error
from app.sessions import Session, reported
from app.settings import LOUPE_SIZE, RenderParams


def loupe_box(point: tuple[float, float], size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The loupe's region ``(x0, y0, x1, y1)`` around full-res ``point`` in a photo of
    ``size = (width, height)``: :data:`LOUPE_SIZE`, moved inside the photo (cut to it when the
    photo is smaller)."""
    width, height = size
    w, h = min(LOUPE_SIZE[0], width), min(LOUPE_SIZE[1], height)
    x0 = min(max(0, round(point[0] - w / 2)), width - w)
    y0 = min(max(0, round(point[1] - h / 2)), height - h)
    return x0, y0, x0 + w, y0 + h


class LoupeEvents:
    """The loupe's events as methods of :class:`~app.handlers.RefocusApp`."""

    def _loupe_picture(self, session: Session, controls: tuple) -> Any:
        """The loupe at ``session.loupe_point`` for the page's values ``controls`` (those of
        :meth:`render_full` after the session)."""
        focus, f_number, blades, rotation, boost, fusion, _view, quality, blur_on, span = controls[
            :10
        ]
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, boost, fusion, quality, blur_on, span,
            size=session.size, paint=session.paint_id,
        )  # fmt: skip
        box = loupe_box(session.loupe_point, session.size)
        result = self.model.render_region(
            session.scene, box, params.focus, params.blur, **params.render_options()
        )
        picture = imaging.to_uint8(result.bokeh)
        x0, y0, x1, y1 = box
        w, h = session.size
        label = f"100 % view: {x1 - x0}x{y1 - y0} px at ({x0}, {y0}) of the {w}x{h} photo"
        return gr.update(value=self._display_file(session, picture, lossless=True), label=label)

    @reported
    def loupe(self, session: Session | None, index: Any, *controls: Any) -> Any:
        """Show the region around the clicked point of the result at full resolution.

        ``index = [x, y]``: the click in the pixels of the result's picture (the screen's
        size, or a preview's); ``controls``: the page's values as :meth:`render_full` takes
        them after the session (the photo's id last).

        Returns:
            a ``gr.Image`` update of the loupe, or ``gr.skip()`` without a photo.
        """
        if session is None or not session.views:
            return gr.skip()
        if controls and not session.shown_by(controls[-1]):
            return gr.skip()
        session.touch()
        try:
            x, y = (float(v) for v in index)
        except (TypeError, ValueError):
            raise user_error(f"Click position must be [x, y], got {index!r}.") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise user_error(f"Click position: x and y must be finite, got {index!r}.")
        shown = session.views["Bokeh"]
        sh, sw = shown.shape[:2]
        w, h = session.size
        point = ((x + 0.5) * w / sw - 0.5, (y + 0.5) * h / sh - 0.5)
        with session.lock:
            session.loupe_point = (
                min(max(point[0], 0.0), w - 1.0),
                min(max(point[1], 0.0), h - 1.0),
            )
        return self._loupe_picture(session, controls)

    @reported
    def refresh_loupe(self, session: Session | None, *controls: Any) -> Any:
        """Render the loupe's region again for the page's values (after the result changed);
        ``gr.skip()`` while the loupe is unused."""
        if session is None or session.loupe_point is None or session.closed:
            return gr.skip()
        if controls and not session.shown_by(controls[-1]):
            return gr.skip()
        return self._loupe_picture(session, controls)
