"""The ONNX partitioner: find where a model can be cut, write prefix/suffix models, verify them.

A cut is a set of tensors that separates the model's inputs from its outputs: the robot computes
them with the *prefix* model (inputs → cut tensors) and the cloud finishes with the *suffix* model
(cut tensors → outputs). Candidates are positions in the model's topological order where few live
non-constant tensors cross (one in a chain; every crossing tensor in a DAG with skips). Cut 0 is
the model inputs (full offload); "everything on the robot" is not a cut.

Stages, one private step each (in the manner of ``onnx.utils.Extractor``): load and check the
model, fix its input shapes, probe every tensor's dtype and shape with one onnxruntime run, collect
the cut tensor sets, plan each cut (reachable nodes on both sides, late-used inputs), write the
sub-models (weights stored once in ``weights.bin`` and referenced as external data), check them
with ``onnx.checker``, and verify prefix∘suffix against the full model on seeded random input.

A split directory holds ``manifest.json`` (the CLI contract), ``full.onnx``, ``weights.bin`` and
``cutNNN.prefix.onnx`` / ``cutNNN.suffix.onnx``. :func:`load_partition` keeps one per model digest
and options in the cache directory so daemons start without splitting again.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper, numpy_helper

from common.errors import UserError
from common.models import ZOO_PREFIX, ModelRef, cache_dir, resolve_model

MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.bin"
FULL_NAME = "full.onnx"
MANIFEST_FORMAT = 1
DEFAULT_MAX_CUT_TENSORS = 2
# Verification tolerance: absolute, for float32 outputs; float16 gets a looser one.
FLOAT32_ATOL = 1e-5
FLOAT16_ATOL = 1e-3
VERIFY_SEED = 0
# Initializers at least this big go to weights.bin (shared by every sub-model); smaller ones
# (shape constants, scalars) stay inline, where duplication costs nothing.
EXTERNAL_MIN_BYTES = 1024
WEIGHT_ALIGN_BYTES = 64
# Constant nodes with a tensor this big become initializers, so that weights among them are shared.
CONSTANT_TO_INITIALIZER_BYTES = 1024
# Which initializers go there, one copy handed to every session (SessionOptions.add_initializer).
# onnxruntime's transpose optimizer (ORT_ENABLE_BASIC and up), pushing a Transpose through an op
# (Mul, Add, Where, Concat, ...), transposes or unsqueezes that op's constant inputs *in place,
# under their own names*; add_initializer then puts the caller's tensor back under that name, in
# its original layout, once the graph is optimized: the node gets the wrong shape (ConvNeXt's
# layer scale, (384,1,1) against NHWC: "BroadcastIterator::Append ... 14 by 384") or wrong
# numbers. Transposes only travel downstream: from Transpose nodes, and from layout-sensitive ops
# (_LAYOUT_OPS: ORT_ENABLE_ALL's NHWC layout transformation wraps some in Transposes), through
# every op but _TRANSPOSE_BARRIERS. So an initializer is shared only when each of its uses is a
# weight operand (_WEIGHT_INPUTS: op → input positions; the fusions that use these write new
# initializers under new names or read them as they are) or an input of a node no Transpose can
# reach; the others stay inline in each file that uses them. Verification checks the
# shared-weight runtime against onnxruntime's own run of the full model: a miss is an error.
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
CUT_SEPARATOR = "+"
# Reason given for automatic cuts left out because another cut beats them (the CLI counts them).
DOMINATED_PREFIX = "dominated by "
_CONTROL_FLOW_OPS = frozenset({"If", "Loop", "Scan"})
# Ops whose output changes from run to run: never treated as constants.
_NONDETERMINISTIC_OPS = frozenset(
    {"RandomNormal", "RandomNormalLike", "RandomUniform", "RandomUniformLike", "Multinomial"}
)
_MAX_REASON_CHARS = 300


class CutError(Exception):
    """A tensor set is not a usable cut; the message says why."""


@dataclass(frozen=True)
class TensorSpec:
    """Name, numpy dtype name and static shape of one tensor (what the cloud validates)."""

    name: str
    dtype: str
    shape: tuple[int, ...]

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize

    def to_json(self) -> dict[str, Any]:
        return {"dtype": self.dtype, "shape": list(self.shape)}

    def value_info(self) -> onnx.ValueInfoProto:
        elem = helper.np_dtype_to_tensor_dtype(np.dtype(self.dtype))
        return helper.make_tensor_value_info(self.name, elem, list(self.shape))


@dataclass
class Cut:
    """One cut: the tensors crossing it, their bytes, and its prefix/suffix model files.

    ``prefix`` is None for cut 0 (the robot sends its inputs as they are). Excluded cuts have
    ``index == -1``, no files, and ``reason`` saying why.
    """

    index: int
    tensors: list[str]
    bytes: int
    prefix: Path | None
    suffix: Path | None
    verified: bool
    max_abs_err: float | None
    prefix_flops: int = 0
    suffix_flops: int = 0
    reason: str = ""


@dataclass
class Partition:
    """A split model on disk: the manifest's content with absolute paths."""

    dir: Path
    model: str
    digest: str
    inputs: list[str]
    outputs: list[str]
    specs: dict[str, TensorSpec]
    cuts: list[Cut]
    excluded: list[Cut] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def full(self) -> Path:
        return self.dir / FULL_NAME

    @property
    def weights(self) -> Path:
        return self.dir / WEIGHTS_NAME

    def cut(self, index: int) -> Cut:
        """Cut ``index``; ValueError naming the valid range otherwise."""
        if not 0 <= index < len(self.cuts):
            raise ValueError(f"unknown cut {index}: this model has cuts 0..{len(self.cuts) - 1}")
        return self.cuts[index]

    def cut_specs(self, index: int) -> list[TensorSpec]:
        return [self.specs[name] for name in self.cut(index).tensors]

    def manifest(self) -> dict[str, Any]:
        """The manifest.json content (the CLI contract), paths relative to the split directory."""

        def rel(p: Path | None) -> str | None:
            return None if p is None else p.relative_to(self.dir).as_posix()

        return {
            "format": MANIFEST_FORMAT,
            "model": self.model,
            "digest": self.digest,
            "inputs": list(self.inputs),
            "outputs": list(self.outputs),
            "cuts": [
                {
                    "index": c.index,
                    "tensors": list(c.tensors),
                    "bytes": c.bytes,
                    "prefix": rel(c.prefix),
                    "suffix": rel(c.suffix),
                    "verified": c.verified,
                    "max_abs_err": c.max_abs_err,
                    "prefix_flops": c.prefix_flops,
                    "suffix_flops": c.suffix_flops,
                }
                for c in self.cuts
            ],
            "excluded": [{"tensors": list(c.tensors), "reason": c.reason} for c in self.excluded],
            "specs": {name: spec.to_json() for name, spec in self.specs.items()},
            "full": FULL_NAME,
            "weights": WEIGHTS_NAME,
            "options": dict(self.options),
        }

    @classmethod
    def load(cls, directory: Path) -> Partition:
        """Read ``directory/manifest.json``; UserError if it is missing or not ours."""
        directory = Path(directory)
        path = directory / MANIFEST_NAME
        try:
            data = json.loads(path.read_text())
            if data.get("format") != MANIFEST_FORMAT:
                raise UserError(f"{path}: unsupported manifest format {data.get('format')!r}")
            specs = {
                name: TensorSpec(name, str(s["dtype"]), tuple(int(d) for d in s["shape"]))
                for name, s in data["specs"].items()
            }
            cuts = [
                Cut(
                    index=int(c["index"]),
                    tensors=[str(t) for t in c["tensors"]],
                    bytes=int(c["bytes"]),
                    prefix=None if c["prefix"] is None else directory / c["prefix"],
                    suffix=directory / c["suffix"],
                    verified=bool(c["verified"]),
                    max_abs_err=None if c["max_abs_err"] is None else float(c["max_abs_err"]),
                    prefix_flops=int(c.get("prefix_flops", 0)),
                    suffix_flops=int(c.get("suffix_flops", 0)),
                )
                for c in data["cuts"]
            ]
            excluded = [
                _excluded([str(t) for t in c["tensors"]], str(c["reason"]))
                for c in data.get("excluded", [])
            ]
            return cls(
                dir=directory,
                model=str(data["model"]),
                digest=str(data["digest"]),
                inputs=[str(n) for n in data["inputs"]],
                outputs=[str(n) for n in data["outputs"]],
                specs=specs,
                cuts=cuts,
                excluded=excluded,
                options=dict(data.get("options", {})),
            )
        except FileNotFoundError:
            raise UserError(f"no split model in {directory} (missing {MANIFEST_NAME})") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise UserError(f"{path} is not a valid split manifest: {exc}") from None


