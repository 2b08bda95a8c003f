"""Which initializers may be handed, one copy, to every session (``add_initializer``).

onnxruntime's transpose optimizer (ORT_ENABLE_BASIC and up), pushing a Transpose through an op
(Mul, Add, Where, Concat, ...), transposes or unsqueezes that op's constant inputs *in place,
under their own names*; add_initializer then puts the caller's tensor back under that name, in
its original layout, once the graph is optimized: the node gets the wrong shape (ConvNeXt's
layer scale, (384,1,1) against NHWC: "BroadcastIterator::Append ... 14 by 384") or wrong
numbers. Transposes only travel downstream: from Transpose nodes, and from layout-sensitive ops
(_LAYOUT_OPS: ORT_ENABLE_ALL's NHWC layout transformation wraps some in Transposes), through
every op but _TRANSPOSE_BARRIERS. So an initializer is shared only when each of its uses is a
weight operand (_WEIGHT_INPUTS: op → input positions; the fusions that use these write new
initializers under new names or read them as they are) or an input of a node no Transpose can
reach; the others stay inline in each file that uses them. Verification checks the
shared-weight runtime against onnxruntime's own run of the full model: a miss is an error.
"""

from __future__ import annotations

from common.partition.graph import DataflowGraph

_WEIGHT_INPUTS: dict[str, frozenset[int]] = {
    "Conv": frozenset({1, 2}),
    "ConvTranspose": frozenset({1, 2}),
    "Gemm": frozenset({1, 2}),
    "MatMul": frozenset({1}),
    "BatchNormalization": frozenset({1, 2, 3, 4}),
    "InstanceNormalization": frozenset({1, 2}),
    "LayerNormalization": frozenset({1, 2}),
    "GroupNormalization": frozenset({1, 2}),
    "Gather": frozenset({0}),
    "LSTM": frozenset({1, 2, 3}),
    "GRU": frozenset({1, 2, 3}),
    "RNN": frozenset({1, 2, 3}),
}
_LAYOUT_OPS = frozenset(
    {
        "Conv", "ConvTranspose", "QLinearConv", "ConvInteger", "MaxPool", "AveragePool",
        "LpPool", "GlobalAveragePool", "GlobalMaxPool", "GlobalLpPool", "MaxUnpool",
        "BatchNormalization", "InstanceNormalization", "LRN", "Resize", "Upsample",
        "DepthToSpace", "SpaceToDepth", "GridSample", "RoiAlign", "MaxRoiPool",
    }
)  # fmt: skip
# Ops the transpose optimizer cannot push a Transpose through (none has a handler in its maps).
_TRANSPOSE_BARRIERS = frozenset(_WEIGHT_INPUTS) | {"Einsum"}
# Uses of their output count as uses of their input 0: onnxruntime removes Identity nodes, and
# its transpose optimizer looks through a DequantizeLinear to edit the initializer behind it.
_PASS_THROUGH_OPS = frozenset({"Identity", "DequantizeLinear"})


def shareable_initializers(graph: DataflowGraph) -> set[str]:
    """Initializers no onnxruntime optimization rewrites in place (see ``_WEIGHT_INPUTS``):
    each use (through ``_PASS_THROUGH_OPS`` too) is a weight operand or an input of a node
    that no Transpose can reach. These alone may be shared between sessions."""
    reached = _transpose_reachable(graph)
    uses: dict[str, list[tuple[int, int]]] = {}
    for i, node in enumerate(graph.nodes):
        for pos, name in enumerate(node.input):
            if name:
                uses.setdefault(name, []).append((i, pos))
        for name in graph.node_inputs[i]:
            if name not in node.input:
                uses.setdefault(name, []).append((i, -1))  # read inside a subgraph
    outputs = set(graph.outputs)

    def safe(name: str) -> bool:
        if name in outputs:
            return False
        for i, pos in uses.get(name, []):
            node = graph.nodes[i]
            if node.domain not in ("", "ai.onnx") or pos < 0:
                return False
            if node.op_type in _PASS_THROUGH_OPS and pos == 0:
                if not all(safe(out) for out in node.output if out):
                    return False
            elif pos in _WEIGHT_INPUTS.get(node.op_type, frozenset()):
                continue
            elif any(n in reached for n in graph.node_inputs[i]):
                return False
        return True

    return {name for name in graph.initializers if safe(name)}


def _transpose_reachable(graph: DataflowGraph) -> set[str]:
    """Tensors a Transpose may be pushed onto: outputs of Transpose nodes and of layout ops
    (``_LAYOUT_OPS``), then of every node fed by one but ``_TRANSPOSE_BARRIERS``."""
    reached: set[str] = set()
    for i, node in enumerate(graph.nodes):  # topological order
        op = node.op_type if node.domain in ("", "ai.onnx") else ""
        fed = any(n in reached for n in graph.node_inputs[i])
        if op == "Transpose" or op in _LAYOUT_OPS or (fed and op not in _TRANSPOSE_BARRIERS):
            reached.update(o for o in node.output if o)
    return reached
