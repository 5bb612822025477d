"""U^2-Net-p salient-object silhouettes as a torch module that reproduces the TFLite teacher.

U^2-Net (Qin, Zhang, Huang, Dehghan, Zaiane and Jagersand, "U^2-Net: Going deeper with nested
U-structure for salient object detection", Pattern Recognition 106, 2020) is a U-Net of six
encoder and five decoder stages whose every stage is itself a small U-Net, a *residual U-block*
(RSU): an input convolution, an encoder of ``L`` convolutions with a 2x2 max-pool between
them, a dilated convolution at the bottom, a decoder that upsamples and concatenates the
encoder's skips, and the input convolution's output added back. The two deepest stages use
RSU-4F, whose levels keep the full resolution and grow the dilation (1, 2, 4, 8) instead of
pooling. Each decoder stage (and the deepest encoder stage) gives a side map (a 3x3
convolution to one channel, upsampled to the input size); a 1x1 convolution over the six side
maps gives the fused map, and its sigmoid is the silhouette. "p" is the small variant: every
stage has 16 channels inside and 64 out (1.1 M parameters).

The original file, ``u2netp_float16.tflite``, takes float32 ``1x320x320x3`` (RGB / 255, then
ImageNet mean and std) and returns seven float32 ``1x320x320x1`` sigmoid maps, the fused one
first (``Identity``). Its weights are float16 (DEQUANTIZE ops), its batch norms folded into
the convolutions' biases. In that graph:

- every convolution pads "same" (a 3x3 convolution of dilation ``d`` pads ``d`` each side);
- every bilinear resize has ``align_corners=True`` (``half_pixel_centers=False``): source
  pixel ``i * (n_in - 1) / (n_out - 1)``, which ``F.interpolate(align_corners=True)`` computes;
- every max-pool is 2x2, stride 2, "valid". At 320 every pooled side is even (320, 160, 80,
  40, 20 pooled down to 10), so the original PyTorch U^2-Net's ``ceil_mode=True``, kept here,
  gives the same sizes.

The fused map needs all six side convolutions; only the six side sigmoids (the graph's other
outputs) are left out, which changes nothing in the fused map.

``d2f_core.train.scene_teachers.SceneTeachers.silhouette`` ran the file on the photo stretched
to 320x320 with PIL's bilinear filter; :func:`silhouette` returns the raw fused map and
:func:`silhouette_label` what ``SceneTeachers.silhouette`` returned (min-max normalised, uint8,
resized to the label size with PIL's bilinear filter).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from .weights import load_teacher

__all__ = [
    "INPUT_SIDE",
    "NAME",
    "RSU",
    "RSU4F",
    "ConvReLU",
    "U2NetP",
    "load_u2netp",
    "silhouette",
    "silhouette_input",
    "silhouette_label",
]

NAME = "u2netp"
#: the square side the network takes and returns
INPUT_SIDE = 320
_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


class ConvReLU(nn.Conv2d):
    """A 3x3 convolution padded to keep the size (``dilation`` each side), then ReLU: the
    original's conv + batch norm + ReLU (``REBNCONV``), the batch norm folded into the bias."""

    def __init__(self, in_channels: int, out_channels: int, dilation: int = 1) -> None:
        super().__init__(in_channels, out_channels, 3, padding=dilation, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu_(super().forward(x))  # in place: one tensor less at a time


def _pool(x: torch.Tensor) -> torch.Tensor:
    return F.max_pool2d(x, 2, 2, ceil_mode=True)


def _upsample(x: torch.Tensor, size: torch.Size | tuple[int, int]) -> torch.Tensor:
    """Bilinear resize to ``size`` with the corners aligned, as the TFLite graph does."""
    return F.interpolate(x, size=size, mode="bilinear", align_corners=True)


class RSU(nn.Module):
    """Residual U-block of ``levels`` levels (RSU-7 ... RSU-4).

    ``conv_in`` maps the input to ``out_channels``; the encoder's first ``levels - 1``
    convolutions run at 1, 1/2, 1/4 ... of the size (a max-pool before each but the first),
    its last one is dilated 2 at the smallest size; the decoder's ``levels - 1``
    convolutions, deepest first, each read the level below (upsampled to the skip's size,
    except at the bottom) concatenated with the encoder's output at their level. The block
    returns the decoder's last output plus ``conv_in``'s.
    """

    def __init__(self, levels: int, in_channels: int, mid_channels: int, out_channels: int):
        super().__init__()
        if levels < 3:
            raise ValueError(f"an RSU block needs at least 3 levels, got {levels}")
        self.levels = levels
        self.conv_in = ConvReLU(in_channels, out_channels)
        self.encoder = nn.ModuleList(
            [ConvReLU(out_channels, mid_channels)]
            + [ConvReLU(mid_channels, mid_channels) for _ in range(levels - 2)]
            + [ConvReLU(mid_channels, mid_channels, dilation=2)]
        )
        self.decoder = nn.ModuleList(
            [ConvReLU(2 * mid_channels, mid_channels) for _ in range(levels - 2)]
            + [ConvReLU(2 * mid_channels, out_channels)]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        top = self.conv_in(x)
        h = self.encoder[0](top)
        skips = [h]
        for conv in self.encoder[1:-1]:
            h = conv(_pool(h))
            skips.append(h)
        h = self.encoder[-1](h)
        for i, (conv, skip) in enumerate(zip(self.decoder, reversed(skips), strict=True)):
            if i > 0:
                h = _upsample(h, skip.shape[-2:])
            h = conv(torch.cat((h, skip), dim=1))
        return h.add_(top)


class RSU4F(nn.Module):
    """RSU-4F: four levels at the full size, dilated 1, 2, 4 and 8 down the encoder and 4, 2
    and 1 up the decoder, with no pooling or upsampling; ``conv_in``'s output added back."""

    def __init__(self, in_channels: int, mid_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv_in = ConvReLU(in_channels, out_channels)
        self.encoder = nn.ModuleList(
            [ConvReLU(out_channels, mid_channels)]
            + [ConvReLU(mid_channels, mid_channels, dilation=d) for d in (2, 4, 8)]
        )
        self.decoder = nn.ModuleList(
            [ConvReLU(2 * mid_channels, mid_channels, dilation=d) for d in (4, 2)]
            + [ConvReLU(2 * mid_channels, out_channels)]
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        top = self.conv_in(x)
        h = top
        skips = []
        for conv in self.encoder:
            h = conv(h)
            skips.append(h)
        h = skips.pop()
        for conv, skip in zip(self.decoder, reversed(skips), strict=True):
            h = conv(torch.cat((h, skip), dim=1))
        return h.add_(top)


#: levels of the encoder's six stages (0 = RSU-4F); the decoder's five mirror the first five
_STAGE_LEVELS = (7, 6, 5, 4, 0, 0)


def _block(levels: int, in_channels: int, mid_channels: int, out_channels: int) -> nn.Module:
    if levels == 0:
        return RSU4F(in_channels, mid_channels, out_channels)
    return RSU(levels, in_channels, mid_channels, out_channels)


class U2NetP(nn.Module):
    """U^2-Net with ``mid_channels`` inside and ``channels`` out of every stage (U^2-Net-p:
    16 and 64).

    ``forward`` takes ``N x 3 x H x W`` normalised RGB (:func:`silhouette_input`) and returns
    the fused silhouette, ``N x 1 x H x W`` probabilities in (0, 1), computed channels-last
    (:func:`load_u2netp` stores the weights so too). For inference: its ReLUs and residual
    adds work in place, which autograd cannot differentiate. ``encoder`` holds the
    six encoder stages (RSU-7, 6, 5, 4, 4F, 4F), ``decoder`` the five decoder stages deepest
    first (RSU-4F, 4, 5, 6, 7), ``side`` the six side convolutions from the finest stage
    (the last decoder stage) to the coarsest (the last encoder stage), ``fuse`` the 1x1
    convolution over their upsampled maps.
    """

    def __init__(self, in_channels: int = 3, mid_channels: int = 16, channels: int = 64) -> None:
        super().__init__()
        ins = [in_channels] + [channels] * (len(_STAGE_LEVELS) - 1)
        self.encoder = nn.ModuleList(
            _block(levels, c, mid_channels, channels)
            for levels, c in zip(_STAGE_LEVELS, ins, strict=True)
        )
        self.decoder = nn.ModuleList(
            _block(levels, 2 * channels, mid_channels, channels)
            for levels in reversed(_STAGE_LEVELS[:-1])
        )
        self.side = nn.ModuleList(
            nn.Conv2d(channels, 1, 3, padding=1) for _ in range(len(_STAGE_LEVELS))
        )
        self.fuse = nn.Conv2d(len(_STAGE_LEVELS), 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        # channels-last runs the CPU convolutions about a fifth faster (same sums, reordered)
        h = x.contiguous(memory_format=torch.channels_last)
        for i, stage in enumerate(self.encoder):
            if i > 0:
                h = _pool(h)
            h = stage(h)
            skips.append(h)
        outs = [skips.pop()]  # the coarsest stage's output is a side output too
        h = outs[0]
        for stage, skip in zip(self.decoder, reversed(skips), strict=True):
            h = stage(torch.cat((_upsample(h, skip.shape[-2:]), skip), dim=1))
            outs.append(h)
        size = x.shape[-2:]
        maps = []
        for conv, out in zip(self.side, reversed(outs), strict=True):
            m = conv(out)
            maps.append(m if m.shape[-2:] == size else _upsample(m, size))
        return torch.sigmoid(self.fuse(torch.cat(maps, dim=1)))


def load_u2netp(path: str | Path | None = None) -> U2NetP:
    """The U^2-Net-p module with the weights of ``path`` (default: the shipped
    ``assets/weights/teacher_u2netp.pt``), in eval mode.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a U^2-Net-p teacher file, or damaged.
    """
    return load_teacher(U2NetP, NAME, path).to(memory_format=torch.channels_last)


@functools.lru_cache(maxsize=1)
def _shipped() -> U2NetP:
    return load_u2netp()


def _rgb(image: Image.Image | np.ndarray) -> Image.Image:
    """``image`` as an 8-bit RGB PIL image (see :func:`silhouette_input`)."""
    if isinstance(image, Image.Image):
        return image if image.mode == "RGB" else image.convert("RGB")
    if not isinstance(image, np.ndarray):
        raise ValueError(f"the image must be a PIL image or a numpy array, got {type(image)}")
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"the image must be H x W x 3 RGB, got shape {image.shape}")
    if image.dtype == np.uint8:
        pixels = image
    elif np.issubdtype(image.dtype, np.floating):
        if not np.isfinite(image).all() or image.min() < 0.0 or image.max() > 1.0:
            raise ValueError("a float image must hold finite values in [0, 1]")
        pixels = np.round(image.astype(np.float32) * 255.0).astype(np.uint8)
    else:
        raise ValueError(f"the image must be uint8 or float in [0, 1], got {image.dtype}")
    return Image.fromarray(np.ascontiguousarray(pixels), "RGB")


def silhouette_input(image: Image.Image | np.ndarray) -> np.ndarray:
    """The teacher's input for ``image``, float32 ``320 x 320 x 3``: the photo stretched to
    320x320 with PIL's bilinear filter, divided by 255, minus the ImageNet mean, over its
    standard deviation, as ``SceneTeachers.silhouette`` made it.

    ``image`` is a PIL image (converted to RGB first) or an RGB array ``H x W x 3``: uint8,
    or float in [0, 1], rounded to 8 bits first (PIL resizes 8-bit images; an image read from
    an 8-bit file as value / 255 comes back to its own bytes, so the result is exact).

    Raises:
        ValueError: an array of another shape or dtype, or a float one outside [0, 1].
    """
    small = _rgb(image).resize((INPUT_SIDE, INPUT_SIDE), Image.BILINEAR)
    x = np.asarray(small, np.float32) / 255
    return ((x - _IMAGENET_MEAN) / _IMAGENET_STD).astype(np.float32)


def silhouette(image: Image.Image | np.ndarray, model: U2NetP | None = None) -> np.ndarray:
    """The fused salient-object probability, float32 ``320 x 320`` in (0, 1): the original's
    ``Identity`` output. ``image`` as for :func:`silhouette_input`; ``model`` defaults to the
    shipped weights. Runs on the caller's torch threads."""
    net = _shipped() if model is None else model
    x = torch.from_numpy(silhouette_input(image)).permute(2, 0, 1)[None]
    with torch.inference_mode():
        return net(x)[0, 0].contiguous().numpy()


def silhouette_label(
    image: Image.Image | np.ndarray, size: tuple[int, int], model: U2NetP | None = None
) -> np.ndarray:
    """What ``SceneTeachers.silhouette`` returned: :func:`silhouette` min-max normalised,
    as uint8 (0-255), resized to ``size`` = ``(width, height)`` with PIL's bilinear filter;
    ``height x width``. The labels used ``scene_teachers.label_size`` of the photo (its
    aspect, long side 256).

    Raises:
        ValueError: a bad ``image`` (see :func:`silhouette_input`) or ``size``.
    """
    if (
        len(size) != 2
        or not all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) for s in size)
        or min(size) < 1
    ):
        raise ValueError(f"size must be (width, height) in whole pixels >= 1, got {size!r}")
    m = silhouette(image, model)
    lo, hi = float(m.min()), float(m.max())
    m = (m - lo) / max(hi - lo, 1e-6)
    img = Image.fromarray(np.round(m * 255).astype(np.uint8))
    return np.asarray(img.resize((int(size[0]), int(size[1])), Image.BILINEAR))