# ---------------------------------------------------------------------------------------------
# Public functions


InputShape = tuple[int, ...] | Mapping[str, tuple[int, ...]] | None


def split_model(
    spec_or_path: str | Path,
    out_dir: Path | str | None = None,
    cuts: str | Sequence[str] = "auto",
    max_cut_tensors: int = DEFAULT_MAX_CUT_TENSORS,
    input_shape: InputShape = None,
    verify: bool = True,
    *,
    atol: float = FLOAT32_ATOL,
    threads: int | None = None,
    prune: bool = True,
) -> Partition:
    """Split a model at every candidate cut (or the given ones) and write the split directory.

    ``cuts`` is ``"auto"`` or a list of cuts, each a tensor name or several joined with ``+``
    (``"a+b"``); cut 0 (the inputs) is always included. ``max_cut_tensors`` caps the tensors
    crossing an automatic cut; ``prune`` drops automatic cuts that another cut beats (same
    FLOPs on the robot, fewer bytes). ``input_shape`` fixes dynamic dimensions: a shape for the
    first input (its batch dimension may be left out) or a mapping from input name to shape.
    Cuts that fail checking or verification are listed in ``Partition.excluded`` with the reason.
    Without ``out_dir`` the split is written to the cache (as :func:`load_partition` would).
    """
    if out_dir is None:
        return load_partition(
            spec_or_path, cuts, max_cut_tensors, input_shape, verify, atol=atol,
            threads=threads, prune=prune, refresh=True,
        )  # fmt: skip
    ref = _resolve(spec_or_path, input_shape)
    partitioner = _Partitioner(
        ref, cuts, max_cut_tensors, input_shape, verify, atol, threads, prune
    )
    return partitioner.run(Path(out_dir))


