"""The model zoo: CNNs defined in code, seeded, exported to ONNX (no downloads).

Every zoo model takes the camera image: input ``input``, uint8, 1×H×W×C (channels last, raw
levels 0..255), with the front end in the graph: cast to float, scale by 1/255, subtract the
mean and divide by the standard deviation per channel (ImageNet's for 3 channels, their average
for any other count), then NHWC→NCHW. So cut 0 of the partitioner is the uint8 image, a quarter
of the bytes of the float tensor the network starts from. The zoo input shape (``3x240x320``)
keeps its meaning C×H×W in every option and config; the file's input is 1×H×W×C.

Channel order: the camera image is **RGB**, because that is what the robot feeds a 3-channel
image input (``common.image_input.InputAdapter`` turns the sources' BGR frames into RGB for every
3-channel input, uint8 included); 1-channel inputs get the grey image. ``CAMERA_ORDER`` says it in
one place; a BGR camera order would add the channel reorder (a Gather) to the front end.

Five networks, so the partitioner meets each case a robot would bring:

- ``vgg``: a plain chain (every cut is one tensor);
- ``resnet``: ResNet-18-like basic blocks with skip connections (cuts inside a block carry two);
- ``mobilenet``: MobileNet-v2-like inverted residuals with depthwise convolutions;
- ``resnet18``: the standard ResNet-18 layout (widths 64-128-256-512, 1000 classes);
- ``mobilenet_v2``: the standard MobileNet-v2 (width 1.0, last conv 1280, 1000 classes).

The first three have reduced widths so that export, split, verification and profiling take seconds
on a two-core machine; the last two are full-width, for the testbed to run a ResNet/MobileNet-class
network at 224×224 or 240×320. Weights are seeded, not trained: the graphs, sizes and times are
the real networks', the predictions are not. torch is imported only inside :func:`export`: the
daemons read the exported ONNX file and never need torch.

Other packages add models built as ONNX graphs in code (no torch, no weights to learn) through
the ``elasticfog.zoo`` entry point group, each a :class:`ZooGraph` with its own inputs and
format version: ``stereo`` (nav.zoo_entry, the stereo navigation pipeline; its inputs are the
left and right camera images). ``common`` never imports them by name.
"""

from __future__ import annotations

import functools
import os
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
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
# Bumped whenever an exported model changes for the same name and shape (2: uint8 image input).
ZOO_FORMAT = 2
ZOO_SEED = 0
NUM_CLASSES = 1000
ZOO_INPUT_DTYPE = "uint8"
# What the robot feeds a 3-channel uint8 input (common.image_input.InputAdapter): RGB. "bgr" would
# reorder the channels in the front end.
CAMERA_ORDER = "rgb"
# ImageNet statistics in RGB order (torchvision's), for 3 channels; other channel counts use
# their averages for every channel (a grey image, typically).
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)
GREY_MEAN = 0.449
GREY_STD = 0.226
PIXEL_MAX = 255.0
# The spatial dimensions are divided by 32 in every zoo model; smaller inputs would vanish.
MIN_SPATIAL_PX = 32
MAX_SPATIAL_PX = 4096


@dataclass(frozen=True)
class ZooModel:
    """One entry of the zoo: what it is and how to build its torch module."""

    name: str
    description: str
    build: Callable[[int], Any]


# Where other packages register their ZooGraph models.
ZOO_ENTRY_POINT_GROUP = "elasticfog.zoo"


@dataclass(frozen=True)
class ZooGraph:
    """A zoo entry built directly as an ONNX graph: ``build`` takes the image shape (C, H, W)
    and returns the onnx.ModelProto. ``format`` is bumped when the graph changes for the same
    name and shape (it names the cached file)."""

    name: str
    description: str
    build: Callable[[tuple[int, int, int]], Any]
    format: int = 1


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


def _resnet(in_channels: int, widths: tuple[int, ...] = (24, 48, 96, 160)) -> Any:
    """Stem 7×7/2 + max pool, two basic blocks per width (the first strided after stage 1)."""
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


