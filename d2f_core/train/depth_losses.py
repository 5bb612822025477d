"""Stage 0's losses: a scale- and shift-invariant L1 (relative targets of real photos), a
plain L1 (absolute targets of generated scenes) and multi-scale gradient matching (MiDaS);
the keep term, a weighted scale- and shift-invariant L1 to an earlier network's output; the
pairwise ranking term (pixel pairs whose targets differ must come out in the same order); and
the scene head's binary cross-entropy."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "depth_loss",
    "gradient_matching_loss",
    "keep_loss",
    "rank_loss",
    "scene_map_loss",
    "ssi_align",
]


def ssi_align(pred: Tensor, target: Tensor) -> Tensor:
    """``pred`` scaled and shifted per sample to fit ``target`` in least squares.

    Shape: (B, 1, H, W) and (B, 1, H, W) -> (B, 1, H, W).
    """
    p = pred.flatten(1)
    t = target.flatten(1)
    pm, tm = p.mean(1, keepdim=True), t.mean(1, keepdim=True)
    pc = p - pm
    scale = (pc * (t - tm)).sum(1, keepdim=True) / pc.pow(2).sum(1, keepdim=True).clamp_min(1e-6)
    return (scale * pc + tm).view_as(pred)


def gradient_matching_loss(pred: Tensor, target: Tensor, scales: int = 4) -> Tensor:
    """MiDaS gradient matching: mean |grad(pred - target)| over ``scales`` halvings."""
    diff = pred - target
    total = pred.new_zeros(())
    for s in range(scales):
        if s:
            diff = F.avg_pool2d(diff, 2)
        gx = (diff[..., :, 1:] - diff[..., :, :-1]).abs().mean()
        gy = (diff[..., 1:, :] - diff[..., :-1, :]).abs().mean()
        total = total + gx + gy
    return total / scales


def depth_loss(
    pred: Tensor,
    target: Tensor,
    relative: Tensor,
    absolute_weight: float = 0.25,
    grad_weight: float = 1.0,
) -> tuple[Tensor, dict[str, float]]:
    """Stage-0 loss of a batch (see the module docstring)."""
    rel = relative.to(pred.device).view(-1, 1, 1, 1).to(pred.dtype)
    aligned = ssi_align(pred, target)
    fit = rel * aligned + (1 - rel) * pred
    l1 = (fit - target).abs().mean()
    absolute = (rel * (pred - target).abs()).mean()
    grad = gradient_matching_loss(fit, target)
    loss = l1 + absolute_weight * absolute + grad_weight * grad
    return loss, {"l1": l1.item(), "abs": absolute.item(), "grad": grad.item()}


def keep_loss(pred: Tensor, reference: Tensor, weight: Tensor) -> Tensor:
    """Weighted scale- and shift-invariant L1 of ``pred`` to ``reference``.

    Per sample, over the pixels that ``weight`` (in [0, 1]) covers, both maps are centred
    on their weighted mean and scaled by their weighted mean absolute deviation (always
    positive, so a near-far swap is not fitted away; MiDaS normalises the same way with
    medians); the loss is the weighted mean absolute difference, in the reference's units.
    Samples with no weight count nothing. Only the relative depth inside the weighted
    region is held, not how it sits against the rest.

    Shape: three (B, 1, H, W) tensors -> a scalar.
    """
    w = weight.flatten(1)
    total = w.sum(1, keepdim=True)
    used = total.squeeze(1) > 0
    if not bool(used.any()):
        return pred.new_zeros(())
    w, total = w[used], total[used]

    def normed(x: Tensor) -> tuple[Tensor, Tensor]:
        x = x.flatten(1)[used]
        centred = x - (w * x).sum(1, keepdim=True) / total
        dev = (w * centred.abs()).sum(1, keepdim=True) / total
        return centred / dev.clamp_min(1e-6), dev

    p, _ = normed(pred)
    r, r_dev = normed(reference)
    return ((w * (p - r).abs()).sum(1, keepdim=True) / total * r_dev).mean()


def rank_loss(
    pred: Tensor,
    target: Tensor,
    pairs: int = 2048,
    reach: int = 12,
    margin: float = 0.25,
    gain: float = 2.0,
    edge: float = 0.0,
) -> Tensor:
    """Pairwise ranking loss: the order of pixel pairs, not their distance.

    Per sample, ``pairs`` pixel pairs are drawn: half anywhere in the frame (the layout),
    half within ``reach`` pixels of each other (a subject against what is right behind it).
    A share ``edge`` of the close pairs starts on a target edge: its first pixel is drawn in
    proportion to the target's step to its right and lower neighbours, so the pairs fall
    across silhouettes rather than inside flat regions.
    A pair counts when its targets differ by more than ``margin`` times the target's mean
    absolute deviation; its loss is ``softplus(-gain * s * (p_i - p_j))`` with ``s`` the
    sign of the targets' difference and ``p`` the prediction centred on its mean and
    divided by its mean absolute deviation (so a positive scale and a shift change nothing,
    and a near-far swap is never fitted away). Samples without a counted pair count nothing.

    Shape: (B, 1, H, W) and (B, 1, H, W) -> a scalar.
    """
    b, _, h, w = pred.shape
    p = pred.flatten(1)
    t = target.flatten(1).to(p.dtype)
    p = p - p.mean(1, keepdim=True)
    p = p / p.abs().mean(1, keepdim=True).clamp_min(1e-6)
    t_dev = (t - t.mean(1, keepdim=True)).abs().mean(1, keepdim=True)
    dev = pred.device
    half = pairs // 2
    first = torch.randint(0, h * w, (b, pairs), device=dev)
    on_edge = int(round(edge * (pairs - half)))
    if on_edge > 0:
        tm = target.detach().to(p.dtype)
        step = torch.zeros_like(tm)
        step[..., :, :-1] = (tm[..., :, 1:] - tm[..., :, :-1]).abs()
        down = (tm[..., 1:, :] - tm[..., :-1, :]).abs()
        step[..., :-1, :] = torch.maximum(step[..., :-1, :], down)
        step = step.flatten(1)
        weight = torch.where(step.sum(1, keepdim=True) > 0, step, torch.ones_like(step))
        first[:, pairs - on_edge :] = torch.multinomial(weight, on_edge, replacement=True)
    far = torch.randint(0, h * w, (b, half), device=dev)
    y0, x0 = first[:, half:] // w, first[:, half:] % w
    dy = torch.randint(-reach, reach + 1, (b, pairs - half), device=dev)
    dx = torch.randint(-reach, reach + 1, (b, pairs - half), device=dev)
    near = (y0 + dy).clamp(0, h - 1) * w + (x0 + dx).clamp(0, w - 1)
    second = torch.cat([far, near], 1)
    dt = t.gather(1, first) - t.gather(1, second)
    dp = p.gather(1, first) - p.gather(1, second)
    counted = (dt.abs() > margin * t_dev).to(p.dtype)
    per = F.softplus(-gain * torch.sign(dt) * dp) * counted
    n = counted.sum(1)
    used = n > 0
    if not bool(used.any()):
        return (pred * 0).sum()  # zero, still in the graph
    return (per.sum(1)[used] / n[used]).mean()


def scene_map_loss(logits: Tensor, maps: Tensor) -> Tensor:
    """Binary cross-entropy of the scene head's logits to its soft targets ``maps`` (in
    [0, 1]; negative where a photo's labels do not say), averaged over the known pixels of
    each map and then over the maps that have any; 0 when none has.

    Shape: (B, C, H, W) and (B, C, H, W) -> a scalar.
    """
    known = maps >= 0
    bce = F.binary_cross_entropy_with_logits(logits, maps.clamp(0, 1), reduction="none")
    per_map = (bce * known).flatten(2).sum(2)  # [B, C]
    count = known.flatten(2).sum(2)
    used = count > 0
    if not bool(used.any()):
        return (logits * 0).sum()  # zero, still in the graph
    return (per_map[used] / count[used]).mean()