def load_partition(
    spec_or_path: str | Path,
    cuts: str | Sequence[str] = "auto",
    max_cut_tensors: int = DEFAULT_MAX_CUT_TENSORS,
    input_shape: InputShape = None,
    verify: bool = True,
    *,
    atol: float = FLOAT32_ATOL,
    threads: int | None = None,
    prune: bool = True,
    refresh: bool = False,
) -> Partition:
    """The split of a model, from the cache if it was split before with the same options.

    The cache entry is keyed by the model's sha256 digest and the options, written to a
    temporary directory and renamed into place, so concurrent daemons never read half a split.
    """
    parsed_cuts = _parse_cuts_option(cuts)
    _check_max_cut_tensors(max_cut_tensors)
    ref = _resolve(spec_or_path, input_shape)
    key_src = json.dumps(
        {
            "format": MANIFEST_FORMAT,
            "digest": ref.digest,
            "cuts": parsed_cuts,
            "max_cut_tensors": max_cut_tensors,
            "input_shape": _shape_key(input_shape),
            "verify": verify,
            "atol": atol,
            "prune": prune,
            "onnxruntime": ort.__version__,
            # 2: only initializers no optimization rewrites in place are shared, and verified
            # against onnxruntime's own run; splits cached before are made and checked again.
            "sharing": 2,
        },
        sort_keys=True,
    )
    key = hashlib.sha256(key_src.encode()).hexdigest()[:16]
    root = cache_dir() / "partitions"
    final = root / f"{ref.name}-{ref.digest[:12]}-{key}"
    if not refresh and (final / MANIFEST_NAME).is_file():
        with contextlib.suppress(UserError):
            cached = Partition.load(final)
            if _files_present(cached):
                return cached
    # Whatever sits at `final` now is stale, broken or asked to be redone.
    replace = final.exists()
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".split-", dir=root))
    try:
        _Partitioner(
            ref, parsed_cuts, max_cut_tensors, input_shape, verify, atol, threads, prune
        ).run(tmp)
        if replace and final.exists():
            # Rename first, delete after: the entry vanishes at once instead of file by file.
            stale = Path(tempfile.mkdtemp(prefix=".stale-", dir=root))
            os.rename(final, stale / "old")
            shutil.rmtree(stale, ignore_errors=True)
        try:
            os.rename(tmp, final)
        except OSError:
            # Another process put the same split in place first; theirs is as good as ours.
            if not (final / MANIFEST_NAME).is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return Partition.load(final)


def _files_present(part: Partition) -> bool:
    paths = [part.full, part.weights]
    for cut in part.cuts:
        paths += [p for p in (cut.prefix, cut.suffix) if p is not None]
    return all(p.is_file() for p in paths)


def parse_cuts(text: str) -> str | list[str]:
    """``auto`` or a comma-separated list of cuts (``a,b+c``) as given on the command line."""
    text = text.strip()
    if text == "auto":
        return "auto"
    items = [item.strip() for item in text.split(",")]
    if not text or any(not item for item in items):
        raise UserError(f"bad --cuts {text!r}: expected 'auto' or tensor names like a,b+c")
    return items


def parse_input_shape(text: str | None) -> InputShape:
    """``3x240x320`` (first input) or ``name=1x3x240x320,other=1x4``, as on the command line."""
    from common.zoo import parse_shape

    if text is None or not text.strip():
        return None
    if "=" not in text:
        return parse_shape(text)
    shapes: dict[str, tuple[int, ...]] = {}
    for item in text.split(","):
        name, sep, shape = item.partition("=")
        if not sep or not name.strip():
            raise UserError(f"bad --input-shape {text!r}: expected NAME=DxDxD,... or DxDxD")
        shapes[name.strip()] = parse_shape(shape)
    return shapes


def load_onnx(path: Path) -> onnx.ModelProto:
    """Load and check an ONNX file; a one-line UserError for anything that is not a valid model."""
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf raises DecodeError, RuntimeWarning-free garbage, OSError
        raise UserError(
            f"{path} is not an ONNX model (unreadable or truncated: {_one_line(exc)})"
        ) from None
    if not model.HasField("graph") or not model.graph.output:
        raise UserError(f"{path} is not an ONNX model (no graph with outputs; truncated?)")
    try:
        if model.ByteSize() < onnx.checker.MAXIMUM_PROTOBUF:
            onnx.checker.check_model(model)
        else:
            onnx.checker.check_model(str(path))
    except Exception as exc:
        raise UserError(f"{path} is not a valid ONNX model: {_one_line(exc)}") from None
    return model


# ---------------------------------------------------------------------------------------------
# Graph facts


@dataclass
class _Plan:
    """Where one cut falls: the tensors crossing it and the nodes on each side."""

    tensors: list[str]
    prefix_nodes: set[int]
    suffix_nodes: set[int]
    prefix_inputs: list[str]
    position: int


