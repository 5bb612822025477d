"""Training losses of D2F.

Stage 1 (defocus + radiance networks): ``L1 + 0.1 * L_vgg + L_ssim + 0.1 * L_grad``.
Stage 2 (fusion network): the stage-1 terms on the fused image ``+ 10 * L_p``.

- :func:`ssim` is differentiable (Gaussian window, 11 px, sigma 1.5); ``L_ssim = 1 - SSIM``.
- :class:`PerceptualLoss` uses VGG19 features whose ImageNet weights come from a LOCAL
  state-dict file only; without one it is switched off (logged once) and returns 0.
- :func:`edge_aware_smoothness` is ``L_grad`` over 4 scales.
- :func:`poisson_loss` is ``L_p = mean((lap(B_t) - lap(B_hr))^2) / 2`` with the target
  ``B_t = I_hr * M_b + B_up * (1 - M_b)``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..errors import InputTypeError
from ..networks import IMAGENET_MEAN, IMAGENET_STD, load_local_state_dict

__all__ = [
    "D2FLoss",
    "PerceptualLoss",
    "VGG19Features",
    "binary_focus_mask",
    "edge_aware_smoothness",
    "gaussian_window",
    "l1_loss",
    "laplacian",
    "poisson_loss",
    "ssim",
    "ssim_loss",
]

logger = logging.getLogger(__name__)


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if not isinstance(pred, Tensor) or not isinstance(target, Tensor):
        raise InputTypeError("pred and target must be torch.Tensors")
    if pred.ndim != 4:
        raise ValueError(f"pred must have shape [B,C,H,W], got {tuple(pred.shape)}")
    if pred.shape != target.shape:
        raise ValueError(
            f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must have the same shape"
        )


def l1_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Mean absolute error. Shape: (B, C, H, W) x2 -> scalar."""
    _check_pair(pred, target)
    return (pred - target).abs().mean()


