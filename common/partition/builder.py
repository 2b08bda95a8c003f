"""Sub-models of a split: a prefix, suffix or segment built from a node set, with the used
initializers (big shared ones as references into weights.bin) and typed boundary tensors."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import onnx
from onnx import helper

from common.partition.errors import CutError
from common.partition.graph import DataflowGraph
from common.partition.manifest import TensorSpec


class SubModelBuilder:
    """Builds a sub-model from a node set: reachable nodes, used initializers, typed boundaries."""

    def __init__(
        self,
        model: onnx.ModelProto,
        graph: DataflowGraph,
        specs: Mapping[str, TensorSpec | None],
        external: Mapping[str, onnx.TensorProto],
    ) -> None:
        self.model = model
        self.graph = graph
        self.specs = specs
        self.external = external
        self.inline = {t.name: t for t in model.graph.initializer}

    def build(
        self, name: str, node_ids: set[int], inputs: Sequence[str], outputs: Sequence[str]
    ) -> onnx.ModelProto:
        nodes = [self.graph.nodes[i] for i in sorted(node_ids)]
        used: set[str] = set()
        for i in node_ids:
            used.update(self.graph.node_inputs[i])
        inits = [self.external.get(t, self.inline[t]) for t in self.inline if t in used]
        g = helper.make_graph(
            nodes,
            name,
            [self._spec(n).value_info() for n in inputs],
            [self._spec(n).value_info() for n in outputs],
            inits,
        )
        sub = helper.make_model(
            g,
            opset_imports=list(self.model.opset_import),
            ir_version=self.model.ir_version,
            producer_name="elasticfog",
        )
        sub.functions.extend(self.model.functions)
        return sub

    def _spec(self, name: str) -> TensorSpec:
        spec = self.specs.get(name)
        if spec is None:
            raise CutError(f"{name!r} is not a tensor")
        return spec