class _Graph:
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

    def shareable_initializers(self) -> set[str]:
        """Initializers no onnxruntime optimization rewrites in place (see ``_WEIGHT_INPUTS``):
        each use (through ``_PASS_THROUGH_OPS`` too) is a weight operand or an input of a node
        that no Transpose can reach. These alone may be shared between sessions."""
        reached = self._transpose_reachable()
        uses: dict[str, list[tuple[int, int]]] = {}
        for i, node in enumerate(self.nodes):
            for pos, name in enumerate(node.input):
                if name:
                    uses.setdefault(name, []).append((i, pos))
            for name in self.node_inputs[i]:
                if name not in node.input:
                    uses.setdefault(name, []).append((i, -1))  # read inside a subgraph
        outputs = set(self.outputs)

        def safe(name: str) -> bool:
            if name in outputs:
                return False
            for i, pos in uses.get(name, []):
                node = self.nodes[i]
                if node.domain not in ("", "ai.onnx") or pos < 0:
                    return False
                if node.op_type in _PASS_THROUGH_OPS and pos == 0:
                    if not all(safe(out) for out in node.output if out):
                        return False
                elif pos in _WEIGHT_INPUTS.get(node.op_type, frozenset()):
                    continue
                elif any(n in reached for n in self.node_inputs[i]):
                    return False
            return True

        return {name for name in self.initializers if safe(name)}

    def _transpose_reachable(self) -> set[str]:
        """Tensors a Transpose may be pushed onto: outputs of Transpose nodes and of layout ops
        (``_LAYOUT_OPS``), then of every node fed by one but ``_TRANSPOSE_BARRIERS``."""
        reached: set[str] = set()
        for i, node in enumerate(self.nodes):  # topological order
            op = node.op_type if node.domain in ("", "ai.onnx") else ""
            fed = any(n in reached for n in self.node_inputs[i])
            if op == "Transpose" or op in _LAYOUT_OPS or (fed and op not in _TRANSPOSE_BARRIERS):
                reached.update(o for o in node.output if o)
        return reached

    def sorted_tensors(self, names: Iterable[str]) -> list[str]:
        """Model inputs first (in input order), then by producing position, then by name."""

        def key(name: str) -> tuple[int, int, str]:
            if name in self.input_set:
                return (0, self.inputs.index(name), name)
            producer = self.producer.get(name)
            pos = self.position.get(producer, -1) if producer is not None else -1
            return (1, pos, name)

        return sorted(set(names), key=key)

    def plan(self, tensors: Iterable[str]) -> _Plan:
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
        return _Plan(
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


def _node_inputs(node: onnx.NodeProto) -> list[str]:
    """Explicit inputs plus outer-scope names read inside the node's subgraphs."""
    names = [n for n in node.input if n]
    for sub in _subgraphs(node):
        names.extend(sorted(_outer_refs(sub) - set(names)))
    return list(dict.fromkeys(names))


# ---------------------------------------------------------------------------------------------
# The partitioner


@dataclass
class _Candidate:
    plan: _Plan
    prefix: Path | None = None
    suffix: Path | None = None
    reason: str = ""
    max_abs_err: float | None = None
    prefix_flops: int = 0
    suffix_flops: int = 0
    bytes: int = 0


class _Partitioner:
    """One split: the stages from loading the model to the manifest, one private step each."""

    def __init__(
        self,
        ref: ModelRef,
        cuts: str | Sequence[str],
        max_cut_tensors: int,
        input_shape: InputShape,
        verify: bool,
        atol: float,
        threads: int | None,
        prune: bool = True,
    ) -> None:
        self.ref = ref
        self.prune = prune
        self.cuts = _parse_cuts_option(cuts)
        _check_max_cut_tensors(max_cut_tensors)
        self.max_cut_tensors = max_cut_tensors
        # A zoo model's input shape (C×H×W) chose the size it was exported at; the file's input
        # (the uint8 camera image, 1×H×W×C) is static, so nothing is left to fix.
        self.input_shape = None if ref.spec.startswith(ZOO_PREFIX) else input_shape
        self.verify = verify
        self.atol = atol
        self.threads = threads
        self.excluded: list[Cut] = []

    def run(self, out_dir: Path) -> Partition:
        model = self._normalize(load_onnx(self.ref.path))
        graph = _Graph(model)
        feeds = sample_feeds(self._input_specs(model))
        specs = self._probe(model, graph, feeds)
        candidates = self._collect_cuts(graph, specs)
        for cand in candidates:
            cand.prefix_flops = _flops(model, graph, specs, cand.plan.prefix_nodes)
            cand.suffix_flops = _flops(model, graph, specs, cand.plan.suffix_nodes)
            cand.bytes = sum(s.nbytes for t in cand.plan.tensors if (s := specs.get(t)))
        if self.cuts == "auto" and self.prune:
            candidates = self._prune(candidates)
        self._prepare_dir(out_dir)
        external = _WeightStore(out_dir / WEIGHTS_NAME).write(model, graph.shareable_initializers())
        _save(_with_external(model, external), out_dir / FULL_NAME)
        builder = _SubModelBuilder(model, graph, specs, external)
        for n, cand in enumerate(candidates):
            self._write_cut(builder, cand, out_dir, f"cand{n:03d}")
        usable = [c for c in candidates if not c.reason]
        if self.verify:
            self._verify(out_dir, graph, specs, usable, feeds)
        return self._finish(out_dir, graph, specs, candidates)

    # -- stages --

    def _normalize(self, model: onnx.ModelProto) -> onnx.ModelProto:
        """Fix input shapes, drop initializers listed as inputs, lift big Constant nodes."""
        g = model.graph
        inits = {t.name for t in g.initializer}
        inputs = [vi for vi in g.input if vi.name not in inits]
        shapes = _resolve_input_shapes(inputs, self.input_shape)
        new_inputs = []
        for vi in inputs:
            elem = vi.type.tensor_type.elem_type
            new_inputs.append(helper.make_tensor_value_info(vi.name, elem, list(shapes[vi.name])))
        del g.input[:]
        g.input.extend(new_inputs)
        kept = []
        for node in g.node:
            value = _big_constant(node)
            if value is not None:
                g.initializer.append(value)
            else:
                kept.append(node)
        del g.node[:]
        g.node.extend(kept)
        # Intermediate shapes recorded in the file may carry the old symbolic dimensions.
        del g.value_info[:]
        return model

    def _input_specs(self, model: onnx.ModelProto) -> list[TensorSpec]:
        specs = []
        for vi in model.graph.input:
            elem = vi.type.tensor_type.elem_type
            try:
                dtype = np.dtype(helper.tensor_dtype_to_np_dtype(elem)).name
            except Exception:
                raise UserError(
                    f"input {vi.name!r} has an unsupported element type {elem}"
                ) from None
            shape = tuple(d.dim_value for d in vi.type.tensor_type.shape.dim)
            specs.append(TensorSpec(vi.name, dtype, shape))
        return specs

    def _probe(
        self, model: onnx.ModelProto, graph: _Graph, feeds: dict[str, np.ndarray]
    ) -> dict[str, TensorSpec | None]:
        """Run the model once with every top-level tensor as an output to learn dtypes and shapes.

        Non-tensor values (sequences, maps) get None: they cannot cross a cut.
        """
        probe = onnx.ModelProto()
        probe.CopyFrom(model)
        known = set(graph.outputs)
        for i in graph.order:
            for out in graph.nodes[i].output:
                if out and out not in known:
                    probe.graph.output.append(onnx.ValueInfoProto(name=out))
                    known.add(out)
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        opts.log_severity_level = 3
        if self.threads:
            opts.intra_op_num_threads = self.threads
        try:
            session = ort.InferenceSession(
                probe.SerializeToString(), opts, providers=["CPUExecutionProvider"]
            )
            names = [o.name for o in session.get_outputs()]
            values = session.run(names, feeds)
        except Exception as exc:
            raise UserError(f"onnxruntime cannot run {self.ref.spec}: {ort_reason(exc)}") from None
        specs: dict[str, TensorSpec | None] = {}
        for name, feed in feeds.items():
            specs[name] = TensorSpec(name, feed.dtype.name, tuple(feed.shape))
        for name, value in zip(names, values, strict=True):
            if isinstance(value, np.ndarray):
                specs[name] = TensorSpec(name, value.dtype.name, tuple(int(d) for d in value.shape))
            else:
                specs[name] = None
        return specs

    def _collect_cuts(
        self, graph: _Graph, specs: Mapping[str, TensorSpec | None]
    ) -> list[_Candidate]:
        """Candidate tensor sets, planned; cut 0 (the inputs) first."""
        if not graph.order:
            raise UserError(f"{self.ref.spec} has no operators to split")
        sets: list[list[str]]
        if self.cuts == "auto":
            crossing = graph.crossing_sets()
            sets = [crossing[0]] + [s for s in crossing[1:] if len(s) <= self.max_cut_tensors]
            for i, node in enumerate(graph.nodes):
                if node.op_type in _CONTROL_FLOW_OPS and i in graph.live_nodes:
                    self.excluded.append(
                        _excluded(
                            [],
                            f"{node.op_type} node {node.name or f'#{i}'!r} runs as a whole: "
                            "no cut inside its subgraphs",
                        )
                    )
        else:
            sets = [graph.crossing_sets()[0], *self._user_sets(graph)]
        candidates: list[_Candidate] = []
        seen: set[frozenset[str]] = set()
        for tensors in sets:
            try:
                plan = graph.plan(tensors)
            except CutError as exc:
                if self.cuts == "auto":
                    self.excluded.append(_excluded(tensors, str(exc)))
                    continue
                shown = CUT_SEPARATOR.join(tensors)
                raise UserError(f"cut {shown!r} is not usable: {exc}") from None
            key = frozenset(plan.tensors)
            if key in seen:
                continue
            seen.add(key)
            not_tensors = [t for t in plan.tensors if specs.get(t) is None]
            cand = _Candidate(plan)
            if not_tensors:
                cand.reason = f"{', '.join(not_tensors)} is not a tensor (sequence or map)"
            candidates.append(cand)
        candidates.sort(key=lambda c: c.plan.position)
        return candidates

    def _prune(self, candidates: list[_Candidate]) -> list[_Candidate]:
        """Drop cuts another cut beats: same robot-side FLOPs, fewer bytes (or as few, later).

        Such a cut only moves a cheap op (ReLU, pooling) across the link, e.g. the output of a
        convolution before its max pool. Cut 0 always stays. Without any FLOPs to compare (graphs
        with no Conv/Gemm/MatMul) nothing is pruned.
        """
        if not any(c.prefix_flops or c.suffix_flops for c in candidates):
            return candidates
        best: dict[int, _Candidate] = {}
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
                    _excluded(
                        cand.plan.tensors,
                        f"{DOMINATED_PREFIX}{shown} "
                        f"({winner.bytes} bytes for the same FLOPs on the robot)",
                    )
                )
        return kept

    def _user_sets(self, graph: _Graph) -> list[list[str]]:
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
            raise UserError(
                f"unknown tensor name(s) in --cuts: {', '.join(dict.fromkeys(unknown))}"
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
                    _excluded(
                        group,
                        f"{', '.join(inside)} is inside the subgraph of {owner}: "
                        "cuts do not pass through control flow",
                    )
                )
                continue
            sets.append(group)
        return sets

    def _prepare_dir(self, out_dir: Path) -> None:
        if out_dir.exists() and not out_dir.is_dir():
            raise UserError(f"--out {out_dir} exists and is not a directory")
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"cannot create {out_dir}: {exc.strerror}") from None
        # Files of an earlier split in the same directory would be stale; remove only ours.
        for pattern in ("cand*.onnx", "cut*.prefix.onnx", "cut*.suffix.onnx"):
            for old in out_dir.glob(pattern):
                old.unlink()
        for name in (MANIFEST_NAME, FULL_NAME, WEIGHTS_NAME):
            with contextlib.suppress(FileNotFoundError):
                (out_dir / name).unlink()

    def _write_cut(
        self, builder: _SubModelBuilder, cand: _Candidate, out_dir: Path, stem: str
    ) -> None:
        if cand.reason:
            return
        plan = cand.plan
        try:
            prefix_outputs = [t for t in plan.tensors if t not in builder.graph.input_set]
            if prefix_outputs:
                cand.prefix = out_dir / f"{stem}.prefix.onnx"
                prefix = builder.build(
                    f"{stem}_prefix", plan.prefix_nodes, plan.prefix_inputs, prefix_outputs
                )
                _save(prefix, cand.prefix)
                onnx.checker.check_model(str(cand.prefix))
            cand.suffix = out_dir / f"{stem}.suffix.onnx"
            suffix = builder.build(
                f"{stem}_suffix", plan.suffix_nodes, plan.tensors, builder.graph.outputs
            )
            _save(suffix, cand.suffix)
            onnx.checker.check_model(str(cand.suffix))
        except Exception as exc:
            cand.reason = f"onnx.checker rejected the sub-model: {_one_line(exc)}"

    def _verify(
        self,
        out_dir: Path,
        graph: _Graph,
        specs: Mapping[str, TensorSpec | None],
        usable: list[_Candidate],
        feeds: dict[str, np.ndarray],
    ) -> None:
        """Run prefix then suffix for every cut and compare with the full model.

        The reference is the full model run by onnxruntime on its own (weights read from the
        file); the daemons' runtime, with its weights shared between sessions, must first agree
        with it on the full model, then every cut is compared with it.
        """
        from common.split_runtime import SplitModel

        part = self._partition(out_dir, graph, specs, usable, verified=False)
        try:
            session = _own_weights_session(part.full, self.threads)
            names = [o.name for o in session.get_outputs()]
            reference = dict(zip(names, session.run(names, feeds), strict=True))
        except Exception as exc:
            raise UserError(f"onnxruntime cannot run {self.ref.spec}: {ort_reason(exc)}") from None
        del session  # its copy of the weights
        runtime = SplitModel(part, threads=self.threads, lazy=True)
        try:
            _, failure = _compare(reference, runtime.run_full(feeds), self.atol)
        except Exception as exc:
            failure = ort_reason(exc)
        if failure:
            # A graph optimization rewrote a shared initializer in place (see _WEIGHT_INPUTS):
            # every session holding that node would compute with it in its old layout.
            raise UserError(
                f"onnxruntime runs {self.ref.spec} on its own, but not with its weights shared "
                f"between sessions: {failure}"
            )
        for k, cand in enumerate(usable):
            try:
                sent = runtime.run_prefix(k, feeds)
                for name in cand.plan.tensors:
                    expected = specs[name]
                    got = sent[name]
                    if expected is None or tuple(got.shape) != expected.shape:
                        raise CutError(f"prefix output {name!r} has shape {got.shape}")
                # No original feeds here: the suffix must run from the cut tensors alone.
                result = runtime.run_suffix(k, sent)
                cand.max_abs_err, failure = _compare(reference, result, self.atol)
                if failure:
                    cand.reason = f"verification failed: {failure}"
            except CutError as exc:
                cand.reason = f"verification failed: {exc}"
            except Exception as exc:
                cand.reason = f"onnxruntime failed on this cut: {ort_reason(exc)}"
            finally:
                runtime.release(k)

    def _finish(
        self,
        out_dir: Path,
        graph: _Graph,
        specs: Mapping[str, TensorSpec | None],
        candidates: list[_Candidate],
    ) -> Partition:
        """Number usable cuts 0..K-1, rename their files, drop the others, write the manifest."""
        usable: list[_Candidate] = []
        for cand in candidates:
            if cand.reason:
                self.excluded.append(_excluded(cand.plan.tensors, cand.reason))
                for path in (cand.prefix, cand.suffix):
                    if path is not None:
                        path.unlink(missing_ok=True)
                continue
            k = len(usable)
            if cand.prefix is not None:
                cand.prefix = cand.prefix.rename(out_dir / f"cut{k:03d}.prefix.onnx")
            assert cand.suffix is not None
            cand.suffix = cand.suffix.rename(out_dir / f"cut{k:03d}.suffix.onnx")
            usable.append(cand)
        part = self._partition(out_dir, graph, specs, usable, verified=self.verify)
        tmp = out_dir / f".{MANIFEST_NAME}.tmp"
        tmp.write_text(json.dumps(part.manifest(), indent=2) + "\n")
        os.replace(tmp, out_dir / MANIFEST_NAME)
        return part

    def _partition(
        self,
        out_dir: Path,
        graph: _Graph,
        specs: Mapping[str, TensorSpec | None],
        cands: list[_Candidate],
        verified: bool,
    ) -> Partition:
        names = list(graph.inputs) + list(graph.outputs)
        for cand in cands:
            names.extend(cand.plan.tensors)
        table: dict[str, TensorSpec] = {}
        for name in names:
            spec = specs.get(name)
            if spec is not None:
                table[name] = spec
        cuts = [
            Cut(
                index=k,
                tensors=list(c.plan.tensors),
                bytes=sum(table[t].nbytes for t in c.plan.tensors),
                prefix=c.prefix,
                suffix=c.suffix,
                verified=verified,
                max_abs_err=c.max_abs_err if verified else None,
                prefix_flops=c.prefix_flops,
                suffix_flops=c.suffix_flops,
            )
            for k, c in enumerate(cands)
        ]
        return Partition(
            dir=out_dir,
            model=self.ref.spec,
            digest=self.ref.digest,
            inputs=list(graph.inputs),
            outputs=list(graph.outputs),
            specs=table,
            cuts=cuts,
            excluded=list(self.excluded),
            options={
                "cuts": self.cuts,
                "max_cut_tensors": self.max_cut_tensors,
                "input_shapes": {n: list(table[n].shape) for n in graph.inputs if n in table},
                "verify": self.verify,
                "atol": self.atol,
                "prune": self.prune,
            },
        )


