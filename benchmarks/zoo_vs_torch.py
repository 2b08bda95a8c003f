"""The zoo's ONNX graphs (common.zoo_nets) against the torch modules they were first written as.

The zoo used to define its five networks as torch modules and export them with torch; it now
writes the same graphs with ``onnx.helper``. This script keeps the torch definitions (here only)
and checks, per model: with the zoo's seeded weights copied into the torch module (convolution,
batch norm before folding, classifier),

- the outputs: torch itself, and the module exported the old way (TorchScript exporter, opset 17,
  constant folding), both against the zoo's file in onnxruntime, on a photograph and on random
  images (max abs error, and relative to the largest logit);
- the graphs: the node sequence (op types and attributes, ``Constant`` nodes aside), the folded
  weights node for node, the parameter counts and the FLOPs;
- the partitioner: ``split_model`` on both files with the default options, the cuts (tensors
  mapped node for node, dtype and shape of every cut tensor, bytes, robot and cloud FLOPs), the
  dominated and failed ones.

Needs torch (the ``bench`` extra); figures in docs/partitioning.md.

    python benchmarks/zoo_vs_torch.py [--shape 3x240x320] [--models vgg,resnet,...] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import torch
import torch.nn as nn
from onnx import numpy_helper
from skimage import data

from common import zoo
from common.partition import DOMINATED_PREFIX, Partition, split_model
from common.zoo_nets import BN_EPS, LayerKind, SeededLayer, build_network

RANDOM_IMAGES = 3

# -- the torch definitions the zoo had (common/zoo.py before the zoo was written in ONNX) --


def torch_vgg(in_channels: int) -> nn.Module:
    layers: list[nn.Module] = []
    channels = in_channels
    for out_ch, convs in ((16, 1), (32, 2), (64, 2), (96, 2), (128, 2)):
        for _ in range(convs):
            layers += [
                nn.Conv2d(channels, out_ch, 3, padding=1, bias=False),
                nn.BatchNorm2d(out_ch),
                nn.ReLU(inplace=True),
            ]
            channels = out_ch
        layers.append(nn.MaxPool2d(2))
    return nn.Sequential(
        *layers, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(channels, zoo.NUM_CLASSES)
    )


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.down: nn.Module | None = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(
                nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.down is None else self.down(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


def torch_resnet(in_channels: int, widths: tuple[int, ...] = (24, 48, 96, 160)) -> nn.Module:
    blocks: list[nn.Module] = []
    cin = widths[0]
    for i, width in enumerate(widths):
        for j in range(2):
            blocks.append(BasicBlock(cin, width, 2 if (i > 0 and j == 0) else 1))
            cin = width
    return nn.Sequential(
        nn.Conv2d(in_channels, widths[0], 7, 2, 3, bias=False),
        nn.BatchNorm2d(widths[0]),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(3, 2, 1),
        *blocks,
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(cin, zoo.NUM_CLASSES),
    )


def _conv_bn(cin: int, cout: int, kernel: int, stride: int, groups: int = 1) -> nn.Module:
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU6(inplace=True),
    )


class InvertedResidual(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, expand: int, expand_at_one: bool) -> None:
        super().__init__()
        hidden = cin * expand
        self.skip = stride == 1 and cin == cout
        layers: list[nn.Module] = []
        if expand != 1 or expand_at_one:
            layers.append(_conv_bn(cin, hidden, 1, 1))
        self.body = nn.Sequential(
            *layers,
            _conv_bn(hidden, hidden, 3, stride, groups=hidden),
            nn.Conv2d(hidden, cout, 1, bias=False),
            nn.BatchNorm2d(cout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.body(x)
        return x + out if self.skip else out


def torch_inverted_residuals(
    in_channels: int,
    stem: int,
    schedule: tuple[tuple[int, int, int, int], ...],
    head: int,
    *,
    expand_at_one: bool,
) -> nn.Module:
    layers: list[nn.Module] = [_conv_bn(in_channels, stem, 3, 2)]
    cin = stem
    for expand, cout, repeats, stride in schedule:
        for r in range(repeats):
            layers.append(
                InvertedResidual(cin, cout, stride if r == 0 else 1, expand, expand_at_one)
            )
            cin = cout
    layers += [
        _conv_bn(cin, head, 1, 1),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(head, zoo.NUM_CLASSES),
    ]
    return nn.Sequential(*layers)


def torch_mobilenet(in_channels: int) -> nn.Module:
    schedule = ((1, 16, 1, 1), (4, 24, 2, 2), (4, 32, 2, 2), (4, 64, 2, 2), (4, 96, 1, 1))
    return torch_inverted_residuals(in_channels, 16, schedule, 256, expand_at_one=True)


def torch_mobilenet_v2(in_channels: int) -> nn.Module:
    schedule = (
        (1, 16, 1, 1),
        (6, 24, 2, 2),
        (6, 32, 3, 2),
        (6, 64, 4, 2),
        (6, 96, 3, 1),
        (6, 160, 3, 2),
        (6, 320, 1, 1),
    )
    return torch_inverted_residuals(in_channels, 32, schedule, 1280, expand_at_one=False)


TORCH_NETWORKS = {
    "vgg": torch_vgg,
    "resnet": torch_resnet,
    "mobilenet": torch_mobilenet,
    "resnet18": lambda c: torch_resnet(c, (64, 128, 256, 512)),
    "mobilenet_v2": torch_mobilenet_v2,
}


class CameraInput(nn.Module):
    """The zoo's front end as it was in torch: uint8 N×H×W×C → normalized float N×C×H×W."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        mean, std = zoo.zoo_normalization(channels)
        self.scale: torch.Tensor
        self.offset: torch.Tensor
        scale = [1.0 / (zoo.PIXEL_MAX * s) for s in std]
        offset = [m / s for m, s in zip(mean, std, strict=True)]
        self.register_buffer("scale", torch.tensor(scale).reshape(1, 1, 1, -1))
        self.register_buffer("offset", torch.tensor(offset).reshape(1, 1, 1, -1))

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return (image.to(torch.float32) * self.scale - self.offset).permute(0, 3, 1, 2)


