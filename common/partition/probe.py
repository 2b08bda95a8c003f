"""Every top-level tensor's dtype and shape, learned from one onnxruntime run of the model with
all of them made outputs: what crosses a cut, and how many bytes, is what onnxruntime computes."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import onnx
import onnxruntime as ort

from common.errors import UserError
from common.partition.errors import ort_reason
from common.partition.graph import DataflowGraph
from common.partition.manifest import TensorSpec


def probe_specs(
    model: onnx.ModelProto,
    graph: DataflowGraph,
    feeds: Mapping[str, np.ndarray],
    *,
    spec: str,
    threads: int | None,
) -> dict[str, TensorSpec | None]:
    """Run the model once with every top-level tensor as an output to learn dtypes and shapes.

    Non-tensor values (sequences, maps) get None: they cannot cross a cut. ``spec`` names the
    model in errors.
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
    if threads:
        opts.intra_op_num_threads = threads
    try:
        session = ort.InferenceSession(
            probe.SerializeToString(), opts, providers=["CPUExecutionProvider"]
        )
        names = [o.name for o in session.get_outputs()]
        values = session.run(names, dict(feeds))
    except Exception as exc:
        raise UserError(f"onnxruntime cannot run {spec}: {ort_reason(exc)}") from None
    specs: dict[str, TensorSpec | None] = {}
    for name, feed in feeds.items():
        specs[name] = TensorSpec(name, feed.dtype.name, tuple(feed.shape))
    for name, value in zip(names, values, strict=True):
        if isinstance(value, np.ndarray):
            specs[name] = TensorSpec(name, value.dtype.name, tuple(int(d) for d in value.shape))
        else:
            specs[name] = None
    return specs