class _SubModelBuilder:
    """Builds a sub-model from a node set: reachable nodes, used initializers, typed boundaries."""

    def __init__(
        self,
        model: onnx.ModelProto,
        graph: _Graph,
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


class _WeightStore:
    """Writes every big shareable initializer once to ``weights.bin``; hands out references.

    Shareable (:meth:`_Graph.shareable_initializers`): no onnxruntime optimization rewrites it
    in place, so every session can be handed the same copy.
    """

    def __init__(self, path: Path) -> None:
        self.path = path

    def write(self, model: onnx.ModelProto, shareable: set[str]) -> dict[str, onnx.TensorProto]:
        refs: dict[str, onnx.TensorProto] = {}
        offset = 0
        with open(self.path, "wb") as f:
            for tensor in model.graph.initializer:
                if tensor.name not in shareable:
                    continue
                try:
                    array = numpy_helper.to_array(tensor)
                except Exception:
                    continue  # exotic types (bfloat16, float8, strings) stay inline
                if array.dtype == object or array.nbytes < EXTERNAL_MIN_BYTES:
                    continue
                pad = -offset % WEIGHT_ALIGN_BYTES
                f.write(b"\0" * pad)
                offset += pad
                data = np.ascontiguousarray(array).tobytes()
                f.write(data)
                ref = onnx.TensorProto(name=tensor.name, data_type=tensor.data_type)
                ref.dims.extend(array.shape)
                ref.data_location = onnx.TensorProto.EXTERNAL
                for key, value in (
                    ("location", WEIGHTS_NAME),
                    ("offset", str(offset)),
                    ("length", str(len(data))),
                ):
                    entry = ref.external_data.add()
                    entry.key, entry.value = key, value
                refs[tensor.name] = ref
                offset += len(data)
        return refs


# ---------------------------------------------------------------------------------------------
# Helpers


def sample_feeds(specs: Sequence[TensorSpec], seed: int = VERIFY_SEED) -> dict[str, np.ndarray]:
    """Seeded random input for each spec: standard normal floats, small integers, random bools."""
    rng = np.random.default_rng(seed)
    feeds: dict[str, np.ndarray] = {}
    for spec in specs:
        dtype = np.dtype(spec.dtype)
        if dtype.kind == "f":
            value = rng.standard_normal(spec.shape).astype(dtype)
        elif dtype.kind in "iu":
            value = rng.integers(0, 10, size=spec.shape).astype(dtype)
        elif dtype.kind == "b":
            value = rng.integers(0, 2, size=spec.shape).astype(bool)
        else:
            raise UserError(f"input {spec.name!r} has unsupported dtype {dtype}")
        feeds[spec.name] = value
    return feeds


def ort_reason(exc: BaseException) -> str:
    """onnxruntime's error without its status prefix and C++ source location, on one line."""
    text = _one_line(exc, limit=2000)
    text = re.sub(r"^\[ONNXRuntimeError\] : \d+ : \w+ : ", "", text)
    if text.startswith("/onnxruntime_src/") or text.startswith("onnxruntime/"):
        # "/path/file.cc:256 Type fn(args...) Message" -> "Message"
        m = re.search(r"\) (?=[A-Z\[])", text)
        if m:
            text = text[m.end() :]
    opset = re.search(r"Opset (\d+) is under development.*domain (\S+) is till opset (\d+)", text)
    if opset:
        used, domain, top = opset.groups()
        return f"the model uses opset {used} of {domain}; this onnxruntime supports up to {top}"
    return text[:_MAX_REASON_CHARS]


def _one_line(exc: BaseException, limit: int = _MAX_REASON_CHARS) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:limit]


