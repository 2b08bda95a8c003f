"""Tiny ONNX graphs built with onnx.helper, for the partitioner, the split runtime, the profiler,
the robot and the CLI tests."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
# A conservative IR version every supported onnxruntime reads (onnx stamps its newest by default).
IR_VERSION = 10


def vi(name: str, shape: Sequence[int | str], elem: int = TensorProto.FLOAT) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, elem, list(shape))


def make_model(
    nodes: Sequence[onnx.NodeProto],
    inputs: Sequence[onnx.ValueInfoProto],
    outputs: Sequence[onnx.ValueInfoProto],
    initializers: Sequence[onnx.TensorProto] = (),
    opset: int = OPSET,
    ir_version: int = IR_VERSION,
) -> onnx.ModelProto:
    graph = helper.make_graph(list(nodes), "g", list(inputs), list(outputs), list(initializers))
    return helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=ir_version
    )


def save(model: onnx.ModelProto, path: Path) -> Path:
    path.write_bytes(model.SerializeToString())
    return path


def node(op: str, ins: Sequence[str], outs: Sequence[str], **attrs: Any) -> onnx.NodeProto:
    return helper.make_node(op, list(ins), list(outs), name=outs[0], **attrs)


def chain() -> onnx.ModelProto:
    """x → Relu → Neg → Add(constant) → y; the Constant node is never a cut position."""
    k = numpy_helper.from_array(np.full((1, 4), 0.5, np.float32), "k")
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["a"], ["b"]),
            helper.make_node("Constant", [], ["k"], value=k),
            node("Add", ["b", "k"], ["y"]),
        ],
        [vi("x", [1, 4])],
        [vi("y", [1, 4])],
    )


def diamond() -> onnx.ModelProto:
    """x → a; a → b and a → c; b + c → y."""
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["a"], ["b"]),
            node("Abs", ["a"], ["c"]),
            node("Add", ["b", "c"], ["y"]),
        ],
        [vi("x", [1, 4])],
        [vi("y", [1, 4])],
    )


def residual() -> onnx.ModelProto:
    """A residual block: a skips over b, c and is added back in d."""
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["a"], ["b"]),
            node("Abs", ["b"], ["c"]),
            node("Add", ["a", "c"], ["d"]),
            node("Relu", ["d"], ["y"]),
        ],
        [vi("x", [1, 4])],
        [vi("y", [1, 4])],
    )


def two_inputs() -> onnx.ModelProto:
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["z"], ["b"]),
            node("Add", ["a", "b"], ["c"]),
            node("Abs", ["c"], ["y"]),
        ],
        [vi("x", [1, 4]), vi("z", [1, 4])],
        [vi("y", [1, 4])],
    )


def two_outputs() -> onnx.ModelProto:
    """y1 is ready early and must still reach the end (the suffix passes it through)."""
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["a"], ["y1"]),
            node("Abs", ["a"], ["c"]),
            node("Sigmoid", ["c"], ["y2"]),
        ],
        [vi("x", [1, 4])],
        [vi("y1", [1, 4]), vi("y2", [1, 4])],
    )


def late_input() -> onnx.ModelProto:
    """Input z is only used by the last node: every cut carries it."""
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            node("Neg", ["a"], ["b"]),
            node("Add", ["b", "z"], ["y"]),
        ],
        [vi("x", [1, 4]), vi("z", [1, 4])],
        [vi("y", [1, 4])],
    )


def with_if() -> onnx.ModelProto:
    """An If node whose branches read the outer tensor a (implicit inputs)."""
    then_g = helper.make_graph(
        [helper.make_node("Neg", ["a"], ["t_out"], name="t_out")], "then", [], [vi("t_out", [1, 4])]
    )
    else_g = helper.make_graph(
        [helper.make_node("Abs", ["a"], ["e_out"], name="e_out")], "else", [], [vi("e_out", [1, 4])]
    )
    return make_model(
        [
            node("Relu", ["x"], ["a"]),
            helper.make_node(
                "If", ["flag"], ["r"], name="branch", then_branch=then_g, else_branch=else_g
            ),
            node("Sigmoid", ["r"], ["y"]),
        ],
        [vi("x", [1, 4]), vi("flag", [], TensorProto.BOOL)],
        [vi("y", [1, 4])],
    )


def matmul_chain(
    layers: int, dim: int, out_dim: int | None = None, seed: int = 0
) -> onnx.ModelProto:
    """x[1,dim] → (MatMul → Relu) × layers; the last MatMul maps to out_dim (default dim)."""
    rng = np.random.default_rng(seed)
    nodes, inits = [], []
    prev = "x"
    for i in range(layers):
        cols = out_dim if (out_dim and i == layers - 1) else dim
        w = (rng.standard_normal((dim, cols)) / np.sqrt(dim)).astype(np.float32)
        inits.append(numpy_helper.from_array(w, f"W{i}"))
        nodes.append(node("MatMul", [prev, f"W{i}"], [f"m{i}"]))
        if i < layers - 1:
            nodes.append(node("Relu", [f"m{i}"], [f"r{i}"]))
            prev = f"r{i}"
    last = nodes[-1].output[0]
    nodes.append(node("Identity", [last], ["y"]))
    cols = out_dim or dim
    return make_model(nodes, [vi("x", [1, dim])], [vi("y", [1, cols])], inits)


def dynamic(dims: Sequence[int | str]) -> onnx.ModelProto:
    return make_model(
        [node("Relu", ["x"], ["a"]), node("Neg", ["a"], ["y"])], [vi("x", dims)], [vi("y", dims)]
    )


def camera_classifier(height: int = 16, width: int = 16, classes: int = 4) -> onnx.ModelProto:
    """image uint8[1,H,W,3] (the camera image) → Cast → Transpose → Conv → Relu →
    GlobalAveragePool → Flatten → Gemm → logits[1,classes]: cut 0 carries the camera image,
    so the image codecs (PNG, JPEG) apply there."""
    rng = np.random.default_rng(0)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array((rng.standard_normal(shape) * 0.3).astype(np.float32), name)

    return make_model(
        [
            node("Cast", ["image"], ["f"], to=TensorProto.FLOAT),
            node("Transpose", ["f"], ["t"], perm=[0, 3, 1, 2]),
            node("Conv", ["t", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
            node("Relu", ["c1"], ["r1"]),
            node("GlobalAveragePool", ["r1"], ["g"]),
            node("Flatten", ["g"], ["v"]),
            node("Gemm", ["v", "w2", "b2"], ["logits"]),
        ],
        [vi("image", [1, height, width, 3], TensorProto.UINT8)],
        [vi("logits", [1, classes])],
        [
            weight("w1", (4, 3, 3, 3)),
            weight("b1", (4,)),
            weight("w2", (4, classes)),
            weight("b2", (classes,)),
        ],
    )
