"""FastDepth indoor depth as a torch module that reproduces the full-integer TFLite teacher.

FastDepth (Wofk, Ma, Yang, Karaman and Sze, "FastDepth: Fast Monocular Depth Estimation on
Embedded Systems", ICRA 2019) is a MobileNet encoder (a stem and 13 depthwise-separable
blocks, widths pruned with NetAdapt) and an NNConv5 decoder: five stages of a 5x5 depthwise
and a 1x1 pointwise convolution, each followed by a 2x nearest-neighbour upsampling, with the
outputs of encoder blocks 1, 3 and 5 (counting from 1) added to the second, third and fourth
stage; a last 1x1 convolution gives the depth. Trained on NYU Depth v2 (indoor rooms).

The original file, ``fast_depth_224_int8.tflite``, is a full-integer graph: uint8 RGB
``1x224x224x3`` in (scale 1/255), uint8 depth ``1x224x224x1`` out, metres = 0.0717 x value.
``d2f_core.train.teachers.Teachers`` ran it on the photo stretched to 224x224 with PIL's
bilinear filter; :func:`depth_uint8` returns what it returned for ``depth``.

Every tensor of that graph is int8 with a scale and a zero point (``real = scale x (q -
zero_point)``), convolution weights are int8 with one scale per output channel and biases
int32. This module computes in the same integer domain, on float tensors: an activation is
held as its levels above the zero point (``q - zero_point``, whole numbers), a convolution
sums whole-number products, which float32 does exactly (the converter checks every channel's
bound), and :func:`requantize` writes the next int8 tensor as the runtime's kernels (XNNPACK,
which ``ai-edge-litert`` applies by default) do: the sum times ``in_scale x weight_scale /
out_scale`` in float32, rounded half to even, clamped to the int8 range as cut by the fused
ReLU / ReLU6 (:func:`level_range`). Its output equals the original's value for value
(measured on 174 photos of ``../shared``). The state dict holds the file's own integers
(``weight`` int8, ``bias`` int32), the config the scales, zero points and activations.

The network's input levels are the uint8 pixel values and its output levels the uint8 depth
values (input and output zero points are -128 in int8, 0 in uint8).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from .weights import load_teacher

__all__ = [
    "ACTIVATIONS",
    "INPUT_SIDE",
    "NAME",
    "FastDepth",
    "QuantAdd",
    "QuantConv",
    "Separable",
    "depth_metres",
    "depth_uint8",
    "fastdepth_input",
    "level_range",
    "load_fastdepth",
    "requantize",
]

#: the teacher's name in its weight file (``assets/weights/teacher_fastdepth.pt``)
NAME = "fastdepth"
#: the square side the network takes and returns
INPUT_SIDE = 224
_INT8_MIN, _INT8_MAX = -128, 127


#: the fused activations of the original graph
ACTIVATIONS = ("none", "relu", "relu6")


def requantize(scaled: torch.Tensor, low: int, high: int) -> torch.Tensor:
    """The int8 tensor a TFLite kernel writes for ``scaled`` (a sum already multiplied by its
    requantisation scale, in output steps): rounded half to even and clamped to the levels
    ``[low, high]`` (:func:`level_range`), returned as levels above the zero point.

    Works in place on ``scaled`` (a fresh tensor at every call site: a new one would cost
    more than the rounding itself)."""
    return scaled.round_().clamp_(low, high)


def level_range(activation: str, scale: float, zero_point: int) -> tuple[int, int]:
    """The levels (above ``zero_point``) an int8 tensor of ``scale`` can hold after a fused
    ``activation``: the int8 range, cut at real 0 by ReLU and also at real 6 by ReLU6."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation {activation!r}; expected one of {ACTIVATIONS}")
    low, high = _INT8_MIN - zero_point, _INT8_MAX - zero_point
    if activation != "none":
        low = max(low, 0)
    if activation == "relu6":
        high = min(high, math.floor(6.0 / scale + 0.5))
    return low, high


