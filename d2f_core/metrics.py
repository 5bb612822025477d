"""Image quality metrics: PSNR and SSIM on numpy ``H x W x C`` or torch ``(B, C, H, W)``."""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity

__all__ = ["psnr", "ssim"]


def _as_numpy(x, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        t = x.detach().to("cpu", torch.float64)
        if t.ndim == 4:
            t = t.permute(0, 2, 3, 1)  # [B,H,W,C]
        elif t.ndim == 3:
            t = t.permute(1, 2, 0)
        return t.numpy()
    arr = np.asarray(x)
    if arr.dtype == np.uint8:
        return arr.astype(np.float64) / 255.0
    return arr.astype(np.float64)


def _pair(pred, target) -> tuple[np.ndarray, np.ndarray]:
    a, b = _as_numpy(pred, "pred"), _as_numpy(target, "target")
    if a.shape != b.shape:
        raise ValueError(f"pred shape {a.shape} does not match target shape {b.shape}")
    if a.size == 0:
        raise ValueError("pred is empty")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("pred and target must be finite")
    return a, b


def psnr(pred, target, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (``inf`` for identical inputs), over all elements."""
    a, b = _pair(pred, target)
    mse = float(np.mean((a - b) ** 2))
    if mse == 0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / mse)


def ssim(pred, target, data_range: float = 1.0) -> float:
    """Mean structural similarity (Gaussian window, sigma 1.5), averaged over a batch."""
    a, b = _pair(pred, target)
    if a.ndim == 4:
        return float(np.mean([ssim(x, y, data_range) for x, y in zip(a, b, strict=True)]))
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    small = min(a.shape[0], a.shape[1])
    if small < 7:
        win = max(1, small if small % 2 else small - 1)
        return float(
            structural_similarity(a, b, data_range=data_range, channel_axis=-1, win_size=win)
        )
    return float(
        structural_similarity(
            a,
            b,
            data_range=data_range,
            channel_axis=-1,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    )
