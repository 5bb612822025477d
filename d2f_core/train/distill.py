"""Feature distillation for stage 0: the encoder learns to hold what an ONNX teacher's
intermediate features know of objects (``d2f-train depth --distill``; training only)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .teachers import FeatureTeacher

__all__ = ["DISTILL_STRIDE", "Distiller", "teacher_grid"]

#: the encoder map that feature distillation reads (with the next one upsampled onto it)
DISTILL_STRIDE = 16


def teacher_grid(teacher: FeatureTeacher, images: Tensor) -> Tensor:
    """The teacher's features of ``images`` (B x 3 x H x W in [0, 1]) averaged onto the
    grid of the network's stride-16 map, ``(H // 16, W // 16)``, as float16.

    Shape: (B, 3, H, W) -> (B, C, H // 16, W // 16).
    """
    h, w = images.shape[-2:]
    feats = torch.from_numpy(teacher(images.permute(0, 2, 3, 1).numpy()))
    grid = F.adaptive_avg_pool2d(feats, (max(1, h // DISTILL_STRIDE), max(1, w // DISTILL_STRIDE)))
    return grid.half()


class Distiller(torch.nn.Module):
    """Feature distillation head (training only; never part of a checkpoint that ships).

    A 1x1 convolution maps the encoder's stride-16 map and its stride-32 map (upsampled)
    onto the teacher's channels; the loss is the mean squared difference to the teacher's
    features, centred per channel and scaled by statistics fixed from the first batch (it
    starts at about 1: the convolution starts at zero). The network
    must then carry, linearly readable from its encoder, what the teacher's features hold.
    """

    def __init__(self, encoder_channels: Sequence[int], teacher_channels: int) -> None:
        super().__init__()
        self.proj = torch.nn.Conv2d(encoder_channels[2] + encoder_channels[3], teacher_channels, 1)
        torch.nn.init.zeros_(self.proj.weight)
        torch.nn.init.zeros_(self.proj.bias)
        self.register_buffer("mean", torch.zeros(1, teacher_channels, 1, 1))
        self.register_buffer("std", torch.ones(1, teacher_channels, 1, 1))
        self.register_buffer("ready", torch.zeros((), dtype=torch.bool))

    def fix_statistics(self, feats: Tensor) -> None:
        """Centre each channel on its mean over ``feats`` and scale all channels by one
        factor, their pooled standard deviation (a scale per channel would blow up the
        channels that happen to be near zero in one batch)."""
        flat = feats.float().transpose(0, 1).flatten(1)  # [C, N]
        mean = flat.mean(1)
        self.mean.copy_(mean.view_as(self.mean))
        pooled = (flat - mean[:, None]).pow(2).mean().sqrt().clamp_min(1e-6)
        self.std.fill_(float(pooled))
        self.ready.fill_(True)

    def forward(self, encoder_feats: Sequence[Tensor], teacher: Tensor) -> Tensor:
        f3, f4 = encoder_feats[2], encoder_feats[3]
        f4 = F.interpolate(f4, size=f3.shape[-2:], mode="bilinear", align_corners=False)
        pred = self.proj(torch.cat([f3, f4], dim=1))
        h, w = teacher.shape[-2:]
        target = (teacher.float() - self.mean) / self.std
        return (pred[..., :h, :w] - target).pow(2).mean()
