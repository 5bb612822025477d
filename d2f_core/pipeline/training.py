"""The differentiable training forwards of D2F (the two-stage training): stage 1 renders the
low-resolution bokeh from the defocus and radiance networks, stage 2 adds deep Poisson fusion
at full resolution, as methods of :class:`~d2f_core.pipeline.D2F`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .. import rendering
from ..rendering.schedule import coc_to_defocus
from ..sizing import resize, scaled_size, size_ratio
from .fusion import per_sample

__all__ = ["TrainingStage"]


class TrainingStage:
    """``forward_stage1`` and ``forward_stage2`` (training), as methods of
    :class:`~d2f_core.pipeline.D2F` (which holds ``config`` and the three networks)."""

    def _render_batch(
        self,
        image: Tensor,
        disparity: Tensor,
        focus: Tensor,
        blur: Tensor,
        radiance: Tensor,
        **options: Any,
    ) -> Tensor:
        # rendering.render takes one blur per call; group samples that share it
        blur_list = [float(v) for v in blur.reshape(-1)]
        focus = focus.reshape(-1)
        if all(v == blur_list[0] for v in blur_list):
            return rendering.render(
                image, disparity, focus, blur_list[0], radiance=radiance, **options
            )
        outs = [
            rendering.render(
                image[i : i + 1],
                disparity[i : i + 1],
                focus[i : i + 1],
                blur_list[i],
                radiance=radiance[i : i + 1],
                **options,
            )
            for i in range(image.shape[0])
        ]
        return torch.cat(outs, dim=0)

    def forward_stage1(
        self, image_lr: Tensor, focus: float | Tensor, blur_lr: float | Tensor, **options: Any
    ) -> dict[str, Tensor]:
        """Differentiable low-resolution bokeh (training stage 1).

        Args:
            image_lr: ``(B, 3, h, w)`` in [0, 1]; the defocus network runs at this size.
            focus: focal disparity, float or ``[B]`` in [0, 1].
            blur_lr: ``K`` in px at this resolution, float or ``[B]``.
            **options: passed to ``rendering.render``.

        Returns:
            ``{"bokeh_lr": (B,3,h,w), "disparity": (B,1,h,w), "radiance": (B,1,h,w)}``.
        """
        b = image_lr.shape[0]
        options.setdefault("order", self.config.order)
        options.setdefault("placement", self.config.placement)
        disparity = self.defocus_net(image_lr)  # [B,1,h,w]
        radiance = self.radiance_net(image_lr)  # [B,1,h,w]
        f = per_sample(focus, b, image_lr).reshape(-1)
        k = per_sample(blur_lr, b, image_lr).reshape(-1)
        bokeh = self._render_batch(image_lr, disparity, f, k, radiance, **options)
        return {"bokeh_lr": bokeh, "disparity": disparity, "radiance": radiance}

    def forward_stage2(
        self, image: Tensor, focus: float | Tensor, blur: float | Tensor, **options: Any
    ) -> dict[str, Tensor]:
        """Full-resolution fused bokeh (training stage 2; gradients reach ``f_p`` only).

        Args:
            image: ``I_hr``, ``(B, 3, H, W)`` in [0, 1].
            focus: focal disparity, float or ``[B]``.
            blur: ``K`` in px at full resolution, float or ``[B]``.

        Returns:
            dict with ``bokeh`` (B,3,H,W) = fused ``B_hr``, ``bokeh_up`` (B,3,H,W),
            ``bokeh_lr`` (B,3,h,w), ``disparity_lr`` (B,1,h,w), ``disparity`` (B,1,H,W),
            ``defocus`` (B,1,H,W) paper-normalised, ``mask`` and ``mask_soft`` (B,1,H,W).
        """
        b = image.shape[0]
        size = (int(image.shape[-2]), int(image.shape[-1]))
        lr_size = scaled_size(size, self.config.render_scale, None)
        lr_ratio = size_ratio(lr_size, size)
        k = per_sample(blur, b, image)
        f = per_sample(focus, b, image)
        frozen = (self.defocus_net, self.radiance_net)
        modes = [m.training for m in frozen]
        with torch.no_grad():
            # the stage-1 networks are frozen here: batch statistics must not move
            for m in frozen:
                m.eval()
            image_lr = resize(image, lr_size).clamp(0, 1)
            low = self.forward_stage1(
                image_lr, f.reshape(-1), (k * lr_ratio).reshape(-1), **options
            )
            bokeh_up = resize(low["bokeh_lr"], size)  # [B,3,H,W]
            disparity = resize(low["disparity"], size).clamp(0, 1)  # [B,1,H,W]
            for m, mode in zip(frozen, modes, strict=True):
                m.train(mode)
        mask, mask_soft = self.fusion_mask(image, disparity, f, k, lr_ratio)
        bokeh = torch.lerp(bokeh_up, image, mask)
        defocus = coc_to_defocus(k * lr_ratio * (disparity - f).abs())
        return {
            "bokeh": bokeh,
            "bokeh_up": bokeh_up,
            "bokeh_lr": low["bokeh_lr"],
            "disparity_lr": low["disparity"],
            "disparity": disparity,
            "defocus": defocus,
            "mask": mask,
            "mask_soft": mask_soft,
        }