# -- the comparison --


def execution_order(module: nn.Module, feed: torch.Tensor) -> list[nn.Module]:
    """The Conv2d, BatchNorm2d and Linear modules in the order the forward pass runs them."""
    order: list[nn.Module] = []
    hooks = [
        m.register_forward_hook(lambda m, _i, _o: order.append(m))
        for m in module.modules()
        if isinstance(m, nn.Conv2d | nn.BatchNorm2d | nn.Linear)
    ]
    try:
        with torch.no_grad():
            module(feed)
    finally:
        for h in hooks:
            h.remove()
    return order


def copy_weights(module: nn.Module, layers: Sequence[SeededLayer], feed: torch.Tensor) -> None:
    """The zoo's seeded layers (node order) into the torch module (execution order)."""
    order = execution_order(module, feed)
    with torch.no_grad():
        for layer in layers:
            if layer.kind is LayerKind.CONV_BN:
                conv, bn = order.pop(0), order.pop(0)
                assert isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d), layer.name
                pairs = [
                    (conv.weight, "weight"),
                    (bn.weight, "bn_weight"),
                    (bn.bias, "bn_bias"),
                    (bn.running_mean, "bn_mean"),
                    (bn.running_var, "bn_var"),
                ]
                assert bn.eps == BN_EPS
            else:
                linear = order.pop(0)
                assert isinstance(linear, nn.Linear), layer.name
                pairs = [(linear.weight, "weight"), (linear.bias, "bias")]
            for tensor, key in pairs:
                assert tensor is not None
                value = torch.from_numpy(layer.params[key])
                assert tensor.shape == value.shape, (layer.name, key, tensor.shape, value.shape)
                tensor.copy_(value)
    assert not order, f"torch modules left without weights: {order}"


def torch_export(module: nn.Module, shape: tuple[int, int, int], out: Path) -> None:
    """The zoo's export before it was written in ONNX."""
    dummy = torch.zeros(zoo.file_input_shape(shape), dtype=torch.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (dummy,),
            str(out),
            dynamo=False,
            opset_version=zoo.ZOO_OPSET,
            input_names=[zoo.ZOO_INPUT_NAME],
            output_names=[zoo.ZOO_OUTPUT_NAME],
            do_constant_folding=True,
        )


def images(shape: tuple[int, int, int]) -> list[np.ndarray]:
    """The astronaut photograph at the input size, then seeded random images: 1×H×W×C uint8."""
    c, h, w = shape
    photo = cv2.resize(data.astronaut(), (w, h), interpolation=cv2.INTER_AREA)
    if c != 3:
        photo = np.repeat(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)[:, :, None], c, axis=2)
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 256, (h, w, c), dtype=np.uint8) for _ in range(RANDOM_IMAGES)]
    return [np.ascontiguousarray(x[None]) for x in (photo, *noise)]


