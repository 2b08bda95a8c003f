"""The model zoo: CNNs written as ONNX graphs in code, with seeded weights (no downloads, no torch).

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

The first three have reduced widths so that building, splitting, verification and profiling take
seconds on a two-core machine; the last two are full-width, for the testbed to run a
ResNet/MobileNet-class network at 224×224 or 240×320. Weights are seeded, not trained: the graphs,
sizes and times are the real networks', the predictions are not. The graphs are written with
``onnx.helper`` in :mod:`common.zoo_nets` (imported only when a model is built, so listing the zoo
stays light), node for node what the torch modules they were first defined as exported to;
``benchmarks/zoo_vs_torch.py`` checks that.

Other packages add models built as ONNX graphs in code (no weights to learn) through the
``elasticfog.zoo`` entry point group, each a :class:`ZooGraph` with its own inputs and format
version: ``stereo`` (nav.zoo_entry, the stereo navigation pipeline; its inputs are the left and
right camera images). ``common`` never imports them by name.

Build options: a ZooGraph may take options besides the shape (``ZooGraph.options``, each with
its default; zoo:stereo takes its camera's geometry, fleet.yaml ``nav.camera``). The cached file
of a model built with options off their defaults carries them in its name
(:func:`cache_file_name`), so two geometries never share a file; at the defaults the name is the
one it had before options existed, and so are the bytes.
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from common.errors import UserError
from common.zoo_format import (
    CAMERA_ORDER as CAMERA_ORDER,
)
from common.zoo_format import (
    GREY_MEAN as GREY_MEAN,
)
from common.zoo_format import (
    GREY_STD as GREY_STD,
)
from common.zoo_format import (
    IMAGENET_MEAN as IMAGENET_MEAN,
)
from common.zoo_format import (
    IMAGENET_STD as IMAGENET_STD,
)
from common.zoo_format import (
    NUM_CLASSES as NUM_CLASSES,
)
from common.zoo_format import (
    PIXEL_MAX as PIXEL_MAX,
)
from common.zoo_format import (
    ZOO_FORMAT as ZOO_FORMAT,
)
from common.zoo_format import (
    ZOO_INPUT_DTYPE as ZOO_INPUT_DTYPE,
)
from common.zoo_format import (  # re-exported: the zoo's conventions
    ZOO_INPUT_NAME as ZOO_INPUT_NAME,
)
from common.zoo_format import (
    ZOO_OPSET as ZOO_OPSET,
)
from common.zoo_format import (
    ZOO_OUTPUT_NAME as ZOO_OUTPUT_NAME,
)
from common.zoo_format import (
    ZOO_SEED as ZOO_SEED,
)
from common.zoo_format import (
    file_input_shape as file_input_shape,
)
from common.zoo_format import (
    zoo_normalization as zoo_normalization,
)

DEFAULT_INPUT_SHAPE: tuple[int, int, int] = (3, 240, 320)
# Chosen for the demo: its cuts halve the bytes sent for every quarter of the FLOPs moved to
# the robot (stem + max pool already halve the input), so the best cut moves visibly with the
# uplink bandwidth and robot CPU (figures in docs/partitioning.md).
DEFAULT_ZOO_MODEL = "resnet"
WEIGHTS_NOTE = (
    "The CNNs' weights are seeded, not trained: their graphs, sizes and times are the real "
    "networks', their outputs (a top-5, a class index) mean nothing. For real predictions give "
    "a trained ONNX file (model: PATH, --model PATH)."
)
"""What `elasticfog model zoo list` prints under the table: a top-5 of a zoo model is no class."""
# The spatial dimensions are divided by 32 in every zoo model; smaller inputs would vanish.
MIN_SPATIAL_PX = 32
MAX_SPATIAL_PX = 4096

# Where other packages register their ZooGraph models.
ZOO_ENTRY_POINT_GROUP = "elasticfog.zoo"


ZooOptions = Mapping[str, float]
"""Build options of a zoo model by name (fleet.yaml `nav.camera` for zoo:stereo)."""


@dataclass(frozen=True)
class ZooGraph:
    """A zoo entry built as an ONNX graph: ``build`` takes the image shape (C, H, W), and each
    of ``options`` as a keyword argument when the entry has any, and returns the
    onnx.ModelProto. ``format`` is bumped when the graph changes for the same name, shape and
    options (it names the cached file). ``options`` are the names the entry takes with their
    defaults."""

    name: str
    description: str
    build: Callable[..., Any]
    format: int = 1
    options: Mapping[str, float] = field(default_factory=dict, hash=False)


def _build_network(name: str, shape: tuple[int, int, int]) -> Any:
    from common.zoo_nets import build_network

    model, _ = build_network(name, shape)
    return model


def _network(name: str, description: str) -> ZooGraph:
    return ZooGraph(name, description, functools.partial(_build_network, name), ZOO_FORMAT)


# The zoo's own networks (common.zoo_nets).
ZOO_MODELS: dict[str, ZooGraph] = {
    m.name: m
    for m in (
        _network("vgg", "VGG-like plain chain of 3x3 convolutions and max pools"),
        _network("resnet", "ResNet-18-like: 8 basic blocks with skip connections"),
        _network("mobilenet", "MobileNet-v2-like: inverted residuals, depthwise convs"),
        _network("resnet18", "ResNet-18: widths 64-128-256-512, 11.7 M parameters"),
        _network("mobilenet_v2", "MobileNet-v2, width 1.0: 3.5 M parameters"),
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


def all_models() -> dict[str, ZooGraph]:
    """Every zoo entry: the zoo's own networks, then the graph models other packages add."""
    return {**ZOO_MODELS, **graph_models()}