def _inverted_residuals(
    in_channels: int,
    stem: int,
    schedule: tuple[tuple[int, int, int, int], ...],
    head: int,
    *,
    expand_at_one: bool,
) -> Any:
    """A MobileNet-v2 network: 3×3/2 stem, inverted residual blocks, 1×1 head, classifier.

    ``schedule`` holds (expansion, out channels, repeats, first stride) per stage. The standard
    network has no expansion convolution where the expansion is 1; ``expand_at_one`` keeps it
    (the small ``mobilenet``).
    """
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
            layers: list[nn.Module] = []
            if expand != 1 or expand_at_one:
                layers.append(conv_bn(cin, hidden, 1, 1))
            self.body = nn.Sequential(
                *layers,
                conv_bn(hidden, hidden, 3, stride, groups=hidden),  # depthwise
                nn.Conv2d(hidden, cout, 1, bias=False),
                nn.BatchNorm2d(cout),
            )

        def forward(self, x: Any) -> Any:
            out = self.body(x)
            return x + out if self.skip else out

    layers: list[nn.Module] = [conv_bn(in_channels, stem, 3, 2)]
    cin = stem
    for expand, cout, repeats, stride in schedule:
        for r in range(repeats):
            layers.append(InvertedResidual(cin, cout, stride if r == 0 else 1, expand))
            cin = cout
    layers += [
        conv_bn(cin, head, 1, 1),
        nn.AdaptiveAvgPool2d(1),
        nn.Flatten(),
        nn.Linear(head, NUM_CLASSES),
    ]
    return nn.Sequential(*layers)


def _mobilenet(in_channels: int) -> Any:
    # A shortened MobileNet-v2 schedule with expansion 4 and a 256-wide head.
    schedule = ((1, 16, 1, 1), (4, 24, 2, 2), (4, 32, 2, 2), (4, 64, 2, 2), (4, 96, 1, 1))
    return _inverted_residuals(in_channels, 16, schedule, 256, expand_at_one=True)


def _mobilenet_v2(in_channels: int) -> Any:
    # Sandler et al. 2018, table 2 (width multiplier 1.0); the classifier's dropout is a no-op in
    # inference and left out.
    schedule = (
        (1, 16, 1, 1),
        (6, 24, 2, 2),
        (6, 32, 3, 2),
        (6, 64, 4, 2),
        (6, 96, 3, 1),
        (6, 160, 3, 2),
        (6, 320, 1, 1),
    )
    return _inverted_residuals(in_channels, 32, schedule, 1280, expand_at_one=False)


def _resnet18(in_channels: int) -> Any:
    # He et al. 2016, table 1: two basic blocks per stage, widths 64-128-256-512.
    return _resnet(in_channels, (64, 128, 256, 512))