def _excluded(tensors: Sequence[str], reason: str) -> Cut:
    return Cut(-1, list(tensors), 0, None, None, False, None, reason=reason)


def _tolerance(dtype: np.dtype, atol: float) -> float:
    if dtype == np.float16:
        return max(atol, FLOAT16_ATOL)
    if dtype.kind in "fc":
        return atol
    return 0.0


def _compare(
    reference: Mapping[str, np.ndarray], result: Mapping[str, np.ndarray], atol: float
) -> tuple[float, str]:
    """Largest absolute difference over all outputs, and why it is too large ("" if it is not)."""
    worst = 0.0
    for name, ref in reference.items():
        got = result.get(name)
        if got is None:
            return float("inf"), f"output {name!r} is missing"
        if got.shape != ref.shape or got.dtype != ref.dtype:
            return float("inf"), f"output {name!r} is {got.dtype}{list(got.shape)}"
        if ref.dtype.kind in "fc":
            ref_nan, got_nan = np.isnan(ref), np.isnan(got)
            if not np.array_equal(ref_nan, got_nan):
                return float("inf"), f"output {name!r} has NaN where the full model has none"
            diff = np.abs(ref.astype(np.float64) - got.astype(np.float64))[~ref_nan]
        else:
            diff = np.abs(ref.astype(np.float64) - got.astype(np.float64))
        err = float(diff.max()) if diff.size else 0.0
        worst = max(worst, err)
        bound = _tolerance(ref.dtype, atol)
        if not err <= bound:
            return worst, f"output {name!r} differs by {err:.3g} (tolerance {bound:g})"
    return worst, ""