def ort_run(path: Path, image: np.ndarray) -> np.ndarray:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return session.run([zoo.ZOO_OUTPUT_NAME], {zoo.ZOO_INPUT_NAME: image})[0]


def errors(want: list[np.ndarray], got: list[np.ndarray]) -> tuple[float, float]:
    """Largest absolute difference, and that over the largest |logit| of the reference."""
    abs_err = max(float(np.max(np.abs(w - g))) for w, g in zip(want, got, strict=True))
    scale = max(float(np.max(np.abs(w))) for w in want)
    return abs_err, abs_err / scale


def _attrs(node: onnx.NodeProto) -> dict[str, Any]:
    # Attributes at their default values are left out by the zoo (dilations 1, Gemm's alpha and
    # beta 1, ceil_mode 0).
    defaults: dict[str, Any] = {"dilations": [1, 1], "alpha": 1.0, "beta": 1.0, "ceil_mode": 0}
    got = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    return {k: v for k, v in got.items() if defaults.get(k, object()) != v}


def node_map(old: onnx.ModelProto, new: onnx.ModelProto) -> dict[str, str]:
    """torch tensor name → zoo tensor name, node for node; fails where the graphs differ."""
    old_nodes = [n for n in old.graph.node if n.op_type != "Constant"]
    new_nodes = list(new.graph.node)
    assert len(old_nodes) == len(new_nodes), (len(old_nodes), len(new_nodes))
    names = {i.name: i.name for i in old.graph.input}
    for a, b in zip(old_nodes, new_nodes, strict=True):
        assert a.op_type == b.op_type, (a.name, a.op_type, b.name, b.op_type)
        assert _attrs(a) == _attrs(b), (a.name, _attrs(a), b.name, _attrs(b))
        data_in = [names[t] for t in a.input if t in names]
        assert data_in == [t for t in b.input if t in names.values()], (a.name, b.name)
        names.update(zip(a.output, b.output, strict=True))
    return names


def weight_diff(old: onnx.ModelProto, new: onnx.ModelProto) -> tuple[float, int, int]:
    """Largest difference between the folded weights node for node, and the numbers of values
    in each file's initializers and Constant nodes."""
    old_init = {t.name: numpy_helper.to_array(t) for t in old.graph.initializer}
    new_init = {t.name: numpy_helper.to_array(t) for t in new.graph.initializer}
    old_nodes = [n for n in old.graph.node if n.op_type != "Constant"]
    worst = 0.0
    for a, b in zip(old_nodes, new.graph.node, strict=True):
        if a.op_type not in ("Conv", "Gemm"):
            continue
        for ta, tb in zip(a.input[1:], b.input[1:], strict=True):
            wa, wb = old_init[ta], new_init[tb]
            assert wa.shape == wb.shape, (a.name, wa.shape, wb.shape)
            worst = max(worst, float(np.max(np.abs(wa - wb))))
    constants = sum(
        numpy_helper.to_array(a.t).size
        for n in old.graph.node
        if n.op_type == "Constant"
        for a in n.attribute
    )
    old_values = sum(a.size for a in old_init.values()) + constants
    return worst, old_values, sum(a.size for a in new_init.values())


def cut_rows(part: Partition, names: dict[str, str] | None = None) -> list[tuple[Any, ...]]:
    """Per cut: (tensors, dtype and shape of each, bytes, robot FLOPs, cloud FLOPs)."""

    def spec(t: str) -> tuple[str, tuple[int, ...]]:
        return (part.specs[t].dtype, part.specs[t].shape)

    return [
        (
            [names[t] if names else t for t in c.tensors],
            [spec(t) for t in c.tensors],
            c.bytes,
            c.prefix_flops,
            c.suffix_flops,
        )
        for c in part.cuts
    ]


