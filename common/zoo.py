"""The model zoo: small CNNs defined in code, seeded, exported to ONNX (no downloads).

Three shapes of dataflow graph, so the partitioner meets each case a robot would bring:
- ``vgg``: a plain chain (every cut is one tensor);
- ``resnet``: ResNet-18-like basic blocks with skip connections (cuts inside a block carry two);
- ``mobilenet``: MobileNet-v2-like inverted residuals with depthwise convolutions.

Widths are reduced from the classic networks so that export, split, verification and profiling take
seconds on a two-core machine. torch is imported only inside :func:`export`: the daemons read the
exported ONNX file and never need torch.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.errors import UserError

DEFAULT_INPUT_SHAPE: tuple[int, int, int] = (3, 240, 320)
# Chosen for the demo: its cuts halve the bytes sent for every quarter of the FLOPs moved to
# the robot (stem + max pool already halve the input), so the best cut moves visibly with the
# uplink bandwidth and robot CPU (figures in docs/partitioning.md).
DEFAULT_ZOO_MODEL = "resnet"
ZOO_INPUT_NAME = "input"
ZOO_OUTPUT_NAME = "logits"
ZOO_OPSET = 17
ZOO_SEED = 0
NUM_CLASSES = 1000
# The spatial dimensions are divided by 32 in every zoo model; smaller inputs would vanish.
MIN_SPATIAL_PX = 32
MAX_SPATIAL_PX = 4096


@dataclass(frozen=True)
class ZooModel:
    """One entry of the zoo: what it is and how to build its torch module."""

    name: str
    description: str
    build: Callable[[int], Any]


def _vgg(in_channels: int) -> Any:
    import torch.nn as nn

    layers: list[nn.Module] = []
    channels = in_channels
    # (out channels, convolutions) per stage; every stage ends with a 2x2 max pool.
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
        *layers,
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(channels, NUM_CLASSES),
    )


def _resnet(in_channels: int) -> Any:
    import torch.nn as nn

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

        def forward(self, x: Any) -> Any:
            identity = x if self.down is None else self.down(x)
            out = self.relu(self.bn1(self.conv1(x)))
            out = self.bn2(self.conv2(out))
            return self.relu(out + identity)

    widths = (24, 48, 96, 160)
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
        nn.Linear(cin, NUM_CLASSES),
    )


def _mobilenet(in_channels: int) -> Any:
    import torch.nn as nn

    def conv_bn(cin: int, cout: int, kernel: int, stride: int, groups: int = 1) -> nn.Module:
        return nn.Sequential(
            nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU6(inplace=True),
        )

    class InvertedResidual(nn.Module):
        def __init__(self, cin: int, cout: int, stride: int, expand: int) -> None:
            super().__init__()
            hidden = cin * expand
            self.skip = stride == 1 and cin == cout
            self.body = nn.Sequential(
                conv_bn(cin, hidden, 1, 1),
                conv_bn(hidden, hidden, 3, stride, groups=hidden),  # depthwise
                nn.Conv2d(hidden, cout, 1, bias=False),
                nn.BatchNorm2d(cout),
            )

        def forward(self, x: Any) -> Any:
            out = self.body(x)
            return x + out if self.skip else out

    # (expansion, out channels, repeats, first stride), a shortened MobileNet-v2 schedule.
    schedule = ((1, 16, 1, 1), (4, 24, 2, 2), (4, 32, 2, 2), (4, 64, 2, 2), (4, 96, 1, 1))
    layers: list[nn.Module] = [conv_bn(in_channels, 16, 3, 2)]
    cin = 16
    for expand, cout, repeats, stride in schedule:
        for r in range(repeats):
            layers.append(InvertedResidual(cin, cout, stride if r == 0 else 1, expand))
            cin = cout
    layers += [
        conv_bn(cin, 256, 1, 1),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(256, NUM_CLASSES),
    ]
    return nn.Sequential(*layers)


ZOO_MODELS: dict[str, ZooModel] = {
    m.name: m
    for m in (
        ZooModel("vgg", "VGG-like plain chain of 3x3 convolutions and max pools", _vgg),
        ZooModel("resnet", "ResNet-18-like: 8 basic blocks with skip connections", _resnet),
        ZooModel("mobilenet", "MobileNet-v2-like: inverted residuals, depthwise convs", _mobilenet),
    )
}


def check_input_shape(input_shape: tuple[int, ...]) -> tuple[int, int, int]:
    """Validate a zoo input shape (C, H, W) and return it; raises UserError naming the problem."""
    if len(input_shape) != 3:
        raise UserError(
            f"zoo input shape must be CxHxW (3 dimensions), got {format_shape(input_shape)}"
        )
    c, h, w = input_shape
    if c < 1 or c > 64:
        raise UserError(f"zoo input shape: channels must be 1..64, got {c}")
    for label, px in (("height", h), ("width", w)):
        if not MIN_SPATIAL_PX <= px <= MAX_SPATIAL_PX:
            raise UserError(
                f"zoo input shape: {label} must be {MIN_SPATIAL_PX}..{MAX_SPATIAL_PX} px, got {px}"
            )
    return (c, h, w)


def format_shape(shape: tuple[int, ...]) -> str:
    """``(3, 240, 320)`` → ``3x240x320``."""
    return "x".join(str(d) for d in shape)


def parse_shape(text: str) -> tuple[int, ...]:
    """``3x240x320`` → ``(3, 240, 320)``; raises UserError on anything else."""
    parts = text.strip().lower().split("x")
    try:
        dims = tuple(int(p) for p in parts)
    except ValueError:
        raise UserError(
            f"bad shape {text!r}: expected dimensions joined by 'x', e.g. 3x240x320"
        ) from None
    if not dims or any(d <= 0 for d in dims):
        raise UserError(f"bad shape {text!r}: every dimension must be a positive integer")
    return dims


def get(name: str) -> ZooModel:
    """The zoo entry called ``name``; raises UserError listing the known names otherwise."""
    try:
        return ZOO_MODELS[name]
    except KeyError:
        raise UserError(
            f"unknown zoo model {name!r}; known: {', '.join(sorted(ZOO_MODELS))}"
        ) from None


def export(name: str, out: Path, input_shape: tuple[int, ...] = DEFAULT_INPUT_SHAPE) -> Path:
    """Build zoo model ``name`` with seeded weights and write it to ``out`` as ONNX (batch 1).

    The file is written next to ``out`` and renamed into place, so a reader never sees half a
    model. The same name, shape and torch version give a byte-identical file, hence the same
    digest on the robot and on the cloud.
    """
    entry = get(name)
    shape = check_input_shape(tuple(input_shape))
    try:
        import torch
    except ImportError:
        raise UserError(
            "exporting the model zoo needs torch (pip install 'elasticfog[zoo]'); "
            "or pass an ONNX file instead of zoo:NAME"
        ) from None

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(ZOO_SEED)
        module = entry.build(shape[0]).eval()
        _init_weights(module)
        dummy = torch.zeros((1, *shape), dtype=torch.float32)
        fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
        os.close(fd)
        try:
            with warnings.catch_warnings():
                # The TorchScript exporter is deprecated in favour of the dynamo one, which
                # needs onnxscript; it still produces the plain opset-17 graph we want.
                warnings.simplefilter("ignore")
                torch.onnx.export(
                    module,
                    (dummy,),
                    tmp,
                    dynamo=False,
                    opset_version=ZOO_OPSET,
                    input_names=[ZOO_INPUT_NAME],
                    output_names=[ZOO_OUTPUT_NAME],
                    do_constant_folding=True,
                )
            os.replace(tmp, out)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    return out


def _init_weights(module: Any) -> None:
    """Seeded He initialisation with non-trivial batch-norm statistics.

    Random running statistics keep the folded convolutions from being plain He weights, and the
    small head keeps logits near unit scale so float32 verification at 1e-5 is meaningful.
    """
    import torch
    import torch.nn as nn

    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.0)
                m.bias.uniform_(-0.1, 0.1)
                for stat, low, high in ((m.running_mean, -0.1, 0.1), (m.running_var, 0.5, 2.0)):
                    if stat is not None:
                        stat.uniform_(low, high)
            elif isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, 0.0, 0.01)
                nn.init.zeros_(m.bias)
