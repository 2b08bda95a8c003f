"""Regenerate the profile fixtures: two CNNs at 3×240×320, timed stage by stage with onnxruntime.

Each model is a chain of stages; cut k is the input of stage k (cut 0 = the model's input). Every
stage is its own ONNX graph, written with the zoo's graph builder (``common.zoo_nets``: a
convolution with its batch norm folded in is one Conv with a bias, as a torch export writes it)
and timed with onnxruntime (1 thread, median of --runs runs); prefix_ms / suffix_ms are sums of
stage medians, FLOPs are counted from the layer shapes. The output has the partitioner's profile
format. Needs no torch.

    python tests/data/profiles/make_profiles.py --out tests/data/profiles [--runs 31]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, shape_inference

from common.zoo import ZOO_OPSET
from common.zoo_nets import Act, NetBuilder

INPUT_SHAPE = (1, 3, 240, 320)
WARMUP_RUNS = 5
STAGE_INPUT = "x"

# A stage writes its nodes after tensor ``x`` of ``cin`` channels, their names prefixed with
# ``p``; returns (output, channels out).
Stage = Callable[[NetBuilder, str, int, str], tuple[str, int]]


def conv_relu(cout: int) -> Stage:
    def stage(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        return b.conv_bn(x, f"{p}conv", cin, cout, 3), cout

    return stage


def max_pool(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
    return b.max_pool(x, f"{p}pool", 2, 2), cin


def flatten(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
    return b.node("Flatten", [x], f"{p}flatten", axis=1), cin


def linear(cin: int, cout: int, relu: bool) -> Stage:
    def stage(b: NetBuilder, x: str, _: int, p: str) -> tuple[str, int]:
        y = b.linear(x, f"{p}fc", cin, cout)
        return (b.node("Relu", [y], f"{p}fc.act") if relu else y), cout

    return stage


def chain(*stages: Stage) -> Stage:
    """Several stages as one."""

    def stage(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        for i, part in enumerate(stages):
            x, cin = part(b, x, cin, f"{p}{i}.")
        return x, cin

    return stage


def vgg_like() -> tuple[list[Stage], list[str]]:
    stages: list[Stage] = [
        conv_relu(32),
        conv_relu(32),
        max_pool,
        conv_relu(64),
        conv_relu(64),
        max_pool,
        conv_relu(128),
        conv_relu(128),
        max_pool,
        conv_relu(256),
        conv_relu(256),
        max_pool,
        chain(conv_relu(512), max_pool, flatten),
        linear(512 * 7 * 10, 1024, relu=True),
        linear(1024, 1024, relu=True),
        linear(1024, 1000, relu=False),
    ]
    names = ["input", "relu1a", "relu1b", "pool1", "relu2a", "relu2b", "pool2", "relu3a"]
    names += ["relu3b", "pool3", "relu4a", "relu4b", "pool4", "pool5_flat", "fc1", "fc2"]
    return stages, names


def ir(cout: int, stride: int, expand: int = 6) -> Stage:
    """MobileNetV2 block: 1×1 expand, 3×3 depthwise, 1×1 project, residual when shapes allow."""

    def stage(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        hidden, out = cin * expand, x
        if expand != 1:
            out = b.conv_bn(out, f"{p}expand", cin, hidden, 1, act=Act.RELU6)
        out = b.conv_bn(out, f"{p}dw", hidden, hidden, 3, stride, hidden, Act.RELU6)
        out = b.conv_bn(out, f"{p}project", hidden, cout, 1, act=Act.NONE)
        return (b.add(x, out, f"{p}add") if stride == 1 and cin == cout else out), cout

    return stage


def mobilenet_like() -> tuple[list[Stage], list[str]]:
    def stem(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        return b.conv_bn(x, f"{p}stem", cin, 32, 3, 2, act=Act.RELU6), 32

    def conv_last(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        return b.conv_bn(x, f"{p}conv_last", cin, 1280, 1, act=Act.RELU6), 1280

    def pool(b: NetBuilder, x: str, cin: int, p: str) -> tuple[str, int]:
        gap = b.node("GlobalAveragePool", [x], f"{p}gap")
        return b.node("Flatten", [gap], f"{p}flat", axis=1), cin

    stages: list[Stage] = [
        stem,
        ir(16, 1, expand=1),
        ir(24, 2),
        ir(24, 1),
        ir(32, 2),
        chain(ir(32, 1), ir(32, 1)),
        ir(64, 2),
        chain(ir(64, 1), ir(64, 1)),
        ir(64, 1),
        chain(ir(96, 1), ir(96, 1), ir(96, 1)),
        ir(160, 2),
        chain(ir(160, 1), ir(160, 1)),
        ir(320, 1),
        conv_last,
        pool,
        linear(1280, 1000, relu=False),
    ]
    names = ["input", "stem", "block1", "block2", "block3", "block4", "block6", "block7"]
    names += ["block8", "block10", "block13", "block14", "block16", "block17", "conv_last", "pool"]
    return stages, names


def stage_model(stage: Stage, x: np.ndarray) -> tuple[onnx.ModelProto, int]:
    """One stage as a model from a float tensor shaped like ``x``, and its channels out."""
    b = NetBuilder()
    out, cout = stage(b, STAGE_INPUT, x.shape[1], "")
    inputs = [helper.make_tensor_value_info(STAGE_INPUT, TensorProto.FLOAT, list(x.shape))]
    # The output's shape from shape inference on a draft (the checked model must state it).
    draft = helper.make_model(
        helper.make_graph(b.nodes, "draft", inputs, [], b.initializers),
        opset_imports=[helper.make_opsetid("", ZOO_OPSET)],
    )
    (shape,) = (
        [d.dim_value for d in v.type.tensor_type.shape.dim]
        for v in shape_inference.infer_shapes(draft).graph.value_info
        if v.name == out
    )
    outputs = [helper.make_tensor_value_info(out, TensorProto.FLOAT, shape)]
    return b.model("stage", inputs, outputs), cout


def stage_flops(model: onnx.ModelProto) -> int:
    """Multiply-adds ×2 of the convolutions and fully connected layers, from the layer shapes."""
    inferred = shape_inference.infer_shapes(model)
    shapes = {
        v.name: [d.dim_value for d in v.type.tensor_type.shape.dim]
        for v in [*inferred.graph.value_info, *inferred.graph.output]
    }
    weights = {t.name: list(t.dims) for t in model.graph.initializer}
    total = 0
    for node in model.graph.node:
        if node.op_type == "Conv":  # 2 × out values × (in channels / groups) × kernel
            total += 2 * math.prod(shapes[node.output[0]]) * math.prod(weights[node.input[1]][1:])
        elif node.op_type == "Gemm":  # transB: weights are out × in
            total += 2 * math.prod(weights[node.input[1]])
    return total


def stage_ms(model: onnx.ModelProto, x: np.ndarray, runs: int) -> tuple[float, np.ndarray]:
    """Median onnxruntime time of one stage on one thread, and its output."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(
        model.SerializeToString(), options, providers=["CPUExecutionProvider"]
    )
    feed = {STAGE_INPUT: x}
    for _ in range(WARMUP_RUNS):
        (out,) = session.run(None, feed)
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        session.run(None, feed)
        times.append((time.perf_counter() - started) * 1000)
    return statistics.median(times), out


