"""Convert the FastDepth int8 TFLite teacher into ``teacher_fastdepth.pt`` (training time).

``python -m d2f_core.train.port_fastdepth TEACHERS OUT`` reads
``TEACHERS/fast_depth_224_int8.tflite`` with ``ai-edge-litert`` (``pip install -e
".[teach]"``): its tensors with the interpreter, its ops' options (strides, padding, fused
activations, resize flags) from the flatbuffer with the schema that ``ai-edge-litert`` ships.
It writes ``OUT/teacher_fastdepth.pt`` for :mod:`d2f_core.teachers.fastdepth`: the file's
int8 weights and int32 biases as they are, and each tensor's scale and zero point and each
convolution's activation in the config.

The graph is read by its structure, op after op: a QUANTIZE of the uint8 input, the stem (PAD,
CONV_2D), the encoder's blocks (PAD, 3x3 DEPTHWISE_CONV_2D, 1x1 CONV_2D), the decoder's stages
(PAD, 5x5 DEPTHWISE_CONV_2D, 1x1 CONV_2D, 2x RESIZE_NEAREST_NEIGHBOR and, for three of them,
an ADD of an encoder block's output), the head (1x1 CONV_2D) and a QUANTIZE to the uint8
output; the skips are found from which tensors each ADD reads. Every weight and bias tensor of
the file is used exactly once, and each convolution is checked to be exact when the module
sums its whole numbers in float32 (:func:`_exact_in_float32`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..teachers.fastdepth import NAME, FastDepth, level_range
from ..teachers.weights import save_teacher

__all__ = ["SOURCE_FILE", "convert", "main", "read_fastdepth"]

#: the original file, in the teachers folder
SOURCE_FILE = "fast_depth_224_int8.tflite"
#: a float32 sum of whole numbers is exact while every partial sum stays under this
_EXACT_FLOAT32 = 2**24


def _schema() -> Any:
    from ai_edge_litert import schema_py_generated

    return schema_py_generated


def _activation_name(code: int) -> str | None:
    """The module's name of a TFLite fused activation (None: one the module lacks)."""
    kinds = _schema().ActivationFunctionType
    return {kinds.NONE: "none", kinds.RELU: "relu", kinds.RELU6: "relu6"}.get(code)


class _Graph:
    """The ops of a TFLite file in execution order, read one by one along the main path."""

    def __init__(self, path: Path) -> None:
        from ai_edge_litert.interpreter import Interpreter, OpResolverType
        from ai_edge_litert.tools import flatbuffer_utils

        # no delegate: the op list is the file's own graph, not the delegate's partition
        resolver = OpResolverType.BUILTIN_WITHOUT_DEFAULT_DELEGATES
        self.net = Interpreter(model_path=str(path), experimental_op_resolver_type=resolver)
        self.net.allocate_tensors()
        self.tensors = {t["index"]: t for t in self.net.get_tensor_details()}
        self.ops = list(self.net._get_ops_details())
        # the ops' options (strides, padding, activations, resize flags), which the
        # interpreter does not expose, from the file's flatbuffer, op for op
        model = flatbuffer_utils.read_model(str(path))
        if len(model.subgraphs) != 1 or len(model.subgraphs[0].operators) != len(self.ops):
            raise ValueError(f"{SOURCE_FILE}: the flatbuffer and the interpreter disagree")
        self.options = []
        for op, fb in zip(self.ops, model.subgraphs[0].operators, strict=True):
            if [int(i) for i in op["outputs"]] != list(fb.outputs):
                raise ValueError(f"{SOURCE_FILE}: op {op['index']} differs in the flatbuffer")
            self.options.append(fb.builtinOptions)
        self.pos = 0
        produced = {int(i) for op in self.ops for i in op["outputs"]}
        inputs = {d["index"] for d in self.net.get_input_details()}
        consumed = {int(i) for op in self.ops for i in op["inputs"] if i >= 0}
        #: constant tensors with quantisation (weights, biases), and how often each is used
        self.uses = {
            i: 0
            for i in consumed - produced - inputs
            if len(self.tensors[i]["quantization_parameters"]["scales"])
        }

    def peek(self) -> str | None:
        return self.ops[self.pos]["op_name"] if self.pos < len(self.ops) else None

    def next_kernel(self) -> int | None:
        """The kernel side of the convolution after the next op (a PAD), if any."""
        if self.pos + 1 >= len(self.ops) or "CONV" not in self.ops[self.pos + 1]["op_name"]:
            return None
        return self.shape(int(self.ops[self.pos + 1]["inputs"][1]))[1]

    def take(self, name: str, current: int | None) -> tuple[list[int], int, Any]:
        """The next op, which must be a ``name`` reading ``current`` (when given) first:
        its input tensor ids, its output tensor id and its options (or None)."""
        if self.pos >= len(self.ops):
            raise ValueError(f"{SOURCE_FILE}: the graph ends where a {name} was expected")
        op = self.ops[self.pos]
        self.pos += 1
        inputs = [int(i) for i in op["inputs"]]
        if op["op_name"] != name or (current is not None and inputs[0] != current):
            raise ValueError(
                f"{SOURCE_FILE}: op {op['index']} is {op['op_name']} on tensor {inputs[0]}, "
                f"expected {name} on tensor {current}"
            )
        if len(op["outputs"]) != 1:
            raise ValueError(f"{SOURCE_FILE}: op {op['index']} has {len(op['outputs'])} outputs")
        return inputs, int(op["outputs"][0]), self.options[self.pos - 1]

    def shape(self, i: int) -> tuple[int, ...]:
        return tuple(int(v) for v in self.tensors[i]["shape"])

    def quant(self, i: int) -> tuple[np.ndarray, np.ndarray, int]:
        q = self.tensors[i]["quantization_parameters"]
        return q["scales"].astype(np.float32), q["zero_points"], int(q["quantized_dimension"])

    def activation(self, i: int) -> tuple[float, int]:
        """A per-tensor int8 activation's ``(scale, zero_point)``."""
        scales, zps, _ = self.quant(i)
        if self.tensors[i]["dtype"] != np.int8 or len(scales) != 1:
            raise ValueError(f"{SOURCE_FILE}: tensor {i} is not a per-tensor int8 activation")
        return float(scales[0]), int(zps[0])

    def constant(self, i: int) -> np.ndarray:
        """A weight or bias tensor's values, counted as used."""
        if i not in self.uses:
            raise ValueError(f"{SOURCE_FILE}: tensor {i} is not a quantised constant")
        self.uses[i] += 1
        return self.net.get_tensor(i)


