"""``weights.bin``: every big shareable initializer written once, aligned, and referenced from
each model file as external data, so sub-models add no copies of the weights on disk and the
runtime can read them into one buffer."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from common.partition.manifest import WEIGHTS_NAME

# Initializers at least this big go to weights.bin (shared by every sub-model); smaller ones
# (shape constants, scalars) stay inline, where duplication costs nothing.
EXTERNAL_MIN_BYTES = 1024
WEIGHT_ALIGN_BYTES = 64


class WeightStore:
    """Writes every big shareable initializer once to ``weights.bin``; hands out references.

    Shareable (:func:`common.partition.sharing.shareable_initializers`): no onnxruntime
    optimization rewrites it in place, so every session can be handed the same copy.
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


def with_external(
    model: onnx.ModelProto, external: Mapping[str, onnx.TensorProto]
) -> onnx.ModelProto:
    """A copy of ``model`` whose initializers in ``external`` point at ``weights.bin``."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    inits = [external.get(t.name, t) for t in model.graph.initializer]
    del out.graph.initializer[:]
    out.graph.initializer.extend(inits)
    return out


def save_graph(model: onnx.ModelProto, path: Path) -> None:
    """Write a model file whose big tensors already point at weights.bin: the graph only."""
    path.write_bytes(model.SerializeToString())
