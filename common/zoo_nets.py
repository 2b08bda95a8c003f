"""The zoo's CNNs as ONNX graphs written with ``onnx.helper``, with seeded weights (no torch).

:func:`build_network` returns the model and the seeded layers it was made from. The graphs are
node for node what the torch modules these networks were first written as exported to (opset 17,
TorchScript exporter, constant folding on), so the partitioner finds the same cuts:

- the front end (:func:`front_end`): Cast to float, [Gather: BGR → RGB], Mul by 1/(255·std),
  Sub mean/std, Transpose NHWC → NCHW;
- every convolution is followed by a batch normalization, folded into the convolution's weights
  and bias (one ``Conv`` node with a bias, as the exporter writes it), then ``Relu`` or ``Clip``
  (0, 6) for ReLU6;
- skip connections are ``Add`` nodes (residual branch first, then the skip, as the exporter
  wrote them); a strided basic block's 1×1 downsampling convolution comes before the block's
  first convolution (it ran first in the torch block's forward);
- the head is ``GlobalAveragePool``, ``Flatten`` (axis 1) and ``Gemm`` (transB = 1) writing
  ``logits``.

``benchmarks/zoo_vs_torch.py`` holds the torch definitions and checks the two against each other
(outputs with the same weights, cuts, tensor shapes, FLOPs, parameter counts); figures in
docs/partitioning.md. The ReLU6 bounds are two shared initializers, where the exporter wrote two
``Constant`` nodes per ``Clip``: constants never cross a cut, so the cuts are the same.

Weights: He (fan-out) initialisation for the convolutions, batch-norm statistics drawn at random
(scale 0.5..1, shift ±0.1, running mean ±0.1, running variance 0.5..2) so that the folded weights
are not plain He weights, and a small classifier (standard deviation 0.01, zero bias) that keeps
the logits near unit scale, so the partitioner's verification at 1e-5 means something. All are
uniform draws from one PCG64 stream seeded with the zoo seed, turned into floats with exact or
correctly rounded IEEE operations only (shift, scale by a power of two, multiply, add, sqrt,
divide, round to float32): the same name, shape and seed give the same bytes on every platform
and NumPy version (NumPy promises its bit generators' streams, not its distributions').
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from common.zoo_format import (
    CAMERA_ORDER,
    NUM_CLASSES,
    PIXEL_MAX,
    ZOO_INPUT_NAME,
    ZOO_OPSET,
    ZOO_OUTPUT_NAME,
    ZOO_SEED,
    file_input_shape,
    zoo_normalization,
)

# The IR version released with opset 17 (onnx 1.12), the one the torch exporter wrote: helper
# would stamp the newest this onnx knows, which older runtimes refuse.
IR_VERSION = 8
PRODUCER = "elasticfog.zoo"
# torch's BatchNorm2d default.
BN_EPS = 1e-5
RELU6_MAX = 6.0
# Seeded batch-norm parameters and statistics: (low, high) of the uniform draws.
BN_SCALE_RANGE = (0.5, 1.0)
BN_SHIFT_RANGE = (-0.1, 0.1)
BN_MEAN_RANGE = (-0.1, 0.1)
BN_VAR_RANGE = (0.5, 2.0)
# Standard deviation of the classifier's weights.
LINEAR_STD = 0.01
# 53 random bits per double in [0, 1): exactly representable, as NumPy's Generator.random does.
_MANTISSA_SHIFT = np.uint64(11)
_TWO_POW_MINUS_53 = 2.0**-53


class LayerKind(str, Enum):
    """What a seeded layer holds."""

    CONV_BN = "conv_bn"  # weight, bn_weight, bn_bias, bn_mean, bn_var (folded into one Conv)
    LINEAR = "linear"  # weight (out × in), bias


class Act(str, Enum):
    """The activation after a convolution."""

    NONE = "none"
    RELU = "relu"
    RELU6 = "relu6"


# The running statistics are buffers, not parameters: torch's parameter count leaves them out.
_BUFFERS = ("bn_mean", "bn_var")


@dataclass(frozen=True)
class SeededLayer:
    """One layer's weights before batch-norm folding, under the name of its node in the graph
    (the Conv or Gemm): what another framework needs to compute the same network."""

    kind: LayerKind
    name: str
    params: dict[str, np.ndarray]

    @property
    def parameter_count(self) -> int:
        """Learned parameters, batch-norm scale and shift included, running statistics not."""
        return sum(a.size for k, a in self.params.items() if k not in _BUFFERS)


class SeededStream:
    """Uniform float32 draws from a PCG64 stream, bit for bit the same on every platform."""

    def __init__(self, seed: int) -> None:
        self._bits = np.random.PCG64(seed)

    def uniform(self, low: float, high: float, shape: Sequence[int]) -> np.ndarray:
        count = math.prod(shape)
        raw = self._bits.random_raw(count) if count else np.zeros(0, np.uint64)
        unit = (np.asarray(raw, np.uint64) >> _MANTISSA_SHIFT).astype(np.float64)
        unit *= _TWO_POW_MINUS_53
        return (low + (high - low) * unit).astype(np.float32).reshape(tuple(shape))


class NetBuilder:
    """Nodes, initializers and seeded layers of one graph; each node's output tensor has the
    node's name."""

    def __init__(self, seed: int = ZOO_SEED) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.layers: list[SeededLayer] = []
        self.stream = SeededStream(seed)
        self._names: set[str] = set()

    # -- writing --

    def const(self, name: str, array: np.ndarray) -> str:
        """An initializer (written once under ``name``)."""
        if name not in self._names:
            self._names.add(name)
            self.initializers.append(numpy_helper.from_array(np.ascontiguousarray(array), name))
        return name

    def node(self, op_type: str, inputs: Sequence[str], name: str, **attrs: Any) -> str:
        if name in self._names:
            raise ValueError(f"tensor name {name!r} used twice")
        self._names.add(name)
        self.nodes.append(helper.make_node(op_type, list(inputs), [name], name=name, **attrs))
        return name

    # -- layers --

    def front_end(self, image: str, channels: int, order: str = CAMERA_ORDER) -> str:
        """uint8 N×H×W×C camera image → normalized float N×C×H×W.

        (x/255 − mean)/std is computed as x·(1/(255·std)) − mean/std: one Mul and one Sub per
        value. A BGR camera order adds the reorder (a Gather) after the cast, so that no cut but
        cut 0 carries uint8 levels.
        """
        mean, std = zoo_normalization(channels)
        scale = np.asarray([1.0 / (PIXEL_MAX * s) for s in std], np.float32).reshape(1, 1, 1, -1)
        offset = np.asarray([m / s for m, s in zip(mean, std, strict=True)], np.float32).reshape(
            1, 1, 1, -1
        )
        x = self.node("Cast", [image], "front.float", to=TensorProto.FLOAT)
        if order == "bgr" and channels == 3:
            index = self.const("front.rgb_index", np.asarray([2, 1, 0], np.int64))
            x = self.node("Gather", [x, index], "front.rgb", axis=3)
        x = self.node("Mul", [x, self.const("front.scale", scale)], "front.scaled")
        x = self.node("Sub", [x, self.const("front.offset", offset)], "front.normalized")
        return self.node("Transpose", [x], "front.nchw", perm=[0, 3, 1, 2])

    def conv_bn(
        self,
        x: str,
        name: str,
        cin: int,
        cout: int,
        kernel: int,
        stride: int = 1,
        groups: int = 1,
        act: Act = Act.RELU,
    ) -> str:
        """Convolution (no bias) + batch normalization, folded into one Conv, then ``act``;
        padding kernel // 2. The Conv is ``name``, its activation ``name.act``."""
        fan_out = cout * kernel * kernel
        bound = math.sqrt(6.0 / fan_out)  # He: std sqrt(2 / fan_out) as a uniform draw
        weight = self.stream.uniform(-bound, bound, (cout, cin // groups, kernel, kernel))
        gamma = self.stream.uniform(*BN_SCALE_RANGE, (cout,))
        beta = self.stream.uniform(*BN_SHIFT_RANGE, (cout,))
        mean = self.stream.uniform(*BN_MEAN_RANGE, (cout,))
        var = self.stream.uniform(*BN_VAR_RANGE, (cout,))
        self.layers.append(
            SeededLayer(
                LayerKind.CONV_BN,
                name,
                {
                    "weight": weight,
                    "bn_weight": gamma,
                    "bn_bias": beta,
                    "bn_mean": mean,
                    "bn_var": var,
                },
            )
        )
        # Folded in float64, rounded once to float32.
        scale = gamma.astype(np.float64) / np.sqrt(var.astype(np.float64) + BN_EPS)
        folded = (weight.astype(np.float64) * scale[:, None, None, None]).astype(np.float32)
        bias = (beta.astype(np.float64) - mean.astype(np.float64) * scale).astype(np.float32)
        pad = kernel // 2
        y = self.node(
            "Conv",
            [x, self.const(f"{name}.weight", folded), self.const(f"{name}.bias", bias)],
            name,
            group=groups,
            kernel_shape=[kernel, kernel],
            pads=[pad, pad, pad, pad],
            strides=[stride, stride],
        )
        return self.activation(y, f"{name}.act", act)

    def activation(self, x: str, name: str, act: Act) -> str:
        if act is Act.RELU:
            return self.node("Relu", [x], name)
        if act is Act.RELU6:
            low = self.const("relu6.min", np.asarray(0.0, np.float32))
            high = self.const("relu6.max", np.asarray(RELU6_MAX, np.float32))
            return self.node("Clip", [x, low, high], name)
        return x

    def max_pool(self, x: str, name: str, kernel: int, stride: int, pad: int = 0) -> str:
        return self.node(
            "MaxPool",
            [x],
            name,
            kernel_shape=[kernel, kernel],
            strides=[stride, stride],
            pads=[pad, pad, pad, pad],
        )

    def add(self, a: str, b: str, name: str) -> str:
        return self.node("Add", [a, b], name)

    def linear(self, x: str, name: str, cin: int, cout: int) -> str:
        """``Gemm`` (transB = 1) with seeded weights out × in and a zero bias."""
        bound = LINEAR_STD * math.sqrt(3.0)
        weight = self.stream.uniform(-bound, bound, (cout, cin))
        bias = np.zeros(cout, np.float32)
        self.layers.append(SeededLayer(LayerKind.LINEAR, name, {"weight": weight, "bias": bias}))
        inputs = [x, self.const(f"{name}.weight", weight), self.const(f"{name}.bias", bias)]
        return self.node("Gemm", inputs, name, transB=1)

    def classifier(self, x: str, cin: int) -> str:
        """Global average pool, flatten, fully connected to the classes: ``logits``."""
        x = self.node("GlobalAveragePool", [x], "pool")
        x = self.node("Flatten", [x], "flatten", axis=1)
        return self.linear(x, ZOO_OUTPUT_NAME, cin, NUM_CLASSES)

    def model(
        self,
        graph_name: str,
        inputs: Sequence[onnx.ValueInfoProto],
        outputs: Sequence[onnx.ValueInfoProto],
    ) -> onnx.ModelProto:
        """The model with opset 17 and IR version 8, checked by ``onnx.checker``."""
        model = helper.make_model(
            helper.make_graph(
                self.nodes, graph_name, list(inputs), list(outputs), self.initializers
            ),
            opset_imports=[helper.make_opsetid("", ZOO_OPSET)],
            producer_name=PRODUCER,
        )
        model.ir_version = IR_VERSION
        onnx.checker.check_model(model, full_check=True)
        return model


# -- the networks: each takes the normalized NCHW image, returns the logits --


def _vgg(b: NetBuilder, x: str, cin: int) -> str:
    """A plain chain: (out channels, convolutions) per stage; each stage ends in a 2×2 max pool."""
    for s, (cout, convs) in enumerate(((16, 1), (32, 2), (64, 2), (96, 2), (128, 2)), start=1):
        for i in range(1, convs + 1):
            x = b.conv_bn(x, f"stage{s}.conv{i}", cin, cout, 3)
            cin = cout
        x = b.max_pool(x, f"stage{s}.pool", 2, 2)
    return b.classifier(x, cin)


def _basic_block(b: NetBuilder, x: str, name: str, cin: int, cout: int, stride: int) -> str:
    identity = x
    if stride != 1 or cin != cout:  # 1×1 projection, first (the torch block ran it first)
        identity = b.conv_bn(x, f"{name}.down", cin, cout, 1, stride, act=Act.NONE)
    out = b.conv_bn(x, f"{name}.conv1", cin, cout, 3, stride)
    out = b.conv_bn(out, f"{name}.conv2", cout, cout, 3, act=Act.NONE)
    return b.node("Relu", [b.add(out, identity, f"{name}.add")], f"{name}.out")


def _resnet(b: NetBuilder, x: str, cin: int, widths: tuple[int, ...] = (24, 48, 96, 160)) -> str:
    """Stem 7×7/2 + 3×3/2 max pool, two basic blocks per width (the first strided after stage 1)."""
    x = b.conv_bn(x, "stem.conv", cin, widths[0], 7, 2)
    x = b.max_pool(x, "stem.pool", 3, 2, 1)
    cin = widths[0]
    for i, width in enumerate(widths):
        for j in range(2):
            x = _basic_block(b, x, f"layer{i + 1}.{j}", cin, width, 2 if (i > 0 and j == 0) else 1)
            cin = width
    return b.classifier(x, cin)


def _resnet18(b: NetBuilder, x: str, cin: int) -> str:
    # He et al. 2016, table 1: two basic blocks per stage, widths 64-128-256-512.
    return _resnet(b, x, cin, (64, 128, 256, 512))


def _inverted_residuals(
    b: NetBuilder,
    x: str,
    cin: int,
    stem: int,
    schedule: tuple[tuple[int, int, int, int], ...],
    head: int,
    *,
    expand_at_one: bool,
) -> str:
    """A MobileNet-v2 network: 3×3/2 stem, inverted residual blocks, 1×1 head, classifier.

    ``schedule`` holds (expansion, out channels, repeats, first stride) per stage. The standard
    network has no expansion convolution where the expansion is 1; ``expand_at_one`` keeps it
    (the small ``mobilenet``).
    """
    x = b.conv_bn(x, "stem.conv", cin, stem, 3, 2, act=Act.RELU6)
    cin = stem
    n = 0
    for expand, cout, repeats, first_stride in schedule:
        for r in range(repeats):
            n += 1
            name, stride, hidden = f"block{n}", first_stride if r == 0 else 1, cin * expand
            out = x
            if expand != 1 or expand_at_one:
                out = b.conv_bn(out, f"{name}.expand", cin, hidden, 1, act=Act.RELU6)
            out = b.conv_bn(out, f"{name}.dw", hidden, hidden, 3, stride, hidden, Act.RELU6)
            out = b.conv_bn(out, f"{name}.project", hidden, cout, 1, act=Act.NONE)
            x = b.add(x, out, f"{name}.add") if stride == 1 and cin == cout else out
            cin = cout
    x = b.conv_bn(x, "head.conv", cin, head, 1, act=Act.RELU6)
    return b.classifier(x, head)


def _mobilenet(b: NetBuilder, x: str, cin: int) -> str:
    # A shortened MobileNet-v2 schedule with expansion 4 and a 256-wide head.
    schedule = ((1, 16, 1, 1), (4, 24, 2, 2), (4, 32, 2, 2), (4, 64, 2, 2), (4, 96, 1, 1))
    return _inverted_residuals(b, x, cin, 16, schedule, 256, expand_at_one=True)


def _mobilenet_v2(b: NetBuilder, x: str, cin: int) -> str:
    # Sandler et al. 2018, table 2 (width multiplier 1.0); the classifier's dropout is a no-op in
    # inference and left out.
    schedule = (
        (1, 16, 1, 1),
        (6, 24, 2, 2),
        (6, 32, 3, 2),
        (6, 64, 4, 2),
        (6, 96, 3, 1),
        (6, 160, 3, 2),
        (6, 320, 1, 1),
    )
    return _inverted_residuals(b, x, cin, 32, schedule, 1280, expand_at_one=False)


NETWORKS: dict[str, Callable[[NetBuilder, str, int], str]] = {
    "vgg": _vgg,
    "resnet": _resnet,
    "mobilenet": _mobilenet,
    "resnet18": _resnet18,
    "mobilenet_v2": _mobilenet_v2,
}


def build_network(
    name: str, shape: tuple[int, int, int], seed: int = ZOO_SEED
) -> tuple[onnx.ModelProto, list[SeededLayer]]:
    """Zoo network ``name`` for the camera image of zoo shape (C, H, W): the model (input
    ``input``, uint8 1×H×W×C; output ``logits``, float 1×1000) and its seeded layers, in node
    order."""
    b = NetBuilder(seed)
    x = b.front_end(ZOO_INPUT_NAME, shape[0])
    logits = NETWORKS[name](b, x, shape[0])
    assert logits == ZOO_OUTPUT_NAME, logits
    image = helper.make_tensor_value_info(
        ZOO_INPUT_NAME, TensorProto.UINT8, list(file_input_shape(shape))
    )
    out = helper.make_tensor_value_info(ZOO_OUTPUT_NAME, TensorProto.FLOAT, [1, NUM_CLASSES])
    return b.model(f"zoo_{name}", [image], [out]), b.layers


def front_end_model(
    channels: int, height: int, width: int, order: str = CAMERA_ORDER
) -> onnx.ModelProto:
    """The front end alone: uint8 1×H×W×C camera image → ``front.nchw``, float 1×C×H×W."""
    b = NetBuilder()
    out = b.front_end(ZOO_INPUT_NAME, channels, order)
    image = helper.make_tensor_value_info(
        ZOO_INPUT_NAME, TensorProto.UINT8, [1, height, width, channels]
    )
    nchw = helper.make_tensor_value_info(out, TensorProto.FLOAT, [1, channels, height, width])
    return b.model("zoo_front_end", [image], [nchw])