def profile(name: str, stages: list[Stage], names: list[str], runs: int) -> dict[str, Any]:
    x = np.random.default_rng(0).standard_normal(INPUT_SHAPE, dtype=np.float32)
    inputs, flops, times = [x], [], []
    for stage in stages:
        model, _ = stage_model(stage, inputs[-1])
        flops.append(stage_flops(model))
        ms, out = stage_ms(model, inputs[-1], runs)
        times.append(ms)
        inputs.append(out)
    cuts = [
        {
            "index": k,
            "tensors": [names[k]],
            "bytes": int(inputs[k].size * 4),
            "prefix_ms": round(sum(times[:k]), 3),
            "suffix_ms": round(sum(times[k:]), 3),
            "prefix_flops": sum(flops[:k]),
            "suffix_flops": sum(flops[k:]),
        }
        for k in range(len(stages))
    ]
    return {
        "model": name,
        # Not an ONNX file's digest: these fixtures stand for a model, not a file.
        "digest": hashlib.sha256(name.encode()).hexdigest(),
        "full_ms": round(sum(times), 3),
        "output_bytes": int(inputs[-1].size * 4),
        "cuts": cuts,
    }


def write(path: Path, prof: dict[str, Any]) -> None:
    """One cut per line, so a diff shows which cut changed."""
    head = [f" {json.dumps(k)}: {json.dumps(v)}," for k, v in prof.items() if k != "cuts"]
    rows = ",\n".join("  " + json.dumps(c) for c in prof["cuts"])
    path.write_text("{\n" + "\n".join(head) + '\n "cuts": [\n' + rows + "\n ]\n}\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="directory for the JSON files")
    parser.add_argument("--runs", type=int, default=31, help="timed runs per stage")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for file, name, build in (
        ("vgg-like-3x240x320.json", "vgg-like 3x240x320", vgg_like),
        ("mobilenet-like-3x240x320.json", "mobilenet-like 3x240x320", mobilenet_like),
    ):
        stages, names = build()
        write(args.out / file, profile(name, stages, names, args.runs))
        print(f"wrote {args.out / file}")


if __name__ == "__main__":
    main()
