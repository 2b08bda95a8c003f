"""Candidate cuts: the tensor sets to split at (automatic, or named by the user and validated up
front), each planned on the graph, measured (bytes, FLOPs on each side) and, for automatic cuts,
pruned when another cut beats it. Sets that are not usable are kept with the reason why."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import onnx

from common.errors import UserError
from common.partition.errors import CutError, OptionError
from common.partition.flops import flops
from common.partition.graph import CutPlan, DataflowGraph
from common.partition.manifest import Cut, TensorSpec, excluded_cut
from common.partition.options import CUT_SEPARATOR

# Reason given for automatic cuts left out because another cut beats them (the CLI counts them).
DOMINATED_PREFIX = "dominated by "
_CONTROL_FLOW_OPS = frozenset({"If", "Loop", "Scan"})


@dataclass
class Candidate:
    """A planned cut on its way to the split: its files once written, and why it was dropped."""

    plan: CutPlan
    prefix: Path | None = None
    suffix: Path | None = None
    reason: str = ""
    max_abs_err: float | None = None
    prefix_flops: int = 0
    suffix_flops: int = 0
    bytes: int = 0


class CutCollector:
    """Chooses the candidate cuts of one model; what it leaves out goes to :attr:`excluded`.

    ``cuts`` is ``"auto"`` or the user's cuts (each a tensor name or several joined with ``+``);
    ``spec`` names the model in errors.
    """

    def __init__(self, cuts: str | list[str], max_cut_tensors: int, spec: str) -> None:
        self.cuts = cuts
        self.max_cut_tensors = max_cut_tensors
        self.spec = spec
        self.excluded: list[Cut] = []

    def collect(
        self, graph: DataflowGraph, specs: Mapping[str, TensorSpec | None]
    ) -> list[Candidate]:
        """Candidate tensor sets, planned; cut 0 (the inputs) first."""
        if not graph.order:
            raise UserError(f"{self.spec} has no operators to split")
        sets: list[list[str]]
        if self.cuts == "auto":
            crossing = graph.crossing_sets()
            sets = [crossing[0]] + [s for s in crossing[1:] if len(s) <= self.max_cut_tensors]
            for i, node in enumerate(graph.nodes):
                if node.op_type in _CONTROL_FLOW_OPS and i in graph.live_nodes:
                    self.excluded.append(
                        excluded_cut(
                            [],
                            f"{node.op_type} node {node.name or f'#{i}'!r} runs as a whole: "
                            "no cut inside its subgraphs",
                        )
                    )
        else:
            sets = [graph.crossing_sets()[0], *self._user_sets(graph)]
        candidates: list[Candidate] = []
        seen: set[frozenset[str]] = set()
        for tensors in sets:
            try:
                plan = graph.plan(tensors)
            except CutError as exc:
                if self.cuts == "auto":
                    self.excluded.append(excluded_cut(tensors, str(exc)))
                    continue
                shown = CUT_SEPARATOR.join(tensors)
                raise UserError(f"cut {shown!r} is not usable: {exc}") from None
            key = frozenset(plan.tensors)
            if key in seen:
                continue
            seen.add(key)
            not_tensors = [t for t in plan.tensors if specs.get(t) is None]
            cand = Candidate(plan)
            if not_tensors:
                cand.reason = f"{', '.join(not_tensors)} is not a tensor (sequence or map)"
            candidates.append(cand)
        candidates.sort(key=lambda c: c.plan.position)
        return candidates

    @staticmethod
    def measure(
        candidates: list[Candidate],
        model: onnx.ModelProto,
        graph: DataflowGraph,
        specs: Mapping[str, TensorSpec | None],
    ) -> None:
        """Fill in each candidate's FLOPs on both sides and the bytes crossing it."""
        for cand in candidates:
            cand.prefix_flops = flops(model, graph, specs, cand.plan.prefix_nodes)
            cand.suffix_flops = flops(model, graph, specs, cand.plan.suffix_nodes)
            cand.bytes = sum(s.nbytes for t in cand.plan.tensors if (s := specs.get(t)))

    def prune(self, candidates: list[Candidate]) -> list[Candidate]:
        """Drop cuts another cut beats: same robot-side FLOPs, fewer bytes (or as few, later).

        Such a cut only moves a cheap op (ReLU, pooling) across the link, e.g. the output of a
        convolution before its max pool. Cut 0 always stays. Without any FLOPs to compare (graphs
        with no Conv/Gemm/MatMul) nothing is pruned.
        """
        if not any(c.prefix_flops or c.suffix_flops for c in candidates):
            return candidates
        best: dict[int, Candidate] = {}
        # Cut 0 competes too: a cut that only converts the input (e.g. a uint8 camera image cast
        # to float) sends more bytes for no FLOPs on the robot.
        for cand in candidates:
            if cand.reason:
                continue
            held = best.get(cand.prefix_flops)
            if held is None or cand.bytes <= held.bytes:
                best[cand.prefix_flops] = cand
        kept = []
        for n, cand in enumerate(candidates):
            winner = best.get(cand.prefix_flops)
            if n == 0 or cand.reason or winner is None or winner is cand:
                kept.append(cand)
            else:
                shown = CUT_SEPARATOR.join(winner.plan.tensors)
                self.excluded.append(
                    excluded_cut(
                        cand.plan.tensors,
                        f"{DOMINATED_PREFIX}{shown} "
                        f"({winner.bytes} bytes for the same FLOPs on the robot)",
                    )
                )
        return kept

    def _user_sets(self, graph: DataflowGraph) -> list[list[str]]:
        """Tensor sets named by the user, names validated up front (the bad ones listed)."""
        assert self.cuts != "auto"
        groups = [[t.strip() for t in item.split(CUT_SEPARATOR)] for item in self.cuts]
        known = set(graph.producer) | graph.input_set
        unknown: list[str] = []
        constants: list[str] = []
        for group in groups:
            for name in group:
                if name in graph.constants:
                    constants.append(name)
                elif name not in known and name not in graph.subgraph_tensors:
                    unknown.append(name)
        if unknown:
            raise OptionError(
                "cuts",
                "unknown tensor name(s) in {option}: {names}",
                names=", ".join(dict.fromkeys(unknown)),
            )
        if constants:
            raise UserError(
                "constant tensor(s) cannot be cut (they are weights, not activations): "
                + ", ".join(dict.fromkeys(constants))
            )
        sets = []
        for group in groups:
            inside = [n for n in group if n in graph.subgraph_tensors and n not in known]
            if inside:
                owner = graph.subgraph_tensors[inside[0]]
                self.excluded.append(
                    excluded_cut(
                        group,
                        f"{', '.join(inside)} is inside the subgraph of {owner}: "
                        "cuts do not pass through control flow",
                    )
                )
                continue
            sets.append(group)
        return sets