class QuantConv(nn.Module):
    """One int8 convolution (square kernel, zero padding of ``kernel // 2``, fused bias) and
    the requantisation of its output.

    Args:
        in_channels, out_channels, kernel, stride: the convolution; ``depthwise`` makes it one
            filter per channel (``out_channels == in_channels``).
        in_scale: the scale of the input tensor.
        weight_scales: one scale per output channel of the int8 weights (zero point 0).
        out_scale, zero_point: the output tensor's quantisation.
        activation: the fused activation, one of :data:`ACTIVATIONS`.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int,
        stride: int,
        depthwise: bool,
        in_scale: float,
        weight_scales: Sequence[float],
        out_scale: float,
        zero_point: int,
        activation: str,
    ) -> None:
        super().__init__()
        if depthwise and out_channels != in_channels:
            raise ValueError("a depthwise convolution keeps its channels")
        if len(weight_scales) != out_channels:
            raise ValueError(f"{out_channels} output channels but {len(weight_scales)} scales")
        self.groups = in_channels if depthwise else 1
        self.stride, self.padding = stride, kernel // 2
        self.out_scale = float(out_scale)
        self.levels = level_range(activation, out_scale, zero_point)
        shape = (out_channels, in_channels // self.groups, kernel, kernel)
        self.register_buffer("weight", torch.zeros(shape, dtype=torch.int8))
        self.register_buffer("bias", torch.zeros(out_channels, dtype=torch.int32))
        # the kernels' own float32 product: in_scale * weight_scale / out_scale
        f32 = functools.partial(torch.tensor, dtype=torch.float32)
        multiplier = f32(in_scale) * f32(list(weight_scales)) / f32(out_scale)
        self.register_buffer("multiplier", multiplier.view(1, -1, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        acc = F.conv2d(
            x, self.weight.float(), self.bias.float(), self.stride, self.padding, 1, self.groups
        )
        return requantize(acc.mul_(self.multiplier), *self.levels)


class QuantAdd(nn.Module):
    """The int8 sum of two tensors of other scales, requantised to its own: ``forward(a, b)``
    scales ``b`` in place."""

    def __init__(self, scales: tuple[float, float], out_scale: float, zero_point: int) -> None:
        super().__init__()
        f32 = np.float32
        self.multipliers = tuple(float(f32(s) / f32(out_scale)) for s in scales)
        self.out_scale = float(out_scale)
        self.levels = level_range("none", out_scale, zero_point)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        ma, mb = self.multipliers
        scaled = a * ma  # a is kept for later; b, the fresh upsampled tensor, is scaled in place
        return requantize(scaled.add_(b.mul_(mb)), *self.levels)


class Separable(nn.Module):
    """A depthwise-separable convolution: ``kernel x kernel`` depthwise (with the stride),
    then 1x1 pointwise; the encoder's blocks (3x3) and the decoder's NNConv5 stages (5x5)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int,
        stride: int,
        in_scale: float,
        quant: Mapping[str, Mapping[str, Any]],
    ) -> None:
        super().__init__()
        dw, pw = quant["depthwise"], quant["pointwise"]
        self.depthwise = QuantConv(
            in_channels, in_channels, kernel, stride, True, in_scale, dw["weight_scales"],
            dw["scale"], dw["zero_point"], dw["activation"],
        )  # fmt: skip
        self.pointwise = QuantConv(
            in_channels, out_channels, 1, 1, False, dw["scale"], pw["weight_scales"],
            pw["scale"], pw["zero_point"], pw["activation"],
        )  # fmt: skip
        self.out_scale = self.pointwise.out_scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pointwise(self.depthwise(x))


class FastDepth(nn.Module):
    """FastDepth (MobileNet + NNConv5) in the integer domain of its int8 TFLite file.

    ``forward`` takes ``N x 3 x H x W`` uint8 pixel values as float (H and W multiples of 32;
    the teacher's contract is 224) and returns ``N x 1 x H x W`` uint8 depth values as float
    (metres = :attr:`metres_per_step` x value).

    Args:
        widths: output channels of the stem and of each encoder block.
        strides: the stride of the stem and of each block's depthwise convolution.
        decoder_widths: output channels of the five decoder stages.
        skips: for each decoder stage, the encoder block whose output is added after its
            upsampling, or -1 for none.
        input_scale: the scale of the input tensor (1/255).
        quant: per layer (``"stem"``, ``"encoder.<i>"``, ``"decoder.<i>"``, ``"skip.<i>"``,
            ``"head"``) its quantisation: ``scale`` and ``zero_point`` of its output and, for
            a convolution, ``weight_scales`` and its fused ``activation``; a separable block
            holds one such entry under ``"depthwise"`` and one under ``"pointwise"``.
    """

    def __init__(
        self,
        widths: Sequence[int],
        strides: Sequence[int],
        decoder_widths: Sequence[int],
        skips: Sequence[int],
        input_scale: float,
        quant: Mapping[str, Mapping[str, Any]],
    ) -> None:
        super().__init__()
        if len(widths) != len(strides) or len(decoder_widths) != len(skips):
            raise ValueError("one stride per encoder width and one skip per decoder stage")
        q = quant["stem"]
        self.stem = QuantConv(
            3, widths[0], 3, strides[0], False, input_scale, q["weight_scales"], q["scale"],
            q["zero_point"], q["activation"],
        )  # fmt: skip
        scales = [self.stem.out_scale]  # of each encoder output, for the skips
        self.encoder = nn.ModuleList()
        for i, (cin, cout, stride) in enumerate(zip(widths[:-1], widths[1:], strides[1:])):
            block = Separable(cin, cout, 3, stride, scales[-1], quant[f"encoder.{i}"])
            self.encoder.append(block)
            scales.append(block.out_scale)
        self.skips = [int(s) for s in skips]
        self.decoder = nn.ModuleList()
        self.merge = nn.ModuleDict()
        scale, cin = scales[-1], widths[-1]
        for i, cout in enumerate(decoder_widths):
            stage = Separable(cin, cout, 5, 1, scale, quant[f"decoder.{i}"])
            self.decoder.append(stage)
            scale, cin = stage.out_scale, cout
            if self.skips[i] >= 0:
                if widths[self.skips[i] + 1] != cout:
                    raise ValueError(f"decoder stage {i} cannot add encoder block {skips[i]}")
                q = quant[f"skip.{i}"]
                skip_scale = scales[self.skips[i] + 1]
                self.merge[str(i)] = QuantAdd((skip_scale, scale), q["scale"], q["zero_point"])
                scale = q["scale"]
        q = quant["head"]
        self.head = QuantConv(
            cin, 1, 1, 1, False, scale, q["weight_scales"], q["scale"], q["zero_point"],
            q["activation"],
        )  # fmt: skip
        #: metres per output step (the output's scale; its uint8 zero point is 0)
        self.metres_per_step = self.head.out_scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # channels last: PyTorch's CPU depthwise convolutions are several times faster so
        x = self.stem(x.contiguous(memory_format=torch.channels_last))
        kept = {}
        for i, block in enumerate(self.encoder):
            x = block(x)
            kept[i] = x
        last = len(self.decoder) - 1
        for i, stage in enumerate(self.decoder):
            x = stage(x)
            if self.skips[i] >= 0:
                x = self.merge[str(i)](kept[self.skips[i]], _upsample(x))
            elif i < last:
                x = _upsample(x)
            else:  # the 1x1 head commutes with the last upsampling: run it on 4x fewer pixels
                return _upsample(self.head(x)).contiguous()
        return self.head(x).contiguous()


