"""Deep Poisson fusion, D2F step 6: ``B_hr = M_s I_hr + (1 - M_s) upsample(B_lr)`` with the
mask ``M_s = f_p(I_hr, D)``, at full resolution, tile by tile on large frames.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from ..depth.subject import index_runs
from ..networks import rgb_to_gray
from ..rendering.schedule import coc_to_defocus, defocus_to_coc, outside_range
from .outputs import Scene

FUSION_TILE = 256
#: ``M_s`` fades out over this share of the gate's CoC below it (:meth:`FusionStage.gate`):
#: a hard gate drew a line across a receding floor, where a third of the sharp photo over a
#: 23 px blur met none over a 24 px one (the detail there dropped 15-fold from one row to the
#: next). With the fade (docs/accuracy.md, "The gate fades"): generated pairs 26.43 dB at
#: their focus as before, 27.05 against 27.08 with no focus given, real cut-outs 30.11
#: against 30.11, six 12 MP scenes 35.58 against 35.57
GATE_FADE = 0.5


# helpers of the fusion stage that the model's render uses too


def per_sample(value: float | Tensor, batch: int, ref: Tensor) -> Tensor:
    """Scalar or ``[B]`` -> ``[B, 1, 1, 1]`` on ``ref``'s device and dtype."""
    t = torch.as_tensor(value, dtype=ref.dtype, device=ref.device).reshape(-1)
    if t.numel() == 1:
        t = t.expand(batch)
    if t.numel() != batch:
        raise ValueError(f"expected a scalar or {batch} values, got {t.numel()}")
    return t.reshape(batch, 1, 1, 1)


def to_numpy_image(x: Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).contiguous().cpu().numpy()