def compare(name: str, shape: tuple[int, int, int], work: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    new_path = zoo.export(name, work / f"{name}.zoo.onnx", shape)
    zoo_build_s = time.perf_counter() - t0
    new = onnx.load(str(new_path))
    _, layers = build_network(name, shape)

    network = TORCH_NETWORKS[name](shape[0])
    module = nn.Sequential(CameraInput(shape[0]), network).eval()
    feeds = images(shape)
    copy_weights(module, layers, torch.from_numpy(feeds[0]))
    old_path = work / f"{name}.torch.onnx"
    t0 = time.perf_counter()
    torch_export(module, shape, old_path)
    torch_export_s = time.perf_counter() - t0
    old = onnx.load(str(old_path))

    with torch.no_grad():
        eager = [module(torch.from_numpy(x)).numpy() for x in feeds]
    new_out = [ort_run(new_path, x) for x in feeds]
    old_out = [ort_run(old_path, x) for x in feeds]
    eager_abs, eager_rel = errors(eager, new_out)
    export_abs, export_rel = errors(old_out, new_out)

    names = node_map(old, new)
    folded_diff, old_values, new_values = weight_diff(old, new)
    parts = {}
    for label, path in (("torch", old_path), ("zoo", new_path)):
        parts[label] = split_model(path, work / f"{name}.{label}.split")
    same_cuts = cut_rows(parts["torch"], names) == cut_rows(parts["zoo"])

    def excluded(part: Partition) -> tuple[int, int]:
        dominated = sum(e.reason.startswith(DOMINATED_PREFIX) for e in part.excluded)
        return dominated, len(part.excluded) - dominated

    torch_params = sum(p.numel() for p in network.parameters())
    zoo_params = sum(layer.parameter_count for layer in layers)
    return {
        "model": name,
        "nodes": len(new.graph.node),
        "torch_nodes": len(old.graph.node),
        "torch_params": torch_params,
        "zoo_params": zoo_params,
        "torch_file_values": old_values,
        "zoo_file_values": new_values,
        "folded_weight_max_diff": folded_diff,
        "torch_gflops": parts["torch"].cuts[0].suffix_flops / 1e9,
        "zoo_gflops": parts["zoo"].cuts[0].suffix_flops / 1e9,
        "torch_cuts": len(parts["torch"].cuts),
        "zoo_cuts": len(parts["zoo"].cuts),
        "same_cuts": same_cuts,
        "torch_dominated_failed": excluded(parts["torch"]),
        "zoo_dominated_failed": excluded(parts["zoo"]),
        "zoo_max_cut_err": max(c.max_abs_err or 0.0 for c in parts["zoo"].cuts),
        "eager_max_abs": eager_abs,
        "eager_max_rel": eager_rel,
        "export_max_abs": export_abs,
        "export_max_rel": export_rel,
        "zoo_build_s": zoo_build_s,
        "torch_export_s": torch_export_s,
    }


def table(rows: list[dict[str, Any]], shape: tuple[int, int, int]) -> str:
    head = (
        f"zoo (onnx.helper) vs torch, input {zoo.format_shape(shape)}, "
        "the zoo's weights in both\n\n"
        "| model | nodes zoo / torch | params zoo / torch | values in file zoo / torch "
        "| folded weights max diff | GFLOP zoo / torch | cuts zoo / torch, same | "
        "dominated, failed zoo / torch | torch eager vs zoo: max abs, rel | "
        "torch export vs zoo: max abs, rel | build s zoo / torch export |\n" + "|---" * 11 + "|\n"
    )
    lines = [
        f"| {r['model']} | {r['nodes']} / {r['torch_nodes']} "
        f"| {r['zoo_params']:,} / {r['torch_params']:,} "
        f"| {r['zoo_file_values']:,} / {r['torch_file_values']:,} "
        f"| {r['folded_weight_max_diff']:.1e} "
        f"| {r['zoo_gflops']:.3f} / {r['torch_gflops']:.3f} "
        f"| {r['zoo_cuts']} / {r['torch_cuts']}, {'yes' if r['same_cuts'] else 'NO'} "
        f"| {r['zoo_dominated_failed'][0]}, {r['zoo_dominated_failed'][1]} / "
        f"{r['torch_dominated_failed'][0]}, {r['torch_dominated_failed'][1]} "
        f"| {r['eager_max_abs']:.1e}, {r['eager_max_rel']:.1e} "
        f"| {r['export_max_abs']:.1e}, {r['export_max_rel']:.1e} "
        f"| {r['zoo_build_s']:.2f} / {r['torch_export_s']:.2f} |"
        for r in rows
    ]
    return head + "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", default="3x240x320", help="zoo input shape CxHxW")
    parser.add_argument("--models", default=",".join(zoo.ZOO_MODELS), help="comma-separated")
    parser.add_argument("--json", action="store_true", help="print the raw figures as JSON")
    args = parser.parse_args(argv)
    shape = zoo.check_input_shape(zoo.parse_shape(args.shape))
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name in args.models.split(","):
            print(f"{name} ...", file=sys.stderr, flush=True)
            rows.append(compare(name, shape, Path(work)))
    print(json.dumps(rows, indent=1) if args.json else table(rows, shape))
    return 0 if all(r["same_cuts"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
