"""Checking an inference request against the model a deployment serves (cloudd.validate).

`write_tiny_model` is also the model of the cloud daemon's integration tests: a small MatMul
network with a skip connection (so one cut carries two tensors), heavy enough per request (a few
milliseconds) that a burst of requests fills a one-worker pool.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from cloudd.validate import check_request
from common.partition import TensorSpec
from common.wire import ErrorCode
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor

TINY_BATCH = 32
TINY_DIM = 512
TINY_OUT = 32
TINY_OPSET = 17


def tiny_model() -> onnx.ModelProto:
    """x[B,D] -> a = relu(x W0) -> b = relu(a W1) -> c = a + b -> y = c W2 [B,OUT]."""
    rng = np.random.default_rng(3)

    def weight(name: str, cols: int) -> onnx.TensorProto:
        w = rng.standard_normal((TINY_DIM, cols)) / np.sqrt(TINY_DIM)
        return numpy_helper.from_array(w.astype(np.float32), name)

    nodes = [
        helper.make_node("MatMul", ["x", "W0"], ["m0"], name="m0"),
        helper.make_node("Relu", ["m0"], ["a"], name="a"),
        helper.make_node("MatMul", ["a", "W1"], ["m1"], name="m1"),
        helper.make_node("Relu", ["m1"], ["b"], name="b"),
        helper.make_node("Add", ["a", "b"], ["c"], name="c"),
        helper.make_node("MatMul", ["c", "W2"], ["y"], name="y"),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [TINY_BATCH, TINY_DIM])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [TINY_BATCH, TINY_OUT])],
        [weight("W0", TINY_DIM), weight("W1", TINY_DIM), weight("W2", TINY_OUT)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", TINY_OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def write_tiny_model(path: Path) -> Path:
    """Save the tiny model to `path` (same bytes every time: same digest, same cache entry)."""
    path.write_bytes(tiny_model().SerializeToString())
    return path


DIGEST = "ab" * 32
SPECS = [
    [TensorSpec("x", "float32", (2, 4))],
    [TensorSpec("a", "float32", (2, 4)), TensorSpec("b", "float32", (2, 4))],
]


def request(**changes: object) -> InferRequest:
    fields: dict[str, object] = {
        "robot": "robot-1",
        "frame": 3,
        "model_digest": DIGEST,
        "cut": 1,
        "tensors": {"a": np.zeros((2, 4), np.float32), "b": np.ones((2, 4), np.float32)},
        "deadline_s": 0.5,
        "sent_at": time.time(),
    }
    fields.update(changes)
    # Arrays stand for raw-coded tensors: what is checked here is their declared dtype and shape.
    tensors = fields["tensors"]
    assert isinstance(tensors, dict)
    fields["tensors"] = {n: EncodedTensor.raw(a) for n, a in tensors.items()}
    return InferRequest(**fields)  # type: ignore[arg-type]


def check(req: InferRequest, robot: str = "robot-1") -> tuple[str, str] | None:
    error = check_request(req, robot=robot, digest=DIGEST, cut_specs=SPECS)
    return None if error is None else (error.code, error.reason)


def test_a_request_that_fits_passes() -> None:
    assert check(request()) is None
    assert check(request(cut=0, tensors={"x": np.zeros((2, 4), np.float32)})) is None


@pytest.mark.parametrize(
    ("changes", "robot", "code", "needles"),
    [
        ({}, "robot-2", ErrorCode.WRONG_ROBOT, ["'robot-1'", "'robot-2'"]),
        ({"model_digest": "cd" * 32}, "robot-1", ErrorCode.MODEL_DIGEST, ["cdcdcd", "ababab"]),
        ({"cut": 2}, "robot-1", ErrorCode.UNKNOWN_CUT, ["unknown cut 2", "0..1"]),
        (
            {"tensors": {"a": np.zeros((2, 4), np.float32)}},
            "robot-1",
            ErrorCode.MISSING_FIELD,
            ["missing 'b'"],
        ),
        (
            {
                "tensors": {
                    "a": np.zeros((2, 4), np.float32),
                    "b": np.zeros((2, 4), np.float32),
                    "z": np.zeros(1, np.float32),
                }
            },
            "robot-1",
            ErrorCode.BAD_VALUE,
            ["unexpected 'z'"],
        ),
        (
            {"tensors": {"a": np.zeros((2, 4), np.float64), "b": np.ones((2, 4), np.float32)}},
            "robot-1",
            ErrorCode.BAD_DTYPE,
            ["'a'", "float64", "expected float32"],
        ),
        (
            {"tensors": {"a": np.zeros((4, 2), np.float32), "b": np.ones((2, 4), np.float32)}},
            "robot-1",
            ErrorCode.SHAPE_MISMATCH,
            ["'a'", "[4, 2]", "expected [2, 4]"],
        ),
    ],
    ids=["robot", "digest", "cut", "missing", "extra", "dtype", "shape"],
)
def test_each_problem_is_named(
    changes: dict[str, object], robot: str, code: ErrorCode, needles: list[str]
) -> None:
    found = check(request(**changes), robot=robot)
    assert found is not None
    assert found[0] == code.value
    for needle in needles:
        assert needle in found[1], (needle, found[1])


def test_tiny_model_is_a_valid_onnx_model(tmp_path: Path) -> None:
    path = write_tiny_model(tmp_path / "tiny.onnx")
    assert path.read_bytes() == write_tiny_model(tmp_path / "again.onnx").read_bytes()