def _upsample(x: torch.Tensor) -> torch.Tensor:
    """2x nearest-neighbour upsampling: output pixel ``i`` copies input pixel ``i // 2``, as
    TFLite's RESIZE_NEAREST_NEIGHBOR without align_corners or half_pixel_centers."""
    return F.interpolate(x, scale_factor=2, mode="nearest")


def load_fastdepth(path: str | Path | None = None) -> FastDepth:
    """The FastDepth module with the weights of ``path`` (default: the shipped
    ``assets/weights/teacher_fastdepth.pt``), in eval mode.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a FastDepth teacher file, or damaged.
    """
    return load_teacher(FastDepth, NAME, path)


@functools.lru_cache(maxsize=1)
def _shipped() -> FastDepth:
    return load_fastdepth()


def fastdepth_input(image: Image.Image | np.ndarray) -> np.ndarray:
    """The teacher's input for ``image``: the photo stretched to 224x224 with PIL's bilinear
    filter, uint8 ``224 x 224 x 3``, as ``Teachers`` made it.

    ``image`` is a PIL image (converted to RGB first, as the labelling did) or an RGB array
    ``H x W x 3``: uint8, or float in [0, 1] (rounded to 8 bits first; an image read from an
    8-bit file as value / 255 comes back to its own bytes, so the result is exact).

    Raises:
        ValueError: an array of another shape or dtype, or a float one outside [0, 1].
    """
    if isinstance(image, Image.Image):
        rgb = image if image.mode == "RGB" else image.convert("RGB")
    elif isinstance(image, np.ndarray):
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
        rgb = Image.fromarray(np.ascontiguousarray(pixels), "RGB")
    else:
        raise ValueError(f"the image must be a PIL image or a numpy array, got {type(image)}")
    return np.array(rgb.resize((INPUT_SIDE, INPUT_SIDE), Image.BILINEAR), dtype=np.uint8)


def _levels(image: Image.Image | np.ndarray, model: FastDepth | None) -> torch.Tensor:
    net = _shipped() if model is None else model
    x = torch.from_numpy(fastdepth_input(image)).permute(2, 0, 1)[None].float()
    with torch.inference_mode():
        return net(x)[0, 0]


def depth_uint8(image: Image.Image | np.ndarray, model: FastDepth | None = None) -> np.ndarray:
    """The teacher's raw depth, uint8 ``224 x 224`` (metres = 0.0717 x value): what
    ``Teachers.__call__`` returned for ``depth``. ``image`` as for :func:`fastdepth_input`;
    ``model`` defaults to the shipped weights. Runs on the caller's torch threads."""
    return _levels(image, model).numpy().astype(np.uint8)


def depth_metres(image: Image.Image | np.ndarray, model: FastDepth | None = None) -> np.ndarray:
    """The teacher's depth in metres, float32 ``224 x 224`` (:func:`depth_uint8` times the
    output's scale, 0.0717 m per step)."""
    net = _shipped() if model is None else model
    return (_levels(image, net) * net.metres_per_step).numpy().astype(np.float32)