def _flops(
    model: onnx.ModelProto,
    graph: _Graph,
    specs: Mapping[str, TensorSpec | None],
    node_ids: Iterable[int],
) -> int:
    """Multiply-add FLOPs (2 per MAC) of the Conv, ConvTranspose, Gemm and MatMul nodes given."""
    init_shapes = {t.name: tuple(t.dims) for t in model.graph.initializer}

    def shape(name: str) -> tuple[int, ...] | None:
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


def _node_flops(node: onnx.NodeProto, shape: Any) -> int:
    op = node.op_type
    if op not in ("Conv", "ConvTranspose", "Gemm", "MatMul") or node.domain not in ("", "ai.onnx"):
        return 0
    ins = [shape(n) for n in node.input[:2]]
    out = shape(node.output[0])
    if any(s is None for s in ins) or out is None:
        return 0
    a, w = ins
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


def _resolve_input_shapes(
    inputs: Sequence[onnx.ValueInfoProto], input_shape: InputShape
) -> dict[str, tuple[int, ...]]:
    """Concrete shapes for the model inputs: given ones, static ones, and a batch of 1."""
    given: dict[str, tuple[int, ...]] = {}
    if isinstance(input_shape, Mapping):
        names = {vi.name for vi in inputs}
        unknown = [n for n in input_shape if n not in names]
        if unknown:
            raise UserError(
                f"--input-shape names unknown input(s) {', '.join(unknown)}; "
                f"the model's inputs are {', '.join(vi.name for vi in inputs)}"
            )
        given = {n: tuple(int(d) for d in s) for n, s in input_shape.items()}
    elif input_shape is not None and inputs:
        given = {inputs[0].name: tuple(int(d) for d in input_shape)}
    shapes: dict[str, tuple[int, ...]] = {}
    for vi in inputs:
        tt = vi.type.tensor_type
        if not vi.type.HasField("tensor_type"):
            raise UserError(f"input {vi.name!r} is not a tensor; only tensor inputs are supported")
        has_shape = tt.HasField("shape")
        dims: list[int | str | None] = []
        for d in tt.shape.dim:
            if d.HasField("dim_value") and d.dim_value > 0:
                dims.append(int(d.dim_value))
            else:
                dims.append(d.dim_param or None)
        if vi.name in given:
            shape = given[vi.name]
            if has_shape and len(shape) == len(dims) - 1:
                shape = (1, *shape)  # the batch dimension may be left out
            if has_shape and len(shape) != len(dims):
                raise UserError(
                    f"--input-shape {_fmt(shape)} has {len(shape)} dimensions but input "
                    f"{vi.name!r} has {len(dims)}"
                )
            for axis, (want, have) in enumerate(zip(dims, shape, strict=False)):
                if isinstance(want, int) and want != have:
                    raise UserError(
                        f"--input-shape {_fmt(shape)} does not match input {vi.name!r}: "
                        f"axis {axis} is fixed at {want}"
                    )
            if any(d <= 0 for d in shape):
                raise UserError(f"--input-shape {_fmt(shape)}: dimensions must be positive")
            shapes[vi.name] = shape
            continue
        if not has_shape:
            raise UserError(f"input {vi.name!r} has no shape; give one with --input-shape")
        resolved: list[int] = []
        for axis, d in enumerate(dims):
            if isinstance(d, int):
                resolved.append(d)
            elif axis == 0:
                resolved.append(1)  # a dynamic batch dimension: one frame at a time
            else:
                raise UserError(
                    f"input {vi.name!r} has a dynamic dimension {d or '?'} at axis {axis}; "
                    "give its shape with --input-shape"
                )
        shapes[vi.name] = tuple(resolved)
    return shapes


