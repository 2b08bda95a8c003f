"""Dataflow facts of a model's top-level graph, and where it can be cut.

Producers, consumers, constants and topological order; the tensors live across each position
of that order (the automatic cut candidates); and the plan of a cut: the nodes on each side,
or why a tensor set is not a cut. Names read inside control-flow subgraphs count as inputs of
the node that owns them, so a cut never passes through If/Loop/Scan.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import onnx

from common.partition.errors import CutError

# Ops whose output changes from run to run: never treated as constants.
_NONDETERMINISTIC_OPS = frozenset(
    {"RandomNormal", "RandomNormalLike", "RandomUniform", "RandomUniformLike", "Multinomial"}
)


@dataclass
class CutPlan:
    """Where one cut falls: the tensors crossing it and the nodes on each side."""

    tensors: list[str]
    prefix_nodes: set[int]
    suffix_nodes: set[int]
    prefix_inputs: list[str]
    position: int


class DataflowGraph:
    """Top-level dataflow facts of a model: producers, consumers, constants, topological order."""

    def __init__(self, model: onnx.ModelProto) -> None:
        g = model.graph
        self.nodes = list(g.node)
        self.initializers = {t.name for t in g.initializer}
        self.inputs = [vi.name for vi in g.input if vi.name not in self.initializers]
        self.input_set = set(self.inputs)
        self.outputs = [vi.name for vi in g.output]
        self.node_inputs: list[list[str]] = [_node_inputs(n) for n in self.nodes]
        self.producer: dict[str, int] = {}
        for i, node in enumerate(self.nodes):
            for out in node.output:
                if out:
                    self.producer[out] = i
        self.constant_nodes = self._constant_nodes()
        self.constants = set(self.initializers)
        for i in self.constant_nodes:
            self.constants.update(o for o in self.nodes[i].output if o)
        self.live_nodes, _ = self.closure(self.outputs, stop=set())
        # Non-constant live nodes in model order: an automatic cut falls between two of them.
        self.order = [
            i
            for i in range(len(self.nodes))
            if i in self.live_nodes and i not in self.constant_nodes
        ]
        self.position = {node: pos for pos, node in enumerate(self.order)}
        self.subgraph_tensors = self._subgraph_tensors()

    def _constant_nodes(self) -> set[int]:
        constant: set[str] = set(self.initializers)
        nodes: set[int] = set()
        for i, node in enumerate(self.nodes):
            ins = [n for n in self.node_inputs[i]]
            is_const = node.op_type == "Constant" or (
                bool(ins)
                and all(n in constant for n in ins)
                and node.op_type not in _NONDETERMINISTIC_OPS
                and node.domain in ("", "ai.onnx")
                and not _has_subgraph(node)
            )
            if is_const:
                nodes.add(i)
                constant.update(o for o in node.output if o)
        return nodes

    def _subgraph_tensors(self) -> dict[str, str]:
        owned: dict[str, str] = {}
        for i, node in enumerate(self.nodes):
            if not _has_subgraph(node):
                continue
            label = f"{node.op_type} node {node.name or f'#{i}'!r}"
            for sub in _subgraphs(node):
                for name in _defined_in(sub):
                    owned.setdefault(name, label)
        return owned

    def closure(self, targets: Iterable[str], stop: set[str]) -> tuple[set[int], set[str]]:
        """Nodes needed for ``targets``, walking back to ``stop``; and the graph inputs reached."""
        nodes: set[int] = set()
        reached: set[str] = set()
        seen: set[str] = set()
        stack = [t for t in targets if t not in stop]
        while stack:
            name = stack.pop()
            if name in seen:
                continue
            seen.add(name)
            producer = self.producer.get(name)
            if producer is None:
                if name in self.input_set:
                    reached.add(name)
                continue
            if producer in nodes:
                continue
            nodes.add(producer)
            for n in self.node_inputs[producer]:
                if n not in stop:
                    stack.append(n)
                elif n in self.input_set:
                    reached.add(n)
        return nodes, reached

    def crossing_sets(self) -> list[list[str]]:
        """For each position of :attr:`order`, the non-constant tensors live across it."""
        end = len(self.order)
        born: dict[str, int] = {name: -1 for name in self.inputs}
        last_use: dict[str, int] = {}
        for pos, i in enumerate(self.order):
            for out in self.nodes[i].output:
                if out:
                    born[out] = pos
            for name in self.node_inputs[i]:
                if name in born:
                    last_use[name] = max(last_use.get(name, -1), pos)
        for name in self.outputs:
            last_use[name] = end  # outputs must reach the end of the model
        sets: list[list[str]] = []
        for p in range(end):
            live = [t for t, b in born.items() if b < p <= last_use.get(t, -2)]
            sets.append(self.sorted_tensors(live))
        return sets

    def sorted_tensors(self, names: Iterable[str]) -> list[str]:
        """Model inputs first (in input order), then by producing position, then by name."""

        def key(name: str) -> tuple[int, int, str]:
            if name in self.input_set:
                return (0, self.inputs.index(name), name)
            producer = self.producer.get(name)
            pos = self.position.get(producer, -1) if producer is not None else -1
            return (1, pos, name)

        return sorted(set(names), key=key)

    def plan(self, tensors: Iterable[str]) -> CutPlan:
        """Nodes on each side of the cut carried by ``tensors``; CutError if it is not a cut.

        Model inputs the suffix still needs (used late) join the cut: the robot sends them too.
        """
        cut = set(tensors)
        suffix_nodes, late_inputs = self.closure(self.outputs, stop=cut)
        cut |= late_inputs
        if not (suffix_nodes - self.constant_nodes):
            raise CutError("it is at the model outputs (everything on the robot is not a cut)")
        prefix_nodes, prefix_inputs = self.closure(cut - self.input_set, stop=self.input_set)
        both = (prefix_nodes & suffix_nodes) - self.constant_nodes
        if both:
            first = self.nodes[min(both)]
            raise CutError(
                "it does not separate the inputs from the outputs: node "
                f"{first.name or first.op_type!r} would run on both sides"
            )
        needed = set(self.outputs)
        for i in suffix_nodes:
            needed.update(self.node_inputs[i])
        unused = cut - needed
        if unused:
            raise CutError(
                f"tensor(s) {', '.join(sorted(unused))} are not used after the cut; leave them out"
            )
        positions = [self.position[i] for i in prefix_nodes if i in self.position]
        return CutPlan(
            tensors=self.sorted_tensors(cut),
            prefix_nodes=prefix_nodes,
            suffix_nodes=suffix_nodes,
            prefix_inputs=[n for n in self.inputs if n in prefix_inputs],
            position=max(positions, default=-1) + 1,
        )


def _has_subgraph(node: onnx.NodeProto) -> bool:
    return any(
        a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS) for a in node.attribute
    )


def _subgraphs(node: onnx.NodeProto) -> list[onnx.GraphProto]:
    subs: list[onnx.GraphProto] = []
    for a in node.attribute:
        if a.type == onnx.AttributeProto.GRAPH:
            subs.append(a.g)
        elif a.type == onnx.AttributeProto.GRAPHS:
            subs.extend(a.graphs)
    return subs


def _node_inputs(node: onnx.NodeProto) -> list[str]:
    """Explicit inputs plus outer-scope names read inside the node's subgraphs."""
    names = [n for n in node.input if n]
    for sub in _subgraphs(node):
        names.extend(sorted(_outer_refs(sub) - set(names)))
    return list(dict.fromkeys(names))


def _defined_in(graph: onnx.GraphProto) -> set[str]:
    """Every name a subgraph defines (its inputs, initializers, node outputs, nested too)."""
    names = {vi.name for vi in graph.input} | {t.name for t in graph.initializer}
    for node in graph.node:
        names.update(o for o in node.output if o)
        for sub in _subgraphs(node):
            names |= _defined_in(sub)
    return names


def _outer_refs(graph: onnx.GraphProto) -> set[str]:
    """Names a subgraph reads from enclosing scopes (its implicit inputs)."""
    defined = {vi.name for vi in graph.input} | {t.name for t in graph.initializer}
    refs: set[str] = set()
    for node in graph.node:
        for name in node.input:
            if name and name not in defined:
                refs.add(name)
        for sub in _subgraphs(node):
            refs |= _outer_refs(sub) - defined
        defined.update(o for o in node.output if o)
    refs.update(o.name for o in graph.output if o.name not in defined)
    return refs
