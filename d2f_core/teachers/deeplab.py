"""DeepLabV3 with a MobileNetV2 backbone: ADE20K scene parsing and PASCAL VOC objects.

One torch module, :class:`DeepLab`, built from a config stored in each weight file, for
the two pretrained graphs the project's labels were made with (converted by
``d2f_core.train.port_deeplab``):

- ``deeplab_ade20k``: 151 ADE20K classes (150 and "other"), from
  ``deeplabv3_mobilenetv2_ade20k.tflite``: input 1x513x513x3 RGB as ``x / 127.5 - 1``, output
  1x513x513x151 logits. MobileNetV2 at width 1, output stride 8, an ASPP of image pooling and
  one 1x1 branch (no atrous branches), the DeepLabV3+ decoder on the stride-4 features,
  resizes with ``align_corners=True``. The graph is dynamic-range quantized: its 1x1
  convolutions (all but the first block's projection) have int8 weights, and the runtime
  rounds their input to int8 per pixel before each (:func:`dynamic_int8`, the config's
  ``quantized``), which this port does too.
- ``deeplab_voc``: 21 PASCAL VOC classes, from ``deeplabv3_mobilenetv2_voc.onnx``: input
  1x257x257x3 RGB in [-1, 1], output 1x257x257x21 logits, float32. MobileNetV2 at width 0.5,
  output stride 8, the same ASPP, no decoder, the logits resized as TensorFlow's legacy
  ``ResizeBilinear`` (source pixel = output pixel x in / out, no half-pixel offset).

Papers: Chen et al., "Rethinking Atrous Convolution for Semantic Image Segmentation"
(DeepLabV3, 2017) and "Encoder-Decoder with Atrous Separable Convolution for Semantic Image
Segmentation" (DeepLabV3+, ECCV 2018); Sandler et al., "MobileNetV2: Inverted Residuals and
Linear Bottlenecks" (CVPR 2018).

The batch norms are folded into the convolutions' biases, as in the original graphs; the
original's dilated depthwise convolutions (space-to-batch, convolution, batch-to-space, then
the batch norm) are real dilated convolutions here, the batch norm folded in. Convolutions of
stride 2 pad as TensorFlow's ``SAME``. The network runs channels-last, its 1x1 convolutions
as matrix products.

How close a port can come: the VOC logits match the original's to float rounding. The
ADE20K graph's int8 rounding of activations makes it chaotic in the last bits: nudging its
input by one float32 ulp moves its own probabilities by up to 0.05-0.07 and changes the
argmax of 0.2-1.2 % of the pixels, so no port matches it closer than that; this one differs
from it by as much as it differs from itself under that nudge (``tests/test_port_deeplab``).

The functions the depth source calls take a PIL image, or an ``H x W x 3`` array (uint8, or
float in [0, 1], read as ``round(255 x)``: exact for a photo loaded as uint8 / 255), and run
the originals' preprocessing (PIL bilinear resizes of the uint8 photo):

- :func:`ade20k_probabilities`: the softmax with the photo's long side at 513 (the
  unpadded part of the original's padded input), and :func:`ade20k_labels`, the class map
  at a label size, as ``SceneTeachers.parse`` of ``d2f_core.train.scene_teachers`` made it;
- :func:`voc_foreground`: ``1 - P(background)`` at 257x257, uint8 as the ``fg`` of
  ``Teachers.__call__`` in ``d2f_core.train.teachers``; :func:`voc_probabilities`, the
  classes' softmax.

They run under ``torch.inference_mode()`` with the caller's torch thread count.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from .weights import load_teacher

__all__ = [
    "ADE20K",
    "ADE_SIDE",
    "ASPP",
    "VOC",
    "VOC_SIDE",
    "ConvAct",
    "DeepLab",
    "Decoder",
    "InvertedResidual",
    "MobileNetV2",
    "ade20k_input",
    "ade20k_labels",
    "ade20k_logits",
    "ade20k_probabilities",
    "dynamic_int8",
    "load_ade20k",
    "load_deeplab",
    "load_voc",
    "voc_foreground",
    "voc_input",
    "voc_probabilities",
]

#: the weight sets' names (``assets/weights/teacher_<name>.pt``)
ADE20K = "deeplab_ade20k"
VOC = "deeplab_voc"
#: the square input side of each graph
ADE_SIDE = 513
VOC_SIDE = 257

#: MobileNetV2's inverted-residual stages: (expansion, repeats, first stride)
STAGES = ((1, 1, 1), (6, 2, 2), (6, 3, 2), (6, 4, 2), (6, 3, 1), (6, 3, 2), (6, 1, 1))
#: the channels at width 1: the stem, then each stage's output
WIDTH_1 = (32, 16, 24, 32, 64, 96, 160, 320)
#: the block whose depthwise output feeds the decoder (stride 4: "layer_4/depthwise_output")
LOW_LEVEL_BLOCK = 2
_ACTS = ("relu6", "relu", "none")
_RESIZES = ("align_corners", "asymmetric")


def _same_pad(x: torch.Tensor, kernel: int, stride: int) -> torch.Tensor:
    """Pad as TensorFlow's ``SAME`` for a strided convolution (more at the bottom/right)."""
    pads = []
    for n in (x.shape[-1], x.shape[-2]):  # F.pad takes the last dimension first
        total = max((-(-n // stride) - 1) * stride + kernel - n, 0)
        pads += [total // 2, total - total // 2]
    return F.pad(x, pads) if any(pads) else x


def dynamic_int8(x: torch.Tensor) -> torch.Tensor:
    """``x`` (``B x C x H x W``) rounded as a dynamic-range quantized convolution reads it:
    each pixel's ``C`` values to int8 with their own asymmetric scale and zero point, and
    back to float.

    This is what the original runtime (TFLite's XNNPACK delegate) does to the input of a
    convolution whose weights are int8: the range is the pixel's ``[min(0, lo), max(0,
    hi)]`` over 255 steps, the zero point is taken from the end with the smaller error and
    rounded half to even, and the values are rounded half to even and saturated.
    """
    lo = x.amin(dim=1, keepdim=True).clamp_(max=0.0)  # (fast on channels-last tensors)
    hi = x.amax(dim=1, keepdim=True).clamp_(min=0.0)
    span = hi - lo
    scale = torch.where(span > 0, 255.0 / span, 1.0)
    lo, hi = lo * scale, hi * scale
    zero = torch.where((lo - 128.0) + (hi + 127.0) > 0, -128.0 - lo, 127.0 - hi)
    zero = zero.clamp_(-128.0, 127.0).round_()
    q = (x * scale).round_().add_(zero).clamp_(-128.0, 127.0)
    return q.sub_(zero).div_(scale)


class ConvAct(nn.Module):
    """A convolution with its batch norm folded into the bias, then ReLU6, ReLU or nothing.

    Stride 1 pads ``dilation x (kernel // 2)`` on every side (TensorFlow's ``SAME`` for an
    odd kernel); a stride of 2 pads as ``SAME`` does for the input's size. With
    ``quantize``, the input is first rounded by :func:`dynamic_int8`, as the original
    runtime does for a convolution with int8 weights.
    """

    def __init__(
        self,
        cin: int,
        cout: int,
        kernel: int = 1,
        stride: int = 1,
        dilation: int = 1,
        groups: int = 1,
        act: str = "relu6",
        quantize: bool = False,
    ) -> None:
        super().__init__()
        if act not in _ACTS:
            raise ValueError(f"act must be one of {_ACTS}, got {act!r}")
        pad = dilation * (kernel // 2) if stride == 1 else 0
        self.conv = nn.Conv2d(cin, cout, kernel, stride, pad, dilation, groups, bias=True)
        self.act = act
        self.quantize = quantize

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.quantize:
            x = dynamic_int8(x)
        conv = self.conv
        if conv.kernel_size == (1, 1) and conv.stride == (1, 1):
            # a matrix product over the channels of the channels-last pixels
            x = x.permute(0, 2, 3, 1)
            x = F.linear(x, conv.weight.flatten(1), conv.bias).permute(0, 3, 1, 2)
        else:
            if conv.stride[0] != 1:
                x = _same_pad(x, conv.kernel_size[0], conv.stride[0])
            x = conv(x)
        if self.act == "relu6":
            return F.hardtanh_(x, 0.0, 6.0)
        if self.act == "relu":
            return F.relu_(x)
        return x


class InvertedResidual(nn.Module):
    """MobileNetV2's block: 1x1 expansion (none when ``expansion`` is 1), 3x3 depthwise
    (strided or dilated), linear 1x1 projection, and the identity added when the shapes
    allow."""

    def __init__(self, cin: int, cout: int, expansion: int, stride: int, dilation: int) -> None:
        super().__init__()
        mid = cin * expansion
        self.expand = ConvAct(cin, mid) if expansion != 1 else None
        self.depthwise = ConvAct(mid, mid, 3, stride, dilation, groups=mid)
        self.project = ConvAct(mid, cout, act="none")
        self.residual = stride == 1 and cin == cout

    def forward_with_depthwise(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The block's output and its depthwise output (the decoder's low-level features)."""
        h = self.expand(x) if self.expand is not None else x
        d = self.depthwise(h)
        out = self.project(d)
        return (out + x if self.residual else out), d

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward_with_depthwise(x)[0]


class MobileNetV2(nn.Module):
    """MobileNetV2's features without its last 1x1 convolution, at ``output_stride``: the
    strides past it become dilations, as in DeepLab (the first block past it keeps its
    dilation, the ones after multiply it by the stride it dropped).

    ``forward`` returns ``(low, x)``: the depthwise output of block :data:`LOW_LEVEL_BLOCK`
    (stride 4) and the last block's output.
    """

    def __init__(self, channels: Sequence[int], output_stride: int = 8) -> None:
        super().__init__()
        if len(channels) != len(STAGES) + 1:
            raise ValueError(f"channels must have {len(STAGES) + 1} values, got {len(channels)}")
        self.stem = ConvAct(3, channels[0], 3, stride=2)
        blocks = []
        stride, rate, cin = 2, 1, channels[0]
        for (expansion, repeats, first), cout in zip(STAGES, channels[1:], strict=True):
            for i in range(repeats):
                s = first if i == 0 else 1
                if s > 1 and stride >= output_stride:
                    block_rate, rate, s = rate, rate * s, 1
                else:
                    block_rate = rate
                    stride *= s
                blocks.append(InvertedResidual(cin, cout, expansion, s, block_rate))
                cin = cout
        self.blocks = nn.ModuleList(blocks)
        self.out_channels = cin
        self.low_channels = blocks[LOW_LEVEL_BLOCK].depthwise.conv.out_channels

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.stem(x)
        low = x
        for i, block in enumerate(self.blocks):
            if i == LOW_LEVEL_BLOCK:
                x, low = block.forward_with_depthwise(x)
            else:
                x = block(x)
        return low, x


class ASPP(nn.Module):
    """DeepLabV3's head as these graphs have it: image pooling and one 1x1 branch (no atrous
    branches), concatenated in that order and projected, each a 1x1 convolution and ReLU."""

    def __init__(self, cin: int, channels: int = 256) -> None:
        super().__init__()
        self.pool = ConvAct(cin, channels, act="relu")
        self.branch = ConvAct(cin, channels, act="relu")
        self.project = ConvAct(2 * channels, channels, act="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = self.pool(x.mean(dim=(2, 3), keepdim=True)).expand(-1, -1, *x.shape[-2:])
        both = torch.cat([pooled, self.branch(x)], dim=1)
        return self.project(both.contiguous(memory_format=torch.channels_last))


class Decoder(nn.Module):
    """DeepLabV3+'s decoder: the head's output resized to the low-level features' size
    (``align_corners=True``), concatenated with their 1x1 projection, then two separable
    convolutions (3x3 depthwise and 1x1, each with ReLU)."""

    def __init__(self, cin: int, low_channels: int, low_out: int = 48, channels: int = 256):
        super().__init__()
        mid = cin + low_out
        self.low = ConvAct(low_channels, low_out, act="relu")
        self.depthwise0 = ConvAct(mid, mid, 3, groups=mid, act="relu")
        self.pointwise0 = ConvAct(mid, channels, act="relu")
        self.depthwise1 = ConvAct(channels, channels, 3, groups=channels, act="relu")
        self.pointwise1 = ConvAct(channels, channels, act="relu")

    def forward(self, x: torch.Tensor, low: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, size=low.shape[-2:], mode="bilinear", align_corners=True)
        x = torch.cat([x, self.low(low)], dim=1)
        x = self.pointwise0(self.depthwise0(x))
        return self.pointwise1(self.depthwise1(x))


def _resize_asymmetric(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize sampling output pixel ``i`` at input ``i x in / out`` (TensorFlow's
    legacy ``ResizeBilinear``, ONNX ``Upsample`` before opset 11), edges clamped.

    The same as an ``align_corners`` resize of the input with its last row and column
    repeated once, from ``in + 1`` to ``out + 1`` pixels (input ``i x in / out`` again),
    less the last output row and column.
    """
    h, w = size
    x = F.pad(x, (0, 1, 0, 1), mode="replicate")
    y = F.interpolate(x, size=(h + 1, w + 1), mode="bilinear", align_corners=True)
    return y[..., :h, :w]


class DeepLab(nn.Module):
    """DeepLabV3 (with the V3+ decoder when ``decoder``) on MobileNetV2.

    Args:
        num_classes: output channels (151 for ADE20K, 21 for VOC).
        channels: MobileNetV2's stem and stage output channels (:data:`WIDTH_1` scaled by
            the width multiplier, as the graph has them).
        output_stride: the backbone's stride; past it, dilations.
        decoder: add DeepLabV3+'s decoder on the stride-4 features.
        resize: how the logits reach the input size: ``"align_corners"`` (ADE20K) or
            ``"asymmetric"`` (VOC).
        quantized: the names of the :class:`ConvAct` modules whose input is rounded by
            :func:`dynamic_int8` (those with int8 weights in the original: ADE20K's 1x1
            convolutions but the first block's projection).

    ``forward`` takes ``B x 3 x H x W`` RGB in [-1, 1] and returns logits ``B x C x H x W``.
    """

    def __init__(
        self,
        num_classes: int,
        channels: Sequence[int] = WIDTH_1,
        output_stride: int = 8,
        decoder: bool = True,
        resize: str = "align_corners",
        quantized: Sequence[str] = (),
    ) -> None:
        super().__init__()
        if resize not in _RESIZES:
            raise ValueError(f"resize must be one of {_RESIZES}, got {resize!r}")
        self.backbone = MobileNetV2(channels, output_stride)
        self.aspp = ASPP(self.backbone.out_channels)
        self.decoder = Decoder(256, self.backbone.low_channels) if decoder else None
        self.logits = ConvAct(256, num_classes, act="none")
        self.resize = resize
        layers = dict(self.named_modules())
        for name in quantized:
            if not isinstance(layers.get(name), ConvAct):
                raise ValueError(f"quantized names no convolution of this DeepLab: {name!r}")
            layers[name].quantize = True

    def coarse_logits(self, x: torch.Tensor) -> torch.Tensor:
        """The logits at the network's own stride (``B x C x h x w``), before the resize to
        the input's size that :meth:`forward` adds."""
        low, feats = self.backbone(x.contiguous(memory_format=torch.channels_last))
        y = self.aspp(feats)
        if self.decoder is not None:
            y = self.decoder(y, low)
        return self.logits(y)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        y = self.coarse_logits(x)
        if self.resize == "align_corners":
            return F.interpolate(y, size=size, mode="bilinear", align_corners=True)
        return _resize_asymmetric(y, size)


def load_deeplab(name: str, path: str | Path | None = None) -> DeepLab:
    """The DeepLab of weight set ``name`` (:data:`ADE20K` or :data:`VOC`), from ``path``
    (default: the shipped file), in eval mode.

    Raises:
        FileNotFoundError: no such file.
        ValueError: an unknown ``name``, or a file that is not this weight set's.
    """
    if name not in (ADE20K, VOC):
        raise ValueError(f"unknown DeepLab weight set {name!r}: use {ADE20K!r} or {VOC!r}")
    return load_teacher(DeepLab, name, path)


def load_ade20k(path: str | Path | None = None) -> DeepLab:
    """The ADE20K scene parser (:func:`load_deeplab` of :data:`ADE20K`)."""
    return load_deeplab(ADE20K, path)


def load_voc(path: str | Path | None = None) -> DeepLab:
    """The PASCAL VOC segmenter (:func:`load_deeplab` of :data:`VOC`)."""
    return load_deeplab(VOC, path)


@lru_cache(maxsize=2)
def _shipped(name: str) -> DeepLab:
    return load_deeplab(name)


def _rgb(image: Image.Image | np.ndarray) -> Image.Image:
    """The photo as a PIL RGB image; arrays are ``H x W x 3``, uint8 or float in [0, 1]
    (read as ``round(255 x)``)."""
    if isinstance(image, Image.Image):
        return image if image.mode == "RGB" else image.convert("RGB")
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"image must be H x W x 3, got shape {arr.shape}")
    if arr.dtype != np.uint8:
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"image must be uint8 or float in [0, 1], got {arr.dtype}")
        if not np.isfinite(arr).all() or arr.min() < 0 or arr.max() > 1:
            raise ValueError("a float image must be finite and in [0, 1]")
        arr = np.round(arr * 255).astype(np.uint8)
    return Image.fromarray(np.ascontiguousarray(arr))


def _batch(x: np.ndarray) -> torch.Tensor:
    """One ``H x W x 3`` input as the graph's ``1 x 3 x H x W`` batch."""
    return torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None]


def _run(model: DeepLab, x: np.ndarray) -> torch.Tensor:
    """Logits ``H x W x C`` of one ``H x W x 3`` input in [-1, 1]."""
    with torch.inference_mode():
        return model(_batch(x))[0].permute(1, 2, 0)


def ade20k_input(
    image: Image.Image | np.ndarray, side: int = ADE_SIDE
) -> tuple[np.ndarray, tuple[int, int]]:
    """The ADE20K graph's input, float32 513x513x3 in [-1, 1]: the photo with its long side
    resized to 513 (PIL bilinear) at the top left, the rest 0 (mid grey); and ``(h, w)``,
    the photo's part. ``side`` in place of 513 gives the same at another size (the network
    is fully convolutional; the original graph reads 513)."""
    rgb = _rgb(image)
    w, h = rgb.size
    s = side / max(w, h)
    rw, rh = max(1, round(w * s)), max(1, round(h * s))
    x = np.zeros((side, side, 3), np.float32)
    x[:rh, :rw] = np.asarray(rgb.resize((rw, rh), Image.BILINEAR), np.float32) / 127.5 - 1
    return x, (rh, rw)


def ade20k_logits(
    image: Image.Image | np.ndarray, model: DeepLab | None = None, side: int = ADE_SIDE
) -> torch.Tensor:
    """ADE20K logits, float32 ``h x w x 151``, of :func:`ade20k_input`'s photo part (the
    padding's logits cut off), the input ``side`` px square."""
    x, (rh, rw) = ade20k_input(image, side)
    return _run(_shipped(ADE20K) if model is None else model, x)[:rh, :rw]


def ade20k_probabilities(
    image: Image.Image | np.ndarray, model: DeepLab | None = None
) -> np.ndarray:
    """ADE20K class probabilities (the softmax of :func:`ade20k_logits`), float32
    ``h x w x 151`` with the photo's long side at 513; the classes index
    ``ade20k_labels_151.txt`` (0 "other", 1 wall, 2 building, 3 sky, ...)."""
    return torch.softmax(ade20k_logits(image, model), dim=-1).numpy()


def ade20k_labels(
    image: Image.Image | np.ndarray,
    size: tuple[int, int],
    model: DeepLab | None = None,
    side: int = ADE_SIDE,
) -> np.ndarray:
    """What ``SceneTeachers.parse`` returned: the argmax class of :func:`ade20k_logits`,
    uint8, resized to ``size`` = ``(width, height)`` with PIL's nearest neighbour;
    ``height x width``. The labels used ``scene_teachers.label_size`` of the photo (its
    aspect, long side 256). ``side``: the input's size (513, the original's, by default).

    Raises:
        ValueError: a bad ``image`` or ``size``.
    """
    size = _size(size)
    net = _shipped(ADE20K) if model is None else model
    if net.resize != "align_corners":
        raise ValueError("ade20k_labels needs the ADE20K graph (its align-corners resize)")
    x, (rh, rw) = ade20k_input(image, side)
    with torch.inference_mode():
        coarse = net.coarse_logits(_batch(x))[0].float().permute(1, 2, 0)  # h x w x C
        # PIL's nearest neighbour reads one pixel of the resized logits per label; each
        # such pixel mixes four coarse ones
        r0, r1, rf = _align_corners_taps(coarse.shape[0], side, _nearest_index(rh, size[1]))
        c0, c1, cf = _align_corners_taps(coarse.shape[1], side, _nearest_index(rw, size[0]))
        return _mixed_argmax(coarse, (r0, r1, rf), (c0, c1, cf)).to(torch.uint8).numpy()


def _mixed_argmax(coarse: torch.Tensor, rows: tuple, cols: tuple) -> torch.Tensor:
    """The argmax class of each bilinear mix of ``coarse`` (``h x w x C``) at the taps
    ``rows`` and ``cols`` (:func:`_align_corners_taps`), ``len(rows) x len(cols)``.

    Where the four pixels mixed have the same argmax class, a weighted mean of them with
    weights >= 0 has it too, so only the mixes across a change of class are computed."""
    r0, r1, rf = rows
    c0, c1, cf = cols
    cls = coarse.argmax(dim=-1)
    a, b = cls[r0][:, c0], cls[r0][:, c1]
    c, d = cls[r1][:, c0], cls[r1][:, c1]
    out = a.clone()
    yi, xi = torch.nonzero((a != b) | (a != c) | (a != d), as_tuple=True)
    if len(yi):
        fy, fx = rf[yi, None], cf[xi, None]
        top = torch.lerp(coarse[r0[yi], c0[xi]], coarse[r0[yi], c1[xi]], fx)
        bottom = torch.lerp(coarse[r1[yi], c0[xi]], coarse[r1[yi], c1[xi]], fx)
        out[yi, xi] = torch.lerp(top, bottom, fy).argmax(dim=-1)
    return out


def _nearest_index(n_in: int, n_out: int) -> torch.Tensor:
    """The source index of each of ``n_out`` pixels of PIL's nearest-neighbour resize of a
    line of ``n_in`` pixels (PIL's own rule, read from a resized line of indices)."""
    line = Image.fromarray(np.arange(n_in, dtype=np.int32)[None, :])
    return torch.from_numpy(np.asarray(line.resize((n_out, 1), Image.NEAREST), np.int64)[0])


def _align_corners_taps(
    n_in: int, n_out: int, index: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(i0, i1, frac)``: the two input samples and the weight of the second that a
    bilinear align-corners resize from ``n_in`` to ``n_out`` samples reads for its output
    samples ``index`` (as ``F.interpolate`` computes them)."""
    scale = (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    pos = index.to(torch.float32) * scale
    i0 = pos.floor().to(torch.int64).clamp_(0, n_in - 1)
    i1 = (i0 + 1).clamp_(max=n_in - 1)
    return i0, i1, (pos - i0).clamp_(0.0, 1.0)


def _size(size: tuple[int, int]) -> tuple[int, int]:
    if (
        len(size) != 2
        or not all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) for s in size)
        or min(size) < 1
    ):
        raise ValueError(f"size must be (width, height) in whole pixels >= 1, got {size!r}")
    return int(size[0]), int(size[1])


def voc_input(image: Image.Image | np.ndarray) -> np.ndarray:
    """The VOC graph's input, float32 257x257x3 in [-1, 1]: the photo stretched to 257x257
    (PIL bilinear)."""
    rgb = _rgb(image).resize((VOC_SIDE, VOC_SIDE), Image.BILINEAR)
    return np.asarray(rgb, np.float32) / 127.5 - 1


def voc_probabilities(image: Image.Image | np.ndarray, model: DeepLab | None = None) -> np.ndarray:
    """PASCAL VOC class probabilities (softmax), float32 257x257x21 (0 is the background)."""
    logits = _run(_shipped(VOC) if model is None else model, voc_input(image))
    return torch.softmax(logits, dim=-1).numpy()


def voc_foreground(image: Image.Image | np.ndarray, model: DeepLab | None = None) -> np.ndarray:
    """What ``Teachers.__call__`` returned as ``fg``: the foreground probability ``1 -
    P(background)`` of :func:`voc_probabilities`, uint8 (0-255, rounded), 257x257."""
    fg = 1.0 - voc_probabilities(image, model)[..., 0]
    return np.round(fg * 255).astype(np.uint8)
