"""Regenerate the profile fixtures: two CNNs at 3×240×320, timed stage by stage with onnxruntime.

Each model is a chain of stages; cut k is the input of stage k (cut 0 = the model's input). Every
stage is exported to ONNX on its own and timed with onnxruntime (1 thread, median of --runs runs);
prefix_ms / suffix_ms are sums of stage medians, FLOPs are counted from the layer shapes. The
output has the partitioner's profile format. Needs torch (the `dev` extra).

    python tests/data/profiles/make_profiles.py --out tests/data/profiles [--runs 31]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import statistics
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import torch
from torch import nn

INPUT_SHAPE = (1, 3, 240, 320)
WARMUP_RUNS = 5


def conv_relu(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU())


def vgg_like() -> tuple[list[nn.Module], list[str]]:
    stages: list[nn.Module] = [
        conv_relu(3, 32),
        conv_relu(32, 32),
        nn.MaxPool2d(2),
        conv_relu(32, 64),
        conv_relu(64, 64),
        nn.MaxPool2d(2),
        conv_relu(64, 128),
        conv_relu(128, 128),
        nn.MaxPool2d(2),
        conv_relu(128, 256),
        conv_relu(256, 256),
        nn.MaxPool2d(2),
        nn.Sequential(conv_relu(256, 512), nn.MaxPool2d(2), nn.Flatten()),
        nn.Sequential(nn.Linear(512 * 7 * 10, 1024), nn.ReLU()),
        nn.Sequential(nn.Linear(1024, 1024), nn.ReLU()),
        nn.Linear(1024, 1000),
    ]
    names = ["input", "relu1a", "relu1b", "pool1", "relu2a", "relu2b", "pool2", "relu3a"]
    names += ["relu3b", "pool3", "relu4a", "relu4b", "pool4", "pool5_flat", "fc1", "fc2"]
    return stages, names


class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1×1 expand, 3×3 depthwise, 1×1 project, residual when shapes allow."""

    def __init__(self, cin: int, cout: int, stride: int, expand: int = 6) -> None:
        super().__init__()
        hidden = cin * expand
        layers: list[nn.Module] = []
        if expand != 1:
            layers += [nn.Conv2d(cin, hidden, 1, bias=False), nn.BatchNorm2d(hidden), nn.ReLU6()]
        layers += [
            nn.Conv2d(hidden, hidden, 3, stride, 1, groups=hidden, bias=False),
            nn.BatchNorm2d(hidden),
            nn.ReLU6(),
            nn.Conv2d(hidden, cout, 1, bias=False),
            nn.BatchNorm2d(cout),
        ]
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x) if self.residual else self.block(x)


def mobilenet_like() -> tuple[list[nn.Module], list[str]]:
    ir = InvertedResidual
    stages: list[nn.Module] = [
        nn.Sequential(nn.Conv2d(3, 32, 3, 2, 1, bias=False), nn.BatchNorm2d(32), nn.ReLU6()),
        ir(32, 16, 1, expand=1),
        ir(16, 24, 2),
        ir(24, 24, 1),
        ir(24, 32, 2),
        nn.Sequential(ir(32, 32, 1), ir(32, 32, 1)),
        ir(32, 64, 2),
        nn.Sequential(ir(64, 64, 1), ir(64, 64, 1)),
        ir(64, 64, 1),
        nn.Sequential(ir(64, 96, 1), ir(96, 96, 1), ir(96, 96, 1)),
        ir(96, 160, 2),
        nn.Sequential(ir(160, 160, 1), ir(160, 160, 1)),
        ir(160, 320, 1),
        nn.Sequential(nn.Conv2d(320, 1280, 1, bias=False), nn.BatchNorm2d(1280), nn.ReLU6()),
        nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten()),
        nn.Linear(1280, 1000),
    ]
    names = ["input", "stem", "block1", "block2", "block3", "block4", "block6", "block7"]
    names += ["block8", "block10", "block13", "block14", "block16", "block17", "conv_last", "pool"]
    return stages, names


def stage_flops(stage: nn.Module, x: torch.Tensor) -> tuple[int, torch.Tensor]:
    """Multiply-adds ×2 of the convolutions and linear layers of a stage, and its output."""
    total = [0]

    def count(module: nn.Module, _: Any, out: torch.Tensor) -> None:
        if isinstance(module, nn.Conv2d):
            k = module.kernel_size[0] * module.kernel_size[1]
            total[0] += 2 * out.numel() * (module.in_channels // module.groups) * k
        elif isinstance(module, nn.Linear):
            total[0] += 2 * module.in_features * module.out_features

    hooks = [m.register_forward_hook(count) for m in stage.modules()]
    try:
        with torch.no_grad():
            out = stage(x)
    finally:
        for h in hooks:
            h.remove()
    return total[0], out


def stage_ms(stage: nn.Module, x: torch.Tensor, runs: int) -> float:
    """Median onnxruntime time of one stage on one thread."""
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(stage, (x,), buffer, dynamo=False)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(buffer.getvalue(), options, providers=["CPUExecutionProvider"])
    feed = {session.get_inputs()[0].name: x.numpy()}
    for _ in range(WARMUP_RUNS):
        session.run(None, feed)
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        session.run(None, feed)
        times.append((time.perf_counter() - started) * 1000)
    return statistics.median(times)


def profile(name: str, stages: list[nn.Module], names: list[str], runs: int) -> dict[str, Any]:
    torch.manual_seed(0)
    for stage in stages:
        stage.eval()
    x = torch.from_numpy(np.random.default_rng(0).standard_normal(INPUT_SHAPE, dtype=np.float32))
    inputs, flops, times = [x], [], []
    for stage in stages:
        f, out = stage_flops(stage, inputs[-1])
        flops.append(f)
        times.append(stage_ms(stage, inputs[-1], runs))
        inputs.append(out)
    cuts = [
        {
            "index": k,
            "tensors": [names[k]],
            "bytes": int(inputs[k].numel() * 4),
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
        "output_bytes": int(inputs[-1].numel() * 4),
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