def _big_constant(node: onnx.NodeProto) -> onnx.TensorProto | None:
    """The tensor of a Constant node worth sharing as an initializer, else None."""
    if node.op_type != "Constant" or node.domain not in ("", "ai.onnx") or len(node.output) != 1:
        return None
    for attr in node.attribute:
        if attr.name == "value" and attr.type == onnx.AttributeProto.TENSOR:
            try:
                array = numpy_helper.to_array(attr.t)
            except Exception:
                return None
            if array.dtype != object and array.nbytes >= CONSTANT_TO_INITIALIZER_BYTES:
                return numpy_helper.from_array(array, node.output[0])
    return None


def _own_weights_session(path: Path, threads: int | None) -> ort.InferenceSession:
    """A plain session of ``path``, weights read from the file (not shared), with the split
    runtime's default level and no pre-packing: the same kernels, hence the same numbers."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    opts.add_session_config_entry("session.disable_prepacking", "1")
    opts.log_severity_level = 3
    if threads:
        opts.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def _with_external(
    model: onnx.ModelProto, external: Mapping[str, onnx.TensorProto]
) -> onnx.ModelProto:
    out = onnx.ModelProto()
    out.CopyFrom(model)
    inits = [external.get(t.name, t) for t in model.graph.initializer]
    del out.graph.initializer[:]
    out.graph.initializer.extend(inits)
    return out


def _save(model: onnx.ModelProto, path: Path) -> None:
    # The tensors already point at weights.bin; save the graph only.
    path.write_bytes(model.SerializeToString())


def _resolve(spec_or_path: str | Path, input_shape: InputShape) -> ModelRef:
    zoo_shape = input_shape if not isinstance(input_shape, Mapping) else None
    if str(spec_or_path).startswith("zoo:") and isinstance(input_shape, Mapping):
        raise UserError("a zoo model takes --input-shape as CxHxW, not NAME=shape")
    return resolve_model(spec_or_path, zoo_shape)


def _parse_cuts_option(cuts: str | Sequence[str]) -> str | list[str]:
    if isinstance(cuts, str):
        return parse_cuts(cuts)
    items = [str(c).strip() for c in cuts]
    if not items or any(not c for c in items):
        raise UserError("cuts must be 'auto' or a non-empty list of tensor names")
    return items


def _check_max_cut_tensors(n: int) -> None:
    if not isinstance(n, int) or n < 1:
        raise UserError(f"--max-cut-tensors must be a positive integer, got {n!r}")


def _shape_key(input_shape: InputShape) -> Any:
    if input_shape is None:
        return None
    if isinstance(input_shape, Mapping):
        return {k: list(v) for k, v in sorted(input_shape.items())}
    return list(input_shape)


def _fmt(shape: Sequence[int]) -> str:
    return "x".join(str(d) for d in shape)
