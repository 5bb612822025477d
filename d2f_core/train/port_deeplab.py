"""Convert the two DeepLab teachers' original files into :class:`~d2f_core.teachers.deeplab.
DeepLab` weights (training-time extras only: ``ai-edge-litert``, ``tflite``, ``onnx``).

- ``deeplabv3_mobilenetv2_ade20k.tflite`` -> ``teacher_deeplab_ade20k.pt``: the weights are
  int8 with one float scale per tensor (a dynamic-range quantized graph; dequantized here as
  ``q x scale``), the biases float32; read with ``ai-edge-litert``'s interpreter, the op
  options (strides, dilations, fused activations, resize flags) with the ``tflite``
  flatbuffer parser.
- ``deeplabv3_mobilenetv2_voc.onnx`` -> ``teacher_deeplab_voc.pt``: float32, read with
  ``onnx``.

Each graph is first read into a small common form (:class:`Graph`: convolutions with their
folded batch norms and activations, residual adds, pooling, resizes, concatenations), then
matched to the module by structure: walking from the input, each of the module's
convolutions takes the one graph convolution that reads the tensor the walk is at and has
its shape, stride, dilation, groups and activation; every residual add, the pooling branch,
the concatenations' order and the final resize are checked on the way. The conversion fails
unless every graph node and every weight tensor is used exactly once.

``python -m d2f_core.train.port_deeplab SRC OUT`` writes both files from the teachers folder
``SRC`` into ``OUT`` (e.g. ``../shared/datasets/teachers assets/weights``).
"""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..teachers.deeplab import ADE20K, VOC, WIDTH_1, ConvAct, DeepLab
from ..teachers.weights import save_teacher, teacher_path

__all__ = ["ADE_FILE", "CONFIGS", "VOC_FILE", "Graph", "convert", "main", "match", "read_onnx"]

ADE_FILE = "deeplabv3_mobilenetv2_ade20k.tflite"
VOC_FILE = "deeplabv3_mobilenetv2_voc.onnx"

