"""The model as the partitioner reads it: loaded and checked, its input shapes fixed, big
Constant nodes lifted to initializers, and the specs of its inputs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from common.errors import UserError
from common.partition.errors import OptionError, one_line
from common.partition.manifest import TensorSpec
from common.partition.options import InputShape, format_shape

# Constant nodes with a tensor this big become initializers, so that weights among them are shared.
CONSTANT_TO_INITIALIZER_BYTES = 1024


def load_onnx(path: Path) -> onnx.ModelProto:
    """Load and check an ONNX file; a one-line UserError for anything that is not a valid model."""
    try:
        model = onnx.load(str(path))
    except Exception as exc:  # protobuf raises DecodeError, RuntimeWarning-free garbage, OSError
        raise UserError(
            f"{path} is not an ONNX model (unreadable or truncated: {one_line(exc)})"
        ) from None
    if not model.HasField("graph") or not model.graph.output:
        raise UserError(f"{path} is not an ONNX model (no graph with outputs; truncated?)")
    try:
        if model.ByteSize() < onnx.checker.MAXIMUM_PROTOBUF:
            onnx.checker.check_model(model)
        else:
            onnx.checker.check_model(str(path))
    except Exception as exc:
        raise UserError(f"{path} is not a valid ONNX model: {one_line(exc)}") from None
    return model


def normalize(model: onnx.ModelProto, input_shape: InputShape) -> onnx.ModelProto:
    """Fix input shapes, drop initializers listed as inputs, lift big Constant nodes (in place)."""
    g = model.graph
    inits = {t.name for t in g.initializer}
    inputs = [vi for vi in g.input if vi.name not in inits]
    shapes = resolve_input_shapes(inputs, input_shape)
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


def input_specs(model: onnx.ModelProto) -> list[TensorSpec]:
    """The specs of a normalized model's inputs (every dimension fixed)."""
    specs = []
    for vi in model.graph.input:
        elem = vi.type.tensor_type.elem_type
        try:
            dtype = np.dtype(helper.tensor_dtype_to_np_dtype(elem)).name
        except Exception:
            raise UserError(f"input {vi.name!r} has an unsupported element type {elem}") from None
        shape = tuple(d.dim_value for d in vi.type.tensor_type.shape.dim)
        specs.append(TensorSpec(vi.name, dtype, shape))
    return specs


def resolve_input_shapes(
    inputs: Sequence[onnx.ValueInfoProto], input_shape: InputShape
) -> dict[str, tuple[int, ...]]:
    """Concrete shapes for the model inputs: given ones, static ones, and a batch of 1."""
    given: dict[str, tuple[int, ...]] = {}
    if isinstance(input_shape, Mapping):
        names = {vi.name for vi in inputs}
        unknown = [n for n in input_shape if n not in names]
        if unknown:
            raise OptionError(
                "input_shape",
                "{option} names unknown input(s) {unknown}; the model's inputs are {known}",
                unknown=", ".join(unknown),
                known=", ".join(vi.name for vi in inputs),
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
            shapes[vi.name] = _given_shape(vi.name, given[vi.name], dims, has_shape)
            continue
        if not has_shape:
            raise OptionError(
                "input_shape", "input {name!r} has no shape; give one with {option}", name=vi.name
            )
        resolved: list[int] = []
        for axis, d in enumerate(dims):
            if isinstance(d, int):
                resolved.append(d)
            elif axis == 0:
                resolved.append(1)  # a dynamic batch dimension: one frame at a time
            else:
                raise OptionError(
                    "input_shape",
                    "input {name!r} has a dynamic dimension {dim} at axis {axis}; "
                    "give its shape with {option}",
                    name=vi.name,
                    dim=d or "?",
                    axis=axis,
                )
        shapes[vi.name] = tuple(resolved)
    return shapes


def _given_shape(
    name: str, shape: tuple[int, ...], dims: Sequence[int | str | None], has_shape: bool
) -> tuple[int, ...]:
    """A shape given for input ``name`` (whose file dimensions are ``dims``), checked against it."""
    if has_shape and len(shape) == len(dims) - 1:
        shape = (1, *shape)  # the batch dimension may be left out
    shown = format_shape(shape)
    if has_shape and len(shape) != len(dims):
        raise OptionError(
            "input_shape",
            "{option} {shape} has {given} dimensions but input {name!r} has {needed}",
            shape=shown,
            given=len(shape),
            name=name,
            needed=len(dims),
        )
    for axis, (want, have) in enumerate(zip(dims, shape, strict=False)):
        if isinstance(want, int) and want != have:
            raise OptionError(
                "input_shape",
                "{option} {shape} does not match input {name!r}: axis {axis} is fixed at {want}",
                shape=shown,
                name=name,
                axis=axis,
                want=want,
            )
    if any(d <= 0 for d in shape):
        raise OptionError(
            "input_shape", "{option} {shape}: dimensions must be positive", shape=shown
        )
    return shape


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