def gaussian_window(size: int = 11, sigma: float = 1.5, *, device=None, dtype=None) -> Tensor:
    """Normalised 2-D Gaussian window, ``[size, size]`` summing to 1."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"size must be a positive odd integer, got {size}")
    x = torch.arange(size, device=device, dtype=dtype or torch.float32) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim(
    pred: Tensor, target: Tensor, *, window: int = 11, sigma: float = 1.5, data_range: float = 1.0
) -> Tensor:
    """Mean structural similarity (Wang et al. 2004), differentiable.

    Gaussian-weighted local statistics over 'valid' windows (no padding); the window shrinks
    to the image for inputs smaller than ``window``.

    Shape: (B, C, H, W) x2 -> scalar in [-1, 1] (1 for identical inputs).
    """
    _check_pair(pred, target)
    size = min(window, pred.shape[-2], pred.shape[-1])
    size -= 1 - size % 2
    c = pred.shape[1]
    w = gaussian_window(size, sigma, device=pred.device, dtype=pred.dtype)
    w = w.expand(c, 1, size, size)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2

    def filt(x: Tensor) -> Tensor:
        return F.conv2d(x, w, groups=c)

    mu_x, mu_y = filt(pred), filt(target)
    sxx = filt(pred * pred) - mu_x**2
    syy = filt(target * target) - mu_y**2
    sxy = filt(pred * target) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2)
    return (num / den).mean()


def ssim_loss(pred: Tensor, target: Tensor, **kwargs) -> Tensor:
    """``1 - ssim(pred, target)``; 0 for identical inputs. Shape: (B, C, H, W) x2 -> scalar."""
    return 1.0 - ssim(pred, target, **kwargs)


def edge_aware_smoothness(disparity: Tensor, image: Tensor, scales: int = 4) -> Tensor:
    """``L_grad``: edge-aware smoothness of a one-channel map, averaged over ``scales``.

    At each scale ``s`` (both inputs average-pooled by ``2**s``):
    ``mean(|dx D| * exp(-||dx I||_1)) + mean(|dy D| * exp(-||dy I||_1))``, where
    ``||.||_1`` sums over colour channels.

    Shape: disparity (B, 1, H, W), image (B, 3, H, W) -> scalar >= 0.
    """
    if disparity.ndim != 4 or disparity.shape[1] != 1:
        raise ValueError(f"disparity must have shape [B,1,H,W], got {tuple(disparity.shape)}")
    if image.ndim != 4 or image.shape[-2:] != disparity.shape[-2:]:
        raise ValueError(
            f"image {tuple(image.shape)} must match disparity {tuple(disparity.shape)} in size"
        )
    if scales < 1:
        raise ValueError(f"scales must be >= 1, got {scales}")
    total = disparity.new_zeros(())
    used = 0
    d, im = disparity, image
    for s in range(scales):
        if s > 0:
            if min(d.shape[-2:]) < 2:
                break
            d, im = F.avg_pool2d(d, 2), F.avg_pool2d(im, 2)
        terms = []
        if d.shape[-1] > 1:
            dx_d = (d[..., :, 1:] - d[..., :, :-1]).abs()
            dx_i = (im[..., :, 1:] - im[..., :, :-1]).abs().sum(dim=1, keepdim=True)
            terms.append((dx_d * torch.exp(-dx_i)).mean())
        if d.shape[-2] > 1:
            dy_d = (d[..., 1:, :] - d[..., :-1, :]).abs()
            dy_i = (im[..., 1:, :] - im[..., :-1, :]).abs().sum(dim=1, keepdim=True)
            terms.append((dy_d * torch.exp(-dy_i)).mean())
        total = total + sum(terms, disparity.new_zeros(()))
        used += 1
    return total / max(used, 1)


def laplacian(x: Tensor) -> Tensor:
    """5-point Laplacian per channel with replicated borders. Shape: (B, C, H, W) -> same."""
    if x.ndim != 4:
        raise ValueError(f"x must have shape [B,C,H,W], got {tuple(x.shape)}")
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]], dtype=x.dtype)
    k = k.to(x.device).expand(x.shape[1], 1, 3, 3)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), k, groups=x.shape[1])


def binary_focus_mask(defocus: Tensor, theta: float = 0.25) -> Tensor:
    """``M_b``: 1 where the paper-normalised defocus is below ``theta``. Shape: same, {0, 1}."""
    return (defocus < theta).to(defocus.dtype)


def poisson_loss(fused: Tensor, image: Tensor, upsampled: Tensor, mask: Tensor) -> Tensor:
    """``L_p = mean((lap(B_t) - lap(B_hr))^2) / 2``, ``B_t = I_hr * M_b + B_up * (1 - M_b)``.

    Args:
        fused: ``B_hr``, (B, 3, H, W).
        image: ``I_hr``, (B, 3, H, W).
        upsampled: ``B_up``, (B, 3, H, W).
        mask: ``M_b``, (B, 1, H, W) in {0, 1} (or soft).

    Returns:
        Scalar >= 0.
    """
    _check_pair(fused, image)
    _check_pair(fused, upsampled)
    target = image * mask + upsampled * (1 - mask)
    return ((laplacian(target) - laplacian(fused)) ** 2).mean() / 2


# --------------------------------------------------------------------------------------
# perceptual loss
# --------------------------------------------------------------------------------------

# torchvision's vgg19 "features" layout: numbers are conv widths, "M" a 2x2 max-pool.
_VGG19_CFG: tuple[int | str, ...] = (
    64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M",
    512, 512, 512, 512, "M", 512, 512, 512, 512, "M",
)  # fmt: skip
_VGG19_RELU = {
    "relu1_2": 3,
    "relu2_2": 8,
    "relu3_4": 17,
    "relu4_4": 26,
    "relu5_4": 35,
}


class VGG19Features(nn.Module):
    """VGG19 convolutional trunk; returns the activations named in ``layers``.

    Module indices match torchvision's ``vgg19().features`` so its state dict loads
    directly. Input in [0, 1]; ImageNet normalisation happens inside.

    Shape: (B, 3, H, W) -> list of (B, C_l, H_l, W_l).
    """

    def __init__(self, layers: Sequence[str] = ("relu1_2", "relu2_2", "relu3_4", "relu4_4")):
        super().__init__()
        unknown = [name for name in layers if name not in _VGG19_RELU]
        if unknown or not layers:
            raise ValueError(f"layers must be a non-empty subset of {list(_VGG19_RELU)}")
        self.layers = list(layers)
        self._taps = sorted(_VGG19_RELU[name] for name in layers)
        modules: list[nn.Module] = []
        cin = 3
        for item in _VGG19_CFG:
            if item == "M":
                modules.append(nn.MaxPool2d(2, 2))
            else:
                modules += [nn.Conv2d(cin, int(item), 3, 1, 1), nn.ReLU(inplace=False)]
                cin = int(item)
        # nothing beyond the deepest tap is ever used
        self.features = nn.Sequential(*modules[: self._taps[-1] + 1])
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: Tensor) -> list[Tensor]:
        x = (x - self.mean) / self.std
        out = []
        for i, module in enumerate(self.features):
            x = module(x)
            if i in self._taps:
                out.append(x)
        return out

    def load_weights(self, path: str | Path) -> None:
        """Load ImageNet VGG19 weights from a LOCAL file (torchvision ``vgg19`` state dict,
        or just its ``features``; ``classifier.*`` keys are ignored).

        Raises:
            FileNotFoundError: no such file.
            ValueError: unreadable file or keys/shapes that are not VGG19's.
        """
        raw = load_local_state_dict(path, "VGG19")
        state = {}
        for key, value in raw.items():
            key = key.removeprefix("module.").removeprefix("vgg.")
            if key.startswith("classifier."):
                continue
            state[key if key.startswith("features.") else f"features.{key}"] = value
        own = self.state_dict()
        missing = [k for k in own if k not in state]
        if missing:
            raise ValueError(f"{path} is not a VGG19 state dict: missing {missing[:3]}")
        bad = [k for k in own if tuple(state[k].shape) != tuple(own[k].shape)]
        if bad:
            raise ValueError(f"{path}: shape mismatch for {bad[0]}: {tuple(state[bad[0]].shape)}")
        self.load_state_dict({k: state[k] for k in own})
        logger.info("loaded VGG19 weights from %s", path)


class PerceptualLoss(nn.Module):
    """Mean L1 distance between VGG19 features of prediction and target.

    Args:
        weights_path: local VGG19 ImageNet state-dict file. ``None`` switches the loss off:
            a warning is logged once and ``forward`` returns 0.
        layers: VGG19 activations compared (equal weights).

    Shape: (B, 3, H, W) x2 in [0, 1] -> scalar.
    """

    def __init__(
        self,
        weights_path: str | Path | None = None,
        layers: Sequence[str] = ("relu1_2", "relu2_2", "relu3_4", "relu4_4"),
    ) -> None:
        super().__init__()
        self.vgg: VGG19Features | None = None
        if weights_path is None:
            logger.warning(
                "no VGG19 weights file given: the perceptual loss is switched off (returns 0)"
            )
            return
        vgg = VGG19Features(layers)
        vgg.load_weights(weights_path)
        for p in vgg.parameters():
            p.requires_grad_(False)
        self.vgg = vgg.eval()

    @property
    def enabled(self) -> bool:
        return self.vgg is not None

    def train(self, mode: bool = True) -> PerceptualLoss:
        super().train(mode)
        if self.vgg is not None:
            self.vgg.eval()  # frozen feature extractor
        return self

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        _check_pair(pred, target)
        if self.vgg is None:
            return pred.new_zeros(())
        with torch.no_grad():
            target_feats = self.vgg(target)
        pred_feats = self.vgg(pred)
        losses = [(a - b).abs().mean() for a, b in zip(pred_feats, target_feats, strict=True)]
        return torch.stack(losses).mean()


# --------------------------------------------------------------------------------------
# totals
# --------------------------------------------------------------------------------------


class D2FLoss(nn.Module):
    """The paper's two training objectives.

    Args:
        vgg_weights: local VGG19 weights file, or ``None`` (perceptual term off, returns 0).
        w_vgg, w_ssim, w_grad, w_poisson: term weights (paper: 0.1, 1, 0.1, 10).
        theta: threshold of the binary in-focus mask ``M_b`` on the normalised defocus.
        perceptual: a ready :class:`PerceptualLoss` (overrides ``vgg_weights``).
    """

    def __init__(
        self,
        vgg_weights: str | Path | None = None,
        *,
        w_vgg: float = 0.1,
        w_ssim: float = 1.0,
        w_grad: float = 0.1,
        w_poisson: float = 10.0,
        theta: float = 0.25,
        perceptual: PerceptualLoss | None = None,
    ) -> None:
        super().__init__()
        self.perceptual = perceptual if perceptual is not None else PerceptualLoss(vgg_weights)
        self.w_vgg, self.w_ssim, self.w_grad, self.w_poisson = w_vgg, w_ssim, w_grad, w_poisson
        self.theta = theta

    def stage1(
        self, pred: Tensor, target: Tensor, disparity: Tensor, image: Tensor
    ) -> dict[str, Tensor]:
        """``L1 + w_vgg * L_vgg + w_ssim * L_ssim + w_grad * L_grad(D, I)``.

        Shape: pred/target/image (B, 3, H, W), disparity (B, 1, h, w) (resized to H, W
        if needed). Returns the terms and ``"total"`` (scalars).
        """
        if disparity.shape[-2:] != image.shape[-2:]:
            disparity = F.interpolate(
                disparity, size=image.shape[-2:], mode="bilinear", align_corners=False
            )
        terms = {
            "l1": l1_loss(pred, target),
            "vgg": self.perceptual(pred, target),
            "ssim": ssim_loss(pred, target),
            "grad": edge_aware_smoothness(disparity, image),
        }
        terms["total"] = (
            terms["l1"]
            + self.w_vgg * terms["vgg"]
            + self.w_ssim * terms["ssim"]
            + self.w_grad * terms["grad"]
        )
        return terms

    def stage2(
        self,
        fused: Tensor,
        target: Tensor,
        disparity: Tensor,
        image: Tensor,
        upsampled: Tensor,
        defocus: Tensor,
    ) -> dict[str, Tensor]:
        """Stage-1 terms on the fused image ``+ w_poisson * L_p``.

        Shape: fused/target/image/upsampled (B, 3, H, W); disparity and defocus (paper-
        normalised, in [0, 1]) (B, 1, H, W). ``M_b = defocus < theta``.
        """
        terms = self.stage1(fused, target, disparity, image)
        mask = binary_focus_mask(defocus, self.theta)
        terms["poisson"] = poisson_loss(fused, image, upsampled, mask)
        terms["total"] = terms["total"] + self.w_poisson * terms["poisson"]
        return terms