def _pad(g: _Graph, current: int, side: int) -> int:
    """A PAD of ``side`` pixels on each side of the height and width."""
    (_, paddings), out, _ = g.take("PAD", current)
    want = [[0, 0], [side, side], [side, side], [0, 0]]
    if g.net.get_tensor(paddings).tolist() != want or g.activation(out) != g.activation(current):
        raise ValueError(f"{SOURCE_FILE}: tensor {out} is not a plain {side}-pixel padding")
    return out


def _conv(
    g: _Graph, current: int, depthwise: bool, kernel: int
) -> tuple[int, dict[str, torch.Tensor], dict[str, Any], int]:
    """A CONV_2D or DEPTHWISE_CONV_2D of a ``kernel x kernel`` VALID window on ``current``
    (its padding is the PAD before it): its output tensor, its weights as the module holds
    them, its quantisation and its stride."""
    (_, wi, bi), out, options = g.take("DEPTHWISE_CONV_2D" if depthwise else "CONV_2D", current)
    w, b = g.constant(wi), g.constant(bi)
    in_scale, in_zp = g.activation(current)
    out_scale, out_zp = g.activation(out)
    w_scales, w_zps, w_axis = g.quant(wi)
    b_scales, b_zps, _ = g.quant(bi)
    if w.dtype != np.int8 or b.dtype != np.int32 or w_zps.any() or b_zps.any():
        raise ValueError(f"{SOURCE_FILE}: tensor {wi} is not int8 weights with int32 bias")
    if depthwise:  # 1 x k x k x C (channel multiplier 1) -> C x 1 x k x k
        if w.shape[0] != 1 or w_axis != 3 or options.depthMultiplier != 1:
            raise ValueError(f"{SOURCE_FILE}: depthwise weights {wi} of shape {w.shape}")
        weight = np.transpose(w, (3, 0, 1, 2))
    else:  # O x k x k x I -> O x I x k x k
        if w_axis != 0:
            raise ValueError(f"{SOURCE_FILE}: weights {wi} not quantised per output channel")
        weight = np.transpose(w, (0, 3, 1, 2))
    channels = weight.shape[0]
    if weight.shape[2:] != (kernel, kernel) or len(w_scales) != channels:
        raise ValueError(f"{SOURCE_FILE}: weights {wi} of shape {w.shape}, not {kernel}x{kernel}")
    if not np.allclose(b_scales, in_scale * w_scales, rtol=1e-5, atol=0):
        raise ValueError(f"{SOURCE_FILE}: bias {bi} is not scaled as input x weight")
    # a VALID window (the padding is the PAD before it) with square stride, no dilation
    stride = options.strideH
    valid = options.padding == _schema().Padding.VALID and options.strideW == stride
    if not valid or options.dilationHFactor != 1 or options.dilationWFactor != 1:
        raise ValueError(f"{SOURCE_FILE}: the convolution on tensor {current} is not plain")
    (_, h_in, w_in, _), (_, h_out, w_out, _) = g.shape(current), g.shape(out)
    if (h_out, w_out) != ((h_in - kernel) // stride + 1, (w_in - kernel) // stride + 1):
        raise ValueError(f"{SOURCE_FILE}: the convolution on tensor {current} is misshapen")
    activation = _activation_name(options.fusedActivationFunction)
    if activation is None:
        raise ValueError(f"{SOURCE_FILE}: op on tensor {current} has an unknown activation")
    # the kernels' float32 requantisation scale, as QuantConv makes it
    multiplier = np.float32(in_scale) * w_scales / np.float32(out_scale)
    levels = level_range(activation, out_scale, out_zp)
    if not _exact_in_float32(weight, b, in_zp, multiplier, levels):
        raise ValueError(f"{SOURCE_FILE}: the sums of tensor {out} may not be exact in float32")
    state = {"weight": torch.from_numpy(weight.copy()), "bias": torch.from_numpy(b.copy())}
    quant = {
        "weight_scales": [float(s) for s in w_scales],
        "scale": out_scale,
        "zero_point": out_zp,
        "activation": activation,
    }
    return out, state, quant, stride


def _exact_in_float32(
    weight: np.ndarray,
    bias: np.ndarray,
    in_zp: int,
    multiplier: np.ndarray,
    levels: tuple[int, int],
) -> bool:
    """Whether a float32 convolution of whole numbers gives the integer kernel's output.

    A channel whose sums (bias included, inputs at most 255 levels from their zero point) stay
    under 2^24 is summed exactly. The others must be channels pruned to nothing (this file has
    biases near +-2^30 on weight scales near 1e-15): there the float32 rounding, at most half
    an ulp of the largest partial sum per addition, must not change the output, so every sum
    the channel can make, widened by that error, must requantise (``multiplier``, rounding,
    clamping to ``levels``) to one value.
    """
    channels = weight.shape[0]
    level = max(abs(-128 - in_zp), abs(127 - in_zp))  # the largest input level
    reach = level * np.abs(weight.astype(np.int64)).reshape(channels, -1).sum(1)
    bias = bias.astype(np.int64)
    largest = np.abs(bias) + reach
    additions = weight[0].size + 1
    for c in np.nonzero(largest >= _EXACT_FLOAT32)[0]:
        err = additions * 2.0**-24 * float(largest[c])
        lo = (float(bias[c] - reach[c]) - err) * float(multiplier[c])
        hi = (float(bias[c] + reach[c]) + err) * float(multiplier[c])
        ends = np.clip(np.floor(np.array([lo, hi]) + 0.5), *levels)
        if ends[0] != ends[1]:
            return False
    return True


def _upsample(g: _Graph, current: int) -> int:
    """A 2x RESIZE_NEAREST_NEIGHBOR without align_corners or half_pixel_centers (source
    pixel ``i // 2``, as ``F.interpolate(scale_factor=2, mode="nearest")``)."""
    (_, size), out, options = g.take("RESIZE_NEAREST_NEIGHBOR", current)
    if options.alignCorners or options.halfPixelCenters:
        raise ValueError(f"{SOURCE_FILE}: the resize of tensor {current} is not plain nearest")
    _, h, w, _ = g.shape(current)
    if g.net.get_tensor(size).tolist() != [2 * h, 2 * w]:
        raise ValueError(f"{SOURCE_FILE}: the resize of tensor {current} is not 2x")
    if g.activation(out) != g.activation(current):
        raise ValueError(f"{SOURCE_FILE}: the resize of tensor {current} requantises")
    return out


def _quantize(g: _Graph, uint8: int, int8: int) -> None:
    """A QUANTIZE between uint8 (zero point 0) and int8 (zero point -128) of the same scale:
    a shift by 128, so that the int8 tensor's levels are the uint8 values."""
    su, zu, _ = g.quant(uint8)
    s8, z8 = g.activation(int8)
    if g.tensors[uint8]["dtype"] != np.uint8 or int(zu[0]) != 0 or z8 != -128 or su[0] != s8:
        raise ValueError(f"{SOURCE_FILE}: tensor {uint8} is not the uint8 twin of {int8}")


def read_fastdepth(path: str | Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The :class:`FastDepth` config and state dict of the TFLite file ``path``.

    Raises:
        ValueError: the graph is not FastDepth as described in this module's docstring.
    """
    g = _Graph(Path(path))
    state: dict[str, torch.Tensor] = {}
    quant: dict[str, Any] = {}

    def keep(name: str, conv_state: dict[str, torch.Tensor]) -> None:
        state.update({f"{name}.{k}": v for k, v in conv_state.items()})

    (source,), x, _ = g.take("QUANTIZE", None)
    if [source] != [d["index"] for d in g.net.get_input_details()]:
        raise ValueError(f"{SOURCE_FILE}: the graph does not start from its input")
    _quantize(g, source, x)
    input_scale, _ = g.activation(x)

    x, conv, quant["stem"], stride = _conv(g, _pad(g, x, 1), False, 3)
    keep("stem", conv)
    widths, strides = [conv["weight"].shape[0]], [stride]
    encoder_out = [x]  # the stem's, then each block's output tensor
    while g.peek() == "PAD" and g.next_kernel() == 3:
        i = len(encoder_out) - 1
        x, dw, qd, stride = _conv(g, _pad(g, x, 1), True, 3)
        x, pw, qp, _ = _conv(g, x, False, 1)
        keep(f"encoder.{i}.depthwise", dw)
        keep(f"encoder.{i}.pointwise", pw)
        quant[f"encoder.{i}"] = {"depthwise": qd, "pointwise": qp}
        widths.append(pw["weight"].shape[0])
        strides.append(stride)
        encoder_out.append(x)

    decoder_widths: list[int] = []
    skips: list[int] = []
    while g.peek() == "PAD":
        i = len(decoder_widths)
        x, dw, qd, stride = _conv(g, _pad(g, x, 2), True, 5)
        x, pw, qp, _ = _conv(g, x, False, 1)
        if stride != 1:
            raise ValueError(f"{SOURCE_FILE}: decoder stage {i} has stride {stride}")
        keep(f"decoder.{i}.depthwise", dw)
        keep(f"decoder.{i}.pointwise", pw)
        quant[f"decoder.{i}"] = {"depthwise": qd, "pointwise": qp}
        decoder_widths.append(pw["weight"].shape[0])
        x = _upsample(g, x)
        skips.append(-1)
        if g.peek() == "ADD":
            (a, b), out, options = g.take("ADD", None)
            if _activation_name(options.fusedActivationFunction) != "none":
                raise ValueError(f"{SOURCE_FILE}: the ADD after decoder stage {i} is activated")
            if b != x or a not in encoder_out[1:]:
                raise ValueError(f"{SOURCE_FILE}: the ADD after decoder stage {i} is no skip")
            scale, zp = g.activation(out)
            quant[f"skip.{i}"] = {"scale": scale, "zero_point": zp}
            skips[-1] = encoder_out.index(a) - 1
            x = out

    x, conv, quant["head"], _ = _conv(g, x, False, 1)
    keep("head", conv)
    (_,), output, _ = g.take("QUANTIZE", x)
    _quantize(g, output, x)
    if [output] != [d["index"] for d in g.net.get_output_details()]:
        raise ValueError(f"{SOURCE_FILE}: the graph does not end at its output")
    if g.peek() is not None:
        raise ValueError(f"{SOURCE_FILE}: ops left after the output: {g.peek()}")
    misused = {i: n for i, n in g.uses.items() if n != 1}
    if misused:
        raise ValueError(f"{SOURCE_FILE}: constants not used exactly once: {misused}")

    config = {
        "widths": widths,
        "strides": strides,
        "decoder_widths": decoder_widths,
        "skips": skips,
        "input_scale": input_scale,
        "quant": quant,
    }
    FastDepth(**config).load_state_dict(state, strict=True)  # every tensor fits the module
    return config, state


def convert(src: Path, out_dir: Path) -> list[Path]:
    """Write ``out_dir/teacher_fastdepth.pt`` from ``src/fast_depth_224_int8.tflite``."""
    config, state = read_fastdepth(Path(src) / SOURCE_FILE)
    return [save_teacher(Path(out_dir) / f"teacher_{NAME}.pt", NAME, config, state)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m d2f_core.train.port_fastdepth",
        description=f"convert {SOURCE_FILE} into teacher_{NAME}.pt",
    )
    parser.add_argument("teachers", type=Path, help="folder holding the original file")
    parser.add_argument("out", type=Path, help="folder for the weight file")
    args = parser.parse_args(argv)
    try:
        for path in convert(args.teachers, args.out):
            print(f"wrote {path}")
    except (OSError, ValueError, ImportError) as exc:
        print(f"port_fastdepth: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
