"""Convert the U^2-Net-p TFLite teacher into ``teacher_u2netp.pt`` (training time).

``python -m d2f_core.train.port_u2net TEACHERS OUT`` reads ``TEACHERS/u2netp_float16.tflite``
with ``ai-edge-litert`` (its ops, tensors and float16 weights) and the ``tflite`` flatbuffer
parser (the op options that the interpreter does not expose), both in ``pip install -e
".[teach]"``, and writes ``OUT/teacher_u2netp.pt`` for :mod:`d2f_core.teachers.u2net`: the
file's float16 weights as they are, in torch's layout.

The graph is read by its structure, backwards from the fused output ``Identity``, block by
block the way :class:`~d2f_core.teachers.u2net.U2NetP` computes it: the LOGISTIC of the 1x1
fuse convolution, the CONCATENATION of the six side maps (RESIZE_BILINEAR of a CONV_2D, the
finest without a resize), each side convolution's input a stage's output, each decoder
stage's input the CONCATENATION of the stage below (resized) and its encoder stage, whose
input is a MAX_POOL_2D of the stage above it (the first reads the graph's input). Inside a
block, the ADD of its last decoder convolution and its input convolution, each decoder
convolution's CONCATENATION of the level below and the encoder's skip, and the encoder's
convolutions and pools up to the input convolution. Every tensor that two paths reach must be
the same tensor, so a skip read from the wrong place fails the conversion.

Each convolution is checked against the module's own (kernel, dilation, "same" padding,
stride 1, ReLU or none), each resize (``align_corners=True``, ``half_pixel_centers=False``,
to the skip's or the input's size), each pool (2x2, stride 2, "valid") and each
CONCATENATION (channels, no activation). Every op of the file is used once, except the six
LOGISTICs of the side outputs ``Identity_1`` ... ``Identity_6``, which the fused map does not
need; every float16 weight is used exactly once.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..teachers.u2net import INPUT_SIDE, NAME, RSU4F, ConvReLU, U2NetP
from ..teachers.weights import save_teacher

__all__ = ["SOURCE_FILE", "convert", "main", "read_u2netp"]

#: the original file, in the teachers folder
SOURCE_FILE = "u2netp_float16.tflite"
#: the module's config, which the file's shapes must fit
CONFIG = {"in_channels": 3, "mid_channels": 16, "channels": 64}


class _Graph:
    """The ops of a TFLite file, found by the tensor each one writes and taken at most once."""

    def __init__(self, path: Path) -> None:
        try:
            import tflite
            from ai_edge_litert.interpreter import Interpreter, OpResolverType
        except ImportError as exc:
            raise ImportError(
                f"reading {SOURCE_FILE} needs ai-edge-litert and tflite "
                f'(pip install -e ".[teach]"): {exc}'
            ) from exc
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found")
        self.tfl = tflite
        # no delegate: the op list is the file's own graph, not the delegate's partition
        resolver = OpResolverType.BUILTIN_WITHOUT_DEFAULT_DELEGATES
        self.net = Interpreter(model_path=str(path), experimental_op_resolver_type=resolver)
        self.net.allocate_tensors()
        self.tensors = {t["index"]: t for t in self.net.get_tensor_details()}
        self.ops = list(self.net._get_ops_details())
        model = tflite.Model.GetRootAsModel(path.read_bytes(), 0)
        self.flat = model.Subgraphs(0)
        if self.flat.OperatorsLength() != len(self.ops):
            raise ValueError(f"{SOURCE_FILE}: the parser and the interpreter count other ops")
        self.producer: dict[int, int] = {}
        for op in self.ops:
            flat = self.flat.Operators(op["index"])
            if list(flat.InputsAsNumpy()) != list(op["inputs"]):
                raise ValueError(f"{SOURCE_FILE}: op {op['index']} reads other tensors")
            for t in op["outputs"]:
                self.producer[int(t)] = op["index"]
        self.used: set[int] = set()
        self.input = int(self.net.get_input_details()[0]["index"])
        self.outputs = {d["name"]: int(d["index"]) for d in self.net.get_output_details()}

    def shape(self, t: int) -> tuple[int, ...]:
        return tuple(int(v) for v in self.tensors[t]["shape"])

    def take(self, name: str, out: int) -> tuple[list[int], Any]:
        """The op that writes tensor ``out``, which must be a ``name`` not taken before: its
        input tensors and its builtin options (``None`` for ops without)."""
        index = self.producer.get(out)
        if index is None:
            raise ValueError(f"{SOURCE_FILE}: tensor {out} is not written by any op")
        op = self.ops[index]
        if op["op_name"] != name:
            raise ValueError(
                f"{SOURCE_FILE}: tensor {out} is written by {op['op_name']}, not {name}"
            )
        if index in self.used:
            raise ValueError(f"{SOURCE_FILE}: op {index} ({name}) is reached twice")
        self.used.add(index)
        options = None
        kind = {
            "CONV_2D": "Conv2DOptions",
            "MAX_POOL_2D": "Pool2DOptions",
            "RESIZE_BILINEAR": "ResizeBilinearOptions",
            "CONCATENATION": "ConcatenationOptions",
            "ADD": "AddOptions",
        }.get(name)
        if kind is not None:
            table = self.flat.Operators(index).BuiltinOptions()
            options = getattr(self.tfl, kind)()
            options.Init(table.Bytes, table.Pos)
        return [int(i) for i in op["inputs"]], options

    def weight(self, t: int) -> torch.Tensor:
        """The float16 constant that the DEQUANTIZE writing ``t`` reads, as float32."""
        (src,), _ = self.take("DEQUANTIZE", t)
        value = self.net.get_tensor(src)
        if value.dtype != np.float16:
            raise ValueError(f"{SOURCE_FILE}: weight tensor {src} is {value.dtype}, not float16")
        return torch.from_numpy(value.astype(np.float32))

    def no_activation(self, options: Any, what: str) -> None:
        if options.FusedActivationFunction() != self.tfl.ActivationFunctionType.NONE:
            raise ValueError(f"{SOURCE_FILE}: {what} has a fused activation")

    def conv(self, out: int, conv: nn.Conv2d, state: dict[str, torch.Tensor], name: str) -> int:
        """The CONV_2D writing ``out``, checked against the module's ``conv``; its weights go
        into ``state`` as ``name.weight`` / ``name.bias``. Returns its input tensor."""
        (x, wi, bi), o = self.take("CONV_2D", out)
        w = self.weight(wi).permute(0, 3, 1, 2).contiguous()  # O x kH x kW x I -> O x I x kH x kW
        b = self.weight(bi)
        relu = isinstance(conv, ConvReLU)
        act = self.tfl.ActivationFunctionType.RELU if relu else self.tfl.ActivationFunctionType.NONE
        found = (
            tuple(w.shape),
            tuple(b.shape),
            (o.DilationHFactor(), o.DilationWFactor()),
            (o.StrideH(), o.StrideW()),
            o.Padding(),
            o.FusedActivationFunction(),
        )
        want = (
            tuple(conv.weight.shape),
            tuple(conv.bias.shape),
            tuple(conv.dilation),
            (1, 1),
            self.tfl.Padding.SAME,
            act,
        )
        if found != want:
            raise ValueError(f"{SOURCE_FILE}: the convolution for {name} is {found}, not {want}")
        # "same" padding is the module's symmetric padding only for odd kernels
        if tuple(conv.padding) != tuple(d * (k // 2) for d, k in zip(conv.dilation, w.shape[2:])):
            raise ValueError(f"{SOURCE_FILE}: {name} does not pad as 'same'")
        state[f"{name}.weight"], state[f"{name}.bias"] = w, b
        return x

    def concat(self, out: int, count: int = 2) -> list[int]:
        """The channel CONCATENATION of ``count`` tensors writing ``out``: its inputs in
        order."""
        inputs, o = self.take("CONCATENATION", out)
        if len(inputs) != count:
            raise ValueError(
                f"{SOURCE_FILE}: the concatenation into {out} has {len(inputs)} inputs"
            )
        if o.Axis() not in (3, -1):
            raise ValueError(f"{SOURCE_FILE}: the concatenation into {out} is not on channels")
        self.no_activation(o, f"the concatenation into {out}")
        return inputs

    def add(self, out: int) -> list[int]:
        inputs, o = self.take("ADD", out)
        if len(inputs) != 2 or self.shape(inputs[0]) != self.shape(inputs[1]):
            raise ValueError(f"{SOURCE_FILE}: the ADD into {out} is not of two like tensors")
        self.no_activation(o, f"the ADD into {out}")
        return inputs

    def resize(self, out: int) -> int:
        """The RESIZE_BILINEAR writing ``out``, which must align the corners without half-pixel
        centres (``F.interpolate(align_corners=True)``). Returns its input tensor."""
        (x, size), o = self.take("RESIZE_BILINEAR", out)
        if not o.AlignCorners() or o.HalfPixelCenters():
            raise ValueError(f"{SOURCE_FILE}: the resize into {out} does not align the corners")
        if self.net.get_tensor(size).tolist() != list(self.shape(out)[1:3]):
            raise ValueError(f"{SOURCE_FILE}: the resize into {out} has another size")
        return x

    def pool(self, out: int) -> int:
        """The 2x2, stride-2 "valid" MAX_POOL_2D writing ``out``. Returns its input tensor."""
        (x,), o = self.take("MAX_POOL_2D", out)
        found = (o.FilterHeight(), o.FilterWidth(), o.StrideH(), o.StrideW(), o.Padding())
        if found != (2, 2, 2, 2, self.tfl.Padding.VALID):
            raise ValueError(f"{SOURCE_FILE}: the pool into {out} is {found}, not 2x2 valid")
        self.no_activation(o, f"the pool into {out}")
        _, h, w, _ = self.shape(x)
        if h % 2 or w % 2:  # ceil_mode (the module) and "valid" (the file) differ on odd sides
            raise ValueError(f"{SOURCE_FILE}: the pool into {out} reads an odd size {h}x{w}")
        return x


def _same(a: int, b: int, what: str) -> None:
    if a != b:
        raise ValueError(f"{SOURCE_FILE}: {what} reads tensor {a}, expected {b}")


def _block(g: _Graph, out: int, block: nn.Module, state: dict[str, torch.Tensor], name: str) -> int:
    """The RSU or RSU-4F block ``block`` (the module's ``name``) that writes ``out``: its
    weights into ``state``. Returns the block's input tensor."""
    pooled = not isinstance(block, RSU4F)
    last, top = g.add(out)
    x = g.conv(top, block.conv_in, state, f"{name}.conv_in")
    levels = len(block.encoder)
    # the decoder, last convolution first: each reads (level below, the encoder's skip)
    skips: list[int] = []
    h = last
    for j in reversed(range(levels - 1)):
        below, skip = g.concat(g.conv(h, block.decoder[j], state, f"{name}.decoder.{j}"))
        skips.append(skip)  # the output of encoder[levels - 2 - j]
        h = g.resize(below) if pooled and j > 0 else below
    # the encoder, bottom first: h is its last convolution's output; each convolution reads
    # the skip of the level above (pooled, between the levels of an RSU), the first ``top``
    for k in reversed(range(levels)):
        inp = g.conv(h, block.encoder[k], state, f"{name}.encoder.{k}")
        if k == 0:
            _same(inp, top, f"{name}.encoder.0")
        else:
            h = g.pool(inp) if pooled and k < levels - 1 else inp
            _same(h, skips[k - 1], f"{name}.encoder.{k}")
    return x


def read_u2netp(path: str | Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The :class:`U2NetP` config and state dict (float32 holding the file's float16 values)
    of the TFLite file ``path``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the graph is not U^2-Net-p as described in this module's docstring.
    """
    g = _Graph(Path(path))
    net = U2NetP(**CONFIG)
    state: dict[str, torch.Tensor] = {}
    if g.shape(g.input) != (1, INPUT_SIDE, INPUT_SIDE, CONFIG["in_channels"]):
        raise ValueError(f"{SOURCE_FILE}: the input is {g.shape(g.input)}")
    if "Identity" not in g.outputs:
        raise ValueError(f"{SOURCE_FILE}: no output named Identity")
    (fused,), _ = g.take("LOGISTIC", g.outputs["Identity"])
    sides = g.concat(g.conv(fused, net.fuse, state, "fuse"), len(net.side))
    # the stages' outputs, finest first: decoder[4] ... decoder[0], then encoder[5]
    stage_outs = []
    for k, m in enumerate(sides):
        stage_outs.append(g.conv(g.resize(m) if k > 0 else m, net.side[k], state, f"side.{k}"))
    n_dec = len(net.decoder)
    encoder_outs: list[int] = [-1] * len(net.encoder)
    encoder_outs[-1] = stage_outs[-1]
    for k in range(n_dec):  # decoder[n_dec - 1 - k] writes stage k's output
        j = n_dec - 1 - k
        below, skip = g.concat(_block(g, stage_outs[k], net.decoder[j], state, f"decoder.{j}"))
        _same(g.resize(below), stage_outs[k + 1], f"decoder.{j}")
        encoder_outs[k] = skip
    # the encoder, deepest first: each stage's input a pool of the stage above
    for k in reversed(range(len(net.encoder))):
        x = _block(g, encoder_outs[k], net.encoder[k], state, f"encoder.{k}")
        if k == 0:
            _same(x, g.input, "encoder.0")
        else:
            _same(g.pool(x), encoder_outs[k - 1], f"encoder.{k}")
    # every op used once but the side outputs' sigmoids; every weight once (by DEQUANTIZE)
    side_outputs = {g.outputs[f"Identity_{k}"] for k in range(1, len(net.side) + 1)}
    left = [op for op in g.ops if op["index"] not in g.used]
    if (
        sorted(op["op_name"] for op in left) != ["LOGISTIC"] * len(side_outputs)
        or {int(op["outputs"][0]) for op in left} != side_outputs
    ):
        names = sorted({op["op_name"] for op in left})
        raise ValueError(f"{SOURCE_FILE}: {len(left)} ops are not part of U^2-Net-p: {names}")
    own = net.state_dict()
    if set(state) != set(own) or any(state[k].shape != own[k].shape for k in own):
        raise ValueError(f"{SOURCE_FILE}: the weights read do not fit U2NetP")
    return dict(CONFIG), {k: state[k] for k in own}


def convert(src: Path, out_dir: Path) -> list[Path]:
    """Write ``out_dir/teacher_u2netp.pt`` from ``src/u2netp_float16.tflite``."""
    config, state = read_u2netp(Path(src) / SOURCE_FILE)
    return [save_teacher(Path(out_dir) / f"teacher_{NAME}.pt", NAME, config, state)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m d2f_core.train.port_u2net",
        description=f"convert {SOURCE_FILE} into teacher_{NAME}.pt",
    )
    parser.add_argument("teachers", type=Path, help="folder holding the original file")
    parser.add_argument("out", type=Path, help="folder for the weight file")
    args = parser.parse_args(argv)
    try:
        for path in convert(args.teachers, args.out):
            print(f"wrote {path}")
    except (OSError, ValueError, ImportError) as exc:
        print(f"port_u2net: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
