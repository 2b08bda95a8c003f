"""Segments: the part of a model between two cuts, as a model of its own (segment offload).

A segment from cut ``a`` to cut ``b`` (``a < b``) takes cut ``a``'s tensors and gives cut ``b``'s:
the robot runs the prefix of ``a``, the cloud the segment, the robot the suffix of ``b``. In the
manner of ``onnx.utils.Extractor``: the nodes are those ``b``'s tensors need, walking back and
stopping at ``a``'s; the initializers those nodes use; the inputs the tensors of ``a`` they read.
A tensor that crosses both cuts (a skip over the whole segment) is not computed by the segment:
the runtime passes it through from its input, as it passes model inputs through a prefix.

:class:`SegmentWriter` plans, writes and checks (``onnx.checker``) every segment of a split's
cuts; verification against the full model is ``common.partition.verify.verify_segments``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import onnx

from common.partition.builder import SubModelBuilder
from common.partition.errors import CutError, one_line
from common.partition.graph import DataflowGraph
from common.partition.manifest import Cut, Segment, excluded_cut, segment_file_name
from common.partition.weights import save_graph


@dataclass(frozen=True)
class SegmentPlan:
    """Where one segment falls: its nodes, the cut tensors it reads and those it computes."""

    start: int
    end: int
    nodes: frozenset[int]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


def plan_segment(graph: DataflowGraph, start: Cut, end: Cut) -> SegmentPlan:
    """The segment between ``start`` and ``end``; CutError when they do not bound one."""
    given = set(start.tensors)
    computed = [t for t in end.tensors if t not in given]
    if not computed:
        raise CutError(
            f"cut {end.index} carries only tensors of cut {start.index}: nothing runs between them"
        )
    nodes, reached = graph.closure(computed, stop=given)
    outside = sorted(reached - given)
    if outside:
        raise CutError(
            f"cut {end.index} needs model input(s) {', '.join(outside)} that cut {start.index} "
            "does not carry"
        )
    before, _ = graph.closure(given - graph.input_set, stop=graph.input_set)
    both = (nodes & before) - graph.constant_nodes
    if both:
        first = graph.nodes[min(both)]
        raise CutError(
            f"cut {start.index} does not come before cut {end.index}: node "
            f"{first.name or first.op_type!r} would run on both sides"
        )
    used: set[str] = set()
    for i in nodes:
        used.update(graph.node_inputs[i])
    return SegmentPlan(
        start=start.index,
        end=end.index,
        nodes=frozenset(nodes),
        inputs=tuple(t for t in start.tensors if t in used),
        outputs=tuple(computed),
    )


class SegmentWriter:
    """Writes the segment between every two cuts of a split; the pairs that cannot be one (or
    that ``onnx.checker`` rejects) go to :attr:`excluded` with the reason."""

    def __init__(self, builder: SubModelBuilder, out_dir: Path) -> None:
        self.builder = builder
        self.out_dir = out_dir
        self.excluded: list[Cut] = []

    def write_all(self, cuts: list[Cut]) -> list[Segment]:
        segments: list[Segment] = []
        for i, start in enumerate(cuts):
            for end in cuts[i + 1 :]:
                segment = self._write(start, end)
                if segment is not None:
                    segments.append(segment)
        return segments

    def _write(self, start: Cut, end: Cut) -> Segment | None:
        path = self.out_dir / segment_file_name(start.index, end.index)
        try:
            plan = plan_segment(self.builder.graph, start, end)
            model = self.builder.build(
                f"segment_{start.index}_{end.index}", set(plan.nodes), plan.inputs, plan.outputs
            )
            save_graph(model, path)
            onnx.checker.check_model(str(path))
        except CutError as exc:
            self._exclude(start, end, str(exc))
            return None
        except Exception as exc:
            path.unlink(missing_ok=True)
            self._exclude(start, end, f"onnx.checker rejected the segment: {one_line(exc)}")
            return None
        return Segment(start.index, end.index, path, verified=False, max_abs_err=None)

    def _exclude(self, start: Cut, end: Cut, reason: str) -> None:
        self.excluded.append(
            excluded_cut(
                end.tensors, f"segment from cut {start.index} to cut {end.index}: {reason}"
            )
        )
