"""Views of a render smaller than the whole photo at full resolution: the whole picture at a
screen's size (:meth:`ViewStage.screen_scene`, ``D2F.render(..., screen=S)``) and one region
at full resolution (:meth:`ViewStage.render_region`, a 100 % loupe), each costing what its own
pixels cost rather than the whole photo's.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from ..depth.brushes import Brushes
from ..errors import InputTypeError
from ..sizing import resize, scaled_size, size_ratio
from .outputs import Result, Scene

#: The pass a region is rendered with reaches this many pass pixels beyond the largest CoC
#: radius around it: what blurs into the region is in it.
REGION_MARGIN = 4


class ViewStage:
    """Screen-size and region renders as methods of :class:`~d2f_core.pipeline.D2F`."""

    def screen_scene(self, scene: Scene, screen: int) -> Scene:
        """``scene`` at a long side of ``screen`` px (itself when it is no larger): the photo
        downscaled, the pass inputs at no more than that side (a preview's, else the scene's
        own), the full-resolution map the scene's downscaled, the paint and the recorded
        focus kept. Made once per size (the paint is not cached with it).

        A render of it is the full render downscaled, but for what fusion does at its own
        scale: a pixel is sharp where its CoC is under ``sharp_coc`` screen pixels.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        size = scaled_size(scene.size, 1.0, screen)
        if tuple(size) == tuple(scene.size):
            return scene
        key = ("screen", size)
        if key not in scene.cache:
            with torch.no_grad():
                # the pass at no more than the screen's size: a smaller one (the pass a photo
                # of that size gets) saves up to half the time at 12 MP but ends 35-37 dB
                # from the full render downscaled, where this one is 46-61 dB away
                lr_size = tuple(scene.image_lr.shape[-2:])
                if max(lr_size) > max(size):
                    image_lr, disparity_lr, radiance_lr = self._preview_inputs(scene, max(size))
                else:
                    image_lr, disparity_lr, radiance_lr = (
                        scene.image_lr, scene.disparity_lr, scene.radiance_lr
                    )  # fmt: skip
                scene.cache[key] = dataclasses.replace(
                    scene,
                    image=resize(scene.image, size).clamp_(0, 1),
                    image_lr=image_lr,
                    disparity_lr=disparity_lr,
                    radiance_lr=radiance_lr,
                    size=tuple(size),
                    brushes=None,
                    pixel_scale=scene.pixel_scale * size_ratio(size, scene.size),
                    cache={"disparity_full": resize(scene.disparity_full_tensor(), size)},
                )
        return dataclasses.replace(scene.cache[key], brushes=scene.brushes)

    def region_scene(self, scene: Scene, box: tuple[int, int, int, int], margin: int) -> tuple:
        """The part of ``scene`` around ``box = (x0, y0, x1, y1)`` (full-res pixels, ends
        excluded), with ``margin`` pass pixels more on every side: a :class:`Scene` of that
        part (the photo and the map at full resolution, the pass inputs cut from the scene's)
        and where ``box`` lies in it, ``(x0, y0, x1, y1)``."""
        height, width = scene.size
        h, w = (int(v) for v in scene.image_lr.shape[-2:])
        sy, sx = height / h, width / w
        x0, y0, x1, y1 = box
        # the pass's pixels that cover the box, and the margin
        lx0, ly0 = max(0, math.floor(x0 / sx) - margin), max(0, math.floor(y0 / sy) - margin)
        lx1, ly1 = min(w, math.ceil(x1 / sx) + margin), min(h, math.ceil(y1 / sy) + margin)
        # their full-resolution span (rounded: the pass maps onto it within half a pixel)
        fx0, fy0 = round(lx0 * sx), round(ly0 * sy)
        fx1, fy1 = min(width, round(lx1 * sx)), min(height, round(ly1 * sy))
        full = (slice(None), slice(None), slice(fy0, fy1), slice(fx0, fx1))
        lr = (slice(None), slice(None), slice(ly0, ly1), slice(lx0, lx1))
        d = scene.disparity_full_tensor()[full]
        part = dataclasses.replace(
            scene,
            image=scene.image[full],
            image_lr=scene.image_lr[lr],
            disparity_lr=scene.disparity_lr[lr],
            radiance_lr=scene.radiance_lr[lr],
            size=(fy1 - fy0, fx1 - fx0),
            given_disparity=d,
            brushes=None,
            cache={"disparity_full": d},
        )
        if scene.brushes is not None:  # the paint of that part, at full resolution
            cut = [
                None if m is None else m[full] for m in (scene.brushes.sharp, scene.brushes.blur)
            ]
            part.brushes = Brushes(*cut)
        return part, (x0 - fx0, y0 - fy0, x1 - fx0, y1 - fy0)

    @torch.no_grad()
    def render_region(
        self,
        scene: Scene,
        box: tuple[int, int, int, int],
        focus: float | None = None,
        blur: float | None = None,
        *,
        f_number: float | None = None,
        focal_range: float | None = None,
        **options: Any,
    ) -> Result:
        """The full-resolution render of one region only, ``box = (x0, y0, x1, y1)`` in
        full-res pixels (ends excluded): what :meth:`render` gives there, for a 100 % view.

        The pass is rendered over the region and what can blur into it (the largest CoC's
        radius and :data:`REGION_MARGIN` more), fusion over the region; focus, blur and the
        focal range are read from the whole photo as :meth:`render` reads them (the default
        focus, the f-number on the photo's long side). ``options`` as :meth:`render`'s
        (``fusion``, ``budget``, ``blades``, ...).

        Returns:
            :class:`Result` of the region: ``bokeh`` ``(y1 - y0, x1 - x0, 3)``, the maps of
            the part rendered.

        Raises:
            ValueError: a box that is not four whole numbers inside the photo, with
                ``x0 < x1`` and ``y0 < y1``.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        height, width = scene.size
        try:
            x0, y0, x1, y1 = (int(v) for v in box)
            exact = all(float(v) == int(v) for v in box)
        except (TypeError, ValueError):
            raise ValueError(
                f"box must be four whole numbers (x0, y0, x1, y1), got {box!r}"
            ) from None
        if not exact or not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
            raise ValueError(
                f"box {tuple(box)!r} must lie in the {width}x{height} photo, with x0 < x1 and "
                "y0 < y1"
            )
        render_options = {k: v for k, v in options.items() if k not in ("fusion", "budget")}
        focus, blur, focal_range, _ = self._render_args(
            scene, focus, blur, f_number, focal_range, None, dict(render_options)
        )
        lr_ratio = scene.image_lr.shape[-1] / width
        # the largest CoC in the pass: the blur at the farthest distance from the focus
        reach = blur * lr_ratio * max(focus, 1.0 - focus) * 0.5
        margin = math.ceil(reach) + REGION_MARGIN
        part, (a, b, c, d) = self.region_scene(scene, (x0, y0, x1, y1), margin)
        result = self.render(part, focus, blur, focal_range=focal_range, **options)
        result.bokeh = result.bokeh[b:d, a:c].copy()
        result.fusion_mask = result.fusion_mask[b:d, a:c].copy()
        return result
