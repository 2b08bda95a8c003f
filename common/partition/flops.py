"""FLOPs estimate of a set of nodes (2 per multiply-add of Conv, ConvTranspose, Gemm, MatMul):
how the robot's and the cloud's share of a cut compare before anything is timed."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import numpy as np
import onnx

from common.partition.graph import DataflowGraph
from common.partition.manifest import TensorSpec

Shape = tuple[int, ...]


def flops(
    model: onnx.ModelProto,
    graph: DataflowGraph,
    specs: Mapping[str, TensorSpec | None],
    node_ids: Iterable[int],
) -> int:
    """Multiply-add FLOPs (2 per MAC) of the Conv, ConvTranspose, Gemm and MatMul nodes given."""
    init_shapes = {t.name: tuple(t.dims) for t in model.graph.initializer}

    def shape(name: str) -> Shape | None:
        spec = specs.get(name)
        if spec is not None:
            return spec.shape
        return init_shapes.get(name)

    total = 0
    for i in node_ids:
        node = graph.nodes[i]
        try:
            total += _node_flops(node, shape)
        except (TypeError, IndexError, ValueError):
            continue  # shapes we cannot read count as zero; this is an estimate
    return total


def _node_flops(node: onnx.NodeProto, shape: Callable[[str], Shape | None]) -> int:
    op = node.op_type
    if op not in ("Conv", "ConvTranspose", "Gemm", "MatMul") or node.domain not in ("", "ai.onnx"):
        return 0
    a, w = (shape(n) for n in node.input[:2])
    out = shape(node.output[0])
    if a is None or w is None or out is None:
        return 0
    if op == "Conv":
        # out: (N, Cout, *spatial); w: (Cout, Cin/group, *kernel)
        return 2 * int(np.prod(out, dtype=np.int64)) * int(np.prod(w[1:], dtype=np.int64))
    if op == "ConvTranspose":
        # every input element meets a (Cout/group, *kernel) slice of the weights
        return 2 * int(np.prod(a, dtype=np.int64)) * int(np.prod(w[1:], dtype=np.int64))
    if op == "Gemm":
        trans_a = any(at.name == "transA" and at.i for at in node.attribute)
        k = a[0] if trans_a else a[1]
        return 2 * int(np.prod(out, dtype=np.int64)) * int(k)
    return 2 * int(np.prod(out, dtype=np.int64)) * int(a[-1])  # MatMul