def _camera_input(channels: int, order: str = CAMERA_ORDER) -> Any:
    """The front end as a torch module: uint8 N×H×W×C camera image → normalized float N×C×H×W.

    (x/255 − mean)/std is computed as x·(1/(255·std)) − mean/std: one Mul and one Sub per pixel.
    """
    import torch
    import torch.nn as nn

    mean, std = zoo_normalization(channels)

    class CameraInput(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.scale: torch.Tensor
            self.offset: torch.Tensor
            self.rgb_index: torch.Tensor
            self.register_buffer(
                "scale", torch.tensor([1.0 / (PIXEL_MAX * s) for s in std]).reshape(1, 1, 1, -1)
            )
            self.register_buffer(
                "offset",
                torch.tensor([m / s for m, s in zip(mean, std, strict=True)]).reshape(1, 1, 1, -1),
            )
            self.reorder = order == "bgr" and channels == 3
            if self.reorder:
                self.register_buffer("rgb_index", torch.tensor([2, 1, 0]))

        def forward(self, image: torch.Tensor) -> torch.Tensor:
            x = image.to(torch.float32)
            if self.reorder:  # BGR → RGB: a Gather, after the cast so no cut but cut 0 is uint8
                x = x.index_select(3, self.rgb_index)
            return (x * self.scale - self.offset).permute(0, 3, 1, 2)

    return CameraInput()


def zoo_normalization(channels: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per-channel (mean, std) of the zoo's front end, in the model's channel order (RGB)."""
    if channels == 3:
        return IMAGENET_MEAN, IMAGENET_STD
    return (GREY_MEAN,) * channels, (GREY_STD,) * channels


ZOO_MODELS: dict[str, ZooModel] = {
    m.name: m
    for m in (
        ZooModel("vgg", "VGG-like plain chain of 3x3 convolutions and max pools", _vgg),
        ZooModel("resnet", "ResNet-18-like: 8 basic blocks with skip connections", _resnet),
        ZooModel("mobilenet", "MobileNet-v2-like: inverted residuals, depthwise convs", _mobilenet),
        ZooModel("resnet18", "ResNet-18: widths 64-128-256-512, 11.7 M parameters", _resnet18),
        ZooModel("mobilenet_v2", "MobileNet-v2, width 1.0: 3.5 M parameters", _mobilenet_v2),
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


def file_input_shape(shape: tuple[int, int, int]) -> tuple[int, int, int, int]:
    """The exported file's input shape for zoo shape (C, H, W): the camera image, 1×H×W×C."""
    c, h, w = shape
    return (1, h, w, c)


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


@functools.cache
def graph_models() -> dict[str, ZooGraph]:
    """The ZooGraph models other packages register (entry point group ``elasticfog.zoo``)."""
    found: dict[str, ZooGraph] = {}
    for ep in sorted(entry_points(group=ZOO_ENTRY_POINT_GROUP), key=lambda e: e.name):
        entry = ep.load()
        if not isinstance(entry, ZooGraph) or entry.name in ZOO_MODELS:
            raise UserError(f"zoo entry point {ep.name!r} ({ep.value}) is not a new ZooGraph")
        found[entry.name] = entry
    return found


def all_models() -> dict[str, ZooModel | ZooGraph]:
    """Every zoo entry: the torch networks, then the graph models."""
    return {**ZOO_MODELS, **graph_models()}


def cache_version(entry: ZooModel | ZooGraph) -> int:
    """The format version in the cached file name of an entry."""
    return entry.format if isinstance(entry, ZooGraph) else ZOO_FORMAT


def get(name: str) -> ZooModel | ZooGraph:
    """The zoo entry called ``name``; raises UserError listing the known names otherwise."""
    entry = ZOO_MODELS.get(name) or graph_models().get(name)
    if entry is None:
        known = [*sorted(ZOO_MODELS), *sorted(graph_models())]
        raise UserError(f"unknown zoo model {name!r}; known: {', '.join(known)}")
    return entry


def export(name: str, out: Path, input_shape: tuple[int, ...] = DEFAULT_INPUT_SHAPE) -> Path:
    """Build zoo model ``name`` with seeded weights and write it to ``out`` as ONNX (batch 1).

    ``input_shape`` is C×H×W; the file's input is the uint8 camera image 1×H×W×C.

    The file is written next to ``out`` and renamed into place, so a reader never sees half a
    model. The same name, shape and torch version give a byte-identical file, hence the same
    digest on the robot and on the cloud.
    """
    entry = get(name)
    shape = check_input_shape(tuple(input_shape))
    if isinstance(entry, ZooGraph):
        return _write_graph(entry, Path(out), shape)
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
        network = entry.build(shape[0])
        _init_weights(network)
        # The front end first, so that the file's input (cut 0) is the uint8 camera image.
        module = torch.nn.Sequential(_camera_input(shape[0]), network).eval()
        dummy = torch.zeros(file_input_shape(shape), dtype=torch.uint8)
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


def _write_graph(entry: ZooGraph, out: Path, shape: tuple[int, int, int]) -> Path:
    """Save a graph model beside ``out`` and rename it into place (as export does)."""
    import onnx

    model = entry.build(shape)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    try:
        onnx.save(model, tmp)
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