def cache_version(entry: ZooGraph) -> int:
    """The format version in the cached file name of an entry."""
    return entry.format


def options_for(entry: ZooGraph, given: ZooOptions | None) -> dict[str, float]:
    """The options `entry` is built with: its defaults, replaced by those of `given` it takes.
    Options it does not take are left out (a fleet's camera geometry means nothing to a CNN)."""
    chosen = dict(entry.options)
    for name, value in (given or {}).items():
        if name in chosen:
            chosen[name] = float(value)
    return chosen


def cache_file_name(
    entry: ZooGraph, shape: tuple[int, ...], options: ZooOptions | None = None
) -> str:
    """The cached file of `entry` built for `shape` with `options` (`options_for`): name, shape,
    each option off its default as NAME+VALUE (the shortest text that reads back the same
    float, so two values never share a name), format version;
    e.g. ``stereo-3x240x320-baseline_m0.12-v4.onnx``, ``stereo-3x240x320-v4.onnx`` at the
    defaults."""
    chosen = options_for(entry, options)
    changed = "".join(
        f"-{name}{value!r}"
        for name, value in sorted(chosen.items())
        if value != entry.options[name]
    )
    return f"{entry.name}-{format_shape(shape)}{changed}-v{cache_version(entry)}.onnx"


def get(name: str) -> ZooGraph:
    """The zoo entry called ``name``; raises UserError listing the known names otherwise."""
    entry = ZOO_MODELS.get(name) or graph_models().get(name)
    if entry is None:
        known = [*sorted(ZOO_MODELS), *sorted(graph_models())]
        raise UserError(f"unknown zoo model {name!r}; known: {', '.join(known)}")
    return entry


def export(
    name: str,
    out: Path,
    input_shape: tuple[int, ...] = DEFAULT_INPUT_SHAPE,
    options: ZooOptions | None = None,
) -> Path:
    """Build zoo model ``name`` with seeded weights and write it to ``out`` as ONNX (batch 1).

    ``input_shape`` is C×H×W; the file's input is the uint8 camera image 1×H×W×C. ``options``
    are build options (`options_for`: those the entry does not take are left out).

    The file is written next to ``out`` and renamed into place, so a reader never sees half a
    model. The same name, shape and options give a byte-identical file on every host, hence the
    same digest on the robot and on the cloud.
    """
    import onnx

    entry = get(name)
    shape = check_input_shape(tuple(input_shape))
    chosen = options_for(entry, options)
    model = entry.build(shape, **chosen) if chosen else entry.build(shape)
    out = Path(out)
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