def ms_since(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


class FusionStage:
    """D2F's step 6 as methods of :class:`~d2f_core.pipeline.D2F`: the fusion mask ``M_s`` and
    ``B_hr = M_s I_hr + (1 - M_s) upsample(B_lr)``, tile by tile on large frames."""

    def gate_coc(self, pixel_scale: float = 1.0) -> float:
        """The CoC (px of a scene at ``pixel_scale``, its ``Scene.pixel_scale``: 1 at the
        photo's own size) from which the fusion gate keeps ``M_s`` at 0: the gate's
        ``D`` at the pass a photo gets at ``render_scale``, counted in the photo's own pixels
        (24 px at the shipped 0.3 and 0.5). One blur in the photo is then gated alike whatever
        pass renders it: a large photo's pass is capped at ``max_render_side``, and a gate at
        the pass's own scale let the sharp photo back up to 46 px of CoC at 12 MP with a
        1024 px pass. A screen's render counts it in its own pixels."""
        cfg = self.config
        return defocus_to_coc(cfg.fusion_gate) / cfg.render_scale * pixel_scale

    def gate(self, coc: Tensor, gate_coc: float) -> Tensor:
        """What is left of ``M_s`` at a CoC of ``coc`` (px) under a gate at ``gate_coc``: 1
        up to ``(1 - GATE_FADE) gate_coc``, then falling linearly to 0 at ``gate_coc``."""
        return ((gate_coc - coc) / (GATE_FADE * gate_coc)).clamp_(0, 1)

    def fusion_mask(
        self,
        image: Tensor,
        disparity: Tensor,
        focus: float | Tensor,
        blur: float | Tensor,
        lr_ratio: float,
    ) -> tuple[Tensor, Tensor]:
        """Soft fusion mask ``M = max(M_s, P)`` at full resolution (dense, differentiable).

        Args:
            image: ``I_hr``, ``(B, 3, H, W)`` in [0, 1].
            disparity: full-resolution disparity ``(B, 1, H, W)`` in [0, 1].
            focus: focal disparity, float or ``[B]``.
            blur: ``K`` in px at full resolution, float or ``[B]``.
            lr_ratio: size of the low-res pass over full size (the defocus ``D`` fed to
                ``f_p`` is the paper's normalised defocus of the CoC at the low-res pass).

        Returns:
            ``(M, M_s)``, both ``(B, 1, H, W)`` in [0, 1].
        """
        cfg = self.config
        b = image.shape[0]
        f = per_sample(focus, b, image)
        k = per_sample(blur, b, image)
        coc = k * (disparity - f).abs()  # [B,1,H,W] full-res px
        prior = ((2.0 * cfg.sharp_coc - coc) / cfg.sharp_coc).clamp(0, 1)
        defocus = coc_to_defocus(coc * lr_ratio)
        gate = self.gate(coc.detach(), self.gate_coc())
        m_s = self.fusion_net(1.0 - defocus, rgb_to_gray(image)) * gate
        return torch.maximum(m_s, prior), m_s

    def _fuse_tiled(
        self,
        scene: Scene,
        bokeh_up: Tensor,
        focus: float,
        blur: float,
        lr_ratio: float,
        behind: tuple[Tensor, Tensor] | None = None,
        focal_range: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        """``B_hr = lerp(B_up, I_hr, M)`` computed tile by tile (inference), in place.

        Each 256-px tile is classified from the range of the disparity inside it (cached per
        scene): far from focus (``M = 0``: keep ``B_up``), entirely sharp (``CoC <= sharp_coc``
        everywhere: ``M = 1``), or mixed, where ``M`` is computed per pixel, running ``f_p``
        only if some pixel can pass its gate. The result equals the dense
        :meth:`fusion_mask` blend; the cost follows the in-focus part of the frame.

        ``behind`` (full size, from ``rendering.render(..., behind=True)``): the share of
        each pixel that the layers at and behind the focal plane make, and their colour.
        Where a blurred foreground covers an in-focus pixel, only that part is sharpened,
        ``B_hr = B_up + M * share * (I_hr - colour)``, so the foreground's blur stays over
        it (a plain lerp pasted the sharp background over the blur of a near object, which
        then ended in a hard edge); where nothing is in front this is the lerp. The mask
        returned is then ``M * share``, the weight of the sharp photo in the result.

        ``focal_range``: CoCs count from the range's edges (``K max(0, |d - f| - r/2)``), so
        every pixel inside the range has CoC 0 and ``M = 1``: the photo's own pixel.

        Returns:
            ``(bokeh, mask)``: ``(1, 3, H, W)`` (``bokeh_up``, modified) and ``(1, 1, H, W)``.
        """
        cfg = self.config
        height, width = scene.size
        t = FUSION_TILE
        lo, hi = scene.disparity_tile_range(t)  # [gh,gw]
        # CoC range of each tile: distance of [lo, hi] to the focal plane
        coc_lo = blur * outside_range(
            torch.clamp(torch.maximum(lo - focus, focus - hi), min=0.0), focal_range
        )
        coc_hi = blur * outside_range(
            torch.maximum((hi - focus).abs(), (lo - focus).abs()), focal_range
        )
        gate_coc = self.gate_coc(scene.pixel_scale)
        sharp = cfg.sharp_coc
        all_sharp = coc_hi <= sharp
        needs_net = (coc_lo < gate_coc * 1.01) & (coc_hi > sharp)
        needs_pixels = ((coc_lo < 2 * sharp) | needs_net) & ~all_sharp
        mask = torch.zeros((1, 1, height, width), device=bokeh_up.device, dtype=bokeh_up.dtype)
        image, d_full = scene.image, scene.disparity_full_tensor()
        halo = self.fusion_net.halo

        def sharpen(y0: int, y1: int, x0: int, x1: int, m: Tensor | float) -> None:
            """Put the photo back into ``bokeh_up`` with weight ``m`` over one region."""
            region, photo = bokeh_up[..., y0:y1, x0:x1], image[..., y0:y1, x0:x1]
            if behind is None:
                mask[..., y0:y1, x0:x1] = m
                if isinstance(m, float):  # m = 1: the photo itself
                    region.copy_(photo)
                else:
                    region.copy_(torch.lerp(region, photo, m))
                return
            m = behind[0][..., y0:y1, x0:x1] * m
            mask[..., y0:y1, x0:x1] = m
            region.addcmul_(m, photo - behind[1][..., y0:y1, x0:x1])

        for row in range(lo.shape[0]):
            y0, y1 = row * t, min(height, (row + 1) * t)
            for c in torch.nonzero(all_sharp[row]).flatten().tolist():
                sharpen(y0, y1, c * t, min(width, (c + 1) * t), 1.0)
            for c0, c1 in index_runs(torch.nonzero(needs_pixels[row]).flatten().tolist()):
                x0, x1 = c0 * t, min(width, (c1 + 1) * t)
                use_net = bool(needs_net[row, c0 : c1 + 1].any())
                pad = halo if use_net else 0
                ya, yb = max(0, y0 - pad), min(height, y1 + pad)
                xa, xb = max(0, x0 - pad), min(width, x1 + pad)
                distance = (d_full[..., ya:yb, xa:xb] - focus).abs()
                coc = blur * outside_range(distance, focal_range)  # [1,1,h',w']
                m = ((2.0 * sharp - coc) / sharp).clamp_(0, 1)
                if use_net:
                    defocus = coc_to_defocus(coc * lr_ratio)
                    m_s = self.fusion_net(
                        (1.0 - defocus).contiguous(memory_format=torch.channels_last),
                        rgb_to_gray(image[..., ya:yb, xa:xb]).contiguous(
                            memory_format=torch.channels_last
                        ),
                    )
                    m_s = m_s * self.gate(coc, gate_coc)
                    m = torch.maximum(m, m_s)
                sharpen(y0, y1, x0, x1, m[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa])
        return bokeh_up, mask
