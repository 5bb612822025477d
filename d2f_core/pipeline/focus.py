"""Choosing the focus, D2F's missing step: the focal plane read from the disparity map at a
clicked point (with the focal range that keeps the clicked subject sharp), or at the subject
the map shows.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from ..depth.subject import RANGE_MAP_SIDE, click_window, locate_subject, subject_range
from ..errors import InputTypeError, whole_number
from ..sizing import resize, scaled_size
from .outputs import Scene


class AutoFocus(NamedTuple):
    """Where a render focuses when it is given no focus (:meth:`FocusStage.default_focus`).

    ``focus``: the focal disparity (1 = nearest); ``focal_range``: the span of disparity kept
    sharp around it; ``point``: the subject's full-res pixel ``(x, y)``, ``None`` for the
    phone's focal plane; ``reason``: ``"photo"`` (the focal plane the phone recorded with its
    depth) or ``"subject"`` (the subject the map shows).
    """

    focus: float
    focal_range: float
    point: tuple[float, float] | None
    reason: str


class FocusStage:
    """Click-to-focus and subject focus as methods of :class:`~d2f_core.pipeline.D2F`."""

    def focus_at(
        self,
        scene: Scene,
        x: float,
        y: float,
        radius: int | None = None,
        *,
        with_range: bool = False,
    ) -> float | tuple[float, float]:
        """Median disparity in a ``(2r+1)^2`` window around full-res pixel ``(x, y)``.

        ``(x, y)`` must lie in the photo, pixel centres at whole numbers: ``x`` in
        ``[-0.5, W - 0.5]``, ``y`` in ``[-0.5, H - 0.5]``; the window is clipped at its
        borders. ``radius`` defaults to ``max(2, round(max(H, W) / 200))`` px.

        With ``with_range``, also the focal range that keeps the clicked subject sharp: the
        extent in depth of the connected region around the point
        (:func:`~d2f_core.depth.subject.subject_range`), for :meth:`render`'s
        ``focal_range``.

        Returns:
            Focal disparity in [0, 1] for :meth:`render`; with ``with_range``,
            ``(focus, focal_range)``.

        Raises:
            ValueError: a point outside the photo, or not finite.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        try:
            xf, yf = float(x), float(y)
        except (TypeError, ValueError):
            raise InputTypeError(f"x and y must be numbers, got {x!r}, {y!r}") from None
        if not (math.isfinite(xf) and math.isfinite(yf)):
            raise ValueError(f"x and y must be finite, got {x!r}, {y!r}")
        height, width = scene.size
        if not (-0.5 <= xf <= width - 0.5 and -0.5 <= yf <= height - 0.5):
            raise ValueError(
                f"the point ({x!r}, {y!r}) is outside the {width}x{height} photo: x must be in "
                f"[0, {width - 1}] and y in [0, {height - 1}]"
            )
        r = None if radius is None else whole_number(radius, "radius", 0)
        window = scene.disparity_full_tensor()[0, 0][click_window(scene.size, xf, yf, r)]
        focus = float(np.clip(np.median(window.detach().cpu().numpy()), 0.0, 1.0))
        if not with_range:
            return focus
        return focus, self._range_at(scene, xf, yf, focus)

    @staticmethod
    def _range_at(scene: Scene, x: float, y: float, focus: float) -> float:
        """:func:`subject_range` at full-res pixel ``(x, y)`` on the scene's map at
        :data:`RANGE_MAP_SIDE` px (made once per scene)."""
        key = ("range_map", RANGE_MAP_SIDE)
        if key not in scene.cache:
            with torch.no_grad():
                d = scene.disparity_full_tensor()
                small = resize(d, scaled_size(scene.size, 1.0, RANGE_MAP_SIDE))
            scene.cache[key] = small[0, 0].clamp(0, 1).cpu().numpy()
        height, width = scene.size
        point = ((x + 0.5) / width, (y + 0.5) / height)
        return subject_range(scene.cache[key], point, focus)

    def default_focus(self, scene: Scene) -> AutoFocus:
        """The focus of a render given none, the one rule of the library, the CLI and the app:
        the focal plane the phone recorded with its depth (``scene.focus``) when there is one,
        as a thin lens; else the subject the map shows, with the focal range that keeps the
        whole subject sharp, as a click on it gets (:meth:`subject_focus` with its range)."""
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        if scene.focus is not None:
            return AutoFocus(float(scene.focus), 0.0, None, "photo")
        focus, point, focal_range = self.subject_focus(scene, with_range=True)
        return AutoFocus(float(focus), float(focal_range), point, "subject")

    def subject_focus(
        self, scene: Scene, *, with_range: bool = False
    ) -> tuple[float, tuple[float, float]] | tuple[float, tuple[float, float], float]:
        """The focal disparity of the subject the disparity map shows, and where it is
        (:func:`find_subject`); a map in which nothing stands out (flat, or a plain ramp) gets
        the focus at the centre, as :meth:`focus_at`.

        With ``with_range``, also the focal range that keeps the whole subject sharp, as a
        click there gets it (:meth:`focus_at`'s ``with_range``: the extent in depth of the
        connected region around the point, about the subject's focus). A map that spreads a
        near subject over some depth otherwise leaves only its focal plane sharp.

        Returns:
            ``(focus, (x, y))``, the point in full-res pixel coordinates; with
            ``with_range``, ``(focus, (x, y), focal_range)``.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        if "subject" not in scene.cache:  # found once per scene (the map never changes)
            with torch.no_grad():
                d = resize(scene.disparity_lr, scaled_size(scene.size, 1.0, 128))[0, 0]
            scene.cache["subject"] = locate_subject(
                d.cpu().numpy(), scene.size, lambda x, y: self.focus_at(scene, x, y)
            )
        focus, point = scene.cache["subject"]
        if not with_range:
            return focus, point
        return focus, point, self._range_at(scene, *point, focus)