#: each weight set's module config, as read from its graph
CONFIGS = {
    ADE20K: {
        "num_classes": 151,
        "channels": list(WIDTH_1),
        "output_stride": 8,
        "decoder": True,
        "resize": "align_corners",
    },
    VOC: {
        "num_classes": 21,
        "channels": [c // 2 for c in WIDTH_1],
        "output_stride": 8,
        "decoder": False,
        "resize": "asymmetric",
    },
}
#: what each weight set is stored as: float16 moves the VOC probabilities by up to 0.03
DTYPES = {ADE20K: torch.float32, VOC: torch.float32}


@dataclass
class Node:
    """One operation of a graph in the common form.

    ``kind`` is ``conv`` (``weight`` OIHW, ``bias``, ``stride``, ``dilation``, ``groups``,
    ``act``, ``pad`` each side), ``add`` (two tensors), ``pool`` (a global mean),
    ``resize`` (``mode``: ``align_corners``, ``asymmetric`` or ``half_pixel``) or
    ``concat`` (channels, in the order of ``inputs``)."""

    kind: str
    inputs: list[str]
    output: str
    attrs: dict = field(default_factory=dict)
    weights: list[str] = field(default_factory=list)  # the constants it holds, by name


@dataclass
class Graph:
    """A graph in the common form: its nodes, its input and output tensor, and every weight
    constant by name (each must end up in exactly one node)."""

    nodes: list[Node]
    input: str
    output: str
    constants: set[str]
    zeros: set[str] = field(default_factory=set)  # the constants that are all zeros

    def consumers(self, tensor: str) -> list[Node]:
        return [n for n in self.nodes if tensor in n.inputs]


# ----------------------------------------------------------------------------- TFLite


def read_tflite(path: Path) -> Graph:
    """The ADE20K graph in the common form: the space-to-batch / depthwise /
    batch-to-space triples become dilated convolutions, the batch norm after them (MUL and
    ADD of constants) is folded in, DEQUANTIZE is read through and a resize to the same size
    dropped (:class:`_TFLiteWalk`)."""
    walk = _TFLiteWalk(path)
    for k in range(walk.sub.OperatorsLength()):
        walk.operator(k)
    return walk.graph()


class _TFLiteWalk:
    """:func:`read_tflite`'s walk over the one subgraph of a TFLite file, operator by
    operator: the tensors' names (DEQUANTIZE and the folded operators rename), the nodes
    made so far and what each tensor is."""

    def __init__(self, path: Path) -> None:
        import tflite
        from ai_edge_litert.interpreter import Interpreter, OpResolverType

        self.tflite, self.path = tflite, path
        self.net = Interpreter(
            model_path=str(path),
            experimental_op_resolver_type=OpResolverType.BUILTIN_WITHOUT_DEFAULT_DELEGATES,
        )
        self.net.allocate_tensors()
        self.details = {d["index"]: d for d in self.net.get_tensor_details()}
        self.model = tflite.Model.GetRootAsModel(path.read_bytes(), 0)
        if self.model.SubgraphsLength() != 1:
            raise ValueError(f"{path}: expected one subgraph, got {self.model.SubgraphsLength()}")
        self.sub = sub = self.model.Subgraphs(0)
        self.op_names = {
            v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")
        }
        self.acts = {
            tflite.ActivationFunctionType.NONE: "none",
            tflite.ActivationFunctionType.RELU: "relu",
            tflite.ActivationFunctionType.RELU6: "relu6",
        }
        count = sub.TensorsLength()
        self.name = {i: f"t{i}" for i in range(count)}  # DEQUANTIZE renames
        self.weights = {f"t{i}" for i in range(count) if self.is_const(i)}
        self.shape = {f"t{i}": tuple(sub.Tensors(i).ShapeAsNumpy()) for i in range(count)}
        self.values: dict[str, np.ndarray] = {}
        self.nodes: list[Node] = []
        self.producer: dict[str, Node] = {}
        self.pending: dict[str, dict] = {}  # space-to-batch outputs: block and pads
        self.structural: set[str] = set()  # int32 constants: shapes, pads, sizes
        self.dequantized: set[int] = set()  # DEQUANTIZE outputs: int8 weights read as float
        self.readers: Counter[int] = Counter()
        for k in range(sub.OperatorsLength()):
            op = sub.Operators(k)
            self.readers.update(op.Inputs(j) for j in range(op.InputsLength()))
        # what each operator kind becomes (AFFINE: a MUL or ADD of a constant)
        self.handlers = {
            "DEQUANTIZE": self._dequantize,
            "SPACE_TO_BATCH_ND": self._space_to_batch,
            "CONV_2D": self._conv,
            "DEPTHWISE_CONV_2D": self._conv,
            "BATCH_TO_SPACE_ND": self._batch_to_space,
            "AFFINE": self._affine,
            "ADD": self._add,
            "AVERAGE_POOL_2D": self._pool,
            "RESIZE_BILINEAR": self._resize,
            "CONCATENATION": self._concat,
        }

    def is_const(self, i: int) -> bool:
        return self.model.Buffers(self.sub.Tensors(i).Buffer()).DataLength() > 0

    def value(self, i: int) -> np.ndarray:
        """A constant as float32 (int8 dequantized with its scale) or as stored (int32)."""
        d = self.details[i]
        v = self.net.get_tensor(i)
        if d["dtype"] == np.int8:
            q = d["quantization_parameters"]
            if np.any(q["zero_points"] != 0):
                raise ValueError(f"{self.path}: tensor {i} has a zero point")
            scale = q["scales"].astype(np.float32)
            if scale.size != 1:  # per output channel
                scale = scale.reshape([-1] + [1] * (v.ndim - 1))
            return v.astype(np.float32) * scale
        if d["dtype"] in (np.float32, np.float16):
            return v.astype(np.float32)
        return v

    @staticmethod
    def options(op, cls):
        o, t = cls(), op.BuiltinOptions()
        o.Init(t.Bytes, t.Pos)
        return o

    def const(self, i: int) -> str:
        key = self.name[i]
        if key not in self.values:
            self.values[key] = self.value(int(key[1:]))
        return key

    def operator(self, k: int) -> None:
        """Operator ``k``: a node of the common form, or a tensor renamed (read through or
        folded into the node that made its input)."""
        op = self.sub.Operators(k)
        code = self.model.OperatorCodes(op.OpcodeIndex())
        kind = self.op_names[max(code.BuiltinCode(), code.DeprecatedBuiltinCode())]
        ins = [op.Inputs(j) for j in range(op.InputsLength())]
        out = f"t{op.Outputs(0)}"
        # a MUL or ADD of a constant: a batch norm's scale or shift
        affine = kind in ("MUL", "ADD") and any(self.is_const(i) for i in ins)
        handler = self.handlers.get("AFFINE" if affine else kind)
        if handler is None:
            raise ValueError(f"{self.path}: op {k}: unsupported operator {kind}")
        node = handler(k, op, kind, ins, out)
        if node is not None:
            self.nodes.append(node)
            self.producer[out] = node

    def _dequantize(self, k, op, kind, ins, out) -> None:
        self.dequantized.add(op.Outputs(0))
        self.name[op.Outputs(0)] = self.name[ins[0]]
        self.weights.discard(out)

    def _space_to_batch(self, k, op, kind, ins, out) -> None:
        block, pads = self.value(ins[1]), self.value(ins[2])
        self.structural |= {self.name[ins[1]], self.name[ins[2]]}
        if block[0] != block[1] or pads[0, 0] != pads[1, 0]:
            raise ValueError(f"{self.path}: op {k}: unequal space-to-batch {block} {pads}")
        self.pending[out] = {
            "input": self.name[ins[0]], "block": int(block[0]), "pad": int(pads[0, 0])
        }  # fmt: skip

    def _conv(self, k, op, kind, ins, out) -> Node:
        tfl, path = self.tflite, self.path
        depthwise = kind == "DEPTHWISE_CONV_2D"
        o = self.options(op, tfl.DepthwiseConv2DOptions if depthwise else tfl.Conv2DOptions)
        w, b = self.const(ins[1]), self.const(ins[2])
        # TFLite holds OHWI (1HWC for a depthwise one), torch OIHW (C1HW)
        weight = self.values[w].transpose((3, 0, 1, 2) if depthwise else (0, 3, 1, 2))
        if depthwise and o.DepthMultiplier() != 1:
            raise ValueError(f"{path}: op {k}: depth multiplier {o.DepthMultiplier()}")
        if (o.StrideH(), o.DilationHFactor()) != (o.StrideW(), o.DilationWFactor()):
            raise ValueError(f"{path}: op {k}: unequal strides or dilations")
        x, dilation = self.name[ins[0]], o.DilationHFactor()
        kernel = weight.shape[-1]
        if x in self.pending:  # a dilated convolution: VALID inside space-to-batch
            if self.readers[ins[0]] != 1:
                raise ValueError(f"{path}: op {k}: a space-to-batch read twice")
            stb = self.pending.pop(x)
            x, dilation = stb["input"], stb["block"]
            if o.Padding() != tfl.Padding.VALID or stb["pad"] != dilation * (kernel // 2):
                raise ValueError(f"{path}: op {k}: space-to-batch pads {stb['pad']}")
            pad = stb["pad"]
        elif o.Padding() != tfl.Padding.SAME:
            raise ValueError(f"{path}: op {k}: VALID padding outside space-to-batch")
        else:
            pad = "same"
        quantized = ins[1] not in self.dequantized and self.details[ins[1]]["dtype"] == np.int8
        attrs = {
            "weight": weight,
            "bias": self.values[b].copy(),
            "stride": o.StrideH(),
            "dilation": dilation,
            "groups": weight.shape[0] if depthwise else 1,
            "act": self.acts[o.FusedActivationFunction()],
            "pad": pad,
            # int8 weights read as they are: the runtime quantizes the input too
            "quantized": quantized,
        }
        return Node("conv", [x], out, attrs, [w, b])

    def _batch_to_space(self, k, op, kind, ins, out) -> None:
        src = self.producer[self.name[ins[0]]]
        crops = self.value(ins[2])
        self.structural |= {self.name[ins[1]], self.name[ins[2]]}
        dilated = src.kind == "conv" and src.attrs["dilation"] == int(self.value(ins[1])[0])
        if not dilated or crops[:, 0].any() or self.readers[ins[0]] != 1:
            raise ValueError(f"{self.path}: op {k}: batch-to-space after no dilated convolution")
        self.name[op.Outputs(0)] = src.output

    def _affine(self, k, op, kind, ins, out) -> None:
        """A MUL or ADD of a constant after a linear convolution: folded into it."""
        (x,) = [self.name[i] for i in ins if not self.is_const(i)]
        (c,) = [self.const(i) for i in ins if self.is_const(i)]
        src = self.producer.get(x)
        if src is None or src.kind != "conv" or src.attrs["act"] != "none":
            raise ValueError(f"{self.path}: op {k}: {kind} of a constant after no linear conv")
        if self.readers[next(i for i in ins if not self.is_const(i))] != 1:
            raise ValueError(f"{self.path}: op {k}: a batch norm on a shared tensor")
        a = src.attrs
        if kind == "MUL":
            a["weight"] = a["weight"] * self.values[c].reshape(-1, 1, 1, 1)
            a["bias"] = a["bias"] * self.values[c]
        else:
            a["bias"] = a["bias"] + self.values[c]
            options = self.options(op, self.tflite.AddOptions)
            a["act"] = self.acts[options.FusedActivationFunction()]
        src.weights.append(c)
        self.name[op.Outputs(0)] = src.output

    def _add(self, k, op, kind, ins, out) -> Node:
        if self.options(op, self.tflite.AddOptions).FusedActivationFunction():
            raise ValueError(f"{self.path}: op {k}: a residual add with an activation")
        return Node("add", [self.name[i] for i in ins], out)

    def _pool(self, k, op, kind, ins, out) -> Node:
        o = self.options(op, self.tflite.Pool2DOptions)
        _, h, w, _ = self.shape[self.name[ins[0]]]
        if (o.FilterHeight(), o.FilterWidth()) != (h, w) or self.shape[out][1:3] != (1, 1):
            raise ValueError(f"{self.path}: op {k}: an average pool that is not global")
        return Node("pool", [self.name[ins[0]]], out)

    def _resize(self, k, op, kind, ins, out) -> Node | None:
        o = self.options(op, self.tflite.ResizeBilinearOptions)
        self.structural.add(self.name[ins[1]])
        if self.shape[self.name[ins[0]]] == self.shape[out] and not o.HalfPixelCenters():
            self.name[op.Outputs(0)] = self.name[ins[0]]  # the identity
            return None
        if o.AlignCorners():
            mode = "align_corners"
        else:
            mode = "half_pixel" if o.HalfPixelCenters() else "asymmetric"
        return Node("resize", [self.name[ins[0]]], out, {"mode": mode})

    def _concat(self, k, op, kind, ins, out) -> Node:
        o = self.options(op, self.tflite.ConcatenationOptions)
        if o.Axis() not in (3, -1) or o.FusedActivationFunction():
            raise ValueError(f"{self.path}: op {k}: a concatenation not on channels")
        return Node("concat", [self.name[i] for i in ins], out)

    def graph(self) -> Graph:
        """The walk's nodes as a :class:`Graph`, the weights' arrays as float32."""
        if self.pending:
            raise ValueError(f"{self.path}: a space-to-batch with no convolution after it")
        weights = self.weights - self.structural
        graph_in, graph_out = f"t{self.sub.Inputs(0)}", self.name[self.sub.Outputs(0)]
        for n in self.nodes:
            for key in ("weight", "bias"):
                if key in n.attrs:
                    n.attrs[key] = n.attrs[key].astype(np.float32)
        zeros = {k for k, v in self.values.items() if not v.any()}
        return Graph(self.nodes, graph_in, graph_out, weights, zeros)


# ----------------------------------------------------------------------------- ONNX


def read_onnx(path: Path) -> Graph:
    """The VOC graph in the common form: Clip(0, 6) and Relu after a convolution become its
    activation, the layout transposes at both ends are read through."""
    import onnx
    from onnx import numpy_helper

    model = onnx.shape_inference.infer_shapes(onnx.load(str(path)))
    g = model.graph
    values = {t.name: numpy_helper.to_array(t).astype(np.float32) for t in g.initializer}
    shapes = {
        v.name: tuple(d.dim_value for d in v.type.tensor_type.shape.dim)
        for v in [*g.input, *g.value_info, *g.output]
    }
    readers = Counter(i for op in g.node for i in op.input)
    alias: dict[str, str] = {}
    nodes: list[Node] = []
    producer: dict[str, Node] = {}
    structural: set[str] = set()

    def name(t: str) -> str:
        return alias.get(t, t)

    for k, op in enumerate(g.node):
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in op.attribute}
        ins, out = [name(i) for i in op.input], op.output[0]
        if op.op_type == "Transpose":
            if k not in (0, len(g.node) - 1):
                raise ValueError(f"{path}: node {k}: a transpose inside the graph")
            alias[out] = ins[0]
            continue
        if op.op_type == "Conv":
            weight = values[ins[1]]
            pads = list(attrs.get("pads", [0, 0, 0, 0]))
            strides, dilations = list(attrs["strides"]), list(attrs.get("dilations", [1, 1]))
            if len(set(pads)) != 1 or len(set(strides)) != 1 or len(set(dilations)) != 1:
                raise ValueError(f"{path}: node {k}: unequal pads, strides or dilations")
            node = Node(
                "conv",
                [ins[0]],
                out,
                {
                    "weight": weight,
                    "bias": values[ins[2]].copy(),
                    "stride": strides[0],
                    "dilation": dilations[0],
                    "groups": attrs.get("group", 1),
                    "act": "none",
                    "pad": pads[0],
                },
                [ins[1], ins[2]],
            )
        elif op.op_type in ("Clip", "Relu"):
            src = producer.get(ins[0])
            if src is None or src.kind != "conv" or src.attrs["act"] != "none":
                raise ValueError(f"{path}: node {k}: {op.op_type} after no linear convolution")
            if readers[op.input[0]] != 1:
                raise ValueError(f"{path}: node {k}: {op.op_type} of a tensor read twice")
            if op.op_type == "Clip" and (attrs.get("min"), attrs.get("max")) != (0.0, 6.0):
                raise ValueError(
                    f"{path}: node {k}: Clip to {attrs.get('min')}..{attrs.get('max')}"
                )
            src.attrs["act"] = "relu6" if op.op_type == "Clip" else "relu"
            alias[out] = src.output
            continue
        elif op.op_type == "Add":
            node = Node("add", ins, out)
        elif op.op_type == "AveragePool":
            h, w = shapes[ins[0]][2:]
            if list(attrs["kernel_shape"]) != [h, w] or any(attrs.get("pads", [0])):
                raise ValueError(f"{path}: node {k}: an average pool that is not global")
            node = Node("pool", ins, out)
        elif op.op_type == "Upsample":
            if attrs.get("mode", b"nearest") not in (b"linear", "linear"):
                raise ValueError(f"{path}: node {k}: Upsample mode {attrs.get('mode')}")
            structural.add(ins[1])
            node = Node("resize", [ins[0]], out, {"mode": "asymmetric"})
        elif op.op_type == "Concat":
            if attrs["axis"] != 1:
                raise ValueError(f"{path}: node {k}: a concatenation not on channels")
            node = Node("concat", ins, out)
        else:
            raise ValueError(f"{path}: node {k}: unsupported operator {op.op_type}")
        nodes.append(node)
        producer[out] = node
    weights = set(values) - structural
    zeros = {k for k in weights if not values[k].any()}
    return Graph(nodes, g.input[0].name, name(g.output[0].name), weights, zeros)


# ----------------------------------------------------------------------------- matching


class _Matcher:
    """Walks a :class:`Graph` in the order of the module, taking each node once."""

    def __init__(self, graph: Graph, source: str) -> None:
        self.graph, self.source = graph, source
        self.taken: set[int] = set()
        self.state: dict[str, torch.Tensor] = {}
        self.uses: Counter[str] = Counter()
        self.quantized: list[str] = []

    def _fail(self, what: str) -> ValueError:
        return ValueError(f"{self.source} does not fit DeepLab: {what}")

    def _take(self, kind: str, inputs: list[str], what: str, test=lambda n: True) -> Node:
        found = [
            n
            for n in self.graph.consumers(inputs[0])
            if n.kind == kind and id(n) not in self.taken and test(n)
        ]
        if kind in ("add", "concat"):
            found = [n for n in found if sorted(n.inputs) == sorted(inputs)]
        if len(found) != 1:
            raise self._fail(f"{len(found)} candidates for {what}")
        node = found[0]
        if kind == "concat" and node.inputs != inputs:
            raise self._fail(f"{what} concatenates in another order")
        self.taken.add(id(node))
        self.uses.update(node.weights)
        return node

    def conv(self, prefix: str, module: ConvAct, x: str) -> str:
        conv, act = module.conv, module.act
        k = conv.kernel_size[0]
        same = conv.padding[0] if conv.stride[0] == 1 else k // 2  # SAME at an odd size

        def fits(n: Node) -> bool:
            a = n.attrs
            return (
                tuple(a["weight"].shape) == tuple(conv.weight.shape)
                and (a["stride"], a["dilation"], a["groups"], a["act"])
                == (conv.stride[0], conv.dilation[0], conv.groups, act)
                and a["pad"] in ("same", same)
            )

        node = self._take("conv", [x], f"{prefix} ({tuple(conv.weight.shape)}, {act})", fits)
        self.state[f"{prefix}.conv.weight"] = torch.from_numpy(node.attrs["weight"].copy())
        self.state[f"{prefix}.conv.bias"] = torch.from_numpy(node.attrs["bias"].copy())
        if node.attrs.get("quantized"):
            self.quantized.append(prefix)
        return node.output

    def one(self, kind: str, inputs: list[str], what: str, **attrs) -> str:
        test = lambda n: all(n.attrs.get(k) == v for k, v in attrs.items())  # noqa: E731
        return self._take(kind, inputs, what, test).output


def match(
    net: DeepLab, graph: Graph, source: str = "the graph"
) -> tuple[dict[str, torch.Tensor], list[str]]:
    """The state dict of ``net`` read from ``graph`` by structure (see the module doc), and
    the names of the convolutions whose input the original runtime quantizes (int8 weights
    read as they are: the module's ``quantized`` config).

    Raises:
        ValueError: the graph does not have the module's structure, or leaves a node or a
            weight unused, or uses a weight twice.
    """
    m = _Matcher(graph, source)
    x = m.conv("backbone.stem", net.backbone.stem, graph.input)
    low = None
    for i, block in enumerate(net.backbone.blocks):
        p = f"backbone.blocks.{i}"
        h = m.conv(f"{p}.expand", block.expand, x) if block.expand is not None else x
        d = m.conv(f"{p}.depthwise", block.depthwise, h)
        low = d if i == 2 else low
        y = m.conv(f"{p}.project", block.project, d)
        x = m.one("add", [y, x], f"{p}'s residual add") if block.residual else y
    pooled = m.one("pool", [x], "the image pooling")
    pooled = m.one("resize", [m.conv("aspp.pool", net.aspp.pool, pooled)], "the pooled resize")
    branch = m.conv("aspp.branch", net.aspp.branch, x)
    y = m.conv("aspp.project", net.aspp.project, m.one("concat", [pooled, branch], "the ASPP"))
    if net.decoder is not None:
        dec = net.decoder
        up = m.one("resize", [y], "the decoder's resize", mode="align_corners")
        y = m.one("concat", [up, m.conv("decoder.low", dec.low, low)], "the decoder's concat")
        for part in ("depthwise0", "pointwise0", "depthwise1", "pointwise1"):
            y = m.conv(f"decoder.{part}", getattr(dec, part), y)
    y = m.one("resize", [m.conv("logits", net.logits, y)], "the logits' resize", mode=net.resize)
    if y != graph.output:
        raise m._fail("the logits' resize is not the graph's output")
    left = [n.kind for n in graph.nodes if id(n) not in m.taken]
    if left:
        raise m._fail(f"{len(left)} nodes left unused: {Counter(left)}")
    # a constant that several nodes read is allowed only as a zero bias
    twice = {k for k, v in m.uses.items() if v > 1} - graph.zeros
    unused = graph.constants - set(m.uses)
    if unused or twice:
        raise m._fail(f"{len(unused)} weights unused, {len(twice)} used more than once")
    own = set(net.state_dict())
    if set(m.state) != own:
        raise m._fail(f"state dict keys differ: {sorted(own ^ set(m.state))[:4]}")
    return m.state, m.quantized


def convert(src: Path, out_dir: Path) -> list[Path]:
    """Write ``teacher_deeplab_ade20k.pt`` and ``teacher_deeplab_voc.pt`` into ``out_dir``
    from the teachers folder ``src``; returns their paths."""
    src, out_dir = Path(src), Path(out_dir)
    written = []
    for name, path, read in ((ADE20K, ADE_FILE, read_tflite), (VOC, VOC_FILE, read_onnx)):
        state, quantized = match(DeepLab(**CONFIGS[name]), read(src / path), path)
        config = {**CONFIGS[name], "quantized": quantized}
        target = out_dir / teacher_path(name).name
        written.append(save_teacher(target, name, config, state, DTYPES[name]))
    return written


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m d2f_core.train.port_deeplab",
        description="convert the DeepLab teachers (ADE20K TFLite, VOC ONNX) to torch weights",
    )
    p.add_argument("src", type=Path, help="teachers folder (e.g. ../shared/datasets/teachers)")
    p.add_argument("out", type=Path, help="folder for teacher_deeplab_*.pt")
    args = p.parse_args(argv)
    for path in convert(args.src, args.out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
