"""The steps of :meth:`D2F.render <d2f_core.pipeline.D2F.render>` as methods of the model: its
arguments checked, the rendering pass's inputs (a preview's, the screen's, the paint applied),
the adaptive settings, the pass itself, and the upsampling and fusion at full size.
"""

from __future__ import annotations

import math
import numbers
import time
from typing import Any

import torch
from torch import Tensor

from .. import rendering
from ..errors import InputTypeError, whole_number
from ..lens import blur_px
from ..rendering import adaptive
from ..rendering.kernels import check_rotation
from ..rendering.schedule import (
    check_focal_range,
    coc_to_defocus,
    outside_range,
)
from ..sizing import resize, scaled_size, size_ratio
from .fusion import FUSION_TILE, ms_since, to_numpy_image
from .outputs import Result, Scene


class RenderSteps:
    """:meth:`D2F.render`'s steps, on the model (its config, networks and renderer)."""

    def _adaptive_pass(
        self,
        scene: Scene,
        inputs: tuple[Tensor, Tensor, Tensor],
        focus: float,
        blur: float,
        lr_ratio: float,
        focal_range: float,
        budget: str | float | None,
        fusion: bool,
        preview: bool,
        render_options: dict[str, Any],
        timings: dict[str, float],
    ) -> tuple[adaptive.RenderSettings | None, bool, Tensor, Any]:
        """``(settings, fuse, bokeh_lr, behind_lr)``: the adaptive settings for ``budget``
        (``None``: the settings as given), whether fusion runs (asked for, a pass smaller
        than the scene, something near enough to the focal plane), and the pass (or the
        identity)."""
        image_lr, disparity_lr, _ = inputs
        lr_size = (int(image_lr.shape[-2]), int(image_lr.shape[-1]))
        settings = None
        gate_coc = self.gate_coc(scene.pixel_scale)  # the full-res CoC of the fusion gate
        if budget is not None:
            t0 = time.perf_counter()
            # (1.01: the CoC under which the gate can open, as _fuse_tiled reads it)
            settings = self._pick_settings(
                scene, disparity_lr, focus, blur, lr_ratio, budget, focal_range, gate_coc * 1.01,
                render_options, full=not preview,
            )  # fmt: skip
            timings["pick"] = ms_since(t0)
        identity = settings is not None and settings.identity
        fuse = (
            fusion
            and lr_size != tuple(scene.size)  # a full-size pass lost no detail to restore
            and not identity
            and (settings is None or settings.fusion)
        )
        t0 = time.perf_counter()
        # foreground layers blurred past the fusion gate (in the pass's px): fusion never
        # sharpens them, and must not paste what lies behind them over their blur
        options = render_options | {"front_size": gate_coc * lr_ratio}
        bokeh_lr, behind_lr = self._pass_or_identity(
            inputs, focus, blur * lr_ratio, fuse, settings, options
        )
        timings["render_lr"] = ms_since(t0)
        return settings, fuse, bokeh_lr, behind_lr

    def _result(
        self,
        scene: Scene,
        passed: tuple[Tensor, Any, Tensor],
        settings: adaptive.RenderSettings | None,
        fuse: bool,
        focus: float,
        blur: float,
        lr_ratio: float,
        focal_range: float,
        preview: bool,
        timings: dict[str, float],
    ) -> Result:
        """The :class:`Result` of a pass (``(bokeh_lr, behind_lr, disparity_lr)``): a
        preview as it is, the identity as the photo, else brought to full size (upsampled,
        fused where ``fuse``); every map as a numpy array."""
        bokeh_lr, behind_lr, disparity_lr = passed
        if preview:
            bokeh, mask = bokeh_lr, torch.zeros_like(disparity_lr)
        elif settings is not None and settings.identity:
            bokeh = scene.image.clone()
            mask = torch.ones((1, 1, *scene.size), device=bokeh.device)
        else:
            bokeh, mask = self._full_size(
                scene, bokeh_lr, behind_lr if fuse else None, fuse, focus, blur, lr_ratio,
                focal_range, timings,
            )  # fmt: skip
        t0 = time.perf_counter()
        defocus_lr = coc_to_defocus(blur * lr_ratio * (disparity_lr - focus).abs())
        result = Result(
            bokeh=to_numpy_image(bokeh.clamp_(0, 1)),
            bokeh_lr=to_numpy_image(bokeh_lr),
            disparity=disparity_lr[0, 0].cpu().numpy(),
            defocus=defocus_lr[0, 0].cpu().numpy(),
            fusion_mask=mask[0, 0].cpu().numpy(),
            timings=timings,
            settings=settings,
            focus=float(focus),
            focal_range=float(focal_range),
            photo_info=scene.photo_info,
        )
        timings["to_numpy"] = ms_since(t0)
        return result

    def _preview_inputs(self, scene: Scene, max_side: int) -> tuple[Tensor, Tensor, Tensor]:
        size = scaled_size(scene.size, 1.0, max_side)
        key = ("preview", size)
        if key not in scene.cache:
            lr_size = tuple(scene.image_lr.shape[-2:])
            src = scene.image_lr if size[0] <= lr_size[0] else scene.image
            scene.cache[key] = (
                resize(src, size).clamp(0, 1),
                resize(scene.disparity_lr, size).clamp(0, 1),
                resize(scene.radiance_lr, size),
            )
        return scene.cache[key]

    def _pass_or_identity(
        self,
        inputs: tuple[Tensor, Tensor, Tensor],
        focus: float,
        blur_lr: float,
        fuse: bool,
        settings: adaptive.RenderSettings | None,
        render_options: dict[str, Any],
    ) -> tuple[Tensor, Any]:
        """``(bokeh_lr, behind_lr)``: the rendering pass with the adaptive ``settings`` (if
        any) over ``render_options``, or the pass's photo itself when every CoC is under a
        pixel of the output (identity)."""
        image_lr, disparity_lr, radiance_lr = inputs
        if settings is not None and settings.identity:
            return image_lr, None
        options = render_options | (settings.render_options() if settings else {})
        return self._render_pass(image_lr, disparity_lr, radiance_lr, focus, blur_lr, fuse, options)

    def _pass_inputs(
        self, scene: Scene, max_side: int | None, screen: int | None, focus: float, blur: float
    ) -> tuple[Scene, float, tuple[Tensor, Tensor, Tensor]]:
        """``(scene, blur, (photo, map, radiance))``: the scene the full-size steps see (at
        ``screen``'s size, with K in its pixels, when a screen is given and it is no
        preview; its full map edited by the paint for ``focus``), and the inputs of the
        rendering pass: the scene's own, or a preview's at ``max_side`` (cached per size),
        the map edited by the paint."""
        if screen is not None and max_side is None:
            small = self.screen_scene(scene, whole_number(screen, "screen", 1))
            blur *= size_ratio(small.size, scene.size)  # K in the screen's pixels
            scene = small
        if max_side is not None:
            image_lr, disparity_lr, radiance_lr = self._preview_inputs(scene, int(max_side))
        else:
            image_lr, disparity_lr, radiance_lr = (
                scene.image_lr,
                scene.disparity_lr,
                scene.radiance_lr,
            )
        if scene.brushes is not None:
            disparity_lr = scene.brushes.apply(disparity_lr, focus)
            if max_side is None:
                scene = scene.brushed(focus)
        return scene, blur, (image_lr, disparity_lr, radiance_lr)

    def _render_args(
        self,
        scene: Any,
        focus: float | None,
        blur: float | None,
        f_number: float | None,
        focal_range: float | None,
        budget: Any,
        render_options: dict[str, Any],
    ) -> tuple[float, float, float, str | float | None]:
        """:meth:`render`'s arguments checked: ``(focus, blur, focal_range, budget)``, the
        default focus found and ``render_options`` given the model's order and placement.

        Raises:
            ValueError: naming the bad argument.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        if f_number is not None:
            if blur is not None:
                raise ValueError("give blur or f_number, not both")
            if isinstance(f_number, bool) or not isinstance(f_number, numbers.Real):
                raise ValueError(f"f_number must be a number, got {f_number!r}")
            blur = blur_px(float(f_number), max(scene.size))
        if focus is None:
            focus, auto_range, _, _ = self.default_focus(scene)
            focal_range = auto_range if focal_range is None else focal_range
        focal_range = 0.0 if focal_range is None else focal_range
        focus, blur = rendering.check_focus_blur(focus, 40.0 if blur is None else blur)
        focal_range = check_focal_range(focal_range)
        if "rotation" in render_options:  # named even when no kernel needs it
            render_options["rotation"] = check_rotation(render_options["rotation"])
        if "radiance" in render_options:
            raise ValueError("render_options must not contain 'radiance' (it comes from scene)")
        if "checked" in render_options:
            raise ValueError("render_options must not contain 'checked' (D2F.render sets it)")
        render_options.setdefault("order", self.config.order)
        render_options.setdefault("placement", self.config.placement)
        if isinstance(budget, str):
            if budget not in adaptive.BUDGETS:
                names = sorted(adaptive.BUDGETS)
                raise ValueError(
                    f"budget must be one of {names}, a dB value or None, got {budget!r}"
                )
        elif budget is not None:
            bad = f"budget must be a name, a dB value or None, got {budget!r}"
            if isinstance(budget, bool):
                raise ValueError(bad)
            try:
                budget = float(budget)
            except (TypeError, ValueError):
                raise ValueError(bad) from None
            if not math.isfinite(budget) or budget <= 0:
                raise ValueError(f"budget must be a PSNR above 0 dB, got {budget}")
        return focus, blur, focal_range, budget

    def _pick_settings(
        self,
        scene: Scene,
        disparity_lr: Tensor,
        focus: float,
        blur: float,
        lr_ratio: float,
        budget: str | float,
        focal_range: float,
        gate_coc: float,
        render_options: dict[str, Any],
        full: bool,
    ) -> adaptive.RenderSettings:
        """The adaptive settings for this focus and blur (:func:`adaptive.choose_settings`
        on the pass's map); for a ``full`` render, identity and fusion then decided from the
        full-resolution map."""
        named = isinstance(budget, str)
        settings = adaptive.choose_settings(
            disparity_lr,
            focus,
            blur * lr_ratio,
            budget_db=None if named else budget,
            quality=budget if named else adaptive.DEFAULT_QUALITY,
            schedule=render_options.get("schedule", "growing"),
            placement=render_options["placement"],
            full_scale=1.0 / lr_ratio if full else 1.0,
            fusion_coc=gate_coc,
            checked=True,  # focus and blur were checked by _render_args; blur_lr <= blur
        )
        if full:
            self._full_size_decisions(scene, settings, focus, blur, focal_range, gate_coc)
        return settings

    def _full_size_decisions(
        self,
        scene: Scene,
        settings: adaptive.RenderSettings,
        focus: float,
        blur: float,
        focal_range: float,
        gate_coc: float,
    ) -> None:
        """Decide ``settings.identity`` and ``settings.fusion`` from the full-resolution map
        (a given map can hold finer extremes than its low-res copy): identity when every
        output CoC is under a pixel, fusion when some pixel is near enough to focus for
        :meth:`_fuse_tiled` to touch it."""
        lo, hi = scene.disparity_tile_range(FUSION_TILE)
        far = float(torch.maximum((hi - focus).abs(), (lo - focus).abs()).max())
        near = float(torch.clamp(torch.maximum(lo - focus, focus - hi), min=0.0).min())
        far, near = (outside_range(v, focal_range) for v in (far, near))
        settings.identity = blur * far < 1.0
        settings.fusion = blur * near < max(gate_coc, 2.0 * self.config.sharp_coc)

    def _render_pass(
        self,
        image_lr: Tensor,
        disparity_lr: Tensor,
        radiance_lr: Tensor,
        focus: float,
        blur_lr: float,
        fuse: bool,
        options: dict[str, Any],
    ) -> tuple[Tensor, tuple[Tensor, Tensor] | None]:
        """The layered render at the pass's size, ``(bokeh_lr, behind_lr)``: with ``fuse``,
        ``behind_lr`` is what the layers behind the blurred foreground make of each pixel
        (share and colour; ``None`` where nothing is in front), the only part fusion
        sharpens."""
        out = rendering.render(
            image_lr,
            disparity_lr,
            focus,
            blur_lr,
            radiance=radiance_lr,
            behind=fuse,
            checked=True,
            **options,
        )  # [1,3,h,w]
        if not fuse:
            return out, None
        bokeh_lr, share_lr, colour_lr = out
        behind = (share_lr, colour_lr) if bool((share_lr < 1.0 - 1e-4).any()) else None
        return bokeh_lr, behind

    def _full_size(
        self,
        scene: Scene,
        bokeh_lr: Tensor,
        behind_lr: tuple[Tensor, Tensor] | None,
        fuse: bool,
        focus: float,
        blur: float,
        lr_ratio: float,
        focal_range: float,
        timings: dict[str, float],
    ) -> tuple[Tensor, Tensor]:
        """Paper step 6: the pass upsampled to the photo's size and, with ``fuse``, deep
        Poisson fusion; ``(bokeh, mask)`` at full resolution."""
        t0 = time.perf_counter()
        bokeh = resize(bokeh_lr, scene.size)  # [1,3,H,W]
        if bokeh is bokeh_lr:
            bokeh = bokeh.clone()  # fusion writes into it; bokeh_lr is returned too
        timings["upsample"] = ms_since(t0)
        if not fuse:
            return bokeh, torch.zeros((1, 1, *scene.size), device=bokeh.device)
        t0 = time.perf_counter()
        behind = None
        if behind_lr is not None:
            behind = tuple(resize(t, scene.size).clamp_(0, 1) for t in behind_lr)
        bokeh, mask = self._fuse_tiled(scene, bokeh, focus, blur, lr_ratio, behind, focal_range)
        timings["fusion"] = ms_since(t0)
        return bokeh, mask
